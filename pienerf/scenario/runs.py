"""The runs of a scenario, one per variant: their simulations built from the tables, stepped under the scenario's
controls and colliders, and summarised.

:func:`build_runs` makes one :class:`ScenarioRun` (a :class:`pienerf.session.Simulation`) per variant;
:func:`advance` steps a run through one frame; :func:`measure_warp_error` compares a run's warped-NeRF renders with
its mesh (``[warp_error]``); :func:`merged_breakdown`, :func:`run_metrics` and :func:`warp_error_summary` summarise.
A scenario's steps iterate to the solver's tolerance (:data:`OFFLINE_NEWTON_ITERATIONS`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from pienerf.render.warp_error import WarpErrorProbe
from pienerf.reports import TimeBreakdown, VolumeHistory
from pienerf.scenario.cameras import scenario_cameras
from pienerf.scenario.colliders import scenario_colliders
from pienerf.scenario.keyframes import keyframe
from pienerf.scenario.nerf import ScenarioNerf
from pienerf.scenario.schema import NERF_WARPS, ScenarioError, scenario_outputs
from pienerf.session import SCENE_SETUPS, Simulation, SimulationConfig
from pienerf.sim.cut import CutPlane
from pienerf.sim.materials import Material
from pienerf.sim.solver import QGMLSStepReport

__all__ = [
    "OFFLINE_NEWTON_ITERATIONS",
    "ScenarioRun",
    "StepTally",
    "advance",
    "apply_controls",
    "build_run",
    "build_runs",
    "measure_warp_error",
    "merged_breakdown",
    "run_metrics",
    "sample_volumes",
    "warp_error_summary",
]

OFFLINE_NEWTON_ITERATIONS = 50
"""Newton iterations a scenario's step may take unless ``solver.newton_iterations`` says otherwise: a scripted
figure iterates each step to ``SolverConfig.newton_tolerance`` instead of taking the interactive viewer's one
iteration (:data:`pienerf.session.INTERACTIVE_SOLVER`). Line-searched Newton converges quadratically near the
solution, so a step that has not met the tolerance after 50 iterations is stalled (the summary line reports its last
update against the tolerance), not slow. Scenario steps run the solver's host loop on every device, which stops at the
tolerance (:meth:`pienerf.sim.solver.SolverQGMLS.step`)."""


@dataclass
class StepTally:
    """How a run's solver steps ended, counted from their step reports (:class:`pienerf.sim.solver.QGMLSStepReport`).

    Attributes:
        steps: steps taken.
        unconverged: steps that ended without meeting the Newton tolerance.
        line_search_failures: steps whose last line search failed, by kind (``"inversion"``, ``"no decrease"``,
            ``"not finite"``).
        stuck: steps whose first line search already failed, so the body did not move in them at all.
        tolerance: the solver's ``newton_tolerance`` (m), the bound a converged step's last update meets.
        iteration_cap: the solver's ``newton_iterations``, the most a step may take.
        largest_unconverged_update: the largest last Newton update (|J Δq|, m) of the unconverged steps: how far
            from convergence they ended, against ``tolerance``.
    """

    steps: int = 0
    unconverged: int = 0
    line_search_failures: dict[str, int] = field(default_factory=dict)
    stuck: int = 0
    tolerance: float | None = None
    iteration_cap: int | None = None
    largest_unconverged_update: float = 0.0

    def add(self, report: QGMLSStepReport) -> None:
        """Count one step's report."""
        self.steps += 1
        self.unconverged += not report.converged
        if not report.converged:
            self.largest_unconverged_update = max(self.largest_unconverged_update, float(report.last_update))
        if report.line_search_failure:
            kind = report.line_search_failure
            self.line_search_failures[kind] = self.line_search_failures.get(kind, 0) + 1
            self.stuck += report.iterations <= 1

    @property
    def failed(self) -> int:
        """Steps whose line search failed, of any kind."""
        return sum(self.line_search_failures.values())

    def wrong_result(self) -> str | None:
        """Why the run's result cannot be trusted, or ``None``: a line search that met non-finite values (NaN in the
        Newton direction or energy), or one that could not move the body in any step of the run."""
        not_finite = self.line_search_failures.get("not finite", 0)
        if not_finite:
            return f"{not_finite} of {self.steps} steps met non-finite values (NaN) in their line search"
        if self.steps and self.stuck == self.steps:
            return f"the line search could not move the body in any of the {self.steps} steps"
        return None

    def to_dict(self) -> dict:
        """The counts as JSON-ready values, with the reason the result is wrong (``null`` when it is not)."""
        return {
            "steps": self.steps,
            "unconverged_steps": self.unconverged,
            "line_search_failed_steps": self.failed,
            "line_search_failures": dict(sorted(self.line_search_failures.items())),
            "stuck_steps": self.stuck,
            "newton_tolerance_m": self.tolerance,
            "newton_iterations_cap": self.iteration_cap,
            "largest_unconverged_update_m": self.largest_unconverged_update if self.unconverged else None,
            "wrong_result": self.wrong_result(),
        }


