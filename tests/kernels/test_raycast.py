import math

import pytest
import torch
import trimesh

from kernels import backend
from kernels.raycast import MeshBVH, cast_rays, shade
from kernels.reference import raycast as reference


def _bumpy_sphere(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """An icosphere with randomly displaced vertices: a small, non-convex closed mesh."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    generator = torch.Generator().manual_seed(seed)
    vertices = torch.tensor(mesh.vertices, dtype=torch.float32)
    vertices = vertices * (1.0 + 0.25 * torch.rand(vertices.shape[0], 1, generator=generator))
    return vertices, torch.tensor(mesh.faces, dtype=torch.int32)


def _rays(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from a sphere of radius 3 toward random points within 1.6 of the origin (some miss the mesh)."""
    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 3.0
    targets = (torch.rand(count, 3, generator=generator) * 2.0 - 1.0) * 1.6
    return origins, (targets - origins) * 0.7  # not unit: the kernel normalises


def _on_device(*tensors):
    return [t.to(backend.torch_device()) for t in tensors]


def test_cast_matches_brute_force(device):
    vertices, faces = _bumpy_sphere(0)
    origins, directions = _rays(800, 1)
    t, face, bary = cast_rays(*_on_device(vertices, faces, origins, directions))
    t_ref, face_ref, bary_ref = reference.cast_rays(vertices, faces, origins, directions)
    hit = face_ref >= 0
    assert 0.2 < float(hit.float().mean()) < 0.95, "the test needs both hits and misses"
    assert torch.equal(face.cpu().long(), face_ref)
    torch.testing.assert_close(t.cpu().double()[hit], t_ref[hit], rtol=1e-5, atol=1e-5)
    assert bool(torch.isinf(t.cpu()[~hit]).all())
    torch.testing.assert_close(bary.cpu().double(), bary_ref, rtol=0, atol=2e-4)
    # The barycentrics reproduce the hit point at distance t along the unit ray.
    corners = vertices.double()[faces.long()[face_ref[hit]]]
    b = bary_ref[hit]
    point = (1 - b[:, :1] - b[:, 1:]) * corners[:, 0] + b[:, :1] * corners[:, 1] + b[:, 1:] * corners[:, 2]
    unit = torch.nn.functional.normalize(directions.double()[hit], dim=-1)
    torch.testing.assert_close(point, origins.double()[hit] + t_ref[hit, None] * unit)


def test_closest_points_match_brute_force(device):
    vertices, faces = _bumpy_sphere(0)
    generator = torch.Generator().manual_seed(3)
    points = (torch.rand(600, 3, generator=generator) * 2.0 - 1.0) * 2.0  # inside, near and far from the surface
    bvh = MeshBVH(*_on_device(vertices, faces))
    found = bvh.closest(points.to(backend.torch_device()))
    expected = reference.closest_points(vertices, faces, points)
    torch.testing.assert_close(found.distance.cpu().double(), expected, rtol=1e-4, atol=2e-6)
    # Face and barycentrics name a surface point at that distance.
    corners = vertices.double()[faces.long()[found.face.cpu().long()]]
    b = found.bary.cpu().double()
    surface = (1 - b[:, :1] - b[:, 1:]) * corners[:, 0] + b[:, :1] * corners[:, 1] + b[:, 1:] * corners[:, 2]
    torch.testing.assert_close(torch.linalg.norm(surface - points.double(), dim=1), expected, rtol=1e-4, atol=2e-6)
    near = bvh.closest(points.to(backend.torch_device()), max_distance=0.05)
    far = expected >= 0.05
    assert bool(far.any()) and bool(torch.isinf(near.distance.cpu()[far]).all())
    assert bool((near.face.cpu()[far] == -1).all())


@pytest.mark.parametrize("method", ["auto", "tree", "direct"])
def test_inside_matches_the_exact_winding_number(device, method):
    vertices, faces = _bumpy_sphere(1)  # 320 faces: two chunks of the direct sum, the second one partial
    generator = torch.Generator().manual_seed(5)
    points = (torch.rand(800, 3, generator=generator) * 2.0 - 1.0) * 1.5
    exact = reference.winding_number(vertices, faces, points)
    clear = (exact - 0.5).abs() > 0.05  # leave out points on the surface itself, where the sign is a tie
    bvh = MeshBVH(*_on_device(vertices, faces), winding_numbers=True)
    inside = bvh.inside(points.to(backend.torch_device()), method=method).cpu()
    assert 100 < int((exact > 0.5).sum()) < 700
    assert torch.equal(inside[clear], (exact > 0.5)[clear])
    assert bvh.inside(points[:0].to(backend.torch_device()), method=method).shape == (0,)
    with pytest.raises(ValueError, match="winding_numbers=True"):
        MeshBVH(*_on_device(vertices, faces)).inside(points.to(backend.torch_device()), method=method)


def test_inside_names_an_unknown_method(device):
    vertices, faces = _bumpy_sphere(1)
    bvh = MeshBVH(*_on_device(vertices, faces), winding_numbers=True)
    with pytest.raises(ValueError, match="'auto', 'tree' or 'direct'"):
        bvh.inside(vertices.to(backend.torch_device()), method="exact")


def test_max_distance_turns_far_hits_into_misses(device):
    vertices, faces = _bumpy_sphere(2)
    origins, directions = _rays(300, 3)
    full = cast_rays(*_on_device(vertices, faces, origins, directions))
    limit = float(full.t[torch.isfinite(full.t)].median())
    near = cast_rays(*_on_device(vertices, faces, origins, directions), max_distance=limit)
    kept = full.t < limit
    assert torch.equal(near.face[kept], full.face[kept])
    assert bool((near.face[~kept] == -1).all()) and bool(torch.isinf(near.t[~kept]).all())


def test_refit_follows_a_deforming_mesh(device):
    vertices, faces = _bumpy_sphere(4)
    origins, directions = _rays(500, 5)
    bvh = MeshBVH(*_on_device(vertices, faces))
    moved = vertices * torch.tensor([1.4, 0.6, 1.0]) + torch.tensor([0.3, 0.0, -0.2])
    bvh.refit(moved.to(backend.torch_device()))
    t, face, _ = bvh.cast(*_on_device(origins, directions))
    t_ref, face_ref, _ = reference.cast_rays(moved, faces, origins, directions)
    assert torch.equal(face.cpu().long(), face_ref)
    hit = face_ref >= 0
    torch.testing.assert_close(t.cpu().double()[hit], t_ref[hit], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("face_colors", [False, True])
def test_shade_matches_reference_with_self_shadowing(device, face_colors):
    vertices, faces = _bumpy_sphere(6)
    # A second, floating blob above the first shadows part of it.
    vertices = torch.cat([vertices, vertices * 0.4 + torch.tensor([0.3, 2.0, 0.2])])
    faces = torch.cat([faces, faces + vertices.shape[0] // 2])
    generator = torch.Generator().manual_seed(7)
    colors = torch.rand(faces.shape[0] if face_colors else vertices.shape[0], 3, generator=generator)
    origins, directions = _rays(1500, 8)
    light = (0.2, 1.0, 0.1)
    out = shade(
        MeshBVH(*_on_device(vertices, faces)),
        *_on_device(origins, directions, colors),
        face_colors=face_colors,
        light_direction=light,
    )
    rgba_ref, depth_ref = reference.shade(
        vertices, faces, origins, directions, colors, face_colors=face_colors, light_direction=light
    )
    hit = torch.isfinite(depth_ref)
    torch.testing.assert_close(out.depth.cpu().double()[hit], depth_ref[hit], rtol=1e-5, atol=1e-5)
    assert bool(torch.isinf(out.depth.cpu()[~hit]).all())
    # Shadow rays that graze an edge may decide differently in float32; allow a handful of such pixels.
    differs = (out.rgba.cpu().double() - rgba_ref).abs().amax(dim=-1) > 1e-4
    assert int(differs.sum()) <= 3
    lit = rgba_ref[hit, :3].sum(-1) > 0
    assert bool(lit.any())
    shadowed = hit & (rgba_ref[:, :3] < 0.3 * colors.max() + 1e-6).all(-1)
    assert int(shadowed.sum()) > 10, "the configuration must shadow some hits"


def _ground_and_quad() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    vertices = torch.tensor(
        [
            [-2, 0, -2],
            [2, 0, -2],
            [2, 0, 2],
            [-2, 0, 2],  # ground y = 0
            [-0.25, 0.5, -0.25],
            [0.25, 0.5, -0.25],
            [0.25, 0.5, 0.25],
            [-0.25, 0.5, 0.25],
        ],  # quad above it
        dtype=torch.float32,
    )
    faces = torch.tensor([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], dtype=torch.int32)
    colors = torch.full((8, 3), 0.8)
    return vertices, faces, colors


def test_quad_shadows_the_ground_below_it(device):
    vertices, faces, colors = _ground_and_quad()
    # Oblique rays that pass beside the quad and land on the ground at x, with z = 0.
    x = torch.tensor([-0.2, 0.0, 0.15, -1.0, 0.6, 1.5])
    targets = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], dim=-1)
    origins = targets + torch.tensor([3.0, 2.0, 0.0])
    bvh = MeshBVH(*_on_device(vertices, faces))
    out = shade(
        bvh,
        *_on_device(origins, targets - origins, colors),
        light_direction=(0.0, 1.0, 0.0),
        ambient=0.25,
        diffuse=0.75,
    )
    rgb = out.rgba[:, :3].cpu()
    torch.testing.assert_close(out.depth.cpu(), torch.full((6,), math.sqrt(13.0)), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(rgb[:3], torch.full((3, 3), 0.8 * 0.25))  # under the quad: ambient only
    torch.testing.assert_close(rgb[3:], torch.full((3, 3), 0.8))  # in the open: fully lit, no acne
    assert bool((out.rgba[:, 3] == 1).all())
    unshadowed = shade(
        bvh,
        *_on_device(origins, targets - origins, colors),
        light_direction=(0.0, 1.0, 0.0),
        ambient=0.25,
        diffuse=0.75,
        shadows=False,
    )
    torch.testing.assert_close(unshadowed.rgba[:, :3].cpu(), torch.full((6, 3), 0.8))
    # The quad itself, seen from straight above, is lit; a ray into the sky is transparent with infinite depth.
    sky = shade(
        bvh,
        *_on_device(
            torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]), torch.tensor([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]), colors
        ),
        light_direction=(0.0, 1.0, 0.0),
        ambient=0.25,
        diffuse=0.75,
    )
    torch.testing.assert_close(sky.rgba.cpu(), torch.tensor([[0.8, 0.8, 0.8, 1.0], [0.0, 0.0, 0.0, 0.0]]))
    assert float(sky.depth[0]) == pytest.approx(0.5) and math.isinf(float(sky.depth[1]))


def test_bad_input_is_refused_with_the_fix(device):
    vertices, faces, colors = _ground_and_quad()
    vertices, faces, colors = _on_device(vertices, faces, colors)
    with pytest.raises(ValueError, match="faces index vertices 0..7"):
        MeshBVH(vertices, faces + 5)
    bvh = MeshBVH(vertices, faces)
    with pytest.raises(ValueError, match="same mesh"):
        bvh.refit(vertices[:4])
    origins = torch.zeros(3, 3, device=vertices.device)
    with pytest.raises(ValueError, match="one row per ray"):
        bvh.cast(origins, origins[:2])
    with pytest.raises(ValueError, match="face_colors=True"):
        shade(bvh, origins, origins + 1, colors[:4])
    with pytest.raises(ValueError, match="light_direction"):
        shade(bvh, origins, origins + 1, colors, light_direction=(0, 0, 0))
