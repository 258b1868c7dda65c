"""Fully fused bias-free ReLU MLP (instant-NGP §4, the NGP NeRF's density and colour networks), in Warp tiles.

A block of ``R`` rows loads its inputs once, runs every layer with the activations held in tiles (shared memory and
registers) and writes only the last layer's outputs: no hidden activation goes to global memory, where a chain of
matrix products writes and reads each layer's ``[N, width]`` activations. The products are ``wp.tile_matmul``
(cuBLASDx on tensor cores on CUDA) with float16 operands and float32 accumulation on CUDA; on the CPU everything is
float32 (Warp's scalar tile products).

Layout of one network (:class:`PackedMLP`): the layers are ``z_{l+1} = a_l W_lᵀ``, ``a_{l+1} = relu(z_{l+1})`` for
the hidden layers and an optional sigmoid after the last. Every hidden layer has the same width ``D`` (a multiple of
16, as the project's networks: 16, 32 or 64); the input width is padded to ``K`` and the output width to ``O``, the
next multiples of 16, with zero rows and columns of the transposed weights. The padding lives in the packed weights
only: the kernels read ``[N, n_in]`` inputs and write ``[N, n_out]`` outputs through bounds-checked tile loads and
stores, whose out-of-range elements read as zero and are not written.

Backward (:func:`fused_mlp_backward`): a fixed number of blocks walks the rows (a grid-stride loop), recomputes each
row block's forward in tiles, keeps the ``H`` hidden activations in one shared ``[H, R, D]`` tile, and runs the
chain rule back through them: ``dW_l += a_lᵀ g_{l+1}`` accumulates in float32 tiles that are added to global memory
once per block, and ``g_l = (g_{l+1} W_l) ⊙ [a_l > 0]``, down to the input's gradient ``g_0 W_0``. The incoming
gradient is scaled by a power of two ``s`` (:func:`_gradient_scale`, on the device, no host sync) so that its
largest entry is ``2^8`` before it is rounded to float16, as mixed-precision training scales its loss: a NeRF's
per-sample gradients (~1e-6) lie below float16's normal range (6.1e-5). Powers of two scale exactly; the results are
divided by ``s`` in float32.

Gradients at a ReLU's kink follow torch (``relu'(0) = 0``). Inputs may be float32 (the hash grid's features) or
float16; they are rounded to the kernel's dtype in the tile.

:class:`FusedMLP` is a ``torch.nn.Sequential`` of the same ``Linear``/``ReLU``/``Sigmoid`` layers as the field's
(state-dict keys unchanged), with float32 master weights for the optimiser; its forward runs
:class:`FusedMLPFunction`, which packs float16 copies of the weights (cached while the parameters' version counters
stand) and launches the kernels. ``executor="torch"`` runs the layers as ``Sequential`` does; ``"auto"``, the
default, does so on the CPU, where Warp runs its tiles on one thread and torch its products on every core (the
``mlp_fused`` and ``mlp_fused_train`` bench workloads time both).
"""

import functools
from dataclasses import dataclass

import torch
import warp as wp

from kernels import backend

__all__ = [
    "EXECUTORS",
    "FusedMLP",
    "FusedMLPFunction",
    "PackedMLP",
    "fused_mlp_backward",
    "fused_mlp_forward",
    "kernel_dtype",
    "pack_mlp",
]

EXECUTORS = ("auto", "warp", "torch")
"""What runs :class:`FusedMLP`: the fused Warp kernels, torch's layer-by-layer products, or ``"auto"``: the kernels
for CUDA tensors and torch for CPU ones (Warp runs CPU tiles on one thread, torch's products on every core)."""

_ALIGN = 16
"""Widths are padded to multiples of this (a float16 tensor-core fragment's edge)."""
_ROWS = 64
"""``R``: rows per block."""
_BLOCK_DIM = 128
"""Threads per block on CUDA (CPU blocks run one thread)."""
_BACKWARD_BLOCKS_PER_SM = 4
"""Blocks of the backward's grid-stride loop per streaming multiprocessor (CUDA); the CPU runs 64 blocks."""
_GRADIENT_TARGET = 2.0**8
"""The incoming gradient is scaled so that its largest entry is this before rounding to float16."""


