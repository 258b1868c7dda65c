"""Reference of :mod:`kernels.friction`: IPC's lagged friction potential and the lagged contact data it reads, as
chains of torch operations.

:func:`lagged_contacts` takes the squared distances and closest-feature types from
:func:`kernels.ipc_barrier.point_triangle_distance` / :func:`kernels.ipc_barrier.edge_edge_distance` and the barrier
derivative from :func:`kernels.ipc_barrier.barrier`, and computes the closest-point weights
(:func:`point_triangle_weights`, :func:`edge_edge_weights`), mollifiers, normals and forces with masked torch
operations, one pair kind at a time.
"""

from __future__ import annotations

import torch

from kernels import ipc_barrier

__all__ = ["edge_edge_weights", "friction_potential", "lagged_contacts", "point_triangle_weights"]


def friction_potential(
    displacement: torch.Tensor,
    index: torch.Tensor,
    weight: torch.Tensor,
    projector: torch.Tensor,
    force: torch.Tensor,
    eps: float,
    hessian: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """IPC's smoothed lagged friction potential ``D = Σ_k μλ_k f₀(‖u_k‖)`` (Li et al. 2020, Eq. 14–16).

    ``u_k = P_k Σ_i w_ki Δx_i`` is the tangential relative displacement of contact ``k`` since the start of the
    step (``P_k = I − n_k n_kᵀ``, weights and normal lagged). ``f₀(y) = −y³/(3ε²) + y²/ε + ε/3`` below
    ``ε = ε_v Δt``, else ``y``; ``f₁ = f₀′``. Gradient ``w_i μλ (f₁/y) u``; Hessian blocks
    ``w_i w_j μλ ((f₁/y) P + c u uᵀ)`` with ``c = −1/(ε² y)`` below ``ε`` and ``−1/y³`` above: PSD on both sides.

    Args:
        displacement: ``[N, 3]`` displacement of every vertex since the start of the step, m.
        index: ``[K, 4]`` vertices of each contact.
        weight: ``[K, 4]`` closest-point weights (``Σ w_i x_i`` is the gap vector).
        projector: ``[K, 3, 3]`` tangent projectors ``I − n nᵀ``.
        force: ``[K]`` ``μ λ``, N.
        eps: ``ε_v Δt``, m.
        hessian: also return the ``[K, 12, 12]`` Hessians.

    Returns:
        ``(energy [K] (J), grad [K, 4, 3] (N), hess [K, 12, 12] or None)``.
    """
    w = weight
    u = torch.einsum("kab,kb->ka", projector, (w[:, :, None] * displacement[index.long()]).sum(1))
    y = torch.linalg.norm(u, dim=1)
    inside = y < eps
    f0 = torch.where(inside, -(y**3) / (3 * eps * eps) + y * y / eps + eps / 3.0, y)
    f1_over_y = torch.where(inside, 2.0 / eps - y / (eps * eps), 1.0 / y.clamp_min(eps))
    grad = (force * f1_over_y)[:, None, None] * w[:, :, None] * u[:, None, :]
    hess = None
    if hessian:
        safe_y = y.clamp_min(1e-300)
        c = torch.where(inside, -1.0 / (eps * eps * safe_y), -1.0 / safe_y**3)
        c = torch.where(y > 0, c, torch.zeros_like(c))
        block = f1_over_y[:, None, None] * projector + c[:, None, None] * u[:, :, None] * u[:, None, :]
        block = force[:, None, None] * block
        hess = (w[:, :, None, None, None] * w[:, None, :, None, None] * block[:, None, None]).permute(0, 1, 3, 2, 4)
        hess = hess.reshape(-1, 12, 12)
    return force * f0, grad, hess


def point_triangle_weights(q: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
    """Closest-point weights of point-triangle pairs: ``Σ_i w_i q_i`` is the point minus its closest triangle point.

    Args:
        q: ``[P, 4, 3]`` positions ``(p, t0, t1, t2)`` of each pair, m.
        kind: ``[P]`` closest-feature types (:data:`kernels.ipc_barrier.POINT_TRIANGLE_TYPES`).

    Returns:
        ``[P, 4]`` weights, 1: ``w_0 = 1`` and the triangle's weights are minus the closest point's barycentric
        coordinates (a corner: one ``−1``; an edge: the clamped segment parameter; the face: the plane projection).
    """
    p, t = q[:, 0], q[:, 1:]
    n = q.shape[0]
    w = torch.zeros(n, 4, dtype=q.dtype, device=q.device)
    w[:, 0] = 1.0
    rows = torch.arange(n, device=q.device)
    k = kind.long()
    vertex = k <= 2
    w[rows[vertex], 1 + k[vertex]] = -1.0
    edge = (k >= 3) & (k <= 5)
    a = (k - 3).clamp(0, 2)
    b = (a + 1) % 3
    ta, tb = t[rows, a], t[rows, b]
    e = tb - ta
    s = (((p - ta) * e).sum(1) / (e * e).sum(1)).clamp(0.0, 1.0)
    w[rows[edge], 1 + a[edge]] = -(1.0 - s[edge])
    w[rows[edge], 1 + b[edge]] = -s[edge]
    face = k == 6
    e1, e2, r = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], p - t[:, 0]
    a11, a12, a22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (r * e1).sum(1), (r * e2).sum(1)
    det = a11 * a22 - a12 * a12
    beta1 = (a22 * r1 - a12 * r2) / det
    beta2 = (a11 * r2 - a12 * r1) / det
    w[face, 1] = -(1.0 - beta1[face] - beta2[face])
    w[face, 2] = -beta1[face]
    w[face, 3] = -beta2[face]
    return w


def edge_edge_weights(q: torch.Tensor, kind: torch.Tensor) -> torch.Tensor:
    """Closest-point weights of edge-edge pairs: ``Σ_i w_i q_i`` is the closest point of edge a minus that of edge b.

    Args:
        q: ``[Q, 4, 3]`` positions ``(ea0, ea1, eb0, eb1)`` of each pair, m.
        kind: ``[Q]`` closest-feature types (:data:`kernels.ipc_barrier.EDGE_EDGE_TYPES`).

    Returns:
        ``[Q, 4]`` weights, 1: edge a's barycentric coordinates of its closest point, then minus edge b's.
    """
    n = q.shape[0]
    rows = torch.arange(n, device=q.device)
    k = kind.long()
    w = torch.zeros(n, 4, dtype=q.dtype, device=q.device)
    ends = k <= 3
    w[rows[ends], (k // 2)[ends]] = 1.0
    w[rows[ends], (k % 2 + 2)[ends]] = -1.0
    da, db = q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]
    # an end point of b against edge a (types 4, 5)
    on_a = (k == 4) | (k == 5)
    pb = q[rows, (k - 2).clamp(2, 3)]
    s = (((pb - q[:, 0]) * da).sum(1) / (da * da).sum(1)).clamp(0.0, 1.0)
    w[on_a, 0] = 1.0 - s[on_a]
    w[on_a, 1] = s[on_a]
    w[rows[on_a], (k - 2)[on_a].clamp(2, 3)] = -1.0
    # an end point of a against edge b (types 6, 7)
    on_b = (k == 6) | (k == 7)
    pa = q[rows, (k - 6).clamp(0, 1)]
    t = (((pa - q[:, 2]) * db).sum(1) / (db * db).sum(1)).clamp(0.0, 1.0)
    w[rows[on_b], (k - 6)[on_b].clamp(0, 1)] = 1.0
    w[on_b, 2] = -(1.0 - t[on_b])
    w[on_b, 3] = -t[on_b]
    # interior line-line (type 8)
    line = k == 8
    r = q[:, 0] - q[:, 2]
    a, e, b = (da * da).sum(1), (db * db).sum(1), (da * db).sum(1)
    c, f = (da * r).sum(1), (db * r).sum(1)
    den = (a * e - b * b).clamp_min(torch.finfo(q.dtype).tiny)
    s_l, t_l = (b * f - c * e) / den, (a * f - b * c) / den
    w[line, 0] = 1.0 - s_l[line]
    w[line, 1] = s_l[line]
    w[line, 2] = -(1.0 - t_l[line])
    w[line, 3] = -t_l[line]
    return w


def lagged_contacts(
    x: torch.Tensor,
    pt_pairs: torch.Tensor,
    ee_pairs: torch.Tensor,
    ee_eps_x: torch.Tensor,
    dhat2: float,
    stiffness: float,
    mu: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lagged friction data of the active contacts (``d < d̂²``), point-triangle pairs first (IPC §5).

    ``λ = −κ m b′(d) 2√d`` (the normal force, ``m = 1`` for point-triangle pairs, the edge-edge mollifier of
    threshold ``ε_x`` otherwise), ``n = g / ‖g‖`` with the gap ``g = Σ_i w_i x_i``.

    Args:
        x: ``[V, 3]`` float64 positions, m.
        pt_pairs: ``[P, 4]`` int32 ``(p, t0, t1, t2)``.
        ee_pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)``.
        ee_eps_x: ``[Q]`` mollifier thresholds, m⁴.
        dhat2: squared activation distance ``d̂²``, m².
        stiffness: barrier stiffness ``κ``, J/m⁴.
        mu: friction coefficient ``μ``, 1.

    Returns:
        ``(index [K, 4] int64, weight [K, 4], projector [K, 3, 3] (I − n nᵀ), force [K] (μλ, N))``.
    """
    pieces = []
    if pt_pairs.shape[0]:
        kind, terms = ipc_barrier.point_triangle_distance(x, pt_pairs)
        q = x[pt_pairs.long()]
        weight = point_triangle_weights(q, kind)
        pieces.append((pt_pairs.long(), terms.energy, weight, torch.ones_like(terms.energy)))
    if ee_pairs.shape[0]:
        kind, terms = ipc_barrier.edge_edge_distance(x, ee_pairs)
        q = x[ee_pairs.long()]
        c = (torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]) ** 2).sum(1)
        mollifier = torch.where(c < ee_eps_x, (2.0 - c / ee_eps_x) * c / ee_eps_x, torch.ones_like(c))
        pieces.append((ee_pairs.long(), terms.energy, edge_edge_weights(q, kind), mollifier))
    if not pieces:
        empty = x.new_zeros(0)
        return torch.zeros(0, 4, dtype=torch.int64, device=x.device), empty.view(0, 4), empty.view(0, 3, 3), empty
    index = torch.cat([p[0] for p in pieces])
    d = torch.cat([p[1] for p in pieces])
    weight = torch.cat([p[2] for p in pieces])
    mollifier = torch.cat([p[3] for p in pieces])
    active = d < dhat2
    index, d, weight, mollifier = index[active], d[active], weight[active], mollifier[active]
    _, b1, _ = ipc_barrier.barrier(d.contiguous(), dhat2)
    force = mu * (-stiffness * mollifier * b1 * 2.0 * torch.sqrt(d))
    gap = (weight[:, :, None] * x[index]).sum(1)
    normal = gap / torch.linalg.norm(gap, dim=1, keepdim=True)
    projector = torch.eye(3, dtype=x.dtype, device=x.device) - normal[:, :, None] * normal[:, None, :]
    return index, weight, projector, force
