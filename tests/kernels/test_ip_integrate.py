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
    by_warp = integrator.sum_blocks(blocks, warp_kernel=True)
    by_torch = integrator.sum_blocks(blocks, warp_kernel=False)
    torch.testing.assert_close(by_warp, by_torch, rtol=1e-13, atol=1e-13)
    assert by_warp.abs().sum() > 0


@pytest.mark.parametrize("assembly", ASSEMBLIES)
@pytest.mark.parametrize("project", [True, False], ids=["projected", "unprojected"])
def test_float32_products_give_the_float64_hessian_to_single_precision(device, assembly, project):
    """Block products in float32: the Hessian comes back float64, within 1e-6 (relative, Frobenius) of the float64
    products' and symmetric to the same degree; energy and gradient are the float64 ones (bit for bit on the CPU)."""
    index, shape_grad, weight, q, n = _problem(seed=7, K=9, S=6, n=11)
    dev = backend.torch_device()
    args = (index.to(dev), shape_grad.to(dev), weight.to(dev), n, 2.0, 5.0, MaterialModel.NEO_HOOKEAN)
    double = IPIntegrator(*args, assembly=assembly).evaluate(q.to(dev), project=project)
    single = IPIntegrator(*args, assembly=assembly, product_dtype=torch.float32).evaluate(q.to(dev), project=project)
    assert single.hessian.dtype == torch.float64
    scale = double.hessian.norm()
    assert scale > 0
    assert (single.hessian - double.hessian).norm() < 1e-6 * scale
    assert (single.hessian - single.hessian.T).norm() < 1e-6 * scale
    assert torch.equal(single.energy, double.energy)
    if dev.type == "cpu":
        assert torch.equal(single.gradient, double.gradient)
    else:  # the per-IP gradient's index_add_ sums in the order its CUDA atomics land, from call to call
        torch.testing.assert_close(single.gradient, double.gradient, rtol=1e-12, atol=1e-12)


def test_unknown_product_dtype_is_refused(device):
    index, shape_grad, weight, _, n = _problem()
    with pytest.raises(ValueError, match="product_dtype .* use torch.float64 or torch.float32"):
        IPIntegrator(index, shape_grad, weight, n, 1.0, 1.0, MaterialModel.ARAP, product_dtype=torch.float16)


def test_float32_blocks_are_summed_in_float64(device):
    """float32 per-IP blocks are summed in float64 by the Warp kernel and by torch alike: the sum of many blocks
    keeps the contributions a float32 sum would round away."""
    index, shape_grad, weight, _, n = _problem(seed=7, K=9, S=6, n=11)
    dev = backend.torch_device()
    integrator = IPIntegrator(index.to(dev), shape_grad.to(dev), weight.to(dev), n, 2.0, 5.0,
                              MaterialModel.NEO_HOOKEAN, assembly="per_ip", product_dtype=torch.float32)
    K, S = index.shape
    blocks = torch.randn(K * S * S, 9, generator=torch.Generator().manual_seed(2), dtype=torch.float32).to(dev)
    blocks[::2] *= 1e8  # large and small contributions meet in the same global blocks
    exact = integrator.sum_blocks(blocks.to(torch.float64), warp_kernel=False)
    for warp_kernel in (True, False):
        summed = integrator.sum_blocks(blocks, warp_kernel=warp_kernel)
        assert summed.dtype == torch.float64
        torch.testing.assert_close(summed, exact, rtol=1e-13, atol=1e-13)
