"""physavatar.body.attachment: points carried by a body mesh's triangles."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from physavatar.body import attach_to_surface
from physavatar.drive import BodyDriver


def _sphere():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    return torch.as_tensor(mesh.vertices, dtype=torch.float64), torch.as_tensor(mesh.faces, dtype=torch.int64)


def _rotation(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def test_points_follow_a_rigid_motion_of_the_body_rigidly():
    vertices, faces = _sphere()
    generator = torch.Generator().manual_seed(0)
    points = torch.nn.functional.normalize(torch.randn(40, 3, generator=generator, dtype=torch.float64), dim=1)
    points = points * (0.2 + 0.02 * torch.rand(40, 1, generator=generator, dtype=torch.float64))
    motions = [(_rotation(0.3 * t), torch.tensor([0.1 * t, 0.05, -0.02 * t], dtype=torch.float64)) for t in range(4)]
    frames = torch.stack([vertices @ r.T + shift for r, shift in motions])
    expected = torch.stack([points @ r.T + shift for r, shift in motions])
    attachment = attach_to_surface(expected[0], frames[0], faces)
    carried = attachment.positions(frames, faces)
    # frame 0 is reproduced to rounding of the foot plus the offset; each later frame rotates both exactly
    torch.testing.assert_close(carried, expected, rtol=0.0, atol=64 * torch.finfo(torch.float64).eps)
    assert torch.equal(attachment.positions(frames[1], faces), carried[1])


def test_the_driver_of_a_captured_body_carries_its_boundary():
    vertices, faces = _sphere()
    garment = torch.tensor([[0.0, 0.21, 0.0], [0.21, 0.0, 0.0], [0.0, -0.3, 0.0]], dtype=torch.float64)
    frames = torch.stack([vertices + torch.tensor([0.0, 0.01 * t, 0.0], dtype=torch.float64) for t in range(3)])
    driver = BodyDriver.from_body_frames(frames, faces, garment, torch.tensor([0, 1]), 30.0)
    assert driver.boundary_targets.shape == (3, 2, 3) and driver.fps == 30.0
    lift = torch.tensor([0.0, 0.02, 0.0], dtype=torch.float64)
    torch.testing.assert_close(driver.boundary_targets[2], garment[:2] + lift, rtol=0.0, atol=1e-14)


def test_bad_points_are_refused_with_the_fix():
    vertices, faces = _sphere()
    with pytest.raises(ValueError, match="non-empty"):
        attach_to_surface(torch.zeros(0, 3, dtype=torch.float64), vertices, faces)
    with pytest.raises(ValueError, match="NaN or inf"):
        attach_to_surface(torch.full((1, 3), float("nan"), dtype=torch.float64), vertices, faces)