@dataclass
class ScenarioRun:
    """One variant of a scenario: its simulation, volume history, drag, render modes, how its steps ended, the
    label its tiles carry when a frame shows several variants (the variant's ``label``, else its name), and, under a
    ``[warp_error]`` table, the probe of its warped-NeRF modes with one record per measured frame
    (:func:`measure_warp_error`)."""

    name: str
    simulation: Simulation
    volumes: VolumeHistory
    drags: list
    modes: list
    label: str = ""
    tally: StepTally = field(default_factory=StepTally)
    warp_error: WarpErrorProbe | None = None
    warp_errors: list = field(default_factory=list)


def build_run(
    scenario: dict, variant: dict, nerf: ScenarioNerf | None = None, modes: list | None = None
) -> ScenarioRun:
    """The simulation of one variant: its config, the NeRF render modes, the pins and the drag (at most one)."""
    scene = scenario["scene"]
    material_spec = {**scenario.get("material", {}), **variant.get("material", {})}
    discretization = {**scenario.get("discretization", {}), **variant.get("discretization", {})}
    solver = scenario.get("solver", {})
    name = str(nerf.checkpoint) if nerf is not None and nerf.checkpoint is not None else scene["name"]
    base = SCENE_SETUPS[name].material if name in SCENE_SETUPS else Material()
    cuts = tuple(
        CutPlane(tuple(c["point"]), tuple(c["normal"]), c.get("radius", math.inf)) for c in scenario.get("cuts", [])
    )
    config = SimulationConfig.create(
        name,
        material=replace(base, **material_spec),
        kernel_count=discretization.get("kernel_count"),
        particle_radius=discretization.get("particle_radius"),
        order=discretization.get("order"),
        lloyd_iterations=discretization.get("lloyd_iterations"),
        seed=discretization.get("seed"),
        dt=solver.get("dt", SimulationConfig.dt) / solver.get("substeps", 1),
        gravity=tuple(solver["gravity"]) if "gravity" in solver else None,
        rayleigh_alpha=solver.get("rayleigh_alpha"),
        rayleigh_beta=solver.get("rayleigh_beta"),
        newton_iterations=solver.get("newton_iterations", OFFLINE_NEWTON_ITERATIONS),
        hessian_precision=solver.get("hessian_precision"),
        device_loop=False,  # the host loop stops at convergence; the device loop would run every one of the cap's
        # iterations (it masks those after convergence so as to read nothing), which suits one interactive iteration
        floor=scene.get("floor"),
        default_pins=scene.get("default_pins"),
        drag_stiffness=solver.get("drag_stiffness"),
        drag_damping=solver.get("drag_damping"),
        drag_max_acceleration=solver.get("max_acceleration"),
        cuts=cuts or None,
        nerf_solid_resolution=nerf.solid_resolution if nerf is not None else None,
        mesh_edge_fraction=scenario_outputs(scenario).get("mesh_edge_fraction"),
    )
    simulation = Simulation(config)
    for warp in nerf.warps if nerf is not None else []:
        if NERF_WARPS[warp] not in simulation.render_backends:
            simulation.add_nerf_render(nerf.field, nerf.grid, name=NERF_WARPS[warp], warp=warp)
    for i, pin in enumerate(scenario.get("pins", [])):
        box = pin.get("box")
        if not (isinstance(box, list) and len(box) == 2 and all(isinstance(c, list) and len(c) == 3 for c in box)):
            raise ScenarioError(f"'pins[{i}].box' must be [[x0, y0, z0], [x1, y1, z1]] (m), got {box!r}")
        simulation.pin_region(box[0], box[1])
    drags = []
    for i, spec in enumerate(scenario.get("drags", [])):
        if "point" not in spec or "keys" not in spec:
            raise ScenarioError(f"'drags[{i}]' needs 'point' (rest position, m) and 'keys' ([[time, [x, y, z]]])")
        drags.append(spec)
    if len(drags) > 1:
        raise ScenarioError("at most one [[drags]] entry: the drag is the mouse; use [[forces]] for further loads")
    volumes = VolumeHistory(simulation.volume())
    run_modes = list(variant.get("modes", modes if modes is not None else ["mesh"]))
    solver_config = simulation.config.solver
    return ScenarioRun(
        variant.get("name", "default"),
        simulation,
        volumes,
        drags,
        run_modes,
        variant.get("label", variant.get("name", "default")),
        warp_error=_warp_error_probe(scenario, simulation, nerf, run_modes),
        tally=StepTally(tolerance=solver_config.newton_tolerance, iteration_cap=solver_config.newton_iterations),
    )


