"""Differentiable tile rasterizer of 2D Gaussians (3D Gaussian Splatting, Kerbl et al. 2023; PhysAvatar §3.1).

PhysAvatar tracks a garment with mesh-aligned 3D Gaussians rendered by the Gaussian Splatting rasterizer.
The 3D → 2D part (projection to pixel means and conics) is done elsewhere in torch; this module composites
the projected Gaussians of ``V`` views into images and returns gradients with respect to the 2D means,
conics, colours and opacities.

Semantics (per view, pixel ``p`` with centre ``(i + 0.5, j + 0.5)``, Gaussians sorted front to back by
depth):

    d = μ_k − p,   power_k = −½ (a d_x² + c d_y²) − b d_x d_y,   α_k = min(0.99, o_k exp(power_k)),

a Gaussian is skipped where ``power_k > 0`` or ``α_k < 1/255``; compositing stops *before* the first
Gaussian with ``T (1 − α_k) < 1e-4``; otherwise ``C += c_k α_k T`` and ``T *= 1 − α_k`` (``T`` starts at 1).
The outputs are ``image = C + T · background`` and ``alpha = 1 − T``.

Binning: the image is cut into 16 × 16 px tiles; a Gaussian with ``radius > 0`` and ``depth > near`` is
listed in every tile its box ``[μ − radius, μ + radius]`` touches, and only pixels of those tiles see it.
The lists are built in torch: one instance per (Gaussian, tile), keyed ``tile · 2^32 + depth rank`` and
sorted once, so every tile's slice of the sorted list is front to back (equal depths keep index order).

Kernels (Taichi):

* forward: one thread per pixel, threads numbered tile-major (the 256 threads of a tile are adjacent, so
  a CUDA warp walks one list); each walks its tile's list front to back and stores the final ``T`` and the
  list position just past its last contributor (``exp`` is skipped where ``power < ln(1/255) − 0.01``,
  which for opacities up to 1 cannot reach ``α ≥ 1/255``);
* backward: the same threads walk back to front from that position, recovering ``T`` before each
  Gaussian as ``T / (1 − α_k)`` and the colour composited behind it, and add to the list entry they read

      ∂C/∂c_k = α_k T_k,   ∂C/∂α_k = T_k (c_k − C_behind,k),   ∂T_final/∂α_k = −T_final / (1 − α_k),

  chained through ``α_k = o_k G_k`` to ``o_k``, ``μ_k`` and ``(a, b, c)``. Where the clamp at 0.99 is
  active, ``α_k`` does not depend on ``o_k`` or ``G_k`` and they receive nothing from that pixel (the
  exact derivative; the original CUDA code passes it through). The background enters through ``T_final``.

Framework: Taichi, because both kernels are per-pixel loops of data-dependent length, the shape the
project gives to Taichi for rendering that must also run on a CPU (Taichi uses every core, Warp's CPU
backend one); a Warp port was not written. Nothing is CPU-only: no shared memory (threads of a tile read
the same list entries from global memory), and the backward has two layouts of one kernel: on the CPU
one thread per tile owns the tile's list entries and adds without atomics (faster than atomics there,
``docs/benchmarks.md``); on CUDA one thread per pixel adds atomically. Per-entry gradients are then summed per Gaussian
with ``index_add_``.

Timings against the dense torch reference: ``docs/benchmarks.md``.
"""

import math
from typing import NamedTuple

import taichi as ti
import torch

from kernels import backend

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "TILE_SIZE",
    "TRANSMITTANCE_MIN",
    "GaussianTiles",
    "RasterizeGaussiansFunction",
    "bin_gaussians",
    "gaussian_radii",
    "rasterize_gaussians",
]

TILE_SIZE = 16
"""Tile edge, px."""

ALPHA_MIN = 1.0 / 255.0
"""A Gaussian whose ``α`` at a pixel is below this is skipped there."""

ALPHA_MAX = 0.99
"""``α`` is clamped to this, so that ``1 − α`` never vanishes."""

TRANSMITTANCE_MIN = 1e-4
"""Compositing stops before the Gaussian that would bring ``T`` below this."""

_PIXELS_PER_TILE = TILE_SIZE * TILE_SIZE

