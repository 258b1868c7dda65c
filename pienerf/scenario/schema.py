"""The scenario format: every key a TOML scenario may hold, its checks, and the values read from a checked one.

:func:`load_scenario` reads and checks a file (a bad key raises :class:`ScenarioError` naming the key and the fix);
:func:`unmet_requirement` says why it cannot run here, :func:`require_video_encoder` why its video cannot be
written; :func:`scenario_outputs`, :func:`frame_count` and :func:`volume_sample_frames` read its tables.
"""

from __future__ import annotations

import copy
import importlib.util
import itertools
import math
import re
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from pienerf.paths import SHARED_DATA
from pienerf.scenario.expectations import FULL_RUN_KEYS
from pienerf.scenes import SCENES
from pienerf.session import SimulationConfig
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig
from pienerf.sim.picking import DragConfig
from pienerf.sim.settings import SettingRange, setting_range
from pienerf.sim.solver import SolverConfig

__all__ = [
    "MAX_COORDINATE",
    "MAX_FRAMES",
    "MAX_STEPS",
    "MAX_TIME",
    "NERF_WARPS",
    "OUTPUT_DEFAULTS",
    "MAX_SWEEP_POINTS",
    "SWEEP_MODES",
    "ScenarioError",
    "apply_sweep_point",
    "frame_count",
    "load_scenario",
    "require_video_encoder",
    "scenario_outputs",
    "sweep_points",
    "unmet_requirement",
    "volume_sample_frames",
]

_VEC3 = "vec3"
_BAND = "band"


MAX_FRAMES = 100_000
"""Most frames a scenario may render (``solver.frames``, ``smoke.frames``): over an hour of video at 24 fps."""
MAX_STEPS = 1_000_000
"""Most solver steps a scenario may take (frames × substeps)."""
MAX_COORDINATE = 1e4
"""Largest magnitude (m, or N for a force) of a 3-vector's entry."""
MAX_TIME = 1e5
"""Latest time (s) a keyframe, force window, release or volume sample may name."""

_NAME = re.compile(r"[A-Za-z0-9_-]+")
"""A name that becomes part of a file name (a variant's): letters, digits, ``_`` and ``-``, so it cannot climb out
of the output folder (``../``) or name a hidden file."""

