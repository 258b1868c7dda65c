"""PhysAvatar end to end on a synthetic capture: capture → track → estimate → appearance → animate → evaluate.

Real multi-view captures are not available to this project, so the ground truth is synthetic and exact: the
cloth simulator with known parameters moves a garment on the skinned mannequin, the capture films it, and the
pipeline must recover the garment's physics and appearance from the images alone. Each stage reads the previous
stages' folders and writes its own, so the stages run one by one (``python -m apps.avatar capture|track|...``)
or all at once (``pipeline``):

``capture/``
    ``transforms.json``, ``images/``, ``masks/`` (:func:`physavatar.capture.write_capture`); ``inputs.npz``: what the
    method is given besides the images — the garment's mesh at the first frame, the body's vertices per frame
    (the paper's SMPL-X fit), the annotated boundary vertices and their skinned targets; ``truth.npz``: the true
    garment frames, albedo and parameters, read by ``evaluate`` only.
``track/``
    ``tracked.npz``: garment vertices and Gaussian colours per frame (§3.1), ``tracking.json``.
``estimate/``
    ``estimate.json``: (κ_s, κ_b) at fixed ρ by Algorithm 1 (forward differences + Adam) and by the analytic
    sensitivities (Levenberg–Marquardt), iterations, simulations, time and the recovered ratios; ``estimate.png``.
``appearance/``
    ``appearance.npz`` (albedo, baked texture), ``appearance.json`` (light), ``relit.png`` (§3.3).
``animate/``
    ``animation.npz``: the garment under a motion not seen in fitting for every method compared (truth, full,
    w/o physics = random parameters, LBS).
``evaluate/``
    ``report.md``, ``report.json``, ``chamfer.png``/``metrics.png`` and ``comparison.png``: the structure of the
    paper's Table 2.

:data:`OUTPUTS` lists these paths, so a program can check them before any work. Every stage writes each file
through the ``staging`` step it is given (:data:`physavatar.result_files.Staging`; the default writes the path
itself), so a program can have each written whole or not at all. Ctrl-C during :func:`run` raises
:class:`PipelineInterrupted`, which names the stage it stopped and the stages that finished before it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from kernels.image_metrics import psnr, ssim
from physavatar.body import MOTIONS, Body, named_motion
from physavatar.capture import (
    CameraRig,
    Capture,
    CaptureFolder,
    Lighting,
    garment_albedo,
    load_capture,
    load_capture_folder,
    load_truth,
    render_capture,
    write_capture,
)
from physavatar.cloth import ClothConfig
from physavatar.drive import BodyDriver
from physavatar.fit.appearance import albedo_error, estimate_appearance, relight
from physavatar.fit.estimation import (
    SYNTHETIC_FABRIC,
    EstimationProblem,
    FabricParameters,
    estimate_analytic,
    estimate_finite_differences,
    rollout,
)
from physavatar.fit.evaluation import geometry_scores, lbs_garment
from physavatar.fit.images import ImageFitConfig, estimate_images
from physavatar.fit.regions import estimate_regions, garment_regions
from physavatar.fit.tracking import TrackConfig, track
from physavatar.garment import procedural_skirt, select_boundary
from physavatar.pipeline.report import SMOKE_NOTE, plot_estimation, plot_report, report_markdown, write_strip
from physavatar.result_files import Staging, write_arrays, write_json, write_text

__all__ = [
    "COARSE_MESH_TRACKING",
    "FITS",
    "OUTPUTS",
    "STAGES",
    "PipelineConfig",
    "PipelineInterrupted",
    "StageInputs",
    "animate",
    "appearance",
    "capture",
    "estimate",
    "evaluate",
    "camera_views",
    "random_parameters",
    "run",
    "run_stages",
    "say",
    "stage_inputs",
    "stderr_progress",
    "track_stage",
]

BODY_COLOR = (0.78, 0.74, 0.68)


STAGES = ("capture", "track", "estimate", "appearance", "animate", "evaluate")
FITS = ("meshes", "images")
"""What the estimate stage fits the simulation to: the tracked meshes (the paper's §3.2) or the capture's images."""
IMAGE_FIT = "images_lbfgs_adjoint"
OUTPUTS: dict[str, tuple[str, ...]] = {
    "capture": (
        "capture/",
        "capture/images/",
        "capture/masks/",
        "capture/truth.npz",
        "capture/transforms.json",
        "capture/inputs.npz",
    ),
    "track": ("track/", "track/tracked.npz", "track/tracking.json"),
    "estimate": ("estimate/", "estimate/estimate.json", "estimate/estimate.png"),
    "appearance": ("appearance/", "appearance/appearance.npz", "appearance/appearance.json", "appearance/relit.png"),
    "animate": ("animate/", "animate/animation.npz"),
    "evaluate": (
        "evaluate/",
        "evaluate/report.json",
        "evaluate/report.md",
        "evaluate/chamfer.png",
        "evaluate/metrics.png",
        "evaluate/comparison.png",
    ),
}
"""What each stage writes under the experiment folder, in order: folders end with ``/`` (``capture/images/`` and
``capture/masks/`` hold one PNG per frame and camera, ``t0000_c00.png``)."""


COARSE_MESH_TRACKING = TrackConfig(face_subdivisions=2, lambda_normal=0.01, iso_tolerance=0.05)
"""Tracking of the experiment's coarse skirt (280 vertices, faces of ~4 cm, ~12 px across at 256²): 16 Gaussians
per face, Eq. 3 at a tenth of the paper's weight, and 5 % of free stretch in Eq. 2.

The paper tracks dense scans whose faces cover a few pixels; on this mesh its settings bias the shape. Eq. 3 sums
``1 − cos θ ≈ θ²/2`` over neighbouring faces, and the dihedral angles ``θ`` grow with the face size, so at
``λ_n = 0.1`` it flattens the folds of the hem; one Gaussian per face cannot cover a 12-px triangle, so the
silhouette pulls the hem inward. With these settings the tracking error fell from 11.0 to 3.2 mm and both ratios
came within 3 % of the truth (24 frames of the walk, 8 views at 256²; the table is in ``docs/benchmarks.md``).
"""


@dataclass(frozen=True)
class PipelineConfig:
    """Sizes and settings of the synthetic experiment.

    Attributes:
        frames: captured frames used for tracking and fitting (paper: 24), at ``fps``.
        eval_frames: frames of the unseen evaluation motion.
        fps: frames per second; one simulation step per frame (paper: Δt = 0.04 s).
        fit_motion, eval_motion: names in :data:`physavatar.body.MOTIONS`.
        cameras: cameras on the capture ring.
        image_size: ``(width, height)`` of every view, px.
        ao_samples: sky-occlusion rays per pixel of the capture.
        skirt_rings, skirt_segments: resolution of the procedural skirt.
        skirt_length: the procedural skirt's length from the hips, m.
        fabric: material and solver settings of the truth and of every fit (:data:`SYNTHETIC_FABRIC`).
        start: where estimation starts (the true κ's are those of ``fabric``).
        random_seed: seed of the "w/o physics" parameters, drawn log-uniformly from the paper's κ range.
        fd_iterations: Algorithm 1's iterations (paper: 100).
        lm_iterations: Levenberg–Marquardt's iteration cap.
        image_iterations: L-BFGS iterations of the fit to the images (:mod:`physavatar.fit.images`).
        tracking: settings of the tracker (:data:`COARSE_MESH_TRACKING`).
        seed: seed of everything else random (occlusion directions).
        smoke_size: a smoke-size run (:meth:`smoke`): every stage runs, but its scores and estimates measure nothing
            (too few frames, pixels and iterations), and the report says so.
    """

    frames: int = 24
    eval_frames: int = 24
    fps: float = 25.0
    fit_motion: str = "walk"
    eval_motion: str = "turn"
    cameras: int = 8
    image_size: tuple[int, int] = (256, 256)
    ao_samples: int = 16
    skirt_rings: int = 10
    skirt_segments: int = 28
    skirt_length: float = 0.40
    fabric: ClothConfig = SYNTHETIC_FABRIC
    start: FabricParameters = FabricParameters(SYNTHETIC_FABRIC.density, 2.0, 0.5)
    random_seed: int = 3
    fd_iterations: int = 100
    lm_iterations: int = 12
    image_iterations: int = 15
    tracking: TrackConfig = COARSE_MESH_TRACKING
    seed: int = 0
    smoke_size: bool = False

    def __post_init__(self):
        for name in ("fit_motion", "eval_motion"):
            if getattr(self, name) not in MOTIONS:
                raise ValueError(f"{name} must be one of {', '.join(MOTIONS)}, got {getattr(self, name)!r}")
        if self.frames < 3 or self.eval_frames < 2:
            raise ValueError(f"frames ({self.frames}) must be >= 3 and eval_frames ({self.eval_frames}) >= 2")
        if not (math.isfinite(self.skirt_length) and 0.1 <= self.skirt_length <= 0.8):
            raise ValueError(f"skirt_length must lie in 0.1–0.8 m, got {self.skirt_length!r}")
        if self.cameras < 1 or min(self.image_size) < 16:
            raise ValueError(f"need >= 1 camera and images of >= 16 px, got {self.cameras} and {self.image_size}")

    @classmethod
    def smoke(cls) -> PipelineConfig:
        """A few frames of a small skirt in tiny images: every stage runs, in about a minute on a CPU.

        The evaluation motion keeps the paper's 24 frames: over fewer, the skirt has not yet swung out and the
        LBS garment stays close to the truth, so the comparison of Table 2 says little.
        """
        return cls(
            frames=6,
            eval_frames=24,
            cameras=4,
            image_size=(64, 64),
            ao_samples=4,
            skirt_rings=5,
            skirt_segments=14,
            fd_iterations=2,
            lm_iterations=3,
            image_iterations=2,
            tracking=dataclasses.replace(COARSE_MESH_TRACKING, first_iterations=30, iterations=15),
            smoke_size=True,
        )


Progress = Callable[[str, str], None]


class PipelineInterrupted(KeyboardInterrupt):
    """Ctrl-C (``KeyboardInterrupt``) during :func:`run`.

    Attributes:
        stage: the stage that was running (a name in :data:`STAGES`); the files it finished are whole, the one in
            progress is as the staging step leaves it.
        finished: the stages that finished before it, in order.
    """

    def __init__(self, stage: str, finished: tuple[str, ...]):
        super().__init__(f"interrupted in the {stage} stage ({len(finished) + 1} of {len(STAGES)})")
        self.stage, self.finished = stage, finished


def say(progress: Progress | None, stage: str, message: str) -> None:
    """Hand ``message`` about ``stage`` to ``progress``, if there is one."""
    if progress is not None:
        progress(stage, message)


def stderr_progress(stage: str, message: str) -> None:
    print(f"[{stage}] {message}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------------------------
# Scene: body, garment, motions
# ---------------------------------------------------------------------------------------------------------------


def _scene(config: PipelineConfig):
    body = Body.mannequin(spacing=0.03)
    garment = procedural_skirt(
        body, rings=config.skirt_rings, segments=config.skirt_segments, length=config.skirt_length
    )
    boundary = select_boundary(garment, body, mode="waist")
    return body, garment, boundary


def _forward(config: PipelineConfig, body: Body, garment, boundary: torch.Tensor, motion: str, frames: int):
    """The garment at rest driven through the first ``frames`` poses of ``motion``: the body's skinned vertices and the
    boundary's targets, as a problem :func:`physavatar.fit.estimation.rollout` simulates (its reference is a
    placeholder, the rest shape). Returns ``(problem, clip)``."""
    clip = named_motion(motion, body.skeleton, frames - 1, config.fps)
    driver = BodyDriver.from_motion(body, clip, garment.vertices, boundary, frames - 1)
    problem = EstimationProblem(
        garment.vertices,
        garment.faces,
        garment.vertices.expand(frames, -1, -1),
        driver.body_frames,
        body.faces,
        driver.boundary_index,
        driver.boundary_targets,
        config.fps,
        config.fabric,
    )
    return problem, clip


# ---------------------------------------------------------------------------------------------------------------
# Stages
# ---------------------------------------------------------------------------------------------------------------


def capture(
    config: PipelineConfig, out: Path, progress: Progress | None = None, staging: Staging = contextlib.nullcontext
) -> Path:
    """Simulate the truth under the fitting motion and film it; writes ``out/capture``, each file through
    ``staging``."""
    folder = Path(out) / "capture"
    body, garment, boundary = _scene(config)
    problem, _ = _forward(config, body, garment, boundary, config.fit_motion, config.frames)
    body_frames, targets = problem.body_frames, problem.boundary_targets
    truth = FabricParameters.from_config(config.fabric)
    say(progress, "capture", f"simulating the truth ({config.frames} frames, {garment.vertices.shape[0]} vertices)")
    frames = rollout(problem, truth).frames
    albedo = garment_albedo(garment.vertices, garment.faces, pattern="checks", bands=6)
    rig = _rig(config, body)
    lighting = Lighting()
    say(progress, "capture", f"rendering {config.cameras} views × {config.frames} frames")
    film = render_capture(
        frames,
        garment.faces,
        body_frames,
        body.faces,
        albedo,
        BODY_COLOR,
        rig,
        lighting,
        config.fps,
        ao_samples=config.ao_samples,
        seed=config.seed,
        progress=lambda done, n: say(progress, "capture", f"frame {done}/{n}"),  # done counts from 1
    )
    write_capture(
        film,
        folder,
        truth={
            "garment_frames": frames.numpy(),
            "albedo": albedo.numpy(),
            "parameters": dataclasses.asdict(truth),
        },
        staging=staging,
    )
    write_arrays(
        folder / "inputs.npz",
        staging,
        first_vertices=frames[0].numpy(),
        faces=garment.faces.numpy(),
        body_frames=body_frames.numpy(),
        body_faces=body.faces.numpy(),
        boundary_index=boundary.numpy(),
        boundary_targets=targets.numpy(),
        fps=config.fps,
    )
    return folder


def _rig(config: PipelineConfig, body: Body) -> CameraRig:
    width, height = config.image_size
    # Framed on the skirt (waist 1.06 m to hem ~0.65 m) rather than the whole body: more pixels per fold.
    return CameraRig.ring(config.cameras, 2.2, 0.25, (0.0, 0.86, 0.0), width, height, fov_deg=24.0, phase_deg=20.0)


def _inputs(path: Path) -> dict:
    """The arrays of an ``inputs.npz`` (the synthetic capture's, or what :mod:`~physavatar.pipeline.user_capture`
    prepared from a user's capture): tensors, and ``fps`` as a number."""
    if not path.is_file():
        stage = "capture" if path.parent.name == "capture" else "prepare"
        raise FileNotFoundError(f"{path} is missing; run the {stage} stage first (python -m apps.avatar {stage})")
    with np.load(path) as data:
        return {k: torch.from_numpy(data[k]) if data[k].ndim else float(data[k]) for k in data.files}


@dataclass(frozen=True, eq=False)
class StageInputs:
    """What the stages after the capture read, from the synthetic experiment or from a user's capture folder.

    Attributes:
        film: the views the fit sees: the synthetic capture, or a user's capture without its held-out cameras;
            ``None`` where the stage asked for no views.
        given: ``first_vertices`` ``[V, 3]`` (m), ``faces``, ``body_frames`` ``[T, B, 3]`` (m), ``body_faces``,
            ``boundary_index`` ``[D]``, ``boundary_targets`` ``[T, D, 3]`` (m) and ``fps``, in the project's y-up
            axes.
        truth: the synthetic capture's ``truth.npz`` (:func:`physavatar.capture.load_truth`), or ``None``.
        folder: the user's capture, or ``None`` for the synthetic experiment or where no views were asked for.
        held_out: cameras of the user's capture kept out of the fit for the evaluation (empty for the synthetic
            experiment, whose evaluation has the truth).
        up: the up axis of the capture's world (``"y"`` for the synthetic experiment), for results written back.
    """

    film: Capture | None
    given: dict
    truth: dict | None
    folder: CaptureFolder | None = None
    held_out: tuple[int, ...] = ()
    up: str = "y"


def stage_inputs(out: Path, capture: Path | None = None, views: bool = True) -> StageInputs:
    """The :class:`StageInputs` of the experiment in ``out``: the synthetic capture in ``out/capture``, or, with
    ``capture``, the user's capture folder as the preparation stage left it in ``out/prepare``. Without ``views``
    no image is read (a stage that needs only the meshes)."""
    if capture is None:
        capture_dir = Path(out) / "capture"
        film = load_capture(capture_dir) if views else None
        given = _inputs(capture_dir / "inputs.npz")
        return StageInputs(film, given, load_truth(capture_dir))
    given = _inputs(Path(out) / "prepare" / "inputs.npz")
    record = json.loads((Path(out) / "prepare" / "prepare.json").read_text())
    held_out = tuple(record["held_out_cameras"])
    if not views:
        return StageInputs(None, given, None, None, held_out, record["up"])
    folder = load_capture_folder(capture)
    if given["faces"].shape != folder.garment_faces.shape or given["body_frames"].shape != folder.body_frames.shape:
        raise ValueError(
            f"{Path(out) / 'prepare'} was prepared from another capture than {capture}; run the prepare stage again "
            "or pass the capture it was prepared from"
        )
    fit = [c for c in range(folder.film.camera_count) if c not in held_out]
    return StageInputs(camera_views(folder.film, fit), given, None, folder, held_out, folder.up)


def camera_views(film: Capture, cameras: list[int]) -> Capture:
    """The capture seen by ``cameras`` only (indices into its rig), renumbered ``0..len(cameras) − 1``."""
    index = torch.as_tensor(cameras, dtype=torch.long)
    rig = film.rig
    intrinsics = rig.intrinsics[index]
    views = CameraRig(rig.c2w[index], rig.width, rig.height, *intrinsics.T)
    return dataclasses.replace(film, images=film.images[:, index], masks=film.masks[:, index], rig=views)


def track_stage(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    capture: Path | None = None,
) -> Path:
    """Track the garment through ``out/capture`` (or the user's ``capture`` folder, prepared in ``out/prepare``);
    writes ``out/track``, each file through ``staging``."""
    folder = Path(out) / "track"
    inputs = stage_inputs(out, capture)
    film, given = inputs.film, inputs.given
    true_frames = None if inputs.truth is None else torch.as_tensor(inputs.truth["garment_frames"])
    _check_frames(film.images.shape[0], given["body_frames"].shape[0], "the capture", "the body frames")
    result = track(
        film,
        given["first_vertices"],
        given["faces"],
        given["body_frames"],
        given["body_faces"],
        config.tracking,
        truth=true_frames,
        progress=lambda t, loss, err: say(
            progress,
            "track",
            f"frame {t + 1}/{film.images.shape[0]}: loss {loss:.4f}"
            + (f", error {err * 1e3:.2f} mm" if true_frames is not None else ""),
        ),
    )
    folder.mkdir(parents=True, exist_ok=True)
    write_arrays(folder / "tracked.npz", staging, vertices=result.vertices.numpy(), colors=result.colors.numpy())
    record = {
        "frames": int(result.vertices.shape[0]),
        "render_loss": result.render_loss.tolist(),
        "vertex_error_m": result.vertex_error.tolist() if true_frames is not None else None,
        "mean_vertex_error_m": float(result.vertex_error[1:].mean()) if len(result.vertex_error) > 1 else None,
        "seconds_per_frame": result.frame_time,
    }
    write_json(folder / "tracking.json", record, staging)
    return folder


def _check_frames(a: int, b: int, name_a: str, name_b: str) -> None:
    if a != b:
        raise ValueError(f"{name_a} has {a} frames but {name_b} has {b}; the stages must come from one capture")


def _tracked(out: Path) -> dict:
    path = Path(out) / "track" / "tracked.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing; run the track stage first (python -m apps.avatar track)")
    with np.load(path) as data:
        return {k: torch.from_numpy(data[k]) for k in data.files}


def estimate(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    exact: bool = False,
    staging: Staging = contextlib.nullcontext,
    capture: Path | None = None,
    regions: int | None = None,
    fit: str = "meshes",
) -> Path:
    """Fit (κ_s, κ_b) at fixed ρ to the tracked meshes (or, with ``exact``, to the true ones) of the first
    ``config.frames`` frames; writes ``out/estimate``, each file through ``staging``. With ``regions``, also a
    (κ_s, κ_b) per angular sector of the garment (:func:`physavatar.fit.regions.estimate_regions`, gradients by the
    rollout's adjoint), from the global estimate, in ``estimate.json``'s ``regions``.

    Both of Algorithm 1 (forward differences + Adam) and the analytic Levenberg–Marquardt run from
    ``config.start``. On a user's ``capture`` (no truth) the report gives the recovered parameters and the fit's
    residual; on the synthetic experiment also their errors against the truth.

    With ``fit="images"`` no tracked mesh is read: the parameters are fitted to the capture's images and masks
    through the rollout (:func:`physavatar.fit.images.estimate_images`), from ``config.start``, and with
    ``regions`` once more per sector from the global result.
    """
    if fit not in FITS:
        raise ValueError(f"fit must be one of {', '.join(FITS)}, got {fit!r}")
    if fit == "images":
        if exact:
            raise ValueError("--exact fits the true meshes; the image fit reads no mesh: drop --exact or --fit images")
        return _estimate_from_images(config, out, progress, staging, capture, regions)
    folder = Path(out) / "estimate"
    inputs = stage_inputs(out, capture, views=False)
    given = inputs.given
    if exact and inputs.truth is None:
        raise ValueError("--exact fits the true meshes, which only the synthetic experiment has; drop --exact")
    reference = torch.as_tensor(inputs.truth["garment_frames"]) if exact else _tracked(out)["vertices"]
    _check_frames(reference.shape[0], given["body_frames"].shape[0], "the reference", "the body frames")
    frames = min(config.frames, reference.shape[0])
    problem = EstimationProblem(
        given["first_vertices"],
        given["faces"],
        reference[:frames],
        given["body_frames"][:frames],
        given["body_faces"],
        given["boundary_index"],
        given["boundary_targets"][:frames],
        given["fps"],
        config.fabric,
    )
    truth = None if inputs.truth is None else FabricParameters(**inputs.truth["parameters"])
    report = {
        "reference": "truth" if exact else "tracked",
        "frames": frames,
        "truth": None if truth is None else dataclasses.asdict(truth),
        "methods": {},
    }
    runs = {}
    for name, run in (
        (
            "analytic_levenberg_marquardt",
            lambda cb: estimate_analytic(problem, config.start, iterations=config.lm_iterations, progress=cb),
        ),
        (
            "finite_differences_adam",
            lambda cb: estimate_finite_differences(problem, config.start, iterations=config.fd_iterations, progress=cb),
        ),
    ):
        say(progress, "estimate", f"{name} from κ_s = {config.start.kappa_s:g}, κ_b = {config.start.kappa_b:g}")
        result = run(
            lambda i, rec, name=name: say(
                progress,
                "estimate",
                f"{name} {i}: κ_s {rec.parameters.kappa_s:.4f}, κ_b {rec.parameters.kappa_b:.4f}, loss {rec.loss:.3e}",
            )
        )
        runs[name] = result
        final = result.final
        report["methods"][name] = {
            "iterations": result.iterations,
            "simulations": result.simulations,
            "seconds": result.total_time or float(sum(result.wall_time)),
            "final": dataclasses.asdict(final),
            "loss": result.loss[-1],
            "ratio_errors": _ratio_errors(final, truth),
            "history": [dataclasses.asdict(p) for p in result.history],
            "loss_history": result.loss,
        }
    best = min(runs.values(), key=lambda r: r.loss[-1])
    report["recovered"] = dataclasses.asdict(best.final)
    if regions is not None:
        sectors = garment_regions(given["first_vertices"], given["faces"], regions)
        say(progress, "estimate", f"κ_s, κ_b in {regions} regions by the rollout's adjoint")
        fit = estimate_regions(
            problem,
            sectors,
            best.final,
            progress=lambda i, loss, s, b: say(progress, "estimate", f"regions {i}: loss {loss:.3e}"),
        )
        report["regions"] = fit.to_dict()
    report["recovered_by"] = best.method
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "estimate.json", report, staging)
    plot_estimation(runs, truth, folder / "estimate.png", staging)
    return folder


