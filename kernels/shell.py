"""Thin-shell energies of the garment simulator: StVK membrane and discrete-shell hinge bending, in Warp.

PhysAvatar (§3.2, Appendix A.3) simulates garments with Codim-IPC [52]: an isotropic StVK membrane and the
discrete-shell hinge bending energy [29, 102], stepped by an implicit Newton solver (Δt = 0.04 s). This module
evaluates, per triangle and per hinge, the energy, its gradient and its exact dense Hessian
(:class:`kernels.element_terms.ElementTerms`, whose conventions hold here: generic over float32 and float64,
vertex-major Hessians), plus the rest-shape quantities and material parameters they need. The contact terms of the
same solver are in :mod:`kernels.contact`, its line-search bound in :mod:`kernels.ccd`.
"""

from typing import Any, NamedTuple

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
    check_values,
    declare_float64_overloads,
    launch_rows,
    per_element,
    scalar_type,
    store_terms,
    vec3_array,
)

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = [
    "STRESS_FILTERS",
    "ClothRest",
    "bending_energy",
    "bending_energy_value",
    "hinges_from_faces",
    "membrane_energy",
    "membrane_energy_value",
    "plane_stress_lame",
    "rest_state",
]

STRESS_FILTERS = ("none", "clamp", "abs")
"""How :func:`membrane_energy` treats the stress term of its Hessians: exactly, with the stress's positive part, or
with its absolute value."""


class ClothRest(NamedTuple):
    """Rest-shape quantities of a garment mesh, computed once by :func:`rest_state`.

    Attributes:
        rest_inv: ``[F, 2, 2]`` inverse of each triangle's rest edge matrix ``D_m`` in its 2D rest frame, 1/m.
        rest_area: ``[F]`` rest area of each triangle, m².
        rest_angle: ``[H]`` rest dihedral angle of each hinge, rad.
        rest_weight: ``[H]`` discrete-shell weight ``3‖ē‖² / Ā`` of each hinge (``Ā`` the two rest areas), 1.
    """

    rest_inv: torch.Tensor
    rest_area: torch.Tensor
    rest_angle: torch.Tensor
    rest_weight: torch.Tensor


# ---------------------------------------------------------------------------------------------------------------
# Material parameters and rest state (plain torch, run once)
# ---------------------------------------------------------------------------------------------------------------


def plane_stress_lame(young: float, poisson: float, thickness: float) -> tuple[float, float]:
    """Thickness-integrated plane-stress Lamé parameters of a thin sheet.

    ``μ = E / (2 (1 + ν))`` and the plane-stress ``λ = E ν / (1 − ν²)``, both multiplied by the thickness, so
    that ``rest_area · Ψ`` (:func:`membrane_energy`) is an energy in J.

    Args:
        young: Young's modulus ``E``, Pa.
        poisson: Poisson's ratio ``ν``, in ``[0, 0.5)``.
        thickness: sheet thickness ``h``, m.

    Returns:
        ``(h μ, h λ)``, both N/m.
    """
    if young <= 0.0 or thickness <= 0.0:
        raise ValueError(f"young ({young}) and thickness ({thickness}) must be positive")
    if not 0.0 <= poisson < 0.5:
        raise ValueError(f"poisson ({poisson}) must lie in [0, 0.5) for a stable isotropic sheet")
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / (1.0 - poisson * poisson)
    return thickness * mu, thickness * lam


