"""Kernel placement, integrator points, cuboids and the mass matrix (PIE-NeRF §4.2–4.4, Eq. 11, 13)."""

from __future__ import annotations

import pytest
import torch

from kernels import backend
from pienerf.sim.integrator_points import (
    IntegratorPoints,
    cuboid_quadrature,
    farthest_point_sampling,
    lloyd_relaxation,
    mass_matrix,
    place_integrator_points,
    place_kernels,
)
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.qgmls import QGMLSBasis, voronoi_partition

F64 = torch.float64


def _particles(shape: str, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Jittered grid particles (spacing ``h``, volume ``h³``) inside a box, a sphere, a thin rod or a thin plate."""
    g = torch.Generator().manual_seed(seed)
    h = 0.1
    counts = {"box": (8, 6, 5), "sphere": (10, 10, 10), "rod": (30, 2, 2), "plate": (14, 14, 1)}[shape]
    axes = [torch.arange(c, dtype=F64) * h for c in counts]
    position = torch.cartesian_prod(*axes)
    if shape == "sphere":
        centre = position.mean(0)
        position = position[(position - centre).norm(dim=1) <= 0.45]
    position = position + 0.1 * h * (torch.rand(position.shape, generator=g, dtype=F64) - 0.5)
    if shape == "plate":
        position[:, 2] = 0.0  # exactly one layer: the neighbour covariance is singular
    volume = torch.full((position.shape[0],), h**3, dtype=F64)
    dev = backend.torch_device()
    return position.to(dev), volume.to(dev)


def _is_row_of(rows: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    return torch.cdist(rows, table, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values < 1e-12


def test_farthest_point_sampling(device):
    points = torch.zeros(11, 3, dtype=F64, device=backend.torch_device())
    points[:, 0] = torch.linspace(0.0, 1.0, 11, dtype=F64)
    picks = farthest_point_sampling(points, 3)
    assert set(picks.tolist()) == {0, 5, 10}  # both ends, then the middle
    seeded = farthest_point_sampling(points, 2, seed_indices=torch.tensor([0]))
    assert seeded.tolist() == [10, 5]
    everything = farthest_point_sampling(points, 10, seed_indices=torch.tensor([3]))
    assert sorted(everything.tolist()) == [i for i in range(11) if i != 3]
    with pytest.raises(ValueError, match="only 10 points left"):
        farthest_point_sampling(points, 11, seed_indices=torch.tensor([3]))


def test_lloyd_relaxation_spreads_free_centres_and_keeps_fixed_ones(device):
    points = torch.zeros(101, 3, dtype=F64, device=backend.torch_device())
    points[:, 0] = torch.linspace(0.0, 1.0, 101, dtype=F64)
    weights = torch.ones(101, dtype=F64, device=points.device)
    start = points[[0, 1, 2]]
    fixed = torch.tensor([True, False, False])
    centres, cell = lloyd_relaxation(points, weights, start, iterations=200, fixed_mask=fixed)
    assert torch.equal(centres[0], start[0])
    assert bool(_is_row_of(centres, points).all())  # snapped onto particles
    # Centroidal Voronoi tessellation of [0, 1] with a centre fixed at 0: free centres at 0.4 and 0.8.
    assert torch.allclose(centres[1:, 0], torch.tensor([0.4, 0.8], dtype=F64, device=points.device), atol=0.021)
    assert torch.equal(cell, voronoi_partition(points, centres)[0])


@pytest.mark.parametrize("shape", ["box", "sphere", "rod", "plate"])
def test_place_kernels(device, shape):
    position, volume = _particles(shape)
    user = position[:1] + 0.01
    kernels = place_kernels(position, volume, 8, user_points=user, lloyd_iterations=4)
    assert kernels.centres.shape == (8, 3) and kernels.support_radius.shape == (8,)
    assert torch.equal(kernels.centres[0], user[0].to(F64))  # the user kernel is kept where it was put
    assert bool(_is_row_of(kernels.centres[1:], position).all())
    assert torch.unique(kernels.centres, dim=0).shape[0] == 8
    assert torch.equal(kernels.cell, voronoi_partition(position, kernels.centres)[0])
    # Every particle is covered: the shape functions evaluate there and sum to one.
    basis = QGMLSBasis(kernels.centres, kernels.support_radius)
    shape_values = basis.evaluate(position, derivatives=0)
    value_terms = (shape_values.index >= 0) & (shape_values.index % basis.terms == 0)
    assert torch.allclose((shape_values.value * value_terms).sum(1), torch.ones_like(volume))


def test_place_kernels_rejects_bad_counts(device):
    position, volume = _particles("box")
    with pytest.raises(ValueError, match=r"asked for 241 new points but there are only 240 particles"):
        place_kernels(position, volume, position.shape[0] + 1)
    with pytest.raises(ValueError, match="number of user kernels = 2"):
        place_kernels(position, volume, 1, user_points=position[:2])
    with pytest.raises(ValueError, match="count must be an int"):
        place_kernels(position, volume, 0)
    with pytest.raises(ValueError, match=r"volume must be \[P\]"):
        place_kernels(position, volume[:-1], 4)


@pytest.mark.parametrize("shape", ["box", "sphere", "rod", "plate"])
def test_place_integrator_points(device, shape):
    position, volume = _particles(shape)
    kernels = place_kernels(position, volume, 6)
    ips = place_integrator_points(position, volume, kernels.centres, 20, neighbours=12)
    assert isinstance(ips, IntegratorPoints) and ips.count == 20
    assert ips.is_kernel_ip.tolist() == [True] * 6 + [False] * 14
    assert torch.equal(ips.position[:6], kernels.centres)
    assert bool(_is_row_of(ips.position, position).all())
    assert torch.unique(ips.position, dim=0).shape[0] == 20
    assert torch.allclose(ips.volume.sum(), volume.sum(), rtol=1e-12)
    assert bool((ips.volume > 0).all())
    assert torch.allclose(ips.extent.prod(-1), ips.volume, rtol=1e-10)
    assert bool((ips.extent[:, :-1] >= ips.extent[:, 1:]).all())
    eye = torch.eye(3, dtype=F64, device=position.device).expand(20, 3, 3)
    assert torch.allclose(ips.frame.mT @ ips.frame, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(ips.frame), torch.ones(20, dtype=F64, device=position.device))
    if shape == "plate":
        # Thin plate: the shortest cuboid axis is the plate normal and the cuboid is as thick as the
        # layer (one particle of edge h = 0.1), not thicker or thinner.
        assert torch.allclose(ips.frame[:, 2, 2].abs(), torch.ones(20, dtype=F64, device=position.device))
        assert torch.allclose(ips.extent[:, 2], torch.full_like(ips.extent[:, 2], 0.1), rtol=0.05)
        assert bool(torch.isfinite(ips.extent).all())


def test_place_integrator_points_rejects_bad_counts(device):
    position, volume = _particles("box")
    kernels = place_kernels(position, volume, 6)
    with pytest.raises(ValueError, match=r"must be an int >= the number of kernels \(6\)"):
        place_integrator_points(position, volume, kernels.centres, 5)
    with pytest.raises(ValueError, match="only 240 particles"):
        place_integrator_points(position, volume, kernels.centres, 6 + position.shape[0] + 1)


def test_cuboid_quadrature_weights_and_exactness(device):
    position, volume = _particles("box")
    kernels = place_kernels(position, volume, 4)
    ips = place_integrator_points(position, volume, kernels.centres, 10)
    for g in (1, 2, 3):
        offset, weight = cuboid_quadrature(ips, points_per_axis=g)
        assert offset.shape == (10, g**3, 3) and weight.shape == (10, g**3)
        assert torch.allclose(weight.sum(1), ips.volume, rtol=1e-12)
        # back to cuboid coordinates about the cuboid centre (the cell centroid, not the IP itself)
        local = torch.einsum("kba,kgb->kga", ips.frame, offset - (ips.centre - ips.position).unsqueeze(1))
        assert bool((local.abs() <= 0.5 * ips.extent.unsqueeze(1) + 1e-12).all())
        # ∫ h_1⁴ over the cuboid = V h_1⁴ / 80: degree 4 per axis, exact from g = 3 (2g − 1 ≥ 4).
        exact = ips.volume * ips.extent[:, 0] ** 4 / 80.0
        quartic = (weight * local[..., 0] ** 4).sum(1)
        assert torch.allclose(quartic, exact, rtol=1e-12) == (g == 3)
    with pytest.raises(ValueError, match="points_per_axis must be an int >= 1"):
        cuboid_quadrature(ips, points_per_axis=0)


@pytest.fixture
def body(device):
    position, volume = _particles("sphere")
    kernels = place_kernels(position, volume, 6)
    ips = place_integrator_points(position, volume, kernels.centres, 15)
    return QGMLSBasis(kernels.centres, kernels.support_radius), ips, volume


@pytest.mark.parametrize("quadrature", ["ip", "cuboid"])
def test_mass_matrix_is_symmetric_psd_and_exact_for_translations(body, quadrature):
    basis, ips, volume = body
    density = 1000.0
    mass = mass_matrix(basis, ips, density, quadrature=quadrature, points_per_axis=2)
    assert mass.shape == (basis.shape_count, basis.shape_count)
    assert torch.equal(mass, mass.T)
    eigenvalues = torch.linalg.eigvalsh(mass)
    assert eigenvalues[0] >= -1e-10 * eigenvalues[-1]

    t = torch.tensor([0.3, -1.2, 0.5], dtype=F64, device=mass.device)
    q = torch.zeros(basis.kernel_count, basis.terms, 3, dtype=F64, device=mass.device)
    q[:, 0] = t
    full = torch.kron(mass, torch.eye(3, dtype=F64, device=mass.device))
    kinetic = q.reshape(-1) @ full @ q.reshape(-1)
    assert torch.allclose(kinetic, density * volume.sum() * t.dot(t), rtol=1e-10)

    rank = int(torch.linalg.matrix_rank(mass, rtol=1e-12))
    if quadrature == "ip":
        assert rank <= ips.count < basis.shape_count  # Eq. 11 with one point per IP is singular
    else:
        assert rank == basis.shape_count  # 15 cuboids x 8 points >= nT = 60: full rank


def test_mass_matrix_matches_equation_11_with_dense_jacobians(body):
    basis, ips, _ = body
    jacobian = basis.dense_jacobian(ips.position)  # [K, 3, 3nT]
    reference = 2.0 * torch.einsum("k,kai,kaj->ij", ips.volume, jacobian, jacobian)  # ρ = 2
    full = torch.kron(mass_matrix(basis, ips, 2.0), torch.eye(3, dtype=F64, device=jacobian.device))
    assert torch.allclose(full, reference, rtol=0.0, atol=1e-12 * reference.abs().max())


def test_mass_matrix_rejects_bad_arguments(body):
    basis, ips, _ = body
    with pytest.raises(ValueError, match="unknown quadrature"):
        mass_matrix(basis, ips, 1.0, quadrature="gauss")
    with pytest.raises(ValueError, match="density must be > 0"):
        mass_matrix(basis, ips, 0.0)


def test_model_discretises_a_lattice_alike_on_every_device(device):
    """A body on an exact lattice (where many particles tie for their nearest centre) gets the same kernels and IPs
    on the backend's device as on the CPU, and from one build to the next: the placement runs on the CPU."""
    axes = [torch.arange(0.0125, extent, 0.025, dtype=F64) for extent in (1.0, 0.1, 0.1)]
    position = torch.cartesian_prod(*axes)
    volume = torch.full((position.shape[0],), 0.025**3, dtype=F64)
    config = DiscretizationConfig(kernel_count=8)
    devices = ("cpu", backend.torch_device(), backend.torch_device())
    models = [QGMLSModel(position, volume, config, device=d) for d in devices]
    for model in models[1:]:
        assert model.kernels.centres.device == model.position.device
        assert torch.equal(model.kernels.centres.cpu(), models[0].kernels.centres)
        assert torch.equal(model.kernels.cell.cpu(), models[0].kernels.cell)
        assert torch.equal(model.ips.position.cpu(), models[0].ips.position)
        assert torch.equal(model.ips.volume.cpu(), models[0].ips.volume)
