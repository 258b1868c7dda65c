"""Bandwidth calibration: a streaming float32 copy in Taichi, Warp and torch."""

from __future__ import annotations

import numpy as np
import torch

from apps.workloads import Case, workload
from kernels import backend
from kernels.copy import copy_taichi, copy_warp
from kernels.reference.copy import copy_numpy, copy_torch

_ELEMENTS = {"smoke": 1 << 20, "paper": 1 << 26, "large": 1 << 28}


def _copy_case(device: str, size: str, kernel) -> Case:
    n = _ELEMENTS[size]
    src = torch.rand(n, device=backend.torch_device())
    dst = torch.empty_like(src)
    bytes_moved = 2.0 * n * src.element_size()
    if kernel is copy_torch:
        # torch's copy is itself the calibration; its reference is the same copy in NumPy on the host.
        host_src, host_dst = src.cpu().numpy(), np.empty(n, dtype=np.float32)
        reference, reference_name = (lambda: copy_numpy(host_src, host_dst)), "numpy (host)"
    else:
        reference, reference_name = (lambda: copy_torch(src, dst)), "torch copy_"
    return Case(
        run=lambda: kernel(src, dst),
        reference=reference,
        params={"elements": n, "dtype": "float32", "megabytes_per_buffer": n * 4 / 2**20},
        work=bytes_moved / 1e9,
        unit="GB/s",
        bytes_moved=bytes_moved,
        reference_name=reference_name,
    )


@workload("copy_taichi", "float32 stream copy in a Taichi kernel (bandwidth roofline)")
def bench_copy_taichi(device: str, size: str) -> Case:
    return _copy_case(device, size, copy_taichi)


@workload("copy_warp", "float32 stream copy in a Warp kernel (bandwidth roofline)")
def bench_copy_warp(device: str, size: str) -> Case:
    return _copy_case(device, size, copy_warp)


@workload("copy_torch", "float32 stream copy by torch's copy_ (bandwidth roofline)")
def bench_copy_torch(device: str, size: str) -> Case:
    return _copy_case(device, size, copy_torch)
