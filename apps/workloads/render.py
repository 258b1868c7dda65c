"""Rendering the deformed NeRF (PIE-NeRF §4.6): the warping kernel alone and whole deformed frames.

* ``warp_rays``: quadratic warping (Eq. 19–21) of packed samples, each with its 3 nearest IPs, by the Taichi
  kernel against the torch reference (the same Newton iteration, vectorised).
* ``render_deformed``: frames per second of :class:`pienerf.render.DeformedRenderer` on the teapot (3 cm grid
  particles, 24 kernels) under a smooth random deformation, at 64² (smoke), 800² on CUDA / 200² on the CPU
  (paper: lego-sized frames) and 1600² / 400² (large). The field is an untrained
  :class:`pienerf.nerf.NGPField` (instant-NGP's configuration, so each query costs what a trained one does)
  marched through the teapot's occupancy grid, so the frame has the teapot's samples. Timed: the frame state
  (deformed IPs, forward-warped occupancy), marching, kNN, warping, NeRF queries and compositing. The
  reference swaps the warp for :func:`kernels.reference.warp_rays.warp_to_rest_torch` and the compositing for
  :func:`kernels.reference.volume_render.composite_torch`.

Measured on this project's shared 2-core CPU under load from other jobs (load average ~6): ``warp_rays``
paper (1M samples) 168 ms, 6.2 Msamples/s, 161x the reference; ``render_deformed`` paper (200², 1.03M samples)
8.9 s per frame against 55 s, most of it the NGP queries (hash grid + MLPs) of the samples; the frame state
(forward-warped occupancy, IP hash) costs ~0.3 s of it. CUDA not yet measured.
"""

from __future__ import annotations

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.reference.volume_render import composite_torch
from kernels.reference.warp_rays import warp_to_rest_torch
from kernels.spatial_hash import SpatialHash
from kernels.volume_render import march_rays
from kernels.warp_rays import warp_to_rest

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


def _teapot_renderer():
    from pienerf.model import DiscretizationConfig, QGMLSModel
    from pienerf.nerf import NGPField
    from pienerf.render import DeformedRenderer, MeshAlbedoField
    from pienerf.sampling import grid_sample
    from pienerf.scenes import scene_density

    particles = grid_sample(scene_density("teapot"), 0.03)
    model = QGMLSModel.from_particles(particles, DiscretizationConfig(kernel_count=24))
    geometry = MeshAlbedoField("teapot")
    torch.manual_seed(0)
    field = NGPField(aabb=geometry.aabb.cpu()).to(backend.torch_device())
    renderer = DeformedRenderer(field, geometry.occupancy_grid(128), model)
    generator = torch.Generator().manual_seed(0)
    q = 0.02 * torch.randn(model.shape_count, 3, generator=generator, dtype=torch.float64)
    return renderer, q.to(model.device)


def _render_reference(renderer, q, origins, directions):
    """The renderer's frame with the torch warp and torch compositing."""
    frame = renderer.frame(q)
    c = renderer.field.config
    colors = []
    for a in range(0, origins.shape[0], renderer.chunk):
        b = min(a + renderer.chunk, origins.shape[0])
        samples = march_rays(origins[a:b], directions[a:b], 0.0, 1e10, frame.occupancy, frame.aabb.cpu(),
                             renderer.min_step, max_samples=c.max_samples)
        neighbours, distances = frame.ip_hash.knn(samples.positions, 3, max_radius=2.0 * float(renderer.cutoff.max()))
        rest, valid, _, _ = warp_to_rest_torch(
            samples.positions, neighbours, distances, frame.ip_deformed, frame.ip_displacement, frame.F,
            frame.grad_F, renderer.cutoff,
        )
        keep = valid & renderer.grid.is_occupied(rest)
        sigma = torch.zeros(rest.shape[0], device=rest.device)
        rgb = torch.zeros(rest.shape[0], 3, device=rest.device)
        if bool(keep.any()):
            sigma[keep], rgb[keep] = renderer.field(rest[keep], directions[a:b][samples.ray_indices][keep])
        colors.append(composite_torch(sigma, rgb, samples.deltas, samples.depths, samples.ray_offsets,
                                      c.transmittance_threshold)[0])
    return torch.cat(colors)


@workload("render_deformed", "deformed NeRF frames: warped occupancy, march, kNN, quadratic warp, NGP, composite")
def bench_render_deformed(device: str, size: str) -> Case:
    from pienerf.scenes import scene_cameras

    resolution = _RESOLUTION[size][device]
    renderer, q = _teapot_renderer()
    cameras = scene_cameras("teapot", views=1, resolution=resolution)
    origins, directions = (t.to(backend.torch_device()).contiguous() for t in cameras.rays(0))

    def run():
        with torch.no_grad():
            return renderer.render(q, rays=(origins, directions))

    def reference():
        with torch.no_grad():
            return _render_reference(renderer, q, origins, directions)

    frame = renderer.frame(q)
    samples = march_rays(origins, directions, 0.0, 1e10, frame.occupancy, frame.aabb.cpu(), renderer.min_step)
    return Case(
        run=run,
        reference=reference,
        params={"resolution": resolution, "rays": resolution * resolution, "ips": renderer.model.ips.count,
                "field": "untrained NGPField", "scene": "teapot"},
        work=1.0,
        unit="frames/s",
        reference_name="torch warp + composite_torch",
        extra={"samples_per_frame": int(samples.positions.shape[0])},
    )
