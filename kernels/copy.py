"""Streaming copy kernels that calibrate the memory-bandwidth roofline on each device.

Each moves ``2 * x.numel() * x.element_size()`` bytes (one read, one write per element).
Both frameworks are kept on purpose: the copy is the bandwidth each framework reaches on a device.

Each thread moves 16 bytes (a 4-vector) when the length allows: HBM needs more bytes in flight per thread
than a scalar load, and with one float per thread the kernels reached well under torch's vectorised copy
(``docs/benchmarks.md``, ``kernels.copy``).
"""


import taichi as ti
import torch
import warp as wp

from kernels import backend

__all__ = ["copy_taichi", "copy_warp"]


@ti.kernel
def _copy_ti(src: ti.types.ndarray(dtype=ti.f32, ndim=1), dst: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in src:
        dst[i] = src[i]


@ti.kernel
def _copy4_ti(
    src: ti.types.ndarray(dtype=ti.types.vector(4, ti.f32), ndim=1),
    dst: ti.types.ndarray(dtype=ti.types.vector(4, ti.f32), ndim=1),
):
    for i in src:
        dst[i] = src[i]


def copy_taichi(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """Copy ``src`` into ``dst`` with a Taichi kernel.

    Args:
        src: float32 tensor ``[N]`` on the backend device.
        dst: float32 tensor ``[N]`` on the backend device, overwritten.

    Returns:
        ``dst``.
    """
    _check_pair(src, dst)
    if src.numel() % 4 == 0:
        _copy4_ti(backend.taichi_arg(src.view(-1, 4)), backend.taichi_arg(dst.view(-1, 4)))
    else:
        _copy_ti(backend.taichi_arg(src), backend.taichi_arg(dst))
    return dst


@wp.kernel
def _copy_wp(src: wp.array(dtype=wp.float32), dst: wp.array(dtype=wp.float32)):
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def _copy4_wp(src: wp.array(dtype=wp.vec4), dst: wp.array(dtype=wp.vec4)):
    i = wp.tid()
    dst[i] = src[i]


def copy_warp(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """Copy ``src`` into ``dst`` with a Warp kernel (arguments as :func:`copy_taichi`)."""
    _check_pair(src, dst)
    if src.numel() % 4 == 0:
        kernel, inputs = _copy4_wp, [backend.to_warp(t.view(-1, 4), dtype=wp.vec4) for t in (src, dst)]
    else:
        kernel, inputs = _copy_wp, [backend.to_warp(src), backend.to_warp(dst)]
    wp.launch(kernel, dim=inputs[0].shape[0], inputs=inputs, device=backend.warp_device())
    return dst


def _check_pair(src: torch.Tensor, dst: torch.Tensor) -> None:
    if src.dtype != torch.float32 or dst.dtype != torch.float32:
        raise TypeError(f"copy expects float32 tensors, got {src.dtype} and {dst.dtype}")
    if src.dim() != 1 or src.shape != dst.shape:
        raise ValueError(f"copy expects two [N] tensors of one shape, got {tuple(src.shape)} and {tuple(dst.shape)}")
