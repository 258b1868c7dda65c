"""Mesh tracking with mesh-aligned Gaussians: losses of Eq. 2–3 and recovery of a rigid motion."""

import math

import pytest
import torch

from physavatar.capture import CameraRig, Lighting, garment_albedo, render_capture
from physavatar.fit.gaussians import GaussianAppearance, Subdivision, face_frames
from physavatar.fit.tracking import TrackConfig, isometry_loss, mesh_neighbours, normal_loss, track
from physavatar.shapes import grid_sheet


def _sheet():
    vertices, faces = grid_sheet(9, 9, 0.04)  # 0.32 m square in the xy plane, facing +z
    return vertices - torch.tensor([0.16, 0.16, 0.0], dtype=torch.float64), faces.long()


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_losses_vanish_on_rigid_motions_and_grow_with_stretch_and_folds():
    vertices, faces = _sheet()
    edges, degree, pairs = mesh_neighbours(faces, vertices.shape[0])
    assert edges.shape[0] == 2 * (2 * 8 * 9 + 8 * 8)  # directed: horizontal, vertical and diagonal edges
    assert pairs.shape[0] == 2 * 8 * 9 + 8 * 8 - 4 * 8  # interior edges (all but the rim) join two faces
    rest = torch.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], dim=1)
    moved = vertices @ _rotation_z(0.3).T + torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    assert float(isometry_loss(moved, rest, edges, degree)) < 1e-12
    assert float(normal_loss(moved, faces, pairs)) < 1e-12
    stretched = vertices * torch.tensor([1.1, 1.0, 1.0], dtype=torch.float64)
    assert float(isometry_loss(stretched, rest, edges, degree)) > 1e-3
    folded = vertices.clone()
    folded[:, 2] = 0.2 * folded[:, 0].clamp_min(0.0)
    assert float(normal_loss(folded, faces, pairs)) > 1e-3


def test_isometry_tolerance_lets_a_fabric_stretch_and_still_stops_distortion():
    """With a tolerance τ, length changes up to τ of the rest length are free and larger ones cost what exceeds τ."""
    vertices, faces = _sheet()
    edges, degree, _ = mesh_neighbours(faces, vertices.shape[0])
    rest = torch.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], dim=1)
    scale = torch.tensor([1.02, 1.0, 1.0], dtype=torch.float64)  # a 2 % stretch along x
    assert float(isometry_loss(vertices * scale, rest, edges, degree)) > 1e-5
    assert float(isometry_loss(vertices * scale, rest, edges, degree, tolerance=0.03)) == 0.0
    # uniform 10 % growth: every edge 10 % longer, of which 3 % is free
    grown = isometry_loss(vertices * 1.1, rest, edges, degree)
    tolerated = isometry_loss(vertices * 1.1, rest, edges, degree, tolerance=0.03)
    assert float(tolerated) == pytest.approx(0.7 * float(grown), rel=1e-9)


def test_gaussians_sit_on_the_faces_in_the_faces_frames():
    vertices, faces = _sheet()
    appearance = GaussianAppearance.initial(vertices, faces)
    centre, rotation = face_frames(vertices, faces, appearance.edge)
    torch.testing.assert_close(centre, vertices[faces].mean(1))
    eye = torch.eye(3, dtype=torch.float64).expand_as(rotation)
    torch.testing.assert_close(rotation.transpose(1, 2) @ rotation, eye)
    torch.testing.assert_close(
        rotation[:, :, 2].abs(), torch.tensor([0.0, 0.0, 1.0]).expand(faces.shape[0], 3).double()
    )
    # The frame turns with the mesh: the same edge stays the x axis.
    turn = _rotation_z(0.5)
    _, turned = face_frames(vertices @ turn.T, faces, appearance.edge)
    torch.testing.assert_close(turned, turn @ rotation)


