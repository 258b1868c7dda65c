"""Forward of a bias-free ReLU MLP (the NGP NeRF's density and colour networks) in plain per-thread Warp code.

Why per-thread code. :mod:`kernels.fused_mlp` keeps a block's activations in tiles and multiplies them with
``wp.tile_matmul``, which Warp builds through cuBLASDx when the module compiles, one device function per product
shape, transpose and dtype: minutes on a fresh machine. Here every thread evaluates whole rows with scalar
fused multiply-adds, so a module holds ordinary code that NVRTC builds in well under a second per network shape
(the CPU build, through Warp's LLVM backend, in about a second), and no hidden activation goes to global memory.

One kernel per network shape (:func:`_forward_kernel`, cached, each in its own Warp module). A thread owns ``R``
rows (``rows_per_thread``) and runs the layers ``z_{l+1} = W_l a_l``, ``a_{l+1} = relu(z_{l+1})``:

* the products loop over the layer's inputs ``k`` at run time and, unrolled at build time, over the ``R`` rows and
  the layer's ``D`` outputs: ``z[r, j] += a[r, k] · Wᵀ[k, j]``. The ``R × D`` float32 accumulators are indexed by
  build-time constants only, so they stay in registers; the activations ``a`` are read at the run-time index ``k``
  (one read per row and input, against ``D`` multiply-adds) and live in the thread's local memory (L1-cached);
* the weights are stored transposed, ``[in, out]``, so the ``D`` weights one input ``k`` meets are contiguous; every
  thread of a warp reads the same weight at the same time (a broadcast, served by the L1 cache: the density network's
  weights are 12 KiB in float32, the colour network's 25 KiB);
* sums are float32 whatever the storage: float32 weights as they are, float16 weights widened on load; inputs float16
  or float32, row-major ``[N, n_in]`` or feature-major (a ``[n_in, N]`` contiguous tensor seen transposed, as the
  hash-grid kernels write their features: then a warp's reads of one feature are coalesced);
* the last layer's ``n_out`` values, after an optional sigmoid, are written as float32 or float16.

Arithmetic, per row: ``Σ_l in_l · out_l`` multiply-adds, 3072 for the density network (32 → 64 → 16) and 6336 for the
colour network (32 → 64 → 64 → 3), 18 816 FLOPs for both; a million rows are 18.8 GFLOP, and read 64 B of features
and 64 B of harmonics (float16) and write 6 B (float16 colour) while the hidden activations stay on chip. Each
multiply-add reads one weight, so the loads are the bound before the FMAs: a streaming multiprocessor issues four
warps' FMAs per cycle but one warp's L1 load, hence a ceiling of a quarter of FP32 peak with ``R = 1`` and half with
``R = 2`` (each weight then feeds two rows), about 8 and 17 TFLOP/s on an H100/H200 class GPU (67 TFLOP/s FP32),
i.e. 2.2 and 1.1 ms per million rows of both networks. Float16 weights add a conversion per load, which Hopper issues
at a quarter of the load rate: float32 storage is the fast one. These are ceilings from the instruction mix, not
measurements; the ``mlp_simt`` bench workload measures the kernel beside cuBLAS (``mlp_torch``).

On the CPU Warp runs the same kernel on one thread (correct, and far slower than torch's products on every core):
there it serves the tests, not speed.
"""

import functools
from dataclasses import dataclass

import torch
import warp as wp

from kernels import backend
from kernels.mlp_chain import check_chain, linear_layers

__all__ = ["SimtMLPWeights", "pack_simt_mlp", "simt_mlp_forward", "simt_mlp_weights_of"]

_WARP_DTYPES = {torch.float16: wp.float16, torch.float32: wp.float32}
_ROWS_PER_THREAD = (1, 2, 4)
"""Allowed ``rows_per_thread``: each row adds ``D`` float32 accumulators to a thread's registers."""


@dataclass(frozen=True)
class SimtMLPWeights:
    """A bias-free ReLU MLP's weights laid out for :func:`simt_mlp_forward` (module docstring).

    Attributes:
        w_first: ``[n_in, D]`` first layer, transposed.
        w_hidden: ``[max(H − 1, 1), D, D]`` hidden-to-hidden layers, each transposed (one zero block when ``H = 1``).
        w_last: ``[D, n_out]`` last layer, transposed.
        hidden_layers: ``H``, hidden activations (linear layers minus one).
        sigmoid: whether a sigmoid follows the last layer.
    """

    w_first: torch.Tensor
    w_hidden: torch.Tensor
    w_last: torch.Tensor
    hidden_layers: int
    sigmoid: bool

    @property
    def n_in(self) -> int:
        return self.w_first.shape[0]

    @property
    def width(self) -> int:
        """``D``, the hidden width."""
        return self.w_first.shape[1]

    @property
    def n_out(self) -> int:
        return self.w_last.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        """The weights' storage dtype."""
        return self.w_first.dtype


