"""Warped-NeRF previews of a simulation: fit an NGP NeRF to a scene's views, simulate its density, render it warped.

PIE-NeRF's loop (§3.1, §4.1, §4.6) starts from a trained NeRF, samples the simulated body from its density and
renders every frame by warping camera rays back into the rest-space NeRF (Eq. 19–21). This module connects the
pieces for the viewer (``apps.demo``) and the scripted renders (``apps.render``):

* :func:`scene_nerf` fits an :class:`~pienerf.nerf.NGPField` to the rendered views of an embedded scene
  (:func:`pienerf.scenes.render_scene`) and :func:`dataset_nerf` to a NeRF-synthetic folder (the lego). Both cache
  the result as a checkpoint (written atomically by :func:`pienerf.train.save_checkpoint`) named by a hash of every
  setting that changes it, so a second start loads it instead of training.
* NeRF-synthetic scenes are z-up with the object near the origin; the simulator is y-up with the ground at y = 0.
  :func:`dataset_nerf` turns the cameras by :data:`Z_UP_TO_Y_UP` and moves them so that the object's visual hull
  (:func:`visual_hull`, the points every view sees inside its silhouette) stands on y = 0, centred over the origin;
  the field is trained in that frame, with the hull's box (grown by a margin) as its scene box.
* :class:`NerfSceneDensity` is the density the simulator samples from a trained field: σ inside the solid the
  NeRF shows, the cells hidden from all six axis directions (at least a quarter of the light reaching them from
  any of them is absorbed on the way), 0 elsewhere. Sampling σ itself would turn a NeRF's faint floaters in empty space
  into particles (the sampler's ε = 0.01 / m is far below them: a short fit of the teapot left 5 % of the empty
  cells above 0.6 / m and 1 % above 1.8 / m, against a median of 5 / m inside), and a density threshold alone
  either keeps such floaters or loses the inside of thin parts and the NeRF's barely constrained interior.
  :func:`nerf_proxy_mesh` extracts a blocky surface of that solid (the faces between solid and empty cells,
  coloured by the field) for picking and the mesh preview of a scene that has no mesh of its own. On the teapot's
  NeRF of the default fit, a 64-cell grid gave 11302 solid cells where 11530 cell centres lie inside the true
  solid, none farther than 3 cm outside it and 15 deeper than 2 cm inside it missed (asking for half the light:
  566 missed; a tenth: 4 outside).
* :class:`NerfRenderBackend` is the ``"nerf"`` render mode of :class:`pienerf.session.Simulation`: it renders the
  body at q through :class:`pienerf.render.DeformedRenderer` (quadratic or linear warping) at a ``downscale``
  the viewer raises while the user drags and lowers to 1 to refine a still view.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from kernels import backend
from kernels.hashgrid import HashGridConfig
from pienerf.data import Cameras, NerfDataset, load_nerf_dataset
from pienerf.density import DensityField
from pienerf.nerf import NGPConfig, NGPField, OccupancyGrid, render_rays
from pienerf.render import MODES, DeformedRenderer, GroundPlane
from pienerf.scenes import render_scene, scene_mesh
from pienerf.train import NerfCheckpoint, TrainConfig, Trainer, load_checkpoint

__all__ = [
    "Z_UP_TO_Y_UP",
    "NerfFit",
    "NerfRenderBackend",
    "NerfSceneDensity",
    "dataset_nerf",
    "dataset_nerf_path",
    "nerf_proxy_mesh",
    "scene_nerf",
    "visual_hull",
]

Progress = Callable[[str, float], None]
"""Progress callback: ``(stage, fraction in [0, 1])``."""

Z_UP_TO_Y_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking Blender's z-up world to the simulator's y-up one: (x, y, z) → (x, z, −y)."""

_FORMAT = "1"
"""Bumped whenever the fitting recipe changes; part of every cached checkpoint's hash."""


