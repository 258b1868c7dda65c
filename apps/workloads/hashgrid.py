"""Multiresolution hash encoding (PIE-NeRF §3.1): forward features and backward table gradient.

DRAM traffic model (``bytes_moved``), compulsory traffic only, every byte counted once:

* forward: read the positions (12 B per point), write the features (``4 L F`` B per point), read
  each table row the level can reach once (``min(T, (N_l + 1)^3)`` rows of ``4 F`` B per level);
* backward: read the positions and the incoming feature gradient (``12 + 4 L F`` B per point), zero
  the whole gradient table (``4 L T F`` B), then read and write every reachable row once.

Repeated reads of a row by other points are assumed to hit the cache; the fraction of the roofline is
therefore an upper bound on how well the kernel uses DRAM, and the gap to it is the cost of the
random gathers (forward) and atomic adds (backward).

The ``_half`` workloads run the same sizes with a float16 table (``HashGridConfig.table_dtype = "float16"``), so
that one run measures both storage types side by side: ``hashgrid_fwd_half`` gathers from the float16 table (rows of
``2 F`` B in the traffic model); ``hashgrid_bwd_half`` is what the float16 table costs per training step besides the
forward: the same float32 table gradient (the backward never reads the table) plus making the float16 copy again from
the float32 master table after the optimiser step (reading ``4 L T F`` B, writing ``2 L T F`` B more).
"""

from __future__ import annotations

import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.hashgrid import (
    TABLE_DTYPES,
    default_framework,
    hashgrid_backward,
    hashgrid_forward,
    level_resolutions,
)
from kernels.reference.hashgrid import hashgrid_backward_torch, hashgrid_forward_torch

# points, log2 table size; 16 levels of 2 features from N_min = 16 to N_max = 2048 at every size.
_SIZES = {"smoke": (1 << 14, 14), "paper": (1 << 20, 19), "large": (1 << 20, 19)}
_LEVELS, _FEATURES, _BASE, _MAX = 16, 2, 16, 2048


def _inputs(size: str, framework: str | None, table_dtype: str = "float32"):
    points, log2_table_size = _SIZES[size]
    device = backend.torch_device()
    generator = torch.Generator(device="cpu").manual_seed(0)
    x = torch.rand(points, 3, generator=generator).to(device)
    table_size = 1 << log2_table_size
    table = (torch.rand(_LEVELS, table_size, _FEATURES, generator=generator) * 2e-4 - 1e-4).to(device)
    table = table.to(TABLE_DTYPES[table_dtype])
    resolutions = level_resolutions(_LEVELS, _BASE, _MAX).to(device)
    reachable_rows = sum(min(table_size, (n + 1) ** 3) for n in level_resolutions(_LEVELS, _BASE, _MAX).tolist())
    params = {
        "points": points,
        "levels": _LEVELS,
        "features": _FEATURES,
        "table_size": table_size,
        "base_resolution": _BASE,
        "max_resolution": _MAX,
        "framework": framework or default_framework(),
        "table_dtype": table_dtype,
    }
    return x, table, resolutions, reachable_rows, params


def _forward_case(size: str, framework: str | None, table_dtype: str = "float32") -> Case:
    x, table, resolutions, reachable_rows, params = _inputs(size, framework, table_dtype)
    points, row_bytes = x.shape[0], table.element_size() * _FEATURES
    bytes_moved = points * (12 + _LEVELS * row_bytes) + reachable_rows * row_bytes
    return Case(
        run=lambda: hashgrid_forward(x, table, resolutions, framework=framework),
        reference=lambda: hashgrid_forward_torch(x, table.float(), resolutions),
        params=params,
        work=points / 1e6,
        unit="Mpoints/s",
        bytes_moved=bytes_moved,
        reference_name="torch gather",
    )


