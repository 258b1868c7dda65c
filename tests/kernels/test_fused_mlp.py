"""The fused MLP kernels against the layer-by-layer torch reference, forward and backward.

Bounds: the reference runs in float64 with the kernels' operands rounded as theirs are (:func:`round_to`: float16 on
CUDA, float32 on the CPU), so what is left between the two is the kernels' float32 sums and what they change
downstream. :func:`_error_bounds` carries elementwise bounds through the network: a sum of ``k`` terms is off by at
most ``γ_k Σ|terms|`` (``γ_k = k u / (1 − k u)``, ``u = 2^-24``); an activation rounded to the operand dtype (unit
roundoff ``u_T``: 2^-11 for float16) moves by at most ``e + u_T (2|a| + e)`` when its argument is off by ``e``; a
ReLU whose argument lies within its error of 0 may pass or stop the gradient, so the bound takes the whole gradient
there; float16 gradients also carry the subnormal spacing ``2^-24 / s`` (``s`` the kernels' power-of-two scale).
"""

import pytest
import torch

from kernels import backend
from kernels.fused_mlp import FusedMLP, FusedMLPFunction, fused_mlp_forward, kernel_dtype, pack_mlp
from kernels.reference.fused_mlp import mlp_forward_torch, round_to

U32 = 2.0**-24
# (inputs, hidden width, hidden layers, outputs, sigmoid): the NeRF's density MLP (32 hash features -> 16), and a
# colour MLP whose 19 inputs and 3 outputs are padded to 32 and 16 inside.
SHAPES = [(32, 64, 1, 16, False), (19, 32, 2, 3, True)]
ROWS = 150  # two full blocks of 64 rows and a partial one


def _gamma(k: int) -> float:
    return k * U32 / (1 - k * U32)


def _network(shape, seed: int):
    n_in, width, hidden, n_out, sigmoid = shape
    generator = torch.Generator().manual_seed(seed)
    layers: list[torch.nn.Module] = [torch.nn.Linear(n_in, width, bias=False)]
    for _ in range(hidden - 1):
        layers += [torch.nn.ReLU(), torch.nn.Linear(width, width, bias=False)]
    layers += [torch.nn.ReLU(), torch.nn.Linear(width, n_out, bias=False)]
    if sigmoid:
        layers.append(torch.nn.Sigmoid())
    mlp = torch.nn.Sequential(*layers)
    with torch.no_grad():
        for layer in mlp:
            if isinstance(layer, torch.nn.Linear):  # He-scaled, so activations stay O(1) through the layers
                scale = (2 / layer.in_features) ** 0.5
                layer.weight.copy_(torch.randn(layer.weight.shape, generator=generator) * scale)
    x = torch.randn(ROWS, n_in, generator=generator)
    grad_y = torch.randn(ROWS, n_out, generator=generator) * 1e-5  # a per-sample loss gradient's size
    return mlp.to(backend.torch_device()), x.to(backend.torch_device()), grad_y.to(backend.torch_device())


def _reference(x, weights, sigmoid, grad_y, operand):
    """The reference's output, input gradient and weight gradients, float64 with the operands rounded to ``operand``."""
    x = x.detach().double().requires_grad_(True)
    ws = [w.detach().double().requires_grad_(True) for w in weights]
    y = mlp_forward_torch(x, ws, sigmoid, operand)
    y.backward(grad_y.double())
    return y.detach(), x.grad, [w.grad for w in ws]


