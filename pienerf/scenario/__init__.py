"""Scripted experiments as TOML scenarios: the schema and its checks, and the pieces a scripted render is made of.

A scenario names the scene, material, discretisation, solver settings, pins, keyframed drags, timed forces, cuts,
colliders (a plane may move along keyframes), cameras (orbit or fixed) and outputs; optional ``[[variants]]``
override the material or discretisation, and a ``[nerf]`` table fits a NeRF to render warped (PIE-NeRF §4.6). The
format is described in :mod:`apps.render`, which writes the images and metrics.

:func:`load_scenario` reads and checks a file (a bad key raises :class:`ScenarioError` naming the key and the fix);
:func:`unmet_requirement` says why it cannot run here; :func:`prepare_nerf` fits or loads its NeRF;
:func:`build_runs` makes one :class:`ScenarioRun` (a :class:`pienerf.session.Simulation`) per variant;
:func:`advance` steps a run through one frame under the scenario's controls and colliders;
:func:`scenario_cameras` gives the frame's cameras; :func:`measure_warp_error` compares a run's warped-NeRF renders
with its mesh (``[warp_error]``); :func:`merged_breakdown`, :func:`run_metrics` and :func:`warp_error_summary`
summarise.
"""

from __future__ import annotations

import importlib.util
import math
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np
import torch

from pienerf.nerf.cameras import Cameras, look_at_cameras, orbit_cameras
from pienerf.nerf.fitting import NerfFit, dataset_nerf, dataset_nerf_path
from pienerf.paths import SHARED_DATA
from pienerf.render.warp_error import WarpErrorProbe
from pienerf.reports import TimeBreakdown, VolumeHistory
from pienerf.scenes import SCENES, scene_nerf
from pienerf.session import SCENE_SETUPS, Simulation, SimulationConfig
from pienerf.sim.cut import CutPlane
from pienerf.sim.materials import MATERIAL_MODELS, Material
from pienerf.sim.qgmls import ORDERS
from pienerf.sim.solver import PlaneCollider, QGMLSStepReport, SphereCollider

__all__ = [
    "MAX_COORDINATE",
    "MAX_FRAMES",
    "MAX_STEPS",
    "MAX_TIME",
    "NERF_WARPS",
    "OFFLINE_NEWTON_ITERATIONS",
    "OUTPUT_DEFAULTS",
    "ScenarioError",
    "ScenarioNerf",
    "ScenarioRun",
    "StepTally",
    "advance",
    "apply_controls",
    "build_run",
    "build_runs",
    "keyframe",
    "load_scenario",
    "frame_count",
    "measure_warp_error",
    "merged_breakdown",
    "nerf_fit",
    "prepare_nerf",
    "progress_log",
    "require_video_encoder",
    "run_metrics",
    "sample_volumes",
    "scenario_cameras",
    "scenario_colliders",
    "scenario_outputs",
    "unmet_requirement",
    "volume_sample_frames",
    "warp_error_summary",
]

_VEC3 = "vec3"


@dataclass(frozen=True)
class _Number:
    """A numeric scenario value: its type (``int`` or ``float``), its allowed range and its unit."""

    kind: type
    low: float
    high: float
    unit: str = ""
    low_open: bool = False

    def describe(self) -> str:
        kind = "an integer" if self.kind is int else "a number"
        bracket = "(" if self.low_open else "["
        unit = f" {self.unit}" if self.unit else ""
        return f"{kind} in {bracket}{self.low:g}, {self.high:g}]{unit}"

    def admits(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float) if self.kind is float else int):
            return False
        if not math.isfinite(value):
            return False
        return (self.low < value if self.low_open else self.low <= value) and value <= self.high


MAX_FRAMES = 100_000
"""Most frames a scenario may render (``solver.frames``, ``smoke.frames``): over an hour of video at 24 fps."""
MAX_STEPS = 1_000_000
"""Most solver steps a scenario may take (frames × substeps)."""
MAX_COORDINATE = 1e4
"""Largest magnitude (m, or N for a force) of a 3-vector's entry."""
MAX_TIME = 1e5
"""Latest time (s) a keyframe, force window, release or volume sample may name."""

