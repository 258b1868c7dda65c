"""Two runs' results compared field by field: exactly on a CPU, where every kernel sums in a fixed order, and to a
relative tolerance on CUDA, whose float32 atomics sum in an order that changes from run to run."""

from __future__ import annotations

import pytest

from pienerf.executor import flatten

__all__ = ["assert_same_results"]


def assert_same_results(ours: dict, theirs: dict, device: str, rel: float, leave_out: tuple[str, ...] = ()) -> None:
    """``ours`` and ``theirs`` (nested tables) hold the same fields with the same values, the fields whose last or
    first key is in ``leave_out`` (timings, process ids) left out: every value exactly on ``device == "cpu"``, the
    floating-point ones to ``rel`` on CUDA (the caller says where ``rel`` comes from)."""
    ours, theirs = (
        {k: v for k, v in flatten(m).items() if not {k.split(".")[0], k.rsplit(".", 1)[-1]} & set(leave_out)}
        for m in (ours, theirs)
    )
    assert ours.keys() == theirs.keys()
    floats = sorted(k for k, v in ours.items() if isinstance(v, float) and isinstance(theirs[k], float))
    assert {k: v for k, v in ours.items() if k not in floats} == {k: v for k, v in theirs.items() if k not in floats}
    expected = [theirs[k] for k in floats]
    assert [ours[k] for k in floats] == (expected if device == "cpu" else pytest.approx(expected, rel=rel, abs=1e-12))
