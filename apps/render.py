"""Scripted offline renders of PIE-NeRF's experiments from TOML scenarios.

    python -m apps.render assets/scenarios/plant_sway.toml --out out/plant_sway [--device cpu|cuda] [--smoke]
                          [--cache-dir DIR]

A scenario names the scene, material, discretisation, solver settings, pins, keyframed drags, timed forces, cuts,
colliders (a plane may move along keyframes), cameras (orbit or fixed) and outputs. Optional ``[[variants]]``
override the material or discretisation; variants run one after another and their images are tiled side by
side (Fig. 6: Neo-Hookean vs ARAP; Fig. 8: quadratic vs linear), each in its ``outputs.modes`` (a variant may
name its own ``modes``). The run writes, under ``--out``:

* ``frames/frame_NNNN.png`` (RGBA tiles of every camera × variant), ``video.mp4``;
* ``depth/…_NNNN.npy`` (float32 metres) and ``depth/…_NNNN.png`` previews; ``shadow/…_NNNN.png`` when asked;
* ``metrics.json``: timings, per-step report, volumes, the time breakdown and what is pending;
* ``volume_bars.png`` (Fig. 6) when ``[[volume_samples]]`` are given, ``time_breakdown.png`` (Fig. 10) always.

A ``[nerf]`` table renders the scene's NeRF warped by the simulated deformation (PIE-NeRF §4.6, Eq. 19–21):

* ``source = "scene"`` fits a NeRF to the embedded scene's rendered views (:func:`pienerf.nerf_backend.scene_nerf`);
  the body is still simulated from the scene's analytic density;
* ``source = "data:NAME"`` fits one to the NeRF-synthetic folder ``../shared/data/NAME``
  (:func:`pienerf.nerf_backend.dataset_nerf`, upright on the ground; ``up`` is the data's up axis), and the body is
  sampled from the NeRF's own solid: ``scene.name`` is then not needed;
* ``warps`` lists the ray warpings to render, each a render mode: ``"nerf"`` for the quadratic warp (Eq. 20),
  ``"nerf_linear"`` for the first-order one and ``"nerf_rest"`` for none;
* the other keys set the fit (``steps``, ``batch_rays``, ``views``, ``resolution``, ``downscale``, ``max_views``,
  ``levels``, ``log2_table_size``, ``max_resolution``, ``hidden``, ``samples_per_diagonal``, ``grid_resolution``,
  ``grid_decay``, ``solid_resolution``); ``[smoke.nerf]`` overrides them at ``--smoke`` size.

The fitted NeRF is cached as a checkpoint under ``--cache-dir`` (default ``$PIE_CACHE_DIR``, else
``~/.cache/pie-physavatar``), so a second run loads it.

``--smoke`` applies the scenario's ``[smoke]`` table (few frames, tiny images, few kernels). A bad scenario stops
with one line naming the key and the fix. A scenario whose ``requires`` cannot be met (a trained NeRF, the
warped-NeRF renderer, a data folder) is skipped: ``metrics.json`` holds ``skipped`` and the reason, exit status 0.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np
import torch

from kernels import backend

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

_VEC3 = "vec3"
_SCHEMA = {
    "": {
        "name": str,
        "description": str,
        "figure": str,
        "requires": list,
        "scene": dict,
        "material": dict,
        "discretization": dict,
        "solver": dict,
        "pins": list,
        "drags": list,
        "forces": list,
        "cuts": list,
        "colliders": list,
        "cameras": dict,
        "outputs": dict,
        "variants": list,
        "volume_samples": list,
        "smoke": dict,
        "pending": list,
        "nerf": dict,
    },
    "scene": {"name": str, "floor": bool, "default_pins": bool},
    "material": {"model": str, "young_modulus": float, "poisson_ratio": float, "density": float},
    "discretization": {
        "kernel_count": int,
        "particle_radius": float,
        "order": str,
        "lloyd_iterations": int,
        "seed": int,
    },
    "solver": {
        "dt": float,
        "frames": int,
        "substeps": int,
        "rayleigh_alpha": float,
        "rayleigh_beta": float,
        "gravity": _VEC3,
        "newton_iterations": int,
        "drag_stiffness": float,
        "drag_damping": float,
        "max_acceleration": float,
    },
    "pins": {"box": list},
    "drags": {"point": _VEC3, "keys": list, "release": float},
    "forces": {"point": _VEC3, "force": _VEC3, "start": float, "end": float},
    "cuts": {"point": _VEC3, "normal": _VEC3, "radius": float},
    "colliders": {"type": str, "point": _VEC3, "normal": _VEC3, "centre": _VEC3, "radius": float, "keys": list},
    "cameras": {
        "type": str,
        "distance": float,
        "elevation": float,
        "azimuths": list,
        "spin_deg_per_s": float,
        "positions": list,
        "look_at": _VEC3,
        "width": int,
        "height": int,
        "fov": float,
    },
    "outputs": {"frames": bool, "mp4": bool, "depth": bool, "shadow": bool, "fps": float, "modes": list},
    "variants": {"name": str, "material": dict, "discretization": dict, "modes": list},
    "volume_samples": {"time": float, "label": str},
    "smoke": {
        "frames": int,
        "width": int,
        "height": int,
        "kernel_count": int,
        "particle_radius": float,
        "lloyd_iterations": int,
        "nerf": dict,
    },
    "nerf": {
        "source": str,
        "up": str,
        "warps": list,
        "steps": int,
        "batch_rays": int,
        "views": int,
        "resolution": int,
        "downscale": int,
        "max_views": int,
        "levels": int,
        "log2_table_size": int,
        "max_resolution": int,
        "hidden": int,
        "samples_per_diagonal": int,
        "grid_resolution": int,
        "grid_decay": float,
        "solid_resolution": int,
    },
}

NERF_WARPS = {"quadratic": "nerf", "linear": "nerf_linear", "rest": "nerf_rest"}
"""Render mode of each ray warping of the ``[nerf]`` table."""


_TYPE_NAMES = {int: "an integer", str: "a string", bool: "true or false", list: "an array", dict: "a table"}


class ScenarioError(ValueError):
    """A scenario key is missing, unknown or of the wrong type; the message names the key and the fix."""


def _check_table(table: dict, section: str, where: str) -> None:
    schema = _SCHEMA[section]
    for key, value in table.items():
        path = f"{where}.{key}" if where else key
        if key not in schema:
            raise ScenarioError(f"unknown key '{path}'; valid keys here: {', '.join(sorted(schema))}")
        expected = schema[key]
        if expected == _VEC3:
            ok = (
                isinstance(value, list)
                and len(value) == 3
                and all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)
            )
            if not ok:
                raise ScenarioError(f"'{path}' must be 3 finite numbers like [0.0, 1.0, 0.0], got {value!r}")
        elif expected is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ScenarioError(f"'{path}' must be a number, got {value!r}")
        elif not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise ScenarioError(f"'{path}' must be {_TYPE_NAMES[expected]}, got {value!r}")
        if section == "" and key in _SCHEMA and isinstance(value, dict):
            _check_table(value, key, key)
        if section == "smoke" and key == "nerf" and isinstance(value, dict):
            _check_table(value, "nerf", path)
        if section in ("", "variants") and key in ("material", "discretization") and isinstance(value, dict):
            _check_table(value, key, path)
        if section == "" and key in _SCHEMA and isinstance(value, list):
            for i, item in enumerate(value):
                if not isinstance(item, dict):
                    raise ScenarioError(f"'{path}' must be an array of tables ([[{key}]]), item {i} is {item!r}")
                _check_table(item, key, f"{path}[{i}]")


def load_scenario(path: Path | str, smoke: bool = False) -> dict:
    """Read and check a scenario; with ``smoke``, the ``[smoke]`` table shrinks it."""
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(
            f"scenario file {path} does not exist; pass a .toml file such as assets/scenarios/plant_sway.toml"
        )
    try:
        scenario = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path} is not valid TOML ({error}); fix the syntax at that line") from None
    _check_table(scenario, "", "")
    for key in ("scene", "cameras"):
        if key not in scenario:
            raise ScenarioError(f"missing table [{key}]; every scenario needs [scene] and [cameras]")
    nerf = scenario.get("nerf")
    if nerf is not None:
        source = nerf.get("source", "scene")
        if source != "scene" and not source.startswith("data:"):
            raise ScenarioError(f'\'nerf.source\' must be "scene" or "data:NAME", got {source!r}')
        for warp in nerf.get("warps", ["quadratic"]):
            if warp not in NERF_WARPS:
                raise ScenarioError(f"'nerf.warps' has {warp!r}; valid: {', '.join(NERF_WARPS)}")
    from_data = nerf is not None and nerf.get("source", "scene").startswith("data:")
    if "name" not in scenario["scene"] and not from_data:
        raise ScenarioError(
            "missing key 'scene.name'; set it to an embedded scene (plant, teapot, jelly, cloth, "
            'sculpture) or a mesh path, or give [nerf] source = "data:NAME"'
        )
    if smoke and "smoke" in scenario:
        shrink = scenario["smoke"]
        solver, cameras = scenario.setdefault("solver", {}), scenario["cameras"]
        discretization = scenario.setdefault("discretization", {})
        for key in ("width", "height"):
            if key in shrink:
                cameras[key] = shrink[key]
        if "frames" in shrink:
            solver["frames"] = shrink["frames"]
        for key in ("kernel_count", "particle_radius", "lloyd_iterations"):
            if key in shrink:
                discretization[key] = shrink[key]
        for variant in scenario.get("variants", []):
            for key in ("kernel_count", "particle_radius"):
                if key in shrink and key in variant.get("discretization", {}):
                    variant["discretization"][key] = shrink[key]
        if "nerf" in shrink and "nerf" in scenario:
            scenario["nerf"] = {**scenario["nerf"], **shrink["nerf"]}
    return scenario


def unmet_requirement(scenario: dict) -> str | None:
    """Why the scenario cannot run here, or ``None``: ``"nerf_renderer"`` needs ``pienerf.nerf_backend``,
    ``"data:NAME"`` the folder ``../shared/data/NAME``, ``"checkpoint:PATH"`` a trained NeRF file."""
    needs = list(scenario.get("requires", []))
    source = scenario.get("nerf", {}).get("source", "scene")
    if source.startswith("data:") and source not in needs:
        needs.append(source)
    for need in needs:
        if need == "nerf_renderer":
            if importlib.util.find_spec("pienerf.nerf_backend") is None:
                return (
                    "the warped-NeRF renderer pienerf.nerf_backend is not in this checkout; this scenario renders "
                    "once it is"
                )
        elif need.startswith("data:"):
            folder = SHARED_DATA / need[5:]
            if not folder.is_dir():
                return f"data folder {folder} is absent; place the dataset there"
        elif need.startswith("checkpoint:"):
            file = Path(need[11:])
            if not file.is_file():
                return f"trained NeRF checkpoint {file} is absent; train it with python -m pienerf.train"
        else:
            raise ScenarioError(
                f"unknown requirement {need!r} in 'requires'; valid: nerf_renderer, data:NAME, checkpoint:PATH"
            )
    return None


def _keyframe(keys: list, t: float, where: str) -> torch.Tensor:
    """Piecewise-linear interpolation of ``[[time, [x, y, z]], …]`` at time ``t`` (held past the ends)."""
    try:
        times = [float(k[0]) for k in keys]
        values = torch.tensor([k[1] for k in keys], dtype=torch.float64)
    except (TypeError, IndexError, ValueError):
        raise ScenarioError(f"'{where}' must be [[time, [x, y, z]], ...], got {keys!r}") from None
    if values.shape != (len(times), 3) or any(b < a for a, b in zip(times, times[1:], strict=False)):
        raise ScenarioError(f"'{where}' must be [[time, [x, y, z]], ...] with increasing times, got {keys!r}")
    if t <= times[0]:
        return values[0]
    for i in range(1, len(times)):
        if t <= times[i]:
            s = (t - times[i - 1]) / max(times[i] - times[i - 1], 1e-12)
            return (1 - s) * values[i - 1] + s * values[i]
    return values[-1]


@dataclass
class _Run:
    name: str
    simulation: object
    volumes: object
    drags: list
    modes: list


@dataclass
class _Nerf:
    """The scenario's fitted NeRF: the rest-space field and grid, its checkpoint when it is the simulated scene."""

    field: object
    grid: object
    checkpoint: Path | None
    warps: list
    source: str
    seconds: float
    solid_resolution: int