def test_subdivision_splits_every_face_in_place_and_shares_midpoints():
    vertices, faces = _sheet()
    bent = vertices.clone()
    bent[:, 2] = 0.5 * bent[:, 0] ** 2  # curved, so the fine vertices must come from the coarse ones, not a grid
    fine = Subdivision.of(faces, vertices.shape[0], 2)
    x = fine(bent)
    assert fine.children == 16 and fine.faces.shape == (16 * faces.shape[0], 3)
    # a 9×9 grid subdivided twice is the 33×33 grid: shared edges got one midpoint each
    assert x.shape == (33 * 33, 3) and int(fine.faces.max()) == 33 * 33 - 1 == fine.vertex_count(81) - 1
    torch.testing.assert_close(x[: vertices.shape[0]], bent)

    def normals(v, f):
        t = v[f]
        return torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])

    # every child lies in its parent's plane, faces the same way, and the children tile the parent
    parent = normals(bent, faces)
    child = normals(x, fine.faces).view(-1, 16, 3)
    assert bool(((child * parent[:, None]).sum(2) > 0).all())
    torch.testing.assert_close(child.sum(1), parent)  # areas (×2) add up, as vectors
    torch.testing.assert_close(x[fine.faces].mean(1).view(-1, 16, 3).mean(1), bent[faces].mean(1))
    # the map is linear in the vertices, so gradients reach the coarse vertices
    bent.requires_grad_(True)
    fine(bent).sum().backward()
    assert bool((bent.grad > 0).all())
    with pytest.raises(ValueError, match="face_subdivisions"):
        TrackConfig(face_subdivisions=4)


@pytest.fixture(scope="module")
def rigid_capture():
    vertices, faces = _sheet()
    frames = torch.stack(
        [
            vertices @ _rotation_z(0.04 * t).T + torch.tensor([0.008 * t, -0.004 * t, 0.006 * t], dtype=torch.float64)
            for t in range(4)
        ]
    )
    rig = CameraRig.look_at(
        [[0.0, 0.1, 1.0], [0.7, 0.0, 0.7], [-0.7, -0.1, 0.7]], (0.0, 0.0, 0.0), 64, 64, fov_deg=30.0
    )
    albedo = garment_albedo(vertices, faces, pattern="checks", bands=4)
    film = render_capture(frames, faces, None, None, albedo, None, rig, Lighting(), 25.0, ao_samples=2)
    return frames, faces, film


@pytest.mark.parametrize("subdivisions", [0, 1])
def test_tracking_recovers_a_rigidly_moving_sheet(device, rigid_capture, subdivisions):
    frames, faces, film = rigid_capture
    config = TrackConfig(first_iterations=60, iterations=60, lr_vertices=2e-3, face_subdivisions=subdivisions)
    seen = []
    result = track(film, frames[0], faces, None, None, config, truth=frames, progress=lambda *a: seen.append(a[0]))
    assert seen == [0, 1, 2, 3]
    assert result.vertices.shape == frames.shape and result.colors.shape == (4, faces.shape[0], 3)
    motion = float(torch.linalg.norm(frames[-1] - frames[0], dim=1).mean())
    error = float(result.vertex_error[-1])
    assert motion > 0.015
    assert error < 0.2 * motion, f"tracked to {error * 1e3:.2f} mm of a {motion * 1e3:.1f} mm motion"
    # The colours learnt on the first frame reproduce the checks: dark and light faces differ.
    assert float(result.colors[0].std(0).max()) > 0.1


def test_bad_input_is_refused(rigid_capture):
    frames, faces, film = rigid_capture
    with pytest.raises(ValueError, match="frames"):
        track(film, frames[0], faces, frames[:2], faces, TrackConfig(first_iterations=1, iterations=1))
    with pytest.raises(ValueError, match="together"):
        track(film, frames[0], faces, frames, None)
    with pytest.raises(ValueError, match="truth"):
        track(film, frames[0], faces, None, None, truth=frames[:2])
    with pytest.raises(ValueError, match="iterations"):
        TrackConfig(iterations=0)
