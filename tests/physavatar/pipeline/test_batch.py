"""Batches of avatars: a 2-capture smoke batch by the local executor and by Ray (the same results point by point),
the study's points, and the batch's bad input."""

from __future__ import annotations

import csv
import json
import shutil

import pytest

from apps import avatar
from kernels import backend
from physavatar.pipeline import capture_points, parse_fabric, study_points
from tests.agreement import assert_same_results
from tests.physavatar.handmade_capture import build_handmade_capture

STAGES = ("prepare", "track")
TIMINGS = ("seconds", "started", "pid", "host", "skipped_as_complete")


@pytest.fixture(scope="module")
def kernel_device(request) -> str:
    """The device of this test process (``pytest --device``, default: cuda when present), initialised."""
    return backend.init(request.config.getoption("--device") or backend.default_device())


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two capture folders: the hand-made capture and a copy under another name."""
    first = tmp_path_factory.mktemp("batch") / "studio_a"
    build_handmade_capture(first)
    second = first.parent / "studio_b"
    shutil.copytree(first, second)
    return [first, second]


def _batch(captures, out, device, *extra) -> int:
    argv = ["batch", "--captures", *map(str, captures), "--stages", *STAGES, "--smoke", "--frames", "3"]
    return avatar.main([*argv, "--device", device, "--out", str(out), *extra])


@pytest.fixture(scope="module")
def local_batch(captures, tmp_path_factory, kernel_device):
    """``(out, index)`` of the 2-capture batch by the local executor."""
    out = tmp_path_factory.mktemp("local")
    assert _batch(captures, out, kernel_device) == 0
    return out, json.loads((out / "batch.json").read_text())


def test_the_local_batch_runs_the_stages_of_each_capture(local_batch):
    out, index = local_batch
    assert [p["name"] for p in index["points"]] == ["studio_a", "studio_b"]
    assert index["counts"] == {"complete": 2, "failed": 0, "skipped": 0}
    for point in index["points"]:
        assert point["parameters"]["stages"] == list(STAGES)
        for name in ("prepare/prepare.json", "track/tracked.npz", "track/tracking.json"):
            assert (out / point["name"] / name).is_file()
        assert (
            point["metrics"]["track"]["frames"]
            == json.loads((out / point["name"] / "track/tracking.json").read_text())["frames"]
        )
        assert point["metrics"]["prepare"]["garment_vertices"] > 0
    # the two folders hold the same capture: the same results
    assert index["points"][0]["metrics"] == index["points"][1]["metrics"]
    rows = list(csv.DictReader(open(out / "batch.csv")))
    assert [r["status"] for r in rows] == ["complete", "complete"] and "metric.track.mean_render_loss" in rows[0]
    assert (out / "batch_summary.png").stat().st_size > 0


def test_ray_gives_the_local_batchs_results_point_by_point(local_batch, captures, local_ray, tmp_path, kernel_device):
    out, index = local_batch
    assert _batch(captures, tmp_path, kernel_device, "--executor", "ray") == 0
    ours = json.loads((tmp_path / "batch.json").read_text())
    assert ours["executor"] == "ray"
    for a, b in zip(ours["points"], index["points"], strict=True):
        # on CUDA the tracker's float32 atomics sum in a run-dependent order: a relative difference of float32's 1e-7
        # per sum, 1e-5 after the few frames' hundreds of optimisation steps
        assert_same_results(a, b, kernel_device, rel=1e-5, leave_out=TIMINGS)


def test_study_points_cover_every_combination():
    points = study_points(["skirt", "short_skirt"], ["walk"], ["1:1", "4:0.5"], ("capture", "track", "estimate"))
    assert list(points) == ["skirt-walk-1x1", "skirt-walk-4x0_5", "short_skirt-walk-1x1", "short_skirt-walk-4x0_5"]
    assert points["short_skirt-walk-4x0_5"] == {
        "garment": "short_skirt",
        "motion": "walk",
        "kappa_s": 4.0,
        "kappa_b": 0.5,
        "stages": ["capture", "track", "estimate"],
    }


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: parse_fabric("stiff"), r"a fabric is KAPPA_S:KAPPA_B, .* got 'stiff'"),
        (lambda: parse_fabric("20:1"), r"got '20:1': κ_s = 20 lies outside 0.1–8"),
        (lambda: study_points(["cape"], ["walk"], ["1:1"]), r"unknown garment 'cape'; valid: skirt, short_skirt"),
        (lambda: study_points(["skirt"], ["moonwalk"], ["1:1"]), r"unknown motion 'moonwalk'; valid: walk"),
        (lambda: study_points(["skirt"], [], ["1:1"]), r"at least one value of --motions"),
        (lambda: study_points(["skirt"], ["walk"], ["1:1"], ("track", "capture")), r"in the pipeline's order"),
        (lambda: capture_points(["/nonexistent/capture"]), r"capture /nonexistent/capture is not a folder"),
        (lambda: capture_points([], ("prepare",)), r"needs at least one capture folder"),
    ],
)
def test_bad_batch_input_is_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_the_batch_command_refuses_a_batch_of_nothing(tmp_path, capsys):
    assert avatar.main(["batch", "--out", str(tmp_path)]) == 2
    assert "needs --captures DIR [DIR ...] and/or --garments" in capsys.readouterr().err