OFFLINE_NEWTON_ITERATIONS = 50
"""Newton iterations a scenario's step may take unless ``solver.newton_iterations`` says otherwise: a scripted
figure iterates each step to ``SolverConfig.newton_tolerance`` instead of taking the interactive viewer's one
iteration (:data:`pienerf.session.INTERACTIVE_SOLVER`). Line-searched Newton converges quadratically near the
solution, so a step that has not met the tolerance after 50 iterations is stalled (the summary line reports its last
update against the tolerance), not slow."""

_NAME = re.compile(r"[A-Za-z0-9_-]+")
"""A name that becomes part of a file name (a variant's): letters, digits, ``_`` and ``-``, so it cannot climb out
of the output folder (``../``) or name a hidden file."""

_PIXELS = _Number(int, 1, 8192, "px")
_KERNELS = _Number(int, 1, 100_000)
_RADIUS = _Number(float, 0.0, 10.0, "m", low_open=True)
_LLOYD = _Number(int, 0, 1000)
_TIME = _Number(float, 0.0, MAX_TIME, "s")
_FRAMES = _Number(int, 1, MAX_FRAMES)

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
        "warp_error": dict,
    },
    "scene": {"name": str, "floor": bool, "default_pins": bool},
    "material": {
        "model": str,
        "young_modulus": _Number(float, 0.0, 1e12, "Pa", low_open=True),
        "poisson_ratio": _Number(float, -0.999, 0.499),
        "density": _Number(float, 0.0, 1e5, "kg/m³", low_open=True),
    },
    "discretization": {
        "kernel_count": _KERNELS,
        "particle_radius": _RADIUS,
        "order": str,
        "lloyd_iterations": _LLOYD,
        "seed": _Number(int, 0, 2**32 - 1),
    },
    "solver": {
        "dt": _Number(float, 0.0, 1.0, "s", low_open=True),
        "frames": _FRAMES,
        "substeps": _Number(int, 1, 10_000),
        "rayleigh_alpha": _Number(float, 0.0, 1e4, "1/s"),
        "rayleigh_beta": _Number(float, 0.0, 10.0, "s"),
        "gravity": _VEC3,
        "newton_iterations": _Number(int, 1, 1000),
        "drag_stiffness": _Number(float, 0.0, 1e12, "N/m", low_open=True),
        "drag_damping": _Number(float, 0.0, 1e12, "N·s/m"),
        "max_acceleration": _Number(float, 0.0, 1e6, "m/s²", low_open=True),
    },
    "pins": {"box": list},
    "drags": {"point": _VEC3, "keys": list, "release": _TIME},
    "forces": {"point": _VEC3, "force": _VEC3, "start": _TIME, "end": _TIME},
    "cuts": {"point": _VEC3, "normal": _VEC3, "radius": _RADIUS},
    "colliders": {"type": str, "point": _VEC3, "normal": _VEC3, "centre": _VEC3, "radius": _RADIUS, "keys": list},
    "cameras": {
        "type": str,
        "distance": _Number(float, 0.0, 1e3, "m", low_open=True),
        "elevation": _Number(float, -90.0, 90.0, "degrees"),
        "azimuths": list,
        "spin_deg_per_s": _Number(float, -3600.0, 3600.0, "degrees/s"),
        "positions": list,
        "look_at": _VEC3,
        "up": _VEC3,
        "width": _PIXELS,
        "height": _PIXELS,
        "fov": _Number(float, 1.0, 179.0, "degrees"),
    },
    "outputs": {
        "frames": bool,
        "mp4": bool,
        "depth": bool,
        "shadow": bool,
        "fps": _Number(float, 1.0, 1000.0, "frames/s"),
        "modes": list,
        "mesh_edge_fraction": _Number(float, 0.0, 10.0, low_open=True),
    },
    "variants": {"name": str, "label": str, "material": dict, "discretization": dict, "modes": list},
    "volume_samples": {"time": _TIME, "label": str},
    "smoke": {
        "frames": _FRAMES,
        "width": _PIXELS,
        "height": _PIXELS,
        "kernel_count": _KERNELS,
        "particle_radius": _RADIUS,
        "lloyd_iterations": _LLOYD,
        "nerf": dict,
    },
    "nerf": {
        "source": str,
        "up": str,
        "warps": list,
        "steps": _Number(int, 1, 1_000_000),
        "batch_rays": _Number(int, 1, 1 << 22),
        "views": _Number(int, 1, 10_000),
        "resolution": _Number(int, 8, 8192, "px"),
        "downscale": _Number(int, 1, 64),
        "max_views": _Number(int, 1, 10_000),
        "levels": _Number(int, 1, 32),
        "log2_table_size": _Number(int, 4, 26),
        "max_resolution": _Number(int, 2, 1 << 16),
        "hidden": _Number(int, 1, 1024),
        "samples_per_diagonal": _Number(int, 1, 8192),
        "grid_resolution": _Number(int, 2, 1024),
        "grid_decay": _Number(float, 0.0, 1.0, low_open=True),
        "solid_resolution": _Number(int, 8, 1024),
    },
    "warp_error": {"region": list, "dilation": _Number(float, 0.0, 1000.0, "px"), "label": str},
}
"""Every key a scenario may hold, per table: its type, and for a number its range and unit (:class:`_Number`)."""