def _error_bounds(x, weights, sigmoid, grad_y, operand):
    """Elementwise bounds on how far the kernels' output, input gradient and weight gradients may lie from
    :func:`_reference`'s (module docstring)."""
    u = torch.finfo(operand).eps / 2
    x, grad_y = x.double(), grad_y.double()
    ws = [round_to(w.detach().double(), operand) for w in weights]
    # forward, keeping each layer's reference values and error bounds
    a, e = round_to(x, operand), torch.zeros_like(x)
    layers = []
    for i, w in enumerate(ws):
        k = -(-w.shape[1] // 16) * 16 + 1
        z = a @ w.t()
        ez = e @ w.abs().t() + _gamma(k) * (a.abs() @ w.abs().t())
        layers.append((a, e, z, ez))
        if i + 1 < len(ws):
            a = round_to(torch.relu(z), operand)
            e = ez + u * (2 * a.abs() + ez)
    y = torch.sigmoid(z) if sigmoid else z
    ey = (ez / 4 if sigmoid else ez) + U32 * y.abs()
    # backward
    g = grad_y * y * (1 - y) if sigmoid else grad_y
    eg = grad_y.abs() * 0.1 * ez + 4 * U32 * g.abs() if sigmoid else torch.zeros_like(g)
    largest = float(g.abs().max())
    subnormal = 2.0**-24 * largest / 128 if operand == torch.float16 else 0.0
    bounds = [None] * len(ws)
    for i in reversed(range(len(ws))):
        a, e, z, ez = layers[i]
        eg = eg + u * (g.abs() + eg) + subnormal  # the gradient rounded to the operand dtype
        bounds[i] = eg.t() @ a.abs() + g.abs().t() @ e + _gamma(a.shape[0] + 1) * (g.abs().t() @ a.abs())
        w = ws[i]
        k = -(-w.shape[0] // 16) * 16 + 1
        g_act = g @ w
        e_act = eg @ w.abs() + _gamma(k) * (g.abs() @ w.abs())
        if i == 0:
            return ey, e_act + U32 * g_act.abs(), bounds
        _, _, z_below, ez_below = layers[i - 1]
        uncertain = z_below.abs() <= ez_below + subnormal / 2 + 2.0**-25
        g = torch.where(z_below > 0, g_act, 0.0)
        eg = torch.where(uncertain, g_act.abs() + e_act, torch.where(z_below > 0, e_act, 0.0))
    raise AssertionError("unreachable")


def _assert_within(name, got, expected, bound):
    excess = (got.double().cpu() - expected.cpu()).abs() / bound.cpu().clamp_min(1e-300)
    worst = int(excess.argmax())
    assert float(excess.max()) <= 1, (
        f"{name} entry {worst}: |{got.flatten()[worst]:.9g} - {expected.flatten()[worst]:.9g}| exceeds the bound "
        f"{bound.flatten()[worst]:.3g} by {float(excess.max()):.3g}x"
    )


@pytest.mark.parametrize("shape", SHAPES, ids=["density", "colour"])
def test_forward_and_backward_match_reference(device, shape):
    """On the device's operand dtype and on float16 (the CUDA kernels' arithmetic, run by Warp's CPU tiles too)."""
    mlp, x, grad_y = _network(shape, seed=1)
    weights = [layer.weight for layer in mlp if isinstance(layer, torch.nn.Linear)]
    for operand in sorted({kernel_dtype(device), torch.float16}, key=str):
        y_ref, gx_ref, gw_ref = _reference(x, weights, shape[4], grad_y, operand)
        ey, egx, egw = _error_bounds(x, weights, shape[4], grad_y, operand)
        # the density MLP reads the hash grid's feature-major layout, the colour MLP a row-major concatenation
        x_in = (x.t().contiguous().t() if shape == SHAPES[0] else x.clone()).requires_grad_(True)
        packed = pack_mlp([w.detach() for w in weights], shape[4], dtype=operand)
        y = FusedMLPFunction.apply(x_in, packed, *weights)
        assert y.dtype == torch.float32 and y.shape == (ROWS, shape[3])
        _assert_within(f"{operand} y", y.detach(), y_ref, ey)
        y.backward(grad_y)
        assert x_in.grad.stride() == x_in.stride()
        _assert_within(f"{operand} grad x", x_in.grad, gx_ref, egx)
        for i, (w, expected, bound) in enumerate(zip(weights, gw_ref, egw, strict=True)):
            _assert_within(f"{operand} grad weight {i}", w.grad, expected, bound)
            w.grad = None


def test_module_keeps_keys_follows_weight_changes_and_matches_torch_executor(device):
    mlp, x, _ = _network(SHAPES[1], seed=2)
    fused = FusedMLP(mlp)
    assert list(fused.state_dict()) == list(mlp.state_dict())
    first = fused(x).detach()
    with torch.no_grad():  # an optimiser's in-place step: the packed copy must follow
        fused[0].weight.mul_(0.5)
    second = fused(x).detach()
    eager = FusedMLP(mlp, executor="torch")(x).detach()
    assert not torch.equal(first, second)
    zero = torch.zeros(ROWS, 3, device=x.device)
    y_ref, _, _ = _reference(x, fused.weights(), True, zero, kernel_dtype(device))
    ey, _, _ = _error_bounds(x, fused.weights(), True, zero, kernel_dtype(device))
    _assert_within("y after the step", second, y_ref, ey)
    assert torch.allclose(eager.double().cpu(), y_ref.cpu(), rtol=0, atol=float(ey.max()) + 1e-6)
    kernels = FusedMLP(mlp, executor="warp")  # the packed copy is the kernels' (on the CPU too)
    before = kernels(x).detach()
    kernels[0].weight.data.mul_(2.0)  # unseen by the version counter (as a fused Adam step) ...
    assert torch.equal(kernels(x).detach(), before), "the unannounced change went unseen"
    kernels.mark_weights_changed()  # ... so announced, as NGPField.mark_weights_changed does after every step
    assert not torch.equal(kernels(x).detach(), before)


def test_zero_rows(device):
    mlp, x, _ = _network(SHAPES[0], seed=3)
    x = x[:0].clone().requires_grad_(True)
    y = FusedMLPFunction.apply(x, pack_mlp([layer.weight for layer in mlp[::2]]), *[layer.weight for layer in mlp[::2]])
    y.sum().backward()
    assert y.shape == (0, 16) and x.grad.shape == (0, 32)


def test_bad_input_raises(device):
    mlp, x, _ = _network(SHAPES[0], seed=4)
    packed = pack_mlp([layer.weight for layer in mlp[::2]])
    with pytest.raises(ValueError, match=r"shape \[N, 32\]"):
        fused_mlp_forward(x[:, :20].contiguous(), packed)
    with pytest.raises(TypeError, match="float16 or float32"):
        fused_mlp_forward(x.double(), packed)
    with pytest.raises(ValueError, match="contiguous"):
        fused_mlp_forward(x[::2], packed)
    with pytest.raises(ValueError, match="multiple of 16"):
        FusedMLP([torch.nn.Linear(32, 24, bias=False), torch.nn.ReLU(), torch.nn.Linear(24, 3, bias=False)])
    with pytest.raises(ValueError, match="bias-free"):
        FusedMLP([torch.nn.Linear(32, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3, bias=False)])
    with pytest.raises(ValueError, match="ReLU, Linear"):
        FusedMLP([torch.nn.Linear(32, 16, bias=False), torch.nn.Tanh(), torch.nn.Linear(16, 3, bias=False)])
