"""Cloth energies of the garment simulator: StVK membrane, discrete-shell bending, IPC contact, additive CCD.

PhysAvatar (§3.2, Appendix A.3) simulates garments with Codim-IPC [52]: an isotropic StVK membrane, the
discrete-shell hinge bending energy [29, 102] and the IPC log-barrier contact potential, stepped by an
implicit Newton solver (Δt = 0.04 s, contact distance d̂ = 1 mm). This module evaluates, per element, the
energy, its gradient and its dense Hessian, which that solver scatters into a sparse matrix, plus the additive
continuous collision detection (ACCD, Li et al. 2021) that bounds its line search.

Conventions:

* Every per-element Hessian is exact (closed form, no Gauss-Newton truncation); :func:`project_psd` replaces it
  by its nearest positive semi-definite matrix (eigenvalues clamped at zero). The projection runs after the
  kernel as one batched eigen-decomposition: cuSOLVER's batched Jacobi solver on CUDA (:mod:`kernels.cusolver`,
  about 3× faster than ``torch.linalg.eigh`` there, and it does not wait for the device), ``torch.linalg.eigh``
  (LAPACK) on the CPU. The projection costs several times the kernel (``docs/benchmarks.md``); a per-thread
  Jacobi eigensolver in Warp is slower on both devices (:mod:`kernels.assembly`); the solver skips projection
  where the Hessian is known PSD (barrier pairs far from contact have zero Hessians).
* Squared distances are what IPC differentiates: ``d`` below is always a squared distance, ``d̂²`` the squared
  activation distance.
* Kernels are generic over the scalar type: ``x`` in float32 runs float32 kernels (the default, for GPU
  speed), ``x`` in float64 runs the same kernels in float64 (used by the tests for closed-form checks, and by
  callers that want contact distances of 1 mm resolved on coordinates of 1 m: float32 keeps about 1e-7 m).
* Distance types use the numbering of the IPC Toolkit (``P_T0``…``P_T`` = 0…6, ``EA0_EB0``…``EA_EB`` = 0…8).
"""

import math
from typing import Any, NamedTuple

import torch
import warp as wp

from kernels import backend, cusolver

# Every derivative here is written out in closed form; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False})

__all__ = [
    "EDGE_EDGE_TYPES",
    "POINT_TRIANGLE_TYPES",
    "STRESS_FILTERS",
    "ClothRest",
    "ElementTerms",
    "barrier",
    "bending_energy",
    "bending_energy_value",
    "contact_energy",
    "contact_energy_value",
    "edge_edge_ccd",
    "edge_edge_distance",
    "edge_edge_distance_value",
    "edge_edge_mollifier_threshold",
    "hinges_from_faces",
    "membrane_energy",
    "membrane_energy_value",
    "pair_boxes_overlap",
    "plane_stress_lame",
    "point_triangle_ccd",
    "point_triangle_distance",
    "point_triangle_distance_value",
    "project_psd",
    "rest_state",
]

POINT_TRIANGLE_TYPES = ("P_T0", "P_T1", "P_T2", "P_E0", "P_E1", "P_E2", "P_T")
"""Closest-feature types of a point-triangle pair; ``P_E0`` is edge t0-t1, ``P_E1`` t1-t2, ``P_E2`` t2-t0."""

EDGE_EDGE_TYPES = ("EA0_EB0", "EA0_EB1", "EA1_EB0", "EA1_EB1", "EA_EB0", "EA_EB1", "EA0_EB", "EA1_EB", "EA_EB")
"""Closest-feature types of an edge-edge pair (``EA_EB0``: vertex eb0 against edge a, ``EA_EB``: line-line)."""

STRESS_FILTERS = ("none", "clamp", "abs")
"""How :func:`membrane_energy` treats the stress term of its Hessians: exactly, with the stress's positive part, or
with its absolute value."""


class ElementTerms(NamedTuple):
    """Per-element energy, gradient and Hessian.

    Attributes:
        energy: ``[N]`` energy of each element, J.
        grad: ``[N, k, 3]`` gradient with respect to the element's ``k`` vertices, N (J/m).
        hess: ``[N, 3k, 3k]`` Hessian, N/m, rows and columns ordered vertex-major (``3 * vertex + axis``).
    """

    energy: torch.Tensor
    grad: torch.Tensor
    hess: torch.Tensor


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
    _check_positions(x_rest)
    _check_index(faces, 3, "faces")
    _check_index(hinges, 4, "hinges")
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