NERF_WARPS = {"quadratic": "nerf", "linear": "nerf_linear", "rest": "nerf_rest"}
"""Render mode of each ray warping of the ``[nerf]`` table."""


_SCENE_FILE_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".pt")

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
            _check_vec3(value, path)
        elif isinstance(expected, _Number):
            if not expected.admits(value):
                raise ScenarioError(f"'{path}' must be {expected.describe()}, got {value!r}")
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


def load_scenario(path: Path | str, smoke: bool = False, frames: int | None = None) -> dict:
    """Read and check a scenario; with ``smoke``, the ``[smoke]`` table shrinks it; ``frames`` (1 to
    :data:`MAX_FRAMES`) then replaces its frame count, volume samples past the end taken at the last frame.

    Raises:
        ScenarioError: the file, a key or ``frames`` is bad; the message names it and the fix.
    """
    integer = isinstance(frames, int) and not isinstance(frames, bool)
    if frames is not None and not (integer and 1 <= frames <= MAX_FRAMES):
        raise ScenarioError(
            f"--frames must be an integer in [1, {MAX_FRAMES}] (frames after the first), got {frames!r}"
        )
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(
            f"scenario file {path} does not exist; pass a .toml file such as assets/scenarios/plant_sway.toml"
        )
    try:
        scenario = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{path} is not valid TOML ({error}); fix the syntax at that line") from None
    try:
        _check_table(scenario, "", "")
        _check_structure(scenario)
    except ScenarioError as error:
        raise ScenarioError(f"{path}: {error}") from None
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
        _shrink_volume_samples(scenario)
    if frames is not None:
        solver = scenario.setdefault("solver", {})
        if frames * solver.get("substeps", 1) > MAX_STEPS:
            raise ScenarioError(
                f"--frames {frames} × 'solver.substeps' is {frames * solver.get('substeps', 1)} solver steps; at most "
                f"{MAX_STEPS}: lower --frames"
            )
        solver["frames"] = frames
        _shrink_volume_samples(scenario, f"--frames {frames}")
    return scenario


def _finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_vec3(value, where: str) -> None:
    if not (
        isinstance(value, list)
        and len(value) == 3
        and all(_finite_number(v) and abs(v) <= MAX_COORDINATE for v in value)
    ):
        raise ScenarioError(
            f"'{where}' must be 3 finite numbers of magnitude <= {MAX_COORDINATE:g} like [0.0, 1.0, 0.0], got {value!r}"
        )


def _check_strings(value: list, where: str, valid=None, empty: bool = True) -> None:
    if not empty and not value:
        raise ScenarioError(f"'{where}' must not be empty")
    for item in value:
        if not isinstance(item, str):
            raise ScenarioError(f"'{where}' must be an array of strings, has {item!r}")
        if valid is not None and item not in valid:
            raise ScenarioError(f"'{where}' has {item!r}; valid: {', '.join(valid)}")


