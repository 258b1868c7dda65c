import pytest
import torch

from kernels import backend
from kernels.hyperelastic import MaterialModel
from kernels.ip_integrate import IPIntegrator
from kernels.reference import ip_integrate as reference


def _problem(seed=0, K=4, G=3, S=5, n=7):
    g = torch.Generator().manual_seed(seed)
    index = torch.stack([torch.randperm(n, generator=g)[:S] for _ in range(K)])
    index[0, -2:] = -1  # padding
    shape_grad = 0.5 * torch.randn(K, G, S, 3, generator=g, dtype=torch.float64)
    weight = 0.1 + torch.rand(K, G, generator=g, dtype=torch.float64)
    q = 0.05 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    return index, shape_grad, weight, q, n


ASSEMBLIES = ["dense", "per_ip"]


@pytest.mark.parametrize("assembly", ASSEMBLIES)
@pytest.mark.parametrize("model", list(MaterialModel), ids=lambda m: m.name.lower())
def test_energy_gradient_hessian_match_autograd(device, model, assembly):
    index, shape_grad, weight, q, n = _problem()
    mu, lam = 2.0, 5.0
    dev = backend.torch_device()
    integrator = IPIntegrator(index.to(dev), shape_grad.to(dev), weight.to(dev), n, mu, lam, model, assembly=assembly)
    result = integrator.evaluate(q.to(dev), project=False)
    energy = reference.ip_energy(q, index, shape_grad, weight, mu, lam, model)
    torch.testing.assert_close(result.energy.cpu(), energy, rtol=1e-10, atol=1e-12)
    gradient = reference.ip_gradient(q, index, shape_grad, weight, mu, lam, model)
    torch.testing.assert_close(result.gradient.cpu(), gradient, rtol=1e-8, atol=1e-10)
    H = reference.ip_hessian(q, index, shape_grad, weight, mu, lam, model, project=False)
    torch.testing.assert_close(result.hessian.cpu(), H, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("assembly", ASSEMBLIES)
@pytest.mark.parametrize("model", [MaterialModel.NEO_HOOKEAN, MaterialModel.ARAP], ids=["neo_hookean", "arap"])
def test_projected_hessian_is_psd_and_matches_reference(device, model, assembly):
    index, shape_grad, weight, q, n = _problem(seed=3)
    q = 8 * q  # large strains: indefinite unprojected Hessian
    dev = backend.torch_device()
    integrator = IPIntegrator(index.to(dev), shape_grad.to(dev), weight.to(dev), n, 1.0, 3.0, model, assembly=assembly)
    result = integrator.evaluate(q.to(dev), project=True)
    assert result.min_det.item() > 0
    H = reference.ip_hessian(q, index, shape_grad, weight, 1.0, 3.0, model, project=True)
    torch.testing.assert_close(result.hessian.cpu(), H, rtol=1e-6, atol=1e-8)
    assert torch.linalg.eigvalsh(result.hessian.cpu()).min().item() > -1e-9


@pytest.mark.parametrize("assembly", ASSEMBLIES)
def test_gradient_matches_finite_differences_of_energy(device, assembly):
    index, shape_grad, weight, q, n = _problem(seed=5)
    dev = backend.torch_device()
    integrator = IPIntegrator(
        index.to(dev), shape_grad.to(dev), weight.to(dev), n, 1.0, 1.0, MaterialModel.STVK, assembly=assembly
    )
    q = q.to(dev)
    grad = integrator.evaluate(q, hessian=False).gradient
    h = 1e-6
    for s, a in [(0, 0), (3, 2), (6, 1)]:
        dq = torch.zeros_like(q)
        dq[s, a] = h
        fd = (integrator.evaluate(q + dq, gradient=False, hessian=False).energy
              - integrator.evaluate(q - dq, gradient=False, hessian=False).energy) / (2 * h)
        assert fd.item() == pytest.approx(grad[s, a].item(), rel=1e-6, abs=1e-9)


def test_mismatched_shapes_are_refused(device):
    index, shape_grad, weight, _, n = _problem()
    with pytest.raises(ValueError, match="disagree"):
        IPIntegrator(index[:, :3], shape_grad, weight, n, 1.0, 1.0, MaterialModel.ARAP)


def test_unknown_assembly_is_refused(device):
    index, shape_grad, weight, _, n = _problem()
    with pytest.raises(ValueError, match="unknown assembly"):
        IPIntegrator(index, shape_grad, weight, n, 1.0, 1.0, MaterialModel.ARAP, assembly="sparse")


def test_block_sums_by_the_warp_kernel_match_torch(device):
    """The per-IP blocks summed into the dense Hessian by the Warp kernel (CUDA's path) and by torch's segmented sum
    (the CPU's path) agree, whatever the device runs them."""
    index, shape_grad, weight, q, n = _problem(seed=7, K=9, S=6, n=11)
    dev = backend.torch_device()
    integrator = IPIntegrator(index.to(dev), shape_grad.to(dev), weight.to(dev), n, 2.0, 5.0,
                              MaterialModel.NEO_HOOKEAN, assembly="per_ip")
    K, S = index.shape
    blocks = torch.randn(K * S * S, 9, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(dev)
    by_warp = integrator._sum_blocks(blocks, warp_kernel=True)
    by_torch = integrator._sum_blocks(blocks, warp_kernel=False)
    torch.testing.assert_close(by_warp, by_torch, rtol=1e-13, atol=1e-13)
    assert by_warp.abs().sum() > 0
