"""NGP NeRF (PIE-NeRF §3.1): volume-rendering compositing and whole training steps.

* ``volume_render``: forward and backward compositing of packed samples (:mod:`kernels.volume_render`)
  against the torch reference (segmented ``cumsum`` + ``index_add_``, autograd). Compulsory DRAM
  traffic per sample: the forward reads σ, δ, t, c (24 B) and the backward reads them again and writes
  ∂σ, ∂c (24 + 16 B); per ray a few dozen bytes more.
* ``nerf_train``: how fast :class:`pienerf.nerf.training.Trainer` learns and steps. Paper and large sizes train
  instant-NGP's configuration on the NeRF-synthetic lego at 800×800 (``../shared/data``): on the training views
  less every 8th (``held_out(8)``), scored on those held-out views over white (and on a few test views when the
  dataset has a test split; the lego here has none). The record's ``curve`` holds ``{seconds, steps, psnr, ssim}``
  (means over the scored views) at the training wall times :data:`CURVE_CHECKPOINTS_S` (evaluations excluded from
  the clock, :func:`pienerf.nerf.train_curve`), over a budget of :data:`TRAINING_BUDGET_S` that stops early
  at :data:`STOP_PSNR`; with ``seconds_to_psnr30`` (interpolated between checkpoints), ``psnr_at_180s``,
  ``ssim_at_180s`` (the last checkpoint's, ``curve_stopped_early`` telling whether it came before the budget; the
  keys name the budget, ``psnr_at_2s`` at smoke size) and
  ``view_psnr`` (per scored view at the last checkpoint: the worst views). With an images folder (``apps.bench``'s
  ``--images``) it writes render | ground truth | error map PNGs of the scored views and a contact sheet
  (:func:`pienerf.nerf.write_error_images`), named in ``error_images``. ``startup_s``: seconds from the start
  of a fresh process to the end of its first training step (:mod:`apps.nerf_startup`), run twice (``first`` may
  find cold kernel caches, ``second`` finds them warm) with the second's phases in ``breakdown``. After all this,
  the timed part is a few training steps (steps/s). Smoke size trains a tiny NeRF on a synthetic ball rendered in
  memory, with a short curve (:data:`SMOKE_CHECKPOINTS_S`) and no start-up probe.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import torch

from apps.workloads import Case, WorkloadUnavailable, workload
from kernels import backend
from kernels.hashgrid import HashGridConfig
from kernels.reference.volume_render import composite_torch
from kernels.volume_render import composite
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.datasets import NerfDataset, load_nerf_dataset
from pienerf.nerf.field import NGPConfig, NGPField
from pienerf.nerf.training import TrainConfig, Trainer
from pienerf.nerf.training_curve import CurvePoint, TrainingCurve, train_curve, write_error_images
from pienerf.paths import SHARED_DATA

# rays, mean samples per ray
_RENDER_SIZES = {"smoke": (4096, 64), "paper": (1 << 14, 128), "large": (1 << 18, 128)}
LEGO = SHARED_DATA / "nerf_synthetic_lego"
"""The NeRF-synthetic lego scene that ``nerf_train`` trains on at paper and large sizes."""
TRAINING_BUDGET_S = 180.0
"""Training wall time of ``nerf_train``'s curve at paper and large sizes, s (evaluations excluded)."""
CURVE_CHECKPOINTS_S = (5.0, 10.0, 15.0, 30.0, 45.0, 60.0, 90.0, 120.0, 150.0, TRAINING_BUDGET_S)
"""Training wall times at which ``nerf_train`` scores the unseen views, s."""
SMOKE_CHECKPOINTS_S = (0.5, 1.0, 2.0)
"""The smoke size's short curve, s."""
PSNR_TARGET = 30.0
"""PSNR whose training time the record gives (``seconds_to_psnr30``), dB."""
STOP_PSNR = 36.0
"""Mean PSNR on the scored views at which training stops before the budget, dB."""
STARTUP_TIMEOUT_S = 300.0
"""Longest a start-up probe may run (a cold kernel cache compiles everything), s."""
_REPOSITORY = Path(__file__).resolve().parents[2]


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
    """A ball with a smooth colour pattern, seen from ``views`` cameras; RGBA rendered analytically, over black."""
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


