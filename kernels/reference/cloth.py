"""Pure torch/NumPy references for the garment simulator's kernels, written independently of their closed forms.

One module serves :mod:`kernels.shell`, :mod:`kernels.ipc_barrier`, :mod:`kernels.contact` and :mod:`kernels.ccd`:
the brute-force distances are what the barrier, contact and first-contact references are built on, and the whole
oracle is short enough to read in one place.

Energies are plain formulas of the element's vertex positions; gradients and Hessians come from
``torch.func`` (autograd), never from the kernels' hand-derived expressions. Distances are found by brute
force: the closest point of a triangle by projecting onto its plane and clamping to its edges, the closest
points of two segments by minimising over the segment parameters. The first contact of a linear trajectory
is the earliest root of the coplanarity cubic at which the primitives touch.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.func import grad, jacrev, vmap

__all__ = [
    "pair_boxes_overlap",
    "barrier",
    "bending_energy",
    "dihedral_angle",
    "edge_edge_distance",
    "edge_edge_first_contact",
    "edge_edge_mollifier",
    "edge_edge_sq_distance",
    "edge_edge_barrier",
    "membrane_energy",
    "point_triangle_barrier",
    "point_triangle_distance",
    "point_triangle_first_contact",
    "point_triangle_sq_distance",
]


def _terms(energy_fn, q: torch.Tensor, *params: torch.Tensor):
    """Energy ``[N]``, gradient ``[N, k, 3]`` and Hessian ``[N, 3k, 3k]`` of ``energy_fn(q_i, *params_i)``."""
    n, k = q.shape[0], q.shape[1]
    if n == 0:  # vmap cannot trace an empty batch
        return q.new_zeros(0), q.new_zeros(0, k, 3), q.new_zeros(0, 3 * k, 3 * k)
    energy = vmap(energy_fn)(q, *params)
    g = vmap(grad(energy_fn))(q, *params)
    # reverse over reverse: torch.func.hessian's forward mode loads decompositions through deprecated TorchScript
    h = vmap(jacrev(jacrev(energy_fn)))(q, *params).reshape(n, 3 * k, 3 * k)
    return energy, g, h


def _membrane_element(q, dm_inv, area, mu, lam):
    ds = torch.stack([q[1] - q[0], q[2] - q[0]], dim=1)
    f = ds @ dm_inv
    strain = 0.5 * (f.T @ f - torch.eye(2, dtype=q.dtype, device=q.device))
    return area * (mu * (strain**2).sum() + 0.5 * lam * torch.trace(strain) ** 2)


def _stvk_density(strain, mu, lam):
    return mu * (strain**2).sum() + 0.5 * lam * torch.trace(strain) ** 2


def membrane_energy(x, faces, rest_inv, rest_area, mu, lam, stress_filter: str = "none"):
    """StVK membrane ``A (μ‖E‖² + ½λ tr(E)²)`` per triangle, with autograd gradient ``[F, 3, 3]`` and Hessian.

    ``stress_filter`` ``"clamp"`` or ``"abs"`` takes the negative part ``S₋`` of the stress ``S = ∂Ψ/∂E`` (autograd,
    then ``torch.linalg.eigh``) out of the Hessian's stress term ``A (β_kᵀ S β_l) I`` once or twice.
    """
    n = faces.shape[0]
    mu = torch.as_tensor(mu, dtype=x.dtype, device=x.device).expand(n)
    lam = torch.as_tensor(lam, dtype=x.dtype, device=x.device).expand(n)
    q = x[faces.long()]
    energy, g, h = _terms(_membrane_element, q, rest_inv, rest_area, mu, lam)
    if stress_filter == "none":
        return energy, g, h
    f = torch.stack([q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]], 2) @ rest_inv
    strain = 0.5 * (f.transpose(1, 2) @ f - torch.eye(2, dtype=x.dtype, device=x.device))
    stress = vmap(grad(_stvk_density))(strain, mu, lam)
    value, vectors = torch.linalg.eigh(stress)
    negative = (vectors * value.clamp(max=0.0)[:, None, :]) @ vectors.transpose(1, 2)
    beta = torch.cat([-rest_inv.sum(1, keepdim=True), rest_inv], 1)  # [F, 3, 2]: row k is β_k
    term = rest_area[:, None, None] * (beta @ negative @ beta.transpose(1, 2))
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    times = {"clamp": 1.0, "abs": 2.0}[stress_filter]
    return energy, g, h - times * torch.einsum("fkl,ij->fkilj", term, eye).reshape(n, 9, 9)


def dihedral_angle(q: torch.Tensor) -> torch.Tensor:
    """Signed dihedral angle of hinge ``q = (x0, x1, x2, x3)`` from the wing directions across the edge.

    The wing tips are projected onto the plane normal to the edge; the angle between the projections is
    ``π`` for a flat hinge. ``θ = atan2(ê·(w₃ × w₂), −w₂·w₃)``: positive when the hinge is convex seen from
    the side the normal ``(x1 − x0) × (x2 − x0)`` points to.
    """
    e = q[1] - q[0]
    e_hat = e / torch.linalg.norm(e)

    def across(p):
        r = p - q[0]
        return r - (r @ e_hat) * e_hat

    w2, w3 = across(q[2]), across(q[3])
    return torch.atan2(e_hat @ torch.linalg.cross(w3, w2), -(w2 @ w3))


def _bending_element(q, rest_angle, weight, k):
    return k * weight * (dihedral_angle(q) - rest_angle) ** 2


def bending_energy(x, hinges, rest_angle, rest_weight, k_bend):
    """Discrete-shell bending ``k w̄ (θ − θ̄)²`` per hinge, with autograd gradient ``[H, 4, 3]`` and Hessian."""
    k = torch.as_tensor(k_bend, dtype=x.dtype, device=x.device).expand(hinges.shape[0])
    return _terms(_bending_element, x[hinges.long()], rest_angle, rest_weight, k)


def barrier(d: torch.Tensor, dhat: float) -> torch.Tensor:
    """``b(d) = −(d − d̂)² ln(d/d̂)`` below ``d̂``, else 0 (squared distances)."""
    inside = d < dhat
    safe = torch.where(inside, d, torch.full_like(d, dhat))
    return torch.where(inside, -((safe - dhat) ** 2) * torch.log(safe / dhat), torch.zeros_like(d))


def _point_segment_sq(p, a, b):
    e = b - a
    s = torch.clamp(((p - a) @ e) / (e @ e), 0.0, 1.0)
    r = p - (a + s * e)
    return r @ r


def point_triangle_sq_distance(q: torch.Tensor) -> torch.Tensor:
    """Squared distance of ``q[0]`` to triangle ``q[1:4]``: the plane projection if inside, else the edges."""
    p, t0, t1, t2 = q
    e1, e2 = t1 - t0, t2 - t0
    # least-squares plane coordinates (u, v) of p by Cramer's rule on the 2×2 Gram system (torch.linalg.solve
    # gives wrong second derivatives under vmap(hessian) in torch 2.13)
    a, b, c = e1 @ e1, e1 @ e2, e2 @ e2
    r1, r2 = (p - t0) @ e1, (p - t0) @ e2
    det = a * c - b * b
    u, v = (c * r1 - b * r2) / det, (a * r2 - b * r1) / det
    inside = (u >= 0) & (v >= 0) & (u + v <= 1)
    r = p - (t0 + u * e1 + v * e2)
    face = torch.where(inside, r @ r, torch.full_like(r[0], float("inf")))
    edges = torch.stack([_point_segment_sq(p, t0, t1), _point_segment_sq(p, t1, t2), _point_segment_sq(p, t2, t0)])
    return torch.min(torch.cat([face[None], edges]))


def edge_edge_sq_distance(q: torch.Tensor) -> torch.Tensor:
    """Squared distance of segments ``q[0]q[1]`` and ``q[2]q[3]``, minimised over both segment parameters.

    The interior stationary point of ``‖a(s) − b(t)‖²`` counts when it lies in ``(0, 1)²``; otherwise the
    minimum lies on the boundary of the parameter square: an end point against the other segment.
    """
    a0, a1, b0, b1 = q
    da, db, r = a1 - a0, b1 - b0, a0 - b0
    aa, bb, ab = da @ da, db @ db, da @ db
    det = aa * bb - ab * ab
    regular = det > 1e-12 * aa * bb
    det = torch.where(regular, det, torch.ones_like(det))
    s = (ab * (db @ r) - bb * (da @ r)) / det
    t = (aa * (db @ r) - ab * (da @ r)) / det
    w = r + s * da - t * db
    interior = regular & (s > 0) & (s < 1) & (t > 0) & (t < 1)
    line = torch.where(interior, w @ w, torch.full_like(w[0], float("inf")))
    ends = torch.stack(
        [
            _point_segment_sq(a0, b0, b1),
            _point_segment_sq(a1, b0, b1),
            _point_segment_sq(b0, a0, a1),
            _point_segment_sq(b1, a0, a1),
        ]
    )
    return torch.min(torch.cat([line[None], ends]))


def point_triangle_distance(x, pairs):
    """Squared point-triangle distances ``[P]`` with autograd gradients ``[P, 4, 3]`` and Hessians."""
    return _terms(point_triangle_sq_distance, x[pairs.long()])


def edge_edge_distance(x, pairs):
    """Squared edge-edge distances ``[Q]`` with autograd gradients ``[Q, 4, 3]`` and Hessians."""
    return _terms(edge_edge_sq_distance, x[pairs.long()])


def edge_edge_mollifier(q: torch.Tensor, eps_x: torch.Tensor) -> torch.Tensor:
    """``m(c) = −c²/ε_x² + 2c/ε_x`` for ``c = ‖ea × eb‖² < ε_x``, else 1."""
    cross = torch.linalg.cross(q[1] - q[0], q[3] - q[2])
    c = cross @ cross
    return torch.where(c < eps_x, -(c**2) / eps_x**2 + 2.0 * c / eps_x, torch.ones_like(c))


def point_triangle_barrier(x, pairs, dhat: float, stiffness: float):
    """``κ b(d)`` per point-triangle pair with autograd gradient and Hessian."""

    def energy(q):
        return stiffness * barrier(point_triangle_sq_distance(q), dhat)

    return _terms(energy, x[pairs.long()])


def edge_edge_barrier(x, pairs, eps_x, dhat: float, stiffness: float):
    """``κ m b(d)`` per edge-edge pair with autograd gradient and Hessian."""

    def energy(q, eps):
        return stiffness * edge_edge_mollifier(q, eps) * barrier(edge_edge_sq_distance(q), dhat)

    return _terms(energy, x[pairs.long()], eps_x)


def _first_coplanar_contact(q0: np.ndarray, dq: np.ndarray, touching) -> float:
    """Earliest ``t`` in ``[0, 1]`` where ``det[x1 − x0, x2 − x0, x3 − x0](t) = 0`` and ``touching(t)``."""

    def volume(t):
        q = q0 + t * dq
        return np.linalg.det(np.stack([q[1] - q[0], q[2] - q[0], q[3] - q[0]]))

    samples = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    coefficients = np.polyfit(samples, [volume(t) for t in samples], 3)
    roots = np.roots(coefficients)
    real = np.sort(roots[np.abs(roots.imag) < 1e-9].real)
    for t in real[(real >= -1e-12) & (real <= 1.0 + 1e-12)]:
        if touching(q0 + max(t, 0.0) * dq):
            return float(max(t, 0.0))
    return float("inf")


def point_triangle_first_contact(q0: np.ndarray, dq: np.ndarray, tol: float = 1e-8) -> float:
    """First time in ``[0, 1]`` the point ``q[0]`` touches triangle ``q[1:4]`` on ``q0 + t dq``; inf if never."""
    scale = max(1.0, float(np.abs(q0).max()), float(np.abs(q0 + dq).max()))

    def touching(q):
        return point_triangle_sq_distance(torch.from_numpy(q)).item() < (tol * scale) ** 2

    return _first_coplanar_contact(q0, dq, touching)


def edge_edge_first_contact(q0: np.ndarray, dq: np.ndarray, tol: float = 1e-8) -> float:
    """First time in ``[0, 1]`` segments ``q[0]q[1]`` and ``q[2]q[3]`` touch on ``q0 + t dq``; inf if never."""
    scale = max(1.0, float(np.abs(q0).max()), float(np.abs(q0 + dq).max()))

    def touching(q):
        return edge_edge_sq_distance(torch.from_numpy(q)).item() < (tol * scale) ** 2

    return _first_coplanar_contact(q0, dq, touching)


def pair_boxes_overlap(x, dx, pairs, split: int, dhat: float, parallel: float = 0.0) -> torch.Tensor:
    """Reference of :func:`kernels.contact.pair_boxes_overlap`: per-vertex boxes of the sweep, united per primitive;
    edge pairs parallel (``sin²θ < parallel``) at both ends dropped."""
    end = x if dx is None else x + dx
    lo, hi = torch.minimum(x, end), torch.maximum(x, end)
    i = pairs.long()
    a_lo, a_hi = lo[i[:, :split]].amin(1) - dhat, hi[i[:, :split]].amax(1) + dhat
    b_lo, b_hi = lo[i[:, split:]].amin(1), hi[i[:, split:]].amax(1)
    overlap = ((a_lo <= b_hi) & (b_lo <= a_hi)).all(1)
    if split == 2 and parallel > 0.0:

        def parallel_at(q):
            da, db = q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]
            cross = (torch.linalg.cross(da, db) ** 2).sum(1)
            return cross < parallel * (da * da).sum(1) * (db * db).sum(1)

        overlap &= ~(parallel_at(x[i]) & parallel_at(end[i]))
    return overlap