def _estimate_from_images(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None,
    staging: Staging,
    capture: Path | None,
    regions: int | None,
) -> Path:
    """:func:`estimate` with ``fit="images"``."""
    folder = Path(out) / "estimate"
    inputs = stage_inputs(out, capture)
    film, given = inputs.film, inputs.given
    _check_frames(film.images.shape[0], given["body_frames"].shape[0], "the capture", "the body frames")
    frames = min(config.frames, film.images.shape[0])
    film = dataclasses.replace(film, images=film.images[:frames], masks=film.masks[:frames])
    truth = None if inputs.truth is None else FabricParameters(**inputs.truth["parameters"])
    settings = ImageFitConfig(iterations=config.image_iterations, appearance=config.tracking)

    def fit_images(initial: FabricParameters, sectors: torch.Tensor | None, label: str):
        say(progress, "estimate", f"{label} from the images: {len(film.rig)} views, {frames} frames")
        return estimate_images(
            film, given["first_vertices"], given["faces"], given["body_frames"][:frames], given["body_faces"],
            given["boundary_index"], given["boundary_targets"][:frames], config.fabric, initial, settings,
            regions=sectors,
            progress=lambda i, loss, s, b: say(
                progress, "estimate", f"{label} {i}: κ_s {_values(s)}, κ_b {_values(b)}, loss {loss:.5f}"
            ),
        )  # fmt: skip

    result = fit_images(config.start, None, "images")
    final = result.parameters
    report = {
        "reference": "images",
        "frames": frames,
        "truth": None if truth is None else dataclasses.asdict(truth),
        "methods": {
            IMAGE_FIT: {
                **result.to_dict(),
                "iterations": result.evaluations,
                "simulations": result.evaluations,
                "final": dataclasses.asdict(final),
                "ratio_errors": _ratio_errors(final, truth),
                "history": [dataclasses.asdict(p) for p in result.history],
            }
        },
        "recovered": dataclasses.asdict(final),
        "recovered_by": IMAGE_FIT,
    }
    if regions is not None:
        sectors = garment_regions(given["first_vertices"], given["faces"], regions)
        report["regions"] = fit_images(final, sectors, f"{regions} regions").to_dict()
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "estimate.json", report, staging)
    plot_estimation({IMAGE_FIT: result}, truth, folder / "estimate.png", staging, loss="image loss (Eq. 1 + mask)")
    return folder


