"""PhysAvatar from the command line.

    python -m apps.avatar simulate --motion walk --frames 100 --out out/walk
    python -m apps.avatar simulate --garment skirt.obj --motion dance.bvh --frames 50 --out out/dance --device cuda
    python -m apps.avatar simulate --smoke --out out/smoke
    python -m apps.avatar pipeline --out out/avatar [--smoke] [--device cuda]
    python -m apps.avatar capture|track|estimate|appearance|animate|evaluate --out out/avatar [--smoke]

``simulate`` dresses the procedural mannequin (:class:`physavatar.body.Body`) in a garment (default: the
DiffCloth skirt ``skirt1252.obj`` from the shared data folder, or the embedded procedural skirt where that folder
is absent; the command says which), drives it through a motion and writes
``sequence.npz`` (garment and body per frame), ``stats.json`` (per-step solver statistics), ``video.mp4``
(orbiting camera) and, with ``--meshes obj|ply``, one garment mesh per frame. A garment that is not on the body
(:func:`physavatar.garment.place_on_body`) is refused; ``--garment-scale`` gives its file's scale where the guess
from its height is wrong. The summary line and ``stats.json`` count the steps whose line search stalled.

``pipeline`` runs PhysAvatar end to end on a synthetic capture (:mod:`physavatar.pipeline`): it films a skirt whose
physics it knows, tracks it with mesh-aligned Gaussians, estimates its stiffness and appearance, animates it under
an unseen motion and writes the Table-2-style report ``evaluate/report.md`` (+ JSON and plots). The stage commands
run one stage each, reading the earlier stages' folders under ``--out``; pass ``--smoke`` to all or to none.
``estimate --exact`` fits the true meshes instead of the tracked ones. Bad input prints one line and exits with
status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from pathlib import Path

from kernels import backend
from physavatar import pipeline
from physavatar import simulate as sim
from physavatar.body import Body
from physavatar.garment import DEFAULT_GARMENT, default_garment, load_garment, place_on_body, select_boundary
from physavatar.motion import MOTIONS, load_bvh, named_motion

SMOKE_FRAMES = 3
MAX_FRAMES = 10_000
"""Most frames ``--frames`` may ask for (6.7 minutes of motion at 25 fps): the frames are held in memory."""
MAX_VIDEO_SIZE = 8192
"""Largest video width or height (px)."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m apps.avatar", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    sim = commands.add_parser("simulate", help="simulate a garment on the moving mannequin")
    sim.add_argument(
        "--garment",
        type=Path,
        default=None,
        help=f"OBJ/PLY garment (default: {DEFAULT_GARMENT.name}, or the procedural skirt without the shared data)",
    )
    sim.add_argument(
        "--garment-scale",
        default="auto",
        help="factor from the garment file's units to metres (1 keeps its coordinates); default auto: a power of ten "
        "guessed from its height",
    )
    sim.add_argument("--motion", default="walk", help="walk, turn, raise, jump or a .bvh file")
    sim.add_argument("--frames", type=int, default=100, help="simulated frames (steps of 1/fps s)")
    sim.add_argument("--out", type=Path, required=True, help="output folder")
    sim.add_argument("--device", choices=backend.DEVICES, default=None, help="default: cuda when present")
    sim.add_argument("--boundary", choices=("auto", "waist", "shoulders"), default="auto", help="Dirichlet vertices")
    sim.add_argument("--meshes", choices=("obj", "ply"), default=None, help="also write one mesh per frame")
    sim.add_argument("--video-size", type=int, nargs=2, default=(480, 368), metavar=("W", "H"))
    sim.add_argument("--smoke", action="store_true", help=f"{SMOKE_FRAMES} frames, small render")
    stages = {
        "pipeline": "every stage below, in order, with one progress display",
        "capture": "simulate the true skirt under the fitting motion and film it",
        "track": "track the garment through the capture with mesh-aligned Gaussians",
        "estimate": "fit the membrane and bending stiffness to the tracked meshes",
        "appearance": "recover the garment's albedo and the light",
        "animate": "simulate the garment under an unseen motion with each method's parameters",
        "evaluate": "score every method against the truth: report.md, report.json, plots",
    }
    for name, text in stages.items():
        stage = commands.add_parser(name, help=text)
        stage.add_argument("--out", type=Path, required=True, help="experiment folder (one subfolder per stage)")
        stage.add_argument("--device", choices=backend.DEVICES, default=None, help="default: cuda when present")
        stage.add_argument("--smoke", action="store_true", help="tiny sizes: a few frames, 4 views of 64 px")
        stage.add_argument("--frames", type=int, default=None, help="captured frames (default 24, the paper's)")
        if name in ("estimate", "pipeline"):
            stage.add_argument(
                "--fd-iterations",
                type=int,
                default=None,
                help="Algorithm 1's Adam iterations (default 100, the paper's)",
            )
        if name in ("track", "pipeline"):
            stage.add_argument(
                "--iso-tolerance",
                type=float,
                default=None,
                help="relative edge-length change the isometry loss lets pass (default 0.05; 0 is the paper's Eq. 2)",
            )
            stage.add_argument(
                "--lambda-normal",
                type=float,
                default=None,
                help="weight of the normal loss, Eq. 3 (default 0.01 for the coarse skirt; the paper's is 0.1)",
            )
            stage.add_argument(
                "--face-subdivisions",
                type=int,
                default=None,
                help="midpoint subdivisions of each face for its Gaussians: 4^L per face (default 2; paper: 0)",
            )
        if name == "estimate":
            stage.add_argument("--exact", action="store_true", help="fit the true meshes instead of the tracked ones")
    return parser


