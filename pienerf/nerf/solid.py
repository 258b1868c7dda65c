"""A trained NeRF as a simulated solid: the density the simulator samples and a surface to pick and preview.

:class:`NerfSceneDensity` is the density the simulator samples from a trained field: σ inside the solid the NeRF
shows, the cells hidden from all six axis directions (at least a quarter of the light reaching them from any of
them is absorbed on the way), 0 elsewhere. Sampling σ itself would turn a NeRF's faint floaters in empty space
into particles (the sampler's ε = 0.01 / m is far below them), and a density threshold alone either keeps such
floaters or loses the inside of thin parts and the NeRF's barely constrained interior; how well the rule finds a
known solid is on the measurements page, ``docs/benchmarks.md``.

:func:`nerf_proxy_mesh` extracts a blocky surface of that solid (the faces between solid and empty cells, coloured
by the field) for picking and the mesh preview of a scene that has no mesh of its own.
"""

from __future__ import annotations

import math

import torch

from pienerf.nerf.field import NerfDensity, NGPField, OccupancyGrid, render_rays
from pienerf.sim.density import DensityField

__all__ = ["NerfSceneDensity", "nerf_proxy_mesh"]


class NerfSceneDensity(DensityField):
    """The solid a trained NeRF describes, for the simulator: the points hidden from every side (module docstring).

    The field's box is cut into cells (``resolution`` along its longest edge); σ is evaluated at their centres
    (0 in cells its occupancy grid marks empty). Along each of the six axis directions the optical depth from the
    box's face up to and including a cell is accumulated, ``τ = Σ σ_c Δ``; a cell is solid when ``τ ≥ −ln(1 −
    opacity)`` from all six, i.e. at least ``opacity`` of the light reaching it from any axis direction has been
    absorbed on the way. Faint fog absorbs little and drops out whatever its extent; a concavity open to one
    side drops out; the inside of a closed surface stays in even where the NeRF left its interior nearly empty.

    ``σ'(x) = max(σ(x), floor)`` in solid cells and 0 elsewhere, so the sampler's ``ε`` keeps the whole inside;
    ``∇σ' = ∇σ`` where ``σ > floor`` in solid cells (autograd through the torch encoding, as
    :class:`pienerf.nerf.NerfDensity`), else 0.

    Args:
        field: the trained NGP field (its parameters are not changed).
        grid: its occupancy grid, or ``None``.
        resolution: cells along the box's longest edge.
        opacity: share of light that must be absorbed from every axis direction.
        floor: density given to solid cells where σ is lower, per metre.
    """

    def __init__(
        self,
        field: NGPField,
        grid: OccupancyGrid | None = None,
        resolution: int = 96,
        opacity: float = 0.25,
        floor: float = 1.0,
    ):
        if not (resolution >= 2 and 0.0 < opacity < 1.0 and floor > 0.0):
            raise ValueError(
                f"need resolution >= 2, 0 < opacity < 1 and floor > 0 per metre; got {resolution}, {opacity}, {floor}"
            )
        self.field, self.grid, self.floor = field, grid, float(floor)
        self._nerf = NerfDensity(field)
        lo, hi = (b.float() for b in self._nerf.bounds)
        size = float((hi - lo).max()) / resolution
        self.counts = [max(1, math.ceil(float(hi[i] - lo[i]) / size)) for i in range(3)]
        self.lo, self.cell_size = lo, size
        sigma = self._nerf.density(self.cell_centres().reshape(-1, 3)).reshape(self.counts)
        if grid is not None:
            sigma = torch.where(
                grid.is_occupied(self.cell_centres().reshape(-1, 3).to(grid.aabb.device)).cpu().reshape(self.counts),
                sigma,
                0.0,
            )
        depth = sigma * size
        needed = -math.log(1.0 - opacity)
        solid = torch.ones(self.counts, dtype=torch.bool)
        for axis in range(3):
            solid &= depth.cumsum(axis) >= needed
            solid &= depth.flip(axis).cumsum(axis).flip(axis) >= needed
        self.solid = solid
        if bool(solid.any()):
            index = torch.nonzero(solid)
            self._bounds = (self.lo + size * index.amin(0)).double(), (self.lo + size * (index.amax(0) + 1)).double()
        else:
            self._bounds = self._nerf.bounds

    def cell_centres(self) -> torch.Tensor:
        """``[Nx, Ny, Nz, 3]`` centres of the cells, metres."""
        axes = [self.lo[i] + self.cell_size * (torch.arange(self.counts[i]) + 0.5) for i in range(3)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)

    @property
    def bounds(self):
        """The solid cells' box (the field's box when no cell is solid), metres, float64."""
        return self._bounds

    def in_solid(self, x: torch.Tensor) -> torch.Tensor:
        """bool ``[N]``: whether points ``x [N, 3]`` (metres) fall in a solid cell."""
        cell = torch.floor((x.detach().float().cpu() - self.lo) / self.cell_size).long()
        counts = torch.tensor(self.counts)
        inside = ((cell >= 0) & (cell < counts)).all(dim=-1)
        cell = torch.minimum(cell.clamp_min(0), counts - 1)
        return (inside & self.solid[cell[:, 0], cell[:, 1], cell[:, 2]]).to(x.device)

    @torch.no_grad()
    def density(self, x: torch.Tensor) -> torch.Tensor:
        """σ' ``[N]`` (per metre) at ``x [N, 3]`` (metres), in ``x``'s dtype and device."""
        sigma = self._nerf.density(x)
        return torch.where(self.in_solid(x), sigma.clamp_min(self.floor), torch.zeros_like(sigma))

    def density_grad(self, x: torch.Tensor) -> torch.Tensor:
        """∇σ' ``[N, 3]`` (per square metre): ∇σ where σ exceeds the floor inside the solid, else 0."""
        keep = self.in_solid(x)
        if bool(keep.any()):
            keep[keep.clone()] = self._nerf.density(x[keep]) > self.floor
        grad = torch.zeros_like(x)
        if bool(keep.any()):
            grad[keep] = self._nerf.density_grad(x[keep])
        return grad