@torch.no_grad()
def pack_simt_mlp(weights: list[torch.Tensor], sigmoid: bool = False, dtype: torch.dtype = torch.float32):
    """Lay out ``Linear`` weights ``[out, in]`` (first to last) for :func:`simt_mlp_forward`, stored in ``dtype``.

    Args:
        weights: at least two matrices whose widths chain, every hidden layer of one width ``D``.
        sigmoid: a sigmoid follows the last layer.
        dtype: storage, ``torch.float32`` (the fast one on CUDA: module docstring) or ``torch.float16``.

    Returns:
        :class:`SimtMLPWeights` on the weights' device.

    Raises:
        ValueError: fewer than two layers, widths that do not chain, hidden layers of different widths, or another
            storage dtype.
    """
    if dtype not in _WARP_DTYPES:
        raise ValueError(f"weights are stored as float16 or float32, got {dtype}; pass dtype=torch.float32")
    width, device = check_chain(weights, "a SIMT MLP"), weights[0].device
    middle = [w.t() for w in weights[1:-1]] or [torch.zeros(width, width, device=device)]
    return SimtMLPWeights(
        w_first=weights[0].t().to(dtype).contiguous(),
        w_hidden=torch.stack(middle).to(dtype).contiguous(),
        w_last=weights[-1].t().to(dtype).contiguous(),
        hidden_layers=len(weights) - 1,
        sigmoid=bool(sigmoid),
    )


def simt_mlp_weights_of(mlp: torch.nn.Sequential, dtype: torch.dtype = torch.float32) -> SimtMLPWeights:
    """:func:`pack_simt_mlp` of a ``Sequential`` of bias-free ``Linear`` layers, ``ReLU`` between them and an optional
    last ``Sigmoid``; ``ValueError`` naming the layers for anything else."""
    linear = linear_layers(list(mlp), "a SIMT MLP")
    sigmoid = isinstance(mlp[-1], torch.nn.Sigmoid)
    return pack_simt_mlp([layer.weight.detach() for layer in linear], sigmoid, dtype)


# ---------------------------------------------------------------------------------------------------
# Warp kernel, one per shape, rows per thread, dtypes, input layout and last activation
# ---------------------------------------------------------------------------------------------------


@functools.cache
def _forward_kernel(
    n_in: int,
    width: int,
    hidden: int,
    n_out: int,
    rows: int,
    w_dtype,
    x_dtype,
    y_dtype,
    feature_major: bool,
    sigmoid: bool,
):
    """``y [N, n_out] = MLP(x)``, thread ``t`` evaluating rows ``t·R … t·R + R − 1`` (those below ``N``)."""
    acc_type = wp.types.matrix(shape=(rows, width), dtype=wp.float32)
    out_type = wp.types.matrix(shape=(rows, n_out), dtype=wp.float32)
    in_type = wp.types.matrix(shape=(rows, n_in), dtype=wp.float32)

    @wp.func
    def _relu_rows(z: acc_type) -> acc_type:
        a = acc_type()
        for r in range(wp.static(rows)):
            for j in range(wp.static(width)):
                a[r, j] = wp.max(z[r, j], 0.0)
        return a

    @wp.kernel(enable_backward=False, module="unique")
    def _simt_mlp_forward(
        x: wp.array2d(dtype=x_dtype),
        w_first: wp.array2d(dtype=w_dtype),
        w_hidden: wp.array3d(dtype=w_dtype),
        w_last: wp.array2d(dtype=w_dtype),
        row_count: wp.int32,
        y: wp.array2d(dtype=y_dtype),
    ):
        first = wp.tid() * wp.static(rows)
        # the inputs, widened to float32; rows past the end repeat the last row and are not written
        a_in = in_type()
        for r in range(wp.static(rows)):
            row = wp.min(first + r, row_count - 1)
            for k in range(wp.static(n_in)):
                if wp.static(feature_major):
                    a_in[r, k] = wp.float32(x[k, row])
                else:
                    a_in[r, k] = wp.float32(x[row, k])
        # the run-time bounds (the weights' shapes) keep the loops over k loops: a bound known when building would
        # unroll them, since their bodies hold wp.static expressions
        z = acc_type()
        for k in range(w_first.shape[0]):
            for j in range(wp.static(width)):
                w = wp.float32(w_first[k, j])
                for r in range(wp.static(rows)):
                    z[r, j] += a_in[r, k] * w
        for layer in range(wp.static(hidden - 1)):
            a = _relu_rows(z)
            z = acc_type()
            for k in range(w_hidden.shape[1]):
                for j in range(wp.static(width)):
                    w = wp.float32(w_hidden[layer, k, j])
                    for r in range(wp.static(rows)):
                        z[r, j] += a[r, k] * w
        a = _relu_rows(z)
        out = out_type()
        for k in range(w_last.shape[0]):
            for j in range(wp.static(n_out)):
                w = wp.float32(w_last[k, j])
                for r in range(wp.static(rows)):
                    out[r, j] += a[r, k] * w
        for r in range(wp.static(rows)):
            row = first + r
            if row < row_count:
                for j in range(wp.static(n_out)):
                    v = out[r, j]
                    if wp.static(sigmoid):
                        v = 1.0 / (1.0 + wp.exp(-v))
                    y[row, j] = y_dtype(v)

    return _simt_mlp_forward


