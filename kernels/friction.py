"""IPC's smoothed lagged friction: the lagged contact data and the potential with its derivatives, in Warp.

The garment simulator (PhysAvatar §3.2 with Codim-IPC) adds the lagged friction potential of IPC (Li et al. 2020,
§5, Eq. 14–16) to its incremental potential and evaluates it at every Newton iteration and line-search trial.
For contact ``k`` with lagged closest-point weights ``w_ki`` over its four vertices, lagged tangent projector
``P_k = I − n_k n_kᵀ`` and lagged normal-force magnitude times friction coefficient ``μλ_k``:

* ``u_k = P_k Σ_i w_ki Δx_i`` is the tangential relative displacement since the start of the step, m;
  ``y = ‖u_k‖``.
* ``D_k = μλ_k f₀(y)`` with ``f₀(y) = −y³/(3ε²) + y²/ε + ε/3`` for ``y < ε`` and ``f₀(y) = y`` above, where
  ``ε = ε_v Δt`` (m) is the velocity threshold times the step; ``f₀`` is C¹ at ``ε``.
* ``∂D_k/∂x_i = w_ki μλ_k (f₁/y) u_k`` with ``f₁/y = 2/ε − y/ε²`` below ``ε`` and ``1/y`` above.
* Hessian blocks ``∂²D_k/∂x_i∂x_j = w_ki w_kj μλ_k ((f₁/y) P_k + c u_k u_kᵀ)`` with ``c = −1/(ε² y)`` below
  ``ε``, ``−1/y³`` above and ``c = 0`` at ``y = 0`` exactly (where ``u_k = 0``), so no entry is ever NaN or
  infinite. For a symmetric idempotent ``P_k`` this is the exact Hessian; it is positive semi-definite.

Units: displacements and ``ε`` in m, ``μλ`` in N; energies in J, gradients in N, Hessians in N/m. Everything is
float64, as in the simulator (1 mm contact gaps on 1 m coordinates). The math and outputs match the reference
:func:`kernels.reference.friction.friction_potential`, a chain of ~20 torch operations whose cost on a GPU is
mostly launch overhead; here it is one launch on torch's current stream (:mod:`kernels.backend`).

The lagged data themselves come from :func:`lagged_contacts`, once per time step, at the positions ``x^t`` where
the step starts: from the candidate point-triangle and edge-edge pairs it keeps those with squared distance
``d < d̂²`` (closest-feature types exactly as :func:`kernels.ipc_barrier.point_triangle_distance` and
:func:`kernels.ipc_barrier.edge_edge_distance` classify them, from the same Warp functions) and returns, per
contact, its four vertices, the weights ``w_ki`` with ``Σ_i w_ki x_i`` the gap between the closest points (m), the
projector ``P_k`` of the unit gap ``n_k`` and ``μλ_k = μ (−κ m b′(d) 2√d)`` (N; ``b′`` the barrier derivative in
m², ``m`` the edge-edge mollifier, 1 for point-triangle pairs). One launch per pair kind and one compaction (one
host read of the active pairs); the reference is :func:`kernels.reference.friction.lagged_contacts`, the masked
torch code with one or more launches per closest-feature type.

Warp, not Taichi: the simulator around it is Warp and torch, and the kernels are per-contact maps with no reduction.
They beat the torch versions on both devices (``docs/benchmarks.md``).
"""

import math

import torch
import warp as wp

from kernels import backend
from kernels.element_terms import check_index, check_positions, check_values
from kernels.ipc_barrier import (
    edge_edge_mollifier,
    edge_edge_type,
    edge_edge_value,
    line_line_gram,
    log_barrier,
    pair_vertex,
    parallel_tolerance,
    point_triangle_type,
    point_triangle_value,
    triangle_corner,
)

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["friction_potential", "lagged_contacts"]

_MAT33D = wp.types.matrix((3, 3), wp.float64)