def _check_keys(keys, where: str) -> None:
    """``[[time, [x, y, z]], …]`` with times in ``[0, MAX_TIME]`` s, not decreasing."""
    shape = "[[time, [x, y, z]], ...] (s, m)"
    if not isinstance(keys, list) or not keys:
        raise ScenarioError(f"'{where}' must be a non-empty {shape}, got {keys!r}")
    times = []
    for key in keys:
        if not (isinstance(key, list) and len(key) == 2 and _TIME.admits(key[0])):
            raise ScenarioError(f"'{where}' must be {shape} with times {_TIME.describe()}, has {key!r}")
        _check_vec3(key[1], where)
        times.append(key[0])
    if any(b < a for a, b in zip(times, times[1:], strict=False)):
        raise ScenarioError(f"'{where}' times must not decrease, got {times}")


def _check_scene_name(name: str) -> None:
    if name in SCENES:
        return
    file = Path(name)
    if file.suffix.lower() not in _SCENE_FILE_SUFFIXES:
        raise ScenarioError(
            f"'scene.name' {name!r} is neither an embedded scene ({', '.join(SCENES)}) nor a mesh "
            f"({', '.join(_SCENE_FILE_SUFFIXES[:-1])}) or NeRF checkpoint (.pt) path"
        )
    if not file.is_file():
        raise ScenarioError(f"'scene.name' file {name!r} does not exist; give a path from the working folder")


