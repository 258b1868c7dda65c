"""The networks the MLP kernels take: a chain of bias-free ``Linear`` layers, ``ReLU`` between them, one hidden width.

:mod:`kernels.fused_mlp` (tiles) and :mod:`kernels.simt_mlp` (per-thread code) lay such a chain out differently and
check it the same way, here; each names itself in the errors (``what``: ``"a fused MLP"``, ``"a SIMT MLP"``).
"""

import torch

__all__ = ["check_chain", "linear_layers"]


def linear_layers(layers: list[torch.nn.Module], what: str) -> list[torch.nn.Linear]:
    """The ``Linear`` layers of ``Linear, (ReLU, Linear) ..., [Sigmoid]``, at least two and bias-free.

    Raises:
        ValueError: another sequence of layers (named), or a layer with a bias.
    """
    kinds = [type(layer) for layer in layers]
    linear = [layer for layer in layers if isinstance(layer, torch.nn.Linear)]
    expected = [torch.nn.Linear] + [torch.nn.ReLU, torch.nn.Linear] * (len(linear) - 1)
    if len(linear) < 2 or kinds not in (expected, expected + [torch.nn.Sigmoid]):
        names = [k.__name__ for k in kinds]
        raise ValueError(f"{what} is Linear, (ReLU, Linear) at least once, then maybe Sigmoid; got {names}")
    if any(layer.bias is not None for layer in linear):
        raise ValueError(f"{what}'s Linear layers are bias-free (bias=False)")
    return linear


def check_chain(weights: list[torch.Tensor], what: str) -> int:
    """Check ``Linear`` weights ``[out, in]`` (first to last) for a chain; returns the hidden width ``D``.

    Raises:
        ValueError: fewer than two matrices, one that is not a floating-point matrix, widths that do not chain, or
            hidden layers of different widths.
    """
    if len(weights) < 2:
        raise ValueError(f"{what} needs at least 2 linear layers (one hidden layer), got {len(weights)}")
    for i, w in enumerate(weights):
        if not isinstance(w, torch.Tensor) or w.dim() != 2 or not w.is_floating_point():
            raise ValueError(f"weight {i} must be a floating-point [out, in] matrix, got {getattr(w, 'shape', w)}")
        if i > 0 and w.shape[1] != weights[i - 1].shape[0]:
            raise ValueError(f"weight {i} takes {w.shape[1]} inputs but layer {i - 1} gives {weights[i - 1].shape[0]}")
    widths = [w.shape[0] for w in weights[:-1]]
    if len(set(widths)) != 1:
        raise ValueError(f"every hidden layer must have the same width, got {widths}")
    return widths[0]