def _warp_error_probe(scenario: dict, simulation: Simulation, nerf, modes: list) -> WarpErrorProbe | None:
    """The ``[warp_error]`` probe of a run that renders warped-NeRF modes, or ``None``: its reference is the run's
    own mesh preview (refined as ``outputs.mesh_edge_fraction`` asks)."""
    spec = scenario.get("warp_error")
    warps = {mode: warp for warp, mode in NERF_WARPS.items() if mode in modes}
    if spec is None or nerf is None or not warps:
        return None
    try:
        return WarpErrorProbe(
            simulation.model,
            simulation.render_backends["mesh"].body_mesh(),
            nerf.field,
            nerf.grid,
            warps,
            tuple(spec["region"]),
            dilation=spec.get("dilation", 2.0),
            label=spec.get("label", "region"),
        )
    except ValueError as error:
        raise ScenarioError(f"'warp_error.region': {error}") from None


def measure_warp_error(run: ScenarioRun, scenario: dict, t: float) -> dict | None:
    """Measure each warped-NeRF mode of ``run`` against its mesh at the current state, seen by the cameras of time
    ``t`` (s) (:class:`pienerf.render.warp_error.WarpErrorProbe`); records the frame in ``run.warp_errors`` and returns
    ``{mode: {"psnr_db", "silhouette_iou", "pixels"}}``, or ``None`` when the run has no probe."""
    if run.warp_error is None:
        return None
    simulation = run.simulation
    cameras = scenario_cameras(scenario, simulation.centre, t)
    errors = {mode: error.to_dict() for mode, error in run.warp_error.measure(simulation.state.q, cameras).items()}
    run.warp_errors.append(errors)
    return errors


def apply_controls(run: ScenarioRun, scenario: dict, t: float) -> None:
    """Drag targets and constant forces at time ``t`` (s); the drag grabs its point as a mouse would."""
    simulation = run.simulation
    for i, spec in enumerate(run.drags):
        if t < spec.get("release", math.inf):
            if not simulation.dragging:
                simulation.grab(spec["point"])
            simulation.drag_to(target=keyframe(spec["keys"], t, f"drags[{i}].keys"))
        elif simulation.dragging:
            simulation.release()
    simulation.clear_forces()
    for i, spec in enumerate(scenario.get("forces", [])):
        if spec.get("start", 0.0) <= t < spec.get("end", math.inf):
            if "point" not in spec or "force" not in spec:
                raise ScenarioError(f"'forces[{i}]' needs 'point' (rest position, m) and 'force' (N)")
            simulation.add_force(spec["point"], spec["force"])


def build_runs(scenario: dict, nerf: ScenarioNerf | None) -> list[ScenarioRun]:
    """One run per variant (one ``default`` without ``[[variants]]``), each checked to have its render modes."""
    modes = scenario_outputs(scenario)["modes"]
    runs = [build_run(scenario, variant, nerf, modes) for variant in scenario.get("variants") or [{"name": "default"}]]
    for run in runs:
        for mode in run.modes:
            if mode not in run.simulation.render_backends:
                raise ScenarioError(
                    f"render mode {mode!r} of variant {run.name!r} is not available; available: "
                    f"{', '.join(run.simulation.render_backends)} (a [nerf] table adds "
                    f"{', '.join(NERF_WARPS.values())})"
                )
    return runs