def _check_structure(scenario: dict) -> None:
    """What the per-key types cannot say: required keys, the arrays' contents, the choices among strings."""
    for key in ("scene", "cameras"):
        if key not in scenario:
            raise ScenarioError(f"missing table [{key}]; every scenario needs [scene] and [cameras]")
    _check_strings(scenario.get("requires", []), "requires")
    for need in scenario.get("requires", []):
        if need != "nerf_renderer" and not need.startswith(("data:", "checkpoint:")):
            raise ScenarioError(
                f"unknown requirement {need!r} in 'requires'; valid: nerf_renderer, data:NAME, checkpoint:PATH"
            )
    _check_strings(scenario.get("pending", []), "pending")
    nerf = scenario.get("nerf")
    if nerf is not None:
        source = nerf.get("source", "scene")
        if source != "scene" and not (source.startswith("data:") and len(source) > 5):
            raise ScenarioError(f'\'nerf.source\' must be "scene" or "data:NAME", got {source!r}')
        if nerf.get("up", "z") not in ("y", "z"):
            raise ScenarioError(f'\'nerf.up\' must be "y" or "z", got {nerf["up"]!r}')
        _check_strings(nerf.get("warps", ["quadratic"]), "nerf.warps", NERF_WARPS, empty=False)
    from_data = nerf is not None and nerf.get("source", "scene").startswith("data:")
    if "name" in scenario["scene"]:
        _check_scene_name(scenario["scene"]["name"])
    elif not from_data:
        raise ScenarioError(
            "missing key 'scene.name'; set it to an embedded scene (plant, teapot, jelly, cloth, "
            'sculpture) or a mesh path, or give [nerf] source = "data:NAME"'
        )
    elif nerf.get("source") == "scene":
        raise ScenarioError("[nerf] source = \"scene\" needs 'scene.name'")
    tables = [("material", scenario.get("material", {}))]
    tables += [(f"variants[{i}].material", v.get("material", {})) for i, v in enumerate(scenario.get("variants", []))]
    for where, material in tables:
        if "model" in material and material["model"] not in MATERIAL_MODELS:
            raise ScenarioError(
                f"'{where}.model' must be one of {', '.join(MATERIAL_MODELS)}, got {material['model']!r}"
            )
    tables = [("discretization", scenario.get("discretization", {}))]
    tables += [
        (f"variants[{i}].discretization", v.get("discretization", {}))
        for i, v in enumerate(scenario.get("variants", []))
    ]
    for where, discretization in tables:
        if "order" in discretization and discretization["order"] not in ORDERS:
            raise ScenarioError(f"'{where}.order' must be one of {', '.join(ORDERS)}, got {discretization['order']!r}")
    solver = scenario.get("solver", {})
    for table in ("solver", "smoke"):
        frames = scenario.get(table, {}).get("frames", solver.get("frames", 30))
        if frames * solver.get("substeps", 1) > MAX_STEPS:
            raise ScenarioError(
                f"'{table}.frames' × 'solver.substeps' is {frames * solver.get('substeps', 1)} solver steps; "
                f"at most {MAX_STEPS}: lower the frames or the substeps"
            )
    _check_strings(scenario.get("outputs", {}).get("modes", ["mesh"]), "outputs.modes", empty=False)
    names = []
    for i, variant in enumerate(scenario.get("variants", [])):
        _check_strings(variant.get("modes", ["mesh"]), f"variants[{i}].modes", empty=False)
        name = variant.get("name", "default")
        if not _NAME.fullmatch(name):
            raise ScenarioError(
                f"'variants[{i}].name' {name!r} becomes part of the output file names: use only letters, digits, "
                "'_' and '-' (put free text in 'label')"
            )
        if name in names:
            raise ScenarioError(f"'variants[{i}].name' {name!r} repeats an earlier variant's; give each its own name")
        names.append(name)
    cameras = scenario["cameras"]
    kind = cameras.get("type", "orbit")
    if kind == "orbit":
        azimuths = cameras.get("azimuths", [0.0])
        if not azimuths or not all(_finite_number(a) and abs(a) <= 3600 for a in azimuths):
            raise ScenarioError(f"'cameras.azimuths' must be a non-empty array of degrees, got {azimuths!r}")
    elif kind == "fixed":
        if "positions" not in cameras or "look_at" not in cameras:
            raise ScenarioError("fixed cameras need 'cameras.positions' ([[x, y, z], ...]) and 'cameras.look_at'")
        if not cameras["positions"]:
            raise ScenarioError("'cameras.positions' must name at least one camera position [x, y, z]")
        for position in cameras["positions"]:
            _check_vec3(position, "cameras.positions")
    else:
        raise ScenarioError(f"'cameras.type' must be 'orbit' or 'fixed', got {kind!r}")
    for i, pin in enumerate(scenario.get("pins", [])):
        box = pin.get("box")
        if not (isinstance(box, list) and len(box) == 2):
            raise ScenarioError(f"'pins[{i}].box' must be [[x0, y0, z0], [x1, y1, z1]] (m), got {box!r}")
        for corner in box:
            _check_vec3(corner, f"pins[{i}].box")
    for i, drag in enumerate(scenario.get("drags", [])):
        if "point" not in drag or "keys" not in drag:
            raise ScenarioError(f"'drags[{i}]' needs 'point' (rest position, m) and 'keys' ([[time, [x, y, z]]])")
        _check_keys(drag["keys"], f"drags[{i}].keys")
    if len(scenario.get("drags", [])) > 1:
        raise ScenarioError("at most one [[drags]] entry: the drag is the mouse; use [[forces]] for further loads")
    for i, force in enumerate(scenario.get("forces", [])):
        if "point" not in force or "force" not in force:
            raise ScenarioError(f"'forces[{i}]' needs 'point' (rest position, m) and 'force' (N)")
        if force.get("end", MAX_TIME) < force.get("start", 0.0):
            raise ScenarioError(f"'forces[{i}].end' ({force['end']} s) is before its 'start' ({force['start']} s)")
    for i, cut in enumerate(scenario.get("cuts", [])):
        if "point" not in cut or "normal" not in cut:
            raise ScenarioError(f"'cuts[{i}]' needs 'point' (m) and 'normal'")
        if not any(cut["normal"]):
            raise ScenarioError(f"'cuts[{i}].normal' must not be [0, 0, 0]")
    for i, collider in enumerate(scenario.get("colliders", [])):
        kind = collider.get("type")
        if kind == "sphere":
            if "centre" not in collider or "radius" not in collider:
                raise ScenarioError(f"'colliders[{i}]' sphere needs 'centre' (m) and 'radius' (m)")
        elif kind == "plane":
            if not any(collider.get("normal", [0.0, 1.0, 0.0])):
                raise ScenarioError(f"'colliders[{i}].normal' must not be [0, 0, 0]")
            if "keys" in collider:
                _check_keys(collider["keys"], f"colliders[{i}].keys")
        else:
            raise ScenarioError(f"'colliders[{i}].type' must be 'plane' or 'sphere', got {kind!r}")
    warp_error = scenario.get("warp_error")
    if warp_error is not None:
        if nerf is None:
            raise ScenarioError("[warp_error] compares warped-NeRF renders with the mesh; add a [nerf] table")
        box = warp_error.get("region")
        if not (isinstance(box, list) and len(box) == 2):
            raise ScenarioError(
                f"'warp_error.region' must be a rest-space box [[x0, y0, z0], [x1, y1, z1]] (m), got {box!r}"
            )
        for corner in box:
            _check_vec3(corner, "warp_error.region")
        if any(a > b for a, b in zip(box[0], box[1], strict=True)):
            raise ScenarioError(f"'warp_error.region' must list its low corner first, got {box!r}")
    for i, sample in enumerate(scenario.get("volume_samples", [])):
        for key in ("time", "label"):
            if key not in sample:
                raise ScenarioError(f"'volume_samples[{i}]' needs '{key}' (time in s and a label for the bar chart)")


