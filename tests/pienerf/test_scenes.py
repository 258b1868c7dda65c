import math

import numpy as np
import pytest
import torch

from kernels import backend
from kernels.raycast import MeshBVH
from pienerf import scenes
from pienerf.nerf.datasets import load_nerf_dataset

VIEWS, RESOLUTION = 8, 32


@pytest.mark.parametrize("name", scenes.SCENES)
def test_scene_mesh_is_watertight_parts_on_the_ground(name):
    mesh = scenes.scene_mesh(name)
    assert mesh.name == name and mesh.faces.shape[0] == mesh.part.shape[0] < 20_000
    assert mesh.colors.shape == mesh.vertices.shape and bool(((mesh.colors >= 0) & (mesh.colors <= 1)).all())
    for index, part_name in enumerate(mesh.part_names):
        part = mesh.part_mesh(index)
        assert part.is_watertight, f"{name}/{part_name} is not watertight"
        assert part.is_winding_consistent and part.volume > 0, f"{name}/{part_name} normals do not point outward"
    lo, hi = mesh.bounds
    assert float(lo[1]) >= -1e-6, "the object must rest on or above the ground y = 0"
    assert float(lo[1]) < 0.15, "the object must stand on the ground, not float"
    assert 0.6 < float((hi - lo).max()) < 1.3, "objects are about 1 m across"


@pytest.mark.parametrize("name", scenes.SCENES)
def test_density_is_the_same_solid_as_the_mesh(name):
    mesh = scenes.scene_mesh(name)
    density = scenes.scene_density(name)
    vertices = mesh.vertices.double()
    distance = density.signed_distance(vertices)
    # Vertices lie on their own part's surface, so on or inside the union.
    assert float(distance.max()) < 1e-5
    # Stepping 2 cm out along the normal of an exposed vertex leaves the solid.
    part = mesh.part_mesh(0)
    points = torch.from_numpy(part.vertices + 0.02 * part.vertex_normals)
    exposed = density.signed_distance(torch.from_numpy(part.vertices)) > -1e-6
    outside = density.signed_distance(points)[exposed]
    assert bool((outside > 0).all()) and float(outside.median()) == pytest.approx(0.02, abs=1e-3)
    lo, hi = density.bounds
    assert bool((lo <= vertices.amin(0)).all() and (hi >= vertices.amax(0)).all())
    # 4 mm inside, the density is near its maximum (the softness is 2 mm).
    inside = torch.from_numpy(part.vertices - 0.004 * part.vertex_normals)
    assert bool((density.density(inside) > 0.7 * density.max_density).all())


def test_unknown_scene_lists_the_names():
    with pytest.raises(ValueError, match="embedded scenes: plant, teapot"):
        scenes.scene_mesh("bunny")


def _sphere_trace(density, origin, direction, far) -> float:
    t = 0.0
    for _ in range(500):
        d = float(density.signed_distance((origin + t * direction)[None])[0])
        if d < 1e-6:
            return t
        t += d
        if t > far:
            return math.inf
    return t


