"""Isotropic hyperelastic energy densities: Ψ(F), P = ∂Ψ/∂F and ∂P/∂F at material points.

Every model is written in the signed singular values σ of F = U diag(σ) Vᵀ (U, V rotations; the
sign of an inverted F sits on the singular value of smallest magnitude). The Hessian ∂P/∂F is
assembled from its analytic eigensystem: three *scaling* modes U diag(v) Vᵀ from the 3×3 Hessian
∂²Ψ/∂σ², and for each pair (i, j) a *twist* mode U(eᵢeⱼᵀ − eⱼeᵢᵀ)Vᵀ/√2 with eigenvalue
(Ψᵢ + Ψⱼ)/(σᵢ + σⱼ) and a *flip* mode U(eᵢeⱼᵀ + eⱼeᵢᵀ)Vᵀ/√2 with eigenvalue (Ψᵢ − Ψⱼ)/(σᵢ − σⱼ),
the latter in closed form per model so that σᵢ = σⱼ needs no special case. Clamping the nine
eigenvalues at zero gives the nearest positive semi-definite Hessian at no extra cost, which is how
the per-integrator-point Hessians of the Q-GMLS solver are made PSD.

Models (μ, λ: Lamé parameters in Pa; energies in J/m³):

* ``NEO_HOOKEAN`` (PIE-NeRF Eq. 22): Ψ = μ/2 (I_C − 3) − μ log J + λ/2 log² J; +inf for J ≤ 0.
* ``ARAP``: Ψ = μ ‖F − R‖²_F = μ Σ (σᵢ − 1)², with R the rotation of F; no volume term.
* ``STVK``: Ψ = μ ‖E‖²_F + λ/2 tr²(E), E = (FᵀF − I)/2.
* ``FIXED_COROTATED``: Ψ = μ ‖F − R‖²_F + λ/2 (J − 1)².

All four agree with linear elasticity (μ ε:ε + λ/2 tr²ε) to first order, except ARAP which lacks
the λ term.

Framework: Warp, float64. The kernel needs a 3×3 SVD, a symmetric 3×3 eigen-decomposition and
9×9 register matrices, which Warp provides as built-ins on CPU and CUDA; the solver runs in float64
so that Newton converges to tight tolerances.
"""

import enum

import torch
import warp as wp

from kernels import backend

# Derivatives are written out analytically; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False})

__all__ = ["MaterialModel", "material_response"]


class MaterialModel(enum.IntEnum):
    """Energy density models of :func:`material_response`."""

    NEO_HOOKEAN = 0
    ARAP = 1
    STVK = 2
    FIXED_COROTATED = 3


_vec9 = wp.types.vector(length=9, dtype=wp.float64)
_mat99 = wp.types.matrix(shape=(9, 9), dtype=wp.float64)

_NEO_HOOKEAN = wp.constant(int(MaterialModel.NEO_HOOKEAN))
_ARAP = wp.constant(int(MaterialModel.ARAP))
_STVK = wp.constant(int(MaterialModel.STVK))
_INF = wp.constant(wp.float64(1.0e300))


@wp.func
def _psi(model: int, s: wp.vec3d, mu: wp.float64, lam: wp.float64) -> wp.float64:
    """Ψ(σ) of each model (module docstring; Neo-Hookean is Eq. 22)."""
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    J = s[0] * s[1] * s[2]
    if model == _NEO_HOOKEAN:
        if J <= wp.float64(0.0):
            return _INF
        logJ = wp.log(J)
        return half * mu * (wp.dot(s, s) - wp.float64(3.0)) - mu * logJ + half * lam * logJ * logJ
    if model == _ARAP:
        d = s - wp.vec3d(one, one, one)
        return mu * wp.dot(d, d)
    if model == _STVK:
        E = half * wp.vec3d(s[0] * s[0] - one, s[1] * s[1] - one, s[2] * s[2] - one)
        trE = E[0] + E[1] + E[2]
        return mu * wp.dot(E, E) + half * lam * trE * trE
    d = s - wp.vec3d(one, one, one)
    return mu * wp.dot(d, d) + half * lam * (J - one) * (J - one)


@wp.func
def _dpsi(model: int, s: wp.vec3d, mu: wp.float64, lam: wp.float64) -> wp.vec3d:
    """∂Ψ/∂σᵢ."""
    one = wp.float64(1.0)
    J = s[0] * s[1] * s[2]
    cof = wp.vec3d(s[1] * s[2], s[0] * s[2], s[0] * s[1])  # ∂J/∂σᵢ
    if model == _NEO_HOOKEAN:
        c = lam * wp.log(wp.max(J, wp.float64(1e-300))) - mu
        return wp.vec3d(mu * s[0] + c / s[0], mu * s[1] + c / s[1], mu * s[2] + c / s[2])
    if model == _ARAP:
        return wp.float64(2.0) * mu * (s - wp.vec3d(one, one, one))
    if model == _STVK:
        half = wp.float64(0.5)
        E = half * wp.vec3d(s[0] * s[0] - one, s[1] * s[1] - one, s[2] * s[2] - one)
        trE = E[0] + E[1] + E[2]
        two_mu = wp.float64(2.0) * mu
        return wp.vec3d(
            s[0] * (two_mu * E[0] + lam * trE), s[1] * (two_mu * E[1] + lam * trE), s[2] * (two_mu * E[2] + lam * trE)
        )
    return wp.float64(2.0) * mu * (s - wp.vec3d(one, one, one)) + lam * (J - one) * cof


