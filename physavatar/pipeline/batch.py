"""Batches of avatars: the pipeline's stages over many capture folders, or over a synthetic study of garments ×
motions × fabrics, one experiment folder per point.

A *point* is a name and a table of JSON-ready parameters; :func:`run_batch_point` runs it: one call of the stages
the pipeline already has (:func:`physavatar.pipeline.run_stages` over :mod:`~physavatar.pipeline.stages`' and
:mod:`~physavatar.pipeline.user_capture`'s stage functions) into the point's folder, and returns what the stages
measured (:func:`point_metrics`). The points are made by

* :func:`capture_points`: one per capture folder (``docs/capture.md``), the stages of :data:`CAPTURE_STAGES`;
* :func:`study_points`: every combination of a garment (:data:`STUDY_GARMENTS`), a fitting motion
  (:data:`physavatar.body.MOTIONS`) and a fabric (``KAPPA_S:KAPPA_B``, the stiffness multipliers of the truth), the
  synthetic experiment's stages (:data:`STAGES`) with that truth.

Running the points (in this process or on Ray actors), resuming, retrying and the index files are the executor's
(``pienerf.executor``, reached through ``apps.avatar batch``; this package does not import ``pienerf``);
:func:`plot_batch_summary` draws the index as a table and a chart.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import re
from pathlib import Path

import numpy as np

from kernels import backend
from physavatar.body import MOTIONS
from physavatar.fit.estimation import SYNTHETIC_FABRIC, FabricParameters
from physavatar.pipeline.stages import (
    STAGES,
    PipelineConfig,
    Progress,
    animate,
    appearance,
    capture,
    estimate,
    evaluate,
    run_stages,
    stderr_progress,
    track_stage,
)
from physavatar.pipeline.user_capture import CAPTURE_STAGES, animate_capture, evaluate_capture, prepare
from physavatar.result_files import Staging, save_figure

__all__ = [
    "BATCH_INDEX",
    "BATCH_SUMMARY",
    "STUDY_GARMENTS",
    "capture_points",
    "parse_fabric",
    "plot_batch_summary",
    "point_metrics",
    "run_batch_point",
    "study_points",
]

BATCH_INDEX = "batch"
"""Stem of a batch's index files, ``batch.json`` and ``batch.csv``."""

BATCH_SUMMARY = "batch_summary.png"
"""The picture of a whole batch: its points' headline metrics as a table and a chart."""

STUDY_GARMENTS = {"skirt": 0.40, "short_skirt": 0.30, "long_skirt": 0.50}
"""The garments of a synthetic study: the procedural skirt (:func:`physavatar.garment.procedural_skirt`) by its
length from the hips (m)."""

_NAME = re.compile(r"[^A-Za-z0-9_-]+")


def parse_fabric(text: str) -> tuple[float, float]:
    """``"KAPPA_S:KAPPA_B"`` (the membrane and bending stiffness multipliers of the truth, each in 0.1–8, the range of
    :class:`physavatar.fit.estimation.FabricParameters`) as two numbers.

    Raises:
        ValueError: not two numbers, or one outside the range; the message names the form.
    """
    parts = str(text).split(":")
    form = f"a fabric is KAPPA_S:KAPPA_B, two stiffness multipliers in 0.1–8 such as 1:1 or 4:0.5; got {text!r}"
    try:
        kappa_s, kappa_b = (float(p) for p in parts)
    except ValueError:
        raise ValueError(form) from None
    try:
        FabricParameters(SYNTHETIC_FABRIC.density, kappa_s, kappa_b)  # the paper's ranges
    except ValueError:
        outside = [f"{n} = {v:g}" for n, v in (("κ_s", kappa_s), ("κ_b", kappa_b)) if not 0.1 <= v <= 8.0]
        raise ValueError(f"{form}: {', '.join(outside) or 'a value'} lies outside 0.1–8") from None
    return kappa_s, kappa_b


def _point_name(text: str) -> str:
    return _NAME.sub("_", text).strip("_") or "point"


def capture_points(
    captures: list[Path | str],
    stages: tuple[str, ...] = CAPTURE_STAGES,
    held_out_cameras: tuple[int, ...] | None = None,
) -> dict[str, dict]:
    """One point per capture folder, named after the folder (a repeated name gets ``_2``, ``_3``…).

    Raises:
        ValueError: no capture, one that is not a folder, or a stage that is not one of :data:`CAPTURE_STAGES`.
    """
    _check_stages(stages, CAPTURE_STAGES, "capture")
    if not captures:
        raise ValueError("a batch over captures needs at least one capture folder: --captures DIR [DIR ...]")
    points: dict[str, dict] = {}
    for folder in captures:
        folder = Path(folder)
        if not folder.is_dir():
            raise ValueError(f"capture {folder} is not a folder; pass capture folders (docs/capture.md)")
        name, n = _point_name(folder.resolve().name), 1
        while (name if n == 1 else f"{name}_{n}") in points:
            n += 1
        parameters = {"capture": str(folder.resolve()), "stages": list(stages)}
        if held_out_cameras is not None:
            parameters["held_out_cameras"] = list(held_out_cameras)
        points[name if n == 1 else f"{name}_{n}"] = parameters
    return points


