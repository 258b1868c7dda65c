"""Reference of :mod:`kernels.gaussian_splat` in dense torch, differentiable by autograd.

Every (view, pixel, Gaussian) triple is evaluated at once, ``[V, H · W, N]``, so this is for small images
(e.g. 32 × 24 px and 50 Gaussians). The Gaussians of each view are sorted by depth (stably, so equal depths
keep index order), and the rasterizer's discrete decisions become masks:

* a Gaussian reaches a pixel only if the pixel's 16 × 16 tile is one its box ``[μ ± radius]`` touches, its
  radius is positive and its depth is beyond ``near``;
* it is skipped where ``power > 0`` or ``α < 1/255`` (its ``α`` is set to 0, so ``1 − α = 1``);
* early termination keeps Gaussian ``k`` only if ``Π_{j ≤ k} (1 − α_j) ≥ 1e-4``: ``T`` never rises front to
  back, so this keeps exactly the Gaussians before the first one that would bring ``T`` below the limit.

Compositing is then an exclusive ``cumprod`` of ``1 − α``; the masks carry no gradient, which matches the
kernel's derivative of the truncated sum with the decisions held fixed.
"""

from __future__ import annotations

import torch

__all__ = ["rasterize_gaussians_torch"]

_TILE = 16


def rasterize_gaussians_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    near: float = 0.01,
    transmittance_min: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference of :func:`kernels.gaussian_splat.rasterize_gaussians`.

    Args:
        means2d ``[V, N, 2]``, conics ``[V, N, 3]``, colors ``[V, N, 3]``, opacities ``[V, N]``: float
            tensors of one dtype (float64 for gradient checks).
        depths: ``[V, N]`` depth, m (sort key; ``<= near`` culls).
        radii: ``[V, N]`` integer radius, px (``<= 0`` culls).
        width, height: image size, px.
        background: ``[3]`` colour, default black.
        near: culling depth, m.
        transmittance_min: early-termination limit on ``T`` (0 disables termination).

    Returns:
        ``(image [V, H, W, 3], alpha [V, H, W])`` in the dtype of ``means2d``.
    """
    views, count = depths.shape
    dtype, device = means2d.dtype, means2d.device
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=device)

    order = torch.sort(depths, dim=1, stable=True).indices
    means = torch.gather(means2d, 1, order[..., None].expand(-1, -1, 2))
    conic = torch.gather(conics, 1, order[..., None].expand(-1, -1, 3))
    color = torch.gather(colors, 1, order[..., None].expand(-1, -1, 3))
    opacity = torch.gather(opacities, 1, order)
    depth = torch.gather(depths, 1, order)
    radius = torch.gather(radii, 1, order)

    ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    pixel_tile_x, pixel_tile_y = (xs // _TILE).flatten(), (ys // _TILE).flatten()  # [P]
    centres = torch.stack([xs.flatten(), ys.flatten()], -1).to(dtype) + 0.5  # [P, 2]

    # Tiles touched by the box [μ ± radius] (half-open ranges), computed in float32 like the binning.
    with torch.no_grad():
        m32, r32 = means.detach().to(torch.float32), radius.to(torch.float32)[..., None]
        lo = torch.floor((m32 - r32) / _TILE)
        hi = torch.floor((m32 + r32) / _TILE) + 1.0
        in_tile = (
            (pixel_tile_x[None, :, None] >= lo[:, None, :, 0])
            & (pixel_tile_x[None, :, None] < hi[:, None, :, 0])
            & (pixel_tile_y[None, :, None] >= lo[:, None, :, 1])
            & (pixel_tile_y[None, :, None] < hi[:, None, :, 1])
        )
        visible = in_tile & ((radius > 0) & (depth > near))[:, None, :]  # [V, P, N]

    d = means[:, None, :, :] - centres[None, :, None, :]  # [V, P, N, 2]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = (conic[..., i][:, None, :] for i in range(3))
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    # clamp(max=0) keeps exp finite where power > 0 (those are masked out, and their gradient is zero).
    raw = opacity[:, None, :] * torch.exp(power.clamp(max=0.0))
    alpha = raw.clamp(max=0.99)
    keep = visible & (power <= 0) & (alpha >= 1.0 / 255.0)
    alpha = torch.where(keep, alpha, 0.0)
    with torch.no_grad():
        stopped = torch.cumprod(1.0 - alpha, -1) < transmittance_min
    alpha = torch.where(stopped, 0.0, alpha)
    survive = torch.cumprod(1.0 - alpha, -1)
    transmittance = torch.cat([torch.ones_like(survive[..., :1]), survive[..., :-1]], -1)
    weights = alpha * transmittance  # [V, P, N]
    image = torch.einsum("vpn,vnc->vpc", weights, color)
    final = survive[..., -1] if count > 0 else torch.ones(views, height * width, dtype=dtype, device=device)
    image = image + final[..., None] * background.to(dtype)
    return image.reshape(views, height, width, 3), (1.0 - final).reshape(views, height, width)
