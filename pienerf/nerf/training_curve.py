"""How fast a NeRF learns and where it still errs: a training curve on unseen views, and error images.

:func:`train_curve` trains a :class:`~pienerf.nerf.training.Trainer` up to a list of training wall times and scores the
field at each on views it never trained on (mean PSNR and SSIM, :mod:`kernels.image_metrics`, and PSNR per view).
The evaluations are excluded from the training clock: at a checkpoint the clock stops, the device is synchronised,
the views are rendered and scored, and the clock restarts. A checkpoint is taken at the first step boundary past its
time, so its ``seconds`` may exceed the nominal time by up to one step.

:func:`write_error_images` shows where the last checkpoint errs: one PNG per view, render | ground truth | error heat
map (the absolute error averaged over RGB, full scale :data:`ERROR_FULL_SCALE`, the perceptually uniform *inferno*
colour map), under a title row naming the view, its PSNR and the scale; and one contact sheet of all views.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from kernels import backend
from pienerf.nerf.datasets import NerfDataset
from pienerf.nerf.training import Trainer
from pienerf.output_files import atomic_path

__all__ = [
    "ERROR_FULL_SCALE",
    "CurvePoint",
    "TrainingCurve",
    "error_heat_map",
    "error_panel",
    "train_curve",
    "write_error_images",
]

ERROR_FULL_SCALE = 0.1
"""Absolute colour error (mean over RGB, colours in [0, 1]) shown at the top of the heat map's colour scale."""

_TITLE_HEIGHT = 22  # pixels of a panel's title row
_SHEET_PANEL_WIDTH = 1200  # the contact sheet shrinks panels wider than this by an integer factor


@dataclass(frozen=True)
class CurvePoint:
    """One checkpoint of a training curve.

    Attributes:
        seconds: training wall time at the checkpoint, s (evaluations excluded).
        steps: optimisation steps done.
        psnr: mean PSNR over the scored views, dB.
        ssim: mean SSIM over the scored views.
        view_psnr: PSNR of each scored view, dB, in the dataset's order.
    """

    seconds: float
    steps: int
    psnr: float
    ssim: float
    view_psnr: tuple[float, ...]

    def record(self) -> dict:
        """``{seconds, steps, psnr, ssim}``, for a JSON record."""
        return {"seconds": self.seconds, "steps": self.steps, "psnr": self.psnr, "ssim": self.ssim}


@dataclass
class TrainingCurve:
    """What :func:`train_curve` returns.

    Attributes:
        points: the checkpoints, in time order.
        renders: ``[V, H, W, 3]`` float32 renders of the scored views at the last checkpoint, CPU, in [0, 1].
        stopped_early: training stopped at the stop PSNR before the last checkpoint time.
    """

    points: list[CurvePoint]
    renders: torch.Tensor
    stopped_early: bool = False

    def seconds_to_psnr(self, target: float) -> float | None:
        """Training seconds until the mean PSNR first reaches ``target`` dB: interpolated linearly in PSNR between
        the last checkpoint below it and the first at or above it (the first checkpoint's time when that one
        already reaches it); ``None`` when no checkpoint reaches it."""
        previous = None
        for point in self.points:
            if point.psnr >= target:
                if previous is None or point.psnr == previous.psnr:
                    return point.seconds
                share = (target - previous.psnr) / (point.psnr - previous.psnr)
                return previous.seconds + share * (point.seconds - previous.seconds)
            previous = point
        return None


