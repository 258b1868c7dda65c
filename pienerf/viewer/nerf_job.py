"""The viewer's NeRF: loading a checkpoint, and fitting an embedded scene's NeRF in a separate process.

The first time the NeRF view is chosen on a scene with no cached NeRF, :class:`NerfJob` fits two in turn: a coarse
one (:data:`FIRST_FIT`, a small hash grid on the same rendered views) shown as soon as it is ready, then the full
one (:class:`pienerf.nerf.fitting.NerfFit`'s defaults), which replaces it. The process runs at a lower priority on
one torch thread so that the simulation keeps its frame rate on a machine of few cores (figures in
``docs/benchmarks.md``). Both are cached by :func:`pienerf.scenes.scene_nerf`, so a later start loads them.

The plant's coarse NeRF also ships with the project (:data:`SHIPPED_NERFS`, ``assets/nerf/``): the scene is the
project's own, so :func:`load_nerf` shows it at once when the settings asked for are :data:`FIRST_FIT` (they are
part of the file's name) and falls back to the cache or a fit otherwise. It is fitted by the project's own code and
stored with float16 weights and no optimizer state; regenerate it after a change to the plant, to
:data:`FIRST_FIT` or to the fitting recipe with ``python -m apps.demo --build-nerf-asset`` (:func:`build_nerf_asset`).
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import tempfile
from pathlib import Path

import torch

from kernels import backend
from kernels.hashgrid import HashGridConfig
from pienerf.nerf.field import NGPConfig
from pienerf.nerf.fitting import NerfFit
from pienerf.nerf.training import TrainConfig, load_checkpoint, save_checkpoint
from pienerf.render.previews import RenderBackend
from pienerf.scenes import SCENES, scene_nerf
from pienerf.session import Simulation

__all__ = [
    "ASSET_DIR",
    "FIRST_FIT",
    "SHIPPED_NERFS",
    "NerfJob",
    "build_nerf_asset",
    "load_nerf",
    "shipped_nerf",
    "shipped_nerf_path",
    "smoke_fit",
]

FIRST_FIT = NerfFit(
    ngp=NGPConfig(
        hashgrid=HashGridConfig(levels=8, features=2, log2_table_size=14, base_resolution=8, max_resolution=128),
        density_hidden=32,
        color_hidden=32,
        color_layers=1,
        grid_resolution=48,
        samples_per_diagonal=192,
    ),
    train=TrainConfig(steps=300, batch_rays=1024, grid_warmup_steps=16),
)
"""The coarse NeRF shown first: the default fit's views (48 of 64²) on an 8-level hash grid of 2¹⁴ entries, 32-wide
layers and 1024 rays a step for 300 steps, about a tenth of the default fit's work per step."""

ASSET_DIR = Path(__file__).resolve().parents[2] / "assets" / "nerf"
"""Where the NeRFs that ship with the project lie."""

SHIPPED_NERFS = ("plant",)
"""Embedded scenes whose :data:`FIRST_FIT` NeRF ships in :data:`ASSET_DIR`."""

_NICENESS = 5  # the fitting process yields the cores to the simulation loop


def smoke_fit() -> NerfFit:
    """A NeRF fit of a few seconds for smoke runs (16 views of 32², 60 steps, a small hash grid)."""
    ngp = NGPConfig(
        hashgrid=HashGridConfig(levels=6, features=2, log2_table_size=12, base_resolution=8, max_resolution=64),
        density_hidden=16,
        color_hidden=16,
        color_layers=1,
        grid_resolution=32,
        samples_per_diagonal=128,
    )
    return NerfFit(ngp=ngp, train=TrainConfig(steps=60, batch_rays=512, grid_warmup_steps=16), views=16, resolution=32)


def shipped_nerf_path(scene: str, fit=None, asset_dir: str | Path | None = None) -> Path:
    """Where the shipped NeRF of ``scene`` fitted with ``fit`` (default :data:`FIRST_FIT`) lies (or would lie):
    ``<asset_dir>/<scene>-<digest>.pt``, the digest of :meth:`pienerf.nerf.fitting.NerfFit.digest`, so a file
    fitted with other settings is never taken for this one."""
    fit = FIRST_FIT if fit is None else fit
    return Path(ASSET_DIR if asset_dir is None else asset_dir) / f"{scene}-{fit.digest(scene=scene)}.pt"


def build_nerf_asset(scene: str = "plant", asset_dir: str | Path | None = None, progress=None) -> Path:
    """Fit ``scene``'s NeRF with :data:`FIRST_FIT` (:func:`pienerf.scenes.scene_nerf`, in a scratch cache so the
    views and the fit are made afresh) and write it compactly to :func:`shipped_nerf_path`: float16 weights and
    occupancy densities, no optimizer state; :func:`pienerf.nerf.training.load_checkpoint` reads it (as float32).
    Returns the path written; other NeRFs of ``scene`` in ``asset_dir`` (older settings) are removed."""
    if scene not in SCENES:
        raise ValueError(f"no NeRF can be fitted to {scene!r}: embedded scenes are {', '.join(SCENES)}")
    path = shipped_nerf_path(scene, asset_dir=asset_dir)
    with tempfile.TemporaryDirectory() as scratch:
        trained = scene_nerf(scene, FIRST_FIT, scratch, progress)
        save_checkpoint(Path(scratch) / "full.pt", trained.field, trained.grid, trained.step)
        payload = torch.load(Path(scratch) / "full.pt", map_location="cpu", weights_only=True)
    # Weights and densities to float16 (the scene box and any integer buffer stay as they are).
    payload["field"] = {name: _half(name, value) for name, value in payload["field"].items()}
    payload["grid"]["density"] = payload["grid"]["density"].half()
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    torch.save(payload, partial)
    partial.replace(path)
    for old in path.parent.glob(f"{scene}-*.pt"):
        if old != path:
            old.unlink()
    return path