@pytest.mark.parametrize("name", scenes.SCENES)
def test_render_round_trips_through_the_loader(device, name, tmp_path):
    folder = scenes.render_scene(name, views=VIEWS, resolution=RESOLUTION, cache_dir=tmp_path, progress=False)
    assert folder.parent == tmp_path / "scenes" and folder.name.startswith(f"{name}-{RESOLUTION}-{VIEWS}-")
    train = load_nerf_dataset(folder, background=(0, 0, 0))
    test = load_nerf_dataset(folder, split="test")
    assert len(train) == VIEWS - 1 and len(test) == 1 and test.names == ["./test/r_0"]
    assert train.images.shape == (VIEWS - 1, RESOLUTION, RESOLUTION, 3)
    cameras = scenes.scene_cameras(name, VIEWS, RESOLUTION)
    torch.testing.assert_close(test.cameras.c2w[0], cameras.c2w[0])
    torch.testing.assert_close(train.cameras.fx, cameras.fx[1:])

    # Alpha covers the object: every vertex projects into a covered pixel (one pixel of slack at silhouettes).
    mesh = scenes.scene_mesh(name)
    c2w = train.cameras.c2w.double()
    local = torch.einsum("nji,nvj->nvi", c2w[:, :3, :3], mesh.vertices.double()[None] - c2w[:, None, :3, 3])
    u = train.cameras.cx.double()[:, None] + train.cameras.fx.double()[:, None] * local[..., 0] / -local[..., 2]
    v = train.cameras.cy.double()[:, None] - train.cameras.fy.double()[:, None] * local[..., 1] / -local[..., 2]
    assert bool(((u > 0) & (u < RESOLUTION) & (v > 0) & (v < RESOLUTION)).all()), "the object leaves the frame"
    covered = torch.nn.functional.max_pool2d(train.alphas[:, None], 3, stride=1, padding=1)[:, 0] > 0
    view = torch.arange(len(train))[:, None].expand_as(u)
    assert bool(covered[view, v.long(), u.long()].all())
    assert float(train.alphas[:, 0, 0].max()) == 0.0 and 0.02 < float(train.alphas.mean()) < 0.6

    # Depth: every hit pixel's point lies on the solid's surface (within the tessellation's sagitta), misses are
    # transparent, and the ray at the image centre hits where sphere tracing the analytic solid does.
    density = scenes.scene_density(name)
    origins, directions = train.cameras.rays()
    depth = torch.from_numpy(np.stack([np.load(folder / f"{n}_depth.npy") for n in train.names])).reshape(-1)
    hit = torch.isfinite(depth)
    points = origins.double()[hit] + depth.double()[hit, None] * directions.double()[hit]
    distance = density.signed_distance(points).abs()
    assert float(distance.max()) < 3e-3 and float(distance.mean()) < 5e-4
    assert bool((train.alphas.reshape(-1)[hit] > 0).all()) and bool((train.alphas.reshape(-1)[~hit] < 1).all())
    bvh = MeshBVH(mesh.vertices.to(backend.torch_device()), mesh.faces.to(backend.torch_device()))
    target = 0.5 * (mesh.vertices.amin(0) + mesh.vertices.amax(0)).double()
    for position in train.cameras.centers.double():
        direction = torch.nn.functional.normalize(target - position, dim=0)
        traced = _sphere_trace(density, position, direction, far=10.0)
        cast = float(
            bvh.cast(
                position[None].float().to(backend.torch_device()), direction[None].float().to(backend.torch_device())
            ).t[0]
        )
        if math.isinf(traced):
            assert math.isinf(cast)
        else:
            assert cast == pytest.approx(traced, abs=3e-3)


def test_render_is_cached_and_atomic(device, tmp_path, monkeypatch):
    monkeypatch.setenv("PIE_CACHE_DIR", str(tmp_path))
    folder = scenes.render_scene("jelly", views=4, resolution=16, progress=False)
    assert folder.parent == tmp_path / "scenes"
    stamps = {p: p.stat().st_mtime_ns for p in folder.rglob("*")}
    assert len(stamps) > 8
    again = scenes.render_scene("jelly", views=4, resolution=16, progress=False)
    assert again == folder
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*")} == stamps, "the cached scene was rendered again"
    other = scenes.render_scene("jelly", views=4, resolution=16, seed=1, progress=False)
    assert other != folder, "different settings must not share a cache folder"
    assert sorted(p.name for p in (tmp_path / "scenes").iterdir() if p.name.startswith(".")) == []


def test_failed_render_leaves_no_folder(device, tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise RuntimeError("interrupted")

    monkeypatch.setattr(scenes, "_render_into", fail)
    with pytest.raises(RuntimeError, match="interrupted"):
        scenes.render_scene("cloth", views=2, resolution=8, cache_dir=tmp_path, progress=False)
    assert list((tmp_path / "scenes").iterdir()) == []