def study_points(
    garments: list[str], motions: list[str], fabrics: list[str], stages: tuple[str, ...] = STAGES
) -> dict[str, dict]:
    """Every combination of a garment of :data:`STUDY_GARMENTS`, a fitting motion of
    :data:`physavatar.body.MOTIONS` and a fabric ``KAPPA_S:KAPPA_B`` (:func:`parse_fabric`), named
    ``GARMENT-MOTION-KSxKB``.

    Raises:
        ValueError: an empty axis, an unknown garment or motion, a bad fabric, or a stage not of :data:`STAGES`.
    """
    _check_stages(stages, STAGES, "study")
    for axis, values in (("--garments", garments), ("--motions", motions), ("--fabrics", fabrics)):
        if not values:
            raise ValueError(f"a study needs at least one value of {axis}")
    for garment in garments:
        if garment not in STUDY_GARMENTS:
            raise ValueError(f"unknown garment {garment!r}; valid: {', '.join(STUDY_GARMENTS)}")
    for motion in motions:
        if motion not in MOTIONS:
            raise ValueError(f"unknown motion {motion!r}; valid: {', '.join(MOTIONS)}")
    parsed = {fabric: parse_fabric(fabric) for fabric in fabrics}
    points = {}
    for garment in garments:
        for motion in motions:
            for kappa_s, kappa_b in parsed.values():
                name = _point_name(f"{garment}-{motion}-{kappa_s:g}x{kappa_b:g}")
                points[name] = {
                    "garment": garment,
                    "motion": motion,
                    "kappa_s": kappa_s,
                    "kappa_b": kappa_b,
                    "stages": list(stages),
                }
    return points


def _check_stages(stages, valid: tuple[str, ...], kind: str) -> None:
    if not stages:
        raise ValueError(f"name at least one stage of the {kind} pipeline: {', '.join(valid)}")
    for stage in stages:
        if stage not in valid:
            raise ValueError(f"unknown stage {stage!r} for a {kind} batch; valid, in order: {', '.join(valid)}")
    order = [valid.index(stage) for stage in stages]
    if order != sorted(order) or len(set(order)) != len(order):
        raise ValueError(f"stages must be given once each in the pipeline's order ({', '.join(valid)}); got {stages}")


def _study_config(base: PipelineConfig, parameters: dict) -> PipelineConfig:
    """The synthetic experiment with the point's garment, fitting motion and true fabric."""
    fabric = dataclasses.replace(base.fabric, kappa_s=parameters["kappa_s"], kappa_b=parameters["kappa_b"])
    return dataclasses.replace(
        base, skirt_length=STUDY_GARMENTS[parameters["garment"]], fit_motion=parameters["motion"], fabric=fabric
    )


def run_batch_point(
    parameters: dict,
    folder: Path,
    *,
    config: PipelineConfig,
    device: str,
    exact: bool = False,
    progress: Progress | None = stderr_progress,
    staging: Staging = contextlib.nullcontext,
) -> dict:
    """One point of a batch: its stages run into ``folder`` on ``device`` (initialised here: a Ray worker is a fresh
    process) with the sizes of ``config``; returns :func:`point_metrics` of what they wrote.

    A point with ``capture`` runs the stages of a user's capture on that folder; a study point (``garment``,
    ``motion``, ``kappa_s``, ``kappa_b``) runs the synthetic experiment with that truth; ``exact`` has its estimate
    fit the true meshes instead of the tracked ones.
    """
    backend.init(device)
    out = Path(folder)
    if "capture" in parameters:
        where = Path(parameters["capture"])
        held_out = parameters.get("held_out_cameras")
        held_out = None if held_out is None else tuple(held_out)
        functions = {
            "prepare": functools.partial(prepare, capture=where, held_out_cameras=held_out),
            "track": functools.partial(track_stage, capture=where),
            "estimate": functools.partial(estimate, capture=where),
            "appearance": functools.partial(appearance, capture=where),
            "animate": functools.partial(animate_capture, capture=where),
            "evaluate": functools.partial(evaluate_capture, capture=where),
        }
    else:
        config = _study_config(config, parameters)
        functions = {
            "capture": capture,
            "track": track_stage,
            "estimate": functools.partial(estimate, exact=exact),
            "appearance": appearance,
            "animate": animate,
            "evaluate": evaluate,
        }
    stages = [
        (name, functools.partial(functions[name], config, out, progress, staging=staging))
        for name in parameters["stages"]
    ]
    run_stages(stages, progress)
    return point_metrics(out)


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def point_metrics(out: Path) -> dict:
    """The headline figures of an experiment folder's stage files, for a batch's index: the garment and its
    boundary (``prepare``), the tracking's mean render loss and vertex error (``track``), the recovered fabric, the
    method that recovered it, its errors in the ratios κ/ρ and each method's where the truth is known
    (``estimate``), and each compared method's scalar scores (``evaluate``)."""
    out = Path(out)
    metrics: dict = {}
    prepared = _read(out / "prepare" / "prepare.json")
    if prepared is not None:
        metrics["prepare"] = {
            "garment_vertices": prepared["garment_vertices"],
            "boundary_vertices": prepared["boundary"]["count"],
            "clearance_m": prepared["clearance_m"],
        }
    tracking = _read(out / "track" / "tracking.json")
    if tracking is not None:
        losses = tracking["render_loss"][1:] or tracking["render_loss"]
        metrics["track"] = {
            "frames": tracking["frames"],
            "mean_render_loss": float(np.mean(losses)),
            "mean_vertex_error_m": tracking["mean_vertex_error_m"],
        }
    estimated = _read(out / "estimate" / "estimate.json")
    if estimated is not None:
        best = [m for m in estimated["methods"].values() if m["final"] == estimated["recovered"]]
        metrics["estimate"] = {
            "recovered": estimated["recovered"],
            "recovered_by": estimated["recovered_by"],
            "recovered_ratio_errors": best[0]["ratio_errors"] if best else None,
            "ratio_errors": {
                name: method["ratio_errors"]
                for name, method in estimated["methods"].items()
                if method.get("ratio_errors") is not None
            },
        }
    report = _read(out / "evaluate" / "report.json")
    if report is not None:
        metrics["evaluate"] = {
            name: {
                key: value
                for key, value in method.items()
                if isinstance(value, (int, float)) and not isinstance(value, bool)
            }
            for name, method in report["methods"].items()
        }
    return metrics


