"""A skirt on the walking mannequin (PhysAvatar §3.2, Eq. 5) and the `apps.avatar simulate` command."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from apps import avatar
from physavatar.body import Body, walk
from physavatar.garment import DEFAULT_GARMENT, load_garment, place_on_body, procedural_skirt, select_boundary
from physavatar.simulate import simulate, write_meshes, write_npz, write_stats_json

pytestmark = pytest.mark.data  # the default garment comes from the shared folder when present

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def body() -> Body:
    return Body.mannequin(spacing=0.03)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "apps.avatar", *args], cwd=ROOT, capture_output=True, text=True, check=False
    )


def test_skirt_on_walking_mannequin_stays_outside_and_follows(device, shared_data, body, tmp_path):
    skirt = place_on_body(load_garment(shared_data / "garments" / "skirt1252.obj"), body)
    boundary = select_boundary(skirt, body, mode="waist")
    motion = walk(body.skeleton)
    frames = 4
    seen = []
    result = simulate(skirt, body, motion, frames=frames, device=device, progress=lambda t, s: seen.append(t))
    assert seen == list(range(1, frames + 1))
    assert result.garment_frames.shape == (frames + 1, skirt.vertices.shape[0], 3)
    assert result.body_frames.shape == (frames + 1, body.vertices.shape[0], 3)
    assert bool(torch.isfinite(result.garment_frames).all())
    for stats in result.stats:
        assert 0.0 < stats.min_distance_body and stats.min_distance_self > 0.0
    # no vertex ends inside the body
    assert float(body.signed_distance(result.garment_frames[-1], result.body_frames[-1]).min()) > 0.0
    # the waistband rides with the body's skinning: exactly on its targets at every frame
    expected = body.skin(motion.rotations[: frames + 1], motion.root_translation[: frames + 1])
    assert torch.equal(result.body_frames, expected)
    torch.testing.assert_close(result.garment_frames[0], skirt.vertices)
    moved = (result.garment_frames[-1] - result.garment_frames[0])[boundary]
    assert float(moved[:, 2].mean()) > 0.0  # walking toward +z drags the waist forward
    # and the free hem falls a little under gravity from its rest shape
    assert float(result.garment_frames[-1][:, 1].min()) < float(skirt.vertices[:, 1].min())

    npz = np.load(write_npz(result, tmp_path / "seq.npz"))
    assert npz["garment_frames"].shape == tuple(result.garment_frames.shape)
    np.testing.assert_array_equal(npz["garment_faces"], skirt.faces.numpy())
    paths = write_meshes(result, tmp_path / "meshes", "ply")
    assert len(paths) == frames + 1 and all(p.stat().st_size > 0 for p in paths)
    record = json.loads(write_stats_json(result, tmp_path / "stats.json").read_text())
    assert [s["step"] for s in record["steps"]] == list(range(1, frames + 1))
    assert record["summary"]["min_distance_body_m"] > 0.0


_CPU_SKIRT = """
import sys, numpy as np
from physavatar.body import Body
from physavatar.garment import load_garment, place_on_body, procedural_skirt, select_boundary
from physavatar.body import walk
from physavatar.simulate import simulate
body = Body.mannequin(spacing=0.03)
skirt = place_on_body(load_garment(sys.argv[1]), body)
result = simulate(skirt, body, walk(body.skeleton), frames=int(sys.argv[2]), device="cpu", progress=False,
                  boundary=select_boundary(skirt, body, mode="waist"))
