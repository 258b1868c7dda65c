"""Training the NGP NeRF of PIE-NeRF §3.1 on posed RGBA images, checkpoints, and held-out evaluation.

The recipe is instant-NGP's (Müller et al. 2022, §5.4 and Appendix E):

* each step renders ``batch_rays`` rays through random pixels of random training views (the batch mixes
  views) and minimises the mean squared colour error (the loss PSNR measures);
* Adam with ``β = (0.9, 0.99)``, ``ε = 1e-15``; the hash table carries no weight decay (an entry only
  sees gradient when a ray visits it), the MLPs L2 weight decay ``1e-6``. Both learn at ``1e-2`` by
  default, instant-NGP's rate: with ``lr_mlp = 1e-3`` the bias-free MLPs learnt so slowly that the test's
  ball scene reached 17.8 dB on held-out views after 200 steps, against 29 dB (training batch) with
  ``1e-2``. Both rates decay exponentially to ``lr_final_factor`` of their start over ``steps``;
* every ray is composited over its own random background colour, and its target pixel over the same
  colour (``target = premultiplied + (1 − α) · background``): a constant background would let the
  network paint it into empty space instead of learning transparency;
* the occupancy grid is left fully occupied for ``grid_warmup_steps`` (16: a fully occupied grid makes every ray
  march the whole box, so fewer warm-up steps reach a higher PSNR in the same time; ``docs/benchmarks.md``, NeRF
  training), then updated every ``grid_update_every`` steps: the first time
  at every cell, later (large grids) at a quarter of the cells drawn uniformly and a quarter drawn among the
  occupied ones, each stored density decaying by ``grid_decay`` (:meth:`pienerf.nerf.OccupancyGrid.update`);
* views are rendered with a running average of the weights (``average_decay``, instant-NGP's EMA of 0.95).

Checkpoints are written atomically (a temporary file in the same folder, then ``os.replace``), so an
interrupted save never leaves a half-written checkpoint under the final name.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import os
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from kernels import backend
from kernels.image_metrics import psnr, ssim
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.datasets import NerfDataset
from pienerf.nerf.field import NGPConfig, NGPField, OccupancyGrid, render_rays

__all__ = [
    "CHECKPOINT_FORMAT",
    "NerfCheckpoint",
    "TrainConfig",
    "Trainer",
    "load_checkpoint",
    "save_checkpoint",
    "start_optimizer_import",
]

CHECKPOINT_FORMAT = "pienerf-ngp-v1"
_GRID_FULL_UPDATE_CELLS = 1 << 18  # grids up to 64³ are re-evaluated at every cell on each update

_optimizer_import: threading.Thread | None = None  # the thread of start_optimizer_import


def start_optimizer_import() -> None:
    """Start importing ``torch._dynamo`` on a background thread, unless it is loaded or loading.

    ``torch.optim``'s optimizers import ``torch._dynamo`` when the first one is built (in :class:`Trainer`): Python on
    one core, the largest part of a training program's start-up after ``import torch`` (``docs/benchmarks.md``, NeRF
    training). A program that will train calls this first thing, so that the import overlaps with its
    backend start and data loading (whose image decoding releases the interpreter lock); the :class:`Trainer` then
    finds the module loaded, or waits for the rest of its import. An import that fails on the thread is retried, and
    raises, where the optimizer is built.
    """
    global _optimizer_import
    if "torch._dynamo" in sys.modules or _optimizer_import is not None:
        return
    _optimizer_import = threading.Thread(target=_import_quietly, args=("torch._dynamo",), daemon=True)
    _optimizer_import.start()


def _import_quietly(name: str) -> None:
    try:
        importlib.import_module(name)
    except Exception:  # retried, and reported, where the optimizer is built
        pass


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (instant-NGP's, module docstring).

    Attributes:
        steps: optimisation steps of a full run (the learning-rate schedule spans them).
        batch_rays: rays per step.
        lr_encoding: Adam learning rate of the hash table.
        lr_mlp: Adam learning rate of the MLPs (module docstring: why not lower).
        betas, eps: Adam's moment decays and denominator guard.
        mlp_weight_decay: L2 weight decay of the MLP weights (none on the table).
        lr_final_factor: the learning rates fall exponentially to this fraction of their start at ``steps``.
        grid_update_every: steps between occupancy-grid updates.
        grid_warmup_steps: steps before the first occupancy-grid update.
        random_background: composite every ray over a random colour (learns transparency).
        near, far: depth interval sampled along each ray, metres (the scene box clips it further).
        seed: seed of the batch sampler, jitter, backgrounds and grid updates.
        average_decay: the views are rendered with a running average of the weights, ``w̄ ← d w̄ + (1 − d) w``
            after every step (instant-NGP's exponential moving average, ``d = 0.95``): at a learning rate of 1e-2
            the raw weights jitter from step to step; 0 renders with the raw weights.
    """

    steps: int = 20_000
    batch_rays: int = 4096
    lr_encoding: float = 1e-2
    lr_mlp: float = 1e-2
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-15
    mlp_weight_decay: float = 1e-6
    lr_final_factor: float = 0.1
    grid_update_every: int = 16
    grid_warmup_steps: int = 16
    random_background: bool = True
    near: float = 0.0
    far: float = 1e10
    seed: int = 0
    average_decay: float = 0.95

    def __post_init__(self):
        if not 0.0 <= self.average_decay < 1.0:
            raise ValueError(f"average_decay must lie in [0, 1), got {self.average_decay}")
        if self.steps < 1 or self.batch_rays < 1 or self.grid_update_every < 1 or self.grid_warmup_steps < 0:
            raise ValueError(
                f"need steps, batch_rays, grid_update_every >= 1 and grid_warmup_steps >= 0, got {self}"
            )
        if not 0.0 < self.lr_final_factor <= 1.0:
            raise ValueError(f"lr_final_factor must lie in (0, 1], got {self.lr_final_factor}")


