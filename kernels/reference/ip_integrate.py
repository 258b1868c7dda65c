"""Reference of :mod:`kernels.ip_integrate`: the energy summed point by point from the reference
energy density, differentiated by autograd; the projected Hessian as Σ Bᵀ A B with explicit B."""

from __future__ import annotations

import torch

from kernels.hyperelastic import MaterialModel
from kernels.reference.hyperelastic import energy_density, material_response

__all__ = ["ip_energy", "ip_gradient", "ip_hessian"]


def _deformation_gradients(q, index, shape_grad):
    F = []
    for k in range(shape_grad.shape[0]):
        for g in range(shape_grad.shape[1]):
            Fkg = torch.eye(3, dtype=q.dtype)
            for slot, s in enumerate(index[k].tolist()):
                if s >= 0:
                    Fkg = Fkg + torch.outer(q[s], shape_grad[k, g, slot])
            F.append(Fkg)
    return torch.stack(F)


def ip_energy(q, index, shape_grad, weight, mu, lam, model: MaterialModel) -> torch.Tensor:
    """U(q) = Σ_kg w_kg Ψ(F_kg) (Eq. 16)."""
    F = _deformation_gradients(q, index, shape_grad)
    psi = torch.stack([energy_density(Fm, torch.as_tensor(mu), torch.as_tensor(lam), model) for Fm in F])
    return (weight.reshape(-1) * psi).sum()


def ip_gradient(q, index, shape_grad, weight, mu, lam, model) -> torch.Tensor:
    """∂U/∂q by autograd (Eq. 17)."""
    return torch.func.grad(lambda x: ip_energy(x, index, shape_grad, weight, mu, lam, model))(q)


def ip_hessian(q, index, shape_grad, weight, mu, lam, model, project: bool) -> torch.Tensor:
    """∂²U/∂q² ``[nT*3, nT*3]``: by autograd when ``project`` is off, else Σ_kg w Bᵀ A⁺ B with the
    reference's eigen-projected A⁺ and the explicit B = ∂vec(F)/∂q."""
    n = q.shape[0]
    if not project:
        energy = lambda x: ip_energy(x.view(n, 3), index, shape_grad, weight, mu, lam, model)  # noqa: E731
        # reverse over reverse: torch.func.hessian's forward mode loads decompositions through deprecated TorchScript
        return torch.func.jacrev(torch.func.jacrev(energy))(q.reshape(-1))
    F = _deformation_gradients(q, index, shape_grad)
    _, _, A = material_response(F, torch.as_tensor(mu), torch.as_tensor(lam), model, project=True)
    H = torch.zeros(3 * n, 3 * n, dtype=q.dtype)
    K, G = weight.shape
    for k in range(K):
        for g in range(G):
            B = torch.zeros(9, 3 * n, dtype=q.dtype)
            for slot, s in enumerate(index[k].tolist()):
                if s >= 0:
                    for a in range(3):
                        B[3 * a : 3 * a + 3, 3 * s + a] += shape_grad[k, g, slot]
            H += weight[k, g] * B.T @ A[k * G + g] @ B
    return H
