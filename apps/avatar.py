"""PhysAvatar from the command line.

    python -m apps.avatar simulate --motion walk --frames 100 --out out/walk
    python -m apps.avatar simulate --garment skirt.obj --motion dance.bvh --frames 50 --out out/dance --device cuda
    python -m apps.avatar simulate --smoke --out out/smoke
    python -m apps.avatar pipeline --out out/avatar [--smoke] [--device cuda]
    python -m apps.avatar capture|track|estimate|appearance|animate|evaluate --out out/avatar [--smoke]
    python -m apps.avatar check CAPTURE
    python -m apps.avatar pipeline --capture my_capture --out out/mine [--smoke] [--device cuda]
    python -m apps.avatar prepare|track|estimate|appearance|animate|evaluate --capture my_capture --out out/mine
    python -m apps.avatar export-capture --out out/avatar --to my_capture [--push-depth-mm 3] [--up z]
    python -m apps.avatar batch --captures cap_a cap_b --out out/batch [--stages prepare track] [--executor ray]
    python -m apps.avatar batch --garments skirt long_skirt --motions walk jump --fabrics 1:1 4:0.5 --out out/study

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
``estimate --exact`` fits the true meshes instead of the tracked ones. With ``--capture DIR`` the stages run on a
user's own capture folder (``docs/capture.md``; :mod:`physavatar.pipeline.user_capture`): ``prepare`` resolves the
garment's intersections with the body and chooses the boundary, and ``evaluate`` scores renders in cameras held out
of the fit, as no truth exists; ``track`` runs ``prepare`` first when its folder is missing. Bad input prints one
line and exits with status 2.

``batch`` runs the stages over many avatars, one experiment folder ``--out/NAME`` per point
(:mod:`physavatar.pipeline.batch`): one point per ``--captures`` folder, and/or one per combination of
``--garments`` × ``--motions`` × ``--fabrics`` (``KAPPA_S:KAPPA_B``, the truth's stiffness multipliers) for a
synthetic study; ``--stages`` picks the stages each point runs (default all). It writes ``batch.json`` and
``batch.csv`` (each point's parameters, status, error and metrics) and ``batch_summary.png`` (a table and a chart of
the points). ``--executor ray`` runs the points on Ray actors, one per GPU (``--ray-address`` or ``$RAY_ADDRESS``,
else a Ray on this machine); a failed point is retried ``--retries`` times, then recorded while the others go on (exit
status 5); a rerun skips the points already complete (``docs/sweeps.md``).

``check`` validates a researcher's capture folder (``docs/capture.md``) before any heavy work
(:func:`physavatar.capture.check_capture`): it prints a summary table when the capture is usable (exit status 0,
warnings allowed) and otherwise every problem with its fix (exit status 2).

Every command checks ``--out`` and the result paths under it before any work and writes each file whole or not at
all (:func:`pienerf.output_files.atomic_path`): a file from an earlier run is replaced only by a complete one.
Ctrl-C during ``simulate``'s simulation writes the frames finished so far (sequence, statistics and meshes, no
video); Ctrl-C during ``pipeline`` keeps the stages finished before it and names the stage command to go on with;
Ctrl-C anywhere else keeps the files already written. Each time the command says what it kept and exits with status
130; a failed write (a full disk) exits with status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import math
import sys
from pathlib import Path

from kernels import backend
from physavatar import pipeline
from physavatar import simulate as sim
from physavatar.body import MOTIONS, Body, load_bvh, named_motion
from physavatar.capture import check_capture
from physavatar.garment import DEFAULT_GARMENT, default_garment, load_garment, place_on_body, select_boundary
from physavatar.pipeline import batch
from physavatar.result_files import Staging
from pienerf.executor import EXECUTORS, ExecutorConfig, ExecutorError, require_ray, run_points
from pienerf.output_files import atomic_path, check_output_folder

SMOKE_FRAMES = 3
MAX_FRAMES = 10_000
"""Most frames ``--frames`` may ask for (6.7 minutes of motion at 25 fps): the frames are held in memory."""
MAX_VIDEO_SIZE = 8192
"""Largest video width or height (px)."""
POINTS_FAILED = 5
"""Exit status of a ``batch`` some of whose points failed after their retries (``batch.json`` holds each error)."""


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
    sim.add_argument(
        "--joint-map",
        default=None,
        metavar="OURS=THEIRS,...",
        help="for a .bvh motion whose joints are named differently: our joint names mapped to the file's, e.g. "
        "pelvis=Hips,spine1=Spine (the joints not named keep the best-matching built-in naming)",
    )
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
        "prepare": "with --capture: resolve the garment's intersections with the body, choose the boundary",
        "track": "track the garment through the capture with mesh-aligned Gaussians",
        "estimate": "fit the membrane and bending stiffness to the tracked meshes",
        "appearance": "recover the garment's albedo and the light",
        "animate": "simulate the garment under an unseen motion with each method's parameters",
        "evaluate": "score every method against the truth: report.md, report.json, plots",
    }
    export = commands.add_parser(
        "export-capture", help="write the synthetic experiment's capture as a capture folder of your own kind"
    )
    export.add_argument("--out", type=Path, required=True, help="experiment folder whose capture stage has run")
    export.add_argument("--to", type=Path, required=True, help="the capture folder to write")
    export.add_argument("--push-depth-mm", type=float, default=3.0, help="depth of the pushed vertices in the body")
    export.add_argument("--push-fraction", type=float, default=0.05, help="fraction of garment vertices pushed in")
    export.add_argument("--up", choices=("y", "z"), default="z", help="world up axis of the written folder")
    for name, text in stages.items():
        stage = commands.add_parser(name, help=text)
        stage.add_argument("--out", type=Path, required=True, help="experiment folder (one subfolder per stage)")
        stage.add_argument("--device", choices=backend.DEVICES, default=None, help="default: cuda when present")
        stage.add_argument("--smoke", action="store_true", help="tiny sizes: a few frames, 4 views of 64 px")
        stage.add_argument("--frames", type=int, default=None, help="captured frames (default 24, the paper's)")
        if name not in ("capture",):
            stage.add_argument(
                "--capture",
                type=Path,
                default=None,
                metavar="DIR",
                help="a capture folder of your own (docs/capture.md) instead of the synthetic experiment",
            )
        if name in ("prepare", "pipeline", "track"):
            stage.add_argument(
                "--held-out-cameras",
                type=int,
                nargs="*",
                default=None,
                metavar="C",
                help="with --capture: cameras kept out of the fit for the evaluation (default: the last of three or "
                "more; none: no camera)",
            )
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
            stage.add_argument(
                "--stiffness",
                choices=("global", "regions"),
                default="global",
                help="regions: also fit (kappa_s, kappa_b) per angular sector of the garment, by the rollout's adjoint",
            )
            stage.add_argument("--regions", type=int, default=8, help="sectors for --stiffness regions (default 8)")
            stage.add_argument(
                "--fit",
                choices=pipeline.FITS,
                default="meshes",
                help="images: fit the parameters to the capture's images through the rollout, no tracked meshes",
            )
    run = commands.add_parser("batch", help="the stages over many captures or a synthetic study, one folder each")
    run.add_argument("--out", type=Path, required=True, help="batch folder (one experiment folder per point)")
    run.add_argument("--captures", type=Path, nargs="*", default=[], metavar="DIR", help="capture folders")
    run.add_argument("--garments", nargs="*", default=[], help=f"study garments: {', '.join(batch.STUDY_GARMENTS)}")
    run.add_argument("--motions", nargs="*", default=["walk"], help=f"study fitting motions: {', '.join(MOTIONS)}")
    run.add_argument("--fabrics", nargs="*", default=["1:1"], metavar="KS:KB", help="study truths: κ_s:κ_b")
    run.add_argument("--stages", nargs="*", default=None, help="the stages each point runs, in order (default all)")
    run.add_argument("--exact", action="store_true", help="study: estimate from the true meshes, not the tracked")
    run.add_argument("--device", choices=backend.DEVICES, default=None, help="default: cuda when present")
    run.add_argument("--smoke", action="store_true", help="tiny sizes: a few frames, 4 views of 64 px")
    run.add_argument("--frames", type=int, default=None, help="captured frames (default 24, the paper's)")
    run.add_argument("--executor", choices=EXECUTORS, default="local", help="local (in turn, here) or ray (tasks)")
    run.add_argument("--ray-address", default=None, help="Ray cluster (default $RAY_ADDRESS, else a local Ray)")
    run.add_argument("--retries", type=int, default=2, help="attempts after the first for a point that fails")
    check = commands.add_parser("check", help="check a capture folder for problems before any heavy work")
    check.add_argument("capture", type=Path, metavar="CAPTURE", help="the capture folder (or its transforms.json)")
    return parser


def _joint_map(text: str | None, body: Body) -> dict[str, str] | None:
    """``--joint-map``'s ``ours=theirs,...`` as load_bvh's name map (over the built-in naming that fits best), or
    ``None``; a malformed pair or a joint we do not have is a ValueError naming it."""
    if text is None:
        return None
    names = body.skeleton.names
    mapping = {}
    for pair in text.split(","):
        ours, sep, theirs = (part.strip() for part in pair.partition("="))
        if not sep or not ours or not theirs:
            raise ValueError(f"--joint-map takes ours=theirs pairs separated by commas, got {pair!r}")
        if ours not in names:
            raise ValueError(f"--joint-map names {ours!r}, which is not one of our joints: {', '.join(names)}")
        mapping[ours] = theirs
    return mapping


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


RESULT_FILES = ("sequence.npz", "stats.json", "video.mp4")
"""What ``simulate`` writes into ``--out`` (and ``meshes/`` with ``--meshes``)."""


def _check_results_in_the_way(out: Path, names) -> None:
    """Refuse, before any work, a result path under ``out`` taken by something it cannot replace, or a result
    folder there that cannot be written into. ``names`` are relative to ``out``; a folder's ends with ``/``."""
    for name in names:
        path = out / name
        if name.endswith("/"):
            if path.exists() and not path.is_dir():
                raise ValueError(f"{path} is a file where a result folder goes; remove it or pass another --out")
            check_output_folder(path)
        elif path.is_dir():
            raise ValueError(f"{path} is a folder where a result file goes; remove it or pass another --out")