# ---------------------------------------------------------------------------------------------------
# Host function
# ---------------------------------------------------------------------------------------------------


def simt_mlp_forward(
    x: torch.Tensor,
    weights: SimtMLPWeights,
    out_dtype: torch.dtype = torch.float32,
    rows_per_thread: int = 1,
) -> torch.Tensor:
    """Evaluate an MLP on every row of ``x`` with the per-thread kernel (module docstring), no gradients.

    Args:
        x: ``[N, n_in]`` float16 or float32 on the backend's device, row-major (contiguous) or feature-major (its
            transpose contiguous, as :func:`kernels.hashgrid.hashgrid_forward` writes features).
        weights: the network (:func:`pack_simt_mlp`), on the same device.
        out_dtype: ``torch.float32`` or ``torch.float16``.
        rows_per_thread: ``R``, rows each thread evaluates: 1, 2 or 4 (module docstring; the same result).

    Returns:
        ``[N, n_out]`` in ``out_dtype``, after the sigmoid when the network has one.

    Raises:
        TypeError: ``x`` not a tensor, or of another dtype.
        ValueError: a wrong width, another device, another layout, or a bad ``out_dtype`` or ``rows_per_thread``.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"x must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 2 or x.shape[1] != weights.n_in:
        raise ValueError(f"x must have shape [N, {weights.n_in}], got {tuple(x.shape)}")
    if x.dtype not in _WARP_DTYPES:
        raise TypeError(f"x must be float16 or float32, got {x.dtype}; cast it with .float()")
    if x.device != weights.w_first.device:
        raise ValueError(f"x is on {x.device}, the weights on {weights.w_first.device}; move it with .to(...)")
    if out_dtype not in _WARP_DTYPES:
        raise ValueError(f"out_dtype must be torch.float16 or torch.float32, got {out_dtype}")
    if rows_per_thread not in _ROWS_PER_THREAD:
        raise ValueError(f"rows_per_thread must be one of {_ROWS_PER_THREAD}, got {rows_per_thread}")
    count = x.shape[0]
    y = torch.empty(count, weights.n_out, dtype=out_dtype, device=x.device)
    if count == 0:
        return y
    feature_major = not x.is_contiguous()
    if feature_major and not x.t().is_contiguous():
        raise ValueError(
            f"x must be row-major or feature-major (its transpose contiguous), got strides {x.stride()}; "
            "call .contiguous() first"
        )
    kernel = _forward_kernel(
        weights.n_in,
        weights.width,
        weights.hidden_layers,
        weights.n_out,
        rows_per_thread,
        _WARP_DTYPES[weights.dtype],
        _WARP_DTYPES[x.dtype],
        _WARP_DTYPES[out_dtype],
        feature_major,
        weights.sigmoid,
    )
    threads = -(-count // rows_per_thread)
    args = [x.t() if feature_major else x, weights.w_first, weights.w_hidden, weights.w_last, count, y]
    backend.launch(kernel, threads, args)
    return y
