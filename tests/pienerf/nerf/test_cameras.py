"""pienerf.nerf.cameras: a browser client's camera becomes the same view in OpenGL axes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pienerf.nerf.cameras import look_at_cameras, quaternion_matrix, viser_cameras


def test_viser_cameras_follow_the_client_camera():
    # A viser (OpenCV) camera at z = 3 looking down −z: x right, y down in the image; quaternion of diag(1, −1, −1).
    cameras = viser_cameras((0.2, 0.5, 3.0), (0.0, 1.0, 0.0, 0.0), math.radians(40.0), 1.5, 60)
    assert (cameras.width, cameras.height) == (90, 60)
    origin, centre = cameras.pixel_rays(0, torch.tensor([45.0]), torch.tensor([30.0]))
    torch.testing.assert_close(origin.reshape(3), torch.tensor([0.2, 0.5, 3.0]))
    torch.testing.assert_close(centre[0], torch.tensor([0.0, 0.0, -1.0]))
    _, top = cameras.pixel_rays(0, torch.tensor([45.0]), torch.tensor([0.0]))
    assert math.degrees(math.atan2(float(top[0, 1]), -float(top[0, 2]))) == pytest.approx(20.0, abs=1e-4)
    _, left = cameras.pixel_rays(0, torch.tensor([0.0]), torch.tensor([30.0]))
    assert float(left[0, 0]) < 0.0, "the image's left edge looks toward −x"


def test_quaternion_matrix_turns_about_its_axis():
    half = math.radians(90.0) / 2.0
    rotation = quaternion_matrix((math.cos(half), 0.0, 0.0, math.sin(half)))  # 90 degrees about +z
    np.testing.assert_allclose(rotation @ np.array([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="must not be zero"):
        quaternion_matrix((0.0, 0.0, 0.0, 0.0))


def test_grid_rays_project_back_to_their_pixels_and_axial_depth_is_the_z_distance():
    cameras = look_at_cameras([[0.3, 0.4, 2.0]], [[0.0, 0.0, 0.0]], 40, 30)
    origins, directions = cameras.grid_rays(0, 8, 6)
    points = origins + 1.7 * directions
    u, v, depth = cameras.project(0, points)
    cols, rows = (torch.arange(8) + 0.5) * 5.0, (torch.arange(6) + 0.5) * 5.0
    torch.testing.assert_close(u, cols.repeat(6), atol=1e-4, rtol=0)
    torch.testing.assert_close(v, rows.repeat_interleave(8), atol=1e-4, rtol=0)
    axial = cameras.axial_depth(0, torch.full((6, 8), 1.7))
    torch.testing.assert_close(axial.reshape(-1), depth, atol=1e-5, rtol=0)
