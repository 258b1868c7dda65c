"""Rendering the deformed NeRF (PIE-NeRF §4.6): the warping kernel alone and whole deformed frames.

* ``warp_rays``: quadratic warping (Eq. 19–21) of packed samples, each with its 3 nearest IPs, by the Taichi
  kernel against the torch reference (the same Newton iteration, vectorised).
* ``render_deformed``: frames per second of :class:`pienerf.render.DeformedRenderer` rendering a trained NeRF under
  a smooth random deformation (q with 2 cm Gaussian entries), at 64² (smoke), 200² on the CPU / 800² on CUDA
  (paper: lego-sized frames) and 400² / 1600² (large). The scene is the teapot's NeRF
  (:func:`pienerf.scenes.scene_nerf`, the default fit: 48 views of 64², 1000 steps, fitted the first time,
  then cached; at smoke size a short fit of 12 views of 32² and 100 steps, whose NeRF is fuzzier but renders the
  same teapot) with the teapot's 3 cm grid body and 24 kernels; at paper size
  on CUDA, when ``../shared/data/nerf_synthetic_lego`` exists beside the repository, the lego's NeRF
  (:func:`pienerf.nerf.fitting.dataset_nerf`, default fit) with a body Poisson-disk sampled (4 cm) from the
  solid the NeRF shows (:class:`pienerf.nerf.solid.NerfSceneDensity`) and 32 kernels, as the lego scenario,
  seen from 4.2 m. A trained NeRF matters: early ray termination only saves samples behind real opacity. Timed:
  the frame state (deformed IPs, forward-warped occupancy) and the rounds of march, nearest IPs, warp, NeRF queries
  and compositing. Recorded besides: ``samples_marched``, ``samples_queried`` and ``rounds`` of a frame, and
  ``samples_full_march``, what one full march of every ray emits (what a renderer without early termination
  warps). The reference renders without early termination, in torch: a full march per 4096 rays, every sample
  warped by
  :func:`kernels.reference.warp_rays.warp_to_rest_torch`, composited by
  :func:`kernels.reference.volume_render.composite_torch`.

Figures of both workloads on the CPU and on an H100, with their history: ``docs/benchmarks.md``.
"""

from __future__ import annotations

import dataclasses

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.reference.volume_render import composite_torch
from kernels.reference.warp_rays import warp_to_rest_torch
from kernels.spatial_hash import SpatialHash
from kernels.volume_render import march_rays
from kernels.warp_rays import warp_to_rest
from pienerf.nerf.cameras import orbit_cameras
from pienerf.nerf.fitting import NerfFit, dataset_nerf
from pienerf.nerf.solid import NerfSceneDensity
from pienerf.paths import SHARED_DATA
from pienerf.render.deformed import DeformedRenderer
from pienerf.scenes import scene_cameras, scene_density, scene_nerf
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.sampling import grid_sample, poisson_disk_sample

_LEGO = SHARED_DATA / "nerf_synthetic_lego"
_WARP_SAMPLES = {"smoke": 1 << 16, "paper": 1 << 20, "large": 1 << 23}
_RESOLUTION = {  # pixels per image side, by size and device
    "smoke": {"cpu": 64, "cuda": 64},
    "paper": {"cpu": 200, "cuda": 800},
    "large": {"cpu": 400, "cuda": 1600},
}


@workload("warp_rays", "quadratic ray warping (Eq. 19-21), 3 IPs per sample, Newton per IP (Taichi vs torch)")
def bench_warp_rays(device: str, size: str) -> Case:
    count = _WARP_SAMPLES[size]
    dev = backend.torch_device()
    generator = torch.Generator().manual_seed(0)
    spacing, side = 0.05, 8
    axis = torch.arange(side, dtype=torch.float32) * spacing
    rest = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    K = rest.shape[0]
    F = torch.eye(3) + 0.3 * (torch.rand(K, 3, 3, generator=generator) - 0.5)
    grad_F = 3.0 * (torch.rand(K, 3, 3, 3, generator=generator) - 0.5)
    displacement = 0.02 * torch.randn(K, 3, generator=generator)
    deformed = rest + displacement
    samples = deformed.amin(0) + (deformed.amax(0) - deformed.amin(0)) * torch.rand(count, 3, generator=generator)
    cutoff = torch.full((K,), 1.5 * spacing)
    tensors = [t.to(dev).contiguous() for t in (samples, deformed, displacement, F, grad_F, cutoff)]
    samples, deformed, displacement, F, grad_F, cutoff = tensors
    neighbours, distances = SpatialHash(deformed, spacing).knn(samples, 3, max_radius=4 * spacing)
    args = (samples, neighbours, distances, deformed, displacement, F, grad_F, cutoff)
    iterations = warp_to_rest(*args).iterations
    return Case(
        run=lambda: warp_to_rest(*args),
        reference=lambda: warp_to_rest_torch(*args),
        params={"samples": count, "ips": K, "neighbours": 3, "max_newton_iterations": 10},
        work=count / 1e6,
        unit="Msamples/s",
        reference_name="torch (batched linalg.solve)",
        extra={"mean_newton_iterations": float(iterations.float().mean())},
    )


