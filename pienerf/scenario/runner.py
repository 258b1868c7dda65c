"""A scenario rendered offline: its frames stepped, rendered, tiled and written with the video, the depth and shadow
images, the charts and ``metrics.json`` (the file layout is described in :mod:`apps.render`).

:func:`render_scenario` runs every variant of a checked scenario (:func:`pienerf.scenario.load_scenario`) and writes
its outputs; the files of an earlier render in the folder are removed first (:func:`clear_earlier_render`). Every
file is written whole or not at all (:func:`pienerf.output_files.atomic_path`); Ctrl-C stops between frames, and
``metrics.json`` then holds the frames that finished.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from kernels import backend
from pienerf.output_files import atomic_path, write_json
from pienerf.reports import plot_time_breakdown, plot_volume_bars
from pienerf.scenario.cameras import scenario_cameras
from pienerf.scenario.colliders import scenario_colliders
from pienerf.scenario.expectations import check_expectations, failed_lines
from pienerf.scenario.nerf import prepare_nerf
from pienerf.scenario.runs import (
    ScenarioRun,
    advance,
    build_runs,
    measure_warp_error,
    merged_breakdown,
    run_metrics,
    sample_volumes,
)
from pienerf.scenario.schema import (
    frame_count,
    require_video_encoder,
    scenario_outputs,
    unmet_requirement,
    volume_sample_frames,
)

__all__ = [
    "MODE_LABELS",
    "OWNED_FILES",
    "clear_earlier_render",
    "failure_summary",
    "label_tile",
    "render_scenario",
    "save_png",
]


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def _depth_preview(depth: torch.Tensor) -> np.ndarray:
    finite = torch.isfinite(depth)
    if not bool(finite.any()):
        return np.zeros(depth.shape, dtype=np.uint8)
    lo, hi = float(depth[finite].min()), float(depth[finite].max())
    scaled = torch.where(finite, 1.0 - (depth - lo) / max(hi - lo, 1e-6) * 0.8, torch.zeros_like(depth))
    return _to_uint8(scaled)


def label_tile(tile: torch.Tensor, text: str) -> torch.Tensor:
    """``tile [H, W, 4]`` (straight-alpha RGBA in [0, 1]) with ``text`` in black on an opaque white box at its
    bottom-left corner (over the ground, clear of what hangs above the body), drawn in PIL's default font and
    clipped to the tile when it is narrower than the text. Lines after the first are left out where the box would
    cover more than a third of the tile's height."""
    image = Image.fromarray(_to_uint8(tile), mode="RGBA")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    lines = text.split("\n")
    while len(lines) > 1 and draw.textbbox((0, 0), "\n".join(lines), font=font)[3] + 6 > image.height / 3:
        lines.pop()
    text = "\n".join(lines)
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    origin = (3 - left, image.height - 3 - bottom)
    draw.rectangle((0, image.height - (bottom - top) - 6, right - left + 6, image.height), fill=(255, 255, 255, 255))
    draw.text(origin, text, fill=(0, 0, 0, 255), font=font)
    return torch.from_numpy(np.asarray(image).astype(np.float32) / 255.0)


MODE_LABELS = {
    "mesh": "mesh",
    "particles": "particles",
    "nerf": "NeRF, quadratic warp",
    "nerf_linear": "NeRF, linear warp",
    "nerf_rest": "NeRF, unwarped",
}
"""What a tile of each render mode shows, as its label says it."""


def _tile_label(run: ScenarioRun, mode: str, labelled: bool, note: str | None = None, modes: int = 1) -> str | None:
    """The label of a tile when the frame holds several variants or modes: the variant's (``label`` or name), then
    what the mode shows (:data:`MODE_LABELS`) when the frame holds several ``modes``, then ``note`` on a second
    line."""
    if not labelled:
        return None
    text = run.label + (f": {MODE_LABELS.get(mode, mode)}" if modes > 1 or len(run.modes) > 1 else "")
    return text + (f"\n{note}" if note else "")


def _warp_error_note(error: dict | None, region: str) -> str | None:
    """A tile's second label line for a warped-NeRF mode measured against the mesh on ``region``, e.g.
    ``vs mesh on rod: 24.1 dB, IoU 0.83``."""
    if error is None or error["pixels"] == 0:
        return None
    return f"vs mesh on {region}: {error['psnr_db']:.1f} dB, IoU {error['silhouette_iou']:.2f}"