def advance(run: ScenarioRun, scenario: dict, t: float, substeps: int) -> list[float]:
    """Step ``run`` from the previous frame to the frame at ``t`` (s): ``substeps`` steps, each under the controls
    and colliders of its own time; returns each step's wall-clock seconds and counts each step in ``run.tally``."""
    simulation = run.simulation
    dt = simulation.config.dt
    seconds = []
    for sub in range(substeps):
        ts = t - substeps * dt + sub * dt
        apply_controls(run, scenario, ts)
        start = time.perf_counter()
        report = simulation.step(1, colliders=scenario_colliders(scenario, ts, simulation.config.floor))
        seconds.append(time.perf_counter() - start)
        run.tally.add(report)
    return seconds


def sample_volumes(run: ScenarioRun, samples: list[dict], frame: int) -> float:
    """Record the samples of :func:`volume_sample_frames` whose frame is ``frame``; returns the body's volume
    relative to rest."""
    volume = run.simulation.volume()
    for sample in samples:
        if sample["frame"] == frame:
            run.volumes.add(sample["label"], volume)
    return volume / run.volumes.rest_volume


def merged_breakdown(runs: list[ScenarioRun]) -> TimeBreakdown:
    """The time breakdown of every run together."""
    breakdown = TimeBreakdown()
    for run in runs:
        for key, value in run.simulation.breakdown.seconds.items():
            breakdown.seconds[key] = breakdown.seconds.get(key, 0.0) + value
        breakdown.steps += run.simulation.breakdown.steps
        breakdown.newton_iterations += run.simulation.breakdown.newton_iterations
    return breakdown


def run_metrics(run: ScenarioRun, step_seconds: list[float]) -> dict:
    """A run's summary, median step time, volumes, largest displacement (m), how its solver steps ended, the size
    of the mesh its mesh tiles show (the scene's, or refined by ``outputs.mesh_edge_fraction``) and, under
    ``[warp_error]``, :func:`warp_error_summary`."""
    simulation = run.simulation
    displacement = simulation.particle_positions() - simulation.model.position.float().cpu()
    mesh = simulation.render_backends["mesh"]
    return {
        "summary": simulation.summary(),
        "mesh_preview": {
            "scene_vertices": simulation.mesh_vertices.shape[0],
            "vertices": mesh.body_vertices,
            "max_edge_m": mesh.max_edge,
        },
        "step_seconds_median": float(np.median(step_seconds)) if step_seconds else None,
        "volume": {"labels": run.volumes.labels, "relative": run.volumes.relative().tolist()},
        "final_relative_volume": simulation.volume() / run.volumes.rest_volume,
        "final_max_displacement_m": float(displacement.norm(dim=1).max()),
        "final_centre_displacement_m": float(displacement.mean(dim=0).norm()),
        "solver": run.tally.to_dict(),
        **({"warp_error": warp_error_summary(run)} if run.warp_error is not None else {}),
    }


def warp_error_summary(run: ScenarioRun) -> dict:
    """Per warped-NeRF mode, the frames' ``psnr_db``, ``silhouette_iou`` and ``pixels`` (lists, one entry per
    measured frame, ``None`` where the region held nothing) and their means over the frames that had a value; with
    the region: its label, rest-space box (m), particle count, dilation (px) and definition."""
    probe = run.warp_error
    summary = {
        "region": {
            "label": probe.label,
            "box_m": [list(corner) for corner in probe.region],
            "particles": probe.particle_count,
            "dilation_px": probe.dilation,
            "definition": "pixels within the projected particle radius + dilation of a deformed particle that rests "
            "in the box, covered by the mesh's or the NeRF's silhouette (alpha > 0.5); no ground in either render",
        },
        "modes": {},
    }
    for mode in probe.nerfs:
        frames = [record[mode] for record in run.warp_errors]
        entry = {key: [f[key] for f in frames] for key in ("psnr_db", "silhouette_iou", "pixels")}
        for key in ("psnr_db", "silhouette_iou"):
            values = [v for v in entry[key] if v is not None and math.isfinite(v)]
            entry[f"mean_{key}"] = float(np.mean(values)) if values else None
        summary["modes"][mode] = entry
    return summary
