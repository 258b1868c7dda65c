"""Reference of :mod:`kernels.volume_render` in plain torch: vectorised over rays, differentiable by autograd.

Compositing writes transmittance in closed form, ``T_i = exp(−Σ_{j<i} σ_j δ_j)``, as a segmented exclusive
``cumsum`` over the packed samples (in float64, so that one long sum over all rays keeps its precision),
and early termination as the mask ``T_i ≥ threshold`` (``T`` never rises along a ray, so the mask keeps
exactly the samples before the first one below the threshold). Autograd through it gives the gradients
the kernel's reverse sweep computes by hand.

Ray marching advances every ray by one step (or one skip) per iteration, in lockstep, with the kernel's
float32 arithmetic.
"""

from __future__ import annotations

import torch

__all__ = ["composite_torch", "march_rays_torch"]

_TINY_DIRECTION = 1e-12


def composite_torch(
    sigmas: torch.Tensor,
    colors: torch.Tensor,
    deltas: torch.Tensor,
    depths: torch.Tensor,
    ray_offsets: torch.Tensor,
    transmittance_threshold: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of :func:`kernels.volume_render.composite_forward`.

    Args:
        sigmas ``[S]``, colors ``[S, 3]``, deltas ``[S]``, depths ``[S]``: packed samples.
        ray_offsets: ``[R + 1]`` CSR offsets.
        transmittance_threshold: samples with ``T_i`` below it get weight 0.

    Returns:
        ``(color [R, 3], opacity [R], depth [R], weights [S])`` in the dtype of ``sigmas``.
    """
    rays = ray_offsets.shape[0] - 1
    offsets = ray_offsets.long()
    counts = offsets[1:] - offsets[:-1]
    ray = torch.repeat_interleave(torch.arange(rays, device=sigmas.device), counts, output_size=sigmas.shape[0])
    tau = sigmas.double() * deltas.double()
    inclusive = torch.cumsum(tau, 0)
    before_ray = torch.cat([tau.new_zeros(1), inclusive])[offsets[:-1]]
    transmittance = torch.exp(-(inclusive - tau - before_ray[ray]))
    alpha = 1.0 - torch.exp(-tau)
    weights = torch.where(transmittance >= transmittance_threshold, transmittance * alpha, 0.0)
    color = torch.zeros(rays, 3, dtype=torch.float64, device=sigmas.device)
    color = color.index_add(0, ray, weights[:, None] * colors.double())
    opacity = torch.zeros(rays, dtype=torch.float64, device=sigmas.device).index_add(0, ray, weights)
    depth = torch.zeros(rays, dtype=torch.float64, device=sigmas.device).index_add(0, ray, weights * depths.double())
    dtype = sigmas.dtype
    return color.to(dtype), opacity.to(dtype), depth.to(dtype), weights.to(dtype)


def _safe(d: torch.Tensor) -> torch.Tensor:
    tiny = torch.where(d >= 0, _TINY_DIRECTION, -_TINY_DIRECTION).to(d.dtype)
    return torch.where(d.abs() < _TINY_DIRECTION, tiny, d)


def march_rays_torch(
    origins: torch.Tensor,
    directions: torch.Tensor,
    near: torch.Tensor | float,
    far: torch.Tensor | float,
    occupancy: torch.Tensor,
    aabb: torch.Tensor,
    min_step: float,
    *,
    max_step: float | None = None,
    cone_angle: float = 0.0,
    max_samples: int = 1024,
    jitter: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of :func:`kernels.volume_render.march_rays` (arguments as there).

    Returns:
        ``(positions [S, 3], depths [S], deltas [S], ray_offsets [R + 1] int32)``.
    """
    rays, device = origins.shape[0], origins.device
    if max_step is None:
        max_step = 1e10 if cone_angle > 0.0 else min_step
    aabb = torch.as_tensor(aabb, dtype=torch.float32, device=device)
    lo, hi = aabb[0], aabb[1]
    resolution = torch.tensor(occupancy.shape, device=device)
    cell_size = (hi - lo) / resolution.float()
    grid = occupancy.bool()
    d = _safe(directions)
    t0, t1 = (lo - origins) / d, (hi - origins) / d
    near = torch.as_tensor(near, dtype=torch.float32, device=device).expand(rays)
    far = torch.as_tensor(far, dtype=torch.float32, device=device).expand(rays)
    begin = torch.maximum(torch.minimum(t0, t1).amax(-1), near)
    end = torch.minimum(torch.maximum(t0, t1).amin(-1), far)
    jitter = torch.zeros(rays, device=device) if jitter is None else jitter

    def step(t):
        return (t * cone_angle).clamp(min_step, max_step)

    t = begin + jitter * step(begin)
    count = torch.zeros(rays, dtype=torch.long, device=device)
    active = begin < end
    emitted = []  # (ray, position, depth, delta) per iteration
    while True:
        active = active & (t < end) & (count < max_samples)
        ray = torch.nonzero(active).flatten()
        if ray.numel() == 0:
            break
        dt = step(t[ray])
        p = origins[ray] + t[ray, None] * directions[ray]
        cell = torch.minimum(((p - lo) / cell_size).floor().long().clamp_min(0), resolution - 1)
        occupied = grid[cell[:, 0], cell[:, 1], cell[:, 2]]
        hit = ray[occupied]
        emitted.append((hit, p[occupied], t[hit], dt[occupied]))
        count[hit] += 1
        t[hit] += dt[occupied]
        miss, p_miss, cell_miss, dt_miss = ray[~occupied], p[~occupied], cell[~occupied], dt[~occupied]
        d_miss = d[miss]
        face = lo + (cell_miss + (d_miss > 0).long()).float() * cell_size
        skip = ((face - p_miss) / d_miss).amin(-1).clamp_min(0.0)
        t[miss] += (torch.floor(skip / dt_miss) + 1.0) * dt_miss

    if emitted:
        ray_of, positions, depths, deltas = (torch.cat(parts) for parts in zip(*emitted, strict=True))
    else:
        ray_of, positions = torch.zeros(0, dtype=torch.long, device=device), torch.zeros(0, 3, device=device)
        depths, deltas = torch.zeros(0, device=device), torch.zeros(0, device=device)
    order = torch.sort(ray_of, stable=True).indices
    ray_offsets = torch.zeros(rays + 1, dtype=torch.int32, device=device)
    ray_offsets[1:] = torch.cumsum(count, 0)
    return positions[order], depths[order], deltas[order], ray_offsets