def _ratio_errors(found: FabricParameters, truth: FabricParameters | None) -> dict | None:
    """The relative errors of the identifiable ratios κ_s/ρ and κ_b/ρ against the truth (``None`` without one)."""
    if truth is None:
        return None
    return {
        "kappa_s_over_rho": found.ratios[0] / truth.ratios[0] - 1.0,
        "kappa_b_over_rho": found.ratios[1] / truth.ratios[1] - 1.0,
    }


def _values(values: list[float]) -> str:
    return " ".join(f"{v:.4f}" for v in values[:4]) + (" …" if len(values) > 4 else "")


def appearance(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    capture: Path | None = None,
) -> Path:
    """Recover the garment's albedo and the light from the tracked meshes (§3.3); writes ``out/appearance``, each
    file through ``staging``. A capture that records no calibrated sun gets the paper's ambient light alone."""
    folder = Path(out) / "appearance"
    inputs = stage_inputs(out, capture)
    film, given = inputs.film, inputs.given
    tracked = _tracked(out)
    say(progress, "appearance", "tracing sky occlusion and sun visibility on the tracked meshes")
    result = estimate_appearance(
        tracked["vertices"],
        given["faces"],
        film,
        face_colors=tracked["colors"],
        body_frames=given["body_frames"],
        body_faces=given["body_faces"],
        sun_direction="capture" if film.lighting is not None else None,
        ao_samples=config.ao_samples,
        seed=config.seed + 1,
    )
    folder.mkdir(parents=True, exist_ok=True)
    write_arrays(
        folder / "appearance.npz",
        staging,
        albedo=result.albedo.numpy(),
        baked=result.initial_albedo.numpy(),
        observed=result.observed.numpy(),
    )
    truth_albedo = None if inputs.truth is None else torch.as_tensor(inputs.truth["albedo"])
    record = {
        "lighting": result.lighting.to_dict(),
        "albedo_error": None if truth_albedo is None else albedo_error(result.albedo, truth_albedo, result.observed),
        "baked_albedo_error": None
        if truth_albedo is None
        else albedo_error(result.initial_albedo, truth_albedo, result.observed),
        "loss_history": result.loss_history,
        "pixels": result.pixel_count,
    }
    write_json(folder / "appearance.json", record, staging)
    new_light = Lighting(ambient=(0.35, 0.35, 0.4), sun=(0.8, 0.7, 0.55), sun_direction=(-0.8, 0.6, 0.3))
    images = relight(
        tracked["vertices"][-1],
        given["faces"],
        result.albedo,
        film.rig,
        new_light,
        given["body_frames"][-1],
        given["body_faces"],
        BODY_COLOR,
        ao_samples=config.ao_samples,
    )
    write_strip(images[0], folder / "relit.png", staging)
    if truth_albedo is not None:
        say(
            progress,
            "appearance",
            f"albedo error {record['albedo_error']:.4f} (baked {record['baked_albedo_error']:.4f})",
        )
    return folder


