"""PhysAvatar end to end at smoke size through the command line: every stage's files and the report."""

import json

import imageio.v2 as imageio
import numpy as np
import pytest

from tests.physavatar.pipeline.commands import run_avatar as _run


def test_pipeline_writes_every_stage_and_the_table(experiment):
    out, log = experiment
    for stage in ("capture", "track", "estimate", "appearance", "animate", "evaluate"):
        assert f"[{stage}] done in" in log
    # the capture's progress counts its 6 frames from 1 to 6
    assert [line for line in log.splitlines() if line.startswith("[capture] frame")][-1] == "[capture] frame 6/6"
    frames = json.loads((out / "capture" / "transforms.json").read_text())["frames"]
    assert len(frames) == 6 * 4  # frames × cameras
    tracking = json.loads((out / "track" / "tracking.json").read_text())
    assert tracking["frames"] == 6 and len(tracking["vertex_error_m"]) == 6
    assert tracking["mean_vertex_error_m"] < 0.02  # a few mm on 64-pixel views of a 0.4 m skirt
    estimate = json.loads((out / "estimate" / "estimate.json").read_text())
    assert set(estimate["methods"]) == {"analytic_levenberg_marquardt", "finite_differences_adam"}
    for method in estimate["methods"].values():
        assert method["loss_history"][-1] <= method["loss_history"][0]
    look = json.loads((out / "appearance" / "appearance.json").read_text())
    assert look["albedo_error"] < look["baked_albedo_error"]  # the baked shadows are (partly) removed
    report = json.loads((out / "evaluate" / "report.json").read_text())
    assert set(report["methods"]) == {"lbs", "without_physics", "without_appearance", "full"}
    for entry in report["methods"].values():
        assert np.isfinite(entry["chamfer"]) and 0.0 <= entry["fscore"] <= 1.0 and entry["psnr"] > 10.0
    # The recovered texture renders closer to the truth than the baked one, on the same geometry.
    assert report["methods"]["full"]["psnr"] > report["methods"]["without_appearance"]["psnr"]
    chamfer = {name: entry["chamfer"] for name, entry in report["methods"].items()}
    assert chamfer["full"] < chamfer["without_physics"] < chamfer["lbs"], chamfer  # the order of Table 2
    markdown = (out / "evaluate" / "report.md").read_text()
    assert "| PhysAvatar (full) |" in markdown and "κ_s/ρ" in markdown
    # smoke-size numbers are labelled as meaningless, in both reports
    assert report["smoke_size"] is True and "mean nothing" in report["note"]
    assert "Smoke size" in markdown and "mean nothing" in markdown
    for image in (
        "evaluate/chamfer.png",
        "evaluate/metrics.png",
        "evaluate/comparison.png",
        "appearance/relit.png",
        "estimate/estimate.png",
    ):
        assert imageio.imread(out / image).std() > 5.0, image


def test_stage_out_of_order_names_the_missing_stage(tmp_path):
    result = _run("animate", "--smoke", "--out", str(tmp_path), "--device", "cpu")
    assert result.returncode == 2
    assert "estimate" in result.stderr and "Traceback" not in result.stderr


def test_mismatched_frame_counts_are_refused(experiment, tmp_path):
    out, _ = experiment
    broken = tmp_path / "broken"
    (broken / "track").mkdir(parents=True)
    (broken / "capture").symlink_to(out / "capture")
    with np.load(out / "track" / "tracked.npz") as data:
        np.savez(broken / "track" / "tracked.npz", vertices=data["vertices"][:3], colors=data["colors"][:3])
    result = _run("estimate", "--smoke", "--out", str(broken), "--device", "cpu")
    assert result.returncode == 2
    assert "3 frames" in result.stderr and "has 6" in result.stderr


@pytest.mark.parametrize(
    ("flag", "value", "name"),
    [
        ("--iso-tolerance", "1.5", "iso_tolerance"),
        ("--face-subdivisions", "5", "face_subdivisions"),
        ("--lambda-normal", "-1", "lambda_normal"),
    ],
)
def test_tracking_options_out_of_range_are_refused(tmp_path, flag, value, name):
    result = _run("track", "--smoke", "--out", str(tmp_path), "--device", "cpu", flag, value)
    assert result.returncode == 2
    assert name in result.stderr and "Traceback" not in result.stderr


def test_estimate_by_regions_writes_each_regions_stiffness(experiment, tmp_path):
    out, _ = experiment
    for stage in ("capture", "track"):
        (tmp_path / stage).symlink_to(out / stage)
    result = _run("estimate", "--smoke", "--out", str(tmp_path), "--device", "cpu", "--stiffness", "regions",
                  "--regions", "2")  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    regions = json.loads((tmp_path / "estimate" / "estimate.json").read_text())["regions"]
    assert len(regions["kappa_s"]) == len(regions["kappa_b"]) == 2 and sum(regions["faces_per_region"]) > 0
    assert regions["loss"][-1] <= regions["loss"][0]
    assert "regions" in result.stderr


def test_estimate_from_the_images_reads_no_tracked_mesh(experiment, tmp_path):
    out, _ = experiment
    (tmp_path / "capture").symlink_to(out / "capture")  # no track folder: the image fit must not need one
    result = _run("estimate", "--smoke", "--out", str(tmp_path), "--device", "cpu", "--fit", "images")
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((tmp_path / "estimate" / "estimate.json").read_text())
    assert report["reference"] == "images" and report["recovered_by"] == "images_lbfgs_adjoint"
    fit = report["methods"]["images_lbfgs_adjoint"]
    assert set(fit["ratio_errors"]) == {"kappa_s_over_rho", "kappa_b_over_rho"}
    # the fit ends at the lowest loss it evaluated (at smoke size its last line search overshoots out of range)
    assert fit["loss"][-1] == min(fit["loss"]) < fit["loss"][0] and fit["history"][-1] == report["recovered"]
    assert report["recovered"] == fit["final"] and (tmp_path / "estimate" / "estimate.png").stat().st_size > 0
    assert "from the images: 4 views, 6 frames" in result.stderr
    refused = _run("estimate", "--smoke", "--out", str(tmp_path), "--device", "cpu", "--fit", "images", "--exact")
    assert refused.returncode != 0 and "drop --exact or --fit images" in refused.stderr
