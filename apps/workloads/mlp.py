"""The NGP NeRF's two MLPs (PIE-NeRF §3.1) on a batch of rows: the fused kernels beside torch's products.

Rows: 16 384 (smoke), 2^20 (paper, the brief's 1M samples of a deformed frame) and 2^22 (large). Each row is the
density MLP on 32 hash features (32 → 64 → 16) and the colour MLP on its 16 outputs and 16 spherical harmonics
(32 → 64 → 64 → 3, sigmoid), the default :class:`pienerf.nerf.NGPConfig`, random He-scaled weights.

* ``mlp_fused``: :class:`kernels.fused_mlp.FusedMLP`'s kernels (float16 operands on CUDA, float32 tiles on the CPU).
* ``mlp_torch``: what the renderer ran before them, :class:`pienerf.nerf.InferenceMLP` (float16 cuBLAS products with
  the ReLU in the epilogue on CUDA, float32 on the CPU).
* ``mlp_fused_train``: forward and backward (gradients wrt the weights and the features) through
  :class:`kernels.fused_mlp.FusedMLPFunction`, a training step's MLP work.

The reference of each is the float32 ``torch.nn.Sequential`` (with autograd for ``mlp_fused_train``). ``flops``
counts the products' multiply-adds (2 per weight per row; three times that for forward + backward).
"""

from __future__ import annotations

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.fused_mlp import FusedMLP
from pienerf.nerf.field import InferenceMLP, NGPConfig, NGPField

_ROWS = {"smoke": 1 << 14, "paper": 1 << 20, "large": 1 << 22}


def _setup(size: str):
    device = backend.torch_device()
    torch.manual_seed(0)
    field = NGPField(NGPConfig(mlp="torch")).to(device)
    rows = _ROWS[size]
    generator = torch.Generator().manual_seed(0)
    features = (torch.rand(rows, field.config.hashgrid.output_dim, generator=generator) * 2e-2 - 1e-2).to(device)
    directions = torch.nn.functional.normalize(torch.randn(rows, 3, generator=generator), dim=-1).to(device)
    sh = field.encode_directions(directions).contiguous()
    weights = sum(p.numel() for mlp in (field.density_mlp, field.color_mlp) for p in mlp.parameters())
    params = {"rows": rows, "density_mlp": "32-64-16", "color_mlp": "32-64-64-3 sigmoid", "device": device.type}
    return field, features, sh, weights, params


def _pair(density, color, features, sh):
    h = density(features)
    return color(torch.cat([h, sh.to(h.dtype)], dim=-1))


def _reference(field, features, sh):
    def run():
        with torch.no_grad():
            return _pair(field.density_mlp, field.color_mlp, features, sh)

    return run


@workload("mlp_fused", "the NeRF's density + colour MLPs on 1M rows (paper) by the fused Warp tile kernels")
def bench_mlp_fused(device: str, size: str) -> Case:
    field, features, sh, weights, params = _setup(size)
    density, color = FusedMLP(field.density_mlp, "warp"), FusedMLP(field.color_mlp, "warp")

    def run():
        with torch.no_grad():
            return _pair(density, color, features, sh)

    rows = features.shape[0]
    return Case(
        run=run, reference=_reference(field, features, sh), params=params, work=rows / 1e6, unit="Mrows/s",
        flops=2.0 * weights * rows, reference_name="torch float32 Sequential",
    )


@workload("mlp_torch", "mlp_fused's work by InferenceMLP (float16 cuBLAS products, ReLU epilogue, on CUDA)")
def bench_mlp_torch(device: str, size: str) -> Case:
    field, features, sh, weights, params = _setup(size)
    dtype = torch.float16 if device == "cuda" else torch.float32
    density, color = InferenceMLP(field.density_mlp, dtype), InferenceMLP(field.color_mlp, dtype)
    sh_cast = sh.to(dtype)

    def run():
        return _pair(density, color, features, sh_cast)

    rows = features.shape[0]
    return Case(
        run=run, reference=_reference(field, features, sh), params={**params, "dtype": str(dtype)},
        work=rows / 1e6, unit="Mrows/s", flops=2.0 * weights * rows, reference_name="torch float32 Sequential",
    )


@workload("mlp_fused_train", "forward + backward of mlp_fused's MLPs (weights' and features' gradients)")
def bench_mlp_fused_train(device: str, size: str) -> Case:
    field, features, sh, weights, params = _setup(size)
    density, color = FusedMLP(field.density_mlp, "warp"), FusedMLP(field.color_mlp, "warp")
    features = features.requires_grad_(True)
    grad_rgb = torch.rand(features.shape[0], 3, device=features.device) * 1e-5

    def step(d, c):
        def run():
            features.grad = None
            for p in field.parameters():
                p.grad = None
            _pair(d, c, features, sh).backward(grad_rgb)

        return run

    rows = features.shape[0]
    return Case(
        run=step(density, color), reference=step(field.density_mlp, field.color_mlp), params=params,
        work=rows / 1e6, unit="Mrows/s", flops=6.0 * weights * rows, reference_name="torch float32 autograd",
    )