def _shrink_volume_samples(scenario: dict, why: str = "smoke") -> None:
    """At smoke size (or under ``--frames``), volume samples past the shortened run are taken at its last frame,
    their labels saying so (``why``), so the volume bars still show every requested sample."""
    solver = scenario.get("solver", {})
    frame_dt = solver.get("dt", SimulationConfig.dt)
    end = solver.get("frames", 30) * frame_dt
    for spec in scenario.get("volume_samples", []):
        if spec.get("time", 0.0) > end + 0.5 * frame_dt:  # the schema check made spec a table, time a number
            label = spec.get("label", f"t = {spec['time']:g} s")
            spec.update(time=end, label=f"{label} ({why}: at {end:.2g} s)")


def unmet_requirement(scenario: dict) -> str | None:
    """Why the scenario cannot run here, or ``None``: ``"nerf_renderer"`` needs :mod:`pienerf.render`'s warped-NeRF
    renderer, ``"data:NAME"`` the folder :data:`pienerf.paths.SHARED_DATA` ``/ NAME``, ``"checkpoint:PATH"`` a
    trained NeRF file."""
    needs = list(scenario.get("requires", []))
    source = scenario.get("nerf", {}).get("source", "scene")
    if source.startswith("data:") and source not in needs:
        needs.append(source)
    for need in needs:
        if need == "nerf_renderer":
            if importlib.util.find_spec("pienerf.render.previews") is None:
                return (
                    "the warped-NeRF renderer pienerf.render is not in this checkout; this scenario renders once it is"
                )
        elif need.startswith("data:"):
            folder = SHARED_DATA / need[5:]
            if not folder.is_dir():
                return f"data folder {folder} is absent; place the dataset there"
        elif need.startswith("checkpoint:"):
            file = Path(need[11:])
            if not file.is_file():
                return f"trained NeRF checkpoint {file} is absent; train it with python -m pienerf.nerf.training"
        else:
            raise ScenarioError(
                f"unknown requirement {need!r} in 'requires'; valid: nerf_renderer, data:NAME, checkpoint:PATH"
            )
    return None


def keyframe(keys: list, t: float, where: str) -> torch.Tensor:
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


@dataclass
class ScenarioNerf:
    """The scenario's fitted NeRF: the rest-space field and grid, its checkpoint when it is the simulated scene."""

    field: object
    grid: object
    checkpoint: Path | None
    warps: list
    source: str
    seconds: float
    solid_resolution: int


def nerf_fit(spec: dict) -> NerfFit:
    """The :class:`pienerf.nerf.fitting.NerfFit` of a ``[nerf]`` table: its defaults, overridden by the table's keys."""
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


