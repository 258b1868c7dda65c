"""physavatar.fit.regions: two halves of a skirt of different stiffness, recovered through the rollout's adjoint."""

import pytest
import torch

from physavatar.body import Body, named_motion
from physavatar.cloth import RolloutScene, rollout
from physavatar.drive import BodyDriver
from physavatar.fit import SYNTHETIC_FABRIC, EstimationProblem, FabricParameters, estimate_regions, garment_regions
from physavatar.garment import procedural_skirt, select_boundary

FRAMES = 6
TRUE_KAPPA_S = (0.5, 2.0)  # the right half four times softer in stretch than the left


@pytest.fixture
def two_halves(device):
    """The coarse skirt on 6 frames of the walk, its halves' κ_s 0.5 and 2.0 (κ_b 1): ``(problem, regions)``."""
    body = Body.mannequin(spacing=0.03)
    skirt = procedural_skirt(body, rings=5, segments=14)
    boundary = select_boundary(skirt, body, mode="waist")
    clip = named_motion("walk", body.skeleton, FRAMES - 1, 25.0)
    driver = BodyDriver.from_motion(body, clip, skirt.vertices, boundary, FRAMES - 1)
    regions = garment_regions(skirt.vertices, skirt.faces, 2)
    scene = RolloutScene(skirt.vertices, skirt.faces, body.faces, boundary, 1.0 / 25.0, SYNTHETIC_FABRIC)
    field = torch.tensor(TRUE_KAPPA_S, dtype=torch.float64)[regions]
    frames = rollout(
        scene, SYNTHETIC_FABRIC.density, 1.0, 1.0, skirt.vertices, driver.body_frames, driver.boundary_targets,
        kappa_s_field=field,
    )  # fmt: skip
    problem = EstimationProblem(
        skirt.vertices, skirt.faces, frames, driver.body_frames, body.faces, boundary, driver.boundary_targets, 25.0,
        SYNTHETIC_FABRIC,
    )  # fmt: skip
    return problem, regions


def test_garment_regions_split_the_skirt_into_its_halves():
    body = Body.mannequin(spacing=0.03)
    skirt = procedural_skirt(body, rings=5, segments=14)
    regions = garment_regions(skirt.vertices, skirt.faces, 2)
    centroid_x = skirt.vertices[skirt.faces].mean(1)[:, 0] - skirt.vertices[:, 0].mean()
    assert torch.equal(regions, (centroid_x >= 0).long())
    assert set(garment_regions(skirt.vertices, skirt.faces, 8).tolist()) == set(range(8))
    with pytest.raises(ValueError, match="at least 1"):
        garment_regions(skirt.vertices, skirt.faces, 0)


def test_each_half_is_recovered_where_one_global_value_cannot_be(two_halves):
    problem, regions = two_halves
    start = FabricParameters(SYNTHETIC_FABRIC.density, 1.0, 1.0)
    fit = estimate_regions(problem, regions, start, iterations=25)
    for found, truth in zip(fit.kappa_s.tolist(), TRUE_KAPPA_S, strict=True):
        assert abs(found / truth - 1.0) < 0.10, fit.kappa_s
    assert fit.loss[-1] < 1e-3 * fit.loss[0]
    one = estimate_regions(problem, torch.zeros_like(regions), start, iterations=25)
    assert all(abs(float(one.kappa_s[0]) / truth - 1.0) > 0.40 for truth in TRUE_KAPPA_S), one.kappa_s
    assert one.loss[-1] > 100.0 * fit.loss[-1]


def test_bad_regions_are_refused_with_the_fix(two_halves):
    problem, regions = two_halves
    start = FabricParameters(SYNTHETIC_FABRIC.density, 1.0, 1.0)
    with pytest.raises(ValueError, match="one non-negative integer per garment face"):
        estimate_regions(problem, regions[:-1], start)
    with pytest.raises(ValueError, match="every region holding a face"):
        estimate_regions(problem, regions * 2, start)