def hinges_from_faces(faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Interior edges of a consistently oriented triangle mesh, as bending hinges.

    Hinge ``(v0, v1, v2, v3)``: the shared edge ``v0 → v1`` as it runs in face ``(v0, v1, v2)``, so that the
    other face is ``(v1, v0, v3)``; both face normals then point to the same side as the mesh's.

    Args:
        faces: ``[F, 3]`` integer vertex indices, counter-clockwise seen from the normal side.

    Returns:
        ``(hinges [H, 4] int32, hinge_faces [H, 2] int64)``: the hinges and the faces holding ``v2`` and ``v3``.

    Raises:
        ValueError: an edge is shared by more than two faces, or two faces disagree in orientation.
    """
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.dtype.is_floating_point:
        raise ValueError(f"faces must be an integer [F, 3] tensor, got {faces.dtype} {tuple(faces.shape)}")
    f = faces.long()
    face_id = torch.arange(f.shape[0], device=f.device).repeat_interleave(3)
    tail = f.reshape(-1)
    head = f.roll(-1, dims=1).reshape(-1)
    opposite = f.roll(-2, dims=1).reshape(-1)
    n = int(f.max()) + 1 if f.numel() else 0
    key = torch.minimum(tail, head) * n + torch.maximum(tail, head)
    key, order = torch.sort(key, stable=True)
    _, counts = torch.unique_consecutive(key, return_counts=True)
    if bool((counts > 2).any()):
        raise ValueError("an edge is shared by more than two faces; bending hinges need a manifold mesh")
    starts = torch.cumsum(counts, 0) - counts
    first = order[starts[counts == 2]]
    second = order[starts[counts == 2] + 1]
    if bool((tail[first] == tail[second]).any()):
        raise ValueError("two faces sharing an edge are oriented oppositely; orient all faces consistently")
    hinges = torch.stack([tail[first], head[first], opposite[first], opposite[second]], dim=1)
    return hinges.to(torch.int32).contiguous(), torch.stack([face_id[first], face_id[second]], dim=1)


def rest_state(x_rest: torch.Tensor, faces: torch.Tensor, hinges: torch.Tensor) -> ClothRest:
    """Rest-shape quantities for :func:`membrane_energy` and :func:`bending_energy`.

    Each triangle's rest frame has its first axis along ``x1 − x0`` and its second in the triangle's plane, so
    ``D_m = [[‖e1‖, e2·t1], [0, e2·t2]]`` is upper triangular with a positive determinant (twice the area).

    Args:
        x_rest: ``[V, 3]`` rest positions, m.
        faces: ``[F, 3]`` int32 vertex indices.
        hinges: ``[H, 4]`` int32 hinges from :func:`hinges_from_faces`.

    Returns:
        :class:`ClothRest` in the dtype of ``x_rest``.
    """
    check_positions(x_rest)
    check_index(faces, 3, "faces")
    check_index(hinges, 4, "hinges")
    tri = x_rest[faces.long()]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    normal = torch.linalg.cross(e1, e2)
    double_area = torch.linalg.norm(normal, dim=1)
    if bool((double_area <= 0.0).any()):
        raise ValueError("a rest triangle has zero area; remove degenerate faces before building the rest state")
    t1 = e1 / torch.linalg.norm(e1, dim=1, keepdim=True)
    t2 = torch.linalg.cross(normal / double_area[:, None], t1)
    dm = torch.zeros(tri.shape[0], 2, 2, dtype=x_rest.dtype, device=x_rest.device)
    dm[:, 0, 0] = (e1 * t1).sum(1)
    dm[:, 0, 1] = (e2 * t1).sum(1)
    dm[:, 1, 1] = (e2 * t2).sum(1)
    angle, weight = _hinge_rest(x_rest, hinges)
    return ClothRest(torch.linalg.inv(dm).contiguous(), 0.5 * double_area, angle, weight)


# ---------------------------------------------------------------------------------------------------------------
# StVK membrane
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _stvk_density(x0: Any, x1: Any, x2: Any, dm_inv: Any, mu: Any, lam: Any):
    """Columns ``f0, f1`` of ``F``, Green strain ``e00, e01, e11``, its trace and the StVK density ``Ψ``."""
    one = type(mu)(1.0)
    half = type(mu)(0.5)
    d1 = x1 - x0
    d2 = x2 - x0
    f0 = d1 * dm_inv[0, 0] + d2 * dm_inv[1, 0]
    f1 = d1 * dm_inv[0, 1] + d2 * dm_inv[1, 1]
    e00 = half * (wp.dot(f0, f0) - one)
    e01 = half * wp.dot(f0, f1)
    e11 = half * (wp.dot(f1, f1) - one)
    tr = e00 + e11
    psi = mu * (e00 * e00 + type(mu)(2.0) * e01 * e01 + e11 * e11) + half * lam * tr * tr
    return f0, f1, e00, e01, e11, tr, psi


@wp.func
def _negative_part(s00: Any, s01: Any, s11: Any):
    """The negative part ``Σ_{λ<0} λ v vᵀ`` of the symmetric 2×2 matrix ``[[s00, s01], [s01, s11]]``, as
    ``(n00, n01, n11)``: with eigenvalues ``m ± r``, the projector onto the smaller one's eigenvector is
    ``(m + r − S) / 2r``."""
    zero = type(s00)(0.0)
    m = type(s00)(0.5) * (s00 + s11)
    h = type(s00)(0.5) * (s00 - s11)
    r = wp.sqrt(h * h + s01 * s01)
    low = m - r
    if low >= zero:
        return zero, zero, zero
    if m + r < zero:
        return s00, s01, s11
    c = low / (type(s00)(2.0) * r)  # r > 0 here: the eigenvalues have opposite signs
    return c * (m + r - s00), -c * s01, c * (m + r - s11)


@wp.func
def _stvk_membrane(x0: Any, x1: Any, x2: Any, dm_inv: Any, area: Any, mu: Any, lam: Any, stress_filter: int):
    """StVK membrane energy of one triangle with its gradient and Hessian (PhysAvatar §3.2, Codim-IPC [52]).

    ``F = D_s D_m⁻¹`` (3×2), ``E = ½(FᵀF − I)``, ``Ψ = μ‖E‖²_F + ½λ tr(E)²``, energy ``A Ψ``. Writing
    ``F = Σ_k x_k β_kᵀ`` (``β_k`` the rows of ``D_m⁻¹``, ``β_0 = −β_1 − β_2``) and ``a_k = F β_k``:
    gradient ``A P β_k`` with ``P = F S``, ``S = 2μE + λ tr(E) I``; Hessian block
    ``H_kl = A [(β_kᵀ S β_l) I + μ a_l a_kᵀ + μ (β_k·β_l) F Fᵀ + λ a_k a_lᵀ]``.

    The last three terms are ``dE : C : dE ≥ 0``; only the stress term ``(β_kᵀ S β_l) I`` can be indefinite, where
    ``S`` has a negative eigenvalue (compression). ``stress_filter`` 1 puts ``S``'s positive part in that term
    instead, 2 its absolute value: either makes the Hessian PSD (:data:`STRESS_FILTERS`).
    """
    beta1 = wp.vector(dm_inv[0, 0], dm_inv[0, 1])
    beta2 = wp.vector(dm_inv[1, 0], dm_inv[1, 1])
    beta0 = -beta1 - beta2
    f0, f1, e00, e01, e11, tr, psi = _stvk_density(x0, x1, x2, dm_inv, mu, lam)
    s00 = type(area)(2.0) * mu * e00 + lam * tr
    s01 = type(area)(2.0) * mu * e01
    s11 = type(area)(2.0) * mu * e11 + lam * tr
    # the stress of the Hessian's geometric term: S, S − S₋ or S − 2 S₋
    n00, n01, n11 = _negative_part(s00, s01, s11)
    c = type(area)(stress_filter)
    t00 = s00 - c * n00
    t01 = s01 - c * n01
    t11 = s11 - c * n11
    ffT = wp.outer(f0, f0) + wp.outer(f1, f1)
    eye = wp.identity(n=3, dtype=type(area))
    g = wp.vector(length=9, dtype=type(area))
    h = wp.matrix(shape=(9, 9), dtype=type(area))
    for k in range(3):
        bk = beta0
        if k == 1:
            bk = beta1
        elif k == 2:
            bk = beta2
        sbk = wp.vector(s00 * bk[0] + s01 * bk[1], s01 * bk[0] + s11 * bk[1])
        tbk = wp.vector(t00 * bk[0] + t01 * bk[1], t01 * bk[0] + t11 * bk[1])
        ak = f0 * bk[0] + f1 * bk[1]
        g = add_vec(g, k, area * (f0 * sbk[0] + f1 * sbk[1]))
        for l in range(3):
            bl = beta0
            if l == 1:
                bl = beta1
            elif l == 2:
                bl = beta2
            al = f0 * bl[0] + f1 * bl[1]
            block = eye * wp.dot(bl, tbk) + mu * wp.outer(al, ak) + (mu * wp.dot(bk, bl)) * ffT + lam * wp.outer(ak, al)
            h = add_block(h, k, l, area * block)
    return area * psi, g, h


@wp.kernel
def _membrane_kernel(
    x: wp.array(dtype=Any),
    faces: wp.array2d(dtype=wp.int32),
    rest_inv: wp.array(dtype=Any),
    rest_area: wp.array(dtype=Any),
    mu: wp.array(dtype=Any),
    lam: wp.array(dtype=Any),
    stress_filter: int,
    energy: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    x0, x1, x2 = x[faces[i, 0]], x[faces[i, 1]], x[faces[i, 2]]
    e, g, h = _stvk_membrane(x0, x1, x2, rest_inv[i], rest_area[i], mu[i], lam[i], stress_filter)
    store_terms(energy, grad, hess, i, e, g, h, 3)


@wp.kernel
def _membrane_value_kernel(
    x: wp.array(dtype=Any),
    faces: wp.array2d(dtype=wp.int32),
    rest_inv: wp.array(dtype=Any),
    rest_area: wp.array(dtype=Any),
    mu: wp.array(dtype=Any),
    lam: wp.array(dtype=Any),
    energy: wp.array(dtype=Any),
):
    i = wp.tid()
    f0, f1, e00, e01, e11, tr, psi = _stvk_density(
        x[faces[i, 0]], x[faces[i, 1]], x[faces[i, 2]], rest_inv[i], mu[i], lam[i]
    )
    energy[i] = rest_area[i] * psi


def membrane_energy(
    x: torch.Tensor,
    faces: torch.Tensor,
    rest_inv: torch.Tensor,
    rest_area: torch.Tensor,
    mu: torch.Tensor | float,
    lam: torch.Tensor | float,
    stress_filter: str = "none",
) -> ElementTerms:
    """StVK membrane energy of each triangle, with per-vertex gradients and the element Hessian (§3.2).

    ``Ψ = μ‖E‖²_F + ½λ tr(E)²`` with ``E = ½(FᵀF − I₂)``, ``F = D_s D_m⁻¹``; element energy ``A Ψ``. The caller
    passes ``μ`` and ``λ`` already multiplied by the sheet thickness (:func:`plane_stress_lame`), so the
    paper's membrane stiffness ``κ_s`` scales both.

    The Hessian is ``A [(β_kᵀ S β_l) I + dE : C : dE]`` per vertex pair (``S`` the second Piola–Kirchhoff stress,
    ``β_k`` the rows of ``D_m⁻¹``); the material part is PSD, the stress part wherever ``S`` is, that is unless the
    triangle is compressed. ``stress_filter`` makes every Hessian PSD in the kernel, in closed form: ``"clamp"``
    puts ``S``'s positive part in the stress term, ``"abs"`` its absolute value (the analogue of flipping negative
    eigenvalues). Each equals the exact Hessian on a triangle under tension, and neither needs an eigensolver; on the
    skirt7271 walk (14 frames) ``"abs"`` took 118 Newton iterations where the flipped eigenvalues of each 9×9 Hessian
    took 113.

    Args:
        x: ``[V, 3]`` float32 or float64 vertex positions, m.
        faces: ``[F, 3]`` int32 vertex indices.
        rest_inv: ``[F, 2, 2]`` ``D_m⁻¹`` from :func:`rest_state`, 1/m.
        rest_area: ``[F]`` rest areas, m².
        mu: ``[F]`` or scalar thickness-integrated shear modulus ``h μ``, N/m.
        lam: ``[F]`` or scalar thickness-integrated plane-stress ``h λ``, N/m.
        stress_filter: ``"none"`` (the exact Hessian), ``"clamp"`` or ``"abs"`` (:data:`STRESS_FILTERS`).

    Returns:
        :class:`ElementTerms` with ``energy [F]`` (J), ``grad [F, 3, 3]``, ``hess [F, 9, 9]``.
    """
    if stress_filter not in STRESS_FILTERS:
        raise ValueError(f"stress_filter ({stress_filter!r}) must be one of {', '.join(map(repr, STRESS_FILTERS))}")
    n, inputs = _membrane_inputs(x, faces, rest_inv, rest_area, mu, lam)
    out = allocate_terms(x, n, 3)
    launch_rows(_membrane_kernel, n, [*inputs, STRESS_FILTERS.index(stress_filter)], out)
    return ElementTerms(*out)


def membrane_energy_value(
    x: torch.Tensor,
    faces: torch.Tensor,
    rest_inv: torch.Tensor,
    rest_area: torch.Tensor,
    mu: torch.Tensor | float,
    lam: torch.Tensor | float,
) -> torch.Tensor:
    """The ``[F]`` energies of :func:`membrane_energy` alone (bit for bit the same), J: for line searches."""
    n, inputs = _membrane_inputs(x, faces, rest_inv, rest_area, mu, lam)
    energy = torch.empty(n, dtype=x.dtype, device=x.device)
    launch_rows(_membrane_value_kernel, n, inputs, [energy])
    return energy


def _membrane_inputs(x, faces, rest_inv, rest_area, mu, lam) -> tuple[int, list]:
    check_positions(x)
    check_index(faces, 3, "faces")
    n = faces.shape[0]
    rest_inv = check_values(rest_inv, x, (n, 2, 2), "rest_inv")
    rest_area = check_values(rest_area, x, (n,), "rest_area")
    mu = per_element(mu, x, n, "mu")
    lam = per_element(lam, x, n, "lam")
    return n, [
        vec3_array(x),
        faces,
        (rest_inv, wp.types.matrix((2, 2), scalar_type(x))),
        rest_area,
        mu,
        lam,
    ]


# ---------------------------------------------------------------------------------------------------------------
# Discrete-shell bending
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _dihedral_angle(x0: Any, x1: Any, x2: Any, x3: Any):
    """Signed dihedral angle of hinge ``(x0, x1 | x2, x3)``, rad, in ``(−π, π]``.

    ``θ = atan2(ê · (n₁ × n₂), n₁ · n₂)`` with ``n₁ = e × (x2 − x0)``, ``n₂ = (x3 − x0) × e``, ``e = x1 − x0``.
    ``θ = 0`` for a flat hinge; ``θ > 0`` when the wings fold away from the side the normals point to (the
    surface is convex seen from that side), ``θ < 0`` when they fold towards it.
    """
    e = x1 - x0
    n1 = wp.cross(e, x2 - x0)
    n2 = wp.cross(x3 - x0, e)
    return wp.atan2(wp.dot(wp.cross(n1, n2), e) / wp.length(e), wp.dot(n1, n2))


@wp.func
def _wing_terms(a: Any, b: Any, p: Any, g: Any, h: Any, slot: int, sign: Any):
    """Add ``sign ×`` one wing's part of ``∇θ`` and ``∇²θ`` (hinge edge ``a → b``, wing tip ``p``).

    With ``n = (b − a) × (p − a)``, ``q = ‖e‖ n / ‖n‖²`` (the tip's rotation about the edge per unit
    displacement) and ``t = (p − a)·e / ‖e‖²`` (the tip's foot on the edge), the wing adds
    ``(−(1 − t) q, −t q, q)`` to the gradient blocks of ``(a, b, p)``; the Hessian blocks are the exact
    derivatives of those, ``∂(c_α q)/∂x_β = c_α ∂q/∂x_β + q ∂c_α/∂x_βᵀ``.
    """
    one = type(sign)(1.0)
    two = type(sign)(2.0)
    e = b - a
    l2 = wp.dot(e, e)
    le = wp.sqrt(l2)
    n = wp.cross(e, p - a)
    nn = wp.dot(n, n)
    q = n * (le / nn)
    t = wp.dot(p - a, e) / l2
    coef = wp.vector(t - one, -t, one)
    eye = wp.identity(n=3, dtype=type(sign))
    # dq = (n / ‖n‖²) d‖e‖ + ‖e‖ P dn, P = (I − 2 n nᵀ / ‖n‖²) / ‖n‖²; dn/da = [p − b]×, dn/db = −[p − a]×,
    # dn/dp = [e]×; d‖e‖ = ê·(db − da).
    proj = (eye - wp.outer(n, n) * (two / nn)) * (le / nn)
    dle = wp.outer(n, e) * (one / (nn * le))
    dq_a = proj * wp.skew(p - b) - dle
    dq_b = -(proj * wp.skew(p - a)) + dle
    dq_p = proj * wp.skew(e)
    # dt/dp = e / ‖e‖², dt/db = (p − a − 2 t e) / ‖e‖², dt/da = −dt/dp − dt/db; dc = (dt, −dt, 0).
    dt_p = e / l2
    dt_b = (p - a - e * (two * t)) / l2
    dt_a = -dt_p - dt_b
    slots = wp.vec3i(0, 1, slot)
    for alpha in range(3):
        c = coef[alpha]
        g = add_vec(g, slots[alpha], q * (sign * c))
        dc = one
        if alpha == 1:
            dc = -one
        elif alpha == 2:
            dc = type(sign)(0.0)
        h = add_block(h, slots[alpha], 0, (dq_a * c + wp.outer(q, dt_a) * dc) * sign)
        h = add_block(h, slots[alpha], 1, (dq_b * c + wp.outer(q, dt_b) * dc) * sign)
        h = add_block(h, slots[alpha], slot, (dq_p * c + wp.outer(q, dt_p) * dc) * sign)
    return g, h


@wp.func
def _hinge_bending(x0: Any, x1: Any, x2: Any, x3: Any, rest_angle: Any, weight: Any, k: Any):
    """Discrete-shell bending energy of one hinge with gradient and Hessian (Grinspun et al. 2003; [29, 102]).

    ``Ψ = k w̄ (θ − θ̄)²``; ``∇Ψ = 2 k w̄ (θ − θ̄) ∇θ``; ``∇²Ψ = 2 k w̄ (∇θ ∇θᵀ + (θ − θ̄) ∇²θ)`` (exact).
    ``∇θ`` is the closed form from the edge and the wing normals (Bridson et al. 2003, Tamstorf and Grinspun
    2013): the tip gradients are ``∓‖e‖ n / ‖n‖²``.
    """
    theta = _dihedral_angle(x0, x1, x2, x3)
    g = wp.vector(length=12, dtype=type(k))
    h = wp.matrix(shape=(12, 12), dtype=type(k))
    g, h = _wing_terms(x0, x1, x2, g, h, 2, -type(k)(1.0))
    g, h = _wing_terms(x0, x1, x3, g, h, 3, type(k)(1.0))
    h = (h + wp.transpose(h)) * type(k)(0.5)
    c = type(k)(2.0) * k * weight
    dtheta = theta - rest_angle
    return k * weight * dtheta * dtheta, g * (c * dtheta), (wp.outer(g, g) + h * dtheta) * c


@wp.kernel
def _bending_kernel(
    x: wp.array(dtype=Any),
    hinges: wp.array2d(dtype=wp.int32),
    rest_angle: wp.array(dtype=Any),
    rest_weight: wp.array(dtype=Any),
    k_bend: wp.array(dtype=Any),
    energy: wp.array(dtype=Any),
    grad: wp.array3d(dtype=Any),
    hess: wp.array3d(dtype=Any),
):
    i = wp.tid()
    e, g, h = _hinge_bending(
        x[hinges[i, 0]], x[hinges[i, 1]], x[hinges[i, 2]], x[hinges[i, 3]], rest_angle[i], rest_weight[i], k_bend[i]
    )
    store_terms(energy, grad, hess, i, e, g, h, 4)


@wp.kernel
def _bending_value_kernel(
    x: wp.array(dtype=Any),
    hinges: wp.array2d(dtype=wp.int32),
    rest_angle: wp.array(dtype=Any),
    rest_weight: wp.array(dtype=Any),
    k_bend: wp.array(dtype=Any),
    energy: wp.array(dtype=Any),
):
    i = wp.tid()
    theta = _dihedral_angle(x[hinges[i, 0]], x[hinges[i, 1]], x[hinges[i, 2]], x[hinges[i, 3]])
    dtheta = theta - rest_angle[i]
    energy[i] = k_bend[i] * rest_weight[i] * dtheta * dtheta


@wp.kernel
def _hinge_rest_kernel(
    x: wp.array(dtype=Any),
    hinges: wp.array2d(dtype=wp.int32),
    angle: wp.array(dtype=Any),
    weight: wp.array(dtype=Any),
):
    i = wp.tid()
    x0 = x[hinges[i, 0]]
    x1 = x[hinges[i, 1]]
    x2 = x[hinges[i, 2]]
    x3 = x[hinges[i, 3]]
    angle[i] = _dihedral_angle(x0, x1, x2, x3)
    e = x1 - x0
    area = (wp.length(wp.cross(e, x2 - x0)) + wp.length(wp.cross(x3 - x0, e))) * type(angle[i])(0.5)
    weight[i] = type(area)(3.0) * wp.dot(e, e) / area


def _hinge_rest(x_rest: torch.Tensor, hinges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    angle = torch.empty(hinges.shape[0], dtype=x_rest.dtype, device=x_rest.device)
    weight = torch.empty_like(angle)
    if hinges.shape[0]:
        backend.launch(_hinge_rest_kernel, hinges.shape[0], [vec3_array(x_rest), hinges, angle, weight])
    return angle, weight


def bending_energy(
    x: torch.Tensor,
    hinges: torch.Tensor,
    rest_angle: torch.Tensor,
    rest_weight: torch.Tensor,
    k_bend: torch.Tensor | float,
) -> ElementTerms:
    """Discrete-shell hinge bending energy, with gradients and exact Hessians (§3.2, [29, 102]).

    ``Ψ = k w̄ (θ − θ̄)²`` with ``θ`` the signed dihedral angle (0 flat, positive when the hinge is convex seen
    from the normal side, in ``(−π, π]``) and ``w̄ = 3‖ē‖²/Ā``. The Hessian is the exact one,
    ``2 k w̄ (∇θ ∇θᵀ + (θ − θ̄) ∇²θ)``; it is indefinite away from the rest angle, so a Newton solver makes it
    PSD (:func:`kernels.element_terms.project_psd`).

    Args:
        x: ``[V, 3]`` float32 or float64 positions, m.
        hinges: ``[H, 4]`` int32 hinges ``(v0, v1, v2, v3)`` from :func:`hinges_from_faces`.
        rest_angle: ``[H]`` rest angles ``θ̄``, rad.
        rest_weight: ``[H]`` weights ``w̄ = 3‖ē‖²/Ā``, 1.
        k_bend: ``[H]`` or scalar bending stiffness ``k`` (the paper's ``κ_b`` in the caller's scaling), J.

    Returns:
        :class:`ElementTerms` with ``energy [H]`` (J), ``grad [H, 4, 3]``, ``hess [H, 12, 12]``.
    """
    n, inputs = _bending_inputs(x, hinges, rest_angle, rest_weight, k_bend)
    out = allocate_terms(x, n, 4)
    launch_rows(_bending_kernel, n, inputs, out)
    return ElementTerms(*out)


def bending_energy_value(
    x: torch.Tensor,
    hinges: torch.Tensor,
    rest_angle: torch.Tensor,
    rest_weight: torch.Tensor,
    k_bend: torch.Tensor | float,
) -> torch.Tensor:
    """The ``[H]`` energies of :func:`bending_energy` alone (bit for bit the same), J: for line searches."""
    n, inputs = _bending_inputs(x, hinges, rest_angle, rest_weight, k_bend)
    energy = torch.empty(n, dtype=x.dtype, device=x.device)
    launch_rows(_bending_value_kernel, n, inputs, [energy])
    return energy


def _bending_inputs(x, hinges, rest_angle, rest_weight, k_bend) -> tuple[int, list]:
    check_positions(x)
    check_index(hinges, 4, "hinges")
    n = hinges.shape[0]
    rest_angle = check_values(rest_angle, x, (n,), "rest_angle")
    rest_weight = check_values(rest_weight, x, (n,), "rest_weight")
    k_bend = per_element(k_bend, x, n, "k_bend")
    return n, [
        vec3_array(x),
        hinges,
        rest_angle,
        rest_weight,
        k_bend,
    ]


declare_float64_overloads(globals())