def _write_results(result: sim.SimulationResult, args: argparse.Namespace, video: bool, written: list[str]) -> None:
    """Write the sequence, statistics, meshes and (with ``video``) the video, each atomically; ``written`` gathers
    the names finished, for the report of a run stopped part way."""
    args.out.mkdir(parents=True, exist_ok=True)
    sim.write_npz(result, args.out / "sequence.npz", staging=atomic_path)
    written.append("sequence.npz")
    sim.write_stats_json(result, args.out / "stats.json", staging=atomic_path)
    written.append("stats.json")
    if args.meshes:
        sim.write_meshes(result, args.out / "meshes", args.meshes, staging=atomic_path)
        written.append(f"meshes/ ({result.garment_frames.shape[0]} {args.meshes} files)")
    if video:
        size = (128, 96) if args.smoke else tuple(args.video_size)
        sim.render_video(result, args.out / "video.mp4", size=size, staging=atomic_path)
        written.append("video.mp4")


def simulate_command(args: argparse.Namespace) -> int:
    frames = SMOKE_FRAMES if args.smoke else args.frames
    if not 1 <= frames <= MAX_FRAMES:
        raise ValueError(f"--frames must be at least 1 and at most {MAX_FRAMES}, got {frames}")
    width, height = args.video_size
    if not (1 <= width <= MAX_VIDEO_SIZE and 1 <= height <= MAX_VIDEO_SIZE):
        raise ValueError(
            f"--video-size must be two positive pixel counts W H, got {width} {height}; each at most {MAX_VIDEO_SIZE}"
        )
    _check_motion(args.motion)
    check_output_folder(args.out)
    _check_results_in_the_way(args.out, RESULT_FILES + (("meshes/",) if args.meshes else ()))
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
        try:
            motion = load_bvh(Path(args.motion), body.skeleton, name_map=_joint_map(args.joint_map, body))
        except ValueError as error:
            raise ValueError(f"{error}: --joint-map ours=theirs,... on this command line") from None
    boundary = select_boundary(garment, body, mode=args.boundary)
    try:
        result = sim.simulate(garment, body, motion, frames=frames, boundary=boundary)
        interrupted = None
    except sim.SimulationInterrupted as stop:
        result, interrupted = stop.result, stop
        if not result.stats:
            print(f"interrupted before the first step finished: nothing written to {args.out}", file=sys.stderr)
            return 130
        print(f"{stop} (Ctrl-C); writing the frames finished so far", file=sys.stderr)
    written: list[str] = []
    try:
        _write_results(result, args, video=interrupted is None, written=written)
    except KeyboardInterrupt:
        print(f"interrupted while writing the results; {_kept(args.out, written)}", file=sys.stderr)
        return 130
    except OSError as error:
        print(f"error: writing the results failed ({error}); {_kept(args.out, written)}", file=sys.stderr)
        return 1
    stalled = sim.stalled_steps(result)
    print(
        f"wrote {args.out}/{', '.join(written)} ({result.garment_frames.shape[0]} frames of the garment "
        f"{garment.name!r}); {stalled} of {len(result.stats)} steps ended with a stalled line search"
        + (" (those frames are not converged solutions)" if stalled else "")
    )
    if interrupted is not None:
        print(f"{interrupted} (Ctrl-C): {args.out} holds the frames finished before it, no video", file=sys.stderr)
        return 130
    return 0


