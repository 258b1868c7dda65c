"""EWA projection of mesh-aligned Gaussians with intrinsics shared by every camera or one row per camera."""

import pytest
import torch

from physavatar.capture import CameraRig
from physavatar.fit.gaussians import GaussianAppearance, face_frames, project_gaussians
from physavatar.shapes import grid_sheet


def _calibrated_rig() -> CameraRig:
    """Three cameras about a sheet at the origin, each with its own focal lengths and principal point (px)."""
    ring = CameraRig.ring(3, 0.6, 0.1, (0.0, 0.0, 0.0), 24, 20, 40.0)
    return CameraRig(ring.c2w, 24, 20, [26.0, 31.5, 22.25], [27.0, 30.0, 22.0], [12.0, 11.25, 13.5], [10.0, 9.5, 10.75])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_per_camera_intrinsics_project_each_view_as_its_own_floats(dtype):
    """View c of a ``[C, 4]`` projection is, bit for bit, view c of a projection with camera c's four floats (same
    poses, so the same arithmetic), and so is the gradient that view sends to the vertices."""
    vertices, faces = grid_sheet(5, 5, 0.05)
    vertices, faces = (vertices - vertices.mean(0)).to(dtype), faces.long()
    appearance = GaussianAppearance.initial(vertices, faces)
    rig = _calibrated_rig()
    w2c = rig.world_to_camera()

    def project(intrinsics, view):
        """The projection and the gradient to the vertices of a smooth function of view ``view``."""
        x = vertices.clone().requires_grad_(True)
        centre, rotation = face_frames(x, faces, appearance.edge)
        thin = torch.full_like(appearance.log_scales[:, :1], appearance.normal_scale)
        scales = torch.cat([appearance.log_scales.exp(), thin], 1).to(centre)
        means2d, conics, depths, radii = project_gaussians(
            centre, rotation, scales, w2c, intrinsics, rig.width, rig.height
        )
        (means2d[view].sin().sum() + conics[view].cos().sum() + depths[view].sum()).backward()
        return means2d, conics, depths, radii, x.grad

    for c in range(len(rig)):
        per_camera = project(rig.intrinsics, c)
        alone = project(tuple(rig.intrinsics[c].tolist()), c)
        assert bool((per_camera[3][c] > 0).any())  # the view sees Gaussians
        for mine, theirs in zip(per_camera[:4], alone[:4], strict=True):
            assert mine[c].dtype == theirs[c].dtype and torch.equal(mine[c], theirs[c])
        assert torch.equal(per_camera[4], alone[4])
    assert not torch.equal(project(rig.intrinsics, 0)[0][1], project(tuple(rig.intrinsics[0].tolist()), 0)[0][1])


def test_intrinsics_of_the_wrong_shape_are_refused():
    rig = _calibrated_rig()
    means = torch.zeros(2, 3, dtype=torch.float64)
    rotations, scales = torch.eye(3, dtype=torch.float64).expand(2, 3, 3), torch.full((2, 3), 0.01)
    args = (means, rotations, scales, rig.world_to_camera())
    with pytest.raises(ValueError, match=r"\[3, 4\] tensor .* got \(2, 4\); pass CameraRig.intrinsics"):
        project_gaussians(*args, rig.intrinsics[:2], rig.width, rig.height)
    with pytest.raises(ValueError, match=r"four floats .* pass CameraRig.intrinsics"):
        project_gaussians(*args, (rig.fx, rig.fy, rig.cx, rig.cy), rig.width, rig.height)
