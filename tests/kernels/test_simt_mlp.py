"""The per-thread MLP kernel against the layer-by-layer torch reference.

Bounds: the reference runs in float64 on the weights as the kernel stores them (rounded to float16 for float16
storage) and on the inputs as given, so what is left between the two is the kernel's float32 arithmetic.
:func:`_error_bound` carries elementwise bounds through the network: a float32 sum of ``k`` products (fused
multiply-adds) is off by at most ``γ_{k+1} Σ|w||a|`` (``γ_k = k u / (1 − k u)``, ``u = 2^-24``) plus ``Σ|w| e`` from
inputs already off by ``e``; a ReLU does not grow an error; a sigmoid scales it by at most 1/4 and rounds its
``exp``, sum and quotient (a few ``u`` on a value in (0, 1), 8 u taken); a float16 output adds half its spacing,
``2^-11 (|y| + e)``, and float16's subnormal spacing ``2^-24``.
"""

import pytest
import torch

from kernels import backend
from kernels.reference.fused_mlp import mlp_forward_torch
from kernels.simt_mlp import pack_simt_mlp, simt_mlp_forward, simt_mlp_weights_of

U32, U16 = 2.0**-24, 2.0**-11
# (inputs, hidden width, hidden layers, outputs, sigmoid): the NeRF's density MLP (32 hash features -> 64 -> 16) and
# colour MLP (16 + 16 harmonics -> 64 -> 64 -> 3, sigmoid)
SHAPES = {"density": (32, 64, 1, 16, False), "colour": (32, 64, 2, 3, True)}
ROWS = 301  # not a multiple of 2 or 4 rows per thread, nor of a block of threads
# (rows per thread, input layout, input dtype, output dtype)
VARIANTS = [
    (1, "row-major", torch.float32, torch.float32),
    (2, "feature-major", torch.float16, torch.float16),
    (4, "row-major", torch.float32, torch.float16),
]


def _network(shape, seed: int) -> tuple[list[torch.Tensor], torch.Tensor]:
    """He-scaled ``[out, in]`` weights (activations stay O(1) through the layers) and ``[ROWS, n_in]`` inputs."""
    n_in, width, hidden, n_out, _ = shape
    generator = torch.Generator().manual_seed(seed)
    widths = [n_in] + [width] * hidden + [n_out]
    weights = [
        torch.randn(o, i, generator=generator) * (2 / i) ** 0.5 for i, o in zip(widths[:-1], widths[1:], strict=True)
    ]
    x = torch.randn(ROWS, n_in, generator=generator)
    device = backend.torch_device()
    return [w.to(device) for w in weights], x.to(device)


def _error_bound(x: torch.Tensor, weights: list[torch.Tensor], sigmoid: bool, out_dtype: torch.dtype):
    """Elementwise bound ``[N, n_out]`` on ``|kernel − reference|`` (module docstring); float64 inputs."""
    act, e = x, torch.zeros_like(x)
    for w in weights:
        k = w.shape[1]
        gamma = (k + 1) * U32 / (1 - (k + 1) * U32)
        e = gamma * ((act.abs() + e) @ w.abs().t()) + e @ w.abs().t()
        act = torch.relu(act @ w.t())  # the reference's next input (unused after the last layer)
    y = mlp_forward_torch(x, weights, sigmoid)
    if sigmoid:
        e = 0.25 * e + 8 * U32
    if out_dtype == torch.float16:
        e = e + U16 * (y.abs() + e) + U32
    return e


@pytest.mark.parametrize("storage", [torch.float32, torch.float16])
@pytest.mark.parametrize("name", list(SHAPES))
def test_forward_matches_the_reference(device, name, storage):
    """Every variant (rows per thread, input layout and dtype, output dtype) lies within the float32 arithmetic's
    bound of the float64 reference on the stored weights."""
    shape = SHAPES[name]
    weights, x = _network(shape, seed=1)
    packed = pack_simt_mlp(weights, shape[4], storage)
    stored = [w.to(storage).double() for w in weights]
    for rows_per_thread, layout, x_dtype, out_dtype in VARIANTS:
        x_in = x.to(x_dtype)
        if layout == "feature-major":
            x_in = x_in.t().contiguous().t()
        y = simt_mlp_forward(x_in, packed, out_dtype, rows_per_thread)
        assert y.shape == (ROWS, shape[3]) and y.dtype == out_dtype
        reference = mlp_forward_torch(x_in.double(), stored, shape[4])
        bound = _error_bound(x_in.double(), stored, shape[4], out_dtype)
        excess = (y.double() - reference).abs() - bound
        assert float(excess.max()) <= 0.0, (rows_per_thread, layout, x_dtype, out_dtype, float(excess.max()))