# matrices per batched eigen-decomposition: float64 12×12 batches of 10⁵ raised CUSOLVER_STATUS_INTERNAL_ERROR on an
# H100 (the ~10⁵ hinges of a 224² sheet), so larger batches are split
_EIGH_BATCH = 1 << 15


def project_psd(hess: torch.Tensor, absolute: bool = False) -> torch.Tensor:
    """Positive semi-definite stand-ins for a batch of symmetric matrices.

    Args:
        hess: ``[N, n, n]`` symmetric matrices.
        absolute: flip negative eigenvalues instead of clamping them (Chen et al. 2024, "Stabler Neo-Hookean
            simulation: absolute eigenvalue filtering for projected Newton"): the Newton direction then keeps
            the curvature of buckling modes instead of treating them as flat, which takes projected Newton to
            convergence in fewer iterations on compressed cloth.

    Returns:
        ``[N, n, n]``: ``Q max(Λ, 0) Qᵀ`` of each eigen-decomposition ``Q Λ Qᵀ`` (the nearest PSD matrix in the
        Frobenius norm), or ``Q |Λ| Qᵀ`` with ``absolute``. The decompositions are cuSOLVER's batched Jacobi
        (:func:`kernels.cusolver.eigh`) on CUDA where it loads, ``torch.linalg.eigh`` elsewhere.
    """
    if hess.shape[0] > _EIGH_BATCH:  # cuSOLVER's batched eigensolver fails on very large batches
        return torch.cat([project_psd(part, absolute) for part in hess.split(_EIGH_BATCH)])
    if hess.shape[0] == 0:
        return hess.clone()
    if hess.device.type == "cuda" and hess.shape[-1] <= cusolver.MAX_SIZE and cusolver.available():
        eigval, eigvec, _ = cusolver.eigh(hess)  # batched Jacobi: 3× faster, and no read from the device
    else:
        eigval, eigvec = torch.linalg.eigh(hess)
    eigval = eigval.abs() if absolute else eigval.clamp_min(0.0)
    return (eigvec * eigval.unsqueeze(-2)) @ eigvec.transpose(-1, -2)


# ---------------------------------------------------------------------------------------------------------------
# Small generic building blocks
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _add_block(h: Any, row: int, col: int, m: Any):
    """``h[3 row : 3 row + 3, 3 col : 3 col + 3] += m`` for a square matrix ``h``."""
    for i in range(3):
        for j in range(3):
            h[3 * row + i, 3 * col + j] = h[3 * row + i, 3 * col + j] + m[i, j]
    return h


@wp.func
def _block(h: Any, row: int, col: int):
    """The 3×3 block ``h[3 row : 3 row + 3, 3 col : 3 col + 3]``."""
    return wp.matrix_from_rows(
        wp.vector(h[3 * row, 3 * col], h[3 * row, 3 * col + 1], h[3 * row, 3 * col + 2]),
        wp.vector(h[3 * row + 1, 3 * col], h[3 * row + 1, 3 * col + 1], h[3 * row + 1, 3 * col + 2]),
        wp.vector(h[3 * row + 2, 3 * col], h[3 * row + 2, 3 * col + 1], h[3 * row + 2, 3 * col + 2]),
    )


@wp.func
def _add_vec(g: Any, k: int, v: Any):
    """``g[3k : 3k + 3] += v`` for a flat vector ``g``."""
    for i in range(3):
        g[3 * k + i] = g[3 * k + i] + v[i]
    return g


