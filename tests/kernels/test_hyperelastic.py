import pytest
import torch

from kernels import backend
from kernels.hyperelastic import MaterialModel, material_response
from kernels.reference import hyperelastic as reference

MODELS = list(MaterialModel)


def _random_F(count: int, spread: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    F = torch.eye(3, dtype=torch.float64) + spread * torch.randn(count, 3, 3, generator=g, dtype=torch.float64)
    flip = torch.det(F) < 0  # keep J > 0 so that every model is finite
    F[flip, :, 0] *= -1
    return F


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name.lower())
@pytest.mark.parametrize("project", [False, True], ids=["exact", "projected"])
def test_kernel_matches_autograd_reference(device, model, project):
    F = _random_F(24, 0.3)
    mu, lam = torch.tensor(3.0e4, dtype=torch.float64), torch.tensor(7.0e4, dtype=torch.float64)
    psi, P, A = material_response(F.to(backend.torch_device()), mu, lam, model, project)
    psi_ref, P_ref, A_ref = reference.material_response(F, mu, lam, model, project)
    torch.testing.assert_close(psi.cpu(), psi_ref, rtol=1e-9, atol=1e-6)
    torch.testing.assert_close(P.cpu(), P_ref, rtol=1e-8, atol=1e-5)
    torch.testing.assert_close(A.cpu(), A_ref, rtol=1e-6, atol=1e-4 * mu.item())


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name.lower())
def test_stress_and_hessian_match_finite_differences(device, model):
    F = _random_F(6, 0.2, seed=1).to(backend.torch_device())
    mu, lam = torch.tensor(1.0, dtype=torch.float64), torch.tensor(2.5, dtype=torch.float64)
    psi, P, A = material_response(F, mu, lam, model, project=False)
    h = 1e-6
    for c in range(9):
        dF = torch.zeros(9, dtype=torch.float64, device=F.device)
        dF[c] = h
        plus = material_response(F + dF.view(3, 3), mu, lam, model, project=False)
        minus = material_response(F - dF.view(3, 3), mu, lam, model, project=False)
        torch.testing.assert_close((plus[0] - minus[0]) / (2 * h), P.reshape(-1, 9)[:, c], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close((plus[1] - minus[1]).reshape(-1, 9) / (2 * h), A[:, :, c], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name.lower())
def test_rest_state_is_stress_free_and_projection_is_psd(device, model):
    count = 8
    F = torch.eye(3, dtype=torch.float64).repeat(count, 1, 1)
    F[1:] = _random_F(count - 1, 0.6, seed=2)
    F = F.to(backend.torch_device())
    mu, lam = torch.tensor(1.0, dtype=torch.float64), torch.tensor(4.0, dtype=torch.float64)
    psi, P, A = material_response(F, mu, lam, model, project=True)
    assert abs(psi[0].item()) < 1e-12 and P[0].abs().max().item() < 1e-12
    assert torch.linalg.eigvalsh(A).min().item() > -1e-9
    # Small strain: the Hessian at F = I is linear elasticity's (ARAP has no λ term).
    l = 0.0 if model == MaterialModel.ARAP else 4.0
    expected = torch.zeros(3, 3, 3, 3, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    expected += l * torch.einsum("ab,cd->abcd", eye, eye)
    expected += 1.0 * (torch.einsum("ac,bd->abcd", eye, eye) + torch.einsum("ad,bc->abcd", eye, eye))
    torch.testing.assert_close(A[0].cpu(), expected.reshape(9, 9), rtol=1e-9, atol=1e-9)


def test_inverted_neo_hookean_point_has_infinite_energy(device):
    F = torch.diag(torch.tensor([1.0, 1.0, -0.5], dtype=torch.float64)).unsqueeze(0).to(backend.torch_device())
    psi, _, _ = material_response(F, torch.tensor(1.0, dtype=torch.float64), torch.tensor(1.0, dtype=torch.float64),
                                  MaterialModel.NEO_HOOKEAN)
    assert torch.isinf(psi).all()


def test_rejects_float32(device):
    with pytest.raises(ValueError, match="float64"):
        material_response(torch.eye(3).unsqueeze(0), torch.tensor(1.0), torch.tensor(1.0), MaterialModel.ARAP)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name.lower())
def test_batched_reference_matches_kernel(device, model):
    F = _random_F(16, 0.25, seed=4)
    mu, lam = torch.tensor(2.0, dtype=torch.float64), torch.tensor(3.0, dtype=torch.float64)
    expected = material_response(F.to(backend.torch_device()), mu, lam, model, project=True)
    for got, want in zip(reference.material_response_batched(F, mu, lam, model, project=True), expected, strict=True):
        torch.testing.assert_close(got, want.cpu(), rtol=1e-7, atol=1e-7)
