"""The IPC barrier and what it is made of: squared pair distances by closest-feature type, the log barrier and the
edge-edge mollifier, with exact gradients and Hessians, in Warp.

The garment simulator (PhysAvatar §3.2, Appendix A.3, Codim-IPC [52]) keeps its garment and the body apart with the
IPC log-barrier contact potential (Li et al. 2020) at contact distance d̂ = 1 mm. Its pieces live here as Warp
functions, which :mod:`kernels.contact` (the barrier over pair lists), :mod:`kernels.ccd` (the line-search bound)
and :mod:`kernels.friction` (the lagged friction) build their kernels from, and as host functions over pair lists.

Conventions:

* Squared distances are what IPC differentiates: ``d`` below is always a squared distance, ``d̂²`` the squared
  activation distance.
* Distance types use the numbering of the IPC Toolkit (``P_T0``…``P_T`` = 0…6, ``EA0_EB0``…``EA_EB`` = 0…8).
* Kernels are generic over float32 and float64 and Hessians are vertex-major, as in :mod:`kernels.element_terms`.
"""

from typing import Any

import torch
import warp as wp

from kernels import backend
from kernels.element_terms import (
    ElementTerms,
    add_block,
    add_vec,
    allocate_terms,
    check_index,
    check_positions,
    declare_float64_overloads,
    launch_rows,
    matrix_block,
    scalar_type,
    store_terms,
    vec3_array,
)

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = [
    "EDGE_EDGE_TYPES",
    "POINT_TRIANGLE_TYPES",
    "barrier",
    "check_dhat",
    "edge_edge_distance",
    "edge_edge_distance_value",
    "edge_edge_mollifier",
    "edge_edge_mollifier_threshold",
    "edge_edge_mollifier_value",
    "edge_edge_terms",
    "edge_edge_type",
    "edge_edge_value",
    "line_line_gram",
    "log_barrier",
    "pair_distance",
    "pair_vertex",
    "parallel_tolerance",
    "point_triangle_distance",
    "point_triangle_distance_value",
    "point_triangle_terms",
    "point_triangle_type",
    "point_triangle_value",
    "triangle_corner",
]


POINT_TRIANGLE_TYPES = ("P_T0", "P_T1", "P_T2", "P_E0", "P_E1", "P_E2", "P_T")
"""Closest-feature types of a point-triangle pair; ``P_E0`` is edge t0-t1, ``P_E1`` t1-t2, ``P_E2`` t2-t0."""


EDGE_EDGE_TYPES = ("EA0_EB0", "EA0_EB1", "EA1_EB0", "EA1_EB1", "EA_EB0", "EA_EB1", "EA0_EB", "EA1_EB", "EA_EB")
"""Closest-feature types of an edge-edge pair (``EA_EB0``: vertex eb0 against edge a, ``EA_EB``: line-line)."""


# ---------------------------------------------------------------------------------------------------------------
# IPC barrier
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def log_barrier(d: Any, dhat: Any):
    """IPC log barrier in squared distance (Li et al. 2020, IPC) and its first two derivatives.

    ``b(d) = −(d − d̂)² ln(d / d̂)`` for ``0 < d < d̂``, else 0;
    ``b′ = (d̂ − d)(2 ln(d/d̂) − d̂/d + 1)``; ``b″ = −2 ln(d/d̂) − 4 (d − d̂)/d + (d − d̂)²/d²``.
    """
    zero = type(d)(0.0)
    b = zero
    b1 = zero
    b2 = zero
    if d < dhat:
        r = d - dhat
        log = wp.log(d / dhat)
        b = -r * r * log
        b1 = -r * (type(d)(2.0) * log - dhat / d + type(d)(1.0))
        b2 = -type(d)(2.0) * log - type(d)(4.0) * r / d + r * r / (d * d)
    return b, b1, b2


@wp.kernel
def _barrier_kernel(
    d: wp.array(dtype=Any), dhat: Any, b: wp.array(dtype=Any), b1: wp.array(dtype=Any), b2: wp.array(dtype=Any)
):
    i = wp.tid()
    v, v1, v2 = log_barrier(d[i], dhat)
    b[i] = v
    b1[i] = v1
    b2[i] = v2


