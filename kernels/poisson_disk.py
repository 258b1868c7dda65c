"""Poisson-disk selection among candidate points with per-point radii, as a parallel independent set.

Candidates ``i`` and ``j`` conflict when ``‖x_i − x_j‖ < max(r_i, r_j)`` (PIE-NeRF §4.1: a
particle's nearest neighbour lies at least its radius ``r(x)`` away, Eq. 3; taking the larger radius
makes the relation symmetric, so both particles of a pair keep their own guarantee). The selection
is the greedy one in decreasing priority, computed in parallel rounds: an undecided candidate is
accepted when no conflicting candidate of higher priority is still undecided or accepted, then every
undecided candidate conflicting with an accepted one is rejected. Each round accepts at least the
highest-priority undecided candidate; with random priorities the rounds number ``O(log² N)``. The
result is the same set a sequential dart-throwing loop over the candidates in priority order gives:
no two accepted points conflict, and every rejected candidate conflicts with an accepted one
(the set is maximal).

Warp, because each candidate walks its hash-grid neighbourhood with early exit: neighbour lists of
a candidate hold ~1000 entries when radii vary threefold, too many to materialise for torch ops.
"""

# Warp needs int(0)/bool(True) to declare variables that change inside dynamic loops.
# ruff: noqa: UP018

import torch
import warp as wp

from kernels import backend
from kernels.spatial_hash import SpatialHash

__all__ = ["poisson_disk_select"]

_UNDECIDED = wp.constant(0)
_ACCEPTED = wp.constant(1)
_REJECTED = wp.constant(2)


@wp.kernel
def _accept_local_maxima(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    priority: wp.array(dtype=wp.int32),
    query_radius: float,
    state: wp.array(dtype=wp.int32),
):
    # Undecided -> accepted does not change what another thread reads ("not rejected"), so the
    # state is updated in place.
    i = wp.hash_grid_point_id(grid, wp.tid())
    if state[i] != _UNDECIDED:
        return
    x = points[i]
    r = radius[i]
    p = priority[i]
    is_maximum = bool(True)
    j = int(0)
    query = wp.hash_grid_query(grid, x, query_radius)
    while is_maximum and wp.hash_grid_query_next(query, j):
        if priority[j] > p and state[j] != _REJECTED:
            reach = wp.max(r, radius[j])
            if wp.length_sq(points[j] - x) < reach * reach:
                is_maximum = False
    if is_maximum:
        state[i] = _ACCEPTED


@wp.kernel
def _reject_conflicts(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    query_radius: float,
    state: wp.array(dtype=wp.int32),
    undecided: wp.array(dtype=wp.int32),
):
    # Undecided -> rejected does not change what another thread reads ("accepted"), so in place.
    i = wp.hash_grid_point_id(grid, wp.tid())
    if state[i] != _UNDECIDED:
        return
    x = points[i]
    r = radius[i]
    conflict = bool(False)
    j = int(0)
    query = wp.hash_grid_query(grid, x, query_radius)
    while not conflict and wp.hash_grid_query_next(query, j):
        if state[j] == _ACCEPTED:
            reach = wp.max(r, radius[j])
            if wp.length_sq(points[j] - x) < reach * reach:
                conflict = True
    if conflict:
        state[i] = _REJECTED
    else:
        wp.atomic_add(undecided, 0, 1)


def poisson_disk_select(points: torch.Tensor, radius: torch.Tensor, priority: torch.Tensor) -> torch.Tensor:
    """The greedy Poisson-disk subset of candidates in decreasing priority (PIE-NeRF §4.1, Eq. 3).

    Args:
        points: float32 ``[N, 3]`` candidate positions, metres, on the backend device.
        radius: float32 ``[N]`` candidate radii ``r`` (Eq. 3), metres, ``> 0``.
        priority: int32 ``[N]`` distinct priorities (e.g. a random permutation of ``0..N-1``).

    Returns:
        bool ``[N]``: True for accepted candidates. No two accepted ``i, j`` have
        ``‖x_i − x_j‖ < max(r_i, r_j)``, and every rejected candidate has such an accepted neighbour.
    """
    n = points.shape[0]
    if points.dtype != torch.float32 or points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be float32 [N, 3], got {points.dtype} {tuple(points.shape)}")
    if radius.dtype != torch.float32 or radius.shape != (n,):
        raise ValueError(f"radius must be float32 [N] with N={n}, got {radius.dtype} {tuple(radius.shape)}")
    if priority.dtype != torch.int32 or priority.shape != (n,):
        raise ValueError(f"priority must be int32 [N] with N={n}, got {priority.dtype} {tuple(priority.shape)}")
    if n == 0:
        return torch.zeros(0, dtype=torch.bool, device=points.device)
    if not bool((radius > 0.0).all()):
        raise ValueError("every candidate radius must be positive; check the radius rule (Eq. 3)")
    if torch.unique(priority).numel() != n:
        raise ValueError("priorities must be distinct; use a random permutation of 0..N-1")

    query_radius = float(radius.max())
    grid = SpatialHash(points, query_radius)
    points_wp = backend.to_warp(points, dtype=wp.vec3)
    radius_wp, priority_wp = backend.to_warp(radius), backend.to_warp(priority)
    state = torch.zeros(n, dtype=torch.int32, device=points.device)
    undecided = torch.zeros(1, dtype=torch.int32, device=points.device)
    state_wp, undecided_wp = backend.to_warp(state), backend.to_warp(undecided)
    remaining = n
    while remaining > 0:
        wp.launch(
            _accept_local_maxima,
            dim=n,
            inputs=[grid.grid_id, points_wp, radius_wp, priority_wp, query_radius, state_wp],
            device=backend.warp_device(),
        )
        undecided.zero_()
        wp.launch(
            _reject_conflicts,
            dim=n,
            inputs=[grid.grid_id, points_wp, radius_wp, query_radius, state_wp, undecided_wp],
            device=backend.warp_device(),
        )
        remaining = int(undecided.item())
    return state == 1