def progress_log(log, what: str):
    """A ``(stage, fraction)`` callback that logs a line at every tenth of the way."""
    reached = [-1]

    def progress(stage: str, fraction: float) -> None:
        tenth = int(10 * fraction)
        if tenth > reached[0]:
            reached[0] = tenth
            log(f"{what}: {stage}")

    return progress


def prepare_nerf(scenario: dict, cache_dir, log) -> ScenarioNerf | None:
    """Fit (or load from the cache) the NeRF of the scenario's ``[nerf]`` table; ``None`` without one.

    ``log(line)`` hears the progress at every tenth of the way; ``cache_dir`` is :func:`pienerf.paths.cache_root`'s.
    """
    spec = scenario.get("nerf")
    if spec is None:
        return None
    fit = nerf_fit(spec)
    source = spec.get("source", "scene")
    progress = progress_log(log, scenario.get("name", "scenario"))
    start = time.perf_counter()
    checkpoint = None
    if source == "scene":
        trained = scene_nerf(scenario["scene"]["name"], fit, cache_dir, progress)
    else:
        folder, up = SHARED_DATA / source[5:], spec.get("up", "z")
        trained = dataset_nerf(folder, fit, up, cache_dir, progress)
        checkpoint = dataset_nerf_path(folder, fit, up, cache_dir)
    return ScenarioNerf(
        trained.field,
        trained.grid,
        checkpoint,
        list(spec.get("warps", ["quadratic"])),
        source,
        time.perf_counter() - start,
        spec.get("solid_resolution", 96),
    )


def scenario_cameras(scenario: dict, centre, t: float) -> Cameras:
    """The ``[cameras]`` table at time ``t`` (s): an orbit about ``centre [3]`` (m), turning at ``spin_deg_per_s``,
    or fixed positions looking at one point.

    ``up`` (default +y) is the world direction shown upright: elevations and azimuths are measured from and about
    it, so a scenario whose gravity points along −z sets ``up = [0, 0, 1]`` to be seen the right way up.
    """
    spec = scenario["cameras"]
    width, height, fov = spec.get("width", 320), spec.get("height", 240), spec.get("fov", 40.0)
    kind = spec.get("type", "orbit")
    turn = _up_rotation(spec.get("up", [0.0, 1.0, 0.0]))  # from a y-up frame to the world
    if kind == "orbit":
        spin = spec.get("spin_deg_per_s", 0.0) * t
        azimuths = [a + spin for a in spec.get("azimuths", [0.0])]
        local_centre = turn.T @ torch.as_tensor(centre, dtype=torch.float64).reshape(3)
        cameras = orbit_cameras(
            local_centre, spec.get("distance", 2.5), azimuths, spec.get("elevation", 15.0), width, height, fov
        )
    elif kind == "fixed":
        if "positions" not in spec or "look_at" not in spec:
            raise ScenarioError("fixed cameras need 'cameras.positions' ([[x, y, z], ...]) and 'cameras.look_at'")
        positions = torch.tensor(spec["positions"], dtype=torch.float64) @ turn
        look_at = turn.T @ torch.tensor(spec["look_at"], dtype=torch.float64)
        cameras = look_at_cameras(positions, look_at.expand_as(positions), width, height, fov)
    else:
        raise ScenarioError(f"'cameras.type' must be 'orbit' or 'fixed', got {kind!r}")
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3] = turn
    return replace(cameras, c2w=(transform @ cameras.c2w.double()).float())


def _up_rotation(up) -> torch.Tensor:
    """The ``[3, 3]`` rotation taking +y to the unit vector of ``up`` (the shortest turn; a half turn about x for
    −y)."""
    target = torch.tensor(up, dtype=torch.float64)
    norm = float(target.norm())
    if norm == 0.0:
        raise ScenarioError("'cameras.up' must be a non-zero direction like [0.0, 1.0, 0.0]")
    target = target / norm
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    axis, cosine = torch.linalg.cross(y, target), float(y @ target)
    if cosine < -1.0 + 1e-12:
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    k = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]], dtype=torch.float64
    )
    return torch.eye(3, dtype=torch.float64) + k + k @ k / (1.0 + cosine)


