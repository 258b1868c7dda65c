"""Reference of :mod:`kernels.spatial_hash`: brute-force distances between every query and every point.

Distances are computed as ``sqrt(sum((q - p)^2))`` without the matrix-product shortcut, so they are
exact to float32 rounding and ties between equal distances stay ties.
"""

from __future__ import annotations

import torch

__all__ = ["knn", "pairwise_distance", "radius_neighbours"]

# Query rows per chunk, so that a chunk's distance matrix stays near 2^24 entries.
_PAIRS_PER_CHUNK = 1 << 24


def pairwise_distance(points: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Euclidean distances ``[Q, P]`` between queries ``[Q, 3]`` and points ``[P, 3]``, metres."""
    return torch.cdist(queries, points, compute_mode="donot_use_mm_for_euclid_dist")


def _chunks(queries: torch.Tensor, points: torch.Tensor):
    rows = max(1, _PAIRS_PER_CHUNK // max(points.shape[0], 1))
    for start in range(0, queries.shape[0], rows):
        yield start, queries[start : start + rows]


def radius_neighbours(points: torch.Tensor, queries: torch.Tensor, radius: float) -> list[torch.Tensor]:
    """For each query, the sorted int64 indices of all points within ``radius`` (inclusive).

    Args:
        points: ``[P, 3]``.
        queries: ``[Q, 3]``.
        radius: metres.

    Returns:
        A list of ``Q`` tensors, each ``[n_q]`` int64 in increasing order.
    """
    if points.shape[0] == 0:
        raise ValueError("radius_neighbours needs at least one point; the point set is empty")
    out = []
    for _, block in _chunks(queries, points):
        within = pairwise_distance(points, block) <= radius
        out.extend(torch.nonzero(row).flatten() for row in within)
    return out


def knn(points: torch.Tensor, queries: torch.Tensor, k: int, max_radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest points of each query within ``max_radius``, by distance then index.

    Args:
        points: ``[P, 3]``.
        queries: ``[Q, 3]``.
        k: neighbours per query.
        max_radius: metres.

    Returns:
        ``(index [Q, k] int64, distance [Q, k])``, -1 and ``inf`` where fewer than ``k`` points lie
        within ``max_radius``.
    """
    if points.shape[0] == 0:
        raise ValueError("knn needs at least one point; the point set is empty")
    index = torch.full((queries.shape[0], k), -1, dtype=torch.int64, device=queries.device)
    distance = torch.full((queries.shape[0], k), float("inf"), dtype=queries.dtype, device=queries.device)
    order_by_index = torch.arange(points.shape[0], device=queries.device)
    take = min(k, points.shape[0])
    for start, block in _chunks(queries, points):
        d = pairwise_distance(points, block)
        # Stable sort by distance of index-ordered columns: ties come out in increasing index.
        d_sorted, column = torch.sort(d, dim=1, stable=True)
        d_sorted, column = d_sorted[:, :take], order_by_index[column[:, :take]]
        inside = d_sorted <= max_radius
        rows = slice(start, start + block.shape[0])
        index[rows, :take] = torch.where(inside, column, torch.full_like(column, -1))
        distance[rows, :take] = torch.where(inside, d_sorted, torch.full_like(d_sorted, float("inf")))
    return index, distance