def _kept(out: Path, written: list[str]) -> str:
    """What a run stopped while writing kept (the file in progress is never left half-written)."""
    if not written:
        return f"nothing written to {out}"
    return f"kept {out}/{', '.join(written)}; the file in progress was not written"


def _recording(written: list[Path]) -> Staging:
    """:func:`atomic_path` that notes in ``written`` every file it puts in place, for the report of a run stopped
    part way."""

    @contextlib.contextmanager
    def staging(path: Path):
        with atomic_path(path) as temporary:
            yield temporary
        written.append(Path(path))

    return staging


def _kept_stages(out: Path, written: list[Path], outputs: dict[str, tuple[str, ...]] = pipeline.OUTPUTS) -> str:
    """What a stage command stopped part way kept: the stages it finished whole, then the files of an unfinished one
    (a folder's frames counted, not listed). No file is ever left half-written."""
    if not written:
        return f"nothing written to {out}; no file was left half-written"
    done = [path.relative_to(out).as_posix() for path in written]
    parts = []
    for stage, names in outputs.items():
        files = [name for name in done if name.startswith(f"{stage}/")]
        whole = all(name in done for name in names if not name.endswith("/"))
        if whole:
            parts.append(f"{stage}/ (whole)")
            continue
        folders: dict[str, list[str]] = {}
        for name in files:
            folders.setdefault(name.rpartition("/")[0], []).append(name)
        for folder, names in folders.items():
            parts.extend(names if len(names) <= 3 else [f"{folder}/ ({len(names)} files)"])
    return f"kept in {out}: {', '.join(parts)}; no file was left half-written"


