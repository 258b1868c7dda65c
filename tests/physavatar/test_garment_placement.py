"""A garment that is not worn by the body is refused with the measured distance and a fix, never simulated falling.

``apps.avatar simulate`` refuses such a garment before the work (exit status 2) and counts the steps whose line
search stalled in one it simulates.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import trimesh

from physavatar.body import Body
from physavatar.garment import MAX_GAP, load_garment, place_on_body, procedural_skirt

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def body() -> Body:
    return Body.mannequin(spacing=0.03)


@pytest.fixture(scope="module")
def skirt(body):
    return procedural_skirt(body, rings=4, segments=12)


def _moved(skirt, offset):
    return skirt.replace(skirt.vertices + torch.tensor(offset, dtype=torch.float64), f"moved by {offset} m")


def test_a_fitted_skirt_is_kept_as_it_is(skirt, body):
    assert place_on_body(skirt, body) is skirt


def test_a_skirt_a_few_centimetres_off_the_body_is_still_worn(skirt, body):
    placed = place_on_body(_moved(skirt, [0.0, 0.0, 0.04]), body)
    assert float(body.signed_distance(placed.vertices).min()) > 1e-3


def test_a_skirt_five_metres_away_is_refused_naming_both_boxes(skirt, body):
    with pytest.raises(ValueError, match=r"not on the body: its bounding box \[4\.\d\d.* does not overlap the body's"):
        place_on_body(_moved(skirt, [5.0, 0.0, 0.0]), body)


def test_a_skirt_in_front_of_the_body_is_refused(skirt, body):
    with pytest.raises(ValueError, match=r"not on the body.*does not overlap.*move or scale it onto the body"):
        place_on_body(_moved(skirt, [0.0, 0.0, 0.5]), body)


def test_a_skirt_around_the_head_is_refused_with_its_distance(skirt, body):
    lifted = _moved(skirt, [0.0, 1.0, 0.0])  # hem at 1.66 m: the box overlaps the body's (up to 1.75 m)
    with pytest.raises(ValueError, match=r"nearest vertex is \d+ mm from the body surface, farther than 100 mm"):
        place_on_body(lifted, body)
    assert place_on_body(lifted, body, max_gap=1.0) is not None  # the option the message names lets it through


def test_max_gap_must_be_a_finite_distance_above_the_margin(skirt, body):
    assert MAX_GAP == pytest.approx(0.1)
    for bad in (0.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="max_gap must be a finite distance above margin"):
            place_on_body(skirt, body, max_gap=bad)


def test_a_garment_auto_rescaled_off_the_body_is_refused_naming_the_rescale(skirt, body, tmp_path):
    """A 0.2x skirt about the origin (inside the body, 8 cm tall) is read as decametres and scaled x10 about the
    origin, which lifts it above the head: placement must refuse it and say what the loading did."""
    path = tmp_path / "small_skirt.obj"
    trimesh.Trimesh((0.2 * skirt.vertices).numpy(), skirt.faces.numpy(), process=False).export(path)
    garment = load_garment(path)
    assert any("scaled by 10 about the origin" in note for note in garment.notes)
    with pytest.raises(ValueError, match=r"not on the body: .* mm from the body surface.*scaled by 10.*scale=1"):
        place_on_body(garment, body)
    kept = load_garment(path, scale=1)  # the fix the message names keeps the file's coordinates
    assert kept.notes == ()
    torch.testing.assert_close(kept.vertices, 0.2 * skirt.vertices, atol=1e-6, rtol=0)


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