def nerf_setup(size: str) -> tuple[NGPConfig, torch.Tensor, TrainConfig]:
    """``nerf_train``'s field config, scene box ``[2, 3]`` (metres) and training config at ``size``."""
    if size == "smoke":
        config = NGPConfig(
            hashgrid=HashGridConfig(levels=8, log2_table_size=14, base_resolution=8, max_resolution=128),
            density_hidden=32, color_hidden=32, color_layers=1, grid_resolution=32, samples_per_diagonal=128,
        )
        return config, torch.tensor([[-1.0] * 3, [1.0] * 3]), TrainConfig(batch_rays=1024, grid_warmup_steps=8)
    batch = 1 << 14 if size == "paper" else 1 << 16
    return NGPConfig(), torch.tensor([[-1.5] * 3, [1.5] * 3]), TrainConfig(steps=20_000, batch_rays=batch)


def parse_startup_report(stdout: str) -> dict:
    """The report :mod:`apps.nerf_startup` printed: the last line of ``stdout`` that is a JSON object with
    ``first_step_s`` and ``breakdown``.

    Raises:
        ValueError: no such line.
    """
    for line in reversed(stdout.strip().splitlines()):
        try:
            report = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(report, dict) and isinstance(report.get("first_step_s"), float) and "breakdown" in report:
            return report
    raise ValueError(f"the start-up probe printed no report line; its output ended with: {stdout[-500:]!r}")


def measure_startup(
    device: str,
    size: str,
    dataset: Path = LEGO,
    downscale: int = 1,
    max_views: int | None = None,
    timeout_s: float = STARTUP_TIMEOUT_S,
) -> dict:
    """Run :mod:`apps.nerf_startup` in a fresh Python process and return its report (``first_step_s``, seconds
    from that process's start to the end of its first training step, and ``breakdown``).

    Raises:
        RuntimeError: the probe failed or printed no report; the message holds the end of its stderr.
    """
    command = [sys.executable, "-m", "apps.nerf_startup", "--device", device, "--size", size, "--dataset", str(dataset)]
    command += ["--downscale", str(downscale)] + ([] if max_views is None else ["--max-views", str(max_views)])
    result = subprocess.run(command, capture_output=True, text=True, cwd=_REPOSITORY, timeout=timeout_s, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"the start-up probe {' '.join(command[1:])} failed: {result.stderr[-2000:]}")
    try:
        return parse_startup_report(result.stdout)
    except ValueError as error:
        raise RuntimeError(f"{error}; stderr: {result.stderr[-2000:]}") from error


def _startup_record(device: str, size: str) -> dict:
    """``startup_s`` of the record: two probes in a row (the first may find cold caches), or the error that stopped
    them (the curve is still measured)."""
    reports = []
    for run in ("first", "second"):
        print(f"nerf_train: start-up probe, {run} run", file=sys.stderr, flush=True)
        try:
            reports.append(measure_startup(device, size))
        except (RuntimeError, subprocess.TimeoutExpired) as error:
            print(f"nerf_train: start-up probe failed: {error}", file=sys.stderr, flush=True)
            return {"error": str(error)[-2000:]}
    first, second = reports
    return {
        "first": first["first_step_s"],
        "second": second["first_step_s"],
        "breakdown": second["breakdown"],
        "first_breakdown": first["breakdown"],
    }


def _joined(first: NerfDataset, second: NerfDataset) -> NerfDataset:
    """The views of ``first`` then ``second`` (one image size and background)."""
    a, b = first.cameras, second.cameras
    cameras = replace(a, **{k: torch.cat([getattr(a, k), getattr(b, k)]) for k in ("c2w", "fx", "fy", "cx", "cy")})
    return replace(
        first,
        images=torch.cat([first.images, second.images]),
        alphas=torch.cat([first.alphas, second.alphas]),
        cameras=cameras,
        names=first.names + second.names,
    )


