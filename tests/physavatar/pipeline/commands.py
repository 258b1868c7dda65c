"""The avatar command line, run as a user runs it, for the pipeline tests."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def run_avatar(*args: str) -> subprocess.CompletedProcess:
    """``python -m apps.avatar ARGS`` in a fresh process, from the repository root."""
    return subprocess.run(
        [sys.executable, "-m", "apps.avatar", *args], cwd=ROOT, capture_output=True, text=True, check=False
    )