def _render_tiles(
    run: ScenarioRun,
    scenario: dict,
    t: float,
    frame: int,
    outputs: dict,
    out: Path,
    labelled: bool = False,
    warp_errors: dict | None = None,
    modes: int = 1,
) -> list:
    """Every mode × view of one run at time ``t``, each tile labelled when ``labelled`` (a warped-NeRF tile with its
    error against the mesh when ``warp_errors`` holds it), the scenario's colliders drawn where a mode can draw
    them; ``modes`` is how many render modes the frame holds; writes the depth and shadow images asked for."""
    simulation = run.simulation
    cameras = scenario_cameras(scenario, simulation.centre, t)
    colliders = scenario_colliders(scenario, t, floor=False)  # the floor is the preview's ground already
    tiles = []
    for mode in run.modes:
        if hasattr(simulation.render_backends[mode], "set_colliders"):
            simulation.render_backends[mode].set_colliders(colliders)
        for view in range(len(cameras)):
            result = simulation.render(cameras, view, mode, shadow=outputs["shadow"])
            tile = result.rgba.cpu()  # render modes may return different devices
            region = scenario.get("warp_error", {}).get("label", "region")
            note = _warp_error_note((warp_errors or {}).get(mode), region)
            text = _tile_label(run, mode, labelled, note, modes)
            tiles.append(label_tile(tile, text) if text else tile)
            stem = f"{run.name}_{mode}_view{view}_{frame:04d}"
            if outputs["depth"]:
                with atomic_path(out / "depth" / f"{stem}.npy") as temporary:
                    np.save(temporary, result.depth.cpu().numpy().astype(np.float32))
                save_png(_depth_preview(result.depth), out / "depth" / f"{stem}.png")
            if outputs["shadow"] and result.shadow is not None:
                save_png(_to_uint8(result.shadow), out / "shadow" / f"{stem}.png")
    return tiles


def save_png(image: np.ndarray, path: Path) -> None:
    """One PNG, written whole or not at all."""
    with atomic_path(path) as temporary:
        Image.fromarray(image).save(temporary)


class _StopBetweenFrames:
    """Ctrl-C while frames are written stops the render at the end of the frame in hand, never inside a write.

    A ``KeyboardInterrupt`` raised inside the video writer makes imageio-ffmpeg kill its encoder, which leaves an
    MP4 without its index: the first Ctrl-C only asks for a stop, which :meth:`check` raises between frames; a second
    Ctrl-C interrupts at once, as usual. Off the main thread (no signal handlers there) it does nothing.
    """

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self) -> _StopBetweenFrames:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._request)
        return self

    def _request(self, signum, frame) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self._previous)  # a second Ctrl-C stops at once

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _write_frames(scenario: dict, runs: list[ScenarioRun], out: Path, outputs: dict, written: dict) -> None:
    """Step and render every frame, writing the tiled PNGs and the video.

    ``written`` gathers the timings and the per-frame record as frames finish, so that a run stopped part way
    (Ctrl-C, a full disk) still reports what it finished. The video is written to a temporary file and moved into
    place when the frames end, or when Ctrl-C stops them (it then holds the finished frames); a failed write
    removes it.
    """
    _, substeps = frame_count(scenario)
    samples = volume_sample_frames(scenario)
    for folder in ("frames", "depth", "shadow"):
        if outputs[folder]:
            (out / folder).mkdir(exist_ok=True)
    step_seconds = {run.name: [] for run in runs}
    per_frame = []
    written.update(
        substeps=substeps,
        samples=samples,
        step_seconds=step_seconds,
        render_seconds=0.0,
        warp_error_seconds=0.0,
        per_frame=per_frame,
    )
    writer, video = None, None
    if outputs["mp4"]:
        video = out / f".video.partial{os.getpid()}.mp4"
        writer = imageio.get_writer(
            video, fps=outputs["fps"], codec="libx264", quality=7, macro_block_size=1, pixelformat="yuv420p"
        )
    keep_video = False
    stop = _StopBetweenFrames()
    try:
        with stop:
            _render_frames(scenario, runs, out, outputs, written, writer, stop)
        keep_video = True
    except KeyboardInterrupt:
        keep_video = bool(per_frame)
        raise
    finally:
        if writer is not None:
            try:
                writer.close()
            finally:
                if keep_video:
                    os.replace(video, out / "video.mp4")
                else:
                    video.unlink(missing_ok=True)


