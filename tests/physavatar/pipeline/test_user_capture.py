"""PhysAvatar on a capture a user made by hand (files on disk, defects included), through the command line."""

import json
import math

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from physavatar.pipeline import CAPTURE_OUTPUTS, CAPTURE_STAGES
from tests.physavatar.handmade_capture import build_handmade_capture
from tests.physavatar.pipeline.commands import run_avatar


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    """``(capture, built, out, stderr)``: the hand-made capture and ``pipeline --capture --smoke`` run on it."""
    capture = tmp_path_factory.mktemp("handmade")
    built = build_handmade_capture(capture)
    out = tmp_path_factory.mktemp("own")
    result = run_avatar("pipeline", "--capture", str(capture), "--smoke", "--out", str(out), "--device", "cpu")
    assert result.returncode == 0, result.stderr[-3000:]
    return capture, built, out, result.stderr


def test_every_stage_runs_without_truth_and_writes_its_files(own):
    capture, _, out, log = own
    assert not (capture / "truth.npz").exists() and not (capture / "inputs.npz").exists()
    for stage in CAPTURE_STAGES:
        assert f"[{stage}] done in" in log
        for name in CAPTURE_OUTPUTS[stage]:
            assert (out / name).exists(), name
    tracking = json.loads((out / "track" / "tracking.json").read_text())
    assert tracking["vertex_error_m"] is None and all(np.isfinite(tracking["render_loss"]))
    estimate = json.loads((out / "estimate" / "estimate.json").read_text())
    assert estimate["truth"] is None and estimate["recovered"]["kappa_s"] > 0.0
    look = json.loads((out / "appearance" / "appearance.json").read_text())
    assert look["albedo_error"] is None and look["pixels"] > 0
    report = json.loads((out / "evaluate" / "report.json").read_text())
    assert report["held_out"] and report["cameras"] == [2]
    assert set(report["methods"]) == {"attached", "without_physics", "full"}
    # At smoke size (64 px, a few iterations) the scores measure nothing but that each method renders where the
    # garment is: the held-out view's colours of faces no fit view saw are a guess; full size: docs/benchmarks.md.
    for entry in report["methods"].values():
        assert math.isfinite(entry["psnr"]) and entry["psnr"] > 0.0 and -1.0 <= entry["ssim"] <= 1.0
        assert 0.9 < entry["mask_iou"] <= 1.0
    assert "| PhysAvatar (full) |" in (out / "evaluate" / "report.md").read_text()
    assert imageio.imread(out / "evaluate" / "comparison.png").std() > 5.0


def test_the_template_inside_the_body_is_resolved_and_stays_out(own):
    _, built, out, _ = own
    record = json.loads((out / "prepare" / "prepare.json").read_text())
    assert record["intersections"]["inside_body"] >= len(built["pushed"])
    assert record["intersections"]["remaining_inside"] == 0
    assert record["boundary"]["chosen"] == "automatic" and record["boundary"]["count"] > 0
    boundary = [int(line) for line in (out / "prepare" / "boundary.txt").read_text().split("\n")[1:] if line]
    assert len(boundary) == record["boundary"]["count"]
    report = json.loads((out / "evaluate" / "report.json").read_text())
    assert report["methods"]["full"]["frames_with_vertices_inside_body"] == []


def test_the_outputs_are_in_the_captures_axes(own):
    capture, built, out, _ = own
    template = _obj_vertices(capture / "garment.obj")
    resolved = _obj_vertices(out / "prepare" / "garment_resolved.obj")
    record = json.loads((out / "prepare" / "prepare.json").read_text())
    moved = np.linalg.norm(resolved - template, axis=1)
    assert moved.max() <= record["intersections"]["max_move_m"] + 1e-8  # 9 significant digits in both files
    followed = record["intersections"]["moved"] + record["intersections"]["relaxed"]  # moved, and their neighbours
    assert (moved < 1e-8).sum() >= template.shape[0] - followed
    frames = sorted((out / "animate").glob("garment_*.obj"))
    assert len(frames) == built["frames"]
    first = _obj_vertices(frames[0])
    np.testing.assert_allclose(first, resolved, rtol=0.0, atol=1e-8)
    with np.load(out / "animate" / "animation.npz") as data:
        full = torch.from_numpy(data["full"])
    assert full.shape[0] == built["frames"]


def _obj_vertices(path):
    lines = path.read_text().splitlines()
    return np.array([[float(c) for c in line.split()[1:4]] for line in lines if line[:2] == "v "])