@dataclass(frozen=True)
class NerfFit:
    """How a NeRF is fitted to a scene's views.

    Attributes:
        ngp: the field's hyper-parameters (its ``samples_per_diagonal`` also sets the render's march step).
        train: optimisation settings.
        padding: the scene box is the object's bounds grown by this on every side, metres.
        views: embedded scenes: views rendered (every 8th is held out).
        resolution: embedded scenes: image side, pixels.
        downscale: data folders: integer factor the images are averaged down by.
        max_views: data folders: read only the first views of the training split (``None``: all).
        seed: seeds the field's initial weights (the trainer's sampler has ``train.seed``).
    """

    ngp: NGPConfig = field(
        default_factory=lambda: NGPConfig(
            hashgrid=HashGridConfig(levels=12, features=2, log2_table_size=16, base_resolution=16, max_resolution=256),
            density_hidden=64,
            color_hidden=64,
            color_layers=2,
            grid_resolution=64,
            samples_per_diagonal=384,
        )
    )
    train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=1000, batch_rays=2048, grid_warmup_steps=64))
    padding: float = 0.05
    views: int = 48
    resolution: int = 64
    downscale: int = 8
    max_views: int | None = None
    seed: int = 0

    def __post_init__(self):
        if not (self.padding >= 0 and self.views >= 2 and self.resolution >= 8 and self.downscale >= 1):
            raise ValueError(f"need padding >= 0 m, views >= 2, resolution >= 8 px and downscale >= 1, got {self}")
        if self.max_views is not None and self.max_views < 2:
            raise ValueError(f"max_views must be at least 2 (or None for all), got {self.max_views}")

    def digest(self, **source) -> str:
        """Ten hex digits of a hash over these settings, the recipe version and ``source`` (what was fitted)."""
        payload = {"format": _FORMAT, "fit": asdict(self), "source": source}
        return hashlib.sha1(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:10]


