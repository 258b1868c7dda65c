"""Reference of :mod:`kernels.poisson_disk`: sequential dart throwing over candidates in priority order."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["poisson_disk_select"]


def poisson_disk_select(points: torch.Tensor, radius: torch.Tensor, priority: torch.Tensor) -> torch.Tensor:
    """Accept candidates one by one in decreasing priority unless they conflict with an accepted one.

    Candidates ``i, j`` conflict when ``‖x_i − x_j‖ < max(r_i, r_j)``; distances are compared
    squared in float32, as the kernel does.

    Args:
        points: ``[N, 3]`` float32, metres.
        radius: ``[N]`` float32, metres.
        priority: ``[N]`` distinct integers.

    Returns:
        bool ``[N]`` on ``points.device``: True for accepted candidates.
    """
    x = points.detach().cpu().numpy().astype(np.float32)
    r = radius.detach().cpu().numpy().astype(np.float32)
    order = np.argsort(-priority.detach().cpu().numpy().astype(np.int64), kind="stable")
    accepted = np.zeros(x.shape[0], dtype=bool)
    kept_x, kept_r, kept = np.empty_like(x), np.empty_like(r), 0
    for i in order:
        offset = kept_x[:kept] - x[i]
        d_sq = (offset * offset).sum(axis=1)
        reach = np.maximum(kept_r[:kept], r[i])
        if not np.any(d_sq < reach * reach):
            accepted[i] = True
            kept_x[kept], kept_r[kept] = x[i], r[i]
            kept += 1
    return torch.from_numpy(accepted).to(points.device)
