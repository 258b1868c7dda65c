"""Quadratic ray warping (PIE-NeRF Eq. 19–21): the kernel inverts known quadratic deformations and matches
the torch reference."""

from __future__ import annotations

import pytest
import torch

import kernels.warp_rays as warp_rays_module
from kernels import backend
from kernels.backend import FRAMEWORKS
from kernels.reference.warp_rays import quadratic_map_torch, warp_to_rest_torch
from kernels.spatial_hash import SpatialHash
from kernels.warp_rays import warp_round, warp_to_rest

SPACING = 0.05  # metres between IPs of the synthetic sets below


def _ips(count: int, seed: int, strain: float = 0.3, curvature: float = 3.0):
    """IPs on a jittered lattice with random F (≈ I + strain) and ∇F (per metre, symmetric in b, c)."""
    g = torch.Generator().manual_seed(seed)
    side = round(count ** (1 / 3))
    axis = torch.arange(side, dtype=torch.float64) * SPACING
    rest = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    rest = rest + 0.1 * SPACING * torch.rand(rest.shape, generator=g, dtype=torch.float64)
    K = rest.shape[0]
    F = torch.eye(3, dtype=torch.float64) + strain * (torch.rand(K, 3, 3, generator=g, dtype=torch.float64) - 0.5)
    grad_F = curvature * (torch.rand(K, 3, 3, 3, generator=g, dtype=torch.float64) - 0.5)
    grad_F = 0.5 * (grad_F + grad_F.transpose(-1, -2))
    displacement = 0.02 * torch.randn(K, 3, generator=g, dtype=torch.float64)
    return rest, rest + displacement, displacement, F, grad_F


def _to_device(*tensors):
    return [t.to(device=backend.torch_device(), dtype=torch.float32).contiguous() for t in tensors]


def test_newton_inverts_a_known_quadratic_deformation(device):
    """x̃ = x̃_k + F_k d + ½∇F_k:dd for random d near x_k; one neighbour, so the warp must return x exactly."""
    rest, deformed, displacement, F, grad_F = _ips(27, seed=0)
    K = rest.shape[0]
    g = torch.Generator().manual_seed(1)
    per_ip = 40
    k = torch.arange(K).repeat_interleave(per_ip)
    d = 0.6 * SPACING * (torch.rand(k.shape[0], 3, generator=g, dtype=torch.float64) - 0.5)
    x = rest[k] + d
    x_tilde = deformed[k] + quadratic_map_torch(d, F[k], grad_F[k])
    neighbours = k[:, None].int()
    distances = (x_tilde - deformed[k]).norm(dim=1, keepdim=True)
    cutoff = torch.full((K,), 10.0 * SPACING, dtype=torch.float64)

    args = _to_device(x_tilde, distances, deformed, displacement, F, grad_F, cutoff)
    neighbours_d = neighbours.to(backend.torch_device())
    out = warp_to_rest(args[0], neighbours_d, *args[1:])
    ref = warp_to_rest_torch(x_tilde, neighbours, distances, deformed, displacement, F, grad_F, cutoff)

    assert bool(out.valid.all()) and not bool(out.fallback.any())
    error = (out.rest.double().cpu() - x).norm(dim=1).max() / SPACING
    assert error < 1e-4, f"kernel recovers x to {error:.2e} of the IP spacing"
    assert (ref[0] - x).norm(dim=1).max() / SPACING < 1e-9
    assert int(out.iterations.max()) <= 6
    assert torch.equal(out.iterations.cpu(), ref[2])

    linear = warp_to_rest(args[0], neighbours_d, *args[1:], quadratic=False)
    linear_error = (linear.rest.double().cpu() - x).norm(dim=1).max() / SPACING
    assert linear_error > 100 * error, "the first-order warp ignores ∇F and must be visibly worse"
    assert bool((linear.iterations == 1).all())