def _padded(width: int) -> int:
    return -(-width // _ALIGN) * _ALIGN


def kernel_dtype(device: str | torch.device) -> torch.dtype:
    """The kernels' operand dtype on a device: float16 on CUDA (tensor cores), float32 on the CPU."""
    return torch.float16 if torch.device(device).type == "cuda" else torch.float32


@dataclass(frozen=True)
class PackedMLP:
    """A bias-free ReLU MLP's weights laid out for the kernels (module docstring).

    Attributes:
        w_in: ``[K, D]`` first layer, transposed, rows past ``n_in`` zero.
        w_hidden: ``[(H − 1) · D, D]`` hidden-to-hidden layers, transposed and stacked (one zero ``[D, D]`` block
            when ``H = 1``).
        w_out: ``[D, O]`` last layer, transposed, columns past ``n_out`` zero.
        n_in, n_out: the network's true input and output widths.
        hidden_layers: ``H``, hidden activations (number of linear layers minus one).
        sigmoid: whether a sigmoid follows the last layer.
    """

    w_in: torch.Tensor
    w_hidden: torch.Tensor
    w_out: torch.Tensor
    n_in: int
    n_out: int
    hidden_layers: int
    sigmoid: bool

    @property
    def width(self) -> int:
        """``D``, the hidden width."""
        return self.w_in.shape[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.w_in.dtype


def _check_weights(weights: list[torch.Tensor]) -> None:
    if len(weights) < 2:
        raise ValueError(f"a fused MLP needs at least 2 linear layers (one hidden layer), got {len(weights)}")
    hidden = weights[0].shape[0]
    for i, w in enumerate(weights):
        if not isinstance(w, torch.Tensor) or w.dim() != 2 or not w.is_floating_point():
            raise ValueError(f"weight {i} must be a floating-point [out, in] matrix, got {getattr(w, 'shape', w)}")
        if i > 0 and w.shape[1] != weights[i - 1].shape[0]:
            raise ValueError(f"weight {i} takes {w.shape[1]} inputs but layer {i - 1} gives {weights[i - 1].shape[0]}")
        if 0 < i + 1 < len(weights) and w.shape[0] != hidden:
            raise ValueError(f"every hidden layer must have the same width, got {[w.shape[0] for w in weights[:-1]]}")
    if hidden % _ALIGN:
        raise ValueError(f"the hidden width must be a multiple of {_ALIGN}, got {hidden}; pick another width")


@torch.no_grad()
def pack_mlp(weights: list[torch.Tensor], sigmoid: bool = False, dtype: torch.dtype | None = None) -> PackedMLP:
    """Lay out ``Linear`` weights ``[out, in]`` (first to last) for the kernels, in ``dtype`` (default:
    :func:`kernel_dtype` of their device).

    Raises:
        ValueError: fewer than two layers, widths that do not chain, hidden layers of different widths or a hidden
            width that is not a multiple of 16.
    """
    _check_weights(weights)
    device = weights[0].device
    dtype = kernel_dtype(device) if dtype is None else dtype
    n_in, width, n_out = weights[0].shape[1], weights[0].shape[0], weights[-1].shape[0]
    hidden_layers = len(weights) - 1
    w_in = torch.zeros(_padded(n_in), width, dtype=dtype, device=device)
    w_in[:n_in] = weights[0].t()
    middle = [w.t() for w in weights[1:-1]] or [torch.zeros(width, width, device=device)]
    w_hidden = torch.cat(middle).to(dtype).contiguous()
    w_out = torch.zeros(width, _padded(n_out), dtype=dtype, device=device)
    w_out[:, :n_out] = weights[-1].t()
    return PackedMLP(w_in, w_hidden, w_out, n_in, n_out, hidden_layers, bool(sigmoid))


# ---------------------------------------------------------------------------------------------------
# Warp kernels, one per shape (R, K, D, O, H), operand dtype, input dtype and last activation
# ---------------------------------------------------------------------------------------------------

_WARP_DTYPES = {torch.float16: wp.float16, torch.float32: wp.float32}


@wp.func
def _relu(z: wp.float32) -> wp.float32:
    return wp.max(z, 0.0)


@wp.func
def _sigmoid(z: wp.float32) -> wp.float32:
    return 1.0 / (1.0 + wp.exp(-z))


@wp.func
def _sigmoid_backward(g: wp.float32, z: wp.float32) -> wp.float32:
    y = 1.0 / (1.0 + wp.exp(-z))
    return g * y * (1.0 - y)


@wp.func
def _relu_backward(g: wp.float32, a: wp.float32) -> wp.float32:
    if a > 0.0:
        return g
    return 0.0


@functools.cache
def _forward_kernel(rows: int, k: int, d: int, o: int, h: int, dtype, in_dtype, sigmoid: bool):
    """``y [N, n_out] float32 = MLP(x [N, n_in])``, one block per ``rows`` rows."""

    @wp.kernel(enable_backward=False, module="unique")
    def _fused_mlp_forward(
        x: wp.array2d(dtype=in_dtype),
        w_in: wp.array2d(dtype=dtype),
        w_hidden: wp.array2d(dtype=dtype),
        w_out: wp.array2d(dtype=dtype),
        y: wp.array2d(dtype=wp.float32),
    ):
        block, _lane = wp.tid()
        row = block * rows
        a = wp.tile_astype(wp.tile_load(x, shape=(rows, k), offset=(row, 0)), dtype)
        z = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
        wp.tile_matmul(a, wp.tile_load(w_in, shape=(k, d), storage="shared"), z)
        act = wp.tile_astype(wp.tile_map(_relu, z), dtype)
        for layer in range(h - 1):
            z_next = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
            w = wp.tile_load(w_hidden, shape=(d, d), offset=(layer * d, 0), storage="shared")
            wp.tile_matmul(act, w, z_next)
            act = wp.tile_astype(wp.tile_map(_relu, z_next), dtype)
        out = wp.tile_zeros(shape=(rows, o), dtype=wp.float32)
        wp.tile_matmul(act, wp.tile_load(w_out, shape=(d, o), storage="shared"), out)
        if wp.static(sigmoid):
            wp.tile_store(y, wp.tile_map(_sigmoid, out), offset=(row, 0))
        else:
            wp.tile_store(y, out, offset=(row, 0))

    return _fused_mlp_forward


@functools.cache
def _backward_kernel(rows: int, k: int, d: int, o: int, hidden: int, dtype, in_dtype, sigmoid: bool):
    """Gradients of ``Σ y ⊙ grad_y`` wrt the packed weights (added into float32 ``[K, D]``, ``[(H − 1) D, D]``,
    ``[D, O]`` arrays) and wrt ``x`` (written, float32 ``[N, n_in]``); ``block_count`` blocks walk the rows."""
    hidden_rows = max(hidden - 1, 1) * d

    @wp.kernel(enable_backward=False, module="unique")
    def _fused_mlp_backward(
        x: wp.array2d(dtype=in_dtype),
        w_in: wp.array2d(dtype=dtype),
        w_hidden: wp.array2d(dtype=dtype),
        w_out: wp.array2d(dtype=dtype),
        grad_y: wp.array2d(dtype=wp.float32),
        scale: wp.array(dtype=wp.float32),
        row_count: wp.int32,
        block_count: wp.int32,
        grad_w_in: wp.array2d(dtype=wp.float32),
        grad_w_hidden: wp.array2d(dtype=wp.float32),
        grad_w_out: wp.array2d(dtype=wp.float32),
        grad_x: wp.array2d(dtype=wp.float32),
    ):
        block, _lane = wp.tid()
        s = scale[0]
        unscale = 1.0 / s
        wi = wp.tile_load(w_in, shape=(k, d), storage="shared")
        wh = wp.tile_load(w_hidden, shape=(hidden_rows, d), storage="shared")
        wo = wp.tile_load(w_out, shape=(d, o), storage="shared")
        gwi = wp.tile_zeros(shape=(k, d), dtype=wp.float32, storage="shared")
        gwh = wp.tile_zeros(shape=(hidden_rows, d), dtype=wp.float32, storage="shared")
        gwo = wp.tile_zeros(shape=(d, o), dtype=wp.float32, storage="shared")
        acts = wp.tile_zeros(shape=(hidden, rows, d), dtype=dtype, storage="shared")
        start = block * rows
        while start < row_count:
            # forward again, the hidden activations kept in `acts`
            a = wp.tile_astype(wp.tile_load(x, shape=(rows, k), offset=(start, 0)), dtype)
            z = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
            wp.tile_matmul(a, wi, z)
            wp.tile_assign(wp.tile_view(acts, offset=(0,)), wp.tile_map(_relu, z))
            for layer in range(hidden - 1):
                z_next = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
                w = wp.tile_view(wh, offset=(layer * d, 0), shape=(d, d))
                wp.tile_matmul(wp.tile_view(acts, offset=(layer,)), w, z_next)
                wp.tile_assign(wp.tile_view(acts, offset=(layer + 1,)), wp.tile_map(_relu, z_next))
            last = wp.tile_view(acts, offset=(hidden - 1,))
            g = wp.tile_load(grad_y, shape=(rows, o), offset=(start, 0))
            if wp.static(sigmoid):
                out = wp.tile_zeros(shape=(rows, o), dtype=wp.float32)
                wp.tile_matmul(last, wo, out)
                g = wp.tile_map(_sigmoid_backward, g, out)
            # back through the layers, the gradient scaled by s
            g_out = wp.tile_astype(g * s, dtype)
            wp.tile_matmul(wp.tile_transpose(last), g_out, gwo)
            g_act = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
            wp.tile_matmul(g_out, wp.tile_transpose(wo), g_act)
            g_z = wp.tile_map(_relu_backward, g_act, wp.tile_astype(last, wp.float32))
            for step in range(hidden - 1):
                layer = hidden - 2 - step
                below = wp.tile_view(acts, offset=(layer,))
                g_step = wp.tile_astype(g_z, dtype)
                grad_w = wp.tile_view(gwh, offset=(layer * d, 0), shape=(d, d))
                wp.tile_matmul(wp.tile_transpose(below), g_step, grad_w)
                g_below = wp.tile_zeros(shape=(rows, d), dtype=wp.float32)
                w = wp.tile_view(wh, offset=(layer * d, 0), shape=(d, d))
                wp.tile_matmul(g_step, wp.tile_transpose(w), g_below)
                g_z = wp.tile_map(_relu_backward, g_below, wp.tile_astype(below, wp.float32))
            g_in = wp.tile_astype(g_z, dtype)
            wp.tile_matmul(wp.tile_transpose(a), g_in, gwi)
            g_x = wp.tile_zeros(shape=(rows, k), dtype=wp.float32)
            wp.tile_matmul(g_in, wp.tile_transpose(wi), g_x)
            wp.tile_store(grad_x, g_x * unscale, offset=(start, 0))
            start += block_count * rows
        wp.tile_atomic_add(grad_w_in, gwi * unscale)
        if wp.static(hidden > 1):
            wp.tile_atomic_add(grad_w_hidden, gwh * unscale)
        wp.tile_atomic_add(grad_w_out, gwo * unscale)

    return _fused_mlp_backward


# ---------------------------------------------------------------------------------------------------
# Host functions
# ---------------------------------------------------------------------------------------------------


def _check_rows(name: str, t: torch.Tensor, width: int, dtypes: tuple[torch.dtype, ...], device: torch.device):
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != 2 or t.shape[1] != width:
        raise ValueError(f"{name} must have shape [N, {width}], got {tuple(t.shape)}")
    if t.dtype not in dtypes:
        names = " or ".join(str(d).removeprefix("torch.") for d in dtypes)
        raise TypeError(f"{name} must be {names}, got {t.dtype}; cast it with .to(torch.{names.split()[0]})")
    if t.device != device:
        raise ValueError(f"{name} is on {t.device}, the weights on {device}; move it with .to('{device}')")
    if not (t.is_contiguous() or t.t().is_contiguous()):
        raise ValueError(
            f"{name} must be row-major or feature-major (its transpose contiguous), got strides {t.stride()}; "
            "call .contiguous() first"
        )


def _launch(kernel, blocks: int, args: list, device: torch.device) -> None:
    arrays = [wp.from_torch(a.detach(), requires_grad=False) if isinstance(a, torch.Tensor) else a for a in args]
    wp.launch_tiled(kernel, dim=[blocks], inputs=arrays, block_dim=_BLOCK_DIM, device=backend.warp_device())


def _shape_key(packed: PackedMLP, x: torch.Tensor) -> tuple:
    return (
        _ROWS,
        packed.w_in.shape[0],
        packed.width,
        packed.w_out.shape[1],
        packed.hidden_layers,
        _WARP_DTYPES[packed.dtype],
        _WARP_DTYPES[x.dtype],
        packed.sigmoid,
    )


def fused_mlp_forward(x: torch.Tensor, packed: PackedMLP) -> torch.Tensor:
    """Evaluate a packed MLP on every row of ``x``, no gradients.

    Args:
        x: ``[N, n_in]`` float16 or float32, on the weights' device, row-major or feature-major (as
            :func:`kernels.hashgrid.hashgrid_forward` writes its features).
        packed: the network (:func:`pack_mlp`).

    Returns:
        ``[N, n_out]`` float32, after the sigmoid when the network has one.
    """
    _check_rows("x", x, packed.n_in, (torch.float16, torch.float32), packed.w_in.device)
    y = torch.empty(x.shape[0], packed.n_out, dtype=torch.float32, device=x.device)
    if x.shape[0] == 0:
        return y
    kernel = _forward_kernel(*_shape_key(packed, x))
    _launch(kernel, -(-x.shape[0] // _ROWS), [x, packed.w_in, packed.w_hidden, packed.w_out, y], x.device)
    return y


def _gradient_scale(grad_y: torch.Tensor) -> torch.Tensor:
    """``[1]`` float32 power of two ``s`` with ``s · max |grad_y| ∈ [2^7, 2^8]`` (1 for a zero gradient), on the
    device: the factor that lifts a float32 gradient into float16's normal range before it is rounded."""
    largest = grad_y.abs().amax() if grad_y.numel() else grad_y.new_zeros(())
    exponent = torch.floor(torch.log2(_GRADIENT_TARGET / largest.clamp_min(1e-30))).clamp(-100, 100)
    exponent = torch.where(largest > 0, exponent, 0.0)
    return torch.pow(2.0, exponent).reshape(1).float()


def _backward_blocks(rows: int, device: torch.device) -> int:
    blocks = -(-rows // _ROWS)
    if device.type == "cuda":
        return min(blocks, _BACKWARD_BLOCKS_PER_SM * torch.cuda.get_device_properties(device).multi_processor_count)
    return min(blocks, 64)


def fused_mlp_backward(
    x: torch.Tensor, packed: PackedMLP, grad_y: torch.Tensor
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Gradients of ``Σ fused_mlp_forward(x, packed) ⊙ grad_y`` wrt ``x`` and the weights.

    Args:
        x: the forward's input, ``[N, n_in]`` (as :func:`fused_mlp_forward` takes it).
        packed: the network.
        grad_y: ``[N, n_out]`` float32, the gradient wrt the outputs.

    Returns:
        ``grad_x`` ``[N, n_in]`` float32, in ``x``'s layout, and the weights' gradients, float32 ``[out, in]`` as the
        ``Linear`` layers hold their weights, first layer first.
    """
    _check_rows("x", x, packed.n_in, (torch.float16, torch.float32), packed.w_in.device)
    _check_rows("grad_y", grad_y, packed.n_out, (torch.float32,), packed.w_in.device)
    device, width = x.device, packed.width
    grad_w_in = torch.zeros(packed.w_in.shape, dtype=torch.float32, device=device)
    grad_w_hidden = torch.zeros(packed.w_hidden.shape, dtype=torch.float32, device=device)
    grad_w_out = torch.zeros(packed.w_out.shape, dtype=torch.float32, device=device)
    grad_x = torch.empty_strided(x.shape, x.stride(), dtype=torch.float32, device=device)
    rows = x.shape[0]
    if rows > 0:
        kernel = _backward_kernel(*_shape_key(packed, x))
        blocks = _backward_blocks(rows, device)
        args = [x, packed.w_in, packed.w_hidden, packed.w_out, grad_y.contiguous(), _gradient_scale(grad_y)]
        args += [rows, blocks, grad_w_in, grad_w_hidden, grad_w_out, grad_x]
        _launch(kernel, blocks, args, device)
    grads = [grad_w_in[: packed.n_in].t()]
    grads += [grad_w_hidden[i * width : (i + 1) * width].t() for i in range(packed.hidden_layers - 1)]
    grads.append(grad_w_out[:, : packed.n_out].t())
    return grad_x, [g.contiguous() for g in grads]


class FusedMLPFunction(torch.autograd.Function):
    """``y = MLP(x)`` through the fused kernels, differentiable wrt ``x`` and the float32 master weights.

    ``FusedMLPFunction.apply(x, packed, *weights)``: ``packed`` is :func:`pack_mlp` of ``weights`` (the ``[out, in]``
    master weights, first to last), which are passed too so that autograd hands their gradients to them. Returns
    ``[N, n_out]`` float32; the gradient wrt ``x`` comes back in ``x``'s dtype and layout.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, packed: PackedMLP, *weights: torch.Tensor) -> torch.Tensor:
        ctx.packed = packed
        ctx.save_for_backward(x)
        return fused_mlp_forward(x, packed)

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor):
        (x,) = ctx.saved_tensors
        grad_x, grad_weights = fused_mlp_backward(x, ctx.packed, grad_y.float().contiguous())
        weight_grads = [g if needed else None for g, needed in zip(grad_weights, ctx.needs_input_grad[2:], strict=True)]
        return (grad_x.to(x.dtype) if ctx.needs_input_grad[0] else None), None, *weight_grads


def _linear_layers(layers: list[torch.nn.Module]) -> list[torch.nn.Linear]:
    """The ``Linear`` layers of ``Linear, [ReLU, Linear] ..., [Sigmoid]``, bias-free; else ``ValueError``."""
    kinds = [type(layer) for layer in layers]
    linear = [layer for layer in layers if isinstance(layer, torch.nn.Linear)]
    expected = [torch.nn.Linear] + [torch.nn.ReLU, torch.nn.Linear] * (len(linear) - 1)
    if len(linear) < 2 or kinds not in (expected, expected + [torch.nn.Sigmoid]):
        names = [k.__name__ for k in kinds]
        raise ValueError(f"a fused MLP is Linear, (ReLU, Linear) at least once, then maybe Sigmoid; got {names}")
    if any(layer.bias is not None for layer in linear):
        raise ValueError("a fused MLP's Linear layers are bias-free (bias=False)")
    return linear


class FusedMLP(torch.nn.Sequential):
    """A bias-free ReLU MLP (``Linear, [ReLU, Linear] ..., [Sigmoid]``) evaluated by the fused kernels.

    A ``Sequential`` of the very layers it is given, so it holds the float32 master weights under the same
    state-dict keys (``"0.weight"``, ``"2.weight"`` ...) and an optimiser over them is unchanged. Its forward packs
    float16 copies of the weights (float32 on the CPU) once per change of the weights (the parameters' version
    counters, which optimiser steps and ``load_state_dict`` bump; a change they do not count, a fused optimiser step
    or a write through ``.data``, is announced by :meth:`mark_weights_changed`) and runs :class:`FusedMLPFunction`.

    Args:
        layers: the layers, e.g. an existing ``torch.nn.Sequential`` (shared, not copied).
        executor: ``"warp"`` (the fused kernels), ``"torch"`` (layer by layer, as ``Sequential``) or ``"auto"``
            (:data:`EXECUTORS`). Inputs of a dtype the kernels do not take (float64, for a gradient check) go through
            torch.
    """

    def __init__(self, layers: torch.nn.Sequential | list[torch.nn.Module], executor: str = "auto"):
        layers = list(layers)
        linear = _linear_layers(layers)
        _check_weights([layer.weight for layer in linear])
        if executor not in EXECUTORS:
            raise ValueError(f"executor must be one of {EXECUTORS}, got {executor!r}")
        super().__init__(*layers)
        self.executor = executor
        self.sigmoid = isinstance(layers[-1], torch.nn.Sigmoid)
        self._packed: tuple[tuple, PackedMLP] | None = None
        self._generation = 0  # changes announced by mark_weights_changed

    def mark_weights_changed(self) -> None:
        """Announce a change of the weights their version counters do not see (torch's fused Adam steps without
        bumping them, as a write through ``.data`` does): the packed copy is made again at the next forward."""
        self._generation += 1

    def weights(self) -> list[torch.Tensor]:
        """The ``Linear`` layers' ``[out, in]`` weights, first to last."""
        return [layer.weight for layer in self if isinstance(layer, torch.nn.Linear)]

    def packed(self) -> PackedMLP:
        """The weights laid out for the kernels in :func:`kernel_dtype` of their device, made again after any change."""
        weights = self.weights()
        key = (self._generation, *((w.data_ptr(), w._version, w.device) for w in weights))
        if self._packed is None or self._packed[0] != key:
            self._packed = (key, pack_mlp([w.detach() for w in weights], self.sigmoid))
        return self._packed[1]

    def runs_kernels(self, device: torch.device) -> bool:
        """Whether inputs on ``device`` (float16 or float32) go through the fused kernels."""
        return self.executor == "warp" or (self.executor == "auto" and torch.device(device).type == "cuda")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[N, n_in]`` → ``[N, n_out]`` (float32 from the kernels; the input's dtype from torch)."""
        if not self.runs_kernels(x.device) or x.dtype not in _WARP_DTYPES:
            return super().forward(x)
        return FusedMLPFunction.apply(x, self.packed(), *self.weights())
