"""apps.render: every scenario of assets/scenarios renders at --smoke size and writes its outputs; the NeRF
scenarios (the lego, Fig. 8) fit their NeRF into the test's cache and render it warped."""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from matplotlib.figure import Figure

from apps import render
from pienerf import scenario as scenario_module
from pienerf.paths import SHARED_DATA
from pienerf.scenario import runner, schema

MAX_TINY_FRAMES = 2000  # the interrupted render would take far longer than the test waits
SCENARIOS = sorted((Path(__file__).resolve().parents[2] / "assets" / "scenarios").glob("*.toml"))


def test_the_paper_figures_have_scenarios():
    names = {path.stem for path in SCENARIOS}
    assert {
        "plant_sway",
        "lego",
        "jelly_compression",
        "sculpture_cut",
        "teapot_rod",
        "cloth_sphere",
        "time_breakdown",
    } <= names


def _run(scenario: Path, out: Path, device: str) -> dict:
    cache = out.parent / "cache"
    args = [str(scenario), "--out", str(out), "--smoke", "--device", device, "--cache-dir", str(cache)]
    assert render.main(args) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize(
    "scenario",
    # the lego scenario reads the lego scene where the shared data folder is present, and skips where it is not
    [pytest.param(path, marks=[pytest.mark.data] if path.stem == "lego" else []) for path in SCENARIOS],
    ids=lambda path: path.stem,
)
def test_scenario_renders_at_smoke_size(device, scenario, tmp_path):
    out = tmp_path / scenario.stem
    metrics = _run(scenario, out, device)
    if "skipped" in metrics:
        assert scenario.stem == "lego" and not (SHARED_DATA / "nerf_synthetic_lego").is_dir()
        assert "nerf_synthetic_lego is absent" in metrics["skipped"]
        return
    spec = scenario_module.load_scenario(scenario, smoke=True)
    # the scenario's own [expect] (over its [smoke.expect]) holds at smoke size
    assert spec["expect"] and metrics["expect"]["passed"], metrics["expect"]
    assert {check["key"] for check in metrics["expect"]["checks"]} >= set(spec["expect"])
    frames = spec["solver"]["frames"] + 1
    outputs = {"frames": True, "mp4": True, "depth": False, "shadow": False, **spec.get("outputs", {})}
    assert metrics["frames"] == frames and (out / "time_breakdown.png").is_file()
    variants = max(len(spec.get("variants", [])), 1)
    tiles = sum(len(v.get("modes", outputs.get("modes", ["mesh"]))) for v in spec.get("variants", [{}]))
    if outputs["frames"]:
        from PIL import Image

        with Image.open(out / "frames" / "frame_0000.png") as first:
            views = len(spec["cameras"].get("positions", spec["cameras"].get("azimuths", [0.0])))
            assert first.size == (spec["cameras"]["width"] * tiles * views, spec["cameras"]["height"])
    breakdown = metrics["time_breakdown"]
    assert breakdown["steps"] == (frames - 1) * variants and breakdown["newton_iterations"] > 0
    if outputs["frames"]:
        assert len(list((out / "frames").glob("frame_*.png"))) == frames
    if outputs["mp4"]:
        import imageio.v2 as imageio

        with imageio.get_reader(out / "video.mp4") as reader:
            assert reader.count_frames() == frames
    if outputs["depth"]:
        assert len(list((out / "depth").glob("*.npy"))) >= frames
    if outputs["shadow"]:
        assert len(list((out / "shadow").glob("*.png"))) >= frames
    if "volume_samples" in spec:
        assert (out / "volume_bars.png").is_file()
    for variant in metrics["variants"].values():
        assert 0.5 < variant["final_relative_volume"] < 1.5
    if "nerf" in spec:
        _check_nerf_outputs(scenario.stem, out, metrics, tmp_path / "cache")
    if scenario.stem in ("cloth_sphere", "jelly_compression"):
        _check_figure(scenario.stem, out, spec, metrics)


