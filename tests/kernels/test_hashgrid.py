import math

import pytest
import torch

from kernels import backend
from kernels.hashgrid import (
    FRAMEWORKS,
    TABLE_DTYPES,
    HashGridConfig,
    HashGridEncoding,
    HashGridFunction,
    hashgrid_backward,
    hashgrid_forward,
    level_resolutions,
)
from kernels.reference.hashgrid import (
    cell_corners_torch,
    hashgrid_backward_torch,
    hashgrid_forward_torch,
    spatial_hash_torch,
)

# 6 levels from 4 to 128 cells: the coarse levels are dense in a 2^12-row table, the fine ones hashed.
LEVELS, BASE, MAX = 6, 4, 128


def _points(n: int, seed: int = 0, spread: float = 0.0) -> torch.Tensor:
    """``[n, 3]`` points in the unit cube, widened by ``spread`` on each side to test clamping."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=generator) * (1 + 2 * spread) - spread
    return x.to(backend.torch_device())


def _summation_bound(
    x: torch.Tensor, grad_out: torch.Tensor, resolutions: torch.Tensor, table_size: int
) -> torch.Tensor:
    """``[L, T, F]`` bound on how far two float32 backwards of ``grad_out`` may differ entry by entry.

    Each table entry is a sum of ``n`` terms ``w g`` (trilinear weight times output gradient), added atomically in an
    order no run repeats. Two orders of the same ``n`` terms differ by at most ``2 (n - 1) eps sum |w g|``; the
    weights, computed by each side in its own order of operations, add a few more roundings of each term (8 here).
    """
    levels = resolutions.shape[0]
    features = grad_out.shape[1] // levels
    counts = torch.zeros(levels, table_size, 1, device=x.device)
    for level, resolution in enumerate(resolutions.tolist()):
        rows, _ = cell_corners_torch(x, resolution, table_size)
        counts[level, :, 0] = torch.bincount(rows.reshape(-1), minlength=table_size).float()
    magnitude = hashgrid_backward_torch(x, grad_out.abs(), resolutions, table_size)
    assert magnitude.shape[-1] == features
    return (2 * counts + 8) * torch.finfo(torch.float32).eps * magnitude


def _assert_within(got: torch.Tensor, expected: torch.Tensor, bound: torch.Tensor) -> None:
    excess = (got - expected).abs() / bound.clamp_min(torch.finfo(torch.float32).tiny)
    worst = int(excess.argmax())
    assert excess.max() <= 1, (
        f"entry {worst}: |{got.flatten()[worst]:.9g} - {expected.flatten()[worst]:.9g}| exceeds the bound of "
        f"{bound.flatten()[worst]:.3g} by {float(excess.max()):.3g}x"
    )


def _table(levels: int, table_size: int, features: int, seed: int = 1) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(levels, table_size, features, generator=generator).to(backend.torch_device())


@pytest.mark.parametrize("framework", FRAMEWORKS)
@pytest.mark.parametrize(("table_size", "features"), [(1 << 12, 2), (3001, 3), (1 << 10, 1)])
def test_forward_matches_reference(device, framework, table_size, features):
    x = _points(4000, spread=0.1)
    table = _table(LEVELS, table_size, features)
    resolutions = level_resolutions(LEVELS, BASE, MAX)
    out = hashgrid_forward(x, table, resolutions, framework=framework)
    expected = hashgrid_forward_torch(x, table, resolutions)
    assert out.shape == (4000, LEVELS * features)
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("framework", FRAMEWORKS)
@pytest.mark.parametrize("feature_major", [False, True])
@pytest.mark.parametrize(("table_size", "features"), [(1 << 12, 2), (3001, 3), (1 << 11, 4)])
def test_backward_matches_reference_with_hash_collisions(device, framework, feature_major, table_size, features):
    x = _points(5000, seed=2)
    resolutions = level_resolutions(LEVELS, BASE, MAX)
    finest = int(resolutions[-1])
    assert (finest + 1) ** 3 > table_size, "the finest level must be hashed for this test"
    rows, _ = cell_corners_torch(x, finest, table_size)
    vertices = (x.clamp(0, 1) * finest).floor().clamp(0, finest - 1).long()[:, None] + torch.tensor(
        [[(c >> a) & 1 for a in range(3)] for c in range(8)], device=x.device
    )
    distinct_vertices = torch.unique(vertices.reshape(-1, 3), dim=0).shape[0]
    assert torch.unique(rows).numel() < distinct_vertices, "distinct vertices must collide in the table"

    grad_out = torch.randn(5000, LEVELS * features, device=x.device)
    if feature_major:  # the same values, laid out as a training step's gradient arrives (strides (1, N))
        grad_out = grad_out.t().contiguous().t()
        assert grad_out.stride() == (1, 5000)
    grad_table = hashgrid_backward(x, grad_out, resolutions, table_size, framework=framework)
    expected = hashgrid_backward_torch(x, grad_out, resolutions, table_size)
    assert grad_table.shape == (LEVELS, table_size, features)
    _assert_within(grad_table, expected, _summation_bound(x, grad_out, resolutions, table_size))


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_autograd_matches_reference_autograd(device, framework, monkeypatch):
    import kernels.hashgrid as module

    config = HashGridConfig(levels=LEVELS, features=2, log2_table_size=11, base_resolution=BASE, max_resolution=MAX)
    encoding = HashGridEncoding(config, framework=framework).to(backend.torch_device())
    table = encoding.table.detach().clone().requires_grad_(True)
    x = _points(3000, seed=3)
    weights = torch.randn(3000, config.output_dim, device=x.device)
    seen = {}

    def spy(x, grad_out, *args, **kwargs):
        seen["grad_out"] = grad_out.clone()
        return hashgrid_backward(x, grad_out, *args, **kwargs)

    monkeypatch.setattr(module, "hashgrid_backward", spy)
    out = encoding(x)
    (out * weights).square().sum().backward()
    expected = hashgrid_forward_torch(x, table, encoding.resolutions)
    grad_expected = torch.autograd.grad((expected * weights).square().sum(), expected, retain_graph=True)[0]
    expected.backward(grad_expected)

    torch.testing.assert_close(out.detach(), expected.detach(), rtol=1e-5, atol=1e-7)
    assert encoding.table.grad.abs().max() > 0
    # The output gradients differ as the two forwards' roundings do; that difference passes on through the weights.
    resolutions, table_size = encoding.resolutions, config.table_size
    bound = _summation_bound(x, grad_expected, resolutions, table_size) + hashgrid_backward_torch(
        x, (seen["grad_out"] - grad_expected).abs(), resolutions, table_size
    ) * (1 + 1e-5)
    _assert_within(encoding.table.grad, table.grad, bound)


def test_training_gradient_reaches_the_warp_kernel_feature_major_without_a_copy(device, monkeypatch):
    """The encoding feeds a bias-free Linear, as the NeRF's density MLP: autograd hands the encoding its gradient
    feature-major (Warp's forward returns a transposed view), and the backward passes that very tensor on."""
    import kernels.hashgrid as module

    config = HashGridConfig(levels=LEVELS, features=2, log2_table_size=11, base_resolution=BASE, max_resolution=MAX)
    encoding = HashGridEncoding(config, framework="warp").to(backend.torch_device())
    layer = torch.nn.Linear(config.output_dim, 16, bias=False).to(backend.torch_device())
    seen = {}

    def spy(x, grad_out, *args, **kwargs):
        seen["stride"] = grad_out.stride()
        seen["grad_out"] = grad_out.clone()
        return hashgrid_backward(x, grad_out, *args, **kwargs)

    monkeypatch.setattr(module, "hashgrid_backward", spy)
    x = _points(3000, seed=4)
    out = encoding(x)
    layer(out).relu().sum().backward()
    assert seen["stride"] == (1, 3000)

    # The reference backward of the very gradient the kernel was handed: the two differ in their sums' order only
    # (the Linear's own backward, a matrix product, may round another layout's gradient in another order).
    expected = hashgrid_backward_torch(x, seen["grad_out"].contiguous(), encoding.resolutions, config.table_size)
    assert expected.abs().max() > 1e-3
    bound = _summation_bound(x, seen["grad_out"], encoding.resolutions, config.table_size)
    _assert_within(encoding.table.grad, expected, bound)


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_dense_and_hashed_levels_index_the_documented_rows(device, framework):
    # A table whose row r holds the feature r turns the encoding at a grid vertex into the row index.
    resolution = 8
    vertices = torch.tensor([[1, 2, 3], [7, 0, 5], [4, 4, 4], [0, 0, 0]])
    x = (vertices.float() / resolution).to(backend.torch_device())
    resolutions = torch.tensor([resolution], dtype=torch.int32)
    side = resolution + 1
    for table_size, dense in ((side**3, True), (side**3 - 1, False)):
        table = torch.arange(table_size, dtype=torch.float32, device=x.device).reshape(1, table_size, 1)
        rows = hashgrid_forward(x, table, resolutions, framework=framework)[:, 0].round().long().cpu()
        if dense:
            expected = vertices[:, 0] + side * (vertices[:, 1] + side * vertices[:, 2])
        else:
            h = vertices[:, 0] ^ (vertices[:, 1] * 2654435761) ^ (vertices[:, 2] * 805459861)
            expected = (h % 2**32) % table_size
            assert torch.equal(spatial_hash_torch(vertices, table_size), expected)
        assert torch.equal(rows, expected), f"dense={dense}"


def test_spatial_hash_wraps_in_uint32():
    vertices = torch.tensor([[2047, 2048, 2047], [1, 1, 1]])
    expected = [((2047 ^ (2048 * 2654435761 % 2**32) ^ (2047 * 805459861 % 2**32)) % 2**32) % 2**19,
                (1 ^ 2654435761 ^ 805459861) % 2**19]
    assert spatial_hash_torch(vertices, 2**19).tolist() == expected


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_points_outside_the_cube_are_clamped(device, framework):
    x = _points(2000, seed=4, spread=0.5)
    assert (x < 0).any() and (x > 1).any()
    table = _table(LEVELS, 1 << 12, 2)
    resolutions = level_resolutions(LEVELS, BASE, MAX)
    outside = hashgrid_forward(x, table, resolutions, framework=framework)
    clamped = hashgrid_forward(x.clamp(0, 1), table, resolutions, framework=framework)
    torch.testing.assert_close(outside, clamped, rtol=0, atol=0)


def test_level_resolutions_follow_the_geometric_growth():
    resolutions = level_resolutions(16, 16, 2048).tolist()
    growth = math.exp(math.log(2048 / 16) / 15)
    assert resolutions[0] == 16 and resolutions[-1] == 2048
    assert all(abs(n - math.floor(16 * growth**level)) <= 1 for level, n in enumerate(resolutions))
    assert resolutions == sorted(set(resolutions))
    assert level_resolutions(1, 32, 64).tolist() == [32]
    with pytest.raises(ValueError, match="base_resolution <= max_resolution"):
        level_resolutions(4, 64, 32)


def test_encoding_module_shapes_and_initialisation(device):
    config = HashGridConfig(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32)
    encoding = HashGridEncoding(config).to(backend.torch_device())
    assert encoding.table.shape == (4, 1024, 2) and encoding.output_dim == 8
    assert encoding.table.abs().max() <= config.init_scale
    assert encoding.resolutions.tolist() == level_resolutions(4, 4, 32).tolist()
    out = encoding(_points(10))
    assert out.shape == (10, 8) and out.dtype == torch.float32
    with pytest.raises(ValueError, match="log2_table_size"):
        HashGridConfig(log2_table_size=40)


def test_empty_input_gives_empty_features_and_zero_gradient(device):
    x = torch.zeros(0, 3, device=backend.torch_device())
    table = _table(2, 64, 2)
    resolutions = level_resolutions(2, 2, 4)
    assert hashgrid_forward(x, table, resolutions).shape == (0, 4)
    grad = hashgrid_backward(x, torch.zeros(0, 4, device=x.device), resolutions, 64)
    assert grad.shape == (2, 64, 2) and not grad.any()


def test_bad_inputs_raise_clear_errors(device):
    dev = backend.torch_device()
    x = _points(8)
    table = _table(3, 64, 2)
    resolutions = level_resolutions(3, 2, 8)
    cases = [
        (lambda: hashgrid_forward(x.double(), table, resolutions), TypeError, "x must be a float32 tensor"),
        (lambda: hashgrid_forward(x[:, :2].contiguous(), table, resolutions), ValueError, r"x must be \[N, 3\]"),
        (lambda: hashgrid_forward(x, table.double(), resolutions), TypeError, "table must be a float32 or float16"),
        (lambda: hashgrid_forward(x, table.transpose(0, 1), resolutions), ValueError, "table must be contiguous"),
        (lambda: hashgrid_forward(x, table[0], resolutions), ValueError, r"table must be \[L, T, F\]"),
        (lambda: hashgrid_forward(x, table, resolutions[:2]), ValueError, "one entry per table level"),
        (lambda: hashgrid_forward(x, table, resolutions.float()), TypeError, "int32 or int64"),
        (lambda: hashgrid_forward(x, table, torch.tensor([2, 0, 8])), ValueError, ">= 1 cell"),
        (lambda: hashgrid_forward(x, table, resolutions, framework="cuda"), ValueError, "unknown framework"),
        (lambda: hashgrid_forward(x.t().contiguous().t(), table, resolutions), ValueError, "contiguous"),
        (lambda: hashgrid_backward(x, torch.zeros(8, 5, device=dev), resolutions, 64), ValueError, r"\[N, L \* F\]"),
        (lambda: hashgrid_backward(x, torch.zeros(8, 6, device=dev), resolutions, 0), ValueError, "table_size"),
        (
            lambda: hashgrid_backward(x, torch.zeros(8, 12, device=dev)[:, ::2], resolutions, 64),
            ValueError,
            r"row-major \[N, L \* F\] or feature-major",
        ),
    ]
    for call, error, message in cases:
        with pytest.raises(error, match=message):
            call()


def test_positions_requiring_a_gradient_are_refused(device):
    encoding = HashGridEncoding(HashGridConfig(levels=2, log2_table_size=8, base_resolution=2, max_resolution=4))
    encoding = encoding.to(backend.torch_device())
    x = _points(4).requires_grad_(True)
    with pytest.raises(ValueError, match=r"x\.detach\(\)"):
        encoding(x)
    assert HashGridFunction.apply(x.detach(), encoding.table, encoding.resolutions).shape == (4, 4)


# -- float16 table storage ---------------------------------------------------------------------------------------------

_HALF_ULP = 2.0**-11
"""Rounding to float16 moves a normal value by at most this much relative (half its 2^-10 spacing)."""
_HALF_SUBNORMAL_STEP = 2.0**-25
"""... and a value below float16's smallest normal (2^-14) by at most half the subnormal spacing 2^-24, absolute."""


def _float32_interpolation_bound(x, table, resolutions) -> torch.Tensor:
    """``[N, L F]`` bound on how far two float32 evaluations of the same interpolation may differ: each side rounds
    every weight (3 factors) and the sum of 8 weighted terms, about 12 roundings of ``sum_c w_c |t_c|`` per side."""
    return 24 * torch.finfo(torch.float32).eps * hashgrid_forward_torch(x, table.abs().float(), resolutions)


@pytest.mark.parametrize("framework", FRAMEWORKS)
@pytest.mark.parametrize("features", [2, 3])  # feature pairs as 32-bit words (Warp) / one float16 at a time
def test_float16_table_forward_matches_the_float32_reference_within_its_rounding(device, framework, features):
    x = _points(4000, seed=5, spread=0.1)
    table = _table(LEVELS, 3001, features, seed=6) * 0.5
    table[0, :40] *= 1e-4  # some entries below float16's smallest normal, 2^-14
    resolutions = level_resolutions(LEVELS, BASE, MAX)
    half = table.half()
    out = hashgrid_forward(x, half, resolutions, framework=framework)
    assert out.dtype == torch.float32 and out.shape == (4000, LEVELS * features)

    # The kernel interpolates the float16 values in float32: the reference of the rounded table, to float32 rounding.
    rounded = half.float()
    _assert_within(out, hashgrid_forward_torch(x, rounded, resolutions),
                   _float32_interpolation_bound(x, rounded, resolutions))
    # Against the float32 table: each stored value moved by at most 2^-11 relative (or 2^-25 absolute below 2^-14),
    # and the trilinear weights are non-negative and sum to 1, so the features move by at most the weighted sum.
    assert (rounded - table).abs().le(torch.maximum(_HALF_ULP * table.abs(), torch.tensor(_HALF_SUBNORMAL_STEP,
            device=table.device))).all(), "float16 rounding exceeds half an ulp"
    rounding = hashgrid_forward_torch(x, _HALF_ULP * table.abs() + _HALF_SUBNORMAL_STEP, resolutions)
    expected = hashgrid_forward_torch(x, table, resolutions)
    _assert_within(out, expected, rounding + _float32_interpolation_bound(x, table, resolutions))
    assert (out - expected).abs().max() > 0, "the float16 table was read as float16"


@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_float16_encoding_trains_a_float32_master_table(device, framework):
    """With ``table_dtype="float16"`` the kernels read a float16 copy, and the float32 parameter gets the very
    gradient the float32 encoding gives it (the backward never reads the table)."""
    config = HashGridConfig(levels=LEVELS, features=2, log2_table_size=11, base_resolution=BASE, max_resolution=MAX,
                            table_dtype="float16", init_scale=0.5)
    encoding = HashGridEncoding(config, framework=framework).to(backend.torch_device())
    assert encoding.table.dtype == torch.float32 and encoding.read_table().dtype == torch.float16
    x = _points(3000, seed=7)
    grad_out = torch.randn(3000, config.output_dim, generator=torch.Generator().manual_seed(8)).to(x.device)
    out = encoding(x)
    out.backward(grad_out)

    rounded = encoding.table.detach().half().float()
    _assert_within(out.detach(), hashgrid_forward_torch(x, rounded, encoding.resolutions),
                   _float32_interpolation_bound(x, rounded, encoding.resolutions))
    grad = encoding.table.grad
    assert grad.dtype == torch.float32 and grad.shape == encoding.table.shape
    expected = hashgrid_backward_torch(x, grad_out, encoding.resolutions, config.table_size)
    assert expected.abs().max() > 1e-3
    _assert_within(grad, expected, _summation_bound(x, grad_out, encoding.resolutions, config.table_size))


def test_float16_copy_is_made_again_exactly_when_the_table_changes(device):
    """The copy's own version counter counts its refreshes: one per change of the master table (an optimiser step,
    ``load_state_dict``; a fused optimiser step or a write through ``.data``, which torch does not count, once announced
    by ``mark_table_changed``), none between changes."""
    config = HashGridConfig(levels=2, features=2, log2_table_size=8, base_resolution=2, max_resolution=8,
                            table_dtype="float16")
    encoding = HashGridEncoding(config).to(backend.torch_device())
    x = _points(64, seed=9)
    copy = encoding.read_table()
    made = copy._version

    def refreshes() -> int:
        nonlocal made
        current = encoding.read_table()
        assert current is copy, "the copy is refreshed in place, not reallocated"
        assert torch.equal(current, encoding.table.detach().half()), "the copy holds the master table, rounded"
        count, made = current._version - made, current._version
        return count

    encoding(x).sum().backward()
    assert refreshes() == 0, "encoding and differentiating leave the table"
    optimizer = torch.optim.Adam(encoding.parameters(), lr=1e-2)
    optimizer.step()
    assert refreshes() == 1 and refreshes() == 0
    encoding(x)
    assert refreshes() == 0
    encoding.load_state_dict({"table": torch.full_like(encoding.table, 0.25), "resolutions": encoding.resolutions})
    assert refreshes() == 1
    encoding.table.data.mul_(2.0)  # unseen by the version counter ...
    encoding.mark_table_changed()  # ... so announced
    assert refreshes() == 1 and float(copy.max()) == 0.5
    optimizer.step()
    encoding.mark_table_changed()  # a change seen twice is copied once
    assert refreshes() == 1
    fused = torch.optim.Adam(encoding.parameters(), lr=1e-2, fused=True)
    fused.step()  # the version counter does not move ...
    stale = encoding.read_table()
    assert stale._version == made and not torch.equal(stale, encoding.table.detach().half()), "fused steps go unseen"
    encoding.mark_table_changed()  # ... so the step is announced, as NGPField.mark_weights_changed does in training
    assert refreshes() == 1


def test_table_dtype_is_validated_and_float32_by_default():
    assert HashGridConfig().table_dtype == "float32" and set(TABLE_DTYPES) == {"float32", "float16"}
    with pytest.raises(ValueError, match=r"table_dtype must be one of 'float32', 'float16', got 'bfloat16'"):
        HashGridConfig(table_dtype="bfloat16")
