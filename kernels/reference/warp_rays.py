"""Reference of :mod:`kernels.warp_rays` in plain torch: the same Newton iteration (Eq. 19–21), vectorised.

Every (sample, neighbour) pair runs the kernel's iteration in lockstep, in the dtype of the inputs (float64 in
the tests, so that the kernel's float32 result is compared with an accurate one), with ``torch.linalg.solve``
for the 3×3 systems and the same stopping rule, singular-Jacobian test and fallbacks.
"""

from __future__ import annotations

import torch

__all__ = ["quadratic_map_torch", "warp_to_rest_torch"]

_SINGULAR_DETERMINANT = 1e-6
_MIN_DISTANCE = 1e-12


def quadratic_map_torch(d: torch.Tensor, F: torch.Tensor, grad_F: torch.Tensor) -> torch.Tensor:
    """Second-order Taylor map of the deformation about an IP: x̃ − x̃_k = F d + ½ ∇F : d d (Eq. 19).

    Args:
        d: ``[..., 3]`` rest offsets x − x_k, metres.
        F: ``[..., 3, 3]`` deformation gradients.
        grad_F: ``[..., 3, 3, 3]`` with ``grad_F[..., a, b, c] = ∂F_ab/∂x_c``, per metre.

    Returns:
        ``[..., 3]`` deformed offsets x̃ − x̃_k, metres.
    """
    linear = torch.einsum("...ab,...b->...a", F, d)
    return linear + 0.5 * torch.einsum("...abc,...b,...c->...a", grad_F, d, d)


def _jacobian(d: torch.Tensor, F: torch.Tensor, grad_F: torch.Tensor) -> torch.Tensor:
    """``∂(F d + ½ ∇F : d d)/∂d = F + ∇F^sym · d``."""
    symmetric = 0.5 * (grad_F + grad_F.transpose(-1, -2))
    return F + torch.einsum("...abc,...c->...ab", symmetric, d)


def _solve(J: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(J⁻¹ rhs, singular)`` with 0 where ``|det J|`` is below the threshold."""
    singular = torch.linalg.det(J).abs() < _SINGULAR_DETERMINANT
    safe = torch.where(singular[..., None, None], torch.eye(3, dtype=J.dtype, device=J.device), J)
    x = torch.linalg.solve(safe, rhs[..., None])[..., 0]
    return torch.where(singular[..., None], 0.0, x), singular


def warp_to_rest_torch(
    samples: torch.Tensor,
    neighbours: torch.Tensor,
    distances: torch.Tensor,
    ip_deformed: torch.Tensor,
    ip_displacement: torch.Tensor,
    F: torch.Tensor,
    grad_F: torch.Tensor,
    cutoff: torch.Tensor,
    quadratic: bool = True,
    iterations: int = 10,
    tolerance: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of :func:`kernels.warp_rays.warp_to_rest` (arguments as there, any float dtype).

    Returns:
        ``(rest [S, 3], valid [S] bool, iterations [S] int32, fallback [S] bool)``.
    """
    dtype = samples.dtype
    index = neighbours.long()
    present = index >= 0
    k = index.clamp_min(0)
    nearest = k[:, 0]
    valid = present[:, 0] & (distances[:, 0].to(dtype) <= cutoff[nearest].to(dtype))
    b = samples[:, None, :] - ip_deformed[k]  # [S, N, 3]
    Fk, Gk = F[k], grad_F[k]

    d, singular_F = _solve(Fk, b)
    d = torch.where(singular_F[..., None], b, d)  # collapsed IP: pure translation
    used = torch.ones(k.shape, dtype=torch.int32, device=samples.device)
    fallback = singular_F.clone()
    if quadratic:
        linear = d
        active = ~singular_F
        converged = torch.zeros_like(active)
        for _ in range(iterations - 1):
            running = active & ~converged
            if not bool(running.any()):
                break
            residual = quadratic_map_torch(d, Fk, Gk) - b
            step, singular = _solve(_jacobian(d, Fk, Gk), -residual)
            stop = running & singular
            active = active & ~stop
            moving = running & ~singular
            d = torch.where(moving[..., None], d + step, d)
            used = used + moving.int()
            converged = converged | (moving & ((step * step).sum(-1) <= tolerance * tolerance))
        failed = ~singular_F & ~converged
        d = torch.where(failed[..., None], linear, d)
        fallback = fallback | failed

    displacement = ip_displacement[k] + (b - d)
    weight = torch.where(present, 1.0 / distances.to(dtype).clamp_min(_MIN_DISTANCE), 0.0)
    blended = (weight[..., None] * displacement).sum(1) / weight.sum(1, keepdim=True)
    rest = torch.where(valid[:, None], samples - blended, samples)
    used = torch.where(valid[:, None] & present, used, 0).amax(1).int()
    fallback = (valid[:, None] & present & fallback).any(1)
    return rest, valid, used, fallback