def _lego_views() -> tuple[NerfDataset, NerfDataset]:
    """Training views (over black: the trainer composites its own backgrounds) and scored views (over white)."""
    train, held = load_nerf_dataset(LEGO, "train", background=(0.0, 0.0, 0.0)).held_out(8)
    scored = held.over_background((1.0, 1.0, 1.0))
    if (LEGO / "transforms_test.json").is_file():  # a test split of its own: a few of its views too
        test = load_nerf_dataset(LEGO, "test", background=(1.0, 1.0, 1.0))
        scored = _joined(scored, test.select(list(range(0, len(test), max(1, len(test) // 4)))[:4]))
    return train, scored


def _print_checkpoint(point: CurvePoint, names: list[str]) -> None:
    worst = min(range(len(names)), key=lambda i: point.view_psnr[i])
    print(
        f"nerf_train: {point.seconds:6.1f} s  {point.steps:6d} steps  PSNR {point.psnr:.2f} dB  SSIM {point.ssim:.4f}"
        f"  (worst {Path(names[worst]).name}: {point.view_psnr[worst]:.2f} dB)",
        file=sys.stderr,
        flush=True,
    )


def _curve_record(curve: TrainingCurve, scored: NerfDataset, budget_s: float) -> dict:
    last = curve.points[-1]
    return {
        "curve": [point.record() for point in curve.points],
        f"seconds_to_psnr{PSNR_TARGET:g}": curve.seconds_to_psnr(PSNR_TARGET),
        f"psnr_at_{budget_s:g}s": last.psnr,
        f"ssim_at_{budget_s:g}s": last.ssim,
        "curve_stopped_early": curve.stopped_early,
        "training_budget_s": budget_s,
        "scored_views": len(scored),
        "view_psnr": dict(zip(scored.names, last.view_psnr, strict=True)),
        "train_steps": last.steps,
    }


@workload(
    "nerf_train",
    "NGP NeRF training: PSNR/SSIM curve on unseen views, error images, start-up time, steps/s (paper: lego 800x800)",
    writes_images=True,
)
def bench_nerf_train(device: str, size: str, images: Path | None = None) -> Case:
    torch.manual_seed(0)
    extra: dict = {}
    config, aabb, train_config = nerf_setup(size)
    if size == "smoke":
        train, held = _ball_dataset(10, 32).held_out(5)
        scored, checkpoints = held.over_background((1.0, 1.0, 1.0)), SMOKE_CHECKPOINTS_S
        iterations = 4
    else:
        if not LEGO.is_dir():
            raise WorkloadUnavailable(f"nerf_train at paper and large sizes needs the lego scene at {LEGO}")
        extra["startup_s"] = _startup_record(device, size)
        train, scored = _lego_views()
        checkpoints = CURVE_CHECKPOINTS_S
        iterations = 20
    trainer = Trainer(NGPField(config, aabb), train, train_config)
    chunk = 1 << 16 if device == "cuda" else 4096
    curve = train_curve(
        trainer, scored, checkpoints, stop_psnr=STOP_PSNR, chunk=chunk,
        on_checkpoint=lambda point: _print_checkpoint(point, scored.names),
    )
    extra.update(_curve_record(curve, scored, checkpoints[-1]))
    extra["error_images"] = None
    if images is not None:
        extra["error_images"] = write_error_images(
            images / f"nerf_train-{size}", scored.names, curve.renders, scored.images, curve.points[-1].view_psnr
        )
    rays = trainer.config.batch_rays

    return Case(
        run=lambda: trainer.train(iterations, progress=False),
        reference=None,
        params={"batch_rays": rays, "iterations": iterations, "hashgrid": trainer.field.config.hashgrid.__dict__},
        work=iterations,
        unit="steps/s",
        extra={**extra, "rays_per_step": rays},
    )
