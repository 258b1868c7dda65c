"""apps.demo: the smoke runs exit 0, with the mesh and with the NeRF render mode; a bad or busy port, or a frame
budget that is not positive, stops the start at once with the fix; a user's capture plays, a folder that is not one
is refused."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from apps import demo
from tests.physavatar.handmade_capture import build_handmade_capture
from tests.pienerf.viewer.test_loop import free_port

ROOT = Path(__file__).resolve().parents[2]


def test_smoke_run_exits_zero(device):
    result = subprocess.run(
        [sys.executable, "-m", "apps.demo", "--smoke", "--port", str(free_port()), "--device", device],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "smoke: 3 steps of plant" in result.stdout


def test_smoke_run_with_the_nerf_render(device, tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "apps.demo",
            "--smoke",
            "--render",
            "nerf",
            "--port",
            str(free_port()),
            "--device",
            device,
            "--cache-dir",
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "smoke: 3 steps of plant" in result.stdout and "smoke: nerf frame 64x48" in result.stdout
    assert list(tmp_path.glob("scenes/plant-*/ngp-*.pt")), "the fitted NeRF is cached under the scene's folder"


def test_a_port_out_of_range_is_refused_with_the_fix():
    result = subprocess.run(
        [sys.executable, "-m", "apps.demo", "--smoke", "--port", "99999"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "port 99999 is not a TCP port" in result.stderr and "--port N" in result.stderr


@pytest.mark.parametrize("budget", ["0", "-5", "nan"])
def test_a_frame_budget_that_is_not_positive_is_refused_with_the_fix(budget):
    result = subprocess.run(
        [sys.executable, "-m", "apps.demo", "--smoke", "--frame-budget-ms", budget],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--frame-budget-ms must be a positive number of milliseconds" in result.stderr


@pytest.mark.parametrize("viewer", ["meshcat", "viser"])
def test_a_port_in_use_is_named_with_the_fix(device, viewer):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "apps.demo", "--smoke", "--viewer", viewer, "--port", str(port), "--device", device],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert result.returncode == 2, result.stderr[-2000:]
    assert f"cannot listen on 127.0.0.1:{port}" in result.stderr and "--port N" in result.stderr


def test_smoke_run_plays_a_users_capture(device, tmp_path):
    build_handmade_capture(tmp_path)
    result = subprocess.run(
        [sys.executable, "-m", "apps.demo", "--smoke", "--scene", "avatar", "--capture", str(tmp_path), "--port",
         str(free_port()), "--device", device],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    assert "smoke: 3 steps of avatar" in result.stdout
    assert f"on the body of the capture {tmp_path.name}: 4 frames at 30 fps" in result.stderr


def test_a_folder_that_is_not_a_capture_stops_the_start_with_the_fix(tmp_path, capsys):
    argv = ["--smoke", "--scene", "avatar", "--capture", str(tmp_path), "--port", "0", "--device", "cpu"]
    assert demo.main(argv) == 2
    error = capsys.readouterr().err
    assert "is not a capture this viewer can play" in error and "transforms.json" in error