def train_curve(
    trainer: Trainer,
    views: NerfDataset,
    checkpoints_s: Sequence[float],
    stop_psnr: float | None = None,
    chunk: int = 4096,
    on_checkpoint: Callable[[CurvePoint], None] | None = None,
) -> TrainingCurve:
    """Train until each of ``checkpoints_s`` (training wall time, s) and score ``views`` there (module docstring).

    Args:
        trainer: the trainer to advance (its step counter goes on from where it is).
        views: unseen views over a solid background, scored at every checkpoint.
        checkpoints_s: training wall times of the checkpoints, s, increasing; the last is the training budget.
        stop_psnr: stop after the first checkpoint whose mean PSNR reaches this, dB (``None``: never).
        chunk: rays rendered at a time in the evaluations.
        on_checkpoint: called with each checkpoint as it is taken (progress lines).

    Returns:
        The curve, with the renders of the last checkpoint.
    """
    checkpoints = [float(s) for s in checkpoints_s]
    rising = all(b > a for a, b in zip(checkpoints, checkpoints[1:], strict=False))
    if not checkpoints or checkpoints[0] <= 0.0 or not rising:
        raise ValueError(f"checkpoints_s must be positive training times in increasing order, got {checkpoints_s!r}")
    points: list[CurvePoint] = []
    renders = torch.zeros(0)
    clock = 0.0
    for target in checkpoints:
        if points and clock >= target:  # one step outlasted this checkpoint: the previous one stands for it
            continue
        start = time.perf_counter()
        while clock + (time.perf_counter() - start) < target:
            trainer.train_step(stats=False)
        backend.synchronize()
        clock += time.perf_counter() - start
        scored = list(trainer.view_scores(views, chunk=chunk))
        view_psnr, view_ssim = [p for p, _, _ in scored], [s for _, s, _ in scored]
        renders = torch.stack([rgb for _, _, rgb in scored])
        point = CurvePoint(
            clock, trainer.step, sum(view_psnr) / len(view_psnr), sum(view_ssim) / len(view_ssim), tuple(view_psnr)
        )
        points.append(point)
        if on_checkpoint is not None:
            on_checkpoint(point)
        if stop_psnr is not None and point.psnr >= stop_psnr:
            return TrainingCurve(points, renders.cpu(), stopped_early=target < checkpoints[-1])
    return TrainingCurve(points, renders.cpu())


def error_heat_map(render: torch.Tensor, target: torch.Tensor, full_scale: float = ERROR_FULL_SCALE) -> np.ndarray:
    """Heat map of the absolute colour error, ``|render − target|`` averaged over RGB, on the *inferno* colour map.

    Args:
        render, target: ``[H, W, 3]`` images in [0, 1].
        full_scale: error drawn at the top of the colour map (larger errors saturate).

    Returns:
        ``[H, W, 3]`` uint8 RGB.
    """
    if render.shape != target.shape or render.dim() != 3 or render.shape[-1] != 3:
        raise ValueError(f"need two [H, W, 3] images of one shape, got {tuple(render.shape)}, {tuple(target.shape)}")
    if not full_scale > 0.0:
        raise ValueError(f"full_scale must be a positive colour error, got {full_scale}")
    error = (render.float().cpu() - target.float().cpu()).abs().mean(-1)
    level = (error / full_scale).clamp(0.0, 1.0).mul(255.0).round().to(torch.uint8).numpy()
    return _inferno()[level]


def error_panel(
    render: torch.Tensor, target: torch.Tensor, title: str, full_scale: float = ERROR_FULL_SCALE
) -> np.ndarray:
    """render | ground truth | error heat map side by side, under a row labelling them (``title`` beside "render")
    with the heat map's colour scale.

    Args:
        render, target: ``[H, W, 3]`` images in [0, 1].
        title: text of the title row (the view's name and PSNR, say).
        full_scale: the heat map's full scale (:func:`error_heat_map`).

    Returns:
        ``[22 + H, 3 W, 3]`` uint8 RGB.
    """
    from PIL import Image, ImageDraw, ImageFont

    heat = error_heat_map(render, target, full_scale)
    height, width = heat.shape[:2]
    images = [_to_uint8(render), _to_uint8(target), heat]
    panel = np.full((_TITLE_HEIGHT + height, 3 * width, 3), 255, dtype=np.uint8)
    for k, image in enumerate(images):
        panel[_TITLE_HEIGHT:, k * width : (k + 1) * width] = image
    canvas = Image.fromarray(panel)
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default(size=13)
    labels = (f"render  {title}", "ground truth", "|error|, RGB mean")
    for k, label in enumerate(labels):
        draw.text((k * width + 4, 3), label, fill=(0, 0, 0), font=font)
    # The heat map's colour bar, 0 to full scale, right of its label when there is room.
    bar_left = int(2 * width + 4 + draw.textlength(labels[2], font=font) + 18)
    bar_width = min(120, 3 * width - 34 - bar_left)
    if bar_width >= 16:
        ramp = _inferno()[np.linspace(0, 255, bar_width).round().astype(np.intp)]
        canvas.paste(Image.fromarray(np.repeat(ramp[None], _TITLE_HEIGHT - 10, axis=0)), (bar_left, 5))
        draw.text((bar_left - 11, 3), "0", fill=(0, 0, 0), font=font)
        draw.text((bar_left + bar_width + 3, 3), f"{full_scale:g}", fill=(0, 0, 0), font=font)
    return np.asarray(canvas)


