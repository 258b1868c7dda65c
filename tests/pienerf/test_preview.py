"""pienerf.preview: the refinement schedule renders coarse while things move and refines once when still."""

from __future__ import annotations

import torch

from pienerf.preview import RefinementSchedule


def test_refinement_schedule_is_coarse_while_moving_and_refines_once_when_still():
    schedule = RefinementSchedule(moving=4, still=1, tolerance=1e-4)
    q = torch.zeros(5, 3, dtype=torch.float64)
    assert schedule.next(q, "view a") == 4
    assert schedule.next(q + 1e-5, "view a") == 1, "still: refine"
    assert schedule.next(q, "view a") is None, "already refined"
    assert schedule.next(q + 1e-3, "view a") == 4, "the body moved"
    assert schedule.next(q + 1e-3, "view b") == 4, "the camera moved"
    assert [schedule.next(q + 1e-3, "view b") for _ in range(3)] == [1, None, None]
