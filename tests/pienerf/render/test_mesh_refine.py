"""mesh_refine: splitting long edges keeps the rest surface, its colours and the original vertices, leaves no
edge over the limit, and lets the teapot's rod preview bend (Fig. 8) where the scene's mesh can only show a chord."""

from __future__ import annotations

import pytest
import torch

from pienerf.nerf.cameras import look_at_cameras
from pienerf.render.mesh_refine import split_long_edges
from pienerf.scenes import scene_mesh
from pienerf.session import Simulation, SimulationConfig

ROD_RADIUS = 0.015  # m, the teapot's rod (pienerf.scenes)
SMOKE_TEAPOT = {"kernel_count": 6, "particle_radius": 0.05, "lloyd_iterations": 0, "drag_max_acceleration": 3000.0}


def _edges(faces: torch.Tensor) -> torch.Tensor:
    faces = faces.long()
    return torch.stack([faces, faces.roll(-1, dims=1)], dim=-1).reshape(-1, 2)


def _rod(vertices: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Vertices on the rod's cylinder (axis x = 0, y = 0.2 m along z) with rest z in [low, high] m."""
    radial = (vertices[:, 0] ** 2 + (vertices[:, 1] - 0.2) ** 2).sqrt()
    return (radial < ROD_RADIUS + 1e-3) & (vertices[:, 2] >= low) & (vertices[:, 2] <= high)


def test_split_long_edges_keeps_the_surface_and_the_original_vertices():
    trimesh = pytest.importorskip("trimesh")
    mesh = scene_mesh("teapot")
    vertices, faces, colors = split_long_edges(mesh.vertices, mesh.faces, mesh.colors, 0.03)
    edges = _edges(faces)
    assert float((vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1).max()) <= 0.03
    assert torch.equal(vertices[: len(mesh.vertices)], mesh.vertices), "the original vertices come first"
    assert torch.equal(colors[: len(mesh.colors)], mesh.colors)
    assert vertices.dtype == mesh.vertices.dtype and faces.dtype == mesh.faces.dtype
    before = trimesh.Trimesh(mesh.vertices.numpy(), mesh.faces.numpy(), process=False)
    after = trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)
    assert after.area == pytest.approx(before.area, rel=1e-6), "midpoints of straight edges add no area"
    assert after.volume == pytest.approx(before.volume, rel=1e-4)
    assert after.is_watertight and after.is_winding_consistent, "no T-junctions, windings kept"
    # The rod was one cylinder between its end rings; now it has a ring at least every 3 cm along it.
    rings = lambda v: torch.unique((v[_rod(v, 0.3, 0.7), 2] * 1e3).round()).numel()  # noqa: E731
    assert rings(mesh.vertices) == 0 and rings(vertices) >= 0.4 / 0.03


def test_split_long_edges_interpolates_attributes_along_each_split_edge():
    vertices = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.25, 0.0]])
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    colors = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    refined, refined_faces, refined_colors = split_long_edges(vertices, faces, colors, 0.3)
    assert refined_faces.shape[0] > 1 and refined.shape[0] > 3
    # Colours stay the linear function of position they were on the triangle: r = x, g = 4 y, b = 1.
    expected = torch.stack([refined[:, 0], 4.0 * refined[:, 1], torch.ones(len(refined))], dim=1)
    torch.testing.assert_close(refined_colors, expected)
    normals = torch.linalg.cross(
        refined[refined_faces[:, 1].long()] - refined[refined_faces[:, 0].long()],
        refined[refined_faces[:, 2].long()] - refined[refined_faces[:, 0].long()],
    )
    assert (normals[:, 2] > 0).all(), "every piece keeps the triangle's winding"
    assert float(normals[:, 2].sum() / 2) == pytest.approx(0.125), "the pieces tile the triangle"


def test_split_long_edges_names_bad_input():
    vertices, faces = torch.zeros(3, 3), torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match="max_edge must be a positive length"):
        split_long_edges(vertices, faces, max_edge=0.0)
    with pytest.raises(ValueError, match="faces index vertices outside"):
        split_long_edges(vertices, torch.tensor([[0, 1, 3]]), max_edge=1.0)
    with pytest.raises(ValueError, match="attributes must be"):
        split_long_edges(vertices, faces, torch.zeros(2, 3), max_edge=1.0)
    big = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="raise max_edge"):
        split_long_edges(big, faces, max_edge=1e-3, max_vertices=1000)


@pytest.mark.slow
def test_refined_teapot_preview_renders_the_rest_state_alike_and_bends_the_rod(device):
    plain = Simulation(SimulationConfig.create("teapot", **SMOKE_TEAPOT))
    refined = Simulation(SimulationConfig.create("teapot", mesh_edge_fraction=0.125, **SMOKE_TEAPOT))
    cameras = look_at_cameras([[2.2, 0.9, 0.4]], [[0.0, 0.25, 0.25]], 96, 72)
    before, after = (sim.render(cameras, 0, "mesh").rgba for sim in (plain, refined))
    assert float((before - after).abs().amax(-1).gt(1e-3).float().mean()) < 0.01, "the same picture at rest"

    mesh = refined.render_backends["mesh"]
    rest, _, _ = mesh.body_mesh()
    assert len(rest) > len(refined.mesh_vertices)
    assert torch.equal(rest[: len(refined.mesh_vertices)], refined.mesh_vertices)
    assert _rod(rest, 0.3, 0.7).sum() > 100 and _rod(refined.mesh_vertices, 0.3, 0.7).sum() == 0

    refined.grab([0.0, 0.2, 0.7])
    refined.drag_to(target=torch.tensor([0.0, 0.45, 0.62], dtype=torch.float64))
    refined.step(30)
    x = mesh.deform(refined.state.q).cpu().double()
    rest = rest.double()
    root, tip, rod = _rod(rest, 0.27, 0.28), _rod(rest, 0.715, 0.721), _rod(rest, 0.27, 0.721)
    a, b = x[root].mean(0), x[tip].mean(0)
    axis = (b - a) / (b - a).norm()
    off_chord = (x[rod] - a) - ((x[rod] - a) @ axis)[:, None] * axis
    assert float(off_chord.norm(dim=1).max()) > 2 * ROD_RADIUS, "the rod's middle leaves the chord: it bends"
    assert refined.deformed_mesh_vertices().shape == refined.mesh_vertices.shape, "the viewers' mesh is the scene's"