def _render_frames(scenario, runs, out, outputs, written, writer, stop: _StopBetweenFrames) -> None:
    """The frame loop of :func:`_write_frames`: step, render, write; a requested stop is taken between frames."""
    frames, substeps = frame_count(scenario)
    samples, per_frame, step_seconds = written["samples"], written["per_frame"], written["step_seconds"]
    labelled = len(runs) > 1 or any(len(run.modes) > 1 for run in runs)
    modes = len({mode for run in runs for mode in run.modes})
    dt = runs[0].simulation.config.dt * substeps
    for frame in range(frames + 1):
        t = frame * dt
        tiles, record = [], {"frame": frame, "time_s": t}
        for run in runs:
            if frame > 0:
                step_seconds[run.name] += advance(run, scenario, t, substeps)
            record[f"{run.name}_relative_volume"] = sample_volumes(run, samples, frame)
            start = time.perf_counter()
            errors = measure_warp_error(run, scenario, t)
            if errors is not None:
                record[f"{run.name}_warp_error"] = errors
            written["warp_error_seconds"] += time.perf_counter() - start
            start = time.perf_counter()
            tiles += _render_tiles(run, scenario, t, frame, outputs, out, labelled, errors, modes)
            written["render_seconds"] += time.perf_counter() - start
        image = torch.cat(tiles, dim=1)
        rgb = image[..., :3] * image[..., 3:] + (1.0 - image[..., 3:])  # over white
        if outputs["frames"]:
            save_png(_to_uint8(image), out / "frames" / f"frame_{frame:04d}.png")
        if writer is not None:
            writer.append_data(_to_uint8(rgb))
        per_frame.append(record)
        stop.check()


def _finished_metrics(runs: list[ScenarioRun], written: dict) -> dict:
    """The metrics of the frames that finished: all of them, or those before a stop."""
    breakdown = merged_breakdown(runs)
    return {
        "frames": len(written["per_frame"]),
        "steps_per_frame": written["substeps"],
        "dt_s": runs[0].simulation.config.dt,
        "render_seconds": written["render_seconds"],
        "warp_error_seconds": written["warp_error_seconds"],
        "time_breakdown": breakdown.to_dict(),
        "variants": {run.name: run_metrics(run, written["step_seconds"][run.name]) for run in runs},
        "per_frame": written["per_frame"],
    }


OWNED_FILES = (
    "metrics.json",
    "video.mp4",
    ".video.partial*.mp4",
    "volume_bars.png",
    "volume_bars.json",
    "time_breakdown.png",
    "time_breakdown.json",
    "frames/frame_*.png",
    "depth/*.npy",
    "depth/*.png",
    "shadow/*.png",
)
"""The files a render writes under ``--out`` (glob patterns): an earlier render's are removed before a new one
starts, so that its frames never sit beside the new ones."""


def clear_earlier_render(out: Path, log=print) -> int:
    """Remove the files of an earlier render in ``out`` (:data:`OWNED_FILES`) and say so, naming the earlier
    scenario where its ``metrics.json`` tells it; files no render writes are left, and their count said. Returns how
    many files were removed."""
    if not out.is_dir():
        return 0
    earlier = None
    try:
        earlier = json.loads((out / "metrics.json").read_text()).get("scenario")
    except (OSError, ValueError, AttributeError):
        pass
    owned = {path for pattern in OWNED_FILES for path in out.glob(pattern) if path.is_file()}
    for path in owned:
        path.unlink()
    others = [path for path in out.rglob("*") if path.is_file()]
    if owned:
        of = f" of scenario {earlier!r}" if earlier else ""
        log(f"{out}: removed {len(owned)} files of an earlier render{of} (frames, video, depth, metrics, charts)")
    if others:
        example = others[0].relative_to(out)
        log(f"{out}: also holds {len(others)} files no render writes (such as {example}); left as they are")
    return len(owned)