np.save(sys.argv[3], result.garment_frames.numpy())
"""


def test_cuda_skirt_agrees_with_cpu_over_ten_frames(device, shared_data, body, tmp_path):
    """The first 10 frames of the skirt on CUDA (CG solves) agree with the CPU's (direct solves) within 0.1 mm."""
    if device != "cuda":
        pytest.skip("compares a CUDA run with a CPU run; run the suite with --device cuda on a GPU machine")
    path, frames = shared_data / "garments" / "skirt1252.obj", 10
    cpu_file = tmp_path / "cpu.npy"
    # Taichi holds one architecture per process: the CPU run gets a process of its own.
    run = subprocess.run(
        [sys.executable, "-c", _CPU_SKIRT, str(path), str(frames), str(cpu_file)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    skirt = place_on_body(load_garment(path), body)
    result = simulate(
        skirt,
        body,
        walk(body.skeleton),
        frames=frames,
        device=device,
        progress=False,
        boundary=select_boundary(skirt, body, mode="waist"),
    )
    cpu = torch.from_numpy(np.load(cpu_file))
    gap = float(torch.linalg.norm(result.garment_frames - cpu, dim=2).max())
    assert gap < 1e-4, f"CPU and CUDA differ by {gap * 1e3:.4f} mm"


def test_skirt_walks_100_frames_without_interpenetration(device, body):
    """100 frames of the walk (4 s): every step ends with garment-body and garment-garment gaps above zero."""
    skirt = procedural_skirt(body, rings=8, segments=20)
    motion = walk(body.skeleton, fps=25.0)
    result = simulate(skirt, body, motion, frames=100, device=device, progress=False)
    assert len(result.stats) == 100 and bool(torch.isfinite(result.garment_frames).all())
    assert min(s.min_distance_body for s in result.stats) > 0.0
    assert min(s.min_distance_self for s in result.stats) > 0.0
    # Inside-outside check of the end state, independent of the solver's own distance bookkeeping.
    assert float(body.signed_distance(result.garment_frames[-1], result.body_frames[-1]).min()) > 0.0
    assert float(torch.linalg.norm(result.garment_frames[-1] - result.garment_frames[0], dim=1).max()) > 0.05


def test_simulate_refuses_more_frames_than_the_motion(device, shared_data, body):
    skirt = load_garment(shared_data / "garments" / "skirt1252.obj")
    with pytest.raises(ValueError, match=r"frames \(200\) must lie in 1\.\.100"):
        simulate(skirt, body, walk(body.skeleton), frames=200, device=device, progress=False)


def test_avatar_simulate_smoke_writes_sequence_video_and_stats(device, tmp_path):
    """Runs with or without the shared data folder: without it the default garment is the embedded skirt."""
    out = tmp_path / "smoke"
    result = _run("simulate", "--smoke", "--out", str(out), "--device", device)
    assert result.returncode == 0, result.stderr
    garment = "skirt1252" if DEFAULT_GARMENT.is_file() else "skirt"
    assert f"frames of the garment '{garment}'" in result.stdout
    sequence = np.load(out / "sequence.npz")
    frames = sequence["garment_frames"].shape[0]
    assert frames >= 3 and sequence["body_frames"].shape[0] == frames
    assert sequence["garment_faces"].shape[1] == 3 and float(sequence["fps"]) == 25.0
    stats = json.loads((out / "stats.json").read_text())
    assert len(stats["steps"]) == frames - 1
    assert all(s["min_distance_body"] is not None and s["min_distance_body"] > 0.0 for s in stats["steps"])
    reader = imageio.get_reader(out / "video.mp4")
    video_frames = [image for image in reader]
    assert len(video_frames) == frames
    assert reader.get_meta_data()["fps"] == 25.0
    assert reader.get_meta_data()["duration"] == pytest.approx(frames / 25.0, abs=0.02)
    image = video_frames[0].astype(float)
    red = (image[..., 0] > image[..., 1] + 60) & (image[..., 0] > image[..., 2] + 60)
    assert red.sum() > 20  # the garment is on screen in its own colour
    assert image.std() > 20  # body, ground, shadow and sky differ


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--motion", "dance.txt"], "--motion must be one of walk, turn, raise, jump or a .bvh file"),
        (["--garment", "missing.obj"], "garment file missing.obj does not exist"),
        (["--frames", "0"], "--frames must be at least 1"),
        (["--frames", "1000000000"], "--frames must be at least 1 and at most 10000, got 1000000000"),
        (["--frames", "1", "--video-size", "1", "99999"], "got 1 99999; each at most 8192"),
        (["--frames", "1", "--video-size", "0", "0"], "--video-size must be two positive pixel counts W H, got 0 0"),
    ],
)
def test_bad_input_is_one_clear_line(args, message, tmp_path):
    result = _run("simulate", "--out", str(tmp_path), *args)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not any(tmp_path.iterdir())  # refused before any work


@pytest.mark.parametrize("command", ["simulate", "capture"])
def test_out_that_is_a_file_is_refused_before_the_work(command, tmp_path):
    taken = tmp_path / "results"
    taken.write_text("not a folder")
    result = _run(command, "--smoke", "--out", str(taken), "--device", "cpu")
    assert result.returncode == 2
    assert f"--out {taken} is a file, not a folder" in result.stderr and "Traceback" not in result.stderr
    assert "step 1/" not in result.stderr and "[capture]" not in result.stderr  # nothing simulated
    assert taken.read_text() == "not a folder"


def test_missing_video_encoder_is_named_before_the_simulation(monkeypatch, tmp_path, capsys):
    """Without imageio-ffmpeg the command stops at once, naming the package, instead of simulating first and then
    failing in another imageio plugin."""
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg" else find_spec(name, *a)
    )
    assert avatar.main(["simulate", "--smoke", "--out", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert "pip install imageio-ffmpeg" in error and "error:" in error
    assert not any(tmp_path.iterdir())  # nothing simulated, nothing written