def barrier(d: torch.Tensor, dhat: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """IPC log barrier of squared distances and its derivatives (Li et al. 2020; PhysAvatar §3.2, A.3).

    Args:
        d: ``[N]`` squared distances, m², positive.
        dhat: squared activation distance ``d̂²``, m² (1e-6 for the paper's 1 mm).

    Returns:
        ``(b, db/dd, d²b/dd²)``, each ``[N]``; all zero where ``d ≥ d̂²``.
    """
    if not d.dtype.is_floating_point or d.dim() != 1:
        raise ValueError(f"d must be a float [N] tensor of squared distances, got {d.dtype} {tuple(d.shape)}")
    check_dhat(dhat)
    d = d.contiguous()
    out = [torch.empty_like(d) for _ in range(3)]
    if d.numel():
        backend.launch(_barrier_kernel, d.numel(), [d, scalar_type(d)(dhat), *out])
    return tuple(out)


# ---------------------------------------------------------------------------------------------------------------
# Squared distances by closest-feature type, with gradients and Hessians
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _point_point(w: Any):
    """``d = ‖w‖²``, ``w = p − q``: gradient ``2w``, Hessian ``2I``."""
    zero = w * type(w[0])(0.0)
    h = wp.matrix(shape=(9, 9), dtype=type(w[0]))
    h = add_block(h, 0, 0, wp.identity(n=3, dtype=type(w[0])) * type(w[0])(2.0))
    return wp.dot(w, w), wp.matrix_from_rows(w * type(w[0])(2.0), zero, zero), h


@wp.func
def _point_edge(u: Any, e: Any):
    """Point-line squared distance ``d = ‖u × e‖² / ‖e‖²``, ``u = p − e0``, ``e = e1 − e0``.

    With ``s = u·e``, ``L = e·e`` (``d = u·u − s²/L``): ``∂d/∂u = 2(u − s e / L)``, ``∂d/∂e = −(s/L) ∂d/∂u``,
    ``∂²d/∂u² = 2I − 2eeᵀ/L``, ``∂²d/∂u∂e = −2(euᵀ + sI)/L + 4s eeᵀ/L²``,
    ``∂²d/∂e² = −2uuᵀ/L + 4s(ueᵀ + euᵀ)/L² + 2s²I/L² − 8s² eeᵀ/L³``.
    """
    two = type(u[0])(2.0)
    eye = wp.identity(n=3, dtype=type(u[0]))
    c = wp.cross(u, e)
    l = wp.dot(e, e)
    s = wp.dot(u, e)
    r = s / l
    gu = (u - e * r) * two
    ge = gu * (-r)
    huu = (eye - wp.outer(e, e) / l) * two
    hue = -(wp.outer(e, u) + eye * s) * (two / l) + wp.outer(e, e) * (two * two * r / l)
    hee = (
        -wp.outer(u, u) * (two / l)
        + (wp.outer(u, e) + wp.outer(e, u)) * (two * two * r / l)
        + eye * (two * r * r)
        - wp.outer(e, e) * (two * two * two * r * r / l)
    )
    h = wp.matrix(shape=(9, 9), dtype=type(u[0]))
    h = add_block(h, 0, 0, huu)
    h = add_block(h, 0, 1, hue)
    h = add_block(h, 1, 0, wp.transpose(hue))
    h = add_block(h, 1, 1, hee)
    return wp.dot(c, c) / l, wp.matrix_from_rows(gu, ge, gu * type(u[0])(0.0)), h


@wp.func
def _cross_chain(e1: Any, e2: Any, g_n: Any, h_nn: Any, h: Any, r1: int, r2: int):
    """Chain a function of ``n = e1 × e2`` to ``(e1, e2)``: returns the gradients and adds the Hessian blocks.

    ``∂n/∂e1 = −[e2]×``, ``∂n/∂e2 = [e1]×``; the bilinear term ``g·(δe1 × δe2)`` adds ``−[g]×`` to the
    ``(e1, e2)`` block.
    """
    j1 = -wp.skew(e2)
    j2 = wp.skew(e1)
    h = add_block(h, r1, r1, wp.transpose(j1) * h_nn * j1)
    h = add_block(h, r2, r2, wp.transpose(j2) * h_nn * j2)
    cross = wp.transpose(j1) * h_nn * j2 - wp.skew(g_n)
    h = add_block(h, r1, r2, cross)
    h = add_block(h, r2, r1, wp.transpose(cross))
    return wp.transpose(j1) * g_n, wp.transpose(j2) * g_n, h


@wp.func
def _point_plane(v: Any, e1: Any, e2: Any):
    """Point-plane (and line-line) squared distance ``d = (v·n)² / ‖n‖²``, ``n = e1 × e2``.

    With ``r = v·n``, ``N = n·n``: ``∂d/∂v = 2rn/N``, ``∂d/∂n = 2rv/N − 2r²n/N²``, ``∂²d/∂v² = 2nnᵀ/N``,
    ``∂²d/∂v∂n = 2(nvᵀ + rI)/N − 4r nnᵀ/N²``,
    ``∂²d/∂n² = 2vvᵀ/N − 4r(vnᵀ + nvᵀ)/N² − 2r²I/N² + 8r² nnᵀ/N³``; chained to ``(e1, e2)`` by
    :func:`_cross_chain`.
    """
    two = type(v[0])(2.0)
    eye = wp.identity(n=3, dtype=type(v[0]))
    n = wp.cross(e1, e2)
    nn = wp.dot(n, n)
    r = wp.dot(v, n)
    rn = r / nn
    g_v = n * (two * rn)
    g_n = (v - n * rn) * (two * rn)
    h_vv = wp.outer(n, n) * (two / nn)
    h_vn = (wp.outer(n, v) + eye * r) * (two / nn) - wp.outer(n, n) * (two * two * rn / nn)
    h_nn = (
        wp.outer(v, v) * (two / nn)
        - (wp.outer(v, n) + wp.outer(n, v)) * (two * two * rn / nn)
        - eye * (two * rn * rn)
        + wp.outer(n, n) * (two * two * two * rn * rn / nn)
    )
    h = wp.matrix(shape=(9, 9), dtype=type(v[0]))
    h = add_block(h, 0, 0, h_vv)
    hv1 = h_vn * (-wp.skew(e2))
    hv2 = h_vn * wp.skew(e1)
    h = add_block(h, 0, 1, hv1)
    h = add_block(h, 0, 2, hv2)
    h = add_block(h, 1, 0, wp.transpose(hv1))
    h = add_block(h, 2, 0, wp.transpose(hv2))
    g1, g2, h = _cross_chain(e1, e2, g_n, h_nn, h, 1, 2)
    return r * rn, wp.matrix_from_rows(g_v, g1, g2), h


@wp.func
def _scatter(gy: Any, hy: Any, plus: wp.vec3i, minus: wp.vec3i, rows: int):
    """Map derivatives in difference vectors ``y_α = x[plus_α] − x[minus_α]`` to the pair's 4 vertices.

    ``∂d/∂x_i = Σ_α C_αi ∂d/∂y_α`` and ``H_ij = Σ_αβ C_αi C_βj ∂²d/∂y_α∂y_β`` with ``C_αi = ±1``.
    """
    g = wp.vector(length=12, dtype=type(gy[0, 0]))
    h = wp.matrix(shape=(12, 12), dtype=type(gy[0, 0]))
    for a in range(rows):
        ga = gy[a]
        g = add_vec(g, plus[a], ga)
        g = add_vec(g, minus[a], -ga)
        for b in range(rows):
            m = matrix_block(hy, a, b)
            h = add_block(h, plus[a], plus[b], m)
            h = add_block(h, plus[a], minus[b], -m)
            h = add_block(h, minus[a], plus[b], -m)
            h = add_block(h, minus[a], minus[b], m)
    return g, h


@wp.func
def point_triangle_type(p: Any, t0: Any, t1: Any, t2: Any):
    """Closest feature of triangle ``t0 t1 t2`` to ``p`` from its Voronoi regions (Ericson 2005, §5.1.5)."""
    zero = type(p[0])(0.0)
    ab = t1 - t0
    ac = t2 - t0
    ap = p - t0
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    bp = p - t1
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    cp = p - t2
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    kind = 6
    if d1 <= zero and d2 <= zero:
        kind = 0
    elif d3 >= zero and d4 <= d3:
        kind = 1
    elif d6 >= zero and d5 <= d6:
        kind = 2
    elif vc <= zero and d1 >= zero and d3 <= zero:
        kind = 3
    elif va <= zero and d4 - d3 >= zero and d5 - d6 >= zero:
        kind = 4
    elif vb <= zero and d2 >= zero and d6 <= zero:
        kind = 5
    return kind


@wp.func
def point_triangle_terms(p: Any, t0: Any, t1: Any, t2: Any):
    """Squared point-triangle distance, its type, and its gradient and Hessian over ``(p, t0, t1, t2)``: ``(kind,
    d, g [12], h [12, 12])``, the type numbered as :data:`POINT_TRIANGLE_TYPES`."""
    kind = point_triangle_type(p, t0, t1, t2)
    plus = wp.vec3i(0, 2, 3)
    minus = wp.vec3i(1, 1, 1)
    rows = 3
    d = p[0] * type(p[0])(0.0)
    gy = wp.outer(p, p) * d
    hy = wp.matrix(shape=(9, 9), dtype=type(d))
    if kind <= 2:
        minus = wp.vec3i(kind + 1, 0, 0)
        rows = 1
        d, gy, hy = _point_point(p - triangle_corner(t0, t1, t2, kind))
    elif kind <= 5:
        a = kind - 3
        b = (a + 1) % 3
        plus = wp.vec3i(0, b + 1, 0)
        minus = wp.vec3i(a + 1, a + 1, 0)
        rows = 2
        ea = triangle_corner(t0, t1, t2, a)
        d, gy, hy = _point_edge(p - ea, triangle_corner(t0, t1, t2, b) - ea)
    else:
        d, gy, hy = _point_plane(p - t0, t1 - t0, t2 - t0)
    g, h = _scatter(gy, hy, plus, minus, rows)
    return kind, d, g, h


@wp.func
def triangle_corner(t0: Any, t1: Any, t2: Any, k: int):
    """Corner ``k`` (0, 1 or 2) of triangle ``t0 t1 t2``."""
    c = t0
    if k == 1:
        c = t1
    elif k == 2:
        c = t2
    return c


@wp.func
def point_triangle_value(p: Any, t0: Any, t1: Any, t2: Any):
    """Squared point-triangle distance only (CCD, energy values), bit for bit that of :func:`point_triangle_terms`."""
    kind = point_triangle_type(p, t0, t1, t2)
    d = type(p[0])(0.0)
    if kind <= 2:
        w = p - triangle_corner(t0, t1, t2, kind)
        d = wp.dot(w, w)
    elif kind <= 5:
        ea = triangle_corner(t0, t1, t2, kind - 3)
        e = triangle_corner(t0, t1, t2, (kind - 2) % 3) - ea
        c = wp.cross(p - ea, e)
        d = wp.dot(c, c) / wp.dot(e, e)
    else:
        n = wp.cross(t1 - t0, t2 - t0)
        r = wp.dot(p - t0, n)
        d = r * (r / wp.dot(n, n))  # rounded as _point_plane rounds it
    return d


@wp.func
def _end_against_segment(p: Any, a: Any, b: Any, best: Any, kind: int, at_a: int, at_b: int, inside: int):
    """Keep the closer of ``best`` and end point ``p`` against segment ``a b`` (type ``at_a``/``at_b``/``inside``)."""
    e = b - a
    s = wp.dot(p - a, e) / wp.dot(e, e)
    k = inside
    if s <= type(best)(0.0):
        s = type(best)(0.0)
        k = at_a
    elif s >= type(best)(1.0):
        s = type(best)(1.0)
        k = at_b
    w = p - a - e * s
    d = wp.dot(w, w)
    if d < best:
        best = d
        kind = k
    return best, kind


@wp.func
def line_line_gram(ea0: Any, ea1: Any, eb0: Any, eb1: Any):
    """Entries ``a, b, c, e, f`` of the 2×2 system of the lines' closest points: with ``da = ea1 − ea0``,
    ``db = eb1 − eb0``, ``r = ea0 − eb0``: ``a = da·da``, ``b = da·db``, ``c = da·r``, ``e = db·db``, ``f = db·r``;
    the parameters are ``s = (b f − c e) / (a e − b²)`` on ``a``, ``t = (a f − b c) / (a e − b²)`` on ``b``."""
    da = ea1 - ea0
    db = eb1 - eb0
    r = ea0 - eb0
    return wp.dot(da, da), wp.dot(da, db), wp.dot(da, r), wp.dot(db, db), wp.dot(db, r)


@wp.func
def _line_line_parameters(ea0: Any, ea1: Any, eb0: Any, eb1: Any):
    """``sin²`` of the angle between the segments' lines and the parameters ``s`` on ``a``, ``t`` on ``b`` of their
    closest points, all from ``n = da × db`` (``da = ea1 − ea0``, ``db = eb1 − eb0``, ``r = eb0 − ea0``):
    ``s = (r × db)·n / ‖n‖²``, ``t = (r × da)·n / ‖n‖²``.

    The cross products keep full relative precision as the lines turn parallel, where the Gram form
    ``a e − b²`` (:func:`line_line_gram`) cancels to rounding noise of size ``ε a e``: for exactly parallel,
    coplanar edges that noise passed the parallel test, put ``s, t`` anywhere, and gave the line-line distance 0.
    ``s`` and ``t`` are only meaningful where ``sin²`` passes the caller's parallel test.
    """
    da = ea1 - ea0
    db = eb1 - eb0
    r = eb0 - ea0
    n = wp.cross(da, db)
    nn = wp.dot(n, n)
    sin2 = nn / (wp.dot(da, da) * wp.dot(db, db))
    s = wp.dot(wp.cross(r, db), n) / nn
    t = wp.dot(wp.cross(r, da), n) / nn
    return sin2, s, t


@wp.func
def edge_edge_type(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
    """Closest features of segments ``a`` and ``b``, minimising ``‖ea0 + s da − eb0 − t db‖²`` over ``[0, 1]²``.

    The unconstrained line-line optimum counts when it lies inside the square; otherwise the optimum lies on
    the square's boundary, i.e. one segment's end point against the other segment, and the closest of the four
    wins. Lines closer to parallel than ``sin² ≤ parallel_tol`` (``sin²`` from ``‖da × db‖²``, exact to rounding
    even for parallel lines) go straight to the boundary: there the boundary minimum is the segments' distance
    to within ``sin θ`` times their length, and the line-line distance, 0 for any two coplanar lines, would
    report parallel neighbours of a flat sheet as touching.
    """
    zero = type(parallel_tol)(0.0)
    one = type(parallel_tol)(1.0)
    da = ea1 - ea0
    db = eb1 - eb0
    a = wp.dot(da, da)
    e = wp.dot(db, db)
    kind = -1
    if wp.length_sq(wp.cross(da, db)) > parallel_tol * a * e:
        sin2, s, t = _line_line_parameters(ea0, ea1, eb0, eb1)
        if s > zero and s < one and t > zero and t < one:
            kind = 8
    if kind < 0:
        best = wp.length_sq(ea0 - eb0) + a + e + one  # above any end-point distance
        best, kind = _end_against_segment(ea0, eb0, eb1, best, kind, 0, 1, 6)
        best, kind = _end_against_segment(ea1, eb0, eb1, best, kind, 2, 3, 7)
        best, kind = _end_against_segment(eb0, ea0, ea1, best, kind, 0, 2, 4)
        best, kind = _end_against_segment(eb1, ea0, ea1, best, kind, 1, 3, 5)
    return kind


@wp.func
def edge_edge_terms(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
    """Squared edge-edge distance, its type, and its gradient and Hessian over ``(ea0, ea1, eb0, eb1)``: ``(kind,
    d, g [12], h [12, 12])``, the type numbered as :data:`EDGE_EDGE_TYPES`."""
    kind = edge_edge_type(ea0, ea1, eb0, eb1, parallel_tol)
    plus = wp.vec3i(2, 1, 3)
    minus = wp.vec3i(0, 0, 2)
    rows = 3
    d = parallel_tol * type(parallel_tol)(0.0)
    gy = wp.outer(ea0, ea0) * d
    hy = wp.matrix(shape=(9, 9), dtype=type(d))
    if kind <= 3:
        i = kind // 2
        j = kind % 2 + 2
        plus = wp.vec3i(i, 0, 0)
        minus = wp.vec3i(j, 0, 0)
        rows = 1
        d, gy, hy = _point_point(pair_vertex(ea0, ea1, eb0, eb1, i) - pair_vertex(ea0, ea1, eb0, eb1, j))
    elif kind <= 7:
        # vertex `pt` against the edge `base → tip` of the other segment
        pt = kind - 2
        base = 0
        tip = 1
        if kind >= 6:
            pt = kind - 6
            base = 2
            tip = 3
        plus = wp.vec3i(pt, tip, 0)
        minus = wp.vec3i(base, base, 0)
        rows = 2
        xb = pair_vertex(ea0, ea1, eb0, eb1, base)
        d, gy, hy = _point_edge(pair_vertex(ea0, ea1, eb0, eb1, pt) - xb, pair_vertex(ea0, ea1, eb0, eb1, tip) - xb)
    else:
        d, gy, hy = _point_plane(eb0 - ea0, ea1 - ea0, eb1 - eb0)
    g, h = _scatter(gy, hy, plus, minus, rows)
    return kind, d, g, h


@wp.func
def pair_vertex(x0: Any, x1: Any, x2: Any, x3: Any, k: int):
    """Vertex ``k`` (0…3) of a pair ``(x0, x1, x2, x3)``: for edge-edge pairs ``(ea0, ea1, eb0, eb1)``."""
    c = x0
    if k == 1:
        c = x1
    elif k == 2:
        c = x2
    elif k == 3:
        c = x3
    return c


@wp.func
def edge_edge_value(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
    """Squared edge-edge distance only (CCD, energy values), bit for bit that of :func:`edge_edge_terms`."""
    kind = edge_edge_type(ea0, ea1, eb0, eb1, parallel_tol)
    d = type(parallel_tol)(0.0)
    if kind <= 3:
        w = pair_vertex(ea0, ea1, eb0, eb1, kind // 2) - pair_vertex(ea0, ea1, eb0, eb1, kind % 2 + 2)
        d = wp.dot(w, w)
    elif kind <= 7:
        pt = kind - 2
        base = 0
        if kind >= 6:
            pt = kind - 6
            base = 2
        xb = pair_vertex(ea0, ea1, eb0, eb1, base)
        e = pair_vertex(ea0, ea1, eb0, eb1, base + 1) - xb
        c = wp.cross(pair_vertex(ea0, ea1, eb0, eb1, pt) - xb, e)
        d = wp.dot(c, c) / wp.dot(e, e)
    else:
        n = wp.cross(ea1 - ea0, eb1 - eb0)
        r = wp.dot(eb0 - ea0, n)
        d = r * (r / wp.dot(n, n))  # rounded as _point_plane rounds it
    return d


@wp.func
def pair_distance(x0: Any, x1: Any, x2: Any, x3: Any, edge_edge: int, parallel_tol: Any):
    """Squared distance of a point-triangle pair ``(p, t0, t1, t2)`` (``edge_edge`` 0, :func:`point_triangle_value`)
    or an edge-edge pair ``(ea0, ea1, eb0, eb1)`` (``edge_edge`` 1, :func:`edge_edge_value`)."""
    d = type(parallel_tol)(0.0)
    if edge_edge == 0:
        d = point_triangle_value(x0, x1, x2, x3)
    else:
        d = edge_edge_value(x0, x1, x2, x3, parallel_tol)
    return d


@wp.kernel
def _point_triangle_distance_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    kind: wp.array(dtype=wp.int32),
    dist: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    k, d, g, h = point_triangle_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    kind[i] = k
    store_terms(dist, grad, hess, i, d, g, h, 4)


@wp.kernel
def _edge_edge_distance_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    parallel_tol: Any,
    kind: wp.array(dtype=wp.int32),
    dist: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    k, d, g, h = edge_edge_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]], parallel_tol)
    kind[i] = k
    store_terms(dist, grad, hess, i, d, g, h, 4)


def point_triangle_distance(x: torch.Tensor, pairs: torch.Tensor) -> tuple[torch.Tensor, ElementTerms]:
    """Squared point-triangle distances with gradients and Hessians, by closest-feature type (Li et al. 2020).

    The type (vertex, edge or face of the triangle) comes from the Voronoi regions of the triangle; the
    distance is then the point-point, point-line or point-plane one, each differentiated in closed form.

    Args:
        x: ``[V, 3]`` float32 or float64 positions, m.
        pairs: ``[P, 4]`` int32 ``(p, t0, t1, t2)``.

    Returns:
        ``(kind [P] int32, terms)``: the type (:data:`POINT_TRIANGLE_TYPES`) and :class:`ElementTerms` holding
        the squared distance ``[P]`` (m²), gradient ``[P, 4, 3]`` and Hessian ``[P, 12, 12]``.
    """
    check_positions(x)
    check_index(pairs, 4, "pairs")
    out = allocate_terms(x, pairs.shape[0], 4)
    kind = torch.empty(pairs.shape[0], dtype=torch.int32, device=x.device)
    if pairs.shape[0]:
        backend.launch(_point_triangle_distance_kernel, pairs.shape[0], [vec3_array(x), pairs, kind, *out])
    return kind, ElementTerms(*out)


def edge_edge_distance(x: torch.Tensor, pairs: torch.Tensor) -> tuple[torch.Tensor, ElementTerms]:
    """Squared edge-edge distances with gradients and Hessians, by closest-feature type (Li et al. 2020).

    Args:
        x: ``[V, 3]`` float32 or float64 positions, m.
        pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)``.

    Returns:
        ``(kind [Q] int32, terms)``: the type (:data:`EDGE_EDGE_TYPES`) and :class:`ElementTerms` holding the
        squared distance ``[Q]`` (m²), gradient ``[Q, 4, 3]`` and Hessian ``[Q, 12, 12]``.
    """
    check_positions(x)
    check_index(pairs, 4, "pairs")
    out = allocate_terms(x, pairs.shape[0], 4)
    kind = torch.empty(pairs.shape[0], dtype=torch.int32, device=x.device)
    if pairs.shape[0]:
        backend.launch(
            _edge_edge_distance_kernel, pairs.shape[0], [vec3_array(x), pairs, parallel_tolerance(x), kind, *out]
        )
    return kind, ElementTerms(*out)


@wp.kernel
def _distance_value_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    edge_edge: int,
    parallel_tol: Any,
    dist: wp.array(dtype=Any),
):
    i = wp.tid()
    dist[i] = pair_distance(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]], edge_edge, parallel_tol)


