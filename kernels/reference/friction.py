"""Reference of :mod:`kernels.friction`: IPC's lagged friction potential as a chain of torch operations."""

from __future__ import annotations

import torch

__all__ = ["friction_potential"]


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