def nerf_proxy_mesh(density: NerfSceneDensity) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A blocky surface of a NeRF's solid: the faces between its solid and empty cells, coloured by the field.

    Every face shared by a solid cell of :class:`NerfSceneDensity` and an empty one (or the box's edge) becomes two
    triangles facing out. A face's colour is what the NeRF shows along a ray from the empty cell's centre through
    the face into the solid cell (volume rendering over those two cells); each vertex takes the mean of its faces'
    colours.

    Returns:
        ``vertices [V, 3]`` float32 (metres), ``faces [F, 3]`` int32 (counter-clockwise from outside) and
        ``colors [V, 3]`` float32 albedo in [0, 1], on the CPU.

    Raises:
        ValueError: no cell is solid.
    """
    solid, lo, size = density.solid, density.lo, density.cell_size
    if not bool(solid.any()):
        raise ValueError(
            "the NeRF's solid is empty: no point is hidden from every side; train the NeRF longer or "
            "lower NerfSceneDensity's opacity"
        )
    padded = torch.nn.functional.pad(solid, (1, 1, 1, 1, 1, 1))
    quads, normals, cells = [], [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (-1, 1):
            # Faces on the ``sign`` side of solid cells whose neighbour there is empty; corners (in cell units from
            # the cell's lower corner) counter-clockwise seen from outside.
            neighbour = torch.roll(padded, shifts=-sign, dims=axis)[1:-1, 1:-1, 1:-1]
            index = torch.nonzero(solid & ~neighbour)
            if index.shape[0] == 0:
                continue
            offsets = torch.zeros(4, 3, dtype=torch.long)
            offsets[:, axis] = 1 if sign > 0 else 0
            square = [(0, 0), (1, 0), (1, 1), (0, 1)] if sign > 0 else [(0, 0), (0, 1), (1, 1), (1, 0)]
            for k, (a, b) in enumerate(square):
                offsets[k, u], offsets[k, v] = a, b
            quads.append(index[:, None, :] + offsets)
            normal = torch.zeros(3)
            normal[axis] = float(sign)
            normals.append(normal.expand(index.shape[0], 3))
            cells.append(index)
    corners = torch.cat(quads)  # [Q, 4, 3] integer corner coordinates
    normals, cells = torch.cat(normals), torch.cat(cells)
    unique, inverse = torch.unique(corners.reshape(-1, 3), dim=0, return_inverse=True)
    inverse = inverse.reshape(-1, 4)
    faces = torch.cat([inverse[:, [0, 1, 2]], inverse[:, [0, 2, 3]]]).int()
    vertices = lo + size * unique.float()
    device = density.field.aabb.device
    outside = (lo + size * (cells.float() + 0.5) + size * normals).to(device).contiguous()
    inward = (-normals).to(device).contiguous()
    grid = density.grid if density.grid is not None else OccupancyGrid(density.field.aabb, 1).to(device)
    with torch.no_grad():
        seen = render_rays(density.field, grid, outside, inward, 0.0, 2.0 * size, (0.0, 0.0, 0.0))
        _, fallback = density.field(outside + 0.5 * size * inward, inward)
    opacity = seen["opacity"][:, None]
    rgb = torch.where(opacity > 1e-2, seen["rgb"] / opacity.clamp_min(1e-2), fallback)
    colors = torch.zeros(unique.shape[0], 3)
    count = torch.zeros(unique.shape[0])
    flat = inverse.reshape(-1)
    colors.index_add_(0, flat, rgb.cpu().float().repeat_interleave(4, dim=0))
    count.index_add_(0, flat, torch.ones_like(flat, dtype=torch.float32))
    return vertices.contiguous(), faces.contiguous(), (colors / count[:, None]).clamp(0, 1)
