"""Geometry metrics of the evaluation and the LBS baseline."""

import math

import pytest
import torch

from physavatar.body import Body, raise_arms
from physavatar.fit.evaluation import chamfer_fscore, geometry_scores, lbs_garment, surface_samples
from physavatar.garment import procedural_skirt
from physavatar.shapes import grid_sheet


@pytest.fixture(scope="module")
def sheet():
    vertices, faces = grid_sheet(6, 5, 0.1)
    return vertices, faces.long()


def test_samples_lie_on_the_surface_and_cover_it_by_area(sheet):
    vertices, faces = sheet
    points = surface_samples(vertices, faces, 4000, seed=1)
    assert torch.allclose(points[:, 2], torch.zeros(4000, dtype=torch.float64))
    assert float(points[:, 0].min()) >= 0.0 and float(points[:, 0].max()) <= 0.5 + 1e-12
    # Uniform by area: the left half of the 0.5 × 0.4 m sheet holds half of the points.
    assert abs(float((points[:, 0] < 0.25).double().mean()) - 0.5) < 0.03
    assert torch.equal(points, surface_samples(vertices, faces, 4000, seed=1))


def test_identical_meshes_score_perfectly_and_offsets_score_as_expected(sheet, device):
    vertices, faces = sheet
    cd, f = chamfer_fscore(vertices, vertices, faces, samples=2000)
    assert cd < 1e-12 and f == 1.0
    # A sheet lifted by 0.5 mm: every point is 0.5 mm from the other surface (inside τ = 1 mm)...
    lifted = vertices + torch.tensor([0.0, 0.0, 5e-4], dtype=torch.float64)
    cd, f = chamfer_fscore(lifted, vertices, faces, samples=2000)
    assert math.isclose(cd, 2 * 5e-4**2, rel_tol=1e-3) and f == 1.0
    # ... and lifted by 2 mm, none is.
    cd, f = chamfer_fscore(
        vertices + torch.tensor([0.0, 0.0, 2e-3], dtype=torch.float64), vertices, faces, samples=2000
    )
    assert math.isclose(cd, 2 * 2e-3**2, rel_tol=1e-3) and f == 0.0


def test_sequence_scores_and_shape_errors(sheet):
    vertices, faces = sheet
    truth = torch.stack([vertices, vertices + 0.01])
    prediction = truth.clone()
    prediction[1, :, 2] += 3e-3
    scores = geometry_scores(prediction, truth, faces, samples=1000)
    assert scores.chamfer.shape == (2,) and scores.fscore[0] == 1.0 and scores.fscore[1] == 0.0
    assert math.isclose(float(scores.vertex_error[1]), 3e-3, rel_tol=1e-9)
    assert set(scores.summary()) >= {"chamfer", "fscore", "vertex_error"}
    with pytest.raises(ValueError, match="same frames and vertices"):
        geometry_scores(prediction[:1], truth, faces)


def test_lbs_garment_follows_the_body_and_is_rigid_at_rest():
    body = Body.mannequin(spacing=0.03)
    skirt = procedural_skirt(body, rings=4, segments=12)
    motion = raise_arms(body.skeleton, duration=0.4, fps=10.0)
    moved = lbs_garment(body, skirt.vertices, motion.rotations, motion.root_translation)
    assert moved.shape == (motion.num_frames, 48, 3)
    torch.testing.assert_close(moved[0], skirt.vertices, atol=1e-9, rtol=0)
