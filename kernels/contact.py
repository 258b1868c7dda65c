"""The IPC contact potential over lists of point-triangle and edge-edge pairs, and the broad-phase test of such lists,
in Warp.

The garment simulator (PhysAvatar §3.2, Appendix A.3, Codim-IPC [52]) adds ``κ Σ b(d_k)`` over its contact pairs to
the incremental potential (Li et al. 2020; d̂ = 1 mm). Per pair this module evaluates the barrier's energy, gradient
and exact Hessian (:class:`kernels.element_terms.ElementTerms`) from the distances, barrier and mollifier of
:mod:`kernels.ipc_barrier`; and it tests which candidate pairs' boxes, swept over a step, come within ``d̂`` of each
other (:func:`pair_boxes_overlap`), which the solver's broad phase filters its candidates with.
"""

from typing import Any

import torch
import warp as wp

from kernels import backend
from kernels.element_terms import (
    ElementTerms,
    allocate_terms,
    check_index,
    check_positions,
    check_values,
    declare_float64_overloads,
    launch_rows,
    scalar_type,
    store_terms,
    vec3_array,
)
from kernels.ipc_barrier import (
    check_dhat,
    edge_edge_mollifier,
    edge_edge_mollifier_value,
    edge_edge_terms,
    edge_edge_value,
    log_barrier,
    parallel_tolerance,
    point_triangle_terms,
    point_triangle_value,
)

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["contact_energy", "contact_energy_value", "pair_boxes_overlap"]


# ---------------------------------------------------------------------------------------------------------------
# Contact potential over pair lists
# ---------------------------------------------------------------------------------------------------------------


@wp.kernel
def _point_triangle_barrier_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    dhat: Any,
    stiffness: Any,
    energy: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    kind, d, gd, hd = point_triangle_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    b, b1, b2 = log_barrier(d, dhat)
    # κ b(d(x)): ∇ = κ b′ ∇d, ∇² = κ (b″ ∇d ∇dᵀ + b′ ∇²d)
    h = (wp.outer(gd, gd) * b2 + hd * b1) * stiffness
    store_terms(energy, grad, hess, i, stiffness * b, gd * (stiffness * b1), h, 4)


@wp.kernel
def _edge_edge_barrier_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    eps_x: wp.array(dtype=Any),
    dhat: Any,
    stiffness: Any,
    parallel_tol: Any,
    energy: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    ea0 = x[pairs[i, 0]]
    ea1 = x[pairs[i, 1]]
    eb0 = x[pairs[i, 2]]
    eb1 = x[pairs[i, 3]]
    kind, d, gd, hd = edge_edge_terms(ea0, ea1, eb0, eb1, parallel_tol)
    b, b1, b2 = log_barrier(d, dhat)
    m, gm, hm = edge_edge_mollifier(ea0, ea1, eb0, eb1, eps_x[i])
    # κ m b: ∇ = κ (m ∇b + b ∇m), ∇² = κ (m ∇²b + ∇m ∇bᵀ + ∇b ∇mᵀ + b ∇²m)
    gb = gd * b1
    hb = wp.outer(gd, gd) * b2 + hd * b1
    g = (gb * m + gm * b) * stiffness
    h = (hb * m + wp.outer(gm, gb) + wp.outer(gb, gm) + hm * b) * stiffness
    store_terms(energy, grad, hess, i, stiffness * m * b, g, h, 4)


@wp.kernel
def _point_triangle_barrier_value_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    dhat: Any,
    stiffness: Any,
    energy: wp.array(dtype=Any),
):
    i = wp.tid()
    d = point_triangle_value(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    b, b1, b2 = log_barrier(d, dhat)
    energy[i] = stiffness * b


@wp.kernel
def _edge_edge_barrier_value_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    eps_x: wp.array(dtype=Any),
    dhat: Any,
    stiffness: Any,
    parallel_tol: Any,
    energy: wp.array(dtype=Any),
):
    i = wp.tid()
    ea0 = x[pairs[i, 0]]
    ea1 = x[pairs[i, 1]]
    eb0 = x[pairs[i, 2]]
    eb1 = x[pairs[i, 3]]
    b, b1, b2 = log_barrier(edge_edge_value(ea0, ea1, eb0, eb1, parallel_tol), dhat)
    energy[i] = stiffness * edge_edge_mollifier_value(ea0, ea1, eb0, eb1, eps_x[i]) * b


