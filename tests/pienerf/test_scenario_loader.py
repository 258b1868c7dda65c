"""The scenario loader: every bad value stops with a ScenarioError naming the file and the key, never a raw exception
or a value silently replaced; a seeded fuzzer of mutated project scenarios holds it to that."""

from __future__ import annotations

import copy
import math
import random
from pathlib import Path

import pytest
import torch

from pienerf import scenario as scenario_module
from pienerf.scenario import MAX_FRAMES, ScenarioError, load_scenario

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

SCENARIOS = sorted((Path(__file__).resolve().parents[2] / "assets" / "scenarios").glob("*.toml"))
BASE = '[scene]\nname = "jelly"\n[cameras]\ntype = "orbit"\n'


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f'"{k}" = {_toml_value(v)}' for k, v in value.items()) + "}"
    raise TypeError(f"no TOML for {value!r}")


def _toml(document: dict) -> str:
    """A TOML text of ``document`` (inline tables and arrays under top-level keys)."""
    return "".join(f'"{key}" = {_toml_value(value)}\n' for key, value in document.items())


def _load_text(tmp_path: Path, text: str, smoke: bool = False) -> dict:
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    return load_scenario(path, smoke=smoke)


def _error(tmp_path: Path, text: str) -> str:
    with pytest.raises(ScenarioError) as caught:
        _load_text(tmp_path, text)
    message = str(caught.value)
    assert str(tmp_path / "scenario.toml") in message, "the error names the file"
    return message


def test_the_toml_writer_round_trips_the_project_scenarios():
    for path in SCENARIOS:
        document = tomllib.loads(path.read_text())
        assert tomllib.loads(_toml(document)) == document


@pytest.mark.parametrize(
    "table, key, value, says",
    [
        ("discretization", "kernel_count", "0", "'discretization.kernel_count' must be an integer in [1, "),
        ("outputs", "fps", "0", "'outputs.fps' must be a number in [1, 1000] frames/s, got 0"),
        ("solver", "drag_damping", "1e300", "'solver.drag_damping' must be a number in [0, 1e+12] N·s/m"),
        ("solver", "frames", "9223372036854775807", f"'solver.frames' must be an integer in [1, {MAX_FRAMES}]"),
        ("solver", "dt", "nan", "'solver.dt' must be a number in (0, 1] s, got nan"),
        ("material", "young_modulus", "-5.0", "'material.young_modulus' must be a number in (0, 1e+12] Pa"),
        ("cameras", "width", "100000", "'cameras.width' must be an integer in [1, 8192] px"),
        ("smoke", "frames", "0", "'smoke.frames' must be an integer in [1, "),
        ("outputs", "mesh_edge_fraction", "0.0", "'outputs.mesh_edge_fraction' must be a number in (0, 10]"),
        ("warp_error", "dilation", "-2.0", "'warp_error.dilation' must be a number in [0, 1000] px"),
        ("solver", "hessian_precision", '"float16"', "'solver.hessian_precision' must be one of auto, float32"),
    ],
)
def test_out_of_range_numbers_name_the_key_and_the_range(tmp_path, table, key, value, says):
    body = BASE if table != "cameras" else '[scene]\nname = "jelly"\n'
    header = f"[{table}]\n" if table != "cameras" else '[cameras]\ntype = "orbit"\n'
    assert says in _error(tmp_path, body + header + f"{key} = {value}\n")


def test_a_sphere_collider_needs_a_positive_radius(tmp_path):
    collider = '[[colliders]]\ntype = "sphere"\ncentre = [0.0, 0.5, 0.0]\nradius = -1.0\n'
    assert "'colliders[0].radius' must be a number in (0, 10] m, got -1.0" in _error(tmp_path, BASE + collider)
    collider = '[[colliders]]\ntype = "sphere"\ncentre = [0.0, 0.5, 0.0]\n'
    assert "sphere needs 'centre' (m) and 'radius' (m)" in _error(tmp_path, BASE + collider)


def test_steps_are_bounded_across_frames_and_substeps(tmp_path):
    message = _error(tmp_path, BASE + "[solver]\nframes = 100000\nsubsteps = 100\n")
    assert "10000000 solver steps; at most 1000000" in message


def test_structure_errors_name_the_field(tmp_path):
    assert "'volume_samples[0]' needs 'time'" in _error(tmp_path, BASE + '[[volume_samples]]\nlabel = "rest"\n')
    (tmp_path / "notes.txt").write_text("not a mesh")
    text = f'[scene]\nname = "{tmp_path / "notes.txt"}"\n[cameras]\n'
    assert "is neither an embedded scene" in _error(tmp_path, text)
    assert "does not exist" in _error(tmp_path, f'[scene]\nname = "{tmp_path / "absent.obj"}"\n[cameras]\n')
    drag = "[[drags]]\npoint = [0.0, 0.5, 0.0]\nkeys = [[0.0, [0.0, 0.5]]]\n"
    assert "'drags[0].keys' must be 3 finite numbers" in _error(tmp_path, BASE + drag)
    cameras = '[scene]\nname = "jelly"\n[cameras]\ntype = "spiral"\n'
    assert "'cameras.type' must be 'orbit' or 'fixed', got 'spiral'" in _error(tmp_path, cameras)
    assert "'outputs.modes' must not be empty" in _error(tmp_path, BASE + "[outputs]\nmodes = []\n")


