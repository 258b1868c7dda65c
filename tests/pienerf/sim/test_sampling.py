import math

import pytest
import torch

from kernels import backend
from pienerf.sim.density import Sphere
from pienerf.sim.sampling import Particles, grid_sample, particle_volume, poisson_disk_sample, sample_radius

R_BAR = 0.15


@pytest.fixture
def sphere() -> Sphere:
    return Sphere([0.0, 0.0, 0.0], 1.0)


@pytest.fixture
def particles(device, sphere) -> Particles:
    return poisson_disk_sample(sphere, R_BAR, seed=3)


def test_sample_radius_is_eq_3():
    g = torch.tensor([0.0, 1e-3, 9e-3, 0.5, 100.0], dtype=torch.float64)
    r = sample_radius(g, r_bar=0.2, kappa=0.1, alpha=1e-3)
    torch.testing.assert_close(r, torch.clamp_min(0.1 * 0.2 / torch.sqrt(g + 1e-3), 0.2))
    assert r[0] == pytest.approx(0.2 * 0.1 / math.sqrt(1e-3)), "flat density: the largest radius κ r̄ / sqrt(α)"
    assert r[2] == pytest.approx(0.2) and r[-1] == pytest.approx(0.2), "‖∇σ‖ ≥ κ² − α: the floor r̄"
    assert bool((r[1:] <= r[:-1]).all()), "the radius shrinks as the gradient grows"


def test_particle_volume_is_eq_4():
    torch.testing.assert_close(
        particle_volume(torch.tensor([1.0, 0.5])), torch.tensor([4.0 / 3.0 * math.pi, math.pi / 6.0])
    )


def test_no_two_particles_closer_than_their_conflict_distance(particles):
    assert len(particles) > 100
    d = torch.cdist(particles.position.cpu(), particles.position.cpu(), compute_mode="donot_use_mm_for_euclid_dist")
    reach = torch.maximum(particles.radius.cpu()[:, None], particles.radius.cpu()[None, :])
    d.fill_diagonal_(math.inf)
    assert bool((d >= reach * (1.0 - 1e-6)).all())


def test_sample_is_maximal_and_covers_the_solid(particles, sphere):
    # Any point above the threshold lies within the conflict distance of a particle, give or take
    # the half-diagonal of a candidate cell (a point between candidates may be in no cell's reach).
    generator = torch.Generator().manual_seed(0)
    probe = (torch.rand(20_000, 3, generator=generator) * 2.4 - 1.2).to(particles.position.device)
    probe = probe[sphere.density(probe) >= 1e-2]
    probe_radius = sample_radius(sphere.density_grad(probe).norm(dim=-1), R_BAR, 0.1)
    d = torch.cdist(probe, particles.position)
    reach = torch.maximum(probe_radius[:, None], particles.radius[None, :]) + math.sqrt(3.0) * 0.5 * R_BAR
    assert bool((d < reach).any(dim=1).all())


def test_radius_follows_eq_3_small_on_the_boundary_large_inside(particles, sphere):
    grad_norm = sphere.density_grad(particles.position).norm(dim=-1)
    torch.testing.assert_close(particles.radius, sample_radius(grad_norm, R_BAR, 0.1))
    torch.testing.assert_close(particles.volume, particle_volume(particles.radius))
    depth = sphere.signed_distance(particles.position)
    boundary, core = depth.abs() < 5 * sphere.softness, depth < -30 * sphere.softness
    assert int(boundary.sum()) > 50 and int(core.sum()) >= 3
    # Steep density on the boundary: the floor r̄; flat density deep inside: κ r̄ / sqrt(α) ≈ 3.2 r̄.
    torch.testing.assert_close(particles.radius[boundary], torch.full_like(particles.radius[boundary], R_BAR))
    largest = 0.1 * R_BAR / math.sqrt(1e-3)
    torch.testing.assert_close(particles.radius[core], torch.full_like(particles.radius[core], largest))
    assert bool((particles.density >= 1e-2).all())


def test_total_volume_counts_overlapping_balls(particles, sphere):
    # Eq. 4 gives each particle its whole ball of radius r although neighbours lie only r apart:
    # the balls overlap and their volumes sum to ~2.4x the solid's (observed 2.38 at r̄ = 0.15).
    ratio = float(particles.volume.sum()) / (4.0 / 3.0 * math.pi)
    assert 1.5 < ratio < 4.0


def test_same_seed_same_particles(device, sphere, particles):
    again = poisson_disk_sample(sphere, R_BAR, seed=3)
    assert torch.equal(again.position, particles.position) and torch.equal(again.radius, particles.radius)
    other = poisson_disk_sample(sphere, R_BAR, seed=4)
    assert other.position.shape != particles.position.shape or not torch.equal(other.position, particles.position)


def test_grid_sample_volume_matches_the_threshold_level_set(device, sphere):
    spacing = 0.05
    particles = grid_sample(sphere, spacing)
    level_radius = 1.0 + sphere.level_distance(1e-2)
    expected = 4.0 / 3.0 * math.pi * level_radius**3
    assert float(particles.volume.sum()) == pytest.approx(expected, rel=0.02)
    assert particles.position.device == backend.torch_device()
    assert bool((particles.radius == spacing).all())


def test_bad_input_is_refused_with_the_fix(device, sphere):
    with pytest.raises(ValueError, match="no particle above the density threshold.*lower epsilon"):
        poisson_disk_sample(sphere, 0.3, epsilon=60.0)
    with pytest.raises(ValueError, match="r_bar"):
        poisson_disk_sample(sphere, 0.0)
    with pytest.raises(ValueError, match="kappa"):
        poisson_disk_sample(sphere, 0.2, kappa=-1.0)
    with pytest.raises(ValueError, match="max_candidates"):
        poisson_disk_sample(sphere, 0.01, max_candidates=1000)
    with pytest.raises(ValueError, match="lower epsilon"):
        grid_sample(sphere, 0.2, epsilon=60.0)