@wp.func
def _store(energy: Any, grad: Any, hess: Any, i: int, e: Any, g: Any, h: Any, nv: int):
    """Write one element's energy, ``[nv, 3]`` gradient and ``[3 nv, 3 nv]`` Hessian to row ``i``."""
    energy[i] = e
    for a in range(3 * nv):
        grad[i, a // 3, a % 3] = g[a]
        for b in range(3 * nv):
            hess[i, a, b] = h[a, b]


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
        g = _add_vec(g, k, area * (f0 * sbk[0] + f1 * sbk[1]))
        for l in range(3):
            bl = beta0
            if l == 1:
                bl = beta1
            elif l == 2:
                bl = beta2
            al = f0 * bl[0] + f1 * bl[1]
            block = eye * wp.dot(bl, tbk) + mu * wp.outer(al, ak) + (mu * wp.dot(bk, bl)) * ffT + lam * wp.outer(ak, al)
            h = _add_block(h, k, l, area * block)
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
    _store(energy, grad, hess, i, e, g, h, 3)


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
    out = _allocate(x, n, 3)
    _launch(_membrane_kernel, n, [*inputs, STRESS_FILTERS.index(stress_filter)], out)
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
    _launch(_membrane_value_kernel, n, inputs, [energy])
    return energy


def _membrane_inputs(x, faces, rest_inv, rest_area, mu, lam) -> tuple[int, list]:
    _check_positions(x)
    _check_index(faces, 3, "faces")
    n = faces.shape[0]
    rest_inv = _check_values(rest_inv, x, (n, 2, 2), "rest_inv")
    rest_area = _check_values(rest_area, x, (n,), "rest_area")
    mu = _per_element(mu, x, n, "mu")
    lam = _per_element(lam, x, n, "lam")
    return n, [
        _vec3(x),
        faces,
        (rest_inv, wp.types.matrix((2, 2), _scalar(x))),
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
        g = _add_vec(g, slots[alpha], q * (sign * c))
        dc = one
        if alpha == 1:
            dc = -one
        elif alpha == 2:
            dc = type(sign)(0.0)
        h = _add_block(h, slots[alpha], 0, (dq_a * c + wp.outer(q, dt_a) * dc) * sign)
        h = _add_block(h, slots[alpha], 1, (dq_b * c + wp.outer(q, dt_b) * dc) * sign)
        h = _add_block(h, slots[alpha], slot, (dq_p * c + wp.outer(q, dt_p) * dc) * sign)
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
    _store(energy, grad, hess, i, e, g, h, 4)


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
        backend.launch(_hinge_rest_kernel, hinges.shape[0], [_vec3(x_rest), hinges, angle, weight])
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
    PSD (:func:`project_psd`).

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
    out = _allocate(x, n, 4)
    _launch(_bending_kernel, n, inputs, out)
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
    _launch(_bending_value_kernel, n, inputs, [energy])
    return energy


def _bending_inputs(x, hinges, rest_angle, rest_weight, k_bend) -> tuple[int, list]:
    _check_positions(x)
    _check_index(hinges, 4, "hinges")
    n = hinges.shape[0]
    rest_angle = _check_values(rest_angle, x, (n,), "rest_angle")
    rest_weight = _check_values(rest_weight, x, (n,), "rest_weight")
    k_bend = _per_element(k_bend, x, n, "k_bend")
    return n, [
        _vec3(x),
        hinges,
        rest_angle,
        rest_weight,
        k_bend,
    ]


# ---------------------------------------------------------------------------------------------------------------
# IPC barrier
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _barrier(d: Any, dhat: Any):
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
    v, v1, v2 = _barrier(d[i], dhat)
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
    _check_dhat(dhat)
    d = d.contiguous()
    out = [torch.empty_like(d) for _ in range(3)]
    if d.numel():
        backend.launch(_barrier_kernel, d.numel(), [d, _scalar(d)(dhat), *out])
    return tuple(out)


# ---------------------------------------------------------------------------------------------------------------
# Squared distances by closest-feature type, with gradients and Hessians
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _point_point(w: Any):
    """``d = ‖w‖²``, ``w = p − q``: gradient ``2w``, Hessian ``2I``."""
    zero = w * type(w[0])(0.0)
    h = wp.matrix(shape=(9, 9), dtype=type(w[0]))
    h = _add_block(h, 0, 0, wp.identity(n=3, dtype=type(w[0])) * type(w[0])(2.0))
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
    h = _add_block(h, 0, 0, huu)
    h = _add_block(h, 0, 1, hue)
    h = _add_block(h, 1, 0, wp.transpose(hue))
    h = _add_block(h, 1, 1, hee)
    return wp.dot(c, c) / l, wp.matrix_from_rows(gu, ge, gu * type(u[0])(0.0)), h


@wp.func
def _cross_chain(e1: Any, e2: Any, g_n: Any, h_nn: Any, h: Any, r1: int, r2: int):
    """Chain a function of ``n = e1 × e2`` to ``(e1, e2)``: returns the gradients and adds the Hessian blocks.

    ``∂n/∂e1 = −[e2]×``, ``∂n/∂e2 = [e1]×``; the bilinear term ``g·(δe1 × δe2)`` adds ``−[g]×`` to the
    ``(e1, e2)`` block.
    """
    j1 = -wp.skew(e2)
    j2 = wp.skew(e1)
    h = _add_block(h, r1, r1, wp.transpose(j1) * h_nn * j1)
    h = _add_block(h, r2, r2, wp.transpose(j2) * h_nn * j2)
    cross = wp.transpose(j1) * h_nn * j2 - wp.skew(g_n)
    h = _add_block(h, r1, r2, cross)
    h = _add_block(h, r2, r1, wp.transpose(cross))
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
    h = _add_block(h, 0, 0, h_vv)
    hv1 = h_vn * (-wp.skew(e2))
    hv2 = h_vn * wp.skew(e1)
    h = _add_block(h, 0, 1, hv1)
    h = _add_block(h, 0, 2, hv2)
    h = _add_block(h, 1, 0, wp.transpose(hv1))
    h = _add_block(h, 2, 0, wp.transpose(hv2))
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
        g = _add_vec(g, plus[a], ga)
        g = _add_vec(g, minus[a], -ga)
        for b in range(rows):
            m = _block(hy, a, b)
            h = _add_block(h, plus[a], plus[b], m)
            h = _add_block(h, plus[a], minus[b], -m)
            h = _add_block(h, minus[a], plus[b], -m)
            h = _add_block(h, minus[a], minus[b], m)
    return g, h


@wp.func
def _point_triangle_type(p: Any, t0: Any, t1: Any, t2: Any):
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
def _point_triangle_terms(p: Any, t0: Any, t1: Any, t2: Any):
    """Squared point-triangle distance, its type, and its gradient and Hessian over ``(p, t0, t1, t2)``."""
    kind = _point_triangle_type(p, t0, t1, t2)
    plus = wp.vec3i(0, 2, 3)
    minus = wp.vec3i(1, 1, 1)
    rows = 3
    d = p[0] * type(p[0])(0.0)
    gy = wp.outer(p, p) * d
    hy = wp.matrix(shape=(9, 9), dtype=type(d))
    if kind <= 2:
        minus = wp.vec3i(kind + 1, 0, 0)
        rows = 1
        d, gy, hy = _point_point(p - _corner(t0, t1, t2, kind))
    elif kind <= 5:
        a = kind - 3
        b = (a + 1) % 3
        plus = wp.vec3i(0, b + 1, 0)
        minus = wp.vec3i(a + 1, a + 1, 0)
        rows = 2
        ea = _corner(t0, t1, t2, a)
        d, gy, hy = _point_edge(p - ea, _corner(t0, t1, t2, b) - ea)
    else:
        d, gy, hy = _point_plane(p - t0, t1 - t0, t2 - t0)
    g, h = _scatter(gy, hy, plus, minus, rows)
    return kind, d, g, h


@wp.func
def _corner(t0: Any, t1: Any, t2: Any, k: int):
    c = t0
    if k == 1:
        c = t1
    elif k == 2:
        c = t2
    return c


@wp.func
def _point_triangle_value(p: Any, t0: Any, t1: Any, t2: Any):
    """Squared point-triangle distance only (CCD, energy values), bit for bit that of :func:`_point_triangle_terms`."""
    kind = _point_triangle_type(p, t0, t1, t2)
    d = type(p[0])(0.0)
    if kind <= 2:
        w = p - _corner(t0, t1, t2, kind)
        d = wp.dot(w, w)
    elif kind <= 5:
        ea = _corner(t0, t1, t2, kind - 3)
        e = _corner(t0, t1, t2, (kind - 2) % 3) - ea
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
def _line_line_gram(ea0: Any, ea1: Any, eb0: Any, eb1: Any):
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
    ``a e − b²`` (:func:`_line_line_gram`) cancels to rounding noise of size ``ε a e``: for exactly parallel,
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
def _edge_edge_type(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
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
def _edge_edge_terms(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
    """Squared edge-edge distance, its type, and its gradient and Hessian over ``(ea0, ea1, eb0, eb1)``."""
    kind = _edge_edge_type(ea0, ea1, eb0, eb1, parallel_tol)
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
        d, gy, hy = _point_point(_pick(ea0, ea1, eb0, eb1, i) - _pick(ea0, ea1, eb0, eb1, j))
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
        xb = _pick(ea0, ea1, eb0, eb1, base)
        d, gy, hy = _point_edge(_pick(ea0, ea1, eb0, eb1, pt) - xb, _pick(ea0, ea1, eb0, eb1, tip) - xb)
    else:
        d, gy, hy = _point_plane(eb0 - ea0, ea1 - ea0, eb1 - eb0)
    g, h = _scatter(gy, hy, plus, minus, rows)
    return kind, d, g, h


@wp.func
def _pick(x0: Any, x1: Any, x2: Any, x3: Any, k: int):
    c = x0
    if k == 1:
        c = x1
    elif k == 2:
        c = x2
    elif k == 3:
        c = x3
    return c


@wp.func
def _edge_edge_value(ea0: Any, ea1: Any, eb0: Any, eb1: Any, parallel_tol: Any):
    """Squared edge-edge distance only (CCD, energy values), bit for bit that of :func:`_edge_edge_terms`."""
    kind = _edge_edge_type(ea0, ea1, eb0, eb1, parallel_tol)
    d = type(parallel_tol)(0.0)
    if kind <= 3:
        w = _pick(ea0, ea1, eb0, eb1, kind // 2) - _pick(ea0, ea1, eb0, eb1, kind % 2 + 2)
        d = wp.dot(w, w)
    elif kind <= 7:
        pt = kind - 2
        base = 0
        if kind >= 6:
            pt = kind - 6
            base = 2
        xb = _pick(ea0, ea1, eb0, eb1, base)
        e = _pick(ea0, ea1, eb0, eb1, base + 1) - xb
        c = wp.cross(_pick(ea0, ea1, eb0, eb1, pt) - xb, e)
        d = wp.dot(c, c) / wp.dot(e, e)
    else:
        n = wp.cross(ea1 - ea0, eb1 - eb0)
        r = wp.dot(eb0 - ea0, n)
        d = r * (r / wp.dot(n, n))  # rounded as _point_plane rounds it
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
    k, d, g, h = _point_triangle_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    kind[i] = k
    _store(dist, grad, hess, i, d, g, h, 4)


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
    k, d, g, h = _edge_edge_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]], parallel_tol)
    kind[i] = k
    _store(dist, grad, hess, i, d, g, h, 4)


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
    _check_positions(x)
    _check_index(pairs, 4, "pairs")
    out = _allocate(x, pairs.shape[0], 4)
    kind = torch.empty(pairs.shape[0], dtype=torch.int32, device=x.device)
    if pairs.shape[0]:
        backend.launch(_point_triangle_distance_kernel, pairs.shape[0], [_vec3(x), pairs, kind, *out])
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
    _check_positions(x)
    _check_index(pairs, 4, "pairs")
    out = _allocate(x, pairs.shape[0], 4)
    kind = torch.empty(pairs.shape[0], dtype=torch.int32, device=x.device)
    if pairs.shape[0]:
        backend.launch(_edge_edge_distance_kernel, pairs.shape[0], [_vec3(x), pairs, _parallel_tol(x), kind, *out])
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
    dist[i] = _pair_distance(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]], edge_edge, parallel_tol)