@wp.func
def _d2psi(model: int, s: wp.vec3d, mu: wp.float64, lam: wp.float64) -> wp.mat33d:
    """∂²Ψ/∂σᵢ∂σⱼ."""
    one = wp.float64(1.0)
    H = wp.mat33d()
    J = s[0] * s[1] * s[2]
    cof = wp.vec3d(s[1] * s[2], s[0] * s[2], s[0] * s[1])
    if model == _NEO_HOOKEAN:
        logJ = wp.log(wp.max(J, wp.float64(1e-300)))
        for i in range(3):
            for j in range(3):
                H[i, j] = lam / (s[i] * s[j])
            H[i, i] = mu + (mu - lam * logJ + lam) / (s[i] * s[i])
        return H
    if model == _ARAP:
        for i in range(3):
            H[i, i] = wp.float64(2.0) * mu
        return H
    if model == _STVK:
        half = wp.float64(0.5)
        trE = half * (wp.dot(s, s) - wp.float64(3.0))
        for i in range(3):
            for j in range(3):
                H[i, j] = lam * s[i] * s[j]
            H[i, i] = mu * (s[i] * s[i] - one) + lam * trE + (wp.float64(2.0) * mu + lam) * s[i] * s[i]
        return H
    for i in range(3):
        for j in range(3):
            k = 3 - i - j
            if i != j:
                H[i, j] = lam * (cof[i] * cof[j] + (J - one) * s[k])
        H[i, i] = wp.float64(2.0) * mu + lam * cof[i] * cof[i]
    return H


@wp.func
def _twist(model: int, s: wp.vec3d, i: int, j: int, mu: wp.float64, lam: wp.float64) -> wp.float64:
    """Twist eigenvalue (Ψᵢ + Ψⱼ)/(σᵢ + σⱼ) of the pair (i, j)."""
    one = wp.float64(1.0)
    k = 3 - i - j
    J = s[0] * s[1] * s[2]
    if model == _NEO_HOOKEAN:
        c = lam * wp.log(wp.max(J, wp.float64(1e-300))) - mu
        return mu + c / (s[i] * s[j])
    if model == _STVK:
        trE = wp.float64(0.5) * (wp.dot(s, s) - wp.float64(3.0))
        return mu * (s[i] * s[i] - s[i] * s[j] + s[j] * s[j] - one) + lam * trE
    # ARAP and fixed-corotated share 2μ(1 − 2/(σᵢ+σⱼ)); the sum is floored so that an inverted
    # pair gives a large negative eigenvalue (clamped by the projection) instead of a division by 0.
    arap = wp.float64(2.0) * mu * (one - wp.float64(2.0) / wp.max(s[i] + s[j], wp.float64(1e-12)))
    if model == _ARAP:
        return arap
    return arap + lam * (J - one) * s[k]


@wp.func
def _flip(model: int, s: wp.vec3d, i: int, j: int, mu: wp.float64, lam: wp.float64) -> wp.float64:
    """Flip eigenvalue (Ψᵢ − Ψⱼ)/(σᵢ − σⱼ) of the pair (i, j), in closed form."""
    one = wp.float64(1.0)
    k = 3 - i - j
    J = s[0] * s[1] * s[2]
    if model == _NEO_HOOKEAN:
        c = lam * wp.log(wp.max(J, wp.float64(1e-300))) - mu
        return mu - c / (s[i] * s[j])
    if model == _ARAP:
        return wp.float64(2.0) * mu
    if model == _STVK:
        trE = wp.float64(0.5) * (wp.dot(s, s) - wp.float64(3.0))
        return mu * (s[i] * s[i] + s[i] * s[j] + s[j] * s[j] - one) + lam * trE
    return wp.float64(2.0) * mu - lam * (J - one) * s[k]


@wp.func
def _flatten(M: wp.mat33d) -> _vec9:
    return _vec9(M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2])


@wp.func
def _mode(U: wp.mat33d, V: wp.mat33d, i: int, j: int, sign: wp.float64) -> _vec9:
    """vec(U (eᵢeⱼᵀ + sign·eⱼeᵢᵀ) Vᵀ / √2): a twist (sign −1) or flip (sign +1) mode."""
    ui = wp.vec3d(U[0, i], U[1, i], U[2, i])
    uj = wp.vec3d(U[0, j], U[1, j], U[2, j])
    vi = wp.vec3d(V[0, i], V[1, i], V[2, i])
    vj = wp.vec3d(V[0, j], V[1, j], V[2, j])
    return _flatten(wp.outer(ui, vj) + sign * wp.outer(uj, vi)) * wp.float64(0.7071067811865476)