def point_triangle_distance_value(x: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """The ``[P]`` squared distances of :func:`point_triangle_distance` alone, m², without derivatives."""
    return _distance_value(x, pairs, 0)


def edge_edge_distance_value(x: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """The ``[Q]`` squared distances of :func:`edge_edge_distance` alone, m², without derivatives."""
    return _distance_value(x, pairs, 1)


def _distance_value(x: torch.Tensor, pairs: torch.Tensor, edge_edge: int) -> torch.Tensor:
    check_positions(x)
    check_index(pairs, 4, "pairs")
    dist = torch.empty(pairs.shape[0], dtype=x.dtype, device=x.device)
    launch_rows(
        _distance_value_kernel, pairs.shape[0], [vec3_array(x), pairs, edge_edge, parallel_tolerance(x)], [dist]
    )
    return dist


# ---------------------------------------------------------------------------------------------------------------
# Edge-edge mollifier
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def edge_edge_mollifier(ea0: Any, ea1: Any, eb0: Any, eb1: Any, eps_x: Any):
    """Edge-edge mollifier of IPC (Li et al. 2020) with its gradient and Hessian.

    ``m(c) = (2 − c/ε_x) c/ε_x`` for ``c = ‖(ea1 − ea0) × (eb1 − eb0)‖² < ε_x``, else 1; it smooths the
    edge-edge barrier where the edges turn parallel and the closest-feature type jumps.
    """
    one = type(eps_x)(1.0)
    two = type(eps_x)(2.0)
    g = wp.vector(length=12, dtype=type(eps_x))
    h = wp.matrix(shape=(12, 12), dtype=type(eps_x))
    m = one
    e1 = ea1 - ea0
    e2 = eb1 - eb0
    n = wp.cross(e1, e2)
    c = wp.dot(n, n)
    if c < eps_x:
        q = c / eps_x
        m = (two - q) * q
        dm = (two - two * q) / eps_x
        ddm = -two / (eps_x * eps_x)
        # c as a function of (e1, e2) through n: ∂c/∂n = 2n, ∂²c/∂n² = 2I
        hc = wp.matrix(shape=(9, 9), dtype=type(eps_x))
        g1, g2, hc = _cross_chain(e1, e2, n * two, wp.identity(n=3, dtype=type(eps_x)) * two, hc, 0, 1)
        gy = wp.matrix_from_rows(g1, g2, g1 * type(eps_x)(0.0))
        gc, hcx = _scatter(gy, hc, wp.vec3i(1, 3, 0), wp.vec3i(0, 2, 0), 2)
        g = gc * dm
        h = wp.outer(gc, gc) * ddm + hcx * dm
    return m, g, h


@wp.func
def edge_edge_mollifier_value(ea0: Any, ea1: Any, eb0: Any, eb1: Any, eps_x: Any):
    """The mollifier of :func:`edge_edge_mollifier` alone."""
    m = type(eps_x)(1.0)
    n = wp.cross(ea1 - ea0, eb1 - eb0)
    c = wp.dot(n, n)
    if c < eps_x:
        q = c / eps_x
        m = (type(eps_x)(2.0) - q) * q
    return m


def edge_edge_mollifier_threshold(x_rest: torch.Tensor, ee_pairs: torch.Tensor) -> torch.Tensor:
    """Mollifier threshold ``ε_x = 10⁻³ ‖ēa‖² ‖ēb‖²`` of each edge-edge pair from rest lengths (Li et al. 2020).

    Args:
        x_rest: ``[V, 3]`` rest positions, m.
        ee_pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)``.

    Returns:
        ``[Q]`` thresholds, m⁴.
    """
    check_positions(x_rest)
    check_index(ee_pairs, 4, "ee_pairs")
    p = x_rest[ee_pairs.long()]
    la = ((p[:, 1] - p[:, 0]) ** 2).sum(1)
    lb = ((p[:, 3] - p[:, 2]) ** 2).sum(1)
    return 1e-3 * la * lb


# ---------------------------------------------------------------------------------------------------------------
# Argument checks
# ---------------------------------------------------------------------------------------------------------------


def parallel_tolerance(x: torch.Tensor):
    """``sin²`` below which edges count as parallel: the dtype's machine epsilon."""
    return scalar_type(x)(torch.finfo(x.dtype).eps)


def check_dhat(dhat: float) -> None:
    """Raise ``ValueError`` unless ``dhat``, the squared activation distance ``d̂²`` (m²), is positive."""
    if not dhat > 0.0:
        raise ValueError(f"dhat ({dhat}) must be positive: it is the squared activation distance d̂², m²")


declare_float64_overloads(globals())
