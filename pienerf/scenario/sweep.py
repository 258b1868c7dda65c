"""A scenario's ``[sweep]``: every point rendered into its own folder by the executor, an index of them all and a
contact sheet of their key frames.

A point is one call of :func:`pienerf.scenario.render_scenario` on the scenario with the point's values set
(:func:`pienerf.scenario.apply_sweep_point`); :func:`run_sweep` hands the points to
:func:`pienerf.executor.run_points` (in this process or on Ray actors), which writes ``sweep.json`` and ``sweep.csv``
(each point's values, status and metrics), then draws ``contact_sheet.png``: the last frame of every point, labelled
with its name and values, in a grid. The format of the ``[sweep]`` table and the files are described in
``docs/sweeps.md``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from kernels import backend
from pienerf.executor import ExecutorConfig, run_points
from pienerf.scenario.runner import label_tile, render_scenario, save_png
from pienerf.scenario.schema import apply_sweep_point, sweep_points

__all__ = ["CONTACT_SHEET", "SWEEP_INDEX", "contact_sheet", "point_summary", "render_point", "run_sweep"]

SWEEP_INDEX = "sweep"
"""Stem of the sweep's index files, ``sweep.json`` and ``sweep.csv``."""

CONTACT_SHEET = "contact_sheet.png"
"""The picture of the whole sweep: every point's last frame in a grid."""

_TILE_WIDTH = 240
"""Width (px) of a point's tile on the contact sheet: its frame scaled to it, up or down."""


def point_summary(metrics: dict) -> dict:
    """What the index keeps of a point's ``metrics.json``: frames, build and render seconds, whether ``[expect]``
    passed, and per variant its final relative volume, largest and centre displacement (m), converged fraction of
    steps and median step time (s)."""
    if "skipped" in metrics:
        return {"skipped": metrics["skipped"]}
    variants = {}
    for name, run in metrics.get("variants", {}).items():
        solver = run["solver"]
        variants[name] = {
            "final_relative_volume": run["final_relative_volume"],
            "final_max_displacement_m": run["final_max_displacement_m"],
            "final_centre_displacement_m": run["final_centre_displacement_m"],
            "converged_fraction": (solver["steps"] - solver["unconverged_steps"]) / max(solver["steps"], 1),
            "step_seconds_median": run["step_seconds_median"],
        }
    return {
        "frames": metrics.get("frames"),
        "build_seconds": metrics.get("build_seconds"),
        "render_seconds": metrics.get("render_seconds"),
        "expect_passed": metrics.get("expect", {}).get("passed"),
        "wrong_results": len(metrics.get("wrong_results", {})),
        "variants": variants,
    }


def render_point(
    parameters: dict, folder: Path, *, scenario: dict, device: str, cache_dir: str | None = None, log=print
) -> dict:
    """One sweep point: the scenario with ``parameters`` (dotted field → value) set, rendered into ``folder`` on
    ``device`` (initialised here: a Ray worker is a fresh process); returns :func:`point_summary` of its metrics."""
    backend.init(device)
    point = apply_sweep_point(scenario, parameters)
    return point_summary(render_scenario(point, Path(folder), log=log, cache_dir=cache_dir))


def _key_frame(folder: Path) -> np.ndarray | None:
    """The last frame a point wrote (``frames/frame_NNNN.png``, RGBA), or ``None``."""
    frames = sorted((folder / "frames").glob("frame_*.png"))
    if not frames:
        return None
    return np.asarray(Image.open(frames[-1]).convert("RGBA"))


def _tile(image: np.ndarray | None, height: int, text: str) -> torch.Tensor:
    """A contact-sheet tile ``[height, _TILE_WIDTH, 4]``: ``image`` scaled to the tile's width over white (grey where
    there is none), ``text`` in its corner."""
    canvas = Image.new("RGBA", (_TILE_WIDTH, height), (255, 255, 255, 255) if image is not None else (200,) * 4)
    if image is not None:
        scaled = Image.fromarray(image).resize(
            (_TILE_WIDTH, max(1, round(image.shape[0] * _TILE_WIDTH / image.shape[1]))),
            Image.NEAREST if image.shape[1] < _TILE_WIDTH else Image.LANCZOS,
        )
        canvas.alpha_composite(scaled, (0, 0))
    tile = torch.from_numpy(np.asarray(canvas).astype(np.float32) / 255.0)
    return label_tile(tile, text)


def contact_sheet(entries: list[dict], root: Path, path: Path | None = None, columns: int | None = None) -> Path:
    """Every point's last frame (its folder under ``root``) in a grid of ``columns`` (default: about square), each
    labelled with its name, status and values; written whole to ``path`` (default ``root/contact_sheet.png``)."""
    root = Path(root)
    path = Path(path) if path is not None else root / CONTACT_SHEET
    images = [_key_frame(root / entry["name"]) if entry["status"] == "complete" else None for entry in entries]
    aspect = max((im.shape[0] / im.shape[1] for im in images if im is not None), default=0.75)
    height = max(96, round(_TILE_WIDTH * aspect))
    tiles = []
    for entry, image in zip(entries, images, strict=True):
        values = "\n".join(
            f"{key.split('.')[-1]} = {value:g}" if isinstance(value, float) else f"{key} = {value}"
            for key, value in entry["parameters"].items()
        )
        status = "" if entry["status"] == "complete" else f" ({entry['status']})"
        tiles.append(_tile(image, height, f"{entry['name']}{status}\n{values}"))
    columns = columns or max(1, math.ceil(math.sqrt(len(tiles))))
    rows = math.ceil(len(tiles) / columns)
    sheet = torch.ones(rows * height, columns * _TILE_WIDTH, 4)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * height : (r + 1) * height, c * _TILE_WIDTH : (c + 1) * _TILE_WIDTH] = tile
    save_png((sheet.clamp(0, 1) * 255).round().to(torch.uint8).numpy(), path)
    return path


def run_sweep(
    scenario: dict,
    out: Path,
    config: ExecutorConfig = ExecutorConfig(),
    cache_dir: Path | str | None = None,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Render every point of the scenario's ``[sweep]`` under ``out`` (``out/pNNN``) with the executor of
    ``config``, skipping points already complete there; write ``sweep.json``, ``sweep.csv`` and the contact sheet.
    Returns the points' records (:func:`pienerf.executor.run_points`).

    Raises:
        ScenarioError: the scenario has no ``[sweep]`` or a point's value is bad, before any work.
        pienerf.executor.ExecutorError: Ray is wanted and missing, or its cluster cannot be reached.
    """
    points = sweep_points(scenario)
    base = {key: value for key, value in scenario.items() if key != "sweep"}
    function = functools.partial(
        render_point,
        scenario=base,
        device=config.device,
        cache_dir=str(cache_dir) if cache_dir is not None else None,
    )
    extra = {"scenario": scenario.get("name", "scenario"), "sweep": scenario["sweep"]}
    entries = run_points(points, function, out, config, index=SWEEP_INDEX, log=log, extra=extra)
    sheet = contact_sheet(entries, out)
    counts = {s: sum(e["status"] == s for e in entries) for s in ("complete", "failed", "skipped")}
    log(
        f"{extra['scenario']}: sweep of {len(entries)} points: {counts['complete']} complete, {counts['failed']} "
        f"failed, {counts['skipped']} skipped → {out / (SWEEP_INDEX + '.json')}, {sheet}"
    )
    return entries
