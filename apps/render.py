"""Scripted offline renders of PIE-NeRF's experiments from TOML scenarios.

    python -m apps.render assets/scenarios/plant_sway.toml --out out/plant_sway [--device cpu|cuda] [--smoke]
                          [--frames N] [--cache-dir DIR]

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

``--smoke`` applies the scenario's ``[smoke]`` table (few frames, tiny images, few kernels); ``--frames N`` (N >= 1)
then sets the number of frames after the first. A bad scenario (an unknown key, a wrong type, a number outside its
range, a missing required key, a variant name that is not a plain file name), a ``--frames`` below 1, a video asked
for where imageio-ffmpeg is not installed, or an ``--out`` that cannot be written stops before any work with one
line naming the file, the key and the fix; exit status 2. A mesh scene file that is empty, not a mesh or has NaN
vertices is named as such, exit status 2.

A render owns the files it writes under ``--out`` (:data:`pienerf.scenario.OWNED_FILES`): those of an earlier
render there (of this scenario or another) are removed first, and the run says so; files no render writes are left
and counted.

Each step iterates Newton to the solver's tolerance (``solver.newton_iterations``, default
:data:`pienerf.scenario.OFFLINE_NEWTON_ITERATIONS`), not the interactive viewer's one iteration, with the solver's
host loop on every device. ``solver.hessian_precision`` (``auto``, ``float32`` or ``float64``) sets the precision of
the elastic Hessian's block products (:class:`pienerf.sim.solver.SolverConfig`).

Every file is written whole or not at all (a temporary file in the same folder, then moved into place). Ctrl-C
stops the render with exit status 130: ``metrics.json`` then holds the frames that finished and
``"interrupted": true``, and ``video.mp4`` those frames. A failed write (a full disk) records ``"error"`` in
``metrics.json`` with the finished frames where it can, and exits with status 1.

Each variant's line ends with how many of its steps ended with a failed line search (by kind: ``inversion``,
``no decrease``, ``not finite``) and how many did not converge, with the largest last Newton update of those against
the tolerance; ``metrics.json`` records the counts under
``variants.NAME.solver``. Where a variant's result is wrong (a line search met NaN, or none of its steps could move
the body), the outputs are still written, ``metrics.json`` names the variant under ``wrong_results`` and the exit
status is 3.

A scenario whose ``requires`` cannot be met (a trained NeRF, the warped-NeRF renderer, a data folder) is skipped:
``metrics.json`` holds ``skipped`` and the reason, exit status 0.

An ``[expect]`` table (:mod:`pienerf.scenario.expectations`: a final volume band, a final displacement band of the
particles or of their centre, a least fraction of converged steps, a least warped-NeRF PSNR) is checked after the
run: ``metrics.json`` records each check under ``expect`` and, where one fails (and no variant's result is wrong),
the exit status is 4 (:data:`EXPECTATION_FAILED`). ``--smoke`` checks ``[smoke.expect]`` over it, bounds derived for
the smoke run's two steps (left out when ``--frames`` changes its length); a variant's ``expect`` overrides both.

A ``[sweep]`` table (a grid or a list of values of any scenario fields; ``docs/sweeps.md``) makes the scenario a
family of points: ``--sweep`` renders every point into its own folder ``--out/pNNN`` (each written whole or not at
all), ``sweep.json`` and ``sweep.csv`` (each point's values, status, error and metrics) and ``contact_sheet.png`` (every
point's last frame); a rerun skips the points already complete. ``--executor ray`` runs the points on Ray actors (one
per GPU), on this machine or on the cluster of ``--ray-address`` (or ``$RAY_ADDRESS``); a point that fails is retried
``--retries`` times and then recorded as failed while the others go on (exit status 5, :data:`POINTS_FAILED`).
Without ``--sweep`` the scenario renders as written, its ``[sweep]`` table unused.

The work is :func:`pienerf.scenario.render_scenario` (:func:`pienerf.scenario.run_sweep` with ``--sweep``); this
program parses the arguments, checks them before any work, prints the progress and turns the outcome into an exit
status.
"""

from __future__ import annotations

import argparse
import errno
import sys
import time
from pathlib import Path

