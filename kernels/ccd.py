"""Additive continuous collision detection (ACCD, Li et al. 2021) of point-triangle and edge-edge pairs, in Warp.

The garment simulator (PhysAvatar §3.2, Appendix A.3, Codim-IPC [52]) keeps every iterate of its implicit Newton
solve intersection-free by bounding each step of its line search with a conservative time of impact of the contact
candidates: the largest fraction of the step that no pair can cross. The pair distances are those of
:mod:`kernels.ipc_barrier`; kernels are generic over float32 and float64.
"""

from typing import Any

import torch
import warp as wp

from kernels import backend
from kernels.element_terms import (
    check_index,
    check_positions,
    check_values,
    declare_float64_overloads,
    scalar_type,
    vec3_array,
)
from kernels.ipc_barrier import pair_distance, parallel_tolerance

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["edge_edge_ccd", "point_triangle_ccd"]


@wp.func
def _additive_ccd(
    x0: Any,
    x1: Any,
    x2: Any,
    x3: Any,
    dx0: Any,
    dx1: Any,
    dx2: Any,
    dx3: Any,
    edge_edge: int,
    min_distance: Any,
    eta: Any,
    max_iterations: int,
    parallel_tol: Any,
):
    """Additive CCD of Codim-IPC (Li et al. 2021): a conservative time of impact in ``[0, 1]``.

    With the mean displacement removed, ``l_p`` bounds how fast the pair's distance can shrink per unit time
    (``‖dp‖ + max‖dt_i‖`` point-triangle, ``max‖dea_i‖ + max‖deb_j‖`` edge-edge). Stepping by
    ``gap / l_p`` (``gap = d − ξ``) can therefore never pass the first contact; the march stops once the gap
    falls below ``η`` times its initial value and returns the last time whose gap was above it, so
    ``t ≤ t_true`` and the pair is separated by more than ``ξ`` at ``t``. Returns 1 when no contact occurs.
    """
    zero = type(eta)(0.0)
    one = type(eta)(1.0)
    quarter = type(eta)(0.25)
    mean = (dx0 + dx1 + dx2 + dx3) * quarter
    p0 = dx0 - mean
    p1 = dx1 - mean
    p2 = dx2 - mean
    p3 = dx3 - mean
    lp = zero
    if edge_edge == 0:
        lp = wp.length(p0) + wp.max(wp.length(p1), wp.max(wp.length(p2), wp.length(p3)))
    else:
        lp = wp.max(wp.length(p0), wp.length(p1)) + wp.max(wp.length(p2), wp.length(p3))
    toi = one
    if lp > zero:
        xi2 = min_distance * min_distance
        d = pair_distance(x0, x1, x2, x3, edge_edge, parallel_tol)
        if d <= xi2:
            toi = zero
        else:
            gap0 = (d - xi2) / (wp.sqrt(d) + min_distance)
            target = eta * gap0
            t = zero
            step = (one - eta) * gap0 / lp
            it = wp.int32(0)
            while it < max_iterations:
                s = t + step
                d = pair_distance(x0 + p0 * s, x1 + p1 * s, x2 + p2 * s, x3 + p3 * s, edge_edge, parallel_tol)
                gap = (d - xi2) / (wp.sqrt(d) + min_distance)
                if t > zero and gap < target:
                    break
                t = s
                if t > one:
                    break
                step = type(eta)(0.9) * gap / lp
                it += 1
            toi = wp.min(t, one)
    return toi


@wp.kernel
def _ccd_kernel(
    x: wp.array(dtype=Any),
    dx: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    edge_edge: int,
    min_distance: Any,
    eta: Any,
    max_iterations: int,
    parallel_tol: Any,
    toi: wp.array(dtype=Any),
):
    i = wp.tid()
    a = pairs[i, 0]
    b = pairs[i, 1]
    c = pairs[i, 2]
    d = pairs[i, 3]
    toi[i] = _additive_ccd(
        x[a], x[b], x[c], x[d], dx[a], dx[b], dx[c], dx[d], edge_edge, min_distance, eta, max_iterations, parallel_tol
    )


def _ccd(x, dx, pairs, edge_edge, min_distance, eta, max_iterations):
    check_positions(x)
    check_values(dx, x, tuple(x.shape), "dx")
    check_index(pairs, 4, "pairs")
    if not 0.0 < eta < 1.0:
        raise ValueError(f"eta ({eta}) must lie in (0, 1); the paper uses 0.1")
    if min_distance < 0.0:
        raise ValueError(f"min_distance ({min_distance}) must be non-negative")
    if max_iterations < 1:
        raise ValueError(f"max_iterations ({max_iterations}) must be at least 1")
    toi = torch.empty(pairs.shape[0], dtype=x.dtype, device=x.device)
    if pairs.shape[0]:
        scalar = scalar_type(x)
        args = [vec3_array(x), vec3_array(dx.contiguous()), pairs, edge_edge, scalar(min_distance), scalar(eta)]
        backend.launch(_ccd_kernel, pairs.shape[0], [*args, max_iterations, parallel_tolerance(x), toi])
    return toi


def point_triangle_ccd(
    x: torch.Tensor,
    dx: torch.Tensor,
    pairs: torch.Tensor,
    min_distance: float = 0.0,
    eta: float = 0.1,
    max_iterations: int = 1_000_000,
) -> torch.Tensor:
    """Conservative time of impact of point-triangle pairs moving linearly from ``x`` to ``x + dx``.

    Additive CCD (Li et al. 2021, Codim-IPC [52]): never later than the first time the pair comes within
    ``min_distance``; at the returned time the pair is still separated by more than ``min_distance``.

    Args:
        x: ``[V, 3]`` float32 or float64 positions at the start of the step, m.
        dx: ``[V, 3]`` displacements over the step, m.
        pairs: ``[P, 4]`` int32 ``(p, t0, t1, t2)``.
        min_distance: separation ``ξ`` treated as contact, m.
        eta: the march stops once the gap falls below ``eta`` times its initial value (paper: 0.1).
        max_iterations: cap on the march per pair; hitting it returns the (still safe) time reached.

    Returns:
        ``[P]`` times of impact in ``[0, 1]`` as fractions of the step; 1 means no contact in the step.
    """
    return _ccd(x, dx, pairs, 0, min_distance, eta, max_iterations)


def edge_edge_ccd(
    x: torch.Tensor,
    dx: torch.Tensor,
    pairs: torch.Tensor,
    min_distance: float = 0.0,
    eta: float = 0.1,
    max_iterations: int = 1_000_000,
) -> torch.Tensor:
    """Conservative time of impact of edge-edge pairs (``(ea0, ea1, eb0, eb1)``, else as :func:`point_triangle_ccd`)."""
    return _ccd(x, dx, pairs, 1, min_distance, eta, max_iterations)


declare_float64_overloads(globals())