def _deformed(field, grid, particles, kernel_count: int):
    """A renderer of ``field`` warped by a Q-GMLS body on ``particles``, and a smooth random q."""
    model = QGMLSModel.from_particles(particles, DiscretizationConfig(kernel_count=kernel_count))
    renderer = DeformedRenderer(field, grid, model)
    generator = torch.Generator().manual_seed(0)
    q = 0.02 * torch.randn(model.shape_count, 3, generator=generator, dtype=torch.float64)
    return renderer, q.to(model.device)


def _teapot_scene(size: str, resolution: int):
    """The teapot's NeRF (a short fit at smoke size), its 3 cm grid body with 24 kernels, and the first view."""
    fit, fit_name = NerfFit(), "default"
    if size == "smoke":
        fit = dataclasses.replace(fit, views=12, resolution=32, train=dataclasses.replace(fit.train, steps=100))
        fit_name = "12 views of 32², 100 steps"
    trained = scene_nerf("teapot", fit)
    renderer, q = _deformed(trained.field, trained.grid, grid_sample(scene_density("teapot"), 0.03), 24)
    rays = scene_cameras("teapot", views=1, resolution=resolution).rays(0)
    return renderer, q, rays, {"scene": "teapot", "nerf_fit": fit_name}


def _lego_scene(resolution: int):
    """The lego's NeRF (the default fit), a body Poisson-disk sampled from its solid (4 cm, 32 kernels, as the lego
    scenario), and a view from 4.2 m at 20° elevation."""
    trained = dataset_nerf(_LEGO, NerfFit())
    solid = NerfSceneDensity(trained.field, trained.grid, resolution=96)
    particles = poisson_disk_sample(solid, 0.04, seed=0)
    renderer, q = _deformed(trained.field, trained.grid, particles, 32)
    lo, hi = solid.bounds
    cameras = orbit_cameras((0.5 * (lo + hi)).tolist(), 4.2, [30.0], 20.0, resolution, resolution)
    return renderer, q, cameras.rays(0), {"scene": "lego", "nerf_fit": "default"}


def _render_reference(renderer, q, origins, directions):
    """The frame without early termination, in torch: every sample of a full march warped by the torch warp, queried
    and composited by ``composite_torch``."""
    frame = renderer.frame(q)
    c = renderer.field.config
    colors = []
    for a in range(0, origins.shape[0], renderer.chunk):
        b = min(a + renderer.chunk, origins.shape[0])
        samples = march_rays(
            origins[a:b],
            directions[a:b],
            0.0,
            1e10,
            frame.occupancy,
            frame.aabb.cpu(),
            renderer.min_step,
            max_samples=c.max_samples,
        )
        neighbours, distances = frame.ip_hash.knn(samples.positions, 3, max_radius=2.0 * float(renderer.cutoff.max()))
        rest, valid, _, _ = warp_to_rest_torch(
            samples.positions,
            neighbours,
            distances,
            frame.ip_deformed,
            frame.ip_displacement,
            frame.F,
            frame.grad_F,
            renderer.cutoff,
        )
        keep = valid & renderer.grid.is_occupied(rest)
        sigma = torch.zeros(rest.shape[0], device=rest.device)
        rgb = torch.zeros(rest.shape[0], 3, device=rest.device)
        if bool(keep.any()):
            sigma[keep], rgb[keep] = renderer.field(rest[keep], directions[a:b][samples.ray_indices][keep])
        colors.append(
            composite_torch(sigma, rgb, samples.deltas, samples.depths, samples.ray_offsets, c.transmittance_threshold)[
                0
            ]
        )
    return torch.cat(colors)


@workload("render_deformed", "deformed NeRF frames: warped occupancy, march, kNN, quadratic warp, NGP, composite")
def bench_render_deformed(device: str, size: str) -> Case:
    resolution = _RESOLUTION[size][device]
    if size == "paper" and device == "cuda" and _LEGO.is_dir():
        renderer, q, rays, scene = _lego_scene(resolution)
    else:
        renderer, q, rays, scene = _teapot_scene(size, resolution)
    origins, directions = (t.float().to(backend.torch_device()).contiguous() for t in rays)

    def run():
        with torch.no_grad():  # the camera stands still: its rays keep one key, so their encoding is reused
            return renderer.render(q, rays=(origins, directions), directions_key=("bench", resolution))

    def reference():
        with torch.no_grad():
            return _render_reference(renderer, q, origins, directions)

    run()
    stats = renderer.stats
    frame = renderer.frame(q)
    c = renderer.field.config
    full = march_rays(
        origins, directions, 0.0, 1e10, frame.occupancy, frame.aabb.cpu(), renderer.min_step, max_samples=c.max_samples
    )
    return Case(
        run=run,
        reference=reference,
        params={
            "resolution": resolution,
            "rays": resolution * resolution,
            "ips": renderer.model.ips.count,
            "field": "trained NGPField",
            **scene,
        },
        work=1.0,
        unit="frames/s",
        reference_name="torch warp + composite_torch, full march",
        extra={
            "samples_marched": stats.samples_marched,
            "samples_queried": stats.samples_queried,
            "rounds": stats.rounds,
            "samples_full_march": int(full.positions.shape[0]),
        },
    )
