"""NGP NeRF (PIE-NeRF §3.1): volume-rendering compositing and whole training steps.

* ``volume_render``: forward and backward compositing of packed samples (:mod:`kernels.volume_render`)
  against the torch reference (segmented ``cumsum`` + ``index_add_``, autograd). Compulsory DRAM
  traffic per sample: the forward reads σ, δ, t, c (24 B) and the backward reads them again and writes
  ∂σ, ∂c (24 + 16 B); per ray a few dozen bytes more.
* ``nerf_train``: training iterations per second of :class:`pienerf.train.Trainer`. Smoke size trains a
  tiny NeRF on a synthetic ball rendered in memory; paper size trains instant-NGP's configuration on the
  NeRF-synthetic lego at 800×800 (``../shared/data``) and, before timing, measures the wall time until
  the held-out views reach 30 dB PSNR (``seconds_to_psnr30`` in the record, or the PSNR reached within
  the budget).
"""

from __future__ import annotations

import math
import time

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.hashgrid import HashGridConfig
from kernels.reference.volume_render import composite_torch
from kernels.volume_render import composite
from pienerf.data import Cameras, NerfDataset, load_nerf_dataset
from pienerf.nerf import NGPConfig, NGPField
from pienerf.paths import SHARED_DATA
from pienerf.train import TrainConfig, Trainer

# rays, mean samples per ray
_RENDER_SIZES = {"smoke": (4096, 64), "paper": (1 << 14, 128), "large": (1 << 18, 128)}
_LEGO = SHARED_DATA / "nerf_synthetic_lego"
_PSNR_TARGET = 30.0
_PSNR_BUDGET_S = 480.0


def _packed_samples(rays: int, mean_samples: int):
    generator = torch.Generator().manual_seed(0)
    counts = torch.randint(0, 2 * mean_samples + 1, (rays,), generator=generator)
    offsets = torch.zeros(rays + 1, dtype=torch.int32)
    offsets[1:] = torch.cumsum(counts, 0)
    samples = int(offsets[-1])
    deltas = torch.full((samples,), 0.01)
    depths = torch.rand(samples, generator=generator) * 4.0
    sigmas = torch.rand(samples, generator=generator) * 20.0
    colors = torch.rand(samples, 3, generator=generator)
    device = backend.torch_device()
    return tuple(t.to(device) for t in (sigmas, colors, deltas, depths, offsets))


@workload("volume_render", "NeRF compositing of packed samples, forward + backward (Taichi vs torch autograd)")
def bench_volume_render(device: str, size: str) -> Case:
    rays, mean_samples = _RENDER_SIZES[size]
    sigmas, colors, deltas, depths, offsets = _packed_samples(rays, mean_samples)
    samples = sigmas.shape[0]
    weights = torch.rand(rays, 3, device=sigmas.device)

    def run(render):
        s, c = sigmas.detach().requires_grad_(), colors.detach().requires_grad_()
        color = render(s, c)
        return torch.autograd.grad((color * weights).sum(), (s, c))

    def kernel(s, c):
        return composite(s, c, deltas, depths, offsets)["color"]

    def reference(s, c):
        return composite_torch(s, c, deltas, depths, offsets)[0]

    return Case(
        run=lambda: run(kernel),
        reference=lambda: run(reference),
        params={"rays": rays, "samples": samples, "mean_samples_per_ray": mean_samples},
        work=samples / 1e6,
        unit="Msamples/s",
        bytes_moved=samples * (24 + 24 + 16) + rays * 64,
        reference_name="torch autograd (cumsum + index_add_)",
    )


def _ball_dataset(views: int, size: int):
    """A ball with a smooth colour pattern, seen from ``views`` cameras; RGBA rendered analytically."""
    fov, radius = 0.8, 0.6
    focal = 0.5 * size / math.tan(0.5 * fov)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    c2w = torch.zeros(views, 4, 4)
    for k in range(views):
        z = 0.9 - 1.5 * (k + 0.5) / views
        ring = math.sqrt(1 - z * z)
        eye = 3.0 * torch.tensor([ring * math.cos(golden * k), ring * math.sin(golden * k), z])
        forward = -eye / eye.norm()
        right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0]))
        right = right / right.norm()
        up = torch.linalg.cross(right, forward)
        c2w[k, :3, 0], c2w[k, :3, 1], c2w[k, :3, 2], c2w[k, :3, 3], c2w[k, 3, 3] = right, up, -forward, eye, 1.0
    cameras = Cameras(c2w, *(torch.full((views,), v) for v in (focal, focal, size / 2, size / 2)), size, size)
    origins, directions = cameras.rays()
    b = (directions * origins).sum(-1)
    discriminant = b * b - ((origins * origins).sum(-1) - radius**2)
    hit = discriminant > 0
    n = (origins + (-b - discriminant.clamp_min(0).sqrt())[:, None] * directions) / radius
    rgb = torch.stack([0.5 + 0.5 * n[:, 0], 0.5 + 0.4 * torch.sin(4 * n[:, 2]), 0.5 + 0.5 * n[:, 2]], -1)
    rgb = torch.where(hit[:, None], rgb, 0.0).view(views, size, size, 3)
    alphas = hit.float().view(views, size, size)
    return NerfDataset(rgb, alphas, cameras, [str(k) for k in range(views)], "train", (0.0, 0.0, 0.0))


@workload("nerf_train", "NGP NeRF training iterations (smoke: synthetic ball; paper: lego 800x800, time to 30 dB)")
def bench_nerf_train(device: str, size: str) -> Case:
    torch.manual_seed(0)
    extra: dict = {}
    if size == "smoke":
        config = NGPConfig(
            hashgrid=HashGridConfig(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128),
            density_hidden=32, color_hidden=32, color_layers=1, grid_resolution=32, samples_per_diagonal=128,
        )
        field = NGPField(config, torch.tensor([[-1.0] * 3, [1.0] * 3]))
        trainer = Trainer(field, _ball_dataset(8, 32), TrainConfig(batch_rays=1024, grid_warmup_steps=8))
        trainer.train(16, progress=False)
        iterations = 4
    else:
        if not _LEGO.is_dir():
            raise FileNotFoundError(f"nerf_train at size {size!r} needs the lego scene at {_LEGO}")
        train, _ = load_nerf_dataset(_LEGO, "train", background=(0.0, 0.0, 0.0)).held_out(8)
        held_out = load_nerf_dataset(_LEGO, "test", background=(1.0, 1.0, 1.0)).select([0, 4, 8])
        field = NGPField(NGPConfig(), torch.tensor([[-1.5] * 3, [1.5] * 3]))
        batch = 1 << 14 if size == "paper" else 1 << 16
        trainer = Trainer(field, train, TrainConfig(steps=20_000, batch_rays=batch))
        start, reached = time.perf_counter(), None
        while time.perf_counter() - start < _PSNR_BUDGET_S:
            trainer.train(250, progress=False)
            backend.synchronize()
            scores = trainer.evaluate(held_out)
            extra = {"held_out_psnr": scores["psnr"], "held_out_ssim": scores["ssim"], "train_steps": trainer.step}
            if scores["psnr"] >= _PSNR_TARGET:
                reached = time.perf_counter() - start  # includes the evaluations
                break
        extra["seconds_to_psnr30"] = reached
        iterations = 20
    rays = trainer.config.batch_rays

    return Case(
        run=lambda: trainer.train(iterations, progress=False),
        reference=None,
        params={"batch_rays": rays, "iterations": iterations, "hashgrid": trainer.field.config.hashgrid.__dict__},
        work=iterations,
        unit="steps/s",
        extra={**extra, "rays_per_step": rays},
    )