@dataclass
class NerfCheckpoint:
    """What :func:`load_checkpoint` returns.

    Attributes:
        field: the NeRF, on the backend device, in eval mode.
        grid: its occupancy grid.
        step: training steps done.
        train_config: the settings it was trained with, or ``None``.
        optimizer_state: Adam's state for resuming, or ``None``.
    """

    field: NGPField
    grid: OccupancyGrid
    step: int
    train_config: TrainConfig | None = None
    optimizer_state: dict | None = None


def save_checkpoint(
    path: str | Path,
    field: NGPField,
    grid: OccupancyGrid,
    step: int,
    train_config: TrainConfig | None = None,
    optimizer_state: dict | None = None,
) -> Path:
    """Write config, weights, occupancy grid, scene box and step to ``path`` atomically.

    Returns:
        The path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "config": field.config.to_dict(),
        "aabb": field.aabb.detach().cpu(),
        "field": {k: v.detach().cpu() for k, v in field.state_dict().items()},
        "grid": {
            "resolution": grid.resolution,
            "decay": grid.decay,
            "threshold": grid.threshold,
            "density": grid.density.cpu(),
            "occupied": grid.occupied.cpu(),
        },
        "step": int(step),
        "train_config": asdict(train_config) if train_config is not None else None,
        "optimizer": optimizer_state,
    }
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp", delete=False) as f:
        temporary = Path(f.name)
    try:
        torch.save(payload, temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path) -> NerfCheckpoint:
    """Read a checkpoint written by :func:`save_checkpoint` onto the backend device.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a readable checkpoint of this format, or its parts do not fit together.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}; train one first (Trainer.save) or fix the path")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a truncated or foreign file
        raise ValueError(
            f"{path} is not a readable checkpoint ({type(error).__name__}: {error}); it may be truncated or "
            "another kind of file: save it again with pienerf.nerf.training.save_checkpoint"
        ) from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(
            f"{path} has format {found!r}, expected {CHECKPOINT_FORMAT!r}; it was not written by "
            "pienerf.nerf.training.save_checkpoint (or by an incompatible version): retrain or convert it"
        )
    missing = [k for k in ("config", "aabb", "field", "grid", "step") if k not in payload]
    if missing:
        raise ValueError(f"{path} lacks {', '.join(missing)}; the checkpoint is incomplete: save it again")
    step = payload["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise ValueError(f"{path} holds step {step!r}, not a count of training steps >= 0: save the checkpoint again")
    try:
        config = NGPConfig.from_dict(payload["config"])
        _check_sizes(path, config, payload)
        field = NGPField(config, payload["aabb"])
        field.load_state_dict(payload["field"])
        g = payload["grid"]
        grid = OccupancyGrid(payload["aabb"], g["resolution"], g["decay"], g["threshold"])
        grid.load_state_dict({"aabb": payload["aabb"], "density": g["density"], "occupied": g["occupied"]})
        train_config = payload.get("train_config")
        if train_config is not None:
            train_config = TrainConfig(**{**train_config, "betas": tuple(train_config["betas"])})
    except (TypeError, KeyError, RuntimeError, ValueError, AttributeError, IndexError, OverflowError) as error:
        raise ValueError(f"{path} holds inconsistent parts ({error}); save the checkpoint again") from error
    device = backend.torch_device()
    return NerfCheckpoint(
        field=field.to(device).eval(),
        grid=grid.to(device),
        step=step,
        train_config=train_config,
        optimizer_state=payload.get("optimizer"),
    )


def _check_sizes(path: Path, config: NGPConfig, payload: dict) -> None:
    """Refuse a checkpoint whose config asks for far more memory than the file stores, before anything is allocated:
    the occupancy grid must be stored at its ``resolution³``, and the hash tables the config implies may not exceed
    the field's stored values (a header claiming 2⁶⁰ table entries must not reach the allocator)."""
    g = payload["grid"]
    if not isinstance(g, dict) or not all(isinstance(g.get(k), torch.Tensor) for k in ("density", "occupied")):
        raise ValueError("'grid' must hold 'density' and 'occupied' tensors")
    resolution = g.get("resolution")
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"grid resolution {resolution!r} is not a positive integer")
    for name in ("density", "occupied"):
        if tuple(g[name].shape) != (resolution,) * 3:
            raise ValueError(f"grid {name} is {tuple(g[name].shape)}, not {resolution}³")
    stored = payload["field"]
    if not isinstance(stored, dict) or not all(isinstance(v, torch.Tensor) for v in stored.values()):
        raise ValueError("'field' must map parameter names to tensors")
    h = config.hashgrid
    table = h.levels * h.table_size * h.features  # the encoding's [L, T, F] parameter
    held = sum(v.numel() for v in stored.values())
    widths = (config.density_hidden, config.color_hidden, config.color_layers, config.geometric_features)
    if table > held or max(widths) > held:
        raise ValueError(f"the config asks for at least {max(table, *widths)} parameters but the file holds {held}")