def write_error_images(
    folder: str | Path,
    names: Sequence[str],
    renders: torch.Tensor,
    targets: torch.Tensor,
    view_psnr: Sequence[float],
    full_scale: float = ERROR_FULL_SCALE,
) -> dict:
    """Write one :func:`error_panel` PNG per view and a contact sheet of all of them into ``folder`` (created).

    Files are written atomically (:func:`pienerf.output_files.atomic_path`). A view's file is named after the last
    part of its name (``./train/r_8`` gives ``r_8.png``); the sheet is ``sheet.png``, its panels shrunk by an
    integer factor to at most 1200 pixels wide.

    Args:
        folder: where the images go.
        names: ``V`` view names.
        renders, targets: ``[V, H, W, 3]`` images in [0, 1].
        view_psnr: ``V`` PSNRs, dB, for the titles.
        full_scale: the heat maps' full scale.

    Returns:
        ``{"views": {name: path}, "sheet": path}`` (paths as strings).
    """
    from PIL import Image

    if not (len(names) == len(renders) == len(targets) == len(view_psnr)) or len(names) == 0:
        raise ValueError(
            f"need one name, render, target and PSNR per view, got {len(names)}, {len(renders)}, {len(targets)} "
            f"and {len(view_psnr)}"
        )
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files, panels, used = {}, [], set()
    for name, render, target, value in zip(names, renders, targets, view_psnr, strict=True):
        stem = _file_stem(name, used)
        panel = error_panel(render, target, f"{name}  {value:.2f} dB", full_scale)
        path = folder / f"{stem}.png"
        with atomic_path(path) as temporary:
            Image.fromarray(panel).save(temporary)
        files[name] = str(path)
        panels.append(panel)
    shrink = max(1, math.ceil(panels[0].shape[1] / _SHEET_PANEL_WIDTH))
    sheet = np.concatenate([p[::shrink, ::shrink] for p in panels]) if shrink > 1 else np.concatenate(panels)
    sheet_path = folder / "sheet.png"
    with atomic_path(sheet_path) as temporary:
        Image.fromarray(np.ascontiguousarray(sheet)).save(temporary)
    return {"views": files, "sheet": str(sheet_path)}


def _file_stem(name: str, used: set) -> str:
    """A file name for a view: the last part of its name, letters, digits, ``-`` and ``_`` only, made unique."""
    base = "".join(c if c.isalnum() or c in "-_" else "_" for c in Path(str(name)).name) or "view"
    stem, k = base, 1
    while stem in used:
        k += 1
        stem = f"{base}_{k}"
    used.add(stem)
    return stem


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    return image.float().cpu().clamp(0.0, 1.0).mul(255.0).round().to(torch.uint8).numpy()


@functools.cache
def _inferno() -> np.ndarray:
    """``[256, 3]`` uint8 look-up table of matplotlib's *inferno* colour map."""
    from matplotlib import colormaps  # matplotlib: heavy to import, needed only when images are written

    return (colormaps["inferno"](np.arange(256))[:, :3] * 255.0).round().astype(np.uint8)
