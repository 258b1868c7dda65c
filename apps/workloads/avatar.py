"""PhysAvatar's inverse pipeline (§3.1–3.2): Gaussian splatting, one tracking frame, physics estimation.

``splat_fwd_bwd``: forward and backward rasterization of the mesh-aligned Gaussians of the dressed mannequin
(one per face of the skirt and the body) into 8 views at 512×512 (smoke: the skirt's alone, 2 views at 64×64); the
reference is the dense torch rasterizer of :mod:`kernels.reference.gaussian_splat`, timed only at smoke size (it holds a
``views × pixels × Gaussians`` tensor).

``track_frame``: one frame of tracking as the pipeline tracks the skirt (:func:`physavatar.fit.tracking.track`'s
per-frame optimisation with :data:`physavatar.pipeline.COARSE_MESH_TRACKING`: 16 Gaussians per face, the default 100
Adam iterations of vertices and colours against 8 views at 256×256; smoke: 4 views at 64×64 and 10 iterations).

``estimate``: the analytic Levenberg–Marquardt fit of (κ_s, κ_b) to 24 exact frames of the skirt on the walking
mannequin (smoke: 6 frames of a coarser skirt), from κ_s = 2, κ_b = 0.5; ``extra`` holds the time at which both
identifiable ratios came within 5 % of the truth and the final errors.

``estimate_images``: the same fit from the images instead of meshes (:func:`physavatar.fit.images.estimate_images`):
the skirt simulated in the truth's fabric on the walk and filmed as the pipeline films it (24 frames, 8 views at
256×256; smoke: 6 frames of the coarser skirt, 4 views at 64×64), then the first frame's appearance fit and
L-BFGS through the rollout's adjoint from κ_s = 2, κ_b = 0.5, no tracked mesh. ``extra`` holds the final ratio
errors, the evaluations, the rejected line-search trials and the appearance fit's share of the time.
"""

from __future__ import annotations

import dataclasses

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.gaussian_splat import rasterize_gaussians
from kernels.reference.gaussian_splat import rasterize_gaussians_torch
from physavatar.body import Body, walk
from physavatar.capture import CameraRig, Lighting, garment_albedo, render_capture
from physavatar.drive import BodyDriver
from physavatar.fit.estimation import SYNTHETIC_FABRIC, EstimationProblem, FabricParameters, estimate_analytic, rollout
from physavatar.fit.gaussians import GaussianAppearance, face_frames, project_gaussians
from physavatar.fit.images import ImageFitConfig, estimate_images
from physavatar.fit.tracking import track
from physavatar.garment import procedural_skirt, select_boundary
from physavatar.pipeline import COARSE_MESH_TRACKING
from physavatar.simulate import simulate

_VIEWS = {"smoke": (2, 64), "paper": (8, 512), "large": (16, 512)}


def _dressed(rings: int = 10, segments: int = 28):
    body = Body.mannequin(spacing=0.03)
    skirt = procedural_skirt(body, rings=rings, segments=segments)
    return body, skirt


def _film(skirt, result, views: int, pixels: int, ao_samples: int, phase_deg: float = 0.0):
    """The simulated ``result`` filmed as the pipeline films the skirt: a ring of ``views`` cameras at ``pixels``²
    framed on the skirt, its checked albedo on the mannequin's colour, under the default light, at 25 fps."""
    rig = CameraRig.ring(views, 2.2, 0.25, (0.0, 0.86, 0.0), pixels, pixels, fov_deg=24.0, phase_deg=phase_deg)
    albedo = garment_albedo(skirt.vertices, skirt.faces, pattern="checks", bands=6)
    return render_capture(
        result.garment_frames, result.garment_faces, result.body_frames, result.body_faces, albedo,
        (0.78, 0.74, 0.68), rig, Lighting(), 25.0, ao_samples=ao_samples,
    )  # fmt: skip


@workload("splat_fwd_bwd", "mesh-aligned Gaussians of the dressed mannequin: rasterize forward + backward")
def bench_splat(device: str, size: str) -> Case:
    views, pixels = _VIEWS[size]
    body, skirt = _dressed()
    dev = backend.torch_device()
    if size == "smoke":  # the skirt alone, so that the dense reference fits in memory and time
        vertices, faces = skirt.vertices.to(dev), skirt.faces.to(dev)
    else:
        vertices = torch.cat([skirt.vertices, body.vertices]).to(dev)
        faces = torch.cat([skirt.faces, body.faces + skirt.vertices.shape[0]]).to(dev)
    appearance = GaussianAppearance.initial(vertices, faces)
    rig = CameraRig.ring(views, 2.2, 0.25, (0.0, 0.9, 0.0), pixels, pixels, fov_deg=45.0)
    centre, rotation = face_frames(vertices, faces, appearance.edge)
    scales = torch.cat([appearance.log_scales.exp(), torch.full_like(appearance.log_scales[:, :1], 5e-4)], 1)
    means2d, conics, depths, radii = project_gaussians(
        centre,
        rotation,
        scales.to(centre),
        rig.world_to_camera().to(dev),
        rig.intrinsics,
        pixels,
        pixels,
    )
    n = faces.shape[0]
    inputs = [
        means2d.float().contiguous().requires_grad_(True),
        conics.float().contiguous().requires_grad_(True),
        torch.rand(views, n, 3, device=dev).requires_grad_(True),
        torch.full((views, n), 0.9, device=dev).requires_grad_(True),
    ]
    depths, radii = depths.float().contiguous(), radii.contiguous()
    weight = torch.rand(views, pixels, pixels, 3, device=dev)

    def run(rasterize=rasterize_gaussians):
        for t in inputs:
            t.grad = None
        image, alpha = rasterize(*inputs, depths, radii, pixels, pixels)
        (image * weight).sum().add(alpha.sum()).backward()
        return inputs[0].grad

    return Case(
        run=run,
        reference=(lambda: run(rasterize_gaussians_torch)) if size == "smoke" else None,
        params={"views": views, "pixels": f"{pixels}x{pixels}", "gaussians": n},
        work=views * pixels * pixels / 1e6,
        unit="Mpixels/s",
        reference_name="dense torch",
    )