def _nerf_fit(spec: dict):
    """The :class:`pienerf.nerf_backend.NerfFit` of a ``[nerf]`` table: its defaults, overridden by the table's keys."""
    from pienerf.nerf_backend import NerfFit

    base = NerfFit()
    hashgrid = replace(
        base.ngp.hashgrid, **{k: spec[k] for k in ("levels", "log2_table_size", "max_resolution") if k in spec}
    )
    ngp = {k: spec[k] for k in ("samples_per_diagonal", "grid_resolution", "grid_decay") if k in spec}
    if "hidden" in spec:
        ngp.update(density_hidden=spec["hidden"], color_hidden=spec["hidden"])
    steps = spec.get("steps", base.train.steps)
    train = replace(
        base.train,
        steps=steps,
        batch_rays=spec.get("batch_rays", base.train.batch_rays),
        grid_warmup_steps=min(base.train.grid_warmup_steps, max(1, steps // 4)),
    )
    sizes = {k: spec[k] for k in ("views", "resolution", "downscale", "max_views") if k in spec}
    return NerfFit(ngp=replace(base.ngp, hashgrid=hashgrid, **ngp), train=train, **sizes)


def _progress_log(log, what: str):
    """A ``(stage, fraction)`` callback that logs a line at every tenth of the way."""
    reached = [-1]

    def progress(stage: str, fraction: float) -> None:
        tenth = int(10 * fraction)
        if tenth > reached[0]:
            reached[0] = tenth
            log(f"{what}: {stage}")

    return progress


def _prepare_nerf(scenario: dict, cache_dir, log) -> _Nerf | None:
    """Fit (or load from the cache) the NeRF of the scenario's ``[nerf]`` table; ``None`` without one."""
    from pienerf.nerf_backend import dataset_nerf, dataset_nerf_path, scene_nerf

    spec = scenario.get("nerf")
    if spec is None:
        return None
    fit = _nerf_fit(spec)
    source = spec.get("source", "scene")
    progress = _progress_log(log, scenario.get("name", "scenario"))
    start = time.perf_counter()
    checkpoint = None
    if source == "scene":
        trained = scene_nerf(scenario["scene"]["name"], fit, cache_dir, progress)
    else:
        folder, up = SHARED_DATA / source[5:], spec.get("up", "z")
        trained = dataset_nerf(folder, fit, up, cache_dir, progress)
        checkpoint = dataset_nerf_path(folder, fit, up, cache_dir)
    return _Nerf(
        trained.field,
        trained.grid,
        checkpoint,
        list(spec.get("warps", ["quadratic"])),
        source,
        time.perf_counter() - start,
        spec.get("solid_resolution", 96),
    )


def _cameras(scenario: dict, simulation, t: float):
    from pienerf.session import look_at_cameras, orbit_cameras

    spec = scenario["cameras"]
    width, height, fov = spec.get("width", 320), spec.get("height", 240), spec.get("fov", 40.0)
    kind = spec.get("type", "orbit")
    if kind == "orbit":
        spin = spec.get("spin_deg_per_s", 0.0) * t
        azimuths = [a + spin for a in spec.get("azimuths", [0.0])]
        return orbit_cameras(
            simulation.centre, spec.get("distance", 2.5), azimuths, spec.get("elevation", 15.0), width, height, fov
        )
    if kind == "fixed":
        if "positions" not in spec or "look_at" not in spec:
            raise ScenarioError("fixed cameras need 'cameras.positions' ([[x, y, z], ...]) and 'cameras.look_at'")
        positions = torch.tensor(spec["positions"], dtype=torch.float64)
        return look_at_cameras(positions, torch.tensor(spec["look_at"]).expand_as(positions), width, height, fov)
    raise ScenarioError(f"'cameras.type' must be 'orbit' or 'fixed', got {kind!r}")


def _colliders(scenario: dict, t: float, floor: bool):
    from pienerf.solver import PlaneCollider, SphereCollider

    colliders = [PlaneCollider()] if floor else []
    for i, spec in enumerate(scenario.get("colliders", [])):
        kind = spec.get("type")
        if kind == "plane":
            point = spec.get("point", [0.0, 0.0, 0.0])
            if "keys" in spec:
                point = _keyframe(spec["keys"], t, f"colliders[{i}].keys").tolist()
            colliders.append(PlaneCollider(tuple(point), tuple(spec.get("normal", [0.0, 1.0, 0.0]))))
        elif kind == "sphere":
            if "centre" not in spec or "radius" not in spec:
                raise ScenarioError(f"'colliders[{i}]' sphere needs 'centre' and 'radius'")
            colliders.append(SphereCollider(tuple(spec["centre"]), float(spec["radius"])))
        else:
            raise ScenarioError(f"'colliders[{i}].type' must be 'plane' or 'sphere', got {kind!r}")
    return colliders


def _build(scenario: dict, variant: dict, nerf: _Nerf | None = None, modes: list | None = None):
    from pienerf.cut import CutPlane
    from pienerf.materials import Material
    from pienerf.reports import VolumeHistory
    from pienerf.session import SCENE_SETUPS, Simulation, SimulationConfig

    scene = scenario["scene"]
    material_spec = {**scenario.get("material", {}), **variant.get("material", {})}
    discretization = {**scenario.get("discretization", {}), **variant.get("discretization", {})}
    solver = scenario.get("solver", {})
    name = str(nerf.checkpoint) if nerf is not None and nerf.checkpoint is not None else scene["name"]
    base = SCENE_SETUPS[name].material if name in SCENE_SETUPS else Material()
    cuts = tuple(
        CutPlane(tuple(c["point"]), tuple(c["normal"]), c.get("radius", math.inf)) for c in scenario.get("cuts", [])
    )
    config = SimulationConfig(
        scene=name,
        material=replace(base, **material_spec),
        kernel_count=discretization.get("kernel_count"),
        particle_radius=discretization.get("particle_radius"),
        order=discretization.get("order", "quadratic"),
        lloyd_iterations=discretization.get("lloyd_iterations", 2),
        seed=discretization.get("seed", 0),
        dt=solver.get("dt", 1.0 / 30.0) / solver.get("substeps", 1),
        gravity=tuple(solver.get("gravity", (0.0, -9.81, 0.0))),
        rayleigh_alpha=solver.get("rayleigh_alpha", 2.0),
        rayleigh_beta=solver.get("rayleigh_beta", 0.0),
        newton_iterations=solver.get("newton_iterations", 2),
        floor=scene.get("floor", True),
        default_pins=scene.get("default_pins", True),
        drag_stiffness=solver.get("drag_stiffness"),
        drag_damping=solver.get("drag_damping"),
        max_acceleration=solver.get("max_acceleration", 30.0),
        cuts=cuts,
        nerf_solid_resolution=nerf.solid_resolution if nerf is not None else 96,
    )
    simulation = Simulation(config)
    for warp in nerf.warps if nerf is not None else []:
        if NERF_WARPS[warp] not in simulation.render_backends:
            simulation.add_nerf_render(nerf.field, nerf.grid, name=NERF_WARPS[warp], warp=warp)
    for i, pin in enumerate(scenario.get("pins", [])):
        box = pin.get("box")
        if not (isinstance(box, list) and len(box) == 2 and all(isinstance(c, list) and len(c) == 3 for c in box)):
            raise ScenarioError(f"'pins[{i}].box' must be [[x0, y0, z0], [x1, y1, z1]] (m), got {box!r}")
        simulation.interaction.pin_region(box[0], box[1], simulation.state.q)
    drags = []
    for i, spec in enumerate(scenario.get("drags", [])):
        if "point" not in spec or "keys" not in spec:
            raise ScenarioError(f"'drags[{i}]' needs 'point' (rest position, m) and 'keys' ([[time, [x, y, z]]])")
        drags.append(spec)
    if len(drags) > 1:
        raise ScenarioError("at most one [[drags]] entry: the drag is the mouse; use [[forces]] for further loads")
    volumes = VolumeHistory(simulation.volume())
    return _Run(
        variant.get("name", "default"),
        simulation,
        volumes,
        drags,
        list(variant.get("modes", modes if modes is not None else ["mesh"])),
    )


def _apply_controls(run: _Run, scenario: dict, t: float) -> None:
    """Drag targets and constant forces at time ``t``; the first drag uses the pick machinery."""
    simulation = run.simulation
    interaction = simulation.interaction
    drag = interaction.drag
    for i, spec in enumerate(run.drags):
        if t < spec.get("release", math.inf):
            if not drag.dragging:
                drag.grab(spec["point"], simulation.state.q)
            drag.update(target=_keyframe(spec["keys"], t, f"drags[{i}].keys"))
        elif drag.dragging:
            drag.release()
    interaction.forces.clear()
    for i, spec in enumerate(scenario.get("forces", [])):
        if spec.get("start", 0.0) <= t < spec.get("end", math.inf):
            if "point" not in spec or "force" not in spec:
                raise ScenarioError(f"'forces[{i}]' needs 'point' (rest position, m) and 'force' (N)")
            interaction.add_force(spec["point"], spec["force"])


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def _depth_preview(depth: torch.Tensor) -> np.ndarray:
    finite = torch.isfinite(depth)
    if not bool(finite.any()):
        return np.zeros(depth.shape, dtype=np.uint8)
    lo, hi = float(depth[finite].min()), float(depth[finite].max())
    scaled = torch.where(finite, 1.0 - (depth - lo) / max(hi - lo, 1e-6) * 0.8, torch.zeros_like(depth))
    return _to_uint8(scaled)


def render_scenario(scenario: dict, out: Path, log=print, cache_dir: Path | str | None = None) -> dict:
    """Run every variant of a checked scenario and write the outputs under ``out``; returns the metrics.

    ``cache_dir`` holds the scene renders and fitted NeRFs (default ``$PIE_CACHE_DIR``, else
    ``~/.cache/pie-physavatar``).
    """
    from PIL import Image

    from pienerf.reports import TimeBreakdown, plot_time_breakdown, plot_volume_bars

    out.mkdir(parents=True, exist_ok=True)
    name = scenario.get("name", "scenario")
    reason = unmet_requirement(scenario)
    metrics = {
        "scenario": name,
        "figure": scenario.get("figure", ""),
        "device": backend.current_device(),
        "pending": scenario.get("pending", []),
    }
    if reason is not None:
        metrics["skipped"] = reason
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
        log(f"{name}: skipped: {reason}")
        return metrics

    outputs = {
        "frames": True,
        "mp4": True,
        "depth": False,
        "shadow": False,
        "fps": 30.0,
        "modes": ["mesh"],
        **scenario.get("outputs", {}),
    }
    solver = scenario.get("solver", {})
    frames, substeps = solver.get("frames", 30), solver.get("substeps", 1)
    if frames < 1 or substeps < 1:
        raise ScenarioError("'solver.frames' and 'solver.substeps' must be >= 1")
    variants = scenario.get("variants") or [{"name": "default"}]
    nerf = _prepare_nerf(scenario, cache_dir, log)
    clock = time.perf_counter()
    runs = [_build(scenario, variant, nerf, outputs["modes"]) for variant in variants]
    build_seconds = time.perf_counter() - clock
    for run in runs:
        for mode in run.modes:
            if mode not in run.simulation.render_backends:
                raise ScenarioError(
                    f"render mode {mode!r} of variant {run.name!r} is not available; available: "
                    f"{', '.join(run.simulation.render_backends)} (a [nerf] table adds "
                    f"{', '.join(NERF_WARPS.values())})"
                )
    samples = sorted(scenario.get("volume_samples", []), key=lambda s: s["time"])
    for folder in ("frames", "depth", "shadow"):
        if outputs["frames" if folder == "frames" else folder]:
            (out / folder).mkdir(exist_ok=True)
    writer = None
    if outputs["mp4"]:
        import imageio.v2 as imageio

        writer = imageio.get_writer(
            out / "video.mp4", fps=outputs["fps"], codec="libx264", quality=7, macro_block_size=1, pixelformat="yuv420p"
        )
    dt = runs[0].simulation.config.dt * substeps
    step_seconds = {run.name: [] for run in runs}
    render_seconds = 0.0
    per_frame = []
    try:
        for frame in range(frames + 1):
            t = frame * dt
            tiles = []
            record = {"frame": frame, "time_s": t}
            for run in runs:
                simulation = run.simulation
                if frame > 0:
                    for sub in range(substeps):
                        ts = t - dt + sub * simulation.config.dt
                        _apply_controls(run, scenario, ts)
                        start = time.perf_counter()
                        simulation.step(1, colliders=_colliders(scenario, ts, simulation.config.floor))
                        step_seconds[run.name].append(time.perf_counter() - start)
                while (
                    samples
                    and len(run.volumes.labels) < len(samples)
                    and t + 1e-9 >= samples[len(run.volumes.labels)]["time"]
                ):
                    run.volumes.add(samples[len(run.volumes.labels)]["label"], simulation.volume())
                record[f"{run.name}_relative_volume"] = simulation.volume() / run.volumes.rest_volume
                cameras = _cameras(scenario, simulation, t)
                start = time.perf_counter()
                for mode in run.modes:
                    for view in range(len(cameras)):
                        result = simulation.render(cameras, view, mode, shadow=outputs["shadow"])
                        tiles.append(result.rgba.cpu())  # render modes may return different devices
                        stem = f"{run.name}_{mode}_view{view}_{frame:04d}"
                        if outputs["depth"]:
                            np.save(out / "depth" / f"{stem}.npy", result.depth.cpu().numpy().astype(np.float32))
                            Image.fromarray(_depth_preview(result.depth)).save(out / "depth" / f"{stem}.png")
                        if outputs["shadow"] and result.shadow is not None:
                            Image.fromarray(_to_uint8(result.shadow)).save(out / "shadow" / f"{stem}.png")
                render_seconds += time.perf_counter() - start
            image = torch.cat(tiles, dim=1)
            rgb = image[..., :3] * image[..., 3:] + (1.0 - image[..., 3:])  # over white
            if outputs["frames"]:
                Image.fromarray(_to_uint8(image), mode="RGBA").save(out / "frames" / f"frame_{frame:04d}.png")
            if writer is not None:
                writer.append_data(_to_uint8(rgb))
            per_frame.append(record)
    finally:
        if writer is not None:
            writer.close()

    breakdown = TimeBreakdown()
    for run in runs:
        for key, value in run.simulation.breakdown.seconds.items():
            breakdown.seconds[key] = breakdown.seconds.get(key, 0.0) + value
        breakdown.steps += run.simulation.breakdown.steps
        breakdown.newton_iterations += run.simulation.breakdown.newton_iterations
    plot_time_breakdown(breakdown, out / "time_breakdown.png", title=name)
    if samples:
        plot_volume_bars([(run.name, run.volumes) for run in runs], out / "volume_bars.png")
    if nerf is not None:
        metrics["nerf"] = {
            "source": nerf.source,
            "checkpoint": str(nerf.checkpoint) if nerf.checkpoint else None,
            "fit_or_load_seconds": nerf.seconds,
            "warps": nerf.warps,
            "modes": {run.name: run.modes for run in runs},
        }
    metrics.update(
        {
            "frames": frames + 1,
            "steps_per_frame": substeps,
            "dt_s": runs[0].simulation.config.dt,
            "build_seconds": build_seconds,
            "render_seconds": render_seconds,
            "time_breakdown": breakdown.to_dict(),
            "variants": {
                run.name: {
                    "summary": run.simulation.summary(),
                    "step_seconds_median": float(np.median(step_seconds[run.name])) if step_seconds[run.name] else None,
                    "volume": {"labels": run.volumes.labels, "relative": run.volumes.relative().tolist()},
                    "final_relative_volume": run.simulation.volume() / run.volumes.rest_volume,
                    "final_max_displacement_m": float(
                        (run.simulation.particle_positions() - run.simulation.model.position.float().cpu())
                        .norm(dim=1)
                        .max()
                    ),
                }
                for run in runs
            },
            "per_frame": per_frame,
        }
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
    log(
        f"{name}: {frames + 1} frames, {len(runs)} variant(s), build {build_seconds:.1f} s, "
        f"{1e3 * breakdown.to_dict()['seconds_per_step'].get('assembly', 0):.1f} ms assembly/step → {out}"
    )
    return metrics


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenario", type=Path, help="scenario TOML file (assets/scenarios/*.toml)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--device", choices=list(backend.DEVICES), default=None, help="cpu or cuda (default: cuda when present)"
    )
    parser.add_argument("--smoke", action="store_true", help="apply the scenario's [smoke] table (tests)")
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of scene renders and fitted NeRFs (default: $PIE_CACHE_DIR, else ~/.cache/pie-physavatar)",
    )
    args = parser.parse_args(argv)
    try:
        scenario = load_scenario(args.scenario, smoke=args.smoke)
        backend.init(args.device)
        render_scenario(scenario, args.out, cache_dir=args.cache_dir)
    except (ScenarioError, ValueError) as error:
        print(f"error: {args.scenario}: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