_POWER_CUTOFF = math.log(ALPHA_MIN) - 0.01
"""Below this power, ``α < 1/255`` for any opacity ≤ 1 (with a margin over exp's rounding): skip, no ``exp``."""


# ---------------------------------------------------------------------------------------------------
# Binning (torch)
# ---------------------------------------------------------------------------------------------------


class GaussianTiles(NamedTuple):
    """Per-tile front-to-back lists of Gaussians (CSR layout over the tiles of all views).

    Attributes:
        tile_offsets: int32 ``[V · Ty · Tx + 1]``; tile ``t`` of view ``v`` (``t = ty · Tx + tx``) owns
            positions ``tile_offsets[v · Ty · Tx + t] : tile_offsets[v · Ty · Tx + t + 1]`` of ``gaussian_ids``.
        gaussian_ids: int32 ``[I]`` flat Gaussian index ``v · N + k``, sorted by tile then depth.
        tiles_x: ``Tx``, tiles per image row.
        tiles_y: ``Ty``, tiles per image column.
    """

    tile_offsets: torch.Tensor
    gaussian_ids: torch.Tensor
    tiles_x: int
    tiles_y: int


def bin_gaussians(
    means2d: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
) -> GaussianTiles:
    """List every visible Gaussian in the 16 × 16 px tiles its box ``[μ ± radius]`` touches, front to back.

    Args:
        means2d: float32 ``[V, N, 2]`` pixel coordinates.
        depths: float32 ``[V, N]`` camera-space depth, m; ``depth <= near`` culls.
        radii: int32 ``[V, N]`` box half-size, px; ``<= 0`` culls.
        width, height: image size, px.
        near: culling depth, m.

    Returns:
        :class:`GaussianTiles`.
    """
    views, count = depths.shape
    device = depths.device
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    tiles_per_view = tiles_x * tiles_y
    radius = radii.to(torch.float32)
    visible = (radii > 0) & (depths > near) & torch.isfinite(means2d).all(-1)
    x0, x1, y0, y1 = _tile_rect(means2d, radius, tiles_x, tiles_y)
    span_x, span_y = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    counts = torch.where(visible, span_x * span_y, 0).flatten()
    total = int(counts.sum())
    tile_offsets = torch.zeros(views * tiles_per_view + 1, dtype=torch.int32, device=device)
    if total == 0:
        return GaussianTiles(tile_offsets, torch.zeros(0, dtype=torch.int32, device=device), tiles_x, tiles_y)

    gaussian = torch.repeat_interleave(torch.arange(views * count, device=device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - first[gaussian]
    row_span = span_x.flatten()[gaussian]
    tx = x0.flatten()[gaussian] + local % row_span
    ty = y0.flatten()[gaussian] + torch.div(local, row_span, rounding_mode="floor")
    tile = torch.div(gaussian, count, rounding_mode="floor") * tiles_per_view + ty * tiles_x + tx
    # Depth rank over all views (stable: equal depths keep index order); ranks < 2^31 fit the low half.
    rank = torch.empty(views * count, dtype=torch.int64, device=device)
    rank[torch.sort(depths.flatten(), stable=True).indices] = torch.arange(views * count, device=device)
    keys = tile * (1 << 32) + rank[gaussian]
    order = torch.sort(keys).indices
    tile_counts = torch.bincount(tile, minlength=views * tiles_per_view)
    tile_offsets[1:] = torch.cumsum(tile_counts, 0)
    return GaussianTiles(tile_offsets, gaussian[order].to(torch.int32), tiles_x, tiles_y)


def _tile_rect(means2d: torch.Tensor, radius: torch.Tensor, tiles_x: int, tiles_y: int):
    """Half-open tile ranges ``[x0, x1) × [y0, y1)`` (int64 ``[V, N]`` each) touched by ``[μ ± radius]``."""
    means = torch.nan_to_num(means2d, nan=0.0, posinf=1e30, neginf=-1e30)
    lo = torch.floor((means - radius[..., None]) / TILE_SIZE)
    hi = torch.floor((means + radius[..., None]) / TILE_SIZE) + 1.0
    x0 = lo[..., 0].clamp(0, tiles_x).long()
    x1 = hi[..., 0].clamp(0, tiles_x).long()
    y0 = lo[..., 1].clamp(0, tiles_y).long()
    y1 = hi[..., 1].clamp(0, tiles_y).long()
    return x0, x1, y0, y1


def gaussian_radii(conics: torch.Tensor, extent: float = 3.0) -> torch.Tensor:
    """Screen-space radius of 2D Gaussians: ``ceil(extent · sqrt(λ_max(Σ)))`` with ``Σ`` the 2D covariance.

    Args:
        conics: float ``[..., 3]`` ``(a, b, c)`` of the inverse covariance ``[[a, b], [b, c]]``, px^-2.
        extent: radius in standard deviations along the major axis (3 in 3DGS).

    Returns:
        int32 ``[...]`` radii, px; 0 where the conic is not positive definite.
    """
    if not isinstance(conics, torch.Tensor) or conics.shape[-1:] != (3,):
        raise ValueError(f"conics must be a [..., 3] tensor (a, b, c), got {getattr(conics, 'shape', conics)}")
    a, b, c = conics.unbind(-1)
    det = a * c - b * b
    mid = 0.5 * (a + c)
    spread = torch.sqrt((mid * mid - det).clamp_min(0.0))
    # λ_max(Σ) = 1 / λ_min(conic) = (mid + spread) / det, free of the cancellation in mid − spread.
    definite = (det > 0) & (a > 0)
    variance = torch.where(definite, (mid + spread) / torch.where(definite, det, 1.0), 0.0)
    return torch.ceil(extent * torch.sqrt(variance)).to(torch.int32)


# ---------------------------------------------------------------------------------------------------
# Kernels (Taichi)
# ---------------------------------------------------------------------------------------------------


@ti.func
def _pixel_of_thread(i, tiles_x, tiles_per_view):
    """View, pixel column and row of thread ``i`` (threads numbered tile-major, 256 per tile)."""
    tile = i // _PIXELS_PER_TILE
    local = i % _PIXELS_PER_TILE
    in_view = tile % tiles_per_view
    px = (in_view % tiles_x) * TILE_SIZE + local % TILE_SIZE
    py = (in_view // tiles_x) * TILE_SIZE + local // TILE_SIZE
    return tile, tile // tiles_per_view, px, py


@ti.func
def _power(mean, conic, px, py):
    """``−½ (a dx² + c dy²) − b dx dy`` and ``(dx, dy) = μ − p`` at the centre of pixel ``(px, py)``."""
    dx = mean[0] - (ti.cast(px, ti.f32) + 0.5)
    dy = mean[1] - (ti.cast(py, ti.f32) + 0.5)
    return -0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy, dx, dy


@ti.kernel
def _forward_ti(
    means: ti.types.ndarray(dtype=ti.math.vec2, ndim=1),
    conics: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    opacities: ti.types.ndarray(dtype=ti.f32, ndim=1),
    tile_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    gaussian_ids: ti.types.ndarray(dtype=ti.i32, ndim=1),
    tiles_x: ti.i32,
    tiles_per_view: ti.i32,
    out_color: ti.types.ndarray(dtype=ti.math.vec3, ndim=3),
    out_transmittance: ti.types.ndarray(dtype=ti.f32, ndim=3),
    out_end: ti.types.ndarray(dtype=ti.i32, ndim=3),
):
    height, width = out_transmittance.shape[1], out_transmittance.shape[2]
    ti.loop_config(block_dim=_PIXELS_PER_TILE)
    for i in range((tile_offsets.shape[0] - 1) * _PIXELS_PER_TILE):
        tile, view, px, py = _pixel_of_thread(i, tiles_x, tiles_per_view)
        if px < width and py < height:
            start, stop = tile_offsets[tile], tile_offsets[tile + 1]
            transmittance = 1.0
            color = ti.math.vec3(0.0)
            end = start
            for j in range(start, stop):
                g = gaussian_ids[j]
                power, _, _ = _power(means[g], conics[g], px, py)
                opacity = opacities[g]
                if power > 0.0 or (power < _POWER_CUTOFF and opacity <= 1.0):
                    continue
                alpha = ti.min(ALPHA_MAX, opacity * ti.exp(power))
                if alpha < ALPHA_MIN:
                    continue
                next_transmittance = transmittance * (1.0 - alpha)
                if next_transmittance < TRANSMITTANCE_MIN:
                    break
                color += colors[g] * (alpha * transmittance)
                transmittance = next_transmittance
                end = j + 1
            out_color[view, py, px] = color
            out_transmittance[view, py, px] = transmittance
            out_end[view, py, px] = end


@ti.func
def _add(grad_entries: ti.template(), j: ti.i32, k: ti.template(), value: ti.f32, atomic: ti.template()):
    if ti.static(atomic):
        ti.atomic_add(grad_entries[j, k], value)
    else:
        grad_entries[j, k] = grad_entries[j, k] + value


@ti.func
def _backward_pixel(
    i: ti.i32,
    means: ti.template(),
    conics: ti.template(),
    colors: ti.template(),
    opacities: ti.template(),
    tile_offsets: ti.template(),
    gaussian_ids: ti.template(),
    tiles_x: ti.i32,
    tiles_per_view: ti.i32,
    final_transmittance: ti.template(),
    ends: ti.template(),
    grad_color: ti.template(),
    grad_transmittance: ti.template(),
    grad_entries: ti.template(),
    atomic: ti.template(),
):
    """Walk pixel ``i``'s list back to front and add its gradients to the list entries (rows of ``grad_entries``)."""
    height, width = final_transmittance.shape[1], final_transmittance.shape[2]
    tile, view, px, py = _pixel_of_thread(i, tiles_x, tiles_per_view)
    if px < width and py < height:
        start, end = tile_offsets[tile], ends[view, py, px]
        t_final = final_transmittance[view, py, px]
        d_color = grad_color[view, py, px]
        d_final = grad_transmittance[view, py, px]
        transmittance = t_final
        behind = ti.math.vec3(0.0)  # colour composited behind the current Gaussian, from T = 1
        for step in range(end - start):
            j = end - 1 - step
            g = gaussian_ids[j]
            power, dx, dy = _power(means[g], conics[g], px, py)
            opacity = opacities[g]
            if power > 0.0 or (power < _POWER_CUTOFF and opacity <= 1.0):
                continue
            gauss = ti.exp(power)
            raw = opacity * gauss
            alpha = ti.min(ALPHA_MAX, raw)
            if alpha < ALPHA_MIN:
                continue
            transmittance /= 1.0 - alpha  # now T before this Gaussian
            c = colors[g]
            weight = alpha * transmittance
            for k in ti.static(range(3)):
                _add(grad_entries, j, 5 + k, weight * d_color[k], atomic)
            d_alpha = transmittance * (c - behind).dot(d_color) - t_final / (1.0 - alpha) * d_final
            behind = alpha * c + (1.0 - alpha) * behind
            if raw <= ALPHA_MAX:  # else α is the clamp's constant: no gradient to o, μ or the conic
                d_power = raw * d_alpha
                conic = conics[g]
                _add(grad_entries, j, 0, -d_power * (conic[0] * dx + conic[1] * dy), atomic)
                _add(grad_entries, j, 1, -d_power * (conic[2] * dy + conic[1] * dx), atomic)
                _add(grad_entries, j, 2, -0.5 * d_power * dx * dx, atomic)
                _add(grad_entries, j, 3, -d_power * dx * dy, atomic)
                _add(grad_entries, j, 4, -0.5 * d_power * dy * dy, atomic)
                _add(grad_entries, j, 8, gauss * d_alpha, atomic)


@ti.kernel
def _backward_ti(
    means: ti.types.ndarray(dtype=ti.math.vec2, ndim=1),
    conics: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    colors: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
    opacities: ti.types.ndarray(dtype=ti.f32, ndim=1),
    tile_offsets: ti.types.ndarray(dtype=ti.i32, ndim=1),
    gaussian_ids: ti.types.ndarray(dtype=ti.i32, ndim=1),
    tiles_x: ti.i32,
    tiles_per_view: ti.i32,
    final_transmittance: ti.types.ndarray(dtype=ti.f32, ndim=3),
    ends: ti.types.ndarray(dtype=ti.i32, ndim=3),
    grad_color: ti.types.ndarray(dtype=ti.math.vec3, ndim=3),
    grad_transmittance: ti.types.ndarray(dtype=ti.f32, ndim=3),
    grad_entries: ti.types.ndarray(dtype=ti.f32, ndim=2),
    per_tile: ti.template(),
):
    """Per-entry gradients ``[I, 9]``: (μ_x, μ_y, a, b, c, r, g, b, o) of every (Gaussian, tile) list entry.

    ``per_tile`` (CPU): one thread per tile walks its 256 pixels in turn and owns the tile's entries, so
    plain adds replace atomics. Otherwise (CUDA): one thread per pixel, atomic adds.
    """
    tiles = tile_offsets.shape[0] - 1
    if ti.static(per_tile):
        for tile in range(tiles):
            for local in range(_PIXELS_PER_TILE):
                _backward_pixel(
                    tile * _PIXELS_PER_TILE + local,
                    means,
                    conics,
                    colors,
                    opacities,
                    tile_offsets,
                    gaussian_ids,
                    tiles_x,
                    tiles_per_view,
                    final_transmittance,
                    ends,
                    grad_color,
                    grad_transmittance,
                    grad_entries,
                    False,
                )
    else:
        ti.loop_config(block_dim=_PIXELS_PER_TILE)
        for i in range(tiles * _PIXELS_PER_TILE):
            _backward_pixel(
                i,
                means,
                conics,
                colors,
                opacities,
                tile_offsets,
                gaussian_ids,
                tiles_x,
                tiles_per_view,
                final_transmittance,
                ends,
                grad_color,
                grad_transmittance,
                grad_entries,
                True,
            )


# ---------------------------------------------------------------------------------------------------
# Autograd and entry point
# ---------------------------------------------------------------------------------------------------


def _backward_per_tile(device: torch.device) -> bool:
    """Backward layout: one thread per tile without atomics on the CPU, one per pixel with atomics on CUDA."""
    return device.type == "cpu"


class RasterizeGaussiansFunction(torch.autograd.Function):
    """``apply(means2d, conics, colors, opacities, depths, radii, background, width, height, near)``.

    Arguments and outputs as :func:`rasterize_gaussians` (checked there; ``background`` is a tensor here).
    Gradients flow to ``means2d``, ``conics``, ``colors``, ``opacities`` and ``background``.
    """

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, background, width, height, near):
        views, count = depths.shape
        device = depths.device
        tiles = bin_gaussians(means2d, depths, radii, width, height, near)
        flat = [
            t.detach().reshape(views * count, *t.shape[2:]).contiguous() for t in (means2d, conics, colors, opacities)
        ]
        color = torch.zeros(views, height, width, 3, device=device)
        transmittance = torch.ones(views, height, width, device=device)
        ends = torch.zeros(views, height, width, dtype=torch.int32, device=device)
        if tiles.gaussian_ids.numel() > 0:
            _forward_ti(
                *(backend.taichi_arg(t) for t in (*flat, tiles.tile_offsets, tiles.gaussian_ids)),
                tiles.tiles_x,
                tiles.tiles_x * tiles.tiles_y,
                *(backend.taichi_arg(t) for t in (color, transmittance, ends)),
            )
        background = background.detach()
        image = color + transmittance[..., None] * background
        ctx.save_for_backward(*flat, background, tiles.tile_offsets, tiles.gaussian_ids, transmittance, ends)
        ctx.tiles = (tiles.tiles_x, tiles.tiles_y)
        ctx.shape = (views, count)
        return image, 1.0 - transmittance

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        means, conics, colors, opacities, background, tile_offsets, gaussian_ids, transmittance, ends = (
            ctx.saved_tensors
        )
        views, count = ctx.shape
        if grad_image is None:
            grad_image = torch.zeros(*transmittance.shape, 3, device=transmittance.device)
        if grad_alpha is None:
            grad_alpha = torch.zeros_like(transmittance)
        grad_image = grad_image.to(torch.float32).contiguous()
        # image = C + T · background and alpha = 1 − T, so dL/dT = background · dL/dimage − dL/dalpha.
        grad_transmittance = ((grad_image * background).sum(-1) - grad_alpha).contiguous()
        grad = torch.zeros(views * count, 9, device=means.device)
        if gaussian_ids.numel() > 0:
            tiles_x, tiles_y = ctx.tiles
            grad_entries = torch.zeros(gaussian_ids.shape[0], 9, device=means.device)
            _backward_ti(
                *(backend.taichi_arg(t) for t in (means, conics, colors, opacities, tile_offsets, gaussian_ids)),
                tiles_x,
                tiles_x * tiles_y,
                *(backend.taichi_arg(t) for t in (transmittance, ends, grad_image, grad_transmittance, grad_entries)),
                _backward_per_tile(means.device),
            )
            grad.index_add_(0, gaussian_ids, grad_entries)
        grad = grad.reshape(views, count, 9)
        grad_means, grad_conics, grad_colors, grad_opacities = (
            grad[..., 0:2],
            grad[..., 2:5],
            grad[..., 5:8],
            grad[..., 8],
        )
        grad_background = None
        if ctx.needs_input_grad[6]:
            grad_background = (grad_image * transmittance[..., None]).sum((0, 1, 2))
        return grad_means, grad_conics, grad_colors, grad_opacities, None, None, grad_background, None, None, None


def rasterize_gaussians(
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
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians of ``V`` views front to back into images (module docstring).

    Args:
        means2d: float32 ``[V, N, 2]`` pixel coordinates (x right, y down; pixel ``(i, j)`` has its centre
            at ``(i + 0.5, j + 0.5)``).
        conics: float32 ``[V, N, 3]`` ``(a, b, c)``: inverse 2D covariance ``[[a, b], [b, c]]``, px^-2.
        colors: float32 ``[V, N, 3]`` per-view colours (an expanded ``[N, 3]`` works).
        opacities: float32 ``[V, N]`` in ``(0, 1)``.
        depths: float32 ``[V, N]`` camera-space depth, m; sorts the Gaussians, ``depth <= near`` culls.
        radii: int32 ``[V, N]`` screen-space radius, px (e.g. :func:`gaussian_radii`); 0 culls.
        width, height: image size, px.
        background: float32 ``[3]`` colour behind the Gaussians; ``None``: black.
        near: culling depth, m.

    Returns:
        ``(image [V, H, W, 3], alpha [V, H, W])``, float32; differentiable with respect to ``means2d``,
        ``conics``, ``colors``, ``opacities`` (and ``background``), not ``depths`` or ``radii``.

    Raises:
        ValueError: an argument has the wrong shape, dtype or device, or the image size is not positive.
    """
    width, height = _check_size(width, "width"), _check_size(height, "height")
    _check_tensor(depths, "depths", torch.float32, 2, "[V, N]")
    views, count = depths.shape
    device = depths.device
    _check_tensor(means2d, "means2d", torch.float32, 3, "[V, N, 2]", (views, count, 2), device)
    _check_tensor(conics, "conics", torch.float32, 3, "[V, N, 3]", (views, count, 3), device)
    _check_tensor(colors, "colors", torch.float32, 3, "[V, N, 3]", (views, count, 3), device)
    _check_tensor(opacities, "opacities", torch.float32, 2, "[V, N]", (views, count), device)
    _check_tensor(radii, "radii", torch.int32, 2, "[V, N]", (views, count), device)
    if background is None:
        background = torch.zeros(3, device=device)
    _check_tensor(background, "background", torch.float32, 1, "[3]", (3,), device)
    if not math.isfinite(float(near)):
        raise ValueError(f"near must be a finite depth in metres, got {near}")
    return RasterizeGaussiansFunction.apply(
        means2d, conics, colors, opacities, depths, radii, background, width, height, float(near)
    )


def _check_size(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name} must be a positive int (pixels), got {value!r}")
    return value


def _check_tensor(tensor, name, dtype, dims, layout, shape=None, device=None) -> None:
    if not isinstance(tensor, torch.Tensor):
        raise ValueError(f"{name} must be a {dtype} tensor {layout}, got {type(tensor).__name__}")
    if tensor.dtype != dtype:
        raise ValueError(f"{name} must be {dtype} {layout}, got {tensor.dtype}; convert it with .to({dtype})")
    if tensor.dim() != dims or (shape is not None and tuple(tensor.shape) != shape):
        expected = layout if shape is None else f"{layout} = {list(shape)}"
        raise ValueError(f"{name} must be {expected}, got {list(tensor.shape)}")
    if device is not None and tensor.device != device:
        raise ValueError(f"{name} is on {tensor.device} but depths is on {device}; move it with .to({device!r})")
