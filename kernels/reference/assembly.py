"""Reference of :mod:`kernels.assembly`: the Newton matrix of element Hessians, assembled densely in torch."""

from __future__ import annotations

import torch

__all__ = ["newton_matrix"]


def newton_matrix(
    n: int,
    elements: list[tuple[torch.Tensor, torch.Tensor, float]],
    dof: torch.Tensor,
    p_kin: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The dense ``[3n, 3n]`` matrix and ``[n, 3]`` right-hand side that :func:`kernels.assembly.scatter_hessians`
    accumulates.

    Args:
        n: free vertices.
        elements: ``(index [N, k], hess [N, 3k, 3k], scale)`` per element kind, as that function takes them.
        dof: ``[V]`` block row of each vertex, ``-1`` for a kinematic one.
        p_kin: ``[V, 3]`` kinematic displacements.
    """
    size = 3 * n
    matrix = p_kin.new_zeros(size + 3, size + 3)  # the last block row and column collect the kinematic vertices
    rhs = p_kin.new_zeros(n + 1, 3)
    for index, hess, scale in elements:
        hess = scale * hess
        k = index.shape[1]
        d = dof.long()[index.long()]
        slot = torch.where(d >= 0, d, n)
        rows = (3 * slot[:, :, None] + torch.arange(3, device=d.device)).reshape(-1, 3 * k)
        for e in range(hess.shape[0]):
            matrix[rows[e][:, None], rows[e][None, :]] += hess[e]
            for j in range(k):
                if d[e, j] < 0:
                    push = hess[e][:, 3 * j : 3 * j + 3] @ p_kin[index[e, j].long()]
                    rhs.index_add_(0, slot[e], -push.view(k, 3))
    return matrix[:size, :size], rhs[:n]