def test_each_row_is_independent_of_the_batch(device):
    """No rows, one row and a tail shorter than a thread's rows give the rows of a full batch, bit for bit (each row's
    arithmetic is the same whatever shares its thread), and write nothing past the end."""
    shape = SHAPES["colour"]
    weights, x = _network(shape, seed=2)
    packed = pack_simt_mlp(weights, shape[4])
    full = simt_mlp_forward(x, packed, rows_per_thread=4)
    empty = simt_mlp_forward(x[:0], packed, rows_per_thread=4)
    assert empty.shape == (0, 3) and empty.dtype == torch.float32
    for count in (1, 5):
        torch.testing.assert_close(simt_mlp_forward(x[:count], packed, rows_per_thread=4), full[:count], rtol=0, atol=0)
    torch.testing.assert_close(simt_mlp_forward(x, packed, rows_per_thread=1), full, rtol=0, atol=0)


def test_sequential_is_packed_as_its_layers(device):
    """:func:`simt_mlp_weights_of` reads a ``Sequential``'s layers and sigmoid; the kernel then agrees with the
    ``Sequential`` itself to the bound's order (float32 reference, a loose 1e-5 on outputs of O(1))."""
    n_in, width, hidden, n_out, _ = SHAPES["colour"]
    torch.manual_seed(3)
    mlp = torch.nn.Sequential(
        torch.nn.Linear(n_in, width, bias=False),
        torch.nn.ReLU(),
        torch.nn.Linear(width, width, bias=False),
        torch.nn.ReLU(),
        torch.nn.Linear(width, n_out, bias=False),
        torch.nn.Sigmoid(),
    ).to(backend.torch_device())
    packed = simt_mlp_weights_of(mlp)
    assert packed.sigmoid and packed.hidden_layers == hidden and packed.dtype == torch.float32
    _, x = _network(SHAPES["colour"], seed=3)
    with torch.no_grad():
        torch.testing.assert_close(simt_mlp_forward(x, packed), mlp(x), rtol=0, atol=1e-5)


def test_bad_input_raises_clear_errors(device):
    weights, x = _network(SHAPES["density"], seed=4)
    packed = pack_simt_mlp(weights)
    with pytest.raises(ValueError, match=r"x must have shape \[N, 32\]"):
        simt_mlp_forward(x[:, :31], packed)
    with pytest.raises(TypeError, match="float16 or float32"):
        simt_mlp_forward(x.double(), packed)
    with pytest.raises(TypeError, match="must be a torch.Tensor"):
        simt_mlp_forward(x.tolist(), packed)
    with pytest.raises(ValueError, match="row-major or feature-major"):
        simt_mlp_forward(torch.cat([x, x], dim=1)[:, ::2], packed)
    with pytest.raises(ValueError, match="out_dtype"):
        simt_mlp_forward(x, packed, torch.float64)
    with pytest.raises(ValueError, match="rows_per_thread"):
        simt_mlp_forward(x, packed, rows_per_thread=3)
    with pytest.raises(ValueError, match="at least 2 linear layers"):
        pack_simt_mlp(weights[:1])
    with pytest.raises(ValueError, match="takes 64 inputs but layer 0 gives 63"):
        pack_simt_mlp([weights[0][:63], weights[1]])
    with pytest.raises(ValueError, match="same width"):
        pack_simt_mlp([weights[0], torch.ones(48, 64), torch.ones(3, 48)])
    with pytest.raises(ValueError, match="stored as float16 or float32"):
        pack_simt_mlp(weights, dtype=torch.bfloat16)
    with pytest.raises(ValueError, match="bias-free"):
        simt_mlp_weights_of(torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2)))
    with pytest.raises(ValueError, match="got \\['Linear', 'Sigmoid', 'Linear'\\]"):
        simt_mlp_weights_of(torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Sigmoid(), torch.nn.Linear(8, 2)))