def test_kernel_matches_reference_with_three_neighbours(device):
    """Inverse-distance blending of three IPs' Newton solutions, cutoff and -1 padding, kernel vs torch."""
    rest, deformed, displacement, F, grad_F = _ips(64, seed=2)
    g = torch.Generator().manual_seed(3)
    lo, hi = deformed.amin(0) - SPACING, deformed.amax(0) + SPACING
    x_tilde = lo + (hi - lo) * torch.rand(3000, 3, generator=g, dtype=torch.float64)
    distance_all = torch.cdist(x_tilde, deformed)
    distances, neighbours = distance_all.topk(3, largest=False)
    neighbours = neighbours.int()
    neighbours[::7, 2] = -1  # a padded slot, as the kNN returns near the edge of its search
    distances[::7, 2] = float("inf")
    cutoff = torch.full((rest.shape[0],), 0.6 * SPACING, dtype=torch.float64)

    args = _to_device(x_tilde, distances, deformed, displacement, F, grad_F, cutoff)
    neighbours_d = neighbours.to(backend.torch_device())
    for quadratic in (True, False):
        out = warp_to_rest(args[0], neighbours_d, *args[1:], quadratic=quadratic)
        ref_rest, ref_valid, ref_used, _ = warp_to_rest_torch(
            x_tilde, neighbours, distances, deformed, displacement, F, grad_F, cutoff, quadratic=quadratic
        )
        assert torch.equal(out.valid.cpu(), ref_valid)
        assert 0 < int(ref_valid.sum()) < x_tilde.shape[0], "the cutoff must split the samples"
        assert torch.allclose(out.rest.double().cpu(), ref_rest, atol=1e-5 * SPACING, rtol=0)
        assert torch.equal(out.rest.cpu()[~ref_valid], args[0].cpu()[~ref_valid]), "invalid samples stay put"
        if quadratic:
            converged = ~out.fallback.cpu() & ref_valid
            assert bool((out.iterations.cpu()[converged] == ref_used[converged]).float().mean() > 0.98)


def test_zero_deformation_returns_the_sample_exactly(device):
    """F = I, ∇F = 0, x̃_k = x_k: the warp is the identity bit for bit (zero-deformation renders equal the NeRF)."""
    rest, _, _, _, _ = _ips(27, seed=4)
    K = rest.shape[0]
    g = torch.Generator().manual_seed(5)
    x_tilde = rest.amin(0) + (rest.amax(0) - rest.amin(0)) * torch.rand(2000, 3, generator=g, dtype=torch.float64)
    distances, neighbours = torch.cdist(x_tilde, rest).topk(3, largest=False)
    F = torch.eye(3, dtype=torch.float64).expand(K, 3, 3)
    args = _to_device(x_tilde, distances, rest, torch.zeros(K, 3), F, torch.zeros(K, 3, 3, 3), torch.full((K,), 1.0))
    for quadratic in (True, False):
        out = warp_to_rest(args[0], neighbours.int().to(backend.torch_device()), *args[1:], quadratic=quadratic)
        assert bool(out.valid.all())
        assert torch.equal(out.rest, args[0])


def test_singular_jacobian_falls_back(device):
    """A collapsed IP (det F = 0) contributes a translation; a fold (no root) falls back to the linear warp."""
    K = 2
    rest = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    F = torch.eye(3, dtype=torch.float64).repeat(K, 1, 1)
    F[0, 2, 2] = 0.0  # flattened along z
    grad_F = torch.zeros(K, 3, 3, 3, dtype=torch.float64)
    grad_F[1, 0, 0, 0] = 40.0  # x̃ − x̃_k = d + 20 d², which never goes below −1/80 along x
    displacement = torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=torch.float64)
    deformed = rest + displacement
    x_tilde = torch.stack([deformed[0] + torch.tensor([0.01, 0.0, 0.01]), deformed[1] - torch.tensor([0.03, 0, 0])])
    neighbours = torch.tensor([[0], [1]], dtype=torch.int32)
    distances = (x_tilde - deformed).norm(dim=1, keepdim=True)
    args = _to_device(x_tilde, distances, deformed, displacement, F, grad_F, torch.ones(K))
    out = warp_to_rest(args[0], neighbours.to(backend.torch_device()), *args[1:])
    ref = warp_to_rest_torch(x_tilde, neighbours, distances, deformed, displacement, F, grad_F, torch.ones(K))
    assert bool(out.fallback.all()) and bool(ref[3].all())
    assert torch.allclose(out.rest.double().cpu()[0], x_tilde[0] - displacement[0], atol=1e-6)
    assert torch.allclose(out.rest.double().cpu()[1], rest[1] + torch.tensor([-0.03, 0.0, 0.0]), atol=1e-6)
    assert torch.allclose(out.rest.double().cpu(), ref[0], atol=1e-6)


