import json
import math
import subprocess
import sys

import pytest

from apps import bench
from apps.workloads.nerf import SMOKE_CHECKPOINTS_S, measure_startup, parse_startup_report
from physavatar.garment import SHARED_GARMENTS


def test_copy_workloads_write_complete_records(device, tmp_path):
    path = tmp_path / "bench.json"
    records = bench.main(
        ["--workload", "copy_taichi,copy_warp,copy_torch", "--device", device, "--size", "smoke",
         "--reps", "2", "--json", str(path)]
    )
    assert json.loads(path.read_text()) == records
    assert [r["workload"] for r in records] == ["copy_taichi", "copy_warp", "copy_torch"]
    for r in records:
        assert r["device"] == device and r["size"] == "smoke" and r["reps"] == 2
        assert 0 < r["min_s"] <= r["median_s"] <= r["max_s"]
        assert r["throughput"] > 0 and r["unit"] == "GB/s"
        assert r["reference_median_s"] > 0
        assert r["speedup_vs_reference"] == pytest.approx(r["reference_median_s"] / r["median_s"])
        assert r["params"]["elements"] == 1 << 20


def test_the_hash_grid_workloads_measure_both_table_dtypes_in_one_run(device):
    names = ["hashgrid_fwd", "hashgrid_fwd_half", "hashgrid_bwd", "hashgrid_bwd_half"]
    records = bench.main(["--workload", ",".join(names), "--device", device, "--size", "smoke", "--reps", "1"])
    assert [r["workload"] for r in records] == names
    assert [r["params"]["table_dtype"] for r in records] == ["float32", "float16"] * 2
    assert all(r["median_s"] > 0 and r["reference_median_s"] > 0 for r in records)


@pytest.mark.slow
def test_the_sheet_workload_runs_with_its_reference(device):
    """The sheet at smoke size with its reference (the solver on the autograd element energies): its steps see
    contacts of one kind only, which the references must take."""
    (record,) = bench.main(["--workload", "cloth_step_large", "--device", device, "--size", "smoke", "--reps", "1"])
    assert record["workload"] == "cloth_step_large" and record["unit"] == "frames/s"
    assert record["median_s"] > 0 and record["reference_median_s"] > 0


@pytest.mark.data
@pytest.mark.slow
def test_the_skirt_workload_runs_or_says_why_not(device, capsys):
    """The skirt at smoke size, measured after every frame by the garment simulator's own distance kernels; without
    the shared data folder the workload is skipped with its reason."""
    records = bench.main(["--workload", "cloth_step", "--device", device, "--size", "smoke", "--reps", "2"])
    if SHARED_GARMENTS.is_dir():
        (skirt,) = records
        assert skirt["workload"] == "cloth_step" and skirt["median_s"] > 0 and skirt["unit"] == "frames/s"
        assert skirt["realtime_factor"] == pytest.approx(0.04 / skirt["median_s"])
        assert 0 < skirt["min_distance_body"] < 0.01 and 0 < skirt["min_distance_self"] < 0.01
        assert skirt["vertices_inside_body"] == 0
        assert skirt["steps_converged"] == skirt["steps"] >= 3 and skirt["newton_iterations_total"] >= skirt["steps"]
    else:
        assert records == []
        skipped = [line for line in capsys.readouterr().err.splitlines() if "cloth_step skipped:" in line]
        assert len(skipped) == 1 and "skirt1252.obj" in skipped[0]
        pytest.skip(skipped[0])


def test_list_names_every_workload(capsys):
    bench.main(["--list"])
    out = capsys.readouterr().out
    for name in ("copy_taichi", "copy_warp", "copy_torch"):
        assert name in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--workload", "nope"], "unknown workload 'nope'; valid: "),
        (["--device", "tpu"], "unknown device 'tpu'; valid devices: cpu, cuda"),
        (["--size", "huge"], "unknown size 'huge'; valid: smoke, paper, large"),
        (["--reps", "0"], "--reps must be between 1 and 10000, got 0"),
        (["--reps", "1000000000"], "--reps must be between 1 and 10000, got 1000000000"),
    ],
)
def test_bad_input_is_one_clear_line(args, message, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(args)
    assert stop.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("bench:")]
    assert len(lines) == 1 and message in lines[0], lines
    assert "copy_taichi" in lines[0] or "workload" not in message