def _cache_root(cache_dir: str | Path | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    return Path(os.environ.get("PIE_CACHE_DIR", Path.home() / ".cache" / "pie-physavatar")).expanduser()


def _fit(
    field_: NGPField, dataset: NerfDataset, fit: NerfFit, path: Path, progress: Progress | None, what: str
) -> NerfCheckpoint:
    """Train ``field_`` on ``dataset`` in chunks (reporting progress), save to ``path`` atomically, return it."""
    trainer = Trainer(field_, dataset, fit.train)
    total = fit.train.steps
    chunk = max(1, min(50, total // 20))
    stats: dict[str, float] = {}
    while trainer.step < total:
        stats = trainer.train(min(chunk, total - trainer.step), progress=False)
        if progress is not None:
            progress(
                f"training the {what} NeRF: step {trainer.step}/{total}, PSNR {stats['psnr']:.1f} dB",
                trainer.step / total,
            )
    trainer.save(path)
    trainer.field.eval()
    return NerfCheckpoint(trainer.field, trainer.grid, trainer.step, fit.train, None)


def scene_nerf(
    scene: str, fit: NerfFit = NerfFit(), cache_dir: str | Path | None = None, progress: Progress | None = None
) -> NerfCheckpoint:
    """The NeRF of an embedded scene, trained on its rendered views, or loaded from the cache.

    The views come from :func:`pienerf.scenes.render_scene` (``fit.views`` views of ``fit.resolution`` pixels,
    cached under ``<cache>/scenes``); the checkpoint is ``ngp-<hash>.pt`` beside them. The scene box is the scene
    mesh's bounds grown by ``fit.padding``.

    Args:
        scene: one of :data:`pienerf.scenes.SCENES`.
        fit: the fitting settings.
        cache_dir: cache root (default ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``).
        progress: called with ``(stage, fraction)`` while rendering and training.

    Returns:
        The trained field (eval mode, backend device) and its occupancy grid.
    """
    backend.init()
    if progress is not None:
        progress(f"rendering {fit.views} views of {scene}", 0.0)
    folder = render_scene(
        scene,
        views=fit.views,
        resolution=fit.resolution,
        seed=fit.seed,
        cache_dir=_cache_root(cache_dir),
        progress=False,
    )
    path = folder / f"ngp-{fit.digest(scene=scene)}.pt"
    if path.is_file():
        return load_checkpoint(path)
    dataset = load_nerf_dataset(folder, "train", background=(0.0, 0.0, 0.0))
    lo, hi = scene_mesh(scene).bounds
    torch.manual_seed(fit.seed)
    field_ = NGPField(fit.ngp, torch.stack([lo - fit.padding, hi + fit.padding]))
    return _fit(field_, dataset, fit, path, progress, scene)


def visual_hull(
    cameras: Cameras, alphas: torch.Tensor, lo, hi, resolution: int = 64, threshold: float = 0.5
) -> torch.Tensor:
    """Centres of the grid cells inside every view's silhouette: the object's visual hull.

    A cell centre belongs to the hull when every view that sees it (it projects inside the image, in front of the
    camera) finds coverage ``alpha ≥ threshold`` at its pixel; a point no view sees is dropped.

    Args:
        cameras: the views (OpenGL axes, :class:`pienerf.data.Cameras`).
        alphas: ``[N, H, W]`` coverage of each view in [0, 1].
        lo, hi: ``[3]`` box searched, metres.
        resolution: cells per box edge.
        threshold: coverage that counts as inside the silhouette.

    Returns:
        ``[M, 3]`` float32 hull points, metres (empty when no point is inside every silhouette).
    """
    lo, hi = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
    axes = [lo[i] + (hi[i] - lo[i]) * (torch.arange(resolution) + 0.5) / resolution for i in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    inside = torch.ones(points.shape[0], dtype=torch.bool)
    seen = torch.zeros(points.shape[0], dtype=torch.bool)
    alphas = alphas.float().cpu()
    cameras = cameras.to("cpu")
    for view in range(len(cameras)):
        c2w = cameras.c2w[view]
        local = (points - c2w[:3, 3]) @ c2w[:3, :3]  # camera axes: looking down −z
        depth = -local[:, 2]
        front = depth > 1e-6
        u = cameras.fx[view] * local[:, 0] / depth.clamp_min(1e-6) + cameras.cx[view]
        v = -cameras.fy[view] * local[:, 1] / depth.clamp_min(1e-6) + cameras.cy[view]
        in_image = front & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        col = u.clamp(0, cameras.width - 1).long()
        row = v.clamp(0, cameras.height - 1).long()
        covered = alphas[view, row, col] >= threshold
        inside &= ~in_image | covered
        seen |= in_image
    return points[inside & seen]


def dataset_nerf(
    folder: str | Path,
    fit: NerfFit = NerfFit(),
    up: str = "z",
    cache_dir: str | Path | None = None,
    progress: Progress | None = None,
    hull_resolution: int = 64,
) -> NerfCheckpoint:
    """The NeRF of a NeRF-synthetic folder (e.g. the lego), trained upright on the ground, or loaded from the cache.

    The training split is read at ``1 / fit.downscale`` size (its first ``fit.max_views`` views); with ``up="z"``
    the cameras are turned by :data:`Z_UP_TO_Y_UP`; then they are moved so that the object's visual hull
    (:func:`visual_hull` over the box ``[-1.5, 1.5]³`` that holds the NeRF-synthetic objects) has its lowest point
    on y = 0 and its centre over x = z = 0. The field's box is the hull's bounds grown by ``fit.padding`` plus one
    hull cell. The checkpoint is ``<cache>/nerf/<folder name>-<hash>.pt``; the data folder is only read.

    The hull is bounded below only by views from near the horizon (a point under the object hides behind it in
    views from above); the NeRF-synthetic cameras include such views, and the lego's base plate came out at
    y = 0.02 m in its solid (:class:`NerfSceneDensity`).

    Args:
        folder: the dataset folder (``transforms_train.json`` and its images).
        fit: the fitting settings (``downscale`` and ``max_views`` apply here).
        up: the dataset's up axis, ``"z"`` (Blender) or ``"y"``.
        cache_dir: cache root (default ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``).
        progress: called with ``(stage, fraction)``.
        hull_resolution: cells per edge of the visual-hull grid.

    Raises:
        FileNotFoundError: the folder or its training json is missing.
        ValueError: ``up`` is not ``"y"`` or ``"z"``, or no point lies inside every silhouette.
    """
    backend.init()
    folder = Path(folder)
    path = dataset_nerf_path(folder, fit, up, cache_dir, hull_resolution)
    if not folder.is_dir():
        raise FileNotFoundError(f"NeRF data folder {folder} is absent; place the dataset there or fix the path")
    if path.is_file():
        return load_checkpoint(path)
    if progress is not None:
        progress(f"reading {folder.name}", 0.0)
    dataset = load_nerf_dataset(
        folder, "train", downscale=fit.downscale, background=(0.0, 0.0, 0.0), max_views=fit.max_views
    )
    world = torch.eye(4)
    if up == "z":
        world[:3, :3] = Z_UP_TO_Y_UP
    cameras = replace(dataset.cameras, c2w=world @ dataset.cameras.c2w)
    hull = visual_hull(cameras, dataset.alphas, [-1.5] * 3, [1.5] * 3, hull_resolution)
    if hull.shape[0] == 0:
        raise ValueError(
            f"no point lies inside every silhouette of {folder}; the alphas or cameras are inconsistent "
            "(check the up axis and that the images carry an alpha channel)"
        )
    cell = 3.0 / hull_resolution
    lo, hi = hull.amin(0) - 0.5 * cell, hull.amax(0) + 0.5 * cell
    shift = torch.stack([-0.5 * (lo[0] + hi[0]), -lo[1], -0.5 * (lo[2] + hi[2])])
    moved = cameras.c2w.clone()
    moved[:, :3, 3] += shift
    dataset = replace(dataset, cameras=replace(cameras, c2w=moved))
    margin = fit.padding + cell
    aabb = torch.stack([lo + shift - margin, hi + shift + margin])
    torch.manual_seed(fit.seed)
    field_ = NGPField(fit.ngp, aabb)
    path.parent.mkdir(parents=True, exist_ok=True)
    return _fit(field_, dataset, fit, path, progress, folder.name)


def dataset_nerf_path(
    folder: str | Path,
    fit: NerfFit = NerfFit(),
    up: str = "z",
    cache_dir: str | Path | None = None,
    hull_resolution: int = 64,
) -> Path:
    """Where :func:`dataset_nerf` caches the checkpoint for these arguments (the file may not exist yet)."""
    if up not in ("y", "z"):
        raise ValueError(f"up must be 'y' or 'z' (the dataset's up axis), got {up!r}")
    folder = Path(folder)
    source = {"folder": str(folder.resolve()), "up": up, "hull_resolution": hull_resolution}
    return _cache_root(cache_dir) / "nerf" / f"{folder.name}-{fit.digest(**source)}.pt"


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
        from pienerf.nerf import NerfDensity

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


class NerfRenderBackend:
    """The ``"nerf"`` render mode: the trained NeRF warped by the body's deformation (PIE-NeRF §4.6, Eq. 19–21).

    Renders one view at ``1 / downscale`` of its pixels (pixel centres of the coarse grid) and repeats each coarse
    pixel to the camera's size, so a viewer can set ``downscale`` to 4 while the user drags and back to 1 to refine
    a still view. RGBA is straight alpha: the object's opacity, and 1 on the ground square when a ground is set.

    Args:
        field: the rest-space radiance field (:class:`pienerf.nerf.NGPField`).
        grid: its occupancy grid.
        model: the discretised body whose integrator points drive the warp (:meth:`rebind` after a re-sampling).
        mode: ``"quadratic"`` (Eq. 20), ``"linear"`` (first-order warp, Fig. 8) or ``"rest"`` (no warp).
        downscale: integer factor of the rendered resolution (1: every pixel).
        ground: a lit ground plane that receives the object's shadow, or ``None``.
        cutoff_scale: see :class:`pienerf.render.DeformedRenderer`.
    """

    def __init__(
        self,
        field,
        grid: OccupancyGrid,
        model,
        *,
        mode: str = "quadratic",
        downscale: int = 1,
        ground: GroundPlane | None = None,
        cutoff_scale: float = 1.5,
    ):
        if mode not in MODES:
            raise ValueError(f"unknown warping mode {mode!r}; valid modes: {', '.join(MODES)}")
        self.field, self.grid, self.mode, self.ground = field, grid, mode, ground
        self.cutoff_scale = cutoff_scale
        self.downscale = downscale
        self.rebind(model)

    @property
    def downscale(self) -> int:
        """Rendered pixels are ``downscale × downscale`` blocks of the camera's pixels."""
        return self._downscale

    @downscale.setter
    def downscale(self, value: int) -> None:
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
            raise ValueError(f"downscale must be an integer >= 1, got {value!r}")
        self._downscale = value

    def rebind(self, model) -> None:
        """Warp by another discretisation of the body (after a re-sampling or a cut)."""
        self.model = model
        self.renderer = DeformedRenderer(self.field, self.grid, model, cutoff_scale=self.cutoff_scale)
        self._frame_q: torch.Tensor | None = None
        self._frame = None

    def _deformed_frame(self, q: torch.Tensor):
        """The renderer's per-q state, rebuilt only when q changes (a still body renders several views cheaply)."""
        if self._frame is None or self._frame_q.shape != q.shape or not torch.equal(self._frame_q, q.detach()):
            self._frame = self.renderer.frame(self.renderer._check_q(q))
            self._frame_q = q.detach().clone()
        return self._frame

    def render(self, q: torch.Tensor, cameras: Cameras, view: int, shadow: bool = False):
        """Render the body at ``q [nT, 3]`` seen by view ``view``; returns a :class:`pienerf.session.Frame`.

        ``depth`` is the object's expected depth where its opacity exceeds ½, else the ground's distance on the
        ground square, else ``inf``; ``shadow`` (when asked, with a ground) is the share of light the object
        blocks on the visible ground, 0 on the object.
        """
        from pienerf.session import Frame

        device = backend.torch_device()
        width, height = cameras.width, cameras.height
        w, h = max(1, math.ceil(width / self.downscale)), max(1, math.ceil(height / self.downscale))
        rows, cols = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        u, v = cols.reshape(-1) * (width / w), rows.reshape(-1) * (height / h)
        # One camera for every ray: its pixel directions (OpenGL axes) turned into the world.
        local = torch.stack(
            [
                (u - float(cameras.cx[view])) / float(cameras.fx[view]),
                -(v - float(cameras.cy[view])) / float(cameras.fy[view]),
                -torch.ones_like(u),
            ],
            dim=-1,
        )
        c2w = cameras.c2w[view].float().cpu()
        directions = torch.nn.functional.normalize(local @ c2w[:3, :3].T, dim=-1).to(device).contiguous()
        origins = c2w[:3, 3].to(device).expand_as(directions).contiguous()
        frame = None if self.mode == "rest" and self.ground is None else self._deformed_frame(q)
        out = self.renderer.render(
            q, rays=(origins, directions), mode=self.mode, background=(0.0, 0.0, 0.0), ground=self.ground, frame=frame
        )
        opacity = out["alpha"].clamp(0.0, 1.0)
        depth = torch.where(opacity > 0.5, out["depth"], math.inf)
        if self.ground is not None:
            on_ground = out["on_ground"]
            t_ground = (self.ground.height - origins[:, 1]) / directions[:, 1]
            depth = torch.where((opacity <= 0.5) & on_ground, t_ground, depth)
            alpha = opacity + (1.0 - opacity) * on_ground.float()
        else:
            alpha = opacity
        straight = torch.where(alpha[:, None] > 1e-6, out["rgb"] / alpha.clamp_min(1e-6)[:, None], 0.0)
        rgba = torch.cat([straight.clamp(0.0, 1.0), alpha[:, None]], dim=1)
        blocked = None
        if shadow and self.ground is not None:
            blocked = ((1.0 - out["ground_transmittance"]) * (1.0 - opacity) * out["on_ground"].float()).clamp(0, 1)
        frame = [rgba.reshape(h, w, 4), depth.reshape(h, w)] + ([blocked.reshape(h, w)] if blocked is not None else [])
        if (h, w) != (height, width):
            frame = [_upsample(image, height, width) for image in frame]
        return Frame(frame[0], frame[1], frame[2] if blocked is not None else None)


def _upsample(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Nearest-neighbour resize of ``[h, w, ...]`` to ``[height, width, ...]``."""
    rows = (torch.arange(height, device=image.device) * image.shape[0]) // height
    cols = (torch.arange(width, device=image.device) * image.shape[1]) // width
    return image[rows][:, cols]