def contact_energy(
    x: torch.Tensor,
    pt_pairs: torch.Tensor,
    ee_pairs: torch.Tensor,
    ee_eps_x: torch.Tensor,
    dhat: float,
    stiffness: float,
) -> tuple[ElementTerms, ElementTerms]:
    """IPC contact potential ``κ Σ b(d_k)`` of point-triangle and mollified edge-edge pairs (Li et al. 2020).

    Point-triangle pairs contribute ``κ b(d)``; edge-edge pairs ``κ m(x) b(d)`` with the mollifier ``m`` of
    threshold ``ε_x`` (:func:`kernels.ipc_barrier.edge_edge_mollifier_threshold`). ``d`` is the squared distance of
    the pair's closest features (:func:`kernels.ipc_barrier.point_triangle_distance`,
    :func:`kernels.ipc_barrier.edge_edge_distance`); pairs at ``d ≥ d̂²`` give
    zero. The barrier has no friction term; Codim-IPC's lagged friction (μ = 0.2) belongs to the solver.

    Args:
        x: ``[V, 3]`` float32 or float64 positions, m.
        pt_pairs: ``[P, 4]`` int32 ``(p, t0, t1, t2)``.
        ee_pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)``.
        ee_eps_x: ``[Q]`` mollifier thresholds, m⁴.
        dhat: squared activation distance ``d̂²``, m² (1e-6 for the paper's 1 mm).
        stiffness: barrier stiffness ``κ``, J/m⁴ (``b`` is in m⁴).

    Returns:
        ``(point_triangle, edge_edge)`` :class:`ElementTerms`, energies ``[P]`` / ``[Q]`` (J), gradients
        ``[·, 4, 3]``, Hessians ``[·, 12, 12]``.
    """
    pt_inputs, ee_inputs = _contact_inputs(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness)
    pt = allocate_terms(x, pt_pairs.shape[0], 4)
    ee = allocate_terms(x, ee_pairs.shape[0], 4)
    launch_rows(_point_triangle_barrier_kernel, pt_pairs.shape[0], pt_inputs, pt)
    launch_rows(_edge_edge_barrier_kernel, ee_pairs.shape[0], ee_inputs, ee)
    return ElementTerms(*pt), ElementTerms(*ee)


