"""Sweeps of a scenario: the ``[sweep]`` table's checks, a 4-point smoke sweep of the plant by the local executor and
by Ray (the same results point by point), its resumption, and ``apps.render --sweep``."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest
from PIL import Image

from apps import render
from kernels import backend
from pienerf.executor import ExecutorConfig
from pienerf.scenario import ScenarioError, load_scenario, run_sweep, sweep_points
from tests.agreement import assert_same_results

PLANT = Path(__file__).resolve().parents[2] / "assets" / "scenarios" / "plant_sway.toml"

SWEEP = """
[sweep]
material.young_modulus = [5.0e5, 2.0e6]
solver.rayleigh_alpha = [0.5, 2.0]
"""

TIMINGS = ("build_seconds", "render_seconds", "step_seconds_median")


def _scenario_file(folder: Path, sweep: str = SWEEP) -> Path:
    """The plant scenario with ``sweep`` appended and no video (the frames are what the contact sheet reads)."""
    text = PLANT.read_text().replace("mp4 = true", "mp4 = false")
    path = folder / "plant_sweep.toml"
    path.write_text(text + sweep)
    return path


@pytest.fixture(scope="module")
def kernel_device(request) -> str:
    """The device of this test process (``pytest --device``, default: cuda when present), initialised."""
    return backend.init(request.config.getoption("--device") or backend.default_device())


@pytest.mark.parametrize(
    ("sweep", "message"),
    [
        (
            "material.youngs_modulus = [1.0e5]",
            r"'sweep.material.youngs_modulus': unknown field 'youngs_modulus' of "
            r"\[material\]; valid fields: density, model, poisson_ratio, young_modulus",
        ),
        ("materials.young_modulus = [1.0e5]", r"'materials' is not a table of the scenario; valid tables: .*material"),
        ("material.young_modulus = []", r"'sweep.material.young_modulus' is an empty array; give it at least one"),
        ("material.young_modulus = 1.0e5", r"must be an array of the values to sweep, e\.g\. \[100000\.0, \.\.\.\]"),
        (
            'material.young_modulus = ["stiff", 1.0e5]',
            r"sweep point p000 \(material.young_modulus = 'stiff'\): "
            r"'material.young_modulus' must be .*got 'stiff'; fix that value in the \[sweep\] table",
        ),
        ("solver.frames = [2, 2.5]", r"sweep point p001 \(solver.frames = 2.5\): 'solver.frames' must be"),
        ('mode = "random"\nsolver.dt = [0.01]', r"'sweep.mode' must be one of: 'grid' .*; 'list' .*; got 'random'"),
        (
            'mode = "list"\nsolver.dt = [0.01, 0.02]\nsolver.rayleigh_alpha = [1.0]',
            r"every array needs the same length; got solver.dt: 2, solver.rayleigh_alpha: 1",
        ),
        ('mode = "grid"', r"\[sweep\] names no field to sweep; add one such as material.young_modulus"),
        ("drags.point = [[0.0, 0.5, 0.0]]", r"\[\[drags\]\] is an array of tables, whose entries a sweep cannot"),
        ("smoke.frames = [2]", r"--smoke applies \[smoke\] before the sweep; sweep the field it sets instead"),
    ],
)
def test_a_bad_sweep_table_names_the_problem_and_the_fix(tmp_path, sweep, message):
    path = _scenario_file(tmp_path, f"\n[sweep]\n{sweep}\n")
    with pytest.raises(ScenarioError, match=message):
        load_scenario(path)


def test_grid_and_list_sweeps_make_their_points(tmp_path):
    grid = load_scenario(_scenario_file(tmp_path))
    assert sweep_points(grid) == {
        "p000": {"material.young_modulus": 5.0e5, "solver.rayleigh_alpha": 0.5},
        "p001": {"material.young_modulus": 5.0e5, "solver.rayleigh_alpha": 2.0},
        "p002": {"material.young_modulus": 2.0e6, "solver.rayleigh_alpha": 0.5},
        "p003": {"material.young_modulus": 2.0e6, "solver.rayleigh_alpha": 2.0},
    }
    quoted = (
        '\n[sweep]\nmode = "list"\n"material.young_modulus" = [5.0e5, 2.0e6]\n"solver.rayleigh_alpha" = [0.5, 2.0]\n'
    )
    listed = load_scenario(_scenario_file(tmp_path, quoted))
    assert list(sweep_points(listed).values()) == [
        {"material.young_modulus": 5.0e5, "solver.rayleigh_alpha": 0.5},
        {"material.young_modulus": 2.0e6, "solver.rayleigh_alpha": 2.0},
    ]


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory, kernel_device):
    """``(scenario, out, entries)``: the 4-point smoke sweep by the local executor."""
    folder = tmp_path_factory.mktemp("sweep")
    scenario = load_scenario(_scenario_file(folder), smoke=True)
    out = folder / "local"
    return scenario, out, run_sweep(scenario, out, ExecutorConfig("local", kernel_device), log=lambda line: None)


def test_the_local_sweep_writes_every_point_an_index_and_a_contact_sheet(local_sweep):
    scenario, out, entries = local_sweep
    assert [e["status"] for e in entries] == ["complete"] * 4
    for entry in entries:
        metrics = json.loads((out / entry["name"] / "metrics.json").read_text())
        assert metrics["frames"] == entry["metrics"]["frames"] == 3  # the smoke run's 2 frames after the first
        assert sorted(p.name for p in (out / entry["name"] / "frames").iterdir()) == [
            f"frame_{i:04d}.png" for i in range(3)
        ]
        assert entry["metrics"]["expect_passed"] is True
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert [float(r["parameter.material.young_modulus"]) for r in rows] == [5.0e5, 5.0e5, 2.0e6, 2.0e6]
    # each point ran with its own values: the modulus changes how far the plant moved
    moves = [float(r["metric.variants.default.final_max_displacement_m"]) for r in rows]
    assert moves[0] != moves[2]
    sheet = Image.open(out / "contact_sheet.png")
    assert sheet.size[0] == 2 * 240 and sheet.size[1] >= 2 * 96  # 4 tiles of 240 px in a 2 × 2 grid


def test_a_rerun_skips_the_complete_points_and_leaves_them_untouched(local_sweep, kernel_device):
    scenario, out, _ = local_sweep
    before = {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("p*/**/*") if p.is_file()}
    entries = run_sweep(scenario, out, ExecutorConfig("local", kernel_device), log=lambda line: None)
    assert all(e.get("skipped_as_complete") for e in entries)
    assert {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("p*/**/*") if p.is_file()} == before


def test_ray_gives_the_local_executors_results_point_by_point(local_sweep, local_ray, kernel_device):
    scenario, out, local = local_sweep
    entries = run_sweep(scenario, out.parent / "ray", ExecutorConfig("ray", kernel_device), log=lambda line: None)
    assert [e["name"] for e in entries] == [e["name"] for e in local]
    assert [e["status"] for e in entries] == ["complete"] * 4
    for ours, theirs in zip(entries, local, strict=True):
        assert ours["parameters"] == theirs["parameters"]
        # on CUDA, two runs of one solver loop differ by about 1e-10 m in q (docs/benchmarks.md): 10⁴ times that
        # against the smoke run's 1e-2 m displacements is 1e-6
        assert_same_results(ours["metrics"], theirs["metrics"], kernel_device, rel=1e-6, leave_out=TIMINGS)
    index = json.loads((out.parent / "ray" / "sweep.json").read_text())
    assert index["executor"] == "ray" and index["counts"]["complete"] == 4


def test_render_app_sweeps_and_refuses_a_scenario_without_a_sweep(tmp_path, capsys, kernel_device):
    path = _scenario_file(tmp_path, '\n[sweep]\nmode = "list"\nsolver.rayleigh_alpha = [1.0]\n')
    out = tmp_path / "out"
    assert render.main([str(path), "--smoke", "--sweep", "--out", str(out), "--device", kernel_device]) == 0
    assert json.loads((out / "sweep.json").read_text())["counts"]["complete"] == 1
    assert (out / "p000" / "metrics.json").is_file() and (out / "contact_sheet.png").is_file()
    assert render.main([str(PLANT), "--smoke", "--sweep", "--out", str(tmp_path / "x"), "--device", kernel_device]) == 2
    assert "has no [sweep] table" in capsys.readouterr().err
    assert render.main([str(PLANT), "--smoke", "--executor", "ray", "--out", str(tmp_path / "x")]) == 2
    assert "add --sweep" in capsys.readouterr().err


def test_render_app_without_ray_says_how_to_install_it(tmp_path, capsys, monkeypatch, kernel_device):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails as where it is not installed
    path = _scenario_file(tmp_path)
    out = str(tmp_path / "out")
    argv = [str(path), "--smoke", "--sweep", "--executor", "ray", "--out", out, "--device", kernel_device]
    assert render.main(argv) == 2
    assert "--executor ray needs Ray, which is not installed: pip install -e '.[cluster]'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # refused before any work