@workload("track_frame", "one tracking frame: Adam on the skirt's vertices and colours against every view")
def bench_track_frame(device: str, size: str) -> Case:
    views, pixels = (4, 64) if size == "smoke" else (8, 256)
    iterations = 10 if size == "smoke" else COARSE_MESH_TRACKING.iterations
    body, skirt = _dressed()
    clip = walk(body.skeleton, fps=25.0)
    result = simulate(skirt, body, clip, config=SYNTHETIC_FABRIC, frames=2, progress=False)
    film = _film(skirt, result, views, pixels, ao_samples=4)
    config = dataclasses.replace(COARSE_MESH_TRACKING, first_iterations=1, iterations=iterations)
    # Frames 0 and 1; the first frame's appearance pass is one iteration, so a repetition is one tracked frame.
    film = dataclasses.replace(film, images=film.images[:2], masks=film.masks[:2])

    def run():
        return track(
            film, result.garment_frames[0], skirt.faces, result.body_frames[:2], body.faces, config, progress=False
        ).vertices

    return Case(
        run=run,
        reference=None,
        params={
            "views": views,
            "pixels": f"{pixels}x{pixels}",
            "iterations": iterations,
            "gaussians": int(skirt.faces.shape[0] * 4**config.face_subdivisions + body.faces.shape[0]),
        },
        work=1.0,
        unit="frames/s",
    )


@workload("estimate", "Levenberg-Marquardt fit of (kappa_s, kappa_b) to exact frames with analytic sensitivities")
def bench_estimate(device: str, size: str) -> Case:
    frames = 6 if size == "smoke" else 24
    body, skirt = _dressed(*((5, 14) if size == "smoke" else (10, 28)))
    boundary = select_boundary(skirt, body, mode="waist")
    driver = BodyDriver.from_motion(body, walk(body.skeleton, fps=25.0), skirt.vertices, boundary, frames - 1)
    truth = FabricParameters.from_config(SYNTHETIC_FABRIC)
    base = EstimationProblem(
        skirt.vertices,
        skirt.faces,
        skirt.vertices.expand(frames, -1, -1),
        driver.body_frames,
        body.faces,
        driver.boundary_index,
        driver.boundary_targets,
        driver.fps,
        SYNTHETIC_FABRIC,
    )
    reference = rollout(base, truth).frames
    problem = dataclasses.replace(base, reference=reference)
    start = FabricParameters(truth.density, 2.0, 0.5)
    extra: dict = {}

    def run():
        result = estimate_analytic(problem, start, progress=False)
        elapsed, reached = 0.0, None
        for record, seconds in zip(result.history[1:], result.wall_time, strict=True):
            elapsed += seconds
            errors = [abs(a / b - 1.0) for a, b in zip(record.ratios, truth.ratios, strict=True)]
            if reached is None and max(errors) < 0.05:
                reached = elapsed
        extra.update(
            iterations=result.iterations,
            simulations=result.simulations,
            seconds_to_5_percent=reached,
            final_ratio_errors=[a / b - 1.0 for a, b in zip(result.ratios, truth.ratios, strict=True)],
        )
        return result

    return Case(
        run=run,
        reference=None,
        params={"frames": frames, "vertices": int(skirt.vertices.shape[0]), "start": [2.0, 0.5], "truth": [1.0, 1.0]},
        work=1.0,
        unit="fits/s",
        extra=extra,
    )


@workload("estimate_images", "fit of (kappa_s, kappa_b) to the images through the rollout's adjoint, no tracking")
def bench_estimate_images(device: str, size: str) -> Case:
    smoke = size == "smoke"
    frames, views, pixels = (6, 4, 64) if smoke else (24, 8, 256)
    body, skirt = _dressed(*((5, 14) if smoke else (10, 28)))
    clip = walk(body.skeleton, fps=25.0)
    boundary = select_boundary(skirt, body, mode="waist")
    result = simulate(skirt, body, clip, config=SYNTHETIC_FABRIC, frames=frames - 1, boundary=boundary, progress=False)
    film = _film(skirt, result, views, pixels, ao_samples=4 if smoke else 16, phase_deg=20.0)
    truth = FabricParameters.from_config(SYNTHETIC_FABRIC)
    start = FabricParameters(truth.density, 2.0, 0.5)
    tracking = dataclasses.replace(COARSE_MESH_TRACKING, first_iterations=30) if smoke else COARSE_MESH_TRACKING
    config = ImageFitConfig(iterations=2 if smoke else 15, appearance=tracking)
    index = result.boundary_index
    extra: dict = {}

    def run():
        fit = estimate_images(
            film, result.garment_frames[0], skirt.faces, result.body_frames, body.faces, index,
            result.garment_frames[:, index], SYNTHETIC_FABRIC, start, config,
        )  # fmt: skip
        extra.update(
            final_ratio_errors=[a / b - 1.0 for a, b in zip(fit.parameters.ratios, truth.ratios, strict=True)],
            evaluations=fit.evaluations,
            rejected=len(fit.rejected),
            appearance_seconds=fit.appearance_seconds,
        )
        return fit

    return Case(
        run=run,
        reference=None,
        params={"frames": frames, "views": views, "pixels": f"{pixels}x{pixels}", "start": [2.0, 0.5],
                "truth": [1.0, 1.0]},  # fmt: skip
        work=1.0,
        unit="fits/s",
        extra=extra,
    )