def _check_figure(name: str, out: Path, spec: dict, metrics: dict) -> None:
    """Fig. 9 shows the ball under the cloth; Fig. 6 shows the plate, a label on each variant's tile and a bar per
    volume sample and variant."""
    import numpy as np
    from PIL import Image

    from tests.pienerf.test_reports import bar_pixels

    rgba = np.asarray(Image.open(out / "frames" / "frame_0002.png")).astype(int)
    r, g, b, a = np.moveaxis(rgba, -1, 0)
    if name == "cloth_sphere":
        ball = (a == 255) & (g > r) & (b > 1.3 * r)  # the ball's blue-grey: the plaid never has g > r
        assert ball.sum() >= 5, "the sphere collider is drawn under the cloth"
    else:
        plate = (a == 255) & (b - r >= 4) & (b > g) & (g >= r)  # the plate's cool grey: not jelly, ground or label
        assert plate.sum() >= 10, "the pressing plate is drawn"
        for tile in np.split(rgba, len(spec["variants"]), axis=1):
            box = tile[-12:, :12]  # the label's white box and the ink of its first letter
            assert (box == 255).all(-1).any() and ((box[..., :3] < 100).all(-1) & (box[..., 3] == 255)).any(), "label"
        for variant in spec["variants"]:
            assert len(metrics["variants"][variant["name"]]["volume"]["labels"]) == len(spec["volume_samples"])
        assert min(bar_pixels(out / "volume_bars.png")) > 500, "a bar per sample and variant"


def test_label_tile_writes_the_text_into_its_corner():
    import torch

    tile = torch.rand(40, 120, 4)
    labelled = runner.label_tile(tile, "ARAP")
    changed = (labelled - tile).abs().amax(-1) > 2 / 255
    assert labelled.shape == tile.shape and changed[-8:, :20].float().mean() > 0.5 and not changed[:20].any()
    assert (labelled[-14:, :30, :3] < 0.1).all(-1).sum() > 10  # the black letters


def test_a_second_label_line_is_drawn_where_the_tile_has_room_for_it():
    import torch

    text = "Q-GMLS: NeRF, quadratic warp\nvs mesh on rod: 24.1 dB, IoU 0.83"
    for height, lines in ((192, 2), (36, 1)):
        tile = torch.zeros(height, 256, 4)
        boxed = (runner.label_tile(tile, text)[..., 3] > 0.5).any(-1).sum()
        one_line = (runner.label_tile(tile, text.split("\n")[0])[..., 3] > 0.5).any(-1).sum()
        assert (boxed > one_line) == (lines == 2), f"{lines} line(s) on a tile {height} px tall"
        assert boxed <= height / 3 or lines == 1


