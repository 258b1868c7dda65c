"""Fit an NGP NeRF to a scene's views and cache it: the NeRF that PIE-NeRF's loop starts from (§3.1, §4.1).

* :func:`dataset_nerf` fits an :class:`~pienerf.nerf.NGPField` to a NeRF-synthetic folder (the lego) and
  :func:`pienerf.scenes.scene_nerf` to the rendered views of an embedded scene, both through :func:`fit_nerf`.
  Both cache
  the result as a checkpoint (written atomically by :func:`pienerf.nerf.training.save_checkpoint`) under
  :func:`pienerf.paths.cache_root`, named by a hash of every setting that changes it, so a second start loads it
  instead of training.
* NeRF-synthetic scenes are z-up with the object near the origin; the simulator is y-up with the ground at y = 0.
  :func:`dataset_nerf` turns the cameras by :data:`Z_UP_TO_Y_UP` and moves them so that the object's visual hull
  (:func:`visual_hull`, the points every view sees inside its silhouette) stands on y = 0, centred over the origin;
  the field is trained in that frame, with the hull's box (grown by a margin) as its scene box.

The trained field becomes a simulated solid in :mod:`pienerf.nerf.solid` and a warped preview in
:mod:`pienerf.render.previews`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch

from kernels import backend
from kernels.hashgrid import HashGridConfig
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.datasets import NerfDataset, load_nerf_dataset
from pienerf.nerf.field import NGPConfig, NGPField
from pienerf.nerf.training import (
    NerfCheckpoint,
    TrainConfig,
    Trainer,
    load_checkpoint,
    start_optimizer_import,
)
from pienerf.paths import cache_root

__all__ = ["Z_UP_TO_Y_UP", "NerfFit", "dataset_nerf", "dataset_nerf_path", "fit_nerf", "visual_hull"]

Progress = Callable[[str, float], None]
"""Progress callback: ``(stage, fraction in [0, 1])``."""


Z_UP_TO_Y_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking Blender's z-up world to the simulator's y-up one: (x, y, z) → (x, z, −y)."""

_FORMAT = "1"
"""Bumped whenever the fitting recipe changes; part of every cached checkpoint's hash."""

_LATER_SETTINGS = {("ngp", "hashgrid", "table_dtype"): "float32"}
"""Settings added after fits were first digested, with the value that behaves as before they existed: a fit that keeps
that value digests without the setting, so the NeRFs fitted (and shipped) before it was added are still found."""


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
        """Ten hex digits of a hash over these settings, the recipe version and ``source`` (what was fitted). What
        runs the MLPs (``ngp.mlp``) is left out, as the device is: it changes how a fit is computed, not what it is."""
        settings = asdict(self)
        settings["ngp"].pop("mlp", None)
        for (*parents, name), unchanged in _LATER_SETTINGS.items():
            where = settings
            for parent in parents:
                where = where[parent]
            if where.get(name) == unchanged:
                del where[name]
        payload = {"format": _FORMAT, "fit": settings, "source": source}
        return hashlib.sha1(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:10]


def fit_nerf(
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
    trainer.keep_averaged_weights()
    trainer.save(path)
    trainer.field.eval()
    return NerfCheckpoint(trainer.field, trainer.grid, trainer.step, fit.train, None)


def visual_hull(
    cameras: Cameras, alphas: torch.Tensor, lo, hi, resolution: int = 64, threshold: float = 0.5
) -> torch.Tensor:
    """Centres of the grid cells inside every view's silhouette: the object's visual hull.

    A cell centre belongs to the hull when every view that sees it (it projects inside the image, in front of the
    camera) finds coverage ``alpha ≥ threshold`` at its pixel; a point no view sees is dropped.

    Args:
        cameras: the views (OpenGL axes, :class:`pienerf.nerf.Cameras`).
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
        u, v, depth = cameras.project(view, points)
        front = depth > 1e-6
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
    start_optimizer_import()  # a fit follows: its optimizer's import overlaps with the loading
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
    return fit_nerf(field_, dataset, fit, path, progress, folder.name)


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
    return cache_root(cache_dir) / "nerf" / f"{folder.name}-{fit.digest(**source)}.pt"