def _stage(args: argparse.Namespace, config: pipeline.PipelineConfig):
    """The function the command runs: ``stage(config, out, progress, staging=...)``."""
    exact = getattr(args, "exact", False)
    fit = getattr(args, "fit", "meshes")
    regions = args.regions if getattr(args, "stiffness", "global") == "regions" else None
    if regions is not None and not 1 <= regions <= 64:
        raise ValueError(f"--regions must lie in 1..64 sectors, got {regions}")
    if args.capture is None:
        return {
            "pipeline": pipeline.run,
            "capture": pipeline.capture,
            "track": pipeline.track_stage,
            "estimate": functools.partial(pipeline.estimate, exact=exact, regions=regions, fit=fit),
            "appearance": pipeline.appearance,
            "animate": pipeline.animate,
            "evaluate": pipeline.evaluate,
        }[args.command]
    capture, held_out = args.capture, getattr(args, "held_out_cameras", None)
    held_out = None if held_out is None else tuple(held_out)

    def track_prepared(config, out, progress, staging):
        if not (Path(out) / "prepare" / "prepare.json").is_file():
            progress("track", f"{Path(out) / 'prepare'} is missing: preparing the capture first")
            pipeline.prepare(config, out, progress, staging, capture=capture, held_out_cameras=held_out)
        return pipeline.track_stage(config, out, progress, staging, capture=capture)

    return {
        "pipeline": functools.partial(pipeline.run_capture, capture=capture, held_out_cameras=held_out),
        "prepare": functools.partial(pipeline.prepare, capture=capture, held_out_cameras=held_out),
        "track": track_prepared,
        "estimate": functools.partial(pipeline.estimate, exact=exact, capture=capture, regions=regions, fit=fit),
        "appearance": functools.partial(pipeline.appearance, capture=capture),
        "animate": functools.partial(pipeline.animate_capture, capture=capture),
        "evaluate": functools.partial(pipeline.evaluate_capture, capture=capture),
    }[args.command]