def _headline(entry: dict) -> dict[str, float]:
    """A point's figures for the summary: the stiffness ratios' errors (%) of the recovered fabric, or the tracking's
    render loss where nothing was estimated."""
    metrics = entry.get("metrics") or {}
    errors = metrics.get("estimate", {}).get("recovered_ratio_errors")
    if errors is not None:
        return {
            "κ_s/ρ error %": 100 * errors["kappa_s_over_rho"],
            "κ_b/ρ error %": 100 * errors["kappa_b_over_rho"],
        }
    if "estimate" in metrics:
        recovered = metrics["estimate"]["recovered"]
        return {"κ_s": recovered["kappa_s"], "κ_b": recovered["kappa_b"]}
    if "track" in metrics:
        return {"render loss": metrics["track"]["mean_render_loss"]}
    return {}


def plot_batch_summary(entries: list[dict], path: Path, staging: Staging = contextlib.nullcontext) -> Path:
    """A batch at a glance: a table of every point (name, status, attempts, seconds, headline figures) above a bar
    chart of the headline figures per point (failed points marked), written to ``path`` through ``staging``."""
    import matplotlib  # deferred: only the summary draws

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    headlines = [_headline(entry) for entry in entries]
    keys = list(dict.fromkeys(key for h in headlines for key in h))
    columns = ["point", "status", "attempts", "seconds", *keys]
    rows = []
    for entry, headline in zip(entries, headlines, strict=True):
        seconds = entry.get("seconds")
        rows.append(
            [
                entry["name"],
                entry["status"],
                str(entry.get("attempts", "")),
                f"{seconds:.1f}" if isinstance(seconds, (int, float)) else "",
                *(f"{headline[k]:.3g}" if k in headline else "" for k in keys),
            ]
        )
    height = 1.2 + 0.28 * len(rows) + (2.8 if keys else 0)
    figure = plt.figure(figsize=(max(7.0, 1.3 * len(columns)), height))
    table_height = (0.28 * len(rows) + 0.5) / height
    axis = figure.add_axes((0.02, 1 - table_height - 0.02, 0.96, table_height))
    axis.axis("off")
    table = axis.table(cellText=rows, colLabels=columns, loc="upper center", cellLoc="left")
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    for i, entry in enumerate(entries):
        if entry["status"] == "failed":
            for j in range(len(columns)):
                table[i + 1, j].set_facecolor("#f4cccc")
    if keys:
        chart = figure.add_axes((0.1, 0.08, 0.85, 2.2 / height))
        x = np.arange(len(entries))
        width = 0.8 / len(keys)
        for k, key in enumerate(keys):
            values = [h.get(key, math.nan) for h in headlines]
            chart.bar(x + (k - (len(keys) - 1) / 2) * width, values, width, label=key)
        chart.set_xticks(x, [entry["name"] for entry in entries], rotation=30, ha="right", fontsize=7)
        chart.axhline(0.0, color="black", linewidth=0.6)
        chart.legend(fontsize=7)
        for i, entry in enumerate(entries):
            if entry["status"] == "failed":
                chart.annotate("failed", (i, 0.0), ha="center", va="bottom", fontsize=7, color="red")
    save_figure(figure, path, staging)
    plt.close(figure)
    return Path(path)