_PIXELS = SettingRange(int, 1, 8192, "px")
_KERNELS = setting_range(DiscretizationConfig, "kernel_count")
_RADIUS = setting_range(SimulationConfig, "particle_radius")
_LENGTH = SettingRange(float, 0.0, 10.0, "m", low_open=True)
_LLOYD = setting_range(DiscretizationConfig, "kernel_lloyd_iterations")
_TIME = SettingRange(float, 0.0, MAX_TIME, "s")
_FRAMES = SettingRange(int, 1, MAX_FRAMES)

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
        "expect": dict,
        "sweep": dict,
    },
    "scene": {"name": str, "floor": bool, "default_pins": bool},
    "material": {key: setting_range(Material, key) for key in ("model", "young_modulus", "poisson_ratio", "density")},
    "discretization": {
        "kernel_count": _KERNELS,
        "particle_radius": _RADIUS,
        "order": setting_range(DiscretizationConfig, "order"),
        "lloyd_iterations": _LLOYD,
        "seed": setting_range(SimulationConfig, "seed"),
    },
    "solver": {
        "dt": setting_range(SimulationConfig, "dt"),
        "frames": _FRAMES,
        "substeps": SettingRange(int, 1, 10_000),
        "rayleigh_alpha": setting_range(SolverConfig, "rayleigh_alpha"),
        "rayleigh_beta": setting_range(SolverConfig, "rayleigh_beta"),
        "gravity": _VEC3,
        "newton_iterations": setting_range(SolverConfig, "newton_iterations"),
        "hessian_precision": setting_range(SolverConfig, "hessian_precision"),
        "drag_stiffness": setting_range(DragConfig, "stiffness"),
        "drag_damping": setting_range(DragConfig, "damping"),
        "max_acceleration": setting_range(DragConfig, "max_acceleration"),
    },
    "pins": {"box": list},
    "drags": {"point": _VEC3, "keys": list, "release": _TIME},
    "forces": {"point": _VEC3, "force": _VEC3, "start": _TIME, "end": _TIME},
    "cuts": {"point": _VEC3, "normal": _VEC3, "radius": _LENGTH},
    "colliders": {"type": str, "point": _VEC3, "normal": _VEC3, "centre": _VEC3, "radius": _LENGTH, "keys": list},
    "cameras": {
        "type": str,
        "distance": SettingRange(float, 0.0, 1e3, "m", low_open=True),
        "elevation": SettingRange(float, -90.0, 90.0, "degrees"),
        "azimuths": list,
        "spin_deg_per_s": SettingRange(float, -3600.0, 3600.0, "degrees/s"),
        "positions": list,
        "look_at": _VEC3,
        "up": _VEC3,
        "width": _PIXELS,
        "height": _PIXELS,
        "fov": SettingRange(float, 1.0, 179.0, "degrees"),
    },
    "outputs": {
        "frames": bool,
        "mp4": bool,
        "depth": bool,
        "shadow": bool,
        "fps": SettingRange(float, 1.0, 1000.0, "frames/s"),
        "modes": list,
        "mesh_edge_fraction": SettingRange(float, 0.0, 10.0, low_open=True),
    },
    "variants": {
        "name": str,
        "label": str,
        "material": dict,
        "discretization": dict,
        "modes": list,
        "expect": dict,
    },
    "volume_samples": {"time": _TIME, "label": str},
    "smoke": {
        "frames": _FRAMES,
        "width": _PIXELS,
        "height": _PIXELS,
        "kernel_count": _KERNELS,
        "particle_radius": _RADIUS,
        "lloyd_iterations": _LLOYD,
        "nerf": dict,
        "expect": dict,
    },
    "nerf": {
        "source": str,
        "up": str,
        "warps": list,
        "steps": SettingRange(int, 1, 1_000_000),
        "batch_rays": SettingRange(int, 1, 1 << 22),
        "views": SettingRange(int, 1, 10_000),
        "resolution": SettingRange(int, 8, 8192, "px"),
        "downscale": SettingRange(int, 1, 64),
        "max_views": SettingRange(int, 1, 10_000),
        "levels": SettingRange(int, 1, 32),
        "log2_table_size": SettingRange(int, 4, 26),
        "max_resolution": SettingRange(int, 2, 1 << 16),
        "hidden": SettingRange(int, 1, 1024),
        "samples_per_diagonal": SettingRange(int, 1, 8192),
        "grid_resolution": SettingRange(int, 2, 1024),
        "grid_decay": SettingRange(float, 0.0, 1.0, low_open=True),
        "solid_resolution": SettingRange(int, 8, 1024),
    },
    "warp_error": {"region": list, "dilation": SettingRange(float, 0.0, 1000.0, "px"), "label": str},
    "expect": {
        "relative_volume": _BAND,
        "max_displacement_m": _BAND,
        "centre_displacement_m": _BAND,
        "converged_fraction": SettingRange(float, 0.0, 1.0),
        "warp_psnr_db": SettingRange(float, 0.0, 200.0, "dB"),
        "warp_psnr_gain_db": SettingRange(float, 0.0, 200.0, "dB"),
    },
}
"""Every key a scenario may hold, per table: its type, and for a number or a choice its
:class:`pienerf.sim.settings.SettingRange`, read from the config field the key sets where there is one (so a range is
declared once, on the field) and given here for the scenario's own keys (frames, cameras, outputs, the NeRF fit)."""

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
        elif expected == _BAND:
            _check_band(value, path)
        elif isinstance(expected, SettingRange):
            if not expected.admits(value):
                raise ScenarioError(f"'{path}' must be {expected.describe()}, got {value!r}")
        elif not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise ScenarioError(f"'{path}' must be {_TYPE_NAMES[expected]}, got {value!r}")
        if section == "" and key in _SCHEMA and isinstance(value, dict):
            _check_table(value, key, key)
        if section == "smoke" and key in ("nerf", "expect") and isinstance(value, dict):
            _check_table(value, key, path)
        if section in ("", "variants") and key in ("material", "discretization", "expect") and isinstance(value, dict):
            _check_table(value, key, path)
        if section == "" and key in _SCHEMA and isinstance(value, list):
            for i, item in enumerate(value):
                if not isinstance(item, dict):
                    raise ScenarioError(f"'{path}' must be an array of tables ([[{key}]]), item {i} is {item!r}")
                _check_table(item, key, f"{path}[{i}]")


