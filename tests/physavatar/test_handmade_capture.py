"""The hand-made user capture: its files say what the builder says they hold, defects included."""

import json

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from physavatar.body import Body, Skeleton
from tests.physavatar.handmade_capture import Y_UP_FROM_Z_UP, build_handmade_capture, read_obj


@pytest.fixture(scope="session")
def handmade(tmp_path_factory):
    """The default capture, built once per session: ``(folder, what the builder returned)``; read it, never write."""
    folder = tmp_path_factory.mktemp("handmade")
    return folder, build_handmade_capture(folder)


def _body(path) -> tuple[Body, np.ndarray]:
    """A body mesh file in the project's y-up axes, as a :class:`Body` (for its distances), and its faces."""
    vertices, faces = read_obj(path)
    y_up = torch.from_numpy(vertices @ Y_UP_FROM_Z_UP.T)
    weights = torch.zeros(len(vertices), 22, dtype=torch.float64)
    return Body(Skeleton.mannequin(), y_up, torch.from_numpy(faces), weights), faces


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z of the cross product of 2-D vectors ``u [2]`` and ``v [N, 2]``."""
    return u[0] * v[:, 1] - u[1] * v[:, 0]


def test_files_and_index(handmade):
    folder, built = handmade
    frames, cameras, (width, height) = built["frames"], built["cameras"], built["size"]
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["fps"] == 30 and meta["up"] == "z" and (meta["w"], meta["h"]) == (width, height)
    assert sorted(p.name for p in (folder / "body").iterdir()) == [f"frame_{t:04d}.obj" for t in range(frames)]
    assert (folder / "garment.obj").is_file() and not (folder / "boundary.txt").exists()
    assert len(meta["frames"]) == frames * cameras
    seen = set()
    for record in meta["frames"]:
        c, t = record["camera"], record["time_index"]
        seen.add((c, t))
        for key in ("file_path", "mask_path"):
            with Image.open(folder / record[key]) as image:
                assert image.size == (width, height)
        np.testing.assert_array_equal(record["transform_matrix"], built["camera_list"][c]["c2w"])
        own = {k: record[k] for k in ("fl_x", "fl_y", "cx", "cy") if k in record}
        if c == built["odd_camera"]:
            assert own == {k: built["camera_list"][c][k] for k in own} and len(own) == 4
            assert all(own[k] != meta[k] for k in own)
        else:
            assert own == {}
    assert seen == {(c, t) for c in range(cameras) for t in range(frames)}
    eyes = np.array([camera["c2w"][:3, 3] for camera in built["camera_list"]])
    heights, distances = eyes[:, 2], np.linalg.norm(eyes[:, :2], axis=1)
    assert np.ptp(heights) > 0.1 and np.ptp(distances) > 0.05, "the cameras stand on a ring"


def test_body_sequence_is_one_topology_in_z_up(handmade):
    folder, built = handmade
    faces0 = None
    for t in range(built["frames"]):
        vertices, faces = read_obj(folder / "body" / f"frame_{t:04d}.obj")
        faces0 = faces if faces0 is None else faces0
        np.testing.assert_array_equal(faces, faces0)
        np.testing.assert_allclose(vertices, built["body_frames"][t], rtol=0.0, atol=5e-7)  # 6 decimals written
    assert vertices.shape == (7356, 3)
    assert vertices[:, 2].min() > -0.05 and vertices[:, 2].max() > 1.6, "the soles are not on z = 0: not z-up"


def test_template_patch_lies_inside_the_body(handmade):
    folder, built = handmade
    body, _ = _body(folder / "body" / "frame_0000.obj")
    template, faces = read_obj(folder / "garment.obj")
    np.testing.assert_array_equal(faces, built["garment_faces"])
    pushed = built["pushed"]
    rest = np.setdiff1d(np.arange(len(template)), pushed)
    np.testing.assert_allclose(template[rest], built["garment_frames"][0][rest], rtol=0.0, atol=5e-7)
    assert 0.04 <= len(pushed) / len(template) <= 0.07
    depth = -body.signed_distance(torch.from_numpy(template[pushed] @ Y_UP_FROM_Z_UP.T)).numpy()
    assert ((depth > 3e-3) & (depth < 5e-3)).all(), depth
    np.testing.assert_allclose(depth, built["push_depth"], rtol=0.0, atol=2e-6)  # the file's 1 µm rounding
    clear = body.signed_distance(torch.from_numpy(template[rest] @ Y_UP_FROM_Z_UP.T))
    assert float(clear.min()) > 0.0
    # one patch, away from the open edges and the waistband
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    pairs, uses = np.unique(edges, axis=0, return_counts=True)
    assert not np.isin(pushed, pairs[uses == 1]).any() and not np.isin(pushed, built["boundary"]).any()
    inner = np.searchsorted(pushed, pairs[np.isin(pairs, pushed).all(1)])
    graph = coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(len(pushed),) * 2)
    assert connected_components(graph, directed=False)[0] == 1


@pytest.mark.parametrize("t", [0, -1])
def test_arm_passes_into_the_chest(handmade, t):
    """Some upper-arm vertices lie inside the rest of the body (winding number ~1½ there, ½ on the own surface),
    2–4 cm below the chest's surface."""
    folder, built = handmade
    t = t % built["frames"]
    body, faces = _body(folder / "body" / f"frame_{t:04d}.obj")
    arm = np.zeros(len(body.vertices), dtype=bool)
    arm[built["arm_vertices"]] = True
    near = cKDTree(body.vertices[~arm].numpy()).query(body.vertices[arm].numpy())[0] < 0.05
    candidates = np.flatnonzero(arm)[near]
    inside = candidates[body.winding_number(body.vertices[candidates].float()).numpy() > 1.25]
    assert len(inside) >= 10
    if t == 0:
        assert set(inside.tolist()) <= set(built["intersecting"].tolist())
    torso = Body(body.skeleton, body.vertices, torch.from_numpy(faces[~arm[faces].any(1)]), body.weights)
    depth = float(torso.closest_points(body.vertices[inside])[1].max())
    assert 0.02 <= depth <= 0.04, depth


