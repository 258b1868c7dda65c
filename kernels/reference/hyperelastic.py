"""Reference of :mod:`kernels.hyperelastic`: energies written from F's invariants and polar
decomposition, differentiated by torch autograd; the PSD projection by a 9×9 eigen-decomposition."""

from __future__ import annotations

import torch

from kernels.hyperelastic import MaterialModel

__all__ = ["energy_density", "material_response"]


def _rotation(F: torch.Tensor) -> torch.Tensor:
    """The rotation R = F (FᵀF)^(-1/2) of the polar decomposition F = R S, for det F > 0.

    Written through a symmetric eigen-decomposition, which (unlike an SVD) torch differentiates
    twice for distinct eigenvalues.
    """
    w, Q = torch.linalg.eigh(F.T @ F)
    return F @ Q @ torch.diag(w.rsqrt()) @ Q.T


def energy_density(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, model: MaterialModel) -> torch.Tensor:
    """Ψ(F) for one 3×3 F (Neo-Hookean: PIE-NeRF Eq. 22)."""
    J = torch.dot(F[0], torch.linalg.cross(F[1], F[2]))  # det F as a triple product (vmap-safe twice)
    if model == MaterialModel.NEO_HOOKEAN:
        logJ = torch.log(J)
        return 0.5 * mu * ((F * F).sum() - 3.0) - mu * logJ + 0.5 * lam * logJ**2
    if model == MaterialModel.STVK:
        E = 0.5 * (F.T @ F - torch.eye(3, dtype=F.dtype, device=F.device))
        return mu * (E * E).sum() + 0.5 * lam * torch.trace(E) ** 2
    corotated = mu * ((F - _rotation(F)) ** 2).sum()
    if model == MaterialModel.ARAP:
        return corotated
    return corotated + 0.5 * lam * (J - 1.0) ** 2


def material_response(
    F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, model: MaterialModel, project: bool = True,
    derivatives: int = 2,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Same contract as :func:`kernels.hyperelastic.material_response`, one point at a time."""
    mu = mu.to(F).expand(F.shape[0])
    lam = lam.to(F).expand(F.shape[0])
    psi, P, dPdF = [], [], []
    for Fm, m, l in zip(F, mu, lam, strict=True):
        def energy(x, m=m, l=l):
            return energy_density(x.reshape(3, 3), m, l, model)

        x = Fm.reshape(9)
        psi.append(energy(x))
        P.append(torch.func.grad(energy)(x).reshape(3, 3))
        H = torch.func.jacrev(torch.func.jacrev(energy))(x)  # reverse over reverse: no TorchScript
        H = 0.5 * (H + H.T)
        if project:
            w, Q = torch.linalg.eigh(H)
            H = Q @ torch.diag(w.clamp(min=0)) @ Q.T
        dPdF.append(H)
    return torch.stack(psi), torch.stack(P), torch.stack(dPdF)


def material_response_batched(
    F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, model: MaterialModel, project: bool = True,
    derivatives: int = 2,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Vectorised form of :func:`material_response` (``torch.func.vmap`` over autograd), the pure
    torch baseline that benchmarks time against the kernel; ``derivatives`` as there (skipped
    outputs are ``None``)."""
    mu = mu.to(F).expand(F.shape[0])
    lam = lam.to(F).expand(F.shape[0])

    def energy(x, m, l):
        return energy_density(x.reshape(3, 3), m, l, model)

    flat = F.reshape(-1, 9)
    psi = torch.func.vmap(energy)(flat, mu, lam)
    if derivatives < 1:
        return psi, None, None
    P = torch.func.vmap(torch.func.grad(energy))(flat, mu, lam).reshape(-1, 3, 3)
    if derivatives < 2:
        return psi, P, None
    H = torch.func.vmap(torch.func.jacrev(torch.func.jacrev(energy)))(flat, mu, lam)
    H = 0.5 * (H + H.mT)
    if project:
        w, Q = torch.linalg.eigh(H)
        H = Q @ torch.diag_embed(w.clamp(min=0)) @ Q.mT
    return psi, P, H