def load_scenario(path: Path | str, smoke: bool = False, frames: int | None = None) -> dict:
    """Read and check a scenario; with ``smoke``, the ``[smoke]`` table shrinks it (its ``[smoke.expect]`` over the
    ``[expect]`` table, key by key, unless ``frames`` changes the smoke run's length); ``frames`` (1 to
    :data:`MAX_FRAMES`) then replaces its frame count, volume samples past the end taken at the last frame. Either drops
    the expectations measured on the full run (:data:`pienerf.scenario.expectations.FULL_RUN_KEYS`).

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
        _check_sweep(scenario)
    except ScenarioError as error:
        raise ScenarioError(f"{path}: {error}") from None
    if smoke or frames is not None:  # bounds measured on the full run
        for table in [scenario.get("expect", {})] + [v.get("expect", {}) for v in scenario.get("variants", [])]:
            for key in FULL_RUN_KEYS:
                table.pop(key, None)
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
        if "expect" in shrink and frames is None:  # its bounds are derived for the smoke run's length
            scenario["expect"] = {**scenario.get("expect", {}), **shrink["expect"]}
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
    if "sweep" in scenario and (smoke or frames is not None):  # each point as the shrunk scenario would run
        try:
            sweep_points(scenario)
        except ScenarioError as error:
            raise ScenarioError(f"{path}: {error}") from None
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


def _check_band(value, where: str) -> None:
    if not (isinstance(value, list) and len(value) == 2 and all(_finite_number(v) for v in value)):
        raise ScenarioError(f"'{where}' must be a band [low, high] of two finite numbers, got {value!r}")
    if value[0] > value[1]:
        raise ScenarioError(f"'{where}' must list its low end first, got {value!r}")


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


SWEEP_MODES = {
    "grid": "every combination of the fields' values",
    "list": "the i-th value of every field together (arrays of one length)",
}
"""How a ``[sweep]`` table combines its fields' values into points."""

MAX_SWEEP_POINTS = 10_000
"""Most points a ``[sweep]`` table may make."""

_UNSWEPT = {
    "sweep": "a sweep cannot sweep itself",
    "smoke": "--smoke applies [smoke] before the sweep; sweep the field it sets instead",
}


def _sweep_fields(table: dict, prefix: str = "") -> list[tuple[str, object]]:
    """``(dotted field, values)`` of a ``[sweep]`` table, its ``mode`` left out: ``material.young_modulus = [...]``
    (TOML's dotted keys, which make nested tables) and ``"material.young_modulus" = [...]`` (one quoted key) alike."""
    fields = []
    for key, value in table.items():
        if not prefix and key == "mode":
            continue
        path = f"{prefix}.{key}" if prefix else key
        if isinstance(value, dict):
            fields += _sweep_fields(value, path)
        else:
            fields.append((path, value))
    return fields


def _check_sweep_field(path: str) -> None:
    """A swept field must name a key of one of the scenario's tables (``TABLE.KEY``, ``nerf.steps``…)."""
    parts = path.split(".")
    top = _SCHEMA[""]
    example = "material.young_modulus = [1.0e5, 1.0e6]"
    if parts[0] in _UNSWEPT:
        raise ScenarioError(f"'sweep.{path}': {_UNSWEPT[parts[0]]}")
    if parts[0] not in top:
        raise ScenarioError(
            f"'sweep.{path}' names no scenario field: '{parts[0]}' is not a table of the scenario; valid tables: "
            f"{', '.join(sorted(k for k, v in top.items() if v is dict and k not in _UNSWEPT))} "
            f"(write TABLE.KEY = [values], e.g. {example})"
        )
    if top[parts[0]] is list:
        raise ScenarioError(
            f"'sweep.{path}': [[{parts[0]}]] is an array of tables, whose entries a sweep cannot address; sweep a "
            f"field of a table such as {example}"
        )
    if top[parts[0]] is not dict or len(parts) != 2:
        raise ScenarioError(
            f"'sweep.{path}' must name one key of a table as TABLE.KEY (e.g. {example}), got {len(parts)} parts"
        )
    if parts[1] not in _SCHEMA[parts[0]]:
        raise ScenarioError(
            f"'sweep.{path}': unknown field '{parts[1]}' of [{parts[0]}]; valid fields: "
            f"{', '.join(sorted(_SCHEMA[parts[0]]))}"
        )