def point_triangle_distance_value(x: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """The ``[P]`` squared distances of :func:`point_triangle_distance` alone, m², without derivatives."""
    return _distance_value(x, pairs, 0)


def edge_edge_distance_value(x: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """The ``[Q]`` squared distances of :func:`edge_edge_distance` alone, m², without derivatives."""
    return _distance_value(x, pairs, 1)


def _distance_value(x: torch.Tensor, pairs: torch.Tensor, edge_edge: int) -> torch.Tensor:
    _check_positions(x)
    _check_index(pairs, 4, "pairs")
    dist = torch.empty(pairs.shape[0], dtype=x.dtype, device=x.device)
    _launch(_distance_value_kernel, pairs.shape[0], [_vec3(x), pairs, edge_edge, _parallel_tol(x)], [dist])
    return dist


# ---------------------------------------------------------------------------------------------------------------
# Contact potential over pair lists
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _mollifier(ea0: Any, ea1: Any, eb0: Any, eb1: Any, eps_x: Any):
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
    kind, d, gd, hd = _point_triangle_terms(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    b, b1, b2 = _barrier(d, dhat)
    # κ b(d(x)): ∇ = κ b′ ∇d, ∇² = κ (b″ ∇d ∇dᵀ + b′ ∇²d)
    h = (wp.outer(gd, gd) * b2 + hd * b1) * stiffness
    _store(energy, grad, hess, i, stiffness * b, gd * (stiffness * b1), h, 4)


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
    kind, d, gd, hd = _edge_edge_terms(ea0, ea1, eb0, eb1, parallel_tol)
    b, b1, b2 = _barrier(d, dhat)
    m, gm, hm = _mollifier(ea0, ea1, eb0, eb1, eps_x[i])
    # κ m b: ∇ = κ (m ∇b + b ∇m), ∇² = κ (m ∇²b + ∇m ∇bᵀ + ∇b ∇mᵀ + b ∇²m)
    gb = gd * b1
    hb = wp.outer(gd, gd) * b2 + hd * b1
    g = (gb * m + gm * b) * stiffness
    h = (hb * m + wp.outer(gm, gb) + wp.outer(gb, gm) + hm * b) * stiffness
    _store(energy, grad, hess, i, stiffness * m * b, g, h, 4)


@wp.func
def _mollifier_value(ea0: Any, ea1: Any, eb0: Any, eb1: Any, eps_x: Any):
    """The mollifier of :func:`_mollifier` alone."""
    m = type(eps_x)(1.0)
    n = wp.cross(ea1 - ea0, eb1 - eb0)
    c = wp.dot(n, n)
    if c < eps_x:
        q = c / eps_x
        m = (type(eps_x)(2.0) - q) * q
    return m


@wp.kernel
def _point_triangle_barrier_value_kernel(
    x: wp.array(dtype=Any),
    pairs: wp.array2d(dtype=wp.int32),
    dhat: Any,
    stiffness: Any,
    energy: wp.array(dtype=Any),
):
    i = wp.tid()
    d = _point_triangle_value(x[pairs[i, 0]], x[pairs[i, 1]], x[pairs[i, 2]], x[pairs[i, 3]])
    b, b1, b2 = _barrier(d, dhat)
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
    b, b1, b2 = _barrier(_edge_edge_value(ea0, ea1, eb0, eb1, parallel_tol), dhat)
    energy[i] = stiffness * _mollifier_value(ea0, ea1, eb0, eb1, eps_x[i]) * b


def edge_edge_mollifier_threshold(x_rest: torch.Tensor, ee_pairs: torch.Tensor) -> torch.Tensor:
    """Mollifier threshold ``ε_x = 10⁻³ ‖ēa‖² ‖ēb‖²`` of each edge-edge pair from rest lengths (Li et al. 2020).

    Args:
        x_rest: ``[V, 3]`` rest positions, m.
        ee_pairs: ``[Q, 4]`` int32 ``(ea0, ea1, eb0, eb1)``.

    Returns:
        ``[Q]`` thresholds, m⁴.
    """
    _check_positions(x_rest)
    _check_index(ee_pairs, 4, "ee_pairs")
    p = x_rest[ee_pairs.long()]
    la = ((p[:, 1] - p[:, 0]) ** 2).sum(1)
    lb = ((p[:, 3] - p[:, 2]) ** 2).sum(1)
    return 1e-3 * la * lb


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
    threshold ``ε_x`` (:func:`edge_edge_mollifier_threshold`). ``d`` is the squared distance of the pair's
    closest features (:func:`point_triangle_distance`, :func:`edge_edge_distance`); pairs at ``d ≥ d̂²`` give
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
    pt = _allocate(x, pt_pairs.shape[0], 4)
    ee = _allocate(x, ee_pairs.shape[0], 4)
    _launch(_point_triangle_barrier_kernel, pt_pairs.shape[0], pt_inputs, pt)
    _launch(_edge_edge_barrier_kernel, ee_pairs.shape[0], ee_inputs, ee)
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
    _launch(_point_triangle_barrier_value_kernel, pt_pairs.shape[0], pt_inputs, [pt])
    _launch(_edge_edge_barrier_value_kernel, ee_pairs.shape[0], ee_inputs, [ee])
    return pt, ee


def _contact_inputs(x, pt_pairs, ee_pairs, ee_eps_x, dhat, stiffness) -> tuple[list, list]:
    _check_positions(x)
    _check_index(pt_pairs, 4, "pt_pairs")
    _check_index(ee_pairs, 4, "ee_pairs")
    ee_eps_x = _check_values(ee_eps_x, x, (ee_pairs.shape[0],), "ee_eps_x")
    _check_dhat(dhat)
    scalar = _scalar(x)
    points = _vec3(x)
    return (
        [points, pt_pairs, scalar(dhat), scalar(stiffness)],
        [
            points,
            ee_pairs,
            ee_eps_x,
            scalar(dhat),
            scalar(stiffness),
            _parallel_tol(x),
        ],
    )


# ---------------------------------------------------------------------------------------------------------------
# Additive CCD
# ---------------------------------------------------------------------------------------------------------------


@wp.func
def _pair_distance(x0: Any, x1: Any, x2: Any, x3: Any, edge_edge: int, parallel_tol: Any):
    d = type(parallel_tol)(0.0)
    if edge_edge == 0:
        d = _point_triangle_value(x0, x1, x2, x3)
    else:
        d = _edge_edge_value(x0, x1, x2, x3, parallel_tol)
    return d


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
        d = _pair_distance(x0, x1, x2, x3, edge_edge, parallel_tol)
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
                d = _pair_distance(x0 + p0 * s, x1 + p1 * s, x2 + p2 * s, x3 + p3 * s, edge_edge, parallel_tol)
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
    _check_positions(x)
    _check_values(dx, x, tuple(x.shape), "dx")
    _check_index(pairs, 4, "pairs")
    if not 0.0 < eta < 1.0:
        raise ValueError(f"eta ({eta}) must lie in (0, 1); the paper uses 0.1")
    if min_distance < 0.0:
        raise ValueError(f"min_distance ({min_distance}) must be non-negative")
    if max_iterations < 1:
        raise ValueError(f"max_iterations ({max_iterations}) must be at least 1")
    toi = torch.empty(pairs.shape[0], dtype=x.dtype, device=x.device)
    if pairs.shape[0]:
        scalar = _scalar(x)
        args = [_vec3(x), _vec3(dx.contiguous()), pairs, edge_edge, scalar(min_distance), scalar(eta)]
        backend.launch(_ccd_kernel, pairs.shape[0], [*args, max_iterations, _parallel_tol(x), toi])
    return toi


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
    _check_positions(x)
    _check_index(pairs, 4, "pairs")
    if split not in (1, 2):
        raise ValueError(f"split ({split}) must be 1 (point–triangle pairs) or 2 (edge–edge pairs)")
    if not 0.0 <= parallel < 1.0:
        raise ValueError(f"parallel ({parallel}) must be a sin² in [0, 1)")
    dx = torch.zeros_like(x) if dx is None else _check_values(dx, x, tuple(x.shape), "dx")
    overlap = torch.empty(pairs.shape[0], dtype=torch.uint8, device=x.device)
    if pairs.shape[0]:
        scalar = _scalar(x)
        args = [_vec3(x), _vec3(dx), pairs, split, scalar(dhat), scalar(parallel), overlap]
        backend.launch(_pair_boxes_kernel, pairs.shape[0], args)
    return overlap.view(torch.bool)


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


# ---------------------------------------------------------------------------------------------------------------
# Argument checks and plumbing
# ---------------------------------------------------------------------------------------------------------------


def _scalar(x: torch.Tensor):
    return wp.float64 if x.dtype == torch.float64 else wp.float32


def _vec3(x: torch.Tensor) -> tuple:
    """``x [N, 3]`` as a :func:`kernels.backend.launch` argument: an array of 3-vectors."""
    return x, wp.vec3d if x.dtype == torch.float64 else wp.vec3f


def _parallel_tol(x: torch.Tensor):
    """``sin²`` below which edges count as parallel: the dtype's machine epsilon."""
    return _scalar(x)(torch.finfo(x.dtype).eps)


def _check_positions(x: torch.Tensor) -> None:
    if x.dtype not in (torch.float32, torch.float64) or x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"positions must be a float32 or float64 [V, 3] tensor, got {x.dtype} {tuple(x.shape)}")
    if not x.is_contiguous():
        raise ValueError("positions are not contiguous; call .contiguous() first")


def _check_index(index: torch.Tensor, width: int, what: str) -> None:
    if index.dtype != torch.int32 or index.dim() != 2 or index.shape[1] != width:
        raise ValueError(
            f"{what} must be an int32 [N, {width}] tensor, got {index.dtype} {tuple(index.shape)}; "
            f"convert with .to(torch.int32)"
        )
    if not index.is_contiguous():
        raise ValueError(f"{what} is not contiguous; call .contiguous() first")


def _check_values(t: torch.Tensor, x: torch.Tensor, shape: tuple, what: str) -> torch.Tensor:
    if tuple(t.shape) != tuple(shape):
        raise ValueError(f"{what} must have shape {list(shape)}, got {list(t.shape)}")
    if t.dtype != x.dtype:
        raise ValueError(f"{what} is {t.dtype} but positions are {x.dtype}; convert with .to({x.dtype})")
    return t.contiguous()


def _per_element(value, x: torch.Tensor, n: int, what: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return _check_values(value, x, (n,), what)
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{what} ({value}) must be a finite non-negative number")
    return torch.full((n,), float(value), dtype=x.dtype, device=x.device)


def _check_dhat(dhat: float) -> None:
    if not dhat > 0.0:
        raise ValueError(f"dhat ({dhat}) must be positive: it is the squared activation distance d̂², m²")


def _launch(kernel, n: int, inputs: list, outputs: list) -> None:
    if n:
        backend.launch(kernel, n, [*inputs, *outputs])


def _allocate(x: torch.Tensor, n: int, nv: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (
        torch.empty(n, dtype=x.dtype, device=x.device),
        torch.empty(n, nv, 3, dtype=x.dtype, device=x.device),
        torch.empty(n, 3 * nv, 3 * nv, dtype=x.dtype, device=x.device),
    )


# ---------------------------------------------------------------------------------------------------------------
# Overloads declared before the module is built
# ---------------------------------------------------------------------------------------------------------------

# the concrete dtypes of the generic array arguments that are not float64 scalars
_ARRAY_DTYPES = {"x": wp.vec3d, "dx": wp.vec3d, "rest_inv": wp.mat22d}


def _declare_float64_overloads() -> None:
    """Declare the float64 overload (positions ``vec3d``) of every generic kernel of this module now.

    Warp builds a module with the overloads its generic kernels have when it is first loaded; an overload that a
    later launch instantiates rebuilds the whole module. Left to the launches, the garment solver rebuilt this
    module at its first steps and again at its first contact, for the barrier kernels, a long stall in the middle
    of a simulation (``docs/benchmarks.md``); declared here, the first launch builds them all at once. Other dtypes
    still work, at the cost of a rebuild."""
    for kernel in [value for value in globals().values() if isinstance(value, wp.Kernel) and value.is_generic]:
        types = {}
        for arg in kernel.adj.args:
            if arg.type is Any:
                types[arg.label] = wp.float64
            elif wp.types.is_array(arg.type) and arg.type.dtype is Any:
                types[arg.label] = wp.array(dtype=_ARRAY_DTYPES.get(arg.label, wp.float64), ndim=arg.type.ndim)
        wp.overload(kernel, types)


_declare_float64_overloads()