def _half(name: str, value: torch.Tensor) -> torch.Tensor:
    """``value`` in float16 when it is a float32 weight (not the scene box)."""
    return value.half() if value.dtype == torch.float32 and "aabb" not in name else value


def shipped_nerf(scene: str, fit=None) -> bool:
    """Whether a NeRF of ``scene`` ships with the project for ``fit`` (``None``, the viewer's default, or
    :data:`FIRST_FIT`): :func:`load_nerf` then loads it instead of fitting."""
    return (fit is None or fit == FIRST_FIT) and shipped_nerf_path(scene).is_file()


def load_nerf(
    simulation: Simulation,
    checkpoint: str | None = None,
    fit=None,
    cache_dir: str | None = None,
    progress=None,
    replace: bool = False,
) -> RenderBackend:
    """Give ``simulation`` its ``"nerf"`` render mode: a given checkpoint, else the NeRF that ships with its scene
    when ``fit`` asks for no other (:func:`shipped_nerf`), else the NeRF of its embedded scene (trained on the
    scene's rendered views, or loaded from the cache); returns the render backend. One already
    there is kept unless ``replace`` (a refined NeRF taking the coarse one's place)."""
    if "nerf" in simulation.render_backends and not replace:
        return simulation.render_backends["nerf"]
    if checkpoint is not None:
        trained = load_checkpoint(checkpoint)
    elif shipped_nerf(simulation.config.scene, fit):
        trained = load_checkpoint(shipped_nerf_path(simulation.config.scene))
    elif simulation.config.scene in SCENES:
        trained = scene_nerf(simulation.config.scene, fit or NerfFit(), cache_dir, progress)
    else:
        raise ValueError(
            f"no NeRF for the mesh scene {simulation.config.scene!r}: pass --nerf-checkpoint PATH "
            "(trained in the mesh's coordinates) or use an embedded scene"
        )
    return simulation.add_nerf_render(trained.field, trained.grid)


def _fit_in_child(scene: str, fits: list, cache_dir: str | None, device: str, messages) -> None:
    """The body of a :class:`NerfJob`'s process: fit (or load) each of ``fits`` into the cache, reporting."""
    try:
        os.nice(_NICENESS)
    except OSError:  # not allowed here: fit at the same priority
        pass
    torch.set_num_threads(1)
    backend.init(device)
    for index, fit in enumerate(fits):
        try:
            scene_nerf(scene, fit, cache_dir, lambda stage, fraction: messages.put(("progress", stage, fraction)))
        except Exception as error:  # reported to the parent, which shows it
            messages.put(("error", f"{type(error).__name__}: {error}", index))
            return
        messages.put(("ready", "", index))
    messages.put(("done", "", len(fits)))


class NerfJob:
    """The fit of an embedded scene's NeRF (:func:`pienerf.scenes.scene_nerf`) in a separate process.

    The process writes each checkpoint to the scene cache, where :func:`load_nerf` then finds it. :meth:`poll`
    never blocks.

    Args:
        scene: one of :data:`pienerf.scenes.SCENES`.
        fit: the fitting settings; ``None`` fits :data:`FIRST_FIT`, then :class:`pienerf.nerf.fitting.NerfFit`'s
            defaults (see :attr:`fits`).
        cache_dir: the cache root (as :func:`pienerf.scenes.scene_nerf`).
        device: where the process fits (default: this process's device).

    Attributes:
        fits: the fits in the order they are made.
        ready: how many of :attr:`fits` are in the cache.
        finished: the process has ended.
        error: why it failed, or ``None``.
    """

    def __init__(self, scene: str, fit=None, cache_dir: str | None = None, device: str | None = None):
        if scene not in SCENES:
            raise ValueError(f"no NeRF can be fitted to {scene!r}: embedded scenes are {', '.join(SCENES)}")
        self.fits = [fit] if fit is not None else [FIRST_FIT, NerfFit()]
        context = multiprocessing.get_context("spawn")  # a fresh interpreter: Taichi and torch state are per process
        self._messages = context.Queue()
        device = device or backend.current_device() or backend.default_device()
        self._process = context.Process(
            target=_fit_in_child, args=(scene, self.fits, cache_dir, device, self._messages), daemon=True
        )
        self._process.start()
        self.ready = 0
        self.finished = False
        self.error: str | None = None

    def poll(self) -> list[tuple[str, float]]:
        """Progress reported since the last call, as ``(stage, fraction)``; sets :attr:`ready`, :attr:`finished`
        and :attr:`error`."""
        updates = []
        alive = self._process.is_alive()
        while True:
            try:
                kind, stage, value = self._messages.get_nowait()
            except queue.Empty:
                break
            if kind == "error":
                self.error, self.finished = stage, True
            elif kind == "ready":
                self.ready = value + 1
            elif kind == "done":
                self.finished = True
            else:
                updates.append((stage, value))
        if not alive and not self.finished:
            self.finished = True
            self.error = f"the fitting process ended with exit code {self._process.exitcode}"
        if self.finished:
            self._process.join(5.0)
        return updates

    def cancel(self) -> None:
        """Stop the process (a partly written checkpoint is never left: the fit saves atomically)."""
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(5.0)
        self.finished = True