@wp.func
def _rotation_variant_svd(F: wp.mat33d):
    """SVD F = U diag(σ) Vᵀ with U, V proper rotations; returns (U, σ, V) with any negative sign on
    the singular value of smallest magnitude."""
    U = wp.mat33d()
    s = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, s, V)
    if wp.determinant(U) < wp.float64(0.0):
        for r in range(3):
            U[r, 2] = -U[r, 2]
        s[2] = -s[2]
    if wp.determinant(V) < wp.float64(0.0):
        for r in range(3):
            V[r, 2] = -V[r, 2]
        s[2] = -s[2]
    # Move a negative sign onto the smallest |σ| (flipping two columns of U keeps det U = +1).
    m = 0
    for i in range(1, 3):
        if wp.abs(s[i]) < wp.abs(s[m]):
            m = i
    for i in range(3):
        if i != m and s[i] < wp.float64(0.0):
            s[i] = -s[i]
            s[m] = -s[m]
            for r in range(3):
                U[r, i] = -U[r, i]
                U[r, m] = -U[r, m]
    return U, s, V


@wp.kernel
def _material_response(
    F: wp.array(dtype=wp.mat33d),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    model: int,
    project: int,
    derivatives: int,
    psi: wp.array(dtype=wp.float64),
    P: wp.array(dtype=wp.mat33d),
    dPdF: wp.array(dtype=_mat99),
):
    p = wp.tid()
    U, s, V = _rotation_variant_svd(F[p])
    m = mu[p]
    l = lam[p]
    psi[p] = _psi(model, s, m, l)
    if derivatives < 1:
        return
    g = _dpsi(model, s, m, l)
    P[p] = U * wp.diag(g) * wp.transpose(V)
    if derivatives < 2:
        return

    zero = wp.float64(0.0)
    A = _mat99()
    Q = wp.mat33d()
    d = wp.vec3d()
    wp.eig3(_d2psi(model, s, m, l), Q, d)
    for e in range(3):
        ev = d[e]
        if project != 0:
            ev = wp.max(ev, zero)
        v = wp.vec3d(Q[0, e], Q[1, e], Q[2, e])
        mode = _flatten(U * wp.diag(v) * wp.transpose(V))
        A += ev * wp.outer(mode, mode)
    for pair in range(3):
        i = wp.where(pair == 2, 1, 0)
        j = wp.where(pair == 0, 1, 2)
        twist = _twist(model, s, i, j, m, l)
        flip = _flip(model, s, i, j, m, l)
        if project != 0:
            twist = wp.max(twist, zero)
            flip = wp.max(flip, zero)
        t = _mode(U, V, i, j, wp.float64(-1.0))
        f = _mode(U, V, i, j, wp.float64(1.0))
        A += twist * wp.outer(t, t) + flip * wp.outer(f, f)
    dPdF[p] = A


def material_response(
    F: torch.Tensor,
    mu: torch.Tensor,
    lam: torch.Tensor,
    model: MaterialModel,
    project: bool = True,
    derivatives: int = 2,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Energy density, first Piola–Kirchhoff stress and its derivative at material points.

    Args:
        F: deformation gradients ``[M, 3, 3]``, float64.
        mu: first Lamé parameter per point ``[M]`` (Pa), float64.
        lam: second Lamé parameter per point ``[M]`` (Pa), float64.
        model: the energy density (module docstring).
        project: clamp the Hessian's eigenvalues at zero (positive semi-definite result).
        derivatives: 0 computes Ψ only, 1 adds P, 2 adds ∂P/∂F; outputs not computed are left
            uninitialised (a line search needs only Ψ).

    Returns:
        ``psi [M]`` (J/m³; +inf for an inverted Neo-Hookean point), ``P [M, 3, 3]`` (Pa) and
        ``dPdF [M, 9, 9]`` (Pa), the latter indexed by row-major flattenings of F and P:
        ``dPdF[m, 3a+b, 3c+d] = ∂P_ab/∂F_cd``.
    """
    if F.dtype != torch.float64 or F.dim() != 3 or F.shape[1:] != (3, 3):
        raise ValueError(f"material_response expects float64 F of shape [M, 3, 3], got {F.dtype} {tuple(F.shape)}")
    count = F.shape[0]
    mu = mu.to(F).expand(count).contiguous()
    lam = lam.to(F).expand(count).contiguous()
    F = F.contiguous()
    psi = torch.empty(count, dtype=F.dtype, device=F.device)
    P = torch.empty_like(F)
    dPdF = torch.empty(count, 9, 9, dtype=F.dtype, device=F.device)
    if count:
        wp.launch(
            _material_response,
            dim=count,
            inputs=[
                backend.to_warp(F, dtype=wp.mat33d),
                backend.to_warp(mu),
                backend.to_warp(lam),
                int(model),
                int(project),
                int(derivatives),
            ],
            outputs=[backend.to_warp(psi), backend.to_warp(P, dtype=wp.mat33d), backend.to_warp(dPdF, dtype=_mat99)],
            device=backend.warp_device(),
        )
    psi = torch.where(psi >= 1e299, torch.full_like(psi, float("inf")), psi)
    return psi, P, dPdF