@wp.kernel
def _friction_kernel(
    displacement: wp.array(dtype=wp.vec3d),
    index: wp.array2d(dtype=wp.int32),
    weight: wp.array2d(dtype=wp.float64),
    projector: wp.array(dtype=_MAT33D),
    force: wp.array(dtype=wp.float64),
    eps: wp.float64,
    with_hessian: wp.int32,
    energy: wp.array(dtype=wp.float64),
    grad: wp.array2d(dtype=wp.vec3d),
    hess: wp.array3d(dtype=wp.float64),
):
    k = wp.tid()
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    gap = wp.vec3d(zero, zero, zero)
    for i in range(4):
        gap += weight[k, i] * displacement[index[k, i]]
    p = projector[k]
    u = p * gap
    y = wp.length(u)
    inv_eps = one / eps
    f0 = y
    f1_over_y = zero
    c = zero
    if y < eps:
        f0 = -(y * y * y) * (inv_eps * inv_eps) / wp.float64(3.0) + y * y * inv_eps + eps / wp.float64(3.0)
        f1_over_y = wp.float64(2.0) * inv_eps - y * (inv_eps * inv_eps)
        if y > zero:
            c = -(inv_eps * inv_eps) / y
    else:
        f1_over_y = one / y
        c = -one / (y * y * y)
    mu_lambda = force[k]
    energy[k] = mu_lambda * f0
    scaled_u = u * (mu_lambda * f1_over_y)
    for i in range(4):
        grad[k, i] = scaled_u * weight[k, i]
    if with_hessian != 0:
        block = (p * f1_over_y + wp.outer(u, u) * c) * mu_lambda
        for i in range(4):
            for j in range(4):
                wij = weight[k, i] * weight[k, j]
                for a in range(3):
                    for b in range(3):
                        hess[k, 3 * i + a, 3 * j + b] = wij * block[a, b]


