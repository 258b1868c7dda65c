"""Reference of :mod:`kernels.fused_mlp` in plain torch: one matrix product per layer.

:func:`mlp_forward_torch` evaluates the same bias-free ReLU MLP layer by layer in the inputs' dtype. With
``operand_dtype`` it rounds the operands where the kernels do (the input, the weights and every hidden activation,
to float16 on CUDA) while computing in the inputs' dtype, e.g. float64: the kernels' result up to the order of their
float32 sums. The rounding passes gradients straight through, so autograd through it gives the exact gradient of
that rounded network, the oracle of :func:`kernels.fused_mlp.fused_mlp_backward`.
"""

from __future__ import annotations

import torch

__all__ = ["mlp_forward_torch", "round_to"]


def round_to(x: torch.Tensor, dtype: torch.dtype | None) -> torch.Tensor:
    """``x`` rounded to ``dtype`` (nearest, ties to even) and back, in ``x``'s dtype; the gradient passes unchanged.
    ``None``: ``x`` itself."""
    if dtype is None:
        return x
    return x + (x.detach().to(dtype).to(x.dtype) - x.detach())


def mlp_forward_torch(
    x: torch.Tensor,
    weights: list[torch.Tensor],
    sigmoid: bool = False,
    operand_dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """``y = [sigmoid](W_L relu(... relu(W_1 x)))`` for ``Linear`` weights ``[out, in]``, first to last.

    Args:
        x: ``[N, n_in]``.
        weights: the layers' weights, in ``x``'s dtype.
        sigmoid: apply a sigmoid to the last layer's output.
        operand_dtype: round the input, the weights and the hidden activations to this dtype (:func:`round_to`).

    Returns:
        ``[N, n_out]`` in ``x``'s dtype, differentiable wrt ``x`` and ``weights``.
    """
    a = round_to(x, operand_dtype)
    for i, w in enumerate(weights):
        z = a @ round_to(w, operand_dtype).t()
        a = round_to(torch.relu(z), operand_dtype) if i + 1 < len(weights) else z
    return torch.sigmoid(a) if sigmoid else a
