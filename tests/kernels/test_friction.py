"""IPC lagged friction kernel against its torch reference, finite differences and closed forms."""

import pytest
import torch

from kernels import backend
from kernels.friction import friction_potential
from kernels.reference import friction as ref

F64 = torch.float64
EPS = 1e-3  # ε_v Δt, m


def _dev(t: torch.Tensor) -> torch.Tensor:
    return t.to(backend.torch_device())


def _projectors(k: int, g: torch.Generator) -> torch.Tensor:
    """``[k, 3, 3]`` tangent projectors ``I − n nᵀ`` of random unit normals."""
    n = torch.nn.functional.normalize(torch.randn(k, 3, dtype=F64, generator=g), dim=1)
    return torch.eye(3, dtype=F64) - n[:, :, None] * n[:, None, :]


def _contacts(seed: int = 0, k: int = 240, still: int = 8):
    """Random contacts whose tangential slip ``y`` spans ``(0, 3ε)``; the first ``still`` have ``y = 0`` exactly.

    Weights are point-triangle-like, ``(1, −a, −b, −c)`` with ``a + b + c = 1``, as the simulator's contacts are.
    Each contact has its own four vertices (so its slip can be set), stored in a shuffled order.
    """
    g = torch.Generator().manual_seed(seed)
    bary = torch.rand(k, 3, dtype=F64, generator=g) + 0.1
    weight = torch.cat([torch.ones(k, 1, dtype=F64), -bary / bary.sum(1, keepdim=True)], dim=1)
    projector = _projectors(k, g)
    force = 0.1 + torch.rand(k, dtype=F64, generator=g)
    direction = torch.randn(k, 4, 3, dtype=F64, generator=g)
    slip = torch.linalg.norm(torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * direction).sum(1)), dim=1)
    target = EPS * torch.linspace(0.02, 3.0, k, dtype=F64)[torch.randperm(k, generator=g)]
    target[:still] = 0.0
    order = torch.randperm(4 * k, generator=g)
    displacement = torch.empty(4 * k, 3, dtype=F64)
    displacement[order] = (direction * (target / slip)[:, None, None]).reshape(-1, 3)
    return displacement, order.reshape(k, 4), weight, projector, force


def _relative_error(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got.cpu() - want.cpu()).abs().max() / want.cpu().abs().max())


@pytest.mark.parametrize("hessian", [True, False])
@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
def test_matches_the_torch_reference(device, hessian, index_dtype):
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts())
    index = index.to(index_dtype)
    energy, grad, hess = friction_potential(displacement, index, weight, projector, force, EPS, hessian)
    want = ref.friction_potential(displacement, index, weight, projector, force, EPS, hessian)

    slip = torch.linalg.norm(
        torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * displacement[index.long()]).sum(1)), dim=1
    )
    assert int((slip == 0).sum()) == 8 and int((slip > EPS).sum()) > 60 and int((slip < EPS).sum()) > 60
    assert energy.shape == (240,) and grad.shape == (240, 4, 3)
    assert energy.dtype == grad.dtype == F64 and energy.device == displacement.device
    assert _relative_error(energy, want[0]) < 1e-12
    assert _relative_error(grad, want[1]) < 1e-12
    if hessian:
        assert hess.shape == (240, 12, 12)
        assert bool(torch.isfinite(hess).all())
        assert _relative_error(hess, want[2]) < 1e-12
    else:
        assert hess is None


def test_zero_slip_closed_form(device):
    """At ``y = 0``: energy ``μλ ε/3``, zero gradient, Hessian ``w_i w_j μλ (2/ε) P`` (the ``u uᵀ`` term vanishes)."""
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts(seed=3, k=8, still=8))
    energy, grad, hess = friction_potential(displacement, index, weight, projector, force, EPS, True)
    torch.testing.assert_close(energy, force * EPS / 3.0, rtol=1e-14, atol=0.0)
    assert bool((grad == 0).all())
    blocks = (2.0 / EPS) * force[:, None, None, None, None] * weight[:, :, None, None, None]
    blocks = blocks * weight[:, None, :, None, None] * projector[:, None, None]
    torch.testing.assert_close(hess, blocks.permute(0, 1, 3, 2, 4).reshape(-1, 12, 12), rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize("hessian", [True, False])
def test_no_contacts(device, hessian):
    d = backend.torch_device()
    energy, grad, hess = friction_potential(
        torch.zeros(5, 3, dtype=F64, device=d),
        torch.zeros(0, 4, dtype=torch.int64, device=d),
        torch.zeros(0, 4, dtype=F64, device=d),
        torch.zeros(0, 3, 3, dtype=F64, device=d),
        torch.zeros(0, dtype=F64, device=d),
        EPS,
        hessian,
    )
    assert energy.shape == (0,) and grad.shape == (0, 4, 3)
    assert hess is None if not hessian else hess.shape == (0, 12, 12)


def test_non_contiguous_inputs(device):
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts(seed=5, k=32))
    want = friction_potential(displacement, index, weight, projector, force, EPS, True)
    got = friction_potential(
        displacement.T.contiguous().T, index.T.contiguous().T, weight.T.contiguous().T, projector, force, EPS, True
    )
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)