def friction_potential(
    displacement: torch.Tensor,
    index: torch.Tensor,
    weight: torch.Tensor,
    projector: torch.Tensor,
    force: torch.Tensor,
    eps: float,
    hessian: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Per-contact lagged friction energy ``μλ f₀(‖u‖)`` with gradient and, optionally, Hessian (IPC Eq. 14–16).

    Args:
        displacement: ``[N, 3]`` float64 displacement of every vertex since the start of the step, m.
        index: ``[K, 4]`` int32 or int64 vertex indices of each contact, each in ``[0, N)`` (not checked: an index
            out of range reads unrelated memory).
        weight: ``[K, 4]`` float64 closest-point weights: ``Σ_i w_i x_i`` is the contact's gap vector, 1.
        projector: ``[K, 3, 3]`` float64 lagged tangent projectors ``I − n nᵀ``, 1.
        force: ``[K]`` float64 lagged ``μλ``: friction coefficient times normal-force magnitude, N.
        eps: ``ε = ε_v Δt``, the displacement below which static friction is smoothed, m; positive.
        hessian: also compute the ``[K, 12, 12]`` Hessians; ``False`` skips computing and storing them.

    Returns:
        ``(energy [K] (J), grad [K, 4, 3] (N), hess [K, 12, 12] (N/m) or None)``; Hessian rows and columns are
        ordered vertex-major (``3 * vertex + axis``). All on the device of the inputs, float64.

    Raises:
        ValueError: an argument has the wrong shape, dtype or device, or ``eps`` is not a positive finite number.
    """
    _check_float64(displacement, (None, 3), "displacement", "[N, 3]")
    if index.dtype not in (torch.int32, torch.int64) or index.dim() != 2 or index.shape[1] != 4:
        raise ValueError(
            f"index must be an int32 or int64 [K, 4] tensor, got {index.dtype} {list(index.shape)}; "
            "stack each contact's four vertex ids into one row"
        )
    k = index.shape[0]
    _check_float64(weight, (k, 4), "weight", "[K, 4]")
    _check_float64(projector, (k, 3, 3), "projector", "[K, 3, 3]")
    _check_float64(force, (k,), "force", "[K]")
    for name, t in (("index", index), ("weight", weight), ("projector", projector), ("force", force)):
        if t.device != displacement.device:
            raise ValueError(
                f"{name} is on {t.device} but displacement is on {displacement.device}; move it with "
                f".to('{displacement.device}')"
            )
    if not (math.isfinite(eps) and eps > 0.0):
        raise ValueError(f"eps ({eps}) must be a positive finite length ε_v Δt, m")

    device = displacement.device
    energy = torch.empty(k, dtype=torch.float64, device=device)
    grad = torch.empty(k, 4, 3, dtype=torch.float64, device=device)
    hess = torch.empty(k if hessian else 0, 12, 12, dtype=torch.float64, device=device)
    if k:
        backend.launch(
            _friction_kernel,
            k,
            [
                (displacement.contiguous(), wp.vec3d),
                index.to(torch.int32).contiguous(),
                weight.contiguous(),
                (projector.contiguous(), _MAT33D),
                force.contiguous(),
                float(eps),
                1 if hessian else 0,
                energy,
                (grad, wp.vec3d),
                hess,
            ],
        )
    return energy, grad, hess if hessian else None


# ---------------------------------------------------------------------------------------------------------------
# Lagged contact data: closest-point weights, tangent projectors and normal forces at the start of the step
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _segment_parameter(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d):
    """Parameter ``s ∈ [0, 1]`` of the point of segment ``a b`` closest to ``p``."""
    e = b - a
    return wp.clamp(wp.dot(p - a, e) / wp.dot(e, e), wp.float64(0.0), wp.float64(1.0))


@wp.func
def _point_triangle_weights(p: wp.vec3d, t0: wp.vec3d, t1: wp.vec3d, t2: wp.vec3d, kind: int):
    """Weights ``w`` over ``(p, t0, t1, t2)`` with ``Σ w_i x_i`` = ``p`` minus its closest point of type ``kind``."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    w = wp.vec4d(one, zero, zero, zero)
    if kind <= 2:
        w[kind + 1] = -one
    elif kind <= 5:
        a = kind - 3
        b = (a + 1) % 3
        s = _segment_parameter(p, triangle_corner(t0, t1, t2, a), triangle_corner(t0, t1, t2, b))
        w[a + 1] = -(one - s)
        w[b + 1] = -s
    else:
        # barycentric coordinates of p's projection onto the plane, from the 2×2 Gram system
        e1 = t1 - t0
        e2 = t2 - t0
        r = p - t0
        a11 = wp.dot(e1, e1)
        a12 = wp.dot(e1, e2)
        a22 = wp.dot(e2, e2)
        r1 = wp.dot(r, e1)
        r2 = wp.dot(r, e2)
        det = a11 * a22 - a12 * a12
        beta1 = (a22 * r1 - a12 * r2) / det
        beta2 = (a11 * r2 - a12 * r1) / det
        w[1] = -(one - beta1 - beta2)
        w[2] = -beta1
        w[3] = -beta2
    return w


@wp.func
def _edge_edge_weights(ea0: wp.vec3d, ea1: wp.vec3d, eb0: wp.vec3d, eb1: wp.vec3d, kind: int):
    """Weights ``w`` over ``(ea0, ea1, eb0, eb1)`` with ``Σ w_i x_i`` = closest point of ``a`` minus that of ``b``."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    w = wp.vec4d(zero, zero, zero, zero)
    if kind <= 3:
        w[kind // 2] = one
        w[kind % 2 + 2] = -one
    elif kind <= 5:  # end point kind - 2 of b against edge a
        s = _segment_parameter(pair_vertex(ea0, ea1, eb0, eb1, kind - 2), ea0, ea1)
        w[0] = one - s
        w[1] = s
        w[kind - 2] = -one
    elif kind <= 7:  # end point kind - 6 of a against edge b
        t = _segment_parameter(pair_vertex(ea0, ea1, eb0, eb1, kind - 6), eb0, eb1)
        w[kind - 6] = one
        w[2] = -(one - t)
        w[3] = -t
    else:
        a, b, c, e, f = line_line_gram(ea0, ea1, eb0, eb1)
        den = wp.max(a * e - b * b, wp.float64(2.2250738585072014e-308))  # the smallest normal float64
        s = (b * f - c * e) / den
        t = (a * f - b * c) / den
        w = wp.vec4d(one - s, s, -(one - t), -t)
    return w


@wp.func
def _contact_frame(
    x0: wp.vec3d,
    x1: wp.vec3d,
    x2: wp.vec3d,
    x3: wp.vec3d,
    w: wp.vec4d,
    d: wp.float64,
    mollifier: wp.float64,
    dhat2: wp.float64,
    stiffness: wp.float64,
    mu: wp.float64,
):
    """Tangent projector ``I − n nᵀ`` (``n`` the unit gap ``Σ w_i x_i``) and ``μλ = μ (−κ m b′(d) 2√d)``."""
    gap = x0 * w[0] + x1 * w[1] + x2 * w[2] + x3 * w[3]
    n = gap / wp.length(gap)
    b, b1, b2 = log_barrier(d, dhat2)
    force = mu * (-stiffness * mollifier * b1 * wp.float64(2.0) * wp.sqrt(d))
    return wp.identity(n=3, dtype=wp.float64) - wp.outer(n, n), force


@wp.kernel
def _point_triangle_contact_kernel(
    x: wp.array(dtype=wp.vec3d),
    pairs: wp.array2d(dtype=wp.int32),
    dhat2: wp.float64,
    stiffness: wp.float64,
    mu: wp.float64,
    active: wp.array(dtype=wp.uint8),
    index: wp.array2d(dtype=wp.int64),
    weight: wp.array2d(dtype=wp.float64),
    projector: wp.array(dtype=_MAT33D),
    force: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    p = x[pairs[i, 0]]
    t0 = x[pairs[i, 1]]
    t1 = x[pairs[i, 2]]
    t2 = x[pairs[i, 3]]
    d = point_triangle_value(p, t0, t1, t2)
    if d < dhat2:
        active[i] = wp.uint8(1)
        w = _point_triangle_weights(p, t0, t1, t2, point_triangle_type(p, t0, t1, t2))
        proj, f = _contact_frame(p, t0, t1, t2, w, d, wp.float64(1.0), dhat2, stiffness, mu)
        for j in range(4):
            index[i, j] = wp.int64(pairs[i, j])
            weight[i, j] = w[j]
        projector[i] = proj
        force[i] = f
    else:
        active[i] = wp.uint8(0)


@wp.kernel
def _edge_edge_contact_kernel(
    x: wp.array(dtype=wp.vec3d),
    pairs: wp.array2d(dtype=wp.int32),
    eps_x: wp.array(dtype=wp.float64),
    dhat2: wp.float64,
    stiffness: wp.float64,
    mu: wp.float64,
    parallel_tol: wp.float64,
    offset: int,
    active: wp.array(dtype=wp.uint8),
    index: wp.array2d(dtype=wp.int64),
    weight: wp.array2d(dtype=wp.float64),
    projector: wp.array(dtype=_MAT33D),
    force: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    row = offset + i
    ea0 = x[pairs[i, 0]]
    ea1 = x[pairs[i, 1]]
    eb0 = x[pairs[i, 2]]
    eb1 = x[pairs[i, 3]]
    d = edge_edge_value(ea0, ea1, eb0, eb1, parallel_tol)
    if d < dhat2:
        active[row] = wp.uint8(1)
        w = _edge_edge_weights(ea0, ea1, eb0, eb1, edge_edge_type(ea0, ea1, eb0, eb1, parallel_tol))
        m, gm, hm = edge_edge_mollifier(ea0, ea1, eb0, eb1, eps_x[i])
        proj, f = _contact_frame(ea0, ea1, eb0, eb1, w, d, m, dhat2, stiffness, mu)
        for j in range(4):
            index[row, j] = wp.int64(pairs[i, j])
            weight[row, j] = w[j]
        projector[row] = proj
        force[row] = f
    else:
        active[row] = wp.uint8(0)


def lagged_contacts(
    x: torch.Tensor,
    pt_pairs: torch.Tensor,
    ee_pairs: torch.Tensor,
    ee_eps_x: torch.Tensor,
    dhat2: float,
    stiffness: float,
    mu: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lagged friction data of the contacts at the start of a step: the active pairs' weights, projectors, ``μλ``.

    A pair is active when its squared distance ``d`` (:func:`kernels.ipc_barrier.point_triangle_distance`,
    :func:`kernels.ipc_barrier.edge_edge_distance`, same closest-feature types) lies below ``d̂²``. For each active
    pair: weights ``w`` with ``Σ_i w_i x_i`` the gap from the closest point of the second primitive to that of the first
    (``‖gap‖² = d``), the tangent projector ``I − n nᵀ`` with ``n = gap / ‖gap‖``, and ``μλ = μ (−κ m b′(d) 2√d)``:
    the friction coefficient times the normal force ``−∂(κ m b)/∂√d``, with ``b′`` the derivative of IPC's barrier
    (:func:`kernels.ipc_barrier.barrier`) and ``m`` 1 for point-triangle pairs, the edge-edge mollifier of threshold
    ``ε_x`` otherwise (Li et al. 2020, IPC §5).

    Args:
        x: ``[V, 3]`` float64 positions at the start of the step, m; contiguous.
        pt_pairs: ``[P, 4]`` int32 ``(p, t0, t1, t2)`` candidate point-triangle pairs, indices in ``[0, V)`` (not
            checked); contiguous.
        ee_pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)`` candidate edge-edge pairs, as ``pt_pairs``.
        ee_eps_x: ``[Q]`` float64 mollifier thresholds (:func:`kernels.ipc_barrier.edge_edge_mollifier_threshold`),
            m⁴.
        dhat2: squared activation distance ``d̂²``, m² (1e-6 for the paper's 1 mm); positive.
        stiffness: barrier stiffness ``κ``, J/m⁴ (``b`` is in m⁴); finite, non-negative.
        mu: friction coefficient ``μ``, 1; finite, non-negative.

    Returns:
        ``(index [K, 4] int64, weight [K, 4] (1), projector [K, 3, 3] (1), force [K] (N))``, float64 on the device
        of ``x``, for the ``K ≤ P + Q`` active pairs: the point-triangle ones first, then the edge-edge ones, each
        in input order. The inputs of :func:`friction_potential`. An active pair at ``d = 0`` (intersecting
        primitives, which IPC never lets happen) has an undefined normal and an infinite force.

    Raises:
        ValueError: an argument has the wrong shape, dtype or device, or a scalar is out of range.
    """
    check_positions(x)
    if x.dtype != torch.float64:
        raise ValueError(f"positions must be float64 here, got {x.dtype}; convert with .to(torch.float64)")
    check_index(pt_pairs, 4, "pt_pairs")
    check_index(ee_pairs, 4, "ee_pairs")
    ee_eps_x = check_values(ee_eps_x, x, (ee_pairs.shape[0],), "ee_eps_x")
    for name, t in (("pt_pairs", pt_pairs), ("ee_pairs", ee_pairs), ("ee_eps_x", ee_eps_x)):
        if t.device != x.device:
            raise ValueError(f"{name} is on {t.device} but x is on {x.device}; move it with .to('{x.device}')")
    if not (math.isfinite(dhat2) and dhat2 > 0.0):
        raise ValueError(f"dhat2 ({dhat2}) must be a positive finite squared activation distance d̂², m²")
    for name, value in (("stiffness", stiffness), ("mu", mu)):
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} ({value}) must be a finite non-negative number")

    p, q = pt_pairs.shape[0], ee_pairs.shape[0]
    n = p + q
    device = x.device
    active = torch.empty(n, dtype=torch.uint8, device=device)
    index = torch.empty(n, 4, dtype=torch.int64, device=device)
    weight = torch.empty(n, 4, dtype=torch.float64, device=device)
    projector = torch.empty(n, 3, 3, dtype=torch.float64, device=device)
    force = torch.empty(n, dtype=torch.float64, device=device)
    if n == 0:
        return index, weight, projector, force
    x_arg = backend.warp_arg(x, dtype=wp.vec3d)
    outputs = [
        backend.warp_arg(active),
        backend.warp_arg(index),
        backend.warp_arg(weight),
        backend.warp_arg(projector, dtype=_MAT33D),
        backend.warp_arg(force),
    ]
    scalars = [wp.float64(dhat2), wp.float64(stiffness), wp.float64(mu)]
    if p:
        backend.warp_launch(
            _point_triangle_contact_kernel,
            dim=p,
            inputs=[x_arg, backend.warp_arg(pt_pairs), *scalars],
            outputs=outputs,
            device=backend.warp_device(),
        )
    if q:
        backend.warp_launch(
            _edge_edge_contact_kernel,
            dim=q,
            inputs=[x_arg, backend.warp_arg(ee_pairs), backend.warp_arg(ee_eps_x), *scalars, parallel_tolerance(x), p],
            outputs=outputs,
            device=backend.warp_device(),
        )
    keep = torch.nonzero(active).squeeze(1)  # the one host read
    if keep.shape[0] == n:
        return index, weight, projector, force
    return index[keep], weight[keep], projector[keep], force[keep]


def _check_float64(t: torch.Tensor, shape: tuple, name: str, layout: str) -> None:
    """Raise unless ``t`` is a float64 tensor of ``shape`` (a ``None`` entry matches any size)."""
    if t.dtype != torch.float64:
        raise ValueError(f"{name} must be a float64 {layout} tensor, got {t.dtype}; convert with .to(torch.float64)")
    if t.dim() != len(shape) or any(want is not None and got != want for got, want in zip(t.shape, shape, strict=True)):
        expected = ["N" if want is None else want for want in shape]
        raise ValueError(f"{name} must have shape {layout}, here {expected}, got {list(t.shape)}")