def scenario_colliders(scenario: dict, t: float, floor: bool) -> list[PlaneCollider | SphereCollider]:
    """The floor (when on) and the ``[[colliders]]`` at time ``t`` (s), keyframed planes moved."""
    colliders = [PlaneCollider()] if floor else []
    for i, spec in enumerate(scenario.get("colliders", [])):
        kind = spec.get("type")
        if kind == "plane":
            point = spec.get("point", [0.0, 0.0, 0.0])
            if "keys" in spec:
                point = keyframe(spec["keys"], t, f"colliders[{i}].keys").tolist()
            colliders.append(PlaneCollider(tuple(point), tuple(spec.get("normal", [0.0, 1.0, 0.0]))))
        elif kind == "sphere":
            if "centre" not in spec or "radius" not in spec:
                raise ScenarioError(f"'colliders[{i}]' sphere needs 'centre' and 'radius'")
            colliders.append(SphereCollider(tuple(spec["centre"]), float(spec["radius"])))
        else:
            raise ScenarioError(f"'colliders[{i}].type' must be 'plane' or 'sphere', got {kind!r}")
    return colliders


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


OUTPUT_DEFAULTS = {"frames": True, "mp4": True, "depth": False, "shadow": False, "fps": 30.0, "modes": ["mesh"]}
"""What a scenario writes unless its ``[outputs]`` table says otherwise."""


def require_video_encoder(scenario: dict) -> None:
    """Refuse, before any work, a scenario whose outputs include ``video.mp4`` where it cannot be written: imageio
    writes an MP4 through the imageio-ffmpeg package, and without it picks another writer by the file name that
    fails at the first frame, after the simulation work.

    Raises:
        ScenarioError: ``outputs.mp4`` is on and imageio-ffmpeg is not installed; the message names both fixes.
    """
    if scenario_outputs(scenario)["mp4"] and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ScenarioError(
            "'outputs.mp4' = true needs the imageio-ffmpeg package to write video.mp4, and it is not installed: "
            "pip install imageio-ffmpeg, or set mp4 = false under [outputs] to write the frames only"
        )


def scenario_outputs(scenario: dict) -> dict:
    """The ``[outputs]`` table over :data:`OUTPUT_DEFAULTS`."""
    return {**OUTPUT_DEFAULTS, **scenario.get("outputs", {})}


def frame_count(scenario: dict) -> tuple[int, int]:
    """``(frames, substeps)`` of the ``[solver]`` table: frames after the first, solver steps per frame."""
    solver = scenario.get("solver", {})
    frames, substeps = solver.get("frames", 30), solver.get("substeps", 1)
    if frames < 1 or substeps < 1:
        raise ScenarioError("'solver.frames' and 'solver.substeps' must be >= 1")
    return frames, substeps


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


def volume_sample_frames(scenario: dict) -> list[dict]:
    """The ``[[volume_samples]]`` in time order, each with the ``frame`` nearest its ``time``.

    A frame lasts ``solver.dt`` (s), so a requested time lies within half a frame of its sample's frame; rounding,
    not flooring, keeps t = 2.0 s of a 60-frame run at dt = 0.0333333 s. A time beyond the last frame (by more than
    half a frame) or before the first raises :class:`ScenarioError` naming the sample and the run's length.
    """
    frames, _ = frame_count(scenario)
    frame_dt = scenario.get("solver", {}).get("dt", SimulationConfig.dt)
    samples = []
    for i, spec in enumerate(scenario.get("volume_samples", [])):
        if "time" not in spec:
            raise ScenarioError(f"'volume_samples[{i}]' needs 'time' (s)")
        frame = round(spec["time"] / frame_dt)
        if not 0 <= frame <= frames:
            raise ScenarioError(
                f"'volume_samples[{i}].time' = {spec['time']} s lies outside the run (0 to {frames * frame_dt:.4g} s: "
                f"{frames} frames of {frame_dt} s); raise 'solver.frames' or sample earlier"
            )
        samples.append({"label": f"t = {spec['time']:g} s", **spec, "frame": frame})
    return sorted(samples, key=lambda s: s["frame"])


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
