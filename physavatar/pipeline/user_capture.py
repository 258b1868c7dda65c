"""PhysAvatar on a user's own capture: prepare → track → estimate → appearance → animate → evaluate, no truth needed.

A capture folder (:func:`physavatar.capture.load_capture_folder`, layout in ``docs/capture.md``) holds calibrated
views, garment masks, a body mesh per frame and the garment at the first frame. Each stage reads the folder and
the earlier stages' outputs under the experiment folder ``out`` and writes its own; ``track``, ``estimate`` and
``appearance`` are :mod:`~physavatar.pipeline.stages`' own stages given the capture, the others are here:

``prepare/``
    ``inputs.npz`` (what the fit is given, in the project's y-up axes), ``garment_resolved.obj`` (the garment
    template with its intersections with the frame-0 body resolved, in the capture's axes), ``boundary.txt`` (the
    Dirichlet vertices, given or chosen automatically, for the user to check) and ``prepare.json`` (what was
    moved, the boundary, the cameras held out of the fit).
``animate/``
    ``animation.npz``: the garment over the capture's body sequence for each method compared (full: the recovered
    parameters; w/o physics: random parameters; attached: every vertex carried by its nearest body triangle, the
    LBS baseline of a body with no skeleton) and ``garment_0000.obj``...: the full method's frames in the
    capture's axes.
``evaluate/``
    ``report.json``, ``report.md`` and ``comparison.png``: each method rendered with the recovered albedo and light
    into the cameras held out of the fit, against what those cameras saw (PSNR and SSIM on the garment, mask IoU),
    the tracking's residuals, and the frames at which a garment vertex lies inside the body.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch

from kernels import backend
from kernels.image_metrics import ssim
from kernels.raycast import MeshBVH
from physavatar.body import attach_to_surface
from physavatar.capture import Lighting, check_capture, load_capture_folder, render_capture, to_capture_axes
from physavatar.drive import GAP_OVER_CONTACT_DISTANCE, drive_captured_garment
from physavatar.fit.estimation import EstimationProblem, FabricParameters, rollout
from physavatar.pipeline.report import SMOKE_NOTE, write_strip
from physavatar.pipeline.stages import (
    BODY_COLOR,
    OUTPUTS,
    PipelineConfig,
    Progress,
    appearance,
    camera_views,
    estimate,
    random_parameters,
    run_stages,
    say,
    stage_inputs,
    track_stage,
)
from physavatar.result_files import Staging, write_arrays, write_json, write_obj, write_text

__all__ = [
    "CAPTURE_OUTPUTS",
    "CAPTURE_STAGES",
    "animate_capture",
    "evaluate_capture",
    "prepare",
    "run_capture",
]

CAPTURE_STAGES = ("prepare", "track", "estimate", "appearance", "animate", "evaluate")
CAPTURE_OUTPUTS: dict[str, tuple[str, ...]] = {
    "prepare": (
        "prepare/",
        "prepare/inputs.npz",
        "prepare/garment_resolved.obj",
        "prepare/boundary.txt",
        "prepare/prepare.json",
    ),
    **{stage: OUTPUTS[stage] for stage in ("track", "estimate", "appearance")},  # the synthetic experiment's stages
    "animate": ("animate/", "animate/animation.npz"),
    "evaluate": ("evaluate/", "evaluate/report.json", "evaluate/report.md", "evaluate/comparison.png"),
}
"""What each stage writes under the experiment folder on a user's capture (``animate/`` also holds one OBJ per
frame)."""


def prepare(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    *,
    capture: Path,
    held_out_cameras: tuple[int, ...] | None = None,
) -> Path:
    """Make a user's capture simulable and write what the fit is given; writes ``out/prepare``.

    Resolves the garment template's intersections with the frame-0 body and with itself
    (:func:`physavatar.intersections.resolve_intersections`, a clearance of :data:`GAP_OVER_CONTACT_DISTANCE` ``d̂``),
    takes the capture's boundary vertices or chooses them (:func:`physavatar.garment.select_boundary`), and carries
    them with their nearest body triangles through the body sequence (:meth:`BodyDriver.from_body_frames`).

    Args:
        config: the fit's settings (its fabric's ``contact_distance`` sets the clearance).
        out: the experiment folder.
        capture: the capture folder.
        progress, staging: as the other stages.
        held_out_cameras: cameras kept out of the fit for the evaluation; ``None``: the last camera when the capture
            has three or more, else none (the evaluation then scores the fit's own views, and says so).

    Raises:
        ValueError: a capture that :func:`physavatar.capture.check_capture` finds problems in (each named with its
            fix), a held-out camera outside the capture, or one that would leave no camera to fit.
    """
    folder_out = Path(out) / "prepare"
    say(progress, "prepare", f"checking {capture}")
    checked = check_capture(capture)
    if not checked.ok:
        raise ValueError(f"the capture {capture} cannot be used as it is:\n{checked.format()}")
    for warning in checked.warnings:
        say(progress, "prepare", f"warning: {warning.where}: {warning.what}")
    folder = load_capture_folder(capture, progress=lambda done, n: say(progress, "prepare", f"frame {done}/{n}"))
    cameras = folder.film.camera_count
    if held_out_cameras is None:
        held_out_cameras = (cameras - 1,) if cameras >= 3 else ()
    held_out = tuple(sorted({int(c) for c in held_out_cameras}))
    if any(not 0 <= c < cameras for c in held_out) or len(held_out) >= cameras:
        raise ValueError(
            f"held-out cameras {list(held_out)} must be among the capture's cameras 0..{cameras - 1} and leave at "
            "least one to fit; hold out fewer cameras"
        )
    gap = GAP_OVER_CONTACT_DISTANCE * config.fabric.contact_distance
    captured = drive_captured_garment(
        folder.body_frames,
        folder.body_faces,
        folder.garment_vertices,
        folder.garment_faces,
        folder.boundary,
        folder.fps,
        gap,
        folder.path.name,
    )
    report, driver, chosen = captured.intersections, captured.driver, captured.boundary_chosen
    resolved, boundary = captured.garment.vertices, driver.boundary_index
    say(progress, "prepare", report.summary())
    say(progress, "prepare", f"{boundary.numel()} boundary vertices ({chosen})")
    folder_out.mkdir(parents=True, exist_ok=True)
    write_arrays(
        folder_out / "inputs.npz",
        staging,
        first_vertices=resolved.numpy(),
        faces=folder.garment_faces.numpy(),
        body_frames=driver.body_frames.numpy(),
        body_faces=folder.body_faces.numpy(),
        boundary_index=driver.boundary_index.numpy(),
        boundary_targets=driver.boundary_targets.numpy(),
        fps=folder.film.fps,
    )
    write_obj(
        folder_out / "garment_resolved.obj",
        folder.to_capture_axes(resolved),
        folder.garment_faces,
        staging,
        "the garment template, its intersections with the body resolved",
    )
    write_text(
        folder_out / "boundary.txt",
        f"# {boundary.numel()} boundary vertices ({chosen}), 0-based indices into garment_resolved.obj\n"
        + "\n".join(str(int(i)) for i in boundary)
        + "\n",
        staging,
    )
    record = {
        "capture": str(folder.path),
        "frames": folder.film.frame_count,
        "cameras": cameras,
        "held_out_cameras": list(held_out),
        "fps": folder.film.fps,
        "up": folder.up,
        "garment_vertices": int(resolved.shape[0]),
        "body_vertices": int(folder.body_frames.shape[1]),
        "boundary": {"chosen": chosen, "count": int(boundary.numel())},
        "clearance_m": gap,
        "intersections": dataclasses.asdict(report),
    }
    write_json(folder_out / "prepare.json", record, staging)
    return folder_out


def _recovered(out: Path) -> FabricParameters:
    path = Path(out) / "estimate" / "estimate.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing; run the estimate stage first (python -m apps.avatar estimate)")
    return FabricParameters(**json.loads(path.read_text())["recovered"])


def animate_capture(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    *,
    capture: Path,
) -> Path:
    """Simulate the garment over the capture's whole body sequence with each method's parameters; writes
    ``out/animate``. The frames past the fit's ``config.frames`` are motion the estimate never saw."""
    folder = Path(out) / "animate"
    inputs = stage_inputs(out, capture, views=False)
    given = inputs.given
    recovered = _recovered(out)
    frames = given["body_frames"].shape[0]
    problem = EstimationProblem(
        given["first_vertices"],
        given["faces"],
        given["first_vertices"].expand(frames, -1, -1),
        given["body_frames"],
        given["body_faces"],
        given["boundary_index"],
        given["boundary_targets"],
        given["fps"],
        config.fabric,
    )
    random = random_parameters(config, recovered.density)
    sequences = {}
    for name, params in (("full", recovered), ("without_physics", random)):
        say(progress, "animate", f"{name}: κ_s {params.kappa_s:.3f}, κ_b {params.kappa_b:.3f} over {frames} frames")
        sequences[name] = rollout(problem, params).frames
    attachment = attach_to_surface(given["first_vertices"], given["body_frames"][0], given["body_faces"])
    sequences["attached"] = attachment.positions(given["body_frames"], given["body_faces"])
    folder.mkdir(parents=True, exist_ok=True)
    for t, vertices in enumerate(sequences["full"]):
        write_obj(
            folder / f"garment_{t:04d}.obj",
            to_capture_axes(vertices, inputs.up),
            given["faces"],
            staging,
            f"frame {t}, the recovered parameters",
        )
    write_arrays(
        folder / "animation.npz",
        staging,
        **{k: v.numpy() for k, v in sequences.items()},
        body_frames=given["body_frames"].numpy(),
        faces=given["faces"].numpy(),
        body_faces=given["body_faces"].numpy(),
        random_parameters=np.array([random.density, random.kappa_s, random.kappa_b]),
    )
    return folder


METHODS = {"attached": "attached (LBS)", "without_physics": "w/o physics", "full": "PhysAvatar (full)"}
"""The methods the evaluation compares, by their key in ``animation.npz``."""


def evaluate_capture(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    *,
    capture: Path,
) -> Path:
    """Score each method where no truth is needed; writes ``out/evaluate``.

    Each method's garment is rendered with the recovered albedo under the recovered light into the cameras held
    out of the fit (or, with none held out, the fit's own), with the body shaded grey, and compared with what those
    cameras saw, on the garment only: PSNR over the pixels either mask covers, SSIM of the images with every other
    pixel set to the background, and the IoU of the rendered and captured garment masks.
    """
    folder = Path(out) / "evaluate"
    inputs = stage_inputs(out, capture)
    path = Path(out) / "animate" / "animation.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing; run the animate stage first (python -m apps.avatar animate)")
    with np.load(path) as data:
        sequences = {k: torch.from_numpy(data[k]) for k in data.files}
    look_path = Path(out) / "appearance"
    with np.load(look_path / "appearance.npz") as look:
        albedo = torch.from_numpy(look["albedo"]).clamp(0.0, 1.0)
    lighting = Lighting.from_dict(json.loads((look_path / "appearance.json").read_text())["lighting"])
    captured = inputs.folder.film
    cameras = list(inputs.held_out) or list(range(captured.camera_count))
    views = camera_views(captured, cameras)
    faces, body_frames, body_faces = sequences["faces"], sequences["body_frames"], sequences["body_faces"]
    background = views.background
    report = {
        "capture": str(inputs.folder.path),
        "frames": int(body_frames.shape[0]),
        "fit_frames": min(config.frames, int(body_frames.shape[0])),
        "cameras": cameras,
        "held_out": bool(inputs.held_out),
        "smoke_size": config.smoke_size,
        "note": SMOKE_NOTE if config.smoke_size else None,
        "tracking": _tracking_residuals(out),
        "methods": {},
    }
    strips = [views.images[-1, 0]]
    for key, label in METHODS.items():
        say(progress, "evaluate", f"{label}: rendering {len(cameras)} held-out view(s) × {body_frames.shape[0]} frames")
        render = render_capture(
            sequences[key],
            faces,
            body_frames,
            body_faces,
            albedo,
            BODY_COLOR,
            views.rig,
            lighting,
            views.fps,
            background,
            ao_samples=config.ao_samples,
            seed=config.seed,
        )
        scores = _image_scores(render.images, render.masks, views.images, views.masks, background)
        inside = _inside_body(sequences[key], body_frames, body_faces)
        report["methods"][key] = {
            "label": label,
            **scores,
            "frames_with_vertices_inside_body": [int(t) for t in torch.nonzero(inside.any(1)).flatten()],
            "most_vertices_inside_body": int(inside.sum(1).max()),
        }
        strips.append(render.images[-1, 0])
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "report.json", report, staging)
    write_text(folder / "report.md", _markdown(report), staging)
    write_strip(torch.stack(strips), folder / "comparison.png", staging)
    return folder