def stage_command(args: argparse.Namespace) -> int:
    check_output_folder(args.out)
    args.capture = getattr(args, "capture", None)
    if args.command == "prepare" and args.capture is None:
        raise ValueError("prepare readies a capture of your own: pass --capture DIR (see docs/capture.md)")
    if args.capture is not None and not args.capture.is_dir():
        raise FileNotFoundError(f"--capture {args.capture} is not a folder; pass a capture folder (docs/capture.md)")
    own = args.capture is not None
    stage_names = pipeline.CAPTURE_STAGES if own else pipeline.STAGES
    outputs = pipeline.CAPTURE_OUTPUTS if own else pipeline.OUTPUTS
    stages = stage_names if args.command == "pipeline" else (args.command,)
    if args.command == "track" and args.capture is not None and not (args.out / "prepare" / "prepare.json").is_file():
        stages = ("prepare", "track")
    _check_results_in_the_way(args.out, [name for stage in stages for name in outputs[stage]])
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
    stage = _stage(args, config)
    written: list[Path] = []
    try:
        print(f"wrote {stage(config, args.out, pipeline.stderr_progress, staging=_recording(written))}")
    except pipeline.PipelineInterrupted as stop:
        again = f"python -m apps.avatar {stop.stage} --out {args.out}" + (" --smoke" if args.smoke else "")
        again += f" --capture {args.capture}" if args.capture is not None else ""
        kept = _kept_stages(args.out, written, outputs)
        print(
            f"{stop} (Ctrl-C); {kept}; to go on, run {again} and the stages after it",
            file=sys.stderr,
        )
        return 130
    except KeyboardInterrupt:
        print(
            f"interrupted: the {args.command} stage stopped (Ctrl-C); {_kept_stages(args.out, written, outputs)}",
            file=sys.stderr,
        )
        return 130
    except FileNotFoundError:
        raise  # an earlier stage's file is missing: named by the stage, exit status 2
    except OSError as error:
        print(f"error: {args.command} failed ({error}); {_kept_stages(args.out, written, outputs)}", file=sys.stderr)
        return 1
    return 0


def check_command(args: argparse.Namespace) -> int:
    """Print the capture's check report; exit status 0 when usable (warnings allowed), 2 with problems."""
    report = check_capture(args.capture)
    print(report.format())
    return 0 if report.ok else 2


def export_command(args: argparse.Namespace) -> int:
    check_output_folder(args.to)
    record = pipeline.export_capture_folder(
        args.out, args.to, args.push_depth_mm * 1e-3, args.push_fraction, args.up, staging=atomic_path
    )
    print(f"wrote {args.to}: {len(record['pushed'])} garment vertices start {args.push_depth_mm:g} mm inside the body")
    return 0


def batch_command(args: argparse.Namespace) -> int:
    """Run the batch's points; exit status 0, 5 when points failed, 130 interrupted."""
    check_output_folder(args.out)
    points: dict[str, dict] = {}
    if args.captures:
        stages = tuple(args.stages) if args.stages is not None else pipeline.CAPTURE_STAGES
        points.update(batch.capture_points(args.captures, stages))
    if args.garments:
        stages = tuple(args.stages) if args.stages is not None else pipeline.STAGES
        study = batch.study_points(args.garments, args.motions, args.fabrics, stages)
        clash = sorted(set(study) & set(points))
        if clash:
            raise ValueError(f"capture folders and study points share the names {clash}; rename those folders")
        points.update(study)
    if not points:
        raise ValueError("a batch needs --captures DIR [DIR ...] and/or --garments NAME [NAME ...] (a study)")
    config = pipeline.PipelineConfig.smoke() if args.smoke else pipeline.PipelineConfig()
    if args.frames is not None:
        if not 3 <= args.frames <= MAX_FRAMES:
            raise ValueError(f"--frames must lie in 3..{MAX_FRAMES}, got {args.frames}")
        config = dataclasses.replace(config, frames=args.frames)
    if args.executor == "ray":
        require_ray()
    if args.executor == "ray":  # the points run in Ray's workers, which may be on other machines
        device = args.device or backend.default_device()
    else:
        device = backend.init(args.device)
    executor = ExecutorConfig(args.executor, device, address=args.ray_address, max_retries=args.retries)
    function = functools.partial(batch.run_batch_point, config=config, device=executor.device, exact=args.exact)
    extra = {"smoke": args.smoke, "frames": config.frames}
    try:
        entries = run_points(points, function, args.out, executor, index=batch.BATCH_INDEX, extra=extra)
    except KeyboardInterrupt:
        print(
            f"interrupted: {args.out / 'batch.json'} lists the points that finished; run the same command again to go "
            "on (the complete points are skipped)",
            file=sys.stderr,
        )
        return 130
    summary = batch.plot_batch_summary(entries, args.out / batch.BATCH_SUMMARY, staging=atomic_path)
    failed = [entry for entry in entries if entry["status"] == "failed"]
    print(
        f"wrote {args.out / 'batch.json'}, {args.out / 'batch.csv'}, {summary}: {len(entries) - len(failed)} of "
        f"{len(entries)} points complete"
    )
    for entry in failed:
        print(f"error: batch point {entry['name']} failed: {entry['error']}", file=sys.stderr)
    return POINTS_FAILED if failed else 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "simulate":
            return simulate_command(args)
        if args.command == "check":
            return check_command(args)
        if args.command == "export-capture":
            return export_command(args)
        if args.command == "batch":
            return batch_command(args)
        return stage_command(args)
    except (ValueError, FileNotFoundError, ModuleNotFoundError, ExecutorError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted: {args.command} stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
