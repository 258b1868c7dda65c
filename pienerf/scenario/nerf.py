"""The NeRF of a scenario's ``[nerf]`` table, fitted or loaded from the cache, to render warped (PIE-NeRF §4.6)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from pienerf.nerf.fitting import NerfFit, dataset_nerf, dataset_nerf_path
from pienerf.paths import SHARED_DATA
from pienerf.scenes import scene_nerf

__all__ = ["ScenarioNerf", "nerf_fit", "prepare_nerf", "progress_log"]


@dataclass
class ScenarioNerf:
    """The scenario's fitted NeRF: the rest-space field and grid, its checkpoint when it is the simulated scene."""

    field: object
    grid: object
    checkpoint: Path | None
    warps: list
    source: str
    seconds: float
    solid_resolution: int


def nerf_fit(spec: dict) -> NerfFit:
    """The :class:`pienerf.nerf.fitting.NerfFit` of a ``[nerf]`` table: its defaults, overridden by the table's keys."""
    base = NerfFit()
    hashgrid = replace(
        base.ngp.hashgrid, **{k: spec[k] for k in ("levels", "log2_table_size", "max_resolution") if k in spec}
    )
    ngp = {k: spec[k] for k in ("samples_per_diagonal", "grid_resolution", "grid_decay") if k in spec}
    if "hidden" in spec:
        ngp.update(density_hidden=spec["hidden"], color_hidden=spec["hidden"])
    steps = spec.get("steps", base.train.steps)
    train = replace(
        base.train,
        steps=steps,
        batch_rays=spec.get("batch_rays", base.train.batch_rays),
        grid_warmup_steps=min(base.train.grid_warmup_steps, max(1, steps // 4)),
    )
    sizes = {k: spec[k] for k in ("views", "resolution", "downscale", "max_views") if k in spec}
    return NerfFit(ngp=replace(base.ngp, hashgrid=hashgrid, **ngp), train=train, **sizes)


def progress_log(log, what: str):
    """A ``(stage, fraction)`` callback that logs a line at every tenth of the way."""
    reached = [-1]

    def progress(stage: str, fraction: float) -> None:
        tenth = int(10 * fraction)
        if tenth > reached[0]:
            reached[0] = tenth
            log(f"{what}: {stage}")

    return progress


def prepare_nerf(scenario: dict, cache_dir, log) -> ScenarioNerf | None:
    """Fit (or load from the cache) the NeRF of the scenario's ``[nerf]`` table; ``None`` without one.

    ``log(line)`` hears the progress at every tenth of the way; ``cache_dir`` is :func:`pienerf.paths.cache_root`'s.
    """
    spec = scenario.get("nerf")
    if spec is None:
        return None
    fit = nerf_fit(spec)
    source = spec.get("source", "scene")
    progress = progress_log(log, scenario.get("name", "scenario"))
    start = time.perf_counter()
    checkpoint = None
    if source == "scene":
        trained = scene_nerf(scenario["scene"]["name"], fit, cache_dir, progress)
    else:
        folder, up = SHARED_DATA / source[5:], spec.get("up", "z")
        trained = dataset_nerf(folder, fit, up, cache_dir, progress)
        checkpoint = dataset_nerf_path(folder, fit, up, cache_dir)
    return ScenarioNerf(
        trained.field,
        trained.grid,
        checkpoint,
        list(spec.get("warps", ["quadratic"])),
        source,
        time.perf_counter() - start,
        spec.get("solid_resolution", 96),
    )