def contact_energy_value(
    x: torch.Tensor,
    pt_pairs: torch.Tensor,
    ee_pairs: torch.Tensor,
    ee_eps_x: torch.Tensor,
    dhat: float,
    stiffness: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``[P]`` and ``[Q]`` energies of :func:`contact_energy` alone (bit for bit the same), J: for line
    searches."""
    pt_inputs, ee_inputs = _contact_inputs(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness)
    pt = torch.empty(pt_pairs.shape[0], dtype=x.dtype, device=x.device)
    ee = torch.empty(ee_pairs.shape[0], dtype=x.dtype, device=x.device)
    launch_rows(_point_triangle_barrier_value_kernel, pt_pairs.shape[0], pt_inputs, [pt])
    launch_rows(_edge_edge_barrier_value_kernel, ee_pairs.shape[0], ee_inputs, [ee])
    return pt, ee


def _contact_inputs(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness) -> tuple[list, list]:
    check_positions(x)
    check_index(pt_pairs, 4, "pt_pairs")
    check_index(ee_pairs, 4, "ee_pairs")
    ee_eps_x = check_values(ee_eps_x, x, (ee_pairs.shape[0],), "ee_eps_x")
    check_dhat(dhat)
    scalar = scalar_type(x)
    points = vec3_array(x)
    return (
        [points, pt_pairs, scalar(dhat), scalar(stiffness)],
        [
            points,
            ee_pairs,
            ee_eps_x,
            scalar(dhat),
            scalar(stiffness),
            parallel_tolerance(x),
        ],
    )


# ---------------------------------------------------------------------------------------------------------------
# Broad-phase test of pair lists
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _edges_parallel(x0: Any, x1: Any, x2: Any, x3: Any, sin2: Any):
    da = x1 - x0
    db = x3 - x2
    return wp.length_sq(wp.cross(da, db)) < sin2 * wp.length_sq(da) * wp.length_sq(db)


@wp.kernel
def _pair_boxes_kernel(
    x: wp.array(dtype=Any),
    dx: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    split: int,
    dhat: Any,
    parallel: Any,
    overlap: wp.array(dtype=wp.uint8),
):
    i = wp.tid()
    big = type(dhat)(1.0e300)
    a_lo = type(x[0])(big, big, big)
    a_hi = -a_lo
    b_lo = a_lo
    b_hi = a_hi
    for k in range(4):
        start = x[pairs[i, k]]
        end = start + dx[pairs[i, k]]
        lo = wp.min(start, end)
        hi = wp.max(start, end)
        if k < split:
            a_lo = wp.min(a_lo, lo)
            a_hi = wp.max(a_hi, hi)
        else:
            b_lo = wp.min(b_lo, lo)
            b_hi = wp.max(b_hi, hi)
    result = wp.uint8(1)
    for axis in range(3):
        if a_lo[axis] - dhat > b_hi[axis] or b_lo[axis] > a_hi[axis] + dhat:
            result = wp.uint8(0)
    if result != wp.uint8(0) and split == 2 and parallel > type(dhat)(0.0):
        q0 = x[pairs[i, 0]]
        q1 = x[pairs[i, 1]]
        q2 = x[pairs[i, 2]]
        q3 = x[pairs[i, 3]]
        if _edges_parallel(q0, q1, q2, q3, parallel):
            q0 = q0 + dx[pairs[i, 0]]
            q1 = q1 + dx[pairs[i, 1]]
            q2 = q2 + dx[pairs[i, 2]]
            q3 = q3 + dx[pairs[i, 3]]
            if _edges_parallel(q0, q1, q2, q3, parallel):
                result = wp.uint8(0)
    overlap[i] = result


def pair_boxes_overlap(
    x: torch.Tensor, dx: torch.Tensor | None, pairs: torch.Tensor, split: int, dhat: float, parallel: float = 0.0
) -> torch.Tensor:
    """Broad-phase test of contact pairs: whether the boxes of their two primitives, swept over ``x → x + dx``, lie
    within ``dhat`` of each other (and, for edge pairs with ``parallel > 0``, whether the edges stay apart from
    parallel at one end of the sweep at least).

    Args:
        x: ``[V, 3]`` float32 or float64 positions, m.
        dx: ``[V, 3]`` displacements of the sweep, m, or ``None`` for the boxes at ``x``.
        pairs: ``[N, 4]`` int32 vertex indices; the first ``split`` form one primitive, the rest the other
            (1 for point–triangle pairs, 2 for edge–edge pairs).
        split: 1 or 2.
        dhat: distance, m, by which the first primitive's box is grown (the IPC activation distance ``d̂``).
        parallel: ``sin²θ`` below which edge pairs (``split`` 2) count as parallel; pairs parallel at both ends of
            the sweep are rejected. 0 keeps them.

    Returns:
        ``[N]`` bool.
    """
    check_positions(x)
    check_index(pairs, 4, "pairs")
    if split not in (1, 2):
        raise ValueError(f"split ({split}) must be 1 (point–triangle pairs) or 2 (edge–edge pairs)")
    if not 0.0 <= parallel < 1.0:
        raise ValueError(f"parallel ({parallel}) must be a sin² in [0, 1)")
    dx = torch.zeros_like(x) if dx is None else check_values(dx, x, tuple(x.shape), "dx")
    overlap = torch.empty(pairs.shape[0], dtype=torch.uint8, device=x.device)
    if pairs.shape[0]:
        scalar = scalar_type(x)
        args = [vec3_array(x), vec3_array(dx), pairs, split, scalar(dhat), scalar(parallel), overlap]
        backend.launch(_pair_boxes_kernel, pairs.shape[0], args)
    return overlap.view(torch.bool)


declare_float64_overloads(globals())