def render_scenario(scenario: dict, out: Path, log=print, cache_dir: Path | str | None = None) -> dict:
    """Run every variant of a checked scenario and write the outputs under ``out``; returns the metrics.

    The files of an earlier render in ``out`` are removed first (:func:`clear_earlier_render`). ``cache_dir`` holds
    the scene renders and fitted NeRFs (default ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``).

    Raises:
        ScenarioError: the scenario asks for a video that cannot be written here (:func:`require_video_encoder`),
            before any work.
    """
    require_video_encoder(scenario)
    clear_earlier_render(out, log)
    out.mkdir(parents=True, exist_ok=True)
    name = scenario.get("name", "scenario")
    metrics = {
        "scenario": name,
        "figure": scenario.get("figure", ""),
        "device": backend.current_device(),
        "pending": scenario.get("pending", []),
    }
    reason = unmet_requirement(scenario)
    if reason is not None:
        metrics["skipped"] = reason
        write_json(out / "metrics.json", metrics)
        log(f"{name}: skipped: {reason}")
        return metrics

    outputs = scenario_outputs(scenario)
    volume_sample_frames(scenario)  # the run's length and its samples are checked before any fitting
    runs, written = [], {}
    try:
        nerf = prepare_nerf(scenario, cache_dir, log)
        clock = time.perf_counter()
        runs = build_runs(scenario, nerf)
        metrics["build_seconds"] = time.perf_counter() - clock
        _write_frames(scenario, runs, out, outputs, written)
        breakdown = merged_breakdown(runs)
        plot_time_breakdown(breakdown, out / "time_breakdown.png", title=name)
        if written["samples"]:
            plot_volume_bars([(run.name, run.volumes) for run in runs], out / "volume_bars.png")
    except (KeyboardInterrupt, OSError) as stop:
        if isinstance(stop, KeyboardInterrupt):
            metrics["interrupted"] = True
        else:
            metrics["error"] = str(stop)
        if runs and written:
            metrics.update(_finished_metrics(runs, written))
        else:
            metrics["frames"] = 0
        write_json(out / "metrics.json", metrics, default=str)
        raise
    if nerf is not None:
        metrics["nerf"] = {
            "source": nerf.source,
            "checkpoint": str(nerf.checkpoint) if nerf.checkpoint else None,
            "fit_or_load_seconds": nerf.seconds,
            "warps": nerf.warps,
            "modes": {run.name: run.modes for run in runs},
        }
    metrics.update(_finished_metrics(runs, written))
    metrics["wrong_results"] = {run.name: run.tally.wrong_result() for run in runs if run.tally.wrong_result()}
    expectations = check_expectations(scenario, metrics["variants"])
    if expectations is not None:
        metrics["expect"] = expectations
    write_json(out / "metrics.json", metrics, default=str)
    log(
        f"{name}: {metrics['frames']} frames, {len(runs)} variant(s), build {metrics['build_seconds']:.1f} s, "
        f"{1e3 * breakdown.to_dict()['seconds_per_step'].get('assembly', 0):.1f} ms assembly/step → {out}"
    )
    for run in runs:
        log(f"{name}: variant {run.name!r}: {failure_summary(run.tally.to_dict())}")
    if expectations is not None:
        failed = failed_lines(expectations)
        log(f"{name}: [expect]: {len(expectations['checks']) - len(failed)} of {len(expectations['checks'])} passed")
        for line in failed:
            log(f"{name}: [expect] failed: {line}")
    return metrics


def failure_summary(solver: dict) -> str:
    """One line: how many steps ended with a failed line search, by kind, and how many did not converge, with the
    largest last Newton update of those against the tolerance and the iteration cap."""
    kinds = ", ".join(f"{kind}: {count}" for kind, count in solver["line_search_failures"].items())
    far = ""
    if solver["unconverged_steps"] and solver.get("largest_unconverged_update_m") is not None:
        far = (
            f" (largest last update {solver['largest_unconverged_update_m']:.3g} m against the tolerance "
            f"{solver['newton_tolerance_m']:.3g} m, at most {solver['newton_iterations_cap']} Newton iterations a step)"
        )
    return (
        f"{solver['line_search_failed_steps']} of {solver['steps']} steps ended with a failed line search"
        + (f" ({kinds})" if kinds else "")
        + f", {solver['unconverged_steps']} did not converge"
        + far
    )