def random_parameters(config: PipelineConfig, density: float) -> FabricParameters:
    """The "w/o physics" fabric: ``κ_s``, ``κ_b`` drawn log-uniformly from the paper's 0.1–8 with
    ``config.random_seed``, at ``density``."""
    generator = np.random.default_rng(config.random_seed)
    lo, hi = math.log(0.1), math.log(8.0)
    return FabricParameters(density, *np.exp(generator.uniform(lo, hi, size=2)).tolist())


def animate(
    config: PipelineConfig, out: Path, progress: Progress | None = None, staging: Staging = contextlib.nullcontext
) -> Path:
    """Simulate the garment under the unseen motion with each method's parameters; writes ``out/animate`` through
    ``staging``."""
    capture_dir, folder = Path(out) / "capture", Path(out) / "animate"
    estimate_path = Path(out) / "estimate" / "estimate.json"
    if not estimate_path.is_file():
        raise FileNotFoundError(f"{estimate_path} is missing; run the estimate stage first")
    recovered = FabricParameters(**json.loads(estimate_path.read_text())["recovered"])
    truth = FabricParameters(**load_truth(capture_dir)["parameters"])
    given = _inputs(capture_dir / "inputs.npz")
    body, garment, boundary = _scene(config)
    if not torch.equal(garment.faces, given["faces"]):
        raise ValueError("the capture's garment differs from this configuration's skirt; use the capture's config")
    problem, clip = _forward(config, body, garment, boundary, config.eval_motion, config.eval_frames)
    random = random_parameters(config, truth.density)
    sequences = {}
    for name, params in (("truth", truth), ("full", recovered), ("without_physics", random)):
        say(progress, "animate", f"{name}: κ_s {params.kappa_s:.3f}, κ_b {params.kappa_b:.3f}")
        sequences[name] = rollout(problem, params).frames
    sequences["lbs"] = lbs_garment(
        body, garment.vertices, clip.rotations[: config.eval_frames], clip.root_translation[: config.eval_frames]
    )
    folder.mkdir(parents=True, exist_ok=True)
    write_arrays(
        folder / "animation.npz",
        staging,
        **{k: v.numpy() for k, v in sequences.items()},
        body_frames=problem.body_frames.numpy(),
        faces=garment.faces.numpy(),
        body_faces=body.faces.numpy(),
        random_parameters=np.array([random.density, random.kappa_s, random.kappa_b]),
    )
    return folder


