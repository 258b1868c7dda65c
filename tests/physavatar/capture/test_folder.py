"""A researcher's capture folder, written by hand, read into the project's y-up axes."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from physavatar.capture import CameraRig, CaptureFolder, load_capture_folder
from tests.physavatar.capture.handmade import (
    CAMERAS,
    FPS,
    FRAMES,
    HEIGHT,
    RING,
    WIDTH,
    body_mesh,
    camera_rig,
    edit_json,
    frame_of,
    garment_mesh,
    image_name,
    to_z_up,
    write_capture_folder,
    write_obj,
)
from tests.physavatar.handmade_capture import Y_UP_FROM_Z_UP


def test_a_y_up_folder_loads_as_written(tmp_path):
    write_capture_folder(tmp_path / "cap")
    loaded = load_capture_folder(tmp_path / "cap")
    assert isinstance(loaded, CaptureFolder) and loaded.path == tmp_path / "cap" and loaded.up == "y"
    film = loaded.film
    assert film.images.shape == (FRAMES, CAMERAS, HEIGHT, WIDTH, 3) and film.images.dtype == torch.float32
    assert film.masks.shape == (FRAMES, CAMERAS, HEIGHT, WIDTH) and film.masks.dtype == torch.bool
    assert film.fps == FPS and film.lighting is None
    assert int(film.masks[0, 0].sum()) == 8 * 12  # the white rectangle of every mask
    assert torch.equal(film.rig.c2w, camera_rig().c2w)
    assert torch.equal(film.rig.intrinsics, camera_rig().intrinsics)
    body = np.stack([body_mesh(t)[0] for t in range(FRAMES)])
    assert loaded.body_frames.dtype == torch.float64 and torch.equal(loaded.body_frames, torch.from_numpy(body))
    assert torch.equal(loaded.body_faces, torch.from_numpy(body_mesh()[1]).long())
    vertices, faces = garment_mesh()
    assert torch.equal(loaded.garment_vertices, torch.from_numpy(vertices))
    assert torch.equal(loaded.garment_faces, torch.from_numpy(faces).long())
    assert loaded.boundary is None and loaded.body_masks is None
    points = torch.rand(5, 3, dtype=torch.float64)
    assert loaded.to_capture_axes(points) is points and loaded.from_capture_axes(points) is points


def test_a_z_up_folder_loads_into_the_same_y_up_scene_seen_at_the_same_pixels(tmp_path):
    write_capture_folder(tmp_path / "y")
    y_up = load_capture_folder(tmp_path / "y")
    meta = write_capture_folder(tmp_path / "z", up="z")
    z_up = load_capture_folder(tmp_path / "z")
    assert z_up.up == "z"
    # (x, y, z) -> (x, z, -y) is a signed permutation: the turned scene is the y-up one, bit for bit
    assert torch.equal(z_up.body_frames, y_up.body_frames)
    assert torch.equal(z_up.garment_vertices, y_up.garment_vertices)
    assert torch.equal(z_up.film.rig.c2w, y_up.film.rig.c2w)
    assert torch.equal(z_up.film.images, y_up.film.images)
    # a point projects to the same pixel through the file's z-up cameras and through the loaded y-up ones
    poses = [frame_of(meta, c, 0)["transform_matrix"] for c in range(CAMERAS)]
    file_rig = CameraRig(torch.tensor(poses, dtype=torch.float64), *_sizes())
    points = torch.from_numpy(to_z_up(garment_mesh()[0]))
    before, depth_before = file_rig.project(points)
    after, depth_after = z_up.film.rig.project(z_up.from_capture_axes(points))
    torch.testing.assert_close(after, before, rtol=0.0, atol=1e-12 * WIDTH)
    torch.testing.assert_close(depth_after, depth_before, rtol=0.0, atol=1e-14 * 3.0)
    assert torch.equal(z_up.to_capture_axes(z_up.garment_vertices), points)
    assert torch.equal(z_up.from_capture_axes(points), z_up.garment_vertices)


def _sizes():
    rig = camera_rig()
    return WIDTH, HEIGHT, rig.fx, rig.fy, rig.cx, rig.cy


def test_boundary_indices_of_the_file_follow_the_weld(tmp_path):
    """The file has a stray vertex first (in no face: trimesh drops it) and the tube's seam split in two (a copy of
    every ring's vertex 0 at the end, used by the last segment): welding merges the copies, shifting indices."""
    folder = tmp_path / "cap"
    write_capture_folder(folder)
    vertices, faces = garment_mesh()
    seam = np.arange(3) * RING  # each ring's first vertex
    copy = {int(v): len(vertices) + r for r, v in enumerate(seam)}
    split = faces.copy()
    for k in range(len(split)):
        if (k // 2) % RING == RING - 1:  # the two faces of each ring's last segment use the copies
            split[k] = [copy.get(int(v), int(v)) for v in split[k]]
    file_vertices = np.concatenate([[[5.0, 5.0, 5.0]], vertices, vertices[seam]])
    write_obj(folder / "garment.obj", file_vertices, split + 1)
    # ring 0's vertices 0 and 1, ring 1's vertex 0, and the copies of ring 0's and ring 1's vertex 0
    listed = [1, 2, 1 + RING, len(file_vertices) - 3, len(file_vertices) - 2]
    (folder / "boundary.txt").write_text(
        f"# the top of the tube\n{listed[0]} {listed[1]}\n\t{listed[2]}  # and below\n{listed[3]}\n{listed[4]}\n"
    )
    loaded = load_capture_folder(folder)
    assert loaded.garment_vertices.shape == (3 * RING, 3) and loaded.garment_faces.shape == faces.shape
    expected = {tuple(p) for p in file_vertices[listed]}  # 5 file indices, 3 positions
    assert len(expected) == 3 and len(loaded.boundary) == 3 and loaded.boundary.dtype == torch.int64
    assert {tuple(p) for p in loaded.garment_vertices[loaded.boundary].tolist()} == expected


def test_per_camera_intrinsics_body_list_natural_order_body_masks_and_progress(tmp_path):
    folder = tmp_path / "cap"
    write_capture_folder(folder)
    for t, name in enumerate(("2.obj", "10.obj", "1.obj")):  # natural order: 1, 2, 10 (time 2, 0, 1)
        (folder / "body" / f"{t:04d}.obj").rename(folder / "body" / f"x{name}")
    (folder / "body_masks").mkdir()
    for f in (folder / "masks").iterdir():
        (folder / "body_masks" / f.name).write_bytes(f.read_bytes())

    def change(meta):
        for frame in meta["frames"]:
            frame["body_mask_path"] = frame["mask_path"].replace("masks/", "body_masks/")
            if frame["camera"] == 1:
                frame.update(fl_x=30.5, cy=11.0)

    edit_json(folder, change)
    calls = []
    loaded = load_capture_folder(folder / "transforms.json", progress=lambda done, total: calls.append((done, total)))
    assert calls == [(k, FRAMES * CAMERAS) for k in range(1, FRAMES * CAMERAS + 1)]
    expected = camera_rig().intrinsics
    expected[1, 0], expected[1, 3] = 30.5, 11.0
    assert torch.equal(loaded.film.rig.intrinsics, expected)
    assert torch.equal(loaded.body_masks, loaded.film.masks)
    order = [2, 0, 1]  # x1.obj, x2.obj, x10.obj
    assert torch.equal(loaded.body_frames, torch.from_numpy(np.stack([body_mesh(t)[0] for t in order])))

    edit_json(folder, lambda meta: meta.update(body=[f"body/x{n}.obj" for n in ("2", "10", "1")]))  # as listed
    body = np.stack([body_mesh(t)[0] for t in range(FRAMES)])
    assert torch.equal(load_capture_folder(folder).body_frames, torch.from_numpy(body))


@pytest.mark.parametrize(
    ("damage", "error", "message"),
    [
        (
            lambda f: edit_json(f, lambda m: m.update(body=["body/0000.obj", "body/0009.obj", "body/0002.obj"])),
            FileNotFoundError,
            r"body/0009\.obj: .*does not exist; add",
        ),
        (lambda f: (f / "body" / "0001.obj").unlink(), ValueError, r"body/: 2 body meshes for 3 time indices; give"),
        (lambda f: edit_json(f, lambda m: m.pop("fps")), ValueError, r"transforms\.json: lacks the key 'fps'; add"),
        (lambda f: (f / "images" / image_name(1, 2)).unlink(), FileNotFoundError, r"images/c1_t2\.png"),
        (
            lambda f: (f / "boundary.txt").write_text("3 99"),
            ValueError,
            r"boundary\.txt: 1 indices are outside 0\.\.35",
        ),
    ],
    ids=["body file", "body count", "fps", "image", "boundary"],
)
def test_the_loader_names_the_first_problem_and_its_fix(tmp_path, damage, error, message):
    folder = tmp_path / "cap"
    write_capture_folder(folder)
    damage(folder)
    with pytest.raises(error, match=message):
        load_capture_folder(folder)


def test_the_json_written_by_hand_is_plain_json(tmp_path):
    meta = write_capture_folder(tmp_path / "cap")
    assert json.loads((tmp_path / "cap" / "transforms.json").read_text()) == meta


def test_a_capture_built_elsewhere_loads_turned_to_y_up(handmade):
    """The hand-made capture (another builder of the same format, z-up, 6-decimal OBJ files): meshes, boundary,
    masks and cameras come back in y-up axes, each garment vertex on the pixel the file's cameras put it."""
    folder, built = handmade
    loaded = load_capture_folder(folder)
    assert loaded.up == "z" and loaded.film.fps == built["fps"]
    turn = Y_UP_FROM_Z_UP.T  # row vectors: p_y = p_z @ turn
    files = 0.5e-6 + 1e-15 * 2.0  # m: 6 decimals, plus the rounding of a coordinate within 2 m
    np.testing.assert_allclose(loaded.body_frames.numpy(), built["body_frames"] @ turn, rtol=0.0, atol=files)
    np.testing.assert_allclose(loaded.garment_vertices.numpy(), built["template"] @ turn, rtol=0.0, atol=files)
    assert np.array_equal(loaded.body_faces.numpy(), built["body_faces"])
    assert np.array_equal(loaded.garment_faces.numpy(), built["garment_faces"])
    assert np.array_equal(loaded.boundary.numpy(), np.unique(built["boundary"]))  # no weld: the file's own indices
    for c, camera in enumerate(built["camera_list"]):
        assert loaded.film.rig.intrinsics[c].tolist() == [camera[k] for k in ("fl_x", "fl_y", "cx", "cy")]
        for t in range(built["frames"]):
            mask = np.asarray(Image.open(folder / "masks" / f"cam{c}_t{t}.png").convert("L")) >= 128
            assert np.array_equal(loaded.film.masks[t, c].numpy(), mask)
    file_rig = CameraRig(
        torch.from_numpy(np.stack([camera["c2w"] for camera in built["camera_list"]])),
        *built["size"],
        *loaded.film.rig.intrinsics.unbind(1),
    )
    points = torch.from_numpy(built["template"])
    before, _ = file_rig.project(points)
    after, _ = loaded.film.rig.project(loaded.from_capture_axes(points))
    torch.testing.assert_close(after, before, rtol=0.0, atol=1e-9)  # px: inverses of two exact turns of one matrix