def test_the_warp_error_table_needs_a_nerf_and_a_box(tmp_path):
    table = "[warp_error]\nregion = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]\n"
    assert "compares warped-NeRF renders with the mesh; add a [nerf] table" in _error(tmp_path, BASE + table)
    nerf = BASE + "[nerf]\n"
    assert "'warp_error.region' must be a rest-space box" in _error(tmp_path, nerf + "[warp_error]\nregion = [1.0]\n")
    flipped = "[warp_error]\nregion = [[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]]\n"
    assert "'warp_error.region' must list its low corner first" in _error(tmp_path, nerf + flipped)
    assert _load_text(tmp_path, nerf + table)["warp_error"]["region"][1] == [1.0, 1.0, 1.0]


def test_the_project_scenarios_load_with_their_values_kept(tmp_path):
    for path in SCENARIOS:
        document = tomllib.loads(path.read_text())
        assert load_scenario(path) == document
        load_scenario(path, smoke=True)
    loaded = _load_text(tmp_path, BASE + "[discretization]\nkernel_count = 1\nlloyd_iterations = 0\n")
    assert loaded["discretization"] == {"kernel_count": 1, "lloyd_iterations": 0}


_STRANGE = [0, -1, 1e300, -1e300, math.nan, math.inf, -math.inf, 2**63 - 1, 0.5, True, "", "x", [], [1.0], {}, {"a": 1}]


def _leaves(value, path=()):
    """Every (path, value) inside nested dicts and lists."""
    yield path, value
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _leaves(item, (*path, index))


def _mutate(document: dict, rng: random.Random) -> dict:
    mutated = copy.deepcopy(document)
    for _ in range(rng.randint(1, 3)):
        places = [path for path, _ in _leaves(mutated) if path]
        path = rng.choice(places)
        parent = mutated
        for step in path[:-1]:
            parent = parent[step]
        last = path[-1]
        action = rng.random()
        if action < 0.25 and isinstance(parent, dict):
            del parent[last]
        elif action < 0.35 and isinstance(parent, dict):
            parent[f"{last}_extra"] = rng.choice(_STRANGE)
        elif action < 0.5 and isinstance(parent[last], (int, float)) and not isinstance(parent[last], bool):
            parent[last] = parent[last] * rng.choice([-1, 0, 1e6, 1e300, math.nan, math.inf])
        else:
            parent[last] = rng.choice(_STRANGE)
    return mutated


def test_fuzzed_scenarios_load_or_fail_with_a_scenario_error(tmp_path, monkeypatch):
    """Mutated copies of the project's scenarios: deleted keys, wrong types, NaN, inf, negative and huge numbers,
    unknown keys. Each loads or raises ScenarioError naming the file; nothing else escapes, and a loaded one gives
    its frame count, cameras and colliders."""
    monkeypatch.chdir(tmp_path)
    rng = random.Random(20260)
    documents = [tomllib.loads(path.read_text()) for path in SCENARIOS]
    outcomes = {"loaded": 0, "refused": 0}
    for trial in range(400):
        document = _mutate(rng.choice(documents), rng)
        path = tmp_path / f"fuzz_{trial}.toml"
        path.write_text(_toml(document))
        try:
            loaded = load_scenario(path, smoke=rng.random() < 0.5)
            scenario_module.frame_count(loaded)
            scenario_module.scenario_cameras(loaded, torch.zeros(3, dtype=torch.float64), 0.5)
            scenario_module.scenario_colliders(loaded, 0.5, floor=True)
            outcomes["loaded"] += 1
        except ScenarioError as error:
            assert str(path) in str(error) and "\n" not in str(error), f"trial {trial}: {error}"
            outcomes["refused"] += 1
    assert outcomes["loaded"] > 20 and outcomes["refused"] > 100, outcomes


def test_variant_names_are_file_names_and_distinct(tmp_path):
    base = '[scene]\nname = "jelly"\n[cameras]\n'
    assert "use only letters, digits" in _error(tmp_path, base + '[[variants]]\nname = "../up"\n')
    twice = base + '[[variants]]\nname = "a"\n[[variants]]\nname = "a"\n'
    assert "'variants[1].name' 'a' repeats an earlier variant's" in _error(tmp_path, twice)


@pytest.mark.parametrize("frames", [0, -1, MAX_FRAMES + 1, True, 2.0])
def test_a_frame_count_below_one_or_past_the_bound_is_refused(tmp_path, frames):
    path = tmp_path / "scenario.toml"
    path.write_text('[scene]\nname = "jelly"\n[cameras]\n')
    with pytest.raises(ScenarioError, match=r"--frames must be an integer in \[1, "):
        load_scenario(path, frames=frames)
    assert load_scenario(path, frames=4)["solver"]["frames"] == 4
