"""``apps.avatar simulate`` refuses a garment that is not on the body and counts the steps whose line search stalled."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import trimesh

from physavatar.body import Body
from physavatar.garment import procedural_skirt

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def skirt():
    return procedural_skirt(Body.mannequin(spacing=0.03), rings=4, segments=12)


def _write(skirt, path: Path, vertices: torch.Tensor) -> Path:
    trimesh.Trimesh(vertices.numpy(), skirt.faces.numpy(), process=False).export(path)
    return path


def _simulate(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "apps.avatar", "simulate", *args], cwd=ROOT, capture_output=True, text=True, check=False
    )


def test_a_garment_five_metres_away_exits_2_naming_the_problem(skirt, tmp_path):
    path = _write(skirt, tmp_path / "far.obj", skirt.vertices + torch.tensor([5.0, 0.0, 0.0], dtype=torch.float64))
    result = _simulate("--garment", str(path), "--frames", "1", "--out", str(tmp_path / "out"), "--device", "cpu")
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "far: the garment is not on the body" in lines[0], result.stderr
    assert "does not overlap the body's" in lines[0] and "--garment-scale" in lines[0]
    assert "step 1/" not in result.stderr and not (tmp_path / "out").exists()


def test_a_bad_garment_scale_is_refused_before_the_work(skirt, tmp_path):
    path = _write(skirt, tmp_path / "skirt.obj", skirt.vertices)
    result = _simulate("--garment", str(path), "--garment-scale", "-3", "--out", str(tmp_path), "--device", "cpu")
    assert result.returncode == 2
    assert "--garment-scale must be 'auto' or a positive number (1 for a file in metres), got '-3'" in result.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["skirt.obj"]


def test_a_worn_garment_reports_its_stalled_steps(skirt, tmp_path):
    path = _write(skirt, tmp_path / "skirt.obj", skirt.vertices)
    out = tmp_path / "out"
    result = _simulate("--garment", str(path), "--smoke", "--out", str(out), "--device", "cpu")
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "stats.json").read_text())["summary"]
    stalled = summary["line_search_stalled_steps"]
    steps = json.loads((out / "stats.json").read_text())["steps"]
    assert stalled == sum(s["line_search_stalled"] for s in steps)
    assert summary["unconverged_steps"] == sum(not s["converged"] for s in steps)
    assert f"{stalled} of {len(steps)} steps ended with a stalled line search" in result.stdout
