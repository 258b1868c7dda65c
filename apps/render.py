"""Scripted offline renders of PIE-NeRF's experiments from TOML scenarios.

    python -m apps.render assets/scenarios/plant_sway.toml --out out/plant_sway [--device cpu|cuda] [--smoke]
                          [--cache-dir DIR]

A scenario names the scene, material, discretisation, solver settings, pins, keyframed drags, timed forces, cuts,
colliders (a plane may move along keyframes), cameras (orbit or fixed) and outputs. Optional ``[[variants]]``
override the material or discretisation; variants run one after another and their images are tiled side by
side (Fig. 6: Neo-Hookean vs ARAP; Fig. 8: quadratic vs linear), each in its ``outputs.modes`` (a variant may
name its own ``modes``); when a frame holds several variants or modes, each tile carries its variant's ``label``
(else its name) and mode. The mesh preview draws the ``[[colliders]]`` (balls, square plates) where they are.
The run writes, under ``--out``:

* ``frames/frame_NNNN.png`` (RGBA tiles of every camera × variant), ``video.mp4``;
* ``depth/…_NNNN.npy`` (float32 metres) and ``depth/…_NNNN.png`` previews; ``shadow/…_NNNN.png`` when asked;
* ``metrics.json``: timings, per-step report, volumes, the time breakdown, what is pending and, under
  ``[warp_error]``, each warped-NeRF mode's error against the mesh (``variants.NAME.warp_error``, per frame and
  mean; each frame's record under ``per_frame``);
* ``volume_bars.png`` (Fig. 6) when ``[[volume_samples]]`` are given, ``time_breakdown.png`` (Fig. 10) always.

A ``[nerf]`` table renders the scene's NeRF warped by the simulated deformation (PIE-NeRF §4.6, Eq. 19–21):

* ``source = "scene"`` fits a NeRF to the embedded scene's rendered views (:func:`pienerf.scenes.scene_nerf`);
  the body is still simulated from the scene's analytic density;
* ``source = "data:NAME"`` fits one to the NeRF-synthetic folder ``../shared/data/NAME``
  (:func:`pienerf.nerf.fitting.dataset_nerf`, upright on the ground; ``up`` is the data's up axis), and the body is
  sampled from the NeRF's own solid: ``scene.name`` is then not needed;
* ``warps`` lists the ray warpings to render, each a render mode: ``"nerf"`` for the quadratic warp (Eq. 20),
  ``"nerf_linear"`` for the first-order one and ``"nerf_rest"`` for none;
* the other keys set the fit (``steps``, ``batch_rays``, ``views``, ``resolution``, ``downscale``, ``max_views``,
  ``levels``, ``log2_table_size``, ``max_resolution``, ``hidden``, ``samples_per_diagonal``, ``grid_resolution``,
  ``grid_decay``, ``solid_resolution``); ``[smoke.nerf]`` overrides them at ``--smoke`` size.

The fitted NeRF is cached as a checkpoint under ``--cache-dir`` (default ``$PIE_CACHE_DIR``, else
``~/.cache/pie-physavatar``), so a second run loads it.

``outputs.mesh_edge_fraction`` splits the mesh tiles' edges until each is shorter than that fraction of the smallest
kernel support radius, so that a bent thin part (Fig. 8's rod) shows its bend instead of a straight chord between
far-apart vertices (:func:`pienerf.render.mesh_refine.split_long_edges`; the rest state renders as before).

A ``[warp_error]`` table (Fig. 8) measures, every frame, each warped-NeRF mode of a variant against the variant's own
mesh render of the same state, both rendered again without the ground (:mod:`pienerf.render`): ``region`` is a
rest-space box ``[[x0, y0, z0], [x1, y1, z1]]`` (m) of the material to look at (the rod), ``dilation`` the pixels
added around its projected particles (default 2), ``label`` its name on the tiles. On the pixels near that
material which either render covers (alpha > ½) it reports the PSNR of the colours over white and the silhouettes'
intersection over union; each warped-NeRF tile's label carries the frame's figures.

``--smoke`` applies the scenario's ``[smoke]`` table (few frames, tiny images, few kernels). A bad scenario (an
unknown key, a wrong type, a number outside its range, a missing required key) or an ``--out`` that cannot be
written stops before any work with one line naming the file, the key and the fix; exit status 2.

Every file is written whole or not at all (a temporary file in the same folder, then moved into place). Ctrl-C
stops the render with exit status 130: ``metrics.json`` then holds the frames that finished and
``"interrupted": true``, and ``video.mp4`` those frames. A failed write (a full disk) records ``"error"`` in
``metrics.json`` with the finished frames where it can, and exits with status 1.

Each variant's line ends with how many of its steps ended with a failed line search (by kind: ``inversion``,
``no decrease``, ``not finite``) and how many did not converge; ``metrics.json`` records the counts under
``variants.NAME.solver``. Where a variant's result is wrong (a line search met NaN, or none of its steps could move
the body), the outputs are still written, ``metrics.json`` names the variant under ``wrong_results`` and the exit
status is 3.

A scenario whose ``requires`` cannot be met (a trained NeRF, the warped-NeRF renderer, a data folder) is skipped:
``metrics.json`` holds ``skipped`` and the reason, exit status 0.

The scenario logic (schema, checks, building, keyframes, colliders, cameras) is :mod:`pienerf.scenario`; this
program renders the frames and writes the files.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from kernels import backend
from pienerf.output_files import OutputPathError, atomic_path, check_output_folder, write_json
from pienerf.reports import plot_time_breakdown, plot_volume_bars
from pienerf.scenario import (
    ScenarioError,
    ScenarioRun,
    advance,
    build_runs,
    frame_count,
    load_scenario,
    measure_warp_error,
    merged_breakdown,
    prepare_nerf,
    require_video_encoder,
    run_metrics,
    sample_volumes,
    scenario_cameras,
    scenario_colliders,
    scenario_outputs,
    unmet_requirement,
    volume_sample_frames,
)


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
                _save_png(_depth_preview(result.depth), out / "depth" / f"{stem}.png")
            if outputs["shadow"] and result.shadow is not None:
                _save_png(_to_uint8(result.shadow), out / "shadow" / f"{stem}.png")
    return tiles


def _save_png(image: np.ndarray, path: Path) -> None:
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
            _save_png(_to_uint8(image), out / "frames" / f"frame_{frame:04d}.png")
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
    write_json(out / "metrics.json", metrics, default=str)
    log(
        f"{name}: {metrics['frames']} frames, {len(runs)} variant(s), build {metrics['build_seconds']:.1f} s, "
        f"{1e3 * breakdown.to_dict()['seconds_per_step'].get('assembly', 0):.1f} ms assembly/step → {out}"
    )
    for run in runs:
        log(f"{name}: variant {run.name!r}: {_failure_summary(run.tally.to_dict())}")
    return metrics


def _failure_summary(solver: dict) -> str:
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


SOLVER_FAILED = 3
"""Exit status of a render whose solver failed so that a variant's result is wrong
(:meth:`pienerf.scenario.StepTally.wrong_result`); the outputs are written all the same, for inspection."""


def main(argv: list[str] | None = None) -> int:
    """Render the scenario; exit status 0, 2 for bad input, 1 when writing failed, 3 when a variant's solver failed
    (:data:`SOLVER_FAILED`), 130 when interrupted."""
    try:
        return _main(argv)
    except KeyboardInterrupt:  # before the render began: nothing to keep
        print("interrupted before rendering began; nothing was written", file=sys.stderr)
        return 130


def _main(argv: list[str] | None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenario", type=Path, help="scenario TOML file (assets/scenarios/*.toml)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--device", choices=list(backend.DEVICES), default=None, help="cpu or cuda (default: cuda when present)"
    )
    parser.add_argument("--smoke", action="store_true", help="apply the scenario's [smoke] table (tests)")
    parser.add_argument(
        "--frames", type=int, default=None, help="frames after the first, replacing the scenario's (and --smoke's)"
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of scene renders and fitted NeRFs (default: $PIE_CACHE_DIR, else ~/.cache/pie-physavatar)",
    )
    args = parser.parse_args(argv)
    try:
        scenario = load_scenario(args.scenario, smoke=args.smoke, frames=args.frames)
        require_video_encoder(scenario)
        check_output_folder(args.out)
        if args.cache_dir is not None:
            check_output_folder(args.cache_dir, "--cache-dir")
        backend.init(args.device)
    except OutputPathError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except ScenarioError as error:
        print(f"error: {error}", file=sys.stderr)  # names the file
        return 2
    except ValueError as error:
        print(f"error: {args.scenario}: {error}", file=sys.stderr)
        return 2
    metrics_file, started = args.out / "metrics.json", time.time()
    try:
        metrics = render_scenario(scenario, args.out, cache_dir=args.cache_dir)
    except KeyboardInterrupt:
        print(f"interrupted: {metrics_file} holds the frames that finished", file=sys.stderr)
        return 130
    except (ScenarioError, ValueError) as error:
        print(f"error: {args.scenario}: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        full = " (the disk is full)" if error.errno == errno.ENOSPC else ""
        fresh = metrics_file.is_file() and metrics_file.stat().st_mtime >= started - 1.0
        kept = f"; {metrics_file} holds the frames that finished" if fresh else ""
        print(f"error: writing under {args.out} failed{full}: {error}{kept}", file=sys.stderr)
        return 1
    for variant, reason in metrics.get("wrong_results", {}).items():
        print(
            f"error: {args.scenario}: variant {variant!r}: {reason}, so its frames are not solutions of the implicit "
            "step; lower solver.dt (or raise solver.substeps), soften the material or the loads",
            file=sys.stderr,
        )
    return SOLVER_FAILED if metrics.get("wrong_results") else 0


if __name__ == "__main__":
    sys.exit(main())