def _check_sweep(scenario: dict) -> None:
    """The ``[sweep]`` table's form: its mode, each field a key of a table with a non-empty array of values, the
    point count; each point's values are checked as the scenario's own by :func:`sweep_points`."""
    sweep = scenario.get("sweep")
    if sweep is None:
        return
    mode = sweep.get("mode", "grid")
    if mode not in SWEEP_MODES:
        raise ScenarioError(
            f"'sweep.mode' must be one of: {'; '.join(f'{k!r} ({v})' for k, v in SWEEP_MODES.items())}; got {mode!r}"
        )
    fields = _sweep_fields(sweep)
    if not fields:
        raise ScenarioError(
            "[sweep] names no field to sweep; add one such as material.young_modulus = [1.0e5, 1.0e6] under it"
        )
    for path, values in fields:
        _check_sweep_field(path)
        if not isinstance(values, list):
            raise ScenarioError(
                f"'sweep.{path}' must be an array of the values to sweep, e.g. [{values!r}, ...], got {values!r} "
                f"(a single value belongs in [{path.split('.')[0]}] itself)"
            )
        if not values:
            raise ScenarioError(f"'sweep.{path}' is an empty array; give it at least one value to sweep")
    if mode == "list":
        lengths = {path: len(values) for path, values in fields}
        if len(set(lengths.values())) > 1:
            raise ScenarioError(
                '[sweep] mode = "list" takes the i-th value of every field together, so every array needs the '
                f'same length; got {", ".join(f"{p}: {n}" for p, n in lengths.items())} (or use mode = "grid")'
            )
    count = math.prod(len(v) for _, v in fields) if mode == "grid" else len(fields[0][1])
    if count > MAX_SWEEP_POINTS:
        raise ScenarioError(f"[sweep] makes {count} points, at most {MAX_SWEEP_POINTS}: sweep fewer values")
    sweep_points(scenario)


def sweep_points(scenario: dict) -> dict[str, dict]:
    """The points of the scenario's ``[sweep]`` table, in order: point name (``p000``, ``p001``…, the folder it is
    written to) → its values (dotted field → value). Each point's scenario is checked as a scenario file is.

    Raises:
        ScenarioError: the scenario has no ``[sweep]``, or a point's value is wrong for its field (the message names
            the point, the field and the value).
    """
    sweep = scenario.get("sweep")
    if sweep is None:
        raise ScenarioError("the scenario has no [sweep] table; add one (docs/sweeps.md) or run it without --sweep")
    fields = _sweep_fields(sweep)
    names = [path for path, _ in fields]
    if sweep.get("mode", "grid") == "grid":
        combos = list(itertools.product(*(values for _, values in fields)))
    else:
        combos = list(zip(*(values for _, values in fields), strict=True))
    width = max(3, len(str(len(combos) - 1)))
    points = {f"p{i:0{width}d}": dict(zip(names, combo, strict=True)) for i, combo in enumerate(combos)}
    for name, parameters in points.items():
        apply_sweep_point(scenario, parameters, name)
    return points


def apply_sweep_point(scenario: dict, parameters: dict, name: str = "point") -> dict:
    """A copy of ``scenario`` with each dotted field of ``parameters`` set to its value and without ``[sweep]``,
    checked as a scenario file is.

    Raises:
        ScenarioError: a value is wrong for its field; the message names the point, the field, the value and the fix.
    """
    point = copy.deepcopy(scenario)
    point.pop("sweep", None)
    for path, value in parameters.items():
        _check_sweep_field(path)
        table, key = path.split(".")
        point.setdefault(table, {})[key] = copy.deepcopy(value)
    try:
        _check_table(point, "", "")
        _check_structure(point)
    except ScenarioError as error:
        values = ", ".join(f"{p} = {v!r}" for p, v in parameters.items())
        raise ScenarioError(f"sweep point {name} ({values}): {error}; fix that value in the [sweep] table") from None
    return point