def test_bad_input_from_the_command_line_exits_2_with_one_line():
    """The same refusal through ``python -m apps.bench``: the exit status and the one line a shell sees."""
    result = subprocess.run(
        [sys.executable, "-m", "apps.bench", "--reps", "0"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 2
    # Only the program's own line counts; libraries may warn on import on some machines.
    lines = [line for line in result.stderr.splitlines() if line.startswith("bench:")]
    assert len(lines) == 1 and "--reps must be between 1 and 10000, got 0" in lines[0], result.stderr


def test_an_unwritable_json_path_is_refused_before_any_work(tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("a file")
    for path, message in [
        (tmp_path, f"--json {tmp_path} is a folder; pass a file path"),
        (taken / "bench.json", f"--json {taken / 'bench.json'} lies under {taken}, a file, not a folder"),
    ]:
        with pytest.raises(SystemExit) as stop:
            bench.main(["--workload", "copy_torch", "--device", "cpu", "--json", str(path)])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert message in err and "copy_torch on" not in err, err
    assert taken.read_text() == "a file"


def test_an_images_folder_that_is_a_file_is_refused_before_any_work(tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("a file")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--workload", "nerf_train", "--device", "cpu", "--images", str(taken)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"--images {taken} is a file, not a folder" in err and "nerf_train on" not in err, err


def test_viewer_and_qgmls_step_workloads_report_their_parts(device):
    """The viewer's frame gives its step and its render apart; the Q-GMLS step runs beside its torch reference."""
    records = bench.main(
        ["--workload", "viewer_frame,qgmls_step", "--device", device, "--size", "smoke", "--reps", "2"]
    )
    by_name = {r["workload"]: r for r in records}
    viewer, step = by_name["viewer_frame"], by_name["qgmls_step"]
    assert viewer["params"]["size"] == "160x120" and viewer["unit"] == "frames/s"
    assert viewer["step_median_s"] > 0 and viewer["render_median_s"] > 0
    assert step["reference_median_s"] > 0
    assert (step["time_device_loop_s"] if step["device_loop"] else step["time_assembly_s"]) > 0


def test_the_avatar_viewer_frame_drags_the_skirt_and_reports_its_parts(device):
    """One garment step and one mesh update while dragging, at the smoke size (a 60-vertex skirt): the parts of the
    frame apart, the session's breakdown, and nothing inside the body."""
    (record,) = bench.main(["--workload", "viewer_frame_avatar", "--device", device, "--size", "smoke", "--reps", "2"])
    assert record["params"]["dragging"] and record["params"]["garment_vertices"] == 60
    assert record["step_median_s"] > 0 and record["update_median_s"] > 0 and record["bytes_sent"] > 0
    parts = record["breakdown_s"]
    assert set(parts) == {"candidate search", "Newton iterations", "linear solves", "contact view"}
    # a frame's own parts (medians over the frames run), each a duration; every step searches for candidates once
    assert all(math.isfinite(seconds) and seconds >= 0 for seconds in parts.values()) and parts["candidate search"] > 0
    assert record["vertices_inside_body"] == 0 and record["realtime_factor"] > 0


def test_the_avatar_inside_workload_finds_what_the_tree_finds(device):
    """The direct solid-angle sum and the BVH's fast winding number find the same garment vertices inside the body
    (none: the garment stands one barrier-guarded step away from it), both timed."""
    (record,) = bench.main(["--workload", "avatar_inside", "--device", device, "--size", "smoke", "--reps", "2"])
    assert record["params"]["garment_vertices"] == 60 and record["params"]["body_faces"] > 1000
    assert record["agree"] and record["inside"] == 0
    assert record["median_s"] > 0 and record["reference_median_s"] > 0 and record["unit"] == "Mpoints/s"


def test_qgmls_assemble_workloads_say_how_they_ran(device):
    """The assembly runs as the solver's device loop runs it, captured on CUDA only, with the solver's default block
    products (float32 on CUDA, float64 on the CPU) beside float64 ones, each beside the same reference."""
    records = bench.main(
        ["--workload", "qgmls_assemble,qgmls_assemble_f64", "--device", device, "--size", "smoke", "--reps", "2"]
    )
    default = "float32" if device == "cuda" else "float64"
    assert [(r["params"]["captured"], r["params"]["product_dtype"]) for r in records] == [
        (device == "cuda", default), (device == "cuda", "float64")
    ]
    for r in records:
        assert r["median_s"] > 0 and r["reference_median_s"] > 0 and r["unit"] == "assemblies/s"


def test_nerf_train_records_a_curve_and_writes_error_images(device, tmp_path):
    """The smoke size's short curve: checkpoints in time and step order with finite scores, and one error image per
    scored view plus a contact sheet, named in the record."""
    (record,) = bench.main(
        ["--workload", "nerf_train", "--device", device, "--size", "smoke", "--reps", "1", "--images", str(tmp_path)]
    )
    curve = record["curve"]
    assert 1 <= len(curve) <= len(SMOKE_CHECKPOINTS_S)
    assert all(a["seconds"] < b["seconds"] and a["steps"] < b["steps"] for a, b in zip(curve, curve[1:], strict=False))
    assert curve[0]["seconds"] >= SMOKE_CHECKPOINTS_S[0] and curve[0]["steps"] >= 1
    assert all(math.isfinite(p["psnr"]) and -1.0 <= p["ssim"] <= 1.0 for p in curve)
    assert record["psnr_at_2s"] == curve[-1]["psnr"] and record["train_steps"] == curve[-1]["steps"]
    assert record["seconds_to_psnr30"] is None or record["seconds_to_psnr30"] > 0
    assert len(record["view_psnr"]) == record["scored_views"] == 2
    images = record["error_images"]
    assert set(images["views"]) == set(record["view_psnr"])
    for path in [*images["views"].values(), images["sheet"]]:
        assert path.startswith(str(tmp_path)) and path.endswith(".png")
        with open(path, "rb") as file:
            assert file.read(8) == b"\x89PNG\r\n\x1a\n"


def test_startup_report_is_the_last_json_line():
    line = '{"first_step_s": 2.5, "breakdown": {"imports": 1.2}}'
    assert parse_startup_report(f"[Taichi] Starting on arch=x64\n{line}\n")["breakdown"] == {"imports": 1.2}
    with pytest.raises(ValueError, match="printed no report line"):
        parse_startup_report('[Taichi] Starting\n{"other": 1}\n')


@pytest.mark.slow  # a fresh Python process that imports torch and trains
def test_startup_probe_trains_one_step_in_a_fresh_process(shared_data):
    """The probe's child process at smoke size on a few downscaled lego views: the phases add up to the total."""
    report = measure_startup("cpu", "smoke", shared_data / "nerf_synthetic_lego", downscale=8, max_views=9)
    phases = report["breakdown"]
    assert set(phases) == {"interpreter", "imports", "backend_init", "data", "field", "trainer", "first_step"}
    assert all(seconds >= 0.0 for seconds in phases.values()) and phases["imports"] > 0.0
    assert sum(phases.values()) == pytest.approx(report["first_step_s"], abs=0.05)
    assert report["views"] == 7 and report["image_size"] == [100, 100]
