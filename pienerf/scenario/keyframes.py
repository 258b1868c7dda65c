"""Keyframed 3-vectors of a scenario (drag targets, moving colliders): piecewise-linear in time."""

from __future__ import annotations

import torch

from pienerf.scenario.schema import ScenarioError

__all__ = ["keyframe"]


def keyframe(keys: list, t: float, where: str) -> torch.Tensor:
    """Piecewise-linear interpolation of ``[[time, [x, y, z]], …]`` at time ``t`` (held past the ends)."""
    try:
        times = [float(k[0]) for k in keys]
        values = torch.tensor([k[1] for k in keys], dtype=torch.float64)
    except (TypeError, IndexError, ValueError):
        raise ScenarioError(f"'{where}' must be [[time, [x, y, z]], ...], got {keys!r}") from None
    if values.shape != (len(times), 3) or any(b < a for a, b in zip(times, times[1:], strict=False)):
        raise ScenarioError(f"'{where}' must be [[time, [x, y, z]], ...] with increasing times, got {keys!r}")
    if t <= times[0]:
        return values[0]
    for i in range(1, len(times)):
        if t <= times[i]:
            s = (t - times[i - 1]) / max(times[i] - times[i - 1], 1e-12)
            return (1 - s) * values[i - 1] + s * values[i]
    return values[-1]