def _inside_body(frames: torch.Tensor, body_frames: torch.Tensor, body_faces: torch.Tensor) -> torch.Tensor:
    """``[T, V]`` bool: garment vertices ``frames [T, V, 3]`` inside the body of the same frame (its generalised
    winding number above ½, :meth:`kernels.raycast.MeshBVH.inside`: a body whose parts overlap counts once)."""
    device = backend.torch_device()
    faces = body_faces.to(device).long()
    return torch.stack(
        [
            MeshBVH(body.to(device), faces, winding_numbers=True).inside(x.to(device)).cpu()
            for x, body in zip(frames, body_frames, strict=True)
        ]
    )


def _tracking_residuals(out: Path) -> dict | None:
    path = Path(out) / "track" / "tracking.json"
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    losses = record["render_loss"]
    return {"render_loss": losses, "mean_render_loss": float(np.mean(losses[1:])) if len(losses) > 1 else None}


def _image_scores(images, masks, target_images, target_masks, background) -> dict:
    """PSNR (dB) over the pixels either garment mask covers, SSIM with every other pixel set to ``background``, and
    the masks' IoU, each over all frames and views of ``[T, C, H, W(, 3)]`` renders and captured views."""
    union = masks | target_masks
    pixels = int(union.sum())
    if pixels == 0:
        return {"psnr": None, "ssim": None, "mask_iou": None, "pixels": 0}
    error = ((images - target_images) ** 2).mean(-1)[union]
    mse = float(error.mean())
    psnr = 10.0 * math.log10(1.0 / max(mse, 1e-12))
    fill = torch.tensor(background, dtype=images.dtype)
    shown = torch.where(union[..., None], images, fill).flatten(0, 1)
    seen = torch.where(union[..., None], target_images, fill).flatten(0, 1)
    return {
        "psnr": psnr,
        "ssim": float(ssim(shown, seen)),
        "mask_iou": float((masks & target_masks).sum()) / pixels,
        "pixels": pixels,
    }