def test_bad_scenarios_fail_with_one_line_naming_the_key(device, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "jelly"\n[material]\nyoungs_modulus = 1e4\n[cameras]\ntype = "orbit"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "material.youngs_modulus" in error and "young_modulus" in error
    bad.write_text('[scene]\nname = "jelly"\n[cameras]\nwidth = "wide"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "'cameras.width' must be an integer" in capsys.readouterr().err
    bad.write_text('[scene]\nname = "jelly"\n')
    assert render.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "missing table [cameras]" in capsys.readouterr().err


def _check_nerf_outputs(name: str, out: Path, metrics: dict, cache: Path) -> None:
    """Fig. 8 tiles the mesh and the NeRF warped quadratically and linearly; the lego is simulated from its NeRF."""
    import numpy as np
    from PIL import Image

    frame = np.asarray(Image.open(out / "frames" / "frame_0002.png")).astype(float) / 255.0
    if name == "teapot_rod":
        assert metrics["nerf"]["warps"] == ["quadratic", "linear"] and metrics["nerf"]["source"] == "scene"
        assert {"render (nerf)", "render (nerf_linear)"} <= set(metrics["time_breakdown"]["seconds"])
        mesh, quadratic, linear, _ = np.split(frame, 4, axis=1)
        for tile in (quadratic, linear):
            assert (tile[..., 3] > 0.5).mean() > 0.2 and (tile[..., 3] < 0.5).mean() > 0.05  # object + ground, sky
        alike = np.abs(quadratic[..., :3] - mesh[..., :3]).sum(-1) < 0.3
        assert alike.mean() > 0.5, "the NeRF render looks like the mesh render of the same state"
        assert list((cache / "scenes").glob("teapot-*/ngp-*.pt")), "the fitted NeRF is cached"
        _check_warp_error(metrics)
    elif name == "lego":
        checkpoint = Path(metrics["nerf"]["checkpoint"])
        assert checkpoint.is_file() and checkpoint.is_relative_to(cache)
        summary = metrics["variants"]["default"]["summary"]
        assert summary["scene"] == str(checkpoint) and summary["particles"] > 50
        width, height, depth = summary["bounding_box_m"]
        assert 0.8 < width < 1.6 and 1.0 < height < 2.0 and 1.5 < depth < 2.6, "the excavator stands upright"
        assert 0.05 < (frame[..., 3] > 0.5).mean() < 0.95


def _check_warp_error(metrics: dict) -> None:
    """Fig. 8's numbers: every frame, each warping of the Q-GMLS variant's NeRF against its mesh on the rod, finite
    and in range; the mesh tiles show a mesh refined past the scene's (the rod's rings: tests/pienerf)."""
    for variant in metrics["variants"].values():
        preview = variant["mesh_preview"]
        assert preview["vertices"] > preview["scene_vertices"] and 0 < preview["max_edge_m"] < 0.3
    assert "warp_error" not in metrics["variants"]["linear"], "the linear GMLS variant renders no NeRF"
    warp_error = metrics["variants"]["quadratic"]["warp_error"]
    assert warp_error["region"]["label"] == "rod" and warp_error["region"]["particles"] > 0
    assert set(warp_error["modes"]) == {"nerf", "nerf_linear"}
    for mode in warp_error["modes"].values():
        assert len(mode["psnr_db"]) == len(mode["silhouette_iou"]) == len(mode["pixels"]) == metrics["frames"]
        for psnr_db, iou, pixels in zip(mode["psnr_db"], mode["silhouette_iou"], mode["pixels"], strict=True):
            assert pixels > 0 and 0.0 < psnr_db < 100.0 and 0.0 <= iou <= 1.0
        assert min(mode["psnr_db"]) <= mode["mean_psnr_db"] <= max(mode["psnr_db"])
    for record in metrics["per_frame"]:
        assert set(record["quadratic_warp_error"]) == {"nerf", "nerf_linear"}


def test_data_scenario_without_its_data_is_skipped_with_the_reason(device, tmp_path, monkeypatch):
    monkeypatch.setattr(schema, "SHARED_DATA", tmp_path / "no-data")
    metrics = _run(SCENARIOS[0].parent / "lego.toml", tmp_path / "lego", device)
    assert metrics["skipped"].startswith(f"data folder {tmp_path / 'no-data' / 'nerf_synthetic_lego'} is absent")
    assert not (tmp_path / "lego" / "frames").exists()


def _tiny_scenario(folder: Path, frames: int = 3, mp4: bool = False) -> Path:
    """A jelly of six kernels at 24 × 18 px with a volume sample at the start: seconds a frame on a CPU."""
    path = folder / "tiny.toml"
    path.write_text(
        'name = "tiny"\n[scene]\nname = "jelly"\n'
        "[discretization]\nkernel_count = 6\nparticle_radius = 0.09\nlloyd_iterations = 0\n"
        f"[solver]\ndt = 0.0333333\nframes = {frames}\n"
        '[[volume_samples]]\ntime = 0.0\nlabel = "rest"\n'
        "[cameras]\nwidth = 24\nheight = 18\n"
        f"[outputs]\nmp4 = {'true' if mp4 else 'false'}\n"
    )
    return path


def _partial_files(out: Path) -> list[Path]:
    return [path for path in out.rglob("*") if ".partial" in path.name]


def test_output_paths_are_refused_before_any_work(tmp_path, capsys):
    scenario = _tiny_scenario(tmp_path)
    taken = tmp_path / "taken"
    taken.write_text("a file")
    assert render.main([str(scenario), "--out", str(taken), "--device", "cpu"]) == 2
    assert f"--out {taken} is a file, not a folder" in capsys.readouterr().err
    assert render.main([str(scenario), "--out", str(taken / "sub"), "--device", "cpu"]) == 2
    assert f"--out's parent {taken} is a file" in capsys.readouterr().err
    assert render.main([str(scenario), "--out", str(tmp_path / "out"), "--cache-dir", str(taken)]) == 2
    assert f"--cache-dir {taken} is a file" in capsys.readouterr().err
    assert taken.read_text() == "a file" and not (tmp_path / "out").exists()


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="permissions do not bind this user")
def test_an_unwritable_out_folder_is_refused_before_any_work(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        assert render.main([str(_tiny_scenario(tmp_path)), "--out", str(locked / "out"), "--device", "cpu"]) == 2
        assert f"cannot write into {locked}" in capsys.readouterr().err
    finally:
        locked.chmod(0o700)


def _disk_full(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_mid_render_keeps_the_finished_frames_in_metrics(device, tmp_path, monkeypatch, capsys):
    save_png = runner.save_png
    calls = []

    def save_until_full(image, path):
        calls.append(path)
        if len(calls) == 3:
            with runner.atomic_path(path) as temporary:
                temporary.write_bytes(b"\x89PNG\r\n")  # the first bytes, then the disk fills
                _disk_full()
        save_png(image, path)

    monkeypatch.setattr(runner, "save_png", save_until_full)
    out = tmp_path / "out"
    assert render.main([str(_tiny_scenario(tmp_path)), "--out", str(out), "--device", device]) == 1
    error = capsys.readouterr().err
    assert "(the disk is full)" in error and f"{out / 'metrics.json'} holds the frames that finished" in error
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 2 and "No space left" in metrics["error"] and len(metrics["per_frame"]) == 2
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["frame_0000.png", "frame_0001.png"]
    assert not (out / "volume_bars.png").exists() and not _partial_files(out)


def test_a_full_disk_while_plotting_leaves_no_truncated_chart(device, tmp_path, monkeypatch, capsys):
    savefig = Figure.savefig

    def fill_the_disk_on_the_bars(figure, path, **options):
        if "volume_bars" not in Path(path).name:
            return savefig(figure, path, **options)
        Path(path).write_bytes(b"\x89PNG\r\n")  # the first bytes, then the disk fills
        _disk_full()

    monkeypatch.setattr(Figure, "savefig", fill_the_disk_on_the_bars)
    out = tmp_path / "out"
    assert render.main([str(_tiny_scenario(tmp_path)), "--out", str(out), "--device", device]) == 1
    assert "(the disk is full)" in capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 4 and "No space left" in metrics["error"]
    assert not (out / "volume_bars.png").exists() and not _partial_files(out)
    assert (out / "time_breakdown.png").is_file() and (out / "time_breakdown.json").is_file()


def test_ctrl_c_mid_render_writes_what_finished_and_exits_130(tmp_path):
    out = tmp_path / "out"
    scenario = _tiny_scenario(tmp_path, frames=MAX_TINY_FRAMES, mp4=True)
    command = [sys.executable, "-m", "apps.render", str(scenario), "--out", str(out), "--device", "cpu"]
    root = Path(__file__).resolve().parents[2]
    process = subprocess.Popen(command, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        second = out / "frames" / "frame_0001.png"
        deadline = time.monotonic() + 300
        while not second.exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # polling for the file, not an assertion on time
        assert second.exists(), f"no second frame: exit status {process.poll()}"
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted:" in stderr and "metrics.json holds the frames" in stderr
    metrics = json.loads((out / "metrics.json").read_text())
    finished = metrics["frames"]
    assert metrics["interrupted"] is True and 2 <= finished < MAX_TINY_FRAMES + 1
    assert len(metrics["per_frame"]) == finished
    assert len(list((out / "frames").glob("frame_*.png"))) in (finished, finished + 1)
    assert not _partial_files(out)
    import imageio.v2 as imageio

    with imageio.get_reader(out / "video.mp4") as reader:
        assert reader.count_frames() == finished


def _stiff_scenario(folder: Path) -> Path:
    """A nearly incompressible jelly a million times stiffer than steel, stepped 1 s at a time under 1000 g: the
    Newton direction is so ill-conditioned that no step along it lowers the energy, in every step. The Hessian's block
    products are float64 on every device: with CUDA's default float32 products the rounded matrix gives another
    direction, along which a step halved eight times happens to lower the energy."""
    path = folder / "stiff.toml"
    path.write_text(
        'name = "stiff"\n[scene]\nname = "jelly"\n'
        '[material]\nmodel = "neo_hookean"\nyoung_modulus = 1.0e12\npoisson_ratio = 0.499\n'
        "[discretization]\nkernel_count = 6\nparticle_radius = 0.09\nlloyd_iterations = 0\n"
        "[solver]\ndt = 1.0\nframes = 2\ngravity = [0.0, -1.0e4, 0.0]\nhessian_precision = \"float64\"\n"
        "[cameras]\nwidth = 24\nheight = 18\n[outputs]\nmp4 = false\n"
    )
    return path


def test_a_line_search_that_never_moves_exits_3_naming_the_variant(device, tmp_path, capsys):
    out = tmp_path / "out"
    assert render.main([str(_stiff_scenario(tmp_path)), "--out", str(out), "--device", device]) == render.SOLVER_FAILED
    captured = capsys.readouterr()
    assert "variant 'default': 2 of 2 steps ended with a failed line search (no decrease: 2)" in captured.out
    errors = [line for line in captured.err.splitlines() if line.startswith("error:")]
    assert (
        len(errors) == 1
        and "variant 'default': the line search could not move the body in any of the 2 steps" in (errors[0])
    )
    assert "lower solver.dt" in errors[0]
    metrics = json.loads((out / "metrics.json").read_text())
    solver = metrics["variants"]["default"]["solver"]
    assert solver["line_search_failures"] == {"no decrease": 2} and solver["stuck_steps"] == 2
    assert metrics["wrong_results"] == {"default": solver["wrong_result"]} and metrics["frames"] == 3
    assert len(list((out / "frames").iterdir())) == 3  # the outputs are kept for inspection


def test_a_sound_render_reports_no_failed_line_search(device, tmp_path, capsys):
    out = tmp_path / "out"
    assert render.main([str(_tiny_scenario(tmp_path, frames=2)), "--out", str(out), "--device", device]) == 0
    assert "variant 'default': 0 of 2 steps ended with a failed line search" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["wrong_results"] == {}
    solver = metrics["variants"]["default"]["solver"]
    assert solver["steps"] == 2 and solver["line_search_failures"] == {} and solver["wrong_result"] is None
    # an offline step iterates to the tolerance, not the interactive viewer's one Newton iteration
    assert solver["unconverged_steps"] == 0
    assert solver["newton_iterations_cap"] == scenario_module.OFFLINE_NEWTON_ITERATIONS
    assert metrics["time_breakdown"]["newton_iterations"] > metrics["time_breakdown"]["steps"]


def test_a_missing_video_encoder_is_refused_before_any_work(device, tmp_path, monkeypatch, capsys):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *args: None if name == "imageio_ffmpeg" else find_spec(name, *args)
    )
    out = tmp_path / "out"
    assert render.main([str(_tiny_scenario(tmp_path, mp4=True)), "--out", str(out), "--device", device]) == 2
    error = capsys.readouterr().err
    assert "pip install imageio-ffmpeg" in error and "mp4 = false" in error
    assert not out.exists()  # refused before any work
    # without a video, the same machine renders the frames
    assert render.main([str(_tiny_scenario(tmp_path, frames=1)), "--out", str(out), "--device", device]) == 0


@pytest.mark.parametrize("name", ["../escaped", "a/b", ".hidden", "", "tab\t"])
def test_a_variant_name_that_is_no_file_name_is_refused(tmp_path, capsys, name):
    scenario = _tiny_scenario(tmp_path)
    scenario.write_text(scenario.read_text() + f'[[variants]]\nname = "{name}"\n')
    out = tmp_path / "out"
    assert render.main([str(scenario), "--out", str(out), "--device", "cpu"]) == 2
    assert "'variants[0].name'" in capsys.readouterr().err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["tiny.toml"]


@pytest.mark.parametrize("frames", ["0", "-3"])
def test_frames_below_one_are_refused(tmp_path, capsys, frames):
    scenario = SCENARIOS[0]
    out = tmp_path / "out"
    assert render.main([str(scenario), "--out", str(out), "--smoke", "--frames", frames, "--device", "cpu"]) == 2
    assert f"--frames must be an integer in [1, {scenario_module.MAX_FRAMES}]" in capsys.readouterr().err
    assert not out.exists()


def test_frames_replace_the_smoke_length(device, tmp_path):
    out = tmp_path / "out"
    args = [str(_tiny_scenario(tmp_path, frames=40)), "--out", str(out), "--frames", "1", "--device", device]
    assert render.main(args) == 0
    assert json.loads((out / "metrics.json").read_text())["frames"] == 2


def test_an_earlier_render_in_the_out_folder_is_cleared_and_said(device, tmp_path, capsys):
    out = tmp_path / "out"
    assert render.main([str(_tiny_scenario(tmp_path, frames=3)), "--out", str(out), "--device", device]) == 0
    (out / "notes.txt").write_text("mine")
    other = tmp_path / "other.toml"
    other.write_text(_tiny_scenario(tmp_path, frames=1).read_text().replace('name = "tiny"', 'name = "other"', 1))
    capsys.readouterr()
    assert render.main([str(other), "--out", str(out), "--device", device]) == 0
    said = capsys.readouterr().out
    assert "files of an earlier render of scenario 'tiny'" in said and "notes.txt" in said
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["frame_0000.png", "frame_0001.png"]
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "metrics.json").read_text())["scenario"] == "other"


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b"", "is empty (0 bytes)"),
        (bytes(range(256)) * 2, "holds no triangles"),
        (b"v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n", "1 of 4 vertices with NaN"),
    ],
    ids=["empty", "garbage", "nan"],
)
def test_a_bad_mesh_scene_is_named_for_what_is_wrong(device, tmp_path, capsys, content, says):
    mesh = tmp_path / "body.obj"
    mesh.write_bytes(content)
    scenario = _tiny_scenario(tmp_path)
    scenario.write_text(scenario.read_text().replace('name = "jelly"', f'name = "{mesh}"'))
    assert render.main([str(scenario), "--out", str(tmp_path / "out"), "--device", device]) == 2
    error = capsys.readouterr().err
    assert says in error and "watertight" not in error


def test_a_failed_expectation_exits_4_naming_it(device, tmp_path, capsys):
    scenario = _tiny_scenario(tmp_path, frames=1)
    scenario.write_text(scenario.read_text() + "[expect]\nmax_displacement_m = [5.0, 6.0]\nconverged_fraction = 1.0\n")
    out = tmp_path / "out"
    assert render.main([str(scenario), "--out", str(out), "--device", device]) == render.EXPECTATION_FAILED
    error = capsys.readouterr().err
    assert "[expect] variant 'default': max_displacement_m = " in error and "expected in [5, 6]" in error
    expect = json.loads((out / "metrics.json").read_text())["expect"]
    assert not expect["passed"] and [c["passed"] for c in expect["checks"]] == [False, True]