def _check_motion(name: str) -> None:
    if name in MOTIONS:
        return
    path = Path(name)
    if path.suffix.lower() != ".bvh":
        raise ValueError(f"--motion must be one of {', '.join(MOTIONS)} or a .bvh file, got {name!r}")
    if not path.is_file():
        raise FileNotFoundError(f"motion file {path} does not exist")


def _garment_scale(text: str) -> float | str:
    """``--garment-scale``: ``"auto"`` or a positive finite number."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--garment-scale must be 'auto' or a positive number (1 for a file in metres), got {text!r}")
    return value


def _check_out(out: Path) -> None:
    """Refuse, before any work, an output folder that cannot be created or written."""
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        what = "--out" if existing == out else f"--out's parent {existing}"
        raise ValueError(f"{what} is a file, not a folder; pass a folder path for the results (it is created)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write into {existing}; pass an --out folder you may write to")


def simulate_command(args: argparse.Namespace) -> None:
    frames = SMOKE_FRAMES if args.smoke else args.frames
    if not 1 <= frames <= MAX_FRAMES:
        raise ValueError(f"--frames must be at least 1 and at most {MAX_FRAMES}, got {frames}")
    width, height = args.video_size
    if not (1 <= width <= MAX_VIDEO_SIZE and 1 <= height <= MAX_VIDEO_SIZE):
        raise ValueError(
            f"--video-size must be two positive pixel counts W H, got {width} {height}; each at most {MAX_VIDEO_SIZE}"
        )
    _check_motion(args.motion)
    _check_out(args.out)
    sim.require_video_encoder()  # before the simulation, not after it
    if args.garment is not None and not args.garment.is_file():
        raise FileNotFoundError(f"garment file {args.garment} does not exist; pass --garment PATH (OBJ or PLY)")
    scale = _garment_scale(args.garment_scale)
    backend.init(args.device)
    body = Body.mannequin(spacing=0.03)
    if args.garment is None:
        garment = default_garment(body)
    else:
        try:
            garment = place_on_body(load_garment(args.garment, scale=scale), body)
        except ValueError as error:
            raise ValueError(f"{error} (here, --garment-scale sets the file's scale)") from None
    for note in garment.notes:
        print(f"{garment.name}: {note}", file=sys.stderr)
    if args.motion in MOTIONS:
        motion = named_motion(args.motion, body.skeleton, frames)
    else:
        motion = load_bvh(Path(args.motion), body.skeleton)
    boundary = select_boundary(garment, body, mode=args.boundary)
    result = sim.simulate(garment, body, motion, frames=frames, boundary=boundary)
    args.out.mkdir(parents=True, exist_ok=True)
    sim.write_npz(result, args.out / "sequence.npz")
    sim.write_stats_json(result, args.out / "stats.json")
    if args.meshes:
        sim.write_meshes(result, args.out / "meshes", args.meshes)
    size = (128, 96) if args.smoke else (width, height)
    sim.render_video(result, args.out / "video.mp4", size=size)
    stalled = sim.stalled_steps(result)
    print(
        f"wrote {args.out}/sequence.npz, stats.json, video.mp4 ({result.garment_frames.shape[0]} frames of the "
        f"garment {garment.name!r}); {stalled} of {len(result.stats)} steps ended with a stalled line search"
        + (" (those frames are not converged solutions)" if stalled else "")
    )


def stage_command(args: argparse.Namespace) -> None:
    _check_out(args.out)
    config = pipeline.PipelineConfig.smoke() if args.smoke else pipeline.PipelineConfig()
    if args.frames is not None and args.frames > MAX_FRAMES:
        raise ValueError(f"--frames must be at most {MAX_FRAMES}, got {args.frames}")
    if args.frames is not None:
        config = dataclasses.replace(config, frames=args.frames)
    if getattr(args, "fd_iterations", None) is not None:
        if args.fd_iterations < 1:
            raise ValueError(f"--fd-iterations must be at least 1, got {args.fd_iterations}")
        config = dataclasses.replace(config, fd_iterations=args.fd_iterations)
    changes = {
        name: getattr(args, name)
        for name in ("iso_tolerance", "lambda_normal", "face_subdivisions")
        if getattr(args, name, None) is not None
    }
    if changes:
        config = dataclasses.replace(config, tracking=dataclasses.replace(config.tracking, **changes))  # range checks
    backend.init(args.device)
    progress = pipeline.stderr_progress
    if args.command == "pipeline":
        report = pipeline.run(config, args.out, progress)
        print(f"wrote {report}")
        return
    stage = {
        "capture": pipeline.capture,
        "track": pipeline.track_stage,
        "estimate": lambda c, o, p: pipeline.estimate(c, o, p, exact=args.exact),
        "appearance": pipeline.appearance,
        "animate": pipeline.animate,
        "evaluate": pipeline.evaluate,
    }[args.command]
    print(f"wrote {stage(config, args.out, progress)}")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "simulate":
            simulate_command(args)
        else:
            stage_command(args)
    except (ValueError, FileNotFoundError, ModuleNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