class Trainer:
    """Fits an :class:`~pienerf.nerf.NGPField` to a dataset's training views (module docstring).

    Args:
        field: the NeRF to train (moved to the backend device).
        dataset: training views, composited over a solid background (``load_nerf_dataset(..., background=
            (r, g, b))``) so that the straight colours can be recovered from images and alphas.
        config: optimisation settings.
        grid: the occupancy grid (default: the one ``field.config`` asks for).
        step: steps already done (when resuming).
    """

    def __init__(
        self,
        field: NGPField,
        dataset: NerfDataset,
        config: TrainConfig | None = None,
        grid: OccupancyGrid | None = None,
        step: int = 0,
    ):
        self.config = config or TrainConfig()
        self.device = backend.torch_device()
        self.field = field.to(self.device)
        self.grid = (grid or OccupancyGrid.for_field(self.field)).to(self.device)
        self.step = int(step)
        self._grid_updates = 0 if step <= self.config.grid_warmup_steps else 1
        self._premultiplied, self._alphas = _premultiplied(dataset)
        self._premultiplied, self._alphas = self._premultiplied.to(self.device), self._alphas.to(self.device)
        self._cameras = dataset.cameras.to(self.device)
        self._generator = torch.Generator(device=self.device).manual_seed(self.config.seed + self.step)
        c = self.config
        mlps = [p for name, p in self.field.named_parameters() if not name.startswith("encoding.")]
        if _optimizer_import is not None:
            _optimizer_import.join()  # (start_optimizer_import) the optimizer's import finishes on its own thread
        self.optimizer = torch.optim.Adam(
            [
                {"params": list(self.field.encoding.parameters()), "lr": c.lr_encoding, "weight_decay": 0.0},
                {"params": mlps, "lr": c.lr_mlp, "weight_decay": c.mlp_weight_decay},
            ],
            betas=c.betas,
            eps=c.eps,
            fused=self.device.type == "cuda",  # one kernel for all 16.8M table entries and the MLPs, not a dozen
        )
        self._base_lrs = [group["lr"] for group in self.optimizer.param_groups]
        self._parameters = list(self.field.parameters())
        average = c.average_decay > 0.0
        self._averaged = [p.detach().clone() for p in self._parameters] if average else None

    @classmethod
    def from_checkpoint(cls, path: str | Path, dataset: NerfDataset, config: TrainConfig | None = None) -> Trainer:
        """Resume training from a checkpoint (weights, grid, step and Adam state)."""
        checkpoint = load_checkpoint(path)
        trainer = cls(
            checkpoint.field.train(), dataset, config or checkpoint.train_config, checkpoint.grid, checkpoint.step
        )
        if checkpoint.optimizer_state is not None:
            trainer.optimizer.load_state_dict(checkpoint.optimizer_state)
        return trainer

    def save(self, path: str | Path) -> Path:
        """Atomic checkpoint of the field, grid, step, settings and Adam state."""
        return save_checkpoint(path, self.field, self.grid, self.step, self.config, self.optimizer.state_dict())

    def _sample_batch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Origins, directions, backgrounds and target colours of ``batch_rays`` random training pixels."""
        views, height, width = self._alphas.shape
        n, g = self.config.batch_rays, self._generator
        view = torch.randint(views, (n,), generator=g, device=self.device)
        row = torch.randint(height, (n,), generator=g, device=self.device)
        col = torch.randint(width, (n,), generator=g, device=self.device)
        origins, directions = self._cameras.pixel_rays(view, col + 0.5, row + 0.5)
        if self.config.random_background:
            background = torch.rand(n, 3, generator=g, device=self.device)
        else:
            background = torch.ones(n, 3, device=self.device)
        alpha = self._alphas[view, row, col][:, None]
        target = self._premultiplied[view, row, col] + (1.0 - alpha) * background
        return origins.contiguous(), directions.contiguous(), background, target

    def _update_grid(self) -> None:
        c = self.config
        if self.step < c.grid_warmup_steps or self.step % c.grid_update_every != 0:
            return
        cells = self.grid.resolution**3
        full = self._grid_updates == 0 or cells <= _GRID_FULL_UPDATE_CELLS
        self.grid.update(self.field.density, samples=None if full else cells // 4, generator=self._generator)
        self._grid_updates += 1

    def train_step(self, stats: bool = True) -> dict[str, float]:
        """One optimisation step; returns ``loss`` (MSE), ``psnr`` (dB, of the batch) and ``samples_per_ray``.

        ``stats=False`` returns ``{}`` instead, without waiting for the device: the host then queues the next step
        while this one runs.
        """
        self.field.train()
        self._update_grid()
        origins, directions, background, target = self._sample_batch()
        jitter = torch.rand(origins.shape[0], generator=self._generator, device=self.device)
        out = render_rays(
            self.field, self.grid, origins, directions, self.config.near, self.config.far, background,
            chunk=None, jitter=jitter,
        )
        loss = torch.mean((out["rgb"] - target) ** 2)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.field.mark_weights_changed()
        if self._averaged is not None:
            with torch.no_grad():
                torch._foreach_lerp_(self._averaged, self._parameters, 1.0 - self.config.average_decay)
        self.step += 1
        decay = self.config.lr_final_factor ** min(1.0, self.step / self.config.steps)
        for group, base in zip(self.optimizer.param_groups, self._base_lrs, strict=True):
            group["lr"] = base * decay
        if not stats:
            return {}
        mse = float(loss.detach())
        return {
            "loss": mse,
            "psnr": -10.0 * math.log10(max(mse, 1e-12)),
            "samples_per_ray": float(out["samples_per_ray"].float().mean()),
        }

    def train(self, steps: int | None = None, progress: bool = True) -> dict[str, float]:
        """Run ``steps`` steps (default: up to ``config.steps``) with an optional rich progress bar.

        The bar shows the loss, the batch PSNR and rays per second (batch rays over wall time per step).

        Returns:
            The statistics of the last step, with ``rays_per_second`` over the whole call.
        """
        steps = max(0, self.config.steps - self.step) if steps is None else int(steps)
        stats: dict[str, float] = {}
        start = time.perf_counter()
        bar = _progress_bar() if progress else None
        task = bar.add_task("NeRF", total=steps, stats="") if bar else None
        if bar:
            bar.start()
        try:
            for i in range(steps):
                shown = bar is not None and i % 10 == 0
                stats = self.train_step(stats=shown or i == steps - 1)
                if shown or (bar and i == steps - 1):
                    rate = self.config.batch_rays * (i + 1) / (time.perf_counter() - start)
                    line = f"loss {stats['loss']:.4f}  PSNR {stats['psnr']:.2f} dB  {rate / 1e3:.1f}k rays/s"
                    bar.update(task, completed=i + 1, stats=line)
        finally:
            if bar:
                bar.stop()
        elapsed = time.perf_counter() - start
        if steps > 0:
            stats["rays_per_second"] = self.config.batch_rays * steps / elapsed
        return stats

    @contextlib.contextmanager
    def averaged_weights(self):
        """Inside the ``with`` block the field holds the running average of its weights (``average_decay``); the
        training weights come back on leaving it. With ``average_decay = 0`` the field keeps its weights."""
        if self._averaged is None:
            yield self.field
            return
        with torch.no_grad():
            current = [p.detach().clone() for p in self._parameters]
            torch._foreach_copy_(self._parameters, self._averaged)
        self.field.mark_weights_changed()
        try:
            yield self.field
        finally:
            with torch.no_grad():
                torch._foreach_copy_(self._parameters, current)
            self.field.mark_weights_changed()

    def keep_averaged_weights(self) -> None:
        """Give the field the running average of its weights for good: call it when training is over (a checkpoint
        saved afterwards holds them; training on from it restarts the average there)."""
        if self._averaged is not None:
            with torch.no_grad():
                torch._foreach_copy_(self._parameters, self._averaged)
            self.field.mark_weights_changed()

    @torch.no_grad()
    def render_view(
        self, cameras: Cameras, index: int, background=(1.0, 1.0, 1.0), chunk: int = 4096
    ) -> dict[str, torch.Tensor]:
        """Render view ``index`` of ``cameras`` with the averaged weights (:meth:`averaged_weights`): ``rgb [H, W,
        3]``, ``opacity [H, W]``, ``depth [H, W]`` (metres)."""
        self.field.eval()
        origins, directions = cameras.to(self.device).rays(index)
        with self.averaged_weights() as field:
            out = render_rays(
                field, self.grid, origins.contiguous(), directions.contiguous(), self.config.near,
                self.config.far, background, chunk=chunk,
            )
        h, w = cameras.height, cameras.width
        return {"rgb": out["rgb"].view(h, w, 3), "opacity": out["opacity"].view(h, w), "depth": out["depth"].view(h, w)}

    def view_scores(
        self, dataset: NerfDataset, max_views: int | None = None, chunk: int = 4096
    ) -> Iterator[tuple[float, float, torch.Tensor]]:
        """Render held-out views over the dataset's background colour one by one and score each against its image.

        Args:
            dataset: the views, composited over a solid background.
            max_views: score only the first this many (``None``: all).
            chunk: rays rendered at a time.

        Yields:
            Each view's PSNR (dB), SSIM and render ``[H, W, 3]`` in [0, 1] on the backend device.

        Raises:
            ValueError: the dataset's background is ``"random"`` (the renders could not match it), or it has no views.
        """
        if isinstance(dataset.background, str):
            raise ValueError(
                "scoring needs views composited over a solid background; load them with background=(r, g, b) or "
                "recomposite them with NerfDataset.over_background"
            )
        views = len(dataset) if max_views is None else min(max_views, len(dataset))
        if views < 1:
            raise ValueError(f"no views to score (the dataset has {len(dataset)}, max_views={max_views})")
        for i in range(views):
            rgb = self.render_view(dataset.cameras, i, dataset.background, chunk=chunk)["rgb"].clamp(0.0, 1.0)
            target = dataset.images[i].to(self.device)
            yield float(psnr(rgb, target)), float(ssim(rgb, target)), rgb

    def evaluate(self, dataset: NerfDataset, max_views: int | None = None) -> dict[str, float]:
        """Mean PSNR (dB) and SSIM over held-out views (:meth:`view_scores`)."""
        scores = [(p, s) for p, s, _ in self.view_scores(dataset, max_views)]  # the renders go as they come
        return {"psnr": sum(p for p, _ in scores) / len(scores), "ssim": sum(s for _, s in scores) / len(scores)}


def _premultiplied(dataset: NerfDataset) -> tuple[torch.Tensor, torch.Tensor]:
    """Colours premultiplied by alpha, ``[N, H, W, 3]``, and alphas ``[N, H, W]`` of a dataset."""
    if isinstance(dataset.background, str):
        raise ValueError(
            "the trainer composites its own random backgrounds and needs the images' colours: load the "
            "dataset over a solid background, e.g. load_nerf_dataset(folder, background=(0, 0, 0))"
        )
    alphas = dataset.alphas.float()
    if dataset.background == (0.0, 0.0, 0.0):  # already premultiplied: no copy of the whole set
        return dataset.images, alphas
    background = torch.tensor(dataset.background, dtype=torch.float32)
    return (dataset.images - (1.0 - alphas[..., None]) * background).clamp(0.0, 1.0), alphas


def _progress_bar():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
        TextColumn("{task.fields[stats]}"),
    )