def _backward_case(size: str, framework: str | None, layout: str = "forward", table_dtype: str = "float32") -> Case:
    """The table gradient from an incoming feature gradient laid out as autograd hands it over in training
    (``"forward"``: as the framework's forward lays out its features, which torch's matrix-product backward keeps;
    feature-major for Warp, :func:`kernels.hashgrid.hashgrid_backward`) or as a contiguous ``[N, L F]``
    (``"row_major"``). With ``table_dtype="float16"`` each run also makes the float16 copy again from a float32
    master table (module docstring)."""
    x, table, resolutions, reachable_rows, params = _inputs(size, framework, table_dtype)
    points, row_bytes = x.shape[0], 4 * _FEATURES
    table_size = table.shape[1]
    master = table.float()
    features = hashgrid_forward(x, table, resolutions, framework=framework)
    generator = torch.Generator(device="cpu").manual_seed(1)
    values = (torch.rand(points, _LEVELS * _FEATURES, generator=generator) - 0.5).to(x.device)
    grad_out = values if layout == "row_major" else torch.empty_strided(
        features.shape, features.stride(), device=x.device).copy_(values)
    params = {**params, "grad_strides": list(grad_out.stride())}
    bytes_moved = points * (12 + _LEVELS * row_bytes) + table.numel() * 4 + 2 * reachable_rows * row_bytes

    def run():
        grad = hashgrid_backward(x, grad_out, resolutions, table_size, framework=framework)
        if table.dtype != torch.float32:
            table.copy_(master)  # the copy HashGridEncoding.read_table makes after an optimiser step
        return grad

    if table.dtype != torch.float32:
        bytes_moved += table.numel() * (4 + table.element_size())
    return Case(
        run=run,
        reference=lambda: hashgrid_backward_torch(x, grad_out, resolutions, table_size),
        params=params,
        work=points / 1e6,
        unit="Mpoints/s",
        bytes_moved=bytes_moved,
        reference_name="torch index_add_",
    )


@workload("hashgrid_fwd", "hash-grid encoding forward, [N, 3] -> [N, 32], in the device's default framework")
def bench_hashgrid_fwd(device: str, size: str) -> Case:
    return _forward_case(size, None)


@workload("hashgrid_bwd", "hash-grid encoding backward, [N, 32] laid out as the forward's features (as in training) "
          "-> [16, T, 2] table gradient, default framework")
def bench_hashgrid_bwd(device: str, size: str) -> Case:
    return _backward_case(size, None)


@workload("hashgrid_fwd_half", "hashgrid_fwd from a float16 table (float32 interpolation and features)")
def bench_hashgrid_fwd_half(device: str, size: str) -> Case:
    return _forward_case(size, None, table_dtype="float16")


@workload("hashgrid_bwd_half", "hashgrid_bwd of a float16 table: the float32 gradient plus the float16 copy's refresh "
          "from the float32 master table")
def bench_hashgrid_bwd_half(device: str, size: str) -> Case:
    return _backward_case(size, None, table_dtype="float16")


@workload("hashgrid_bwd_row_major", "hashgrid_bwd with the incoming gradient a contiguous [N, 32] instead")
def bench_hashgrid_bwd_row_major(device: str, size: str) -> Case:
    return _backward_case(size, None, "row_major")


@workload("hashgrid_fwd_taichi", "hashgrid_fwd in Taichi")
def bench_hashgrid_fwd_taichi(device: str, size: str) -> Case:
    return _forward_case(size, "taichi")


@workload("hashgrid_fwd_warp", "hashgrid_fwd in Warp")
def bench_hashgrid_fwd_warp(device: str, size: str) -> Case:
    return _forward_case(size, "warp")


@workload("hashgrid_bwd_taichi", "hashgrid_bwd in Taichi")
def bench_hashgrid_bwd_taichi(device: str, size: str) -> Case:
    return _backward_case(size, "taichi")


@workload("hashgrid_bwd_warp", "hashgrid_bwd in Warp")
def bench_hashgrid_bwd_warp(device: str, size: str) -> Case:
    return _backward_case(size, "warp")
