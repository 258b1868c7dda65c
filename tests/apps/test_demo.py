"""apps.demo: the smoke runs exit 0, with the mesh and with the NeRF render mode."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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