def test_masks_match_the_index(handmade):
    """Every garment pixel of a mask has its centre inside the garment's triangles projected with the json's z-up
    pose and intrinsics (the mask also loses pixels where the body hides the garment)."""
    folder, built = handmade
    meta = json.loads((folder / "transforms.json").read_text())
    faces = built["garment_faces"]
    width, height = built["size"]
    centres = np.stack(np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5), -1).reshape(-1, 2)
    for record in meta["frames"]:
        k = {key: record.get(key, meta[key]) for key in ("fl_x", "fl_y", "cx", "cy")}
        c2w = np.asarray(record["transform_matrix"])
        local = (built["garment_frames"][record["time_index"]] - c2w[:3, 3]) @ c2w[:3, :3]
        pixels = np.stack(
            [k["cx"] + k["fl_x"] * local[:, 0] / -local[:, 2], k["cy"] - k["fl_y"] * local[:, 1] / -local[:, 2]], 1
        )
        covered = np.zeros(len(centres), dtype=bool)
        for a, b, c in pixels[faces]:
            d1, d2, d3 = (_cross(q - p, centres - p) for p, q in ((a, b), (b, c), (c, a)))
            covered |= ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
        with Image.open(folder / record["mask_path"]) as image:
            mask = np.asarray(image).reshape(-1) >= 128
        assert mask.sum() > 0.05 * mask.size
        # a ray through a pixel centre hits the garment exactly when the centre lies in a projected triangle
        assert (mask & ~covered).sum() == 0, record["mask_path"]
        assert (covered & ~mask).sum() < 0.25 * covered.sum(), record["mask_path"]  # the body hides 2–8 %


def test_boundary_file_on_request(tmp_path):
    built = build_handmade_capture(tmp_path, frames=2, cameras=2, size=(16, 16), boundary=True)
    lines = (tmp_path / "boundary.txt").read_text().splitlines()
    assert lines[0].startswith("#")
    index = np.array([int(x) for line in lines[1:] for x in line.split()])
    np.testing.assert_array_equal(index, built["boundary"])
    assert 0 < len(index) < len(built["template"])
    with pytest.raises(ValueError, match="frames >= 2"):
        build_handmade_capture(tmp_path / "none", frames=1)