def test_finite_differences_and_psd(device):
    """Central differences of the kernel's own energy and gradient, on contacts below and above ``ε``."""
    g = torch.Generator().manual_seed(7)
    k = 6
    projector = _projectors(k, g)
    weight = torch.cat([torch.ones(k, 1, dtype=F64), -torch.softmax(torch.randn(k, 3, dtype=F64, generator=g), 1)], 1)
    force = 0.5 + torch.rand(k, dtype=F64, generator=g)
    index = torch.arange(4 * k).reshape(k, 4)
    direction = torch.randn(k, 4, 3, dtype=F64, generator=g)
    slip = torch.linalg.norm(torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * direction).sum(1)), dim=1)
    target = EPS * torch.tensor([0.2, 0.5, 0.8, 1.3, 2.0, 4.0], dtype=F64)  # clear of y = 0 and of y = ε
    displacement = (direction * (target / slip)[:, None, None]).reshape(-1, 3)
    args = [_dev(t) for t in (index, weight, projector, force)]

    def evaluate(x: torch.Tensor):
        return friction_potential(_dev(x), *args, EPS, True)

    _, grad, hess = (t.cpu() for t in evaluate(displacement))
    h = 1e-8
    fd_grad = torch.empty(k, 12, dtype=F64)
    fd_hess = torch.empty(k, 12, 12, dtype=F64)
    for column in range(12):
        plus, minus = displacement.clone().reshape(k, 12), displacement.clone().reshape(k, 12)
        plus[:, column] += h
        minus[:, column] -= h
        e_plus, g_plus, _ = evaluate(plus.reshape(-1, 3))
        e_minus, g_minus, _ = evaluate(minus.reshape(-1, 3))
        fd_grad[:, column] = ((e_plus - e_minus) / (2 * h)).cpu()
        fd_hess[:, :, column] = ((g_plus - g_minus).reshape(k, 12) / (2 * h)).cpu()
    torch.testing.assert_close(grad.reshape(k, 12), fd_grad, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(hess, fd_hess, rtol=1e-6, atol=1e-6 * float(hess.abs().max()))
    torch.testing.assert_close(hess, hess.transpose(1, 2), rtol=0.0, atol=1e-12 * float(hess.abs().max()))
    assert float(torch.linalg.eigvalsh(hess).min()) > -1e-9 * float(hess.abs().max())


def _valid(k: int = 3, n: int = 6) -> dict:
    d = backend.torch_device()
    return {
        "displacement": torch.zeros(n, 3, dtype=F64, device=d),
        "index": torch.zeros(k, 4, dtype=torch.int64, device=d),
        "weight": torch.zeros(k, 4, dtype=F64, device=d),
        "projector": torch.zeros(k, 3, 3, dtype=F64, device=d),
        "force": torch.zeros(k, dtype=F64, device=d),
        "eps": EPS,
        "hessian": True,
    }


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("displacement", lambda a: a.float(), r"displacement must be a float64 \[N, 3\].*to\(torch.float64\)"),
        ("displacement", lambda a: a[:, :2], r"displacement must have shape \[N, 3\]"),
        ("index", lambda a: a.double(), r"index must be an int32 or int64 \[K, 4\]"),
        ("index", lambda a: a[:, :3], r"index must be an int32 or int64 \[K, 4\]"),
        ("weight", lambda a: a[:2], r"weight must have shape \[K, 4\], here \[3, 4\], got \[2, 4\]"),
        ("weight", lambda a: a.float(), r"weight must be a float64"),
        ("projector", lambda a: a.reshape(3, 9), r"projector must have shape \[K, 3, 3\]"),
        ("force", lambda a: a[:, None], r"force must have shape \[K\]"),
        ("force", lambda a: a.to(torch.int64), r"force must be a float64"),
        ("eps", lambda a: 0.0, r"eps \(0.0\) must be a positive finite length"),
        ("eps", lambda a: float("nan"), r"eps \(nan\) must be a positive finite length"),
    ],
)
def test_bad_inputs(device, name, make, message):
    args = _valid()
    args[name] = make(args[name])
    with pytest.raises(ValueError, match=message):
        friction_potential(**args)


def test_inputs_on_another_device(device):
    args = _valid()
    args["force"] = torch.zeros(3, dtype=F64, device="meta")
    with pytest.raises(ValueError, match=r"force is on meta but displacement is on .*move it with"):
        friction_potential(**args)