def evaluate(
    config: PipelineConfig, out: Path, progress: Progress | None = None, staging: Staging = contextlib.nullcontext
) -> Path:
    """Table 2 on the unseen motion: geometry and appearance of each method against the truth; writes
    ``out/evaluate``, each file through ``staging``."""
    capture_dir, folder = Path(out) / "capture", Path(out) / "evaluate"
    path = Path(out) / "animate" / "animation.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing; run the animate stage first")
    with np.load(path) as data:
        seq = {k: torch.from_numpy(data[k]) for k in data.files}
    look = np.load(Path(out) / "appearance" / "appearance.npz")
    albedo, baked = torch.from_numpy(look["albedo"]), torch.from_numpy(look["baked"])
    # Faces no camera saw have no baked colour: give them the estimate's, so only the seen faces differ.
    baked = torch.where(torch.isfinite(baked), baked, albedo).clamp(0.0, 1.0)
    true_albedo = torch.as_tensor(load_truth(capture_dir)["albedo"])
    film = load_capture(capture_dir)
    faces, body_frames, body_faces = seq["faces"], seq["body_frames"], seq["body_faces"]
    rows = {
        "lbs": ("LBS", albedo),
        "without_physics": ("w/o physics", albedo),
        "without_appearance": ("w/o appearance", baked),
        "full": ("PhysAvatar (full)", albedo),
    }
    frames_shown = sorted({0, seq["truth"].shape[0] // 2, seq["truth"].shape[0] - 1})

    def render(vertices, texture):
        return relight(
            vertices[frames_shown],
            faces,
            texture,
            film.rig,
            film.lighting,
            body_frames[frames_shown],
            body_faces,
            BODY_COLOR,
            ao_samples=config.ao_samples,
        )

    reference = render(seq["truth"], true_albedo)
    report = {
        "motion": config.eval_motion,
        "frames": int(seq["truth"].shape[0]),
        "smoke_size": config.smoke_size,
        "note": SMOKE_NOTE if config.smoke_size else None,
        "methods": {},
    }
    renders = {"truth": reference}
    for key, (label, texture) in rows.items():
        geometry = seq["full" if key == "without_appearance" else key]
        say(progress, "evaluate", f"{label}: geometry and renders")
        scores = geometry_scores(geometry, seq["truth"], faces)
        images = render(geometry, texture)
        renders[key] = images
        report["methods"][key] = {
            "label": label,
            **scores.summary(),
            "chamfer_per_frame": scores.chamfer.tolist(),
            "psnr": float(psnr(images, reference)),
            "ssim": float(ssim(images.flatten(0, 1), reference.flatten(0, 1))),
        }
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "report.json", report, staging)
    write_text(folder / "report.md", report_markdown(report, Path(out)), staging)
    plot_report(report, folder, staging)
    write_strip(
        torch.cat([renders[k][-1][:1] for k in ("truth", "lbs", "without_physics", "full")]),
        folder / "comparison.png",
        staging,
    )
    return folder


def run(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = stderr_progress,
    staging: Staging = contextlib.nullcontext,
) -> Path:
    """Every stage in order, each file written through ``staging``; returns the report's path.

    Raises:
        PipelineInterrupted: on Ctrl-C, naming the stage it stopped and those that finished.
    """
    out = Path(out)
    stages = (capture, track_stage, estimate, appearance, animate, evaluate)
    bound = [functools.partial(stage, config, out, progress, staging=staging) for stage in stages]
    run_stages(list(zip(STAGES, bound, strict=True)), progress)
    return out / "evaluate" / "report.md"


def run_stages(stages: list[tuple[str, Callable[[], object]]], progress: Progress | None) -> None:
    """Run ``(name, stage)`` pairs in order, saying when each starts and how long it took.

    Raises:
        PipelineInterrupted: on Ctrl-C, naming the stage it stopped and those that finished.
    """
    for index, (name, stage) in enumerate(stages):
        start = time.perf_counter()
        say(progress, name, f"stage {index + 1}/{len(stages)}")
        try:
            stage()
        except KeyboardInterrupt as stop:
            raise PipelineInterrupted(name, tuple(n for n, _ in stages[:index])) from stop
        say(progress, name, f"done in {time.perf_counter() - start:.1f} s")