def _markdown(report: dict) -> str:
    where = "held out of the fit" if report["held_out"] else "of the fit (the capture has too few to hold one out)"
    lines = [
        f"# PhysAvatar on the capture {report['capture']}",
        "",
        *([f"**{SMOKE_NOTE}**", ""] if report.get("smoke_size") else []),
        f"{report['frames']} frames (the fit saw the first {report['fit_frames']}); renders against camera(s) "
        f"{report['cameras']}, {where}, on the garment only.",
        "",
        "| method | PSNR (dB) ↑ | SSIM ↑ | mask IoU ↑ | frames with a vertex inside the body ↓ |",
        "|---|---|---|---|---|",
    ]
    for entry in report["methods"].values():
        psnr = "—" if entry["psnr"] is None else f"{entry['psnr']:.2f}"
        ssim_text = "—" if entry["ssim"] is None else f"{entry['ssim']:.4f}"
        iou = "—" if entry["mask_iou"] is None else f"{entry['mask_iou']:.3f}"
        lines.append(
            f"| {entry['label']} | {psnr} | {ssim_text} | {iou} | {len(entry['frames_with_vertices_inside_body'])} |"
        )
    tracking = report.get("tracking")
    if tracking and tracking["mean_render_loss"] is not None:
        lines += [
            "",
            f"Tracking: mean render loss {tracking['mean_render_loss']:.4g} over frames 1–{report['frames'] - 1}.",
        ]
    lines += ["", "`comparison.png`: what the camera saw at the last frame, then attached, w/o physics, full."]
    return "\n".join(lines) + "\n"


def run_capture(
    config: PipelineConfig,
    out: Path,
    progress: Progress | None = None,
    staging: Staging = contextlib.nullcontext,
    *,
    capture: Path,
    held_out_cameras: tuple[int, ...] | None = None,
) -> Path:
    """Every stage of :data:`CAPTURE_STAGES` in order on a user's capture; returns the report's path.

    Raises:
        PipelineInterrupted: on Ctrl-C, naming the stage it stopped and those that finished.
    """
    out = Path(out)
    stages = (
        lambda: prepare(config, out, progress, staging, capture=capture, held_out_cameras=held_out_cameras),
        lambda: track_stage(config, out, progress, staging, capture=capture),
        lambda: estimate(config, out, progress, staging=staging, capture=capture),
        lambda: appearance(config, out, progress, staging, capture=capture),
        lambda: animate_capture(config, out, progress, staging, capture=capture),
        lambda: evaluate_capture(config, out, progress, staging, capture=capture),
    )
    run_stages(list(zip(CAPTURE_STAGES, stages, strict=True)), progress)
    return out / "evaluate" / "report.md"