from kernels import backend
from pienerf.executor import EXECUTORS, ExecutorConfig, ExecutorError, require_ray
from pienerf.output_files import OutputPathError, check_output_folder
from pienerf.scenario import (
    ScenarioError,
    failed_lines,
    load_scenario,
    render_scenario,
    require_video_encoder,
    run_sweep,
    sweep_points,
)

SOLVER_FAILED = 3
"""Exit status of a render whose solver failed so that a variant's result is wrong
(:meth:`pienerf.scenario.StepTally.wrong_result`); the outputs are written all the same, for inspection."""

EXPECTATION_FAILED = 4
"""Exit status of a render whose ``[expect]`` table failed (:func:`pienerf.scenario.check_expectations`); the outputs
are written all the same."""

POINTS_FAILED = 5
"""Exit status of a ``--sweep`` some of whose points failed after their retries (``sweep.json`` holds each error);
the other points are complete."""


def main(argv: list[str] | None = None) -> int:
    """Render the scenario; exit status 0, 2 for bad input, 1 when writing failed, 3 when a variant's solver failed
    (:data:`SOLVER_FAILED`), 4 when an ``[expect]`` check failed (:data:`EXPECTATION_FAILED`), 5 when points of a
    ``--sweep`` failed (:data:`POINTS_FAILED`), 130 when interrupted."""
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
    parser.add_argument(
        "--sweep", action="store_true", help="render every point of the scenario's [sweep] table into --out/pNNN"
    )
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="with --sweep: local (in this process, one point after another) or ray (Ray actors, one per GPU)",
    )
    parser.add_argument(
        "--ray-address",
        default=None,
        help="with --executor ray: the cluster to join (ray start --head prints it; default $RAY_ADDRESS, else a Ray "
        "started on this machine)",
    )
    parser.add_argument(
        "--retries", type=int, default=2, help="with --sweep: attempts after the first for a point that fails"
    )
    args = parser.parse_args(argv)
    try:
        scenario = load_scenario(args.scenario, smoke=args.smoke, frames=args.frames)
        require_video_encoder(scenario)
        check_output_folder(args.out)
        if args.cache_dir is not None:
            check_output_folder(args.cache_dir, "--cache-dir")
        if args.sweep:
            sweep_points(scenario)  # a scenario without [sweep] is refused before any work
            if args.executor == "ray":
                require_ray()
        elif args.executor != "local" or args.ray_address is not None:
            raise ScenarioError("--executor and --ray-address choose how the points of a --sweep run; add --sweep")
        if args.sweep and args.executor == "ray":  # the points run in Ray's workers, which may be on other machines
            device = args.device or backend.default_device()
        else:
            device = backend.init(args.device)
        if args.sweep:
            config = ExecutorConfig(args.executor, device, address=args.ray_address, max_retries=args.retries)
    except ExecutorError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except OutputPathError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except ScenarioError as error:
        print(f"error: {error}", file=sys.stderr)  # names the file
        return 2
    except ValueError as error:
        print(f"error: {args.scenario}: {error}", file=sys.stderr)
        return 2
    if args.sweep:
        return _sweep(scenario, args, config)
    if "sweep" in scenario:
        print(
            f"{args.scenario}: rendering the scenario as written; --sweep renders its [sweep] points", file=sys.stderr
        )
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
    if metrics.get("wrong_results"):
        return SOLVER_FAILED
    for line in failed_lines(metrics.get("expect")):
        print(f"error: {args.scenario}: [expect] {line}", file=sys.stderr)
    return EXPECTATION_FAILED if not metrics.get("expect", {}).get("passed", True) else 0


def _sweep(scenario: dict, args: argparse.Namespace, config: ExecutorConfig) -> int:
    """Render the sweep's points; exit status 0, 5 when points failed, 2 when Ray cannot start, 130 interrupted."""
    try:
        entries = run_sweep(scenario, args.out, config, cache_dir=args.cache_dir)
    except KeyboardInterrupt:
        print(
            f"interrupted: {args.out / 'sweep.json'} lists the points that finished; run the same command again to go "
            "on (the complete points are skipped)",
            file=sys.stderr,
        )
        return 130
    except ExecutorError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    failed = [entry for entry in entries if entry["status"] == "failed"]
    for entry in failed:
        print(f"error: {args.scenario}: sweep point {entry['name']} failed: {entry['error']}", file=sys.stderr)
    return POINTS_FAILED if failed else 0


if __name__ == "__main__":
    sys.exit(main())
