"""garment_distances: the garment simulator's distance measure, applied to any positions."""

import math

import pytest
import torch

from physavatar.cloth.contact import garment_distances

# a closed, outward-oriented tetrahedron below the plane z = 0: its top face is the triangle (0,0,0) (1,0,0) (0,1,0)
_BODY = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
_BODY_FACES = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])


def _garment() -> tuple[torch.Tensor, torch.Tensor]:
    """Three separate triangles parallel to the body's top face: 4 mm above it, 3 mm above that one, and one inside
    the body 0.1 m below it."""

    def triangle(x, y, size, z):
        return [[x, y, z], [x + size, y, z], [x, y + size, z]]

    x = torch.tensor(
        triangle(0.2, 0.2, 0.1, 0.004) + triangle(0.22, 0.22, 0.03, 0.007) + triangle(0.1, 0.1, 0.05, -0.1),
        dtype=torch.float64,
    )
    return x, torch.arange(9).reshape(3, 3)


def test_distances_to_the_body_and_between_triangles_that_share_no_vertex(device):
    x, faces = _garment()
    d = garment_distances(x, faces, _BODY, _BODY_FACES)
    assert d.body == pytest.approx(0.004, abs=1e-9)  # the lowest triangle above the body: its vertices over the face
    assert d.garment == pytest.approx(0.003, abs=1e-9)  # the upper triangle's vertices over the lower one
    assert d.inside == 3  # the triangle inside the body counts by the winding number, not by a distance


def test_distances_beyond_the_reach_are_infinite(device):
    x, faces = _garment()
    d = garment_distances(x, faces, _BODY, _BODY_FACES, reach=2e-3)
    assert math.isinf(d.body) and math.isinf(d.garment) and d.inside == 3
    with pytest.raises(ValueError, match="reach"):
        garment_distances(x, faces, _BODY, _BODY_FACES, reach=0.0)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        garment_distances(x[:, :2], faces, _BODY, _BODY_FACES)
