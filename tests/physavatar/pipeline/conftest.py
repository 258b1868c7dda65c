"""The synthetic experiment at smoke size, run once per session for every pipeline test that reads it."""

import pytest

from tests.physavatar.pipeline.commands import run_avatar


@pytest.fixture(scope="session")
def experiment(tmp_path_factory):
    """``(out, stderr)`` of ``pipeline --smoke`` on the CPU: every stage's folder under ``out``."""
    out = tmp_path_factory.mktemp("avatar")
    result = run_avatar("pipeline", "--smoke", "--out", str(out), "--device", "cpu")
    assert result.returncode == 0, result.stderr[-3000:]
    return out, result.stderr