def _round_inputs(rays: int, k: int, seed: int):
    """A renderer's round over the IPs of :func:`_ips`: ``[A, k, 3]`` samples with ``counts`` (some rays full, some
    empty, the rest in between) and a random rest occupancy grid over a box around the IPs."""
    rest, deformed, displacement, F, grad_F = _ips(64, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    lo, hi = deformed.amin(0) - SPACING, deformed.amax(0) + SPACING
    samples = lo + (hi - lo) * torch.rand(rays, k, 3, generator=g, dtype=torch.float64)
    counts = torch.randint(0, k + 1, (rays,), generator=g, dtype=torch.int32)
    counts[:3] = torch.tensor([0, k, 1], dtype=torch.int32)
    occupancy = torch.rand(12, 10, 14, generator=g) < 0.6
    box = torch.stack([rest.amin(0) - SPACING, rest.amax(0) + 0.5 * SPACING]).float()
    cutoff = torch.full((rest.shape[0],), 1.2 * SPACING, dtype=torch.float64)
    dev = backend.torch_device()
    samples_d, deformed_d, displacement_d, F_d, grad_F_d, cutoff_d = _to_device(
        samples, deformed, displacement, F, grad_F, cutoff
    )
    return samples_d, counts.to(dev), deformed_d, displacement_d, F_d, grad_F_d, cutoff_d, occupancy.to(dev), box


@pytest.mark.parametrize("exhaustive_ips", [0, 512], ids=["grid_search", "exhaustive_search"])
@pytest.mark.parametrize("framework", FRAMEWORKS)
def test_round_warp_matches_knn_warp_and_occupancy(device, framework, exhaustive_ips, monkeypatch):
    """A round's fused warp (nearest IPs, Taylor inversion, rest-occupancy test) gives, on every filled slot, what
    :meth:`SpatialHash.knn`, :func:`warp_to_rest` and the grid lookup give one after the other; empty slots are
    never kept. The nearest IPs come from the hash grid or, for few IPs, from every IP (Warp): the same rows."""
    monkeypatch.setattr(warp_rays_module, "EXHAUSTIVE_IPS", exhaustive_ips)
    samples, counts, deformed, displacement, F, grad_F, cutoff, occupancy, box = _round_inputs(300, 6, seed=7)
    ip_hash = SpatialHash(deformed, 0.5 * SPACING)
    radius = 4 * SPACING
    k = samples.shape[1]
    filled = (torch.arange(k, device=counts.device) < counts[:, None]).view(-1)
    positions = samples.view(-1, 3)[filled].contiguous()
    neighbours, distances = ip_hash.knn(positions, 3, max_radius=radius)
    for quadratic in (True, False):
        rest, keep = warp_round(
            samples, counts, ip_hash, displacement, F, grad_F, cutoff, occupancy, box,
            max_radius=radius, quadratic=quadratic, framework=framework,
        )
        assert rest.shape == (samples.shape[0] * k, 3) and keep.dtype == torch.bool
        assert not bool(keep[~filled].any()), "empty slots are never kept"
        expected = warp_to_rest(
            positions, neighbours, distances, deformed, displacement, F, grad_F, cutoff, quadratic=quadratic
        )
        torch.testing.assert_close(rest[filled], expected.rest, rtol=0.0, atol=1e-6 * SPACING)
        resolution = torch.tensor(occupancy.shape, device=rest.device)
        cell = torch.floor((expected.rest - box[0].to(rest.device)) / ((box[1] - box[0]).to(rest.device) / resolution))
        inside = ((cell >= 0) & (cell < resolution)).all(-1)
        cell = torch.minimum(cell.long().clamp_min(0), resolution - 1)
        occupied = inside & occupancy[cell[:, 0], cell[:, 1], cell[:, 2]]
        assert torch.equal(keep[filled], expected.valid & occupied)
        valid, kept = float(expected.valid.float().mean()), float(keep[filled].float().mean())
        assert 0.2 < kept < valid < 0.95, f"the cutoff and the grid must both drop samples ({valid}, {kept})"


def test_round_warp_frameworks_agree_and_keep_zero_deformation_exact(device):
    """Taichi and Warp give the same round; with zero deformation both return every sample bit for bit."""
    samples, counts, deformed, displacement, F, grad_F, cutoff, occupancy, box = _round_inputs(200, 5, seed=9)
    ip_hash = SpatialHash(deformed, 0.5 * SPACING)
    out = {
        framework: warp_round(
            samples, counts, ip_hash, displacement, F, grad_F, cutoff, occupancy, box,
            max_radius=4 * SPACING, framework=framework,
        )
        for framework in FRAMEWORKS
    }
    torch.testing.assert_close(out["warp"][0], out["taichi"][0], rtol=0.0, atol=1e-6 * SPACING)
    assert torch.equal(out["warp"][1], out["taichi"][1])

    K = deformed.shape[0]
    identity = torch.eye(3, device=F.device).expand(K, 3, 3).contiguous()
    filled = (torch.arange(samples.shape[1], device=counts.device) < counts[:, None]).view(-1)
    for framework in FRAMEWORKS:
        rest, _ = warp_round(
            samples, counts, ip_hash, torch.zeros_like(displacement), identity, torch.zeros_like(grad_F),
            torch.full_like(cutoff, 1.0), occupancy, box, max_radius=4 * SPACING, framework=framework,
        )
        assert torch.equal(rest[filled], samples.view(-1, 3)[filled]), framework


def test_bad_arguments_raise_clear_errors(device):
    K, S = 4, 5
    dev = backend.torch_device()
    good = dict(
        samples=torch.zeros(S, 3, device=dev),
        neighbours=torch.zeros(S, 3, dtype=torch.int32, device=dev),
        distances=torch.zeros(S, 3, device=dev),
        ip_deformed=torch.zeros(K, 3, device=dev),
        ip_displacement=torch.zeros(K, 3, device=dev),
        F=torch.eye(3, device=dev).repeat(K, 1, 1),
        grad_F=torch.zeros(K, 3, 3, 3, device=dev),
        cutoff=torch.ones(K, device=dev),
    )
    assert warp_to_rest(**good).rest.shape == (S, 3)
    with pytest.raises(TypeError, match="samples must be a torch.float32"):
        warp_to_rest(**{**good, "samples": good["samples"].double()})
    with pytest.raises(ValueError, match=r"grad_F must have shape \[4, 3, 3, 3\]"):
        warp_to_rest(**{**good, "grad_F": torch.zeros(K, 3, 3, device=dev)})
    with pytest.raises(TypeError, match="neighbours must be a torch.int32"):
        warp_to_rest(**{**good, "neighbours": good["neighbours"].long()})
    with pytest.raises(ValueError, match="iterations >= 1"):
        warp_to_rest(**good, iterations=0)


def test_round_warp_bad_arguments_raise_clear_errors(device):
    samples, counts, deformed, displacement, F, grad_F, cutoff, occupancy, box = _round_inputs(20, 4, seed=13)
    ip_hash = SpatialHash(deformed, 0.5 * SPACING)
    args = (ip_hash, displacement, F, grad_F, cutoff, occupancy, box)
    with pytest.raises(ValueError, match=r"samples must be float32 \[A, k, 3\]"):
        warp_round(samples.view(-1, 3), counts, *args, max_radius=0.2)
    with pytest.raises(ValueError, match="counts must be int32"):
        warp_round(samples, counts.long(), *args, max_radius=0.2)
    with pytest.raises(TypeError, match="F must be a torch.float32"):
        warp_round(samples, counts, ip_hash, displacement, F.double(), grad_F, cutoff, occupancy, box, max_radius=0.2)
    with pytest.raises(ValueError, match="max_radius"):
        warp_round(samples, counts, *args, max_radius=0.0)
    with pytest.raises(ValueError, match="unknown framework"):
        warp_round(samples, counts, *args, max_radius=0.2, framework="cuda")
