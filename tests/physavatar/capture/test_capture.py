"""Synthetic multi-view capture: cameras, ray-traced shading (shadows, ambient occlusion) and the capture files."""

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from kernels.raycast import cast_rays
from physavatar.capture import (
    CameraRig,
    Capture,
    Lighting,
    dressed_scene,
    garment_albedo,
    hemisphere_directions,
    load_capture,
    load_truth,
    render_capture,
    shade_mesh,
    write_capture,
)
from physavatar.shapes import grid_sheet, icosphere

SHEET_Y = -0.35  # m, height of the horizontal sheet under the ball
SUN = (0.3, 1.0, 0.2)


def _sheet() -> tuple[torch.Tensor, torch.Tensor]:
    """A 0.8 m square horizontal sheet at y = SHEET_Y, centred under the origin (9 × 9 vertices)."""
    v, f = grid_sheet(9, 9, 0.1)
    return torch.stack([v[:, 0] - 0.4, torch.full_like(v[:, 0], SHEET_Y), v[:, 1] - 0.4], 1), f


def _ball() -> tuple[torch.Tensor, torch.Tensor]:
    return icosphere(2, 0.2)


def _rig(count: int = 3) -> CameraRig:
    return CameraRig.ring(count, 1.3, 1.0, (0.0, -0.3, 0.0), 48, 40, 40.0)


def _calibrated_rig() -> CameraRig:
    """Three cameras of :func:`_rig`'s ring, each with its own focal lengths and principal point (px)."""
    ring = _rig()
    return CameraRig(
        ring.c2w, 48, 40, [40.0 / 3.0, 61.7, 52.123456789], (55.0, 60.1, 49.9), torch.tensor([24.0, 23.1, 25.7]), 20.3
    )


def _small_capture(frames: int = 2) -> tuple[Capture, dict]:
    sheet, sheet_faces = _sheet()
    ball, ball_faces = _ball()
    garment = torch.stack([sheet + torch.tensor([0.0, 0.01 * t, 0.0]) for t in range(frames)])
    body = torch.stack([ball + torch.tensor([0.1 * t, 0.0, 0.0]) for t in range(frames)])
    albedo = garment_albedo(sheet, sheet_faces)
    lighting = Lighting((0.45, 0.45, 0.5), (0.6, 0.55, 0.5), SUN)
    capture = render_capture(garment, sheet_faces, body, ball_faces, albedo, (0.7, 0.7, 0.7), _rig(), lighting, 25.0)
    truth = {
        "garment_frames": garment,
        "garment_faces": sheet_faces,
        "body_frames": body,
        "albedo": albedo,
        "params": {"density": 0.2, "stretch": 50.0},
        "fps": 25.0,
    }
    return capture, truth


def test_ring_cameras_look_at_target_from_the_circle():
    target = torch.tensor([0.1, 0.9, -0.2], dtype=torch.float64)
    rig = CameraRig.ring(5, 2.0, 0.4, target, 64, 48, 50.0)
    assert len(rig) == 5 and rig.c2w.shape == (5, 4, 4) and rig.c2w.dtype == torch.float64
    offset = rig.centers - target
    torch.testing.assert_close(offset[:, [0, 2]].norm(dim=1), torch.full((5,), 2.0, dtype=torch.float64))
    torch.testing.assert_close(offset[:, 1], torch.full((5,), 0.4, dtype=torch.float64))
    torch.testing.assert_close(rig.world_to_camera() @ rig.c2w, torch.eye(4, dtype=torch.float64).expand(5, 4, 4))
    pixels, depth = rig.project(target[None])
    torch.testing.assert_close(pixels[:, 0], torch.tensor([[32.0, 24.0]], dtype=torch.float64).expand(5, 2))
    torch.testing.assert_close(depth[:, 0], offset.norm(dim=1))
    # A point above the target appears above the image centre (y down), a point behind a camera has depth < 0.
    above, _ = rig.project((target + torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64))[None])
    assert bool((above[:, 0, 1] < 24.0).all())
    _, behind = rig.project((2.0 * rig.centers[0] - target)[None])
    assert float(behind[0, 0]) < 0.0


def test_intrinsics_are_per_camera_tensors_given_as_floats_or_sequences():
    rig = _calibrated_rig()
    for name in ("fx", "fy", "cx", "cy"):
        value = getattr(rig, name)
        assert value.shape == (3,) and value.dtype == torch.float64 and value.device.type == "cpu"
    assert rig.intrinsics.shape == (3, 4) and rig.intrinsics.dtype == torch.float64
    cx = float(torch.tensor(23.1))  # cx came as a float32 tensor: widened exactly
    assert torch.equal(rig.intrinsics[1], torch.tensor([61.7, 60.1, cx, 20.3], dtype=torch.float64))
    assert not rig.shared_intrinsics
    ring = _rig()
    assert ring.shared_intrinsics and torch.equal(ring.intrinsics, ring.intrinsics[:1].expand(3, 4))
    focal = torch.tensor([50.0, 51.0, 52.0], requires_grad=True)
    copied = CameraRig(ring.c2w, 48, 40, focal, 50.0, 24.0, 20.0)
    assert not copied.fx.requires_grad
    focal.data[0] = 99.0  # the rig keeps its own copy
    assert float(copied.fx[0]) == 50.0
    with pytest.raises(ValueError, match=r"fy must be one number for every camera or 3 numbers.*length-3"):
        CameraRig(ring.c2w, 48, 40, 50.0, [50.0, 51.0], 24.0, 20.0)
    with pytest.raises(ValueError, match=r"fx must be finite \(focal lengths positive\)"):
        CameraRig(ring.c2w, 48, 40, [50.0, 0.0, 50.0], 50.0, 24.0, 20.0)
    with pytest.raises(ValueError, match=r"cx must be finite"):
        CameraRig(ring.c2w, 48, 40, 50.0, 50.0, [24.0, float("nan"), 24.0], 20.0)
    with pytest.raises(ValueError, match=r"cy must be numbers in pixels.*length-3 sequence"):
        CameraRig(ring.c2w, 48, 40, 50.0, 50.0, 24.0, "centre")


def test_each_camera_rays_and_projects_with_its_own_intrinsics():
    """A rig of cameras calibrated separately computes camera c as the rig of camera c alone would, bit for bit."""
    rig = _calibrated_rig()
    points = torch.tensor([[0.1, -0.2, 0.05], [-0.3, -0.35, 0.2], [0.0, 0.1, -0.25]], dtype=torch.float64)
    pixels, depth = rig.project(points)
    for c in range(len(rig)):
        alone = CameraRig(rig.c2w[c : c + 1], rig.width, rig.height, *rig.intrinsics[c].tolist())
        for mine, theirs in zip(rig.rays(c, "cpu"), alone.rays(0, "cpu"), strict=True):
            assert torch.equal(mine, theirs)
        # The same poses sharing camera c's intrinsics: one batch of pose arithmetic (a batched matrix product may
        # round differently from a single camera's), so camera c's pixels agree exactly.
        shared = CameraRig(rig.c2w, rig.width, rig.height, *rig.intrinsics[c].tolist())
        shared_pixels, shared_depth = shared.project(points)
        assert torch.equal(pixels[c], shared_pixels[c]) and torch.equal(depth[c], shared_depth[c])
        assert rig.project(points.float())[0][c].dtype == torch.float32
        # A point 1.5 m along the ray through a pixel centre projects to that centre, up to the rounding of the
        # float32 rays (origins ~1.6 m away): a few ε₃₂ · f px.
        origins, directions = rig.rays(c, "cpu")
        on_ray = (origins + 1.5 * directions).double()
        pixel = torch.arange(rig.height * rig.width)
        centres = torch.stack([pixel % rig.width, pixel // rig.width], 1).double() + 0.5
        tolerance = 16 * 2**-24 * float(rig.fx[c].max(rig.fy[c]))
        torch.testing.assert_close(rig.project(on_ray)[0][c], centres, atol=tolerance, rtol=0)
    assert not torch.equal(pixels[0], CameraRig(rig.c2w, 48, 40, *rig.intrinsics[1].tolist()).project(points)[0][0])


def test_projection_of_a_pixels_first_hit_is_its_centre(device):
    sheet, sheet_faces = _sheet()
    ball, ball_faces = _ball()
    vertices, faces, _ = dressed_scene(sheet, sheet_faces, ball, ball_faces)
    rig = _rig()
    for c in range(len(rig)):
        origins, directions = rig.rays(c)
        assert origins.shape == directions.shape == (rig.height * rig.width, 3)
        torch.testing.assert_close(directions.norm(dim=1).cpu(), torch.ones(len(directions)))
        hits = cast_rays(vertices[0].to(origins.device), faces.to(origins.device), origins, directions)
        hit = torch.nonzero(hits.face >= 0).flatten()
        assert len(hit) > 100
        points = (origins[hit] + hits.t[hit, None] * directions[hit]).double().cpu().requires_grad_(True)
        pixels, depth = rig.project(points)
        expected = torch.stack([hit % rig.width, hit // rig.width], 1).double().cpu() + 0.5
        torch.testing.assert_close(pixels[c].detach(), expected, atol=2e-3, rtol=0)
        forward = -rig.c2w[c, :3, 2]
        torch.testing.assert_close(
            depth[c].detach(),
            hits.t[hit].double().cpu() * (directions[hit].double().cpu() @ forward),
            atol=1e-5,
            rtol=1e-5,
        )
        pixels[c].sum().backward()  # differentiable in the points
        assert bool(torch.isfinite(points.grad).all()) and float(points.grad.abs().sum()) > 0.0
        # float32 points give float32 pixels
        assert rig.project(points.detach().float())[0].dtype == torch.float32


def test_shadow_of_the_body_is_darker_and_masks_mark_the_garment(device):
    sheet, sheet_faces = _sheet()
    ball, ball_faces = _ball()
    vertices, faces, garment_face_count = dressed_scene(sheet, sheet_faces, ball, ball_faces)
    albedo = torch.cat(
        [torch.full((garment_face_count, 3), 0.8), torch.full((len(faces) - garment_face_count, 3), 0.6)]
    )
    lighting = Lighting((0.3, 0.3, 0.3), (0.6, 0.6, 0.6), SUN)
    rig = _rig()
    view = shade_mesh(vertices[0], faces, albedo, rig, 0, lighting, ao_samples=16)
    sun = torch.tensor(lighting.sun_direction, dtype=torch.float64)
    in_shadow = (-sun * (0.0 - SHEET_Y) / sun[1])[None]  # the ball's centre projected along the sun onto the sheet
    lit = torch.tensor([[0.3, SHEET_Y, 0.35]], dtype=torch.float64)
    centre = torch.zeros(1, 3, dtype=torch.float64)

    def pixel_of(point):
        xy = rig.project(point)[0][0, 0]
        return int(xy[1]), int(xy[0])

    shadow_px, lit_px, ball_px = pixel_of(in_shadow), pixel_of(lit), pixel_of(centre)
    face = view.face.cpu()
    assert 0 <= int(face[shadow_px]) < garment_face_count and 0 <= int(face[lit_px]) < garment_face_count
    assert int(face[ball_px]) >= garment_face_count  # the ball hides the sheet behind it
    assert float(view.sun[shadow_px]) == 0.0 and float(view.sun[lit_px]) > 0.5
    rgb = view.rgb.cpu()
    assert float(rgb[shadow_px].sum()) < 0.6 * float(rgb[lit_px].sum())
    # the colour is the image formation of the module: albedo · (L_a · AO + L_s · sun)
    for px in (shadow_px, lit_px):
        expected = 0.8 * (0.3 * view.ao[px] + 0.6 * view.sun[px])
        torch.testing.assert_close(rgb[px], expected.cpu().expand(3), atol=1e-6, rtol=0)
    assert torch.equal(view.rgb[view.face < 0].cpu(), torch.ones(int((view.face < 0).sum()), 3))

    seen = []
    capture = render_capture(
        sheet,
        sheet_faces,
        ball,
        ball_faces,
        albedo[:garment_face_count],
        (0.6, 0.6, 0.6),
        rig,
        lighting,
        25.0,
        progress=lambda t, n: seen.append((t, n)),
    )
    assert seen == [(1, 1)]
    assert capture.images.shape == (1, 3, 40, 48, 3) and capture.masks.shape == (1, 3, 40, 48)
    mask = capture.masks[0, 0]
    assert bool(mask[shadow_px]) and bool(mask[lit_px]) and not bool(mask[ball_px])
    assert torch.equal(mask, (face >= 0) & (face < garment_face_count))
    assert bool(((capture.images * 255).round() == capture.images * 255).all())  # 8-bit quantised


def test_ambient_occlusion_is_one_in_the_open_and_below_one_in_a_crease(device):
    flat, flat_faces = _sheet()
    rig = CameraRig.look_at([[-1.0, 1.2, 1.2]], [-0.15, 0.05, 0.4], 48, 40, 45.0)
    sky = Lighting((1.0, 1.0, 1.0), (0.0, 0.0, 0.0), SUN)
    open_view = shade_mesh(flat, flat_faces, torch.full((len(flat_faces), 3), 0.5), rig, 0, sky, ao_samples=16)
    assert int((open_view.face >= 0).sum()) > 100
    assert bool((open_view.ao[open_view.face >= 0] == 1.0).all())

    # An L-shaped fold: a floor (x < 0, y = 0) meeting a wall (x = 0, y > 0) along the crease x = y = 0.
    v, faces = grid_sheet(9, 9, 0.1)
    u = v[:, 0] - 0.4
    fold = torch.stack([u.clamp(max=0.0), u.clamp(min=0.0), v[:, 1]], 1)
    view = shade_mesh(fold, faces, torch.full((len(faces), 3), 0.5), rig, 0, sky, ao_samples=32)
    near = rig.project(torch.tensor([[-0.03, 0.0, 0.4]], dtype=torch.float64))[0][0, 0]
    far = rig.project(torch.tensor([[-0.33, 0.0, 0.4]], dtype=torch.float64))[0][0, 0]
    ao_near = float(view.ao[int(near[1]), int(near[0])])
    ao_far = float(view.ao[int(far[1]), int(far[0])])
    assert 0.3 < ao_near < 0.7  # the wall hides about half of the floor's cosine-weighted sky at the crease
    assert ao_far > ao_near + 0.2
    rgb = view.rgb.cpu()
    assert float(rgb[int(near[1]), int(near[0])].sum()) < float(rgb[int(far[1]), int(far[0])].sum())


def test_hemisphere_directions_are_unit_cosine_weighted_and_fixed():
    d = hemisphere_directions(4096, seed=3)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(4096, dtype=torch.float64))
    assert bool((d[:, 2] >= 0).all())
    assert abs(float(d[:, 2].mean()) - 2.0 / 3.0) < 2e-3  # E[cos θ] = 2/3 under the cos θ / π density
    assert abs(float(d[:, 0].mean())) < 1e-2 and abs(float(d[:, 1].mean())) < 1e-2
    assert torch.equal(hemisphere_directions(16, 0), hemisphere_directions(16, 0))
    assert not torch.equal(hemisphere_directions(16, 0), hemisphere_directions(16, 1))


def test_garment_albedo_patterns_follow_the_rest_shape():
    sheet, faces = _sheet()
    stripes = garment_albedo(sheet, faces, "stripes", bands=4, axis=0)
    checks = garment_albedo(sheet, faces, "checks", bands=4)
    assert stripes.shape == checks.shape == (len(faces), 3)
    for albedo in (stripes, checks):
        colours = torch.unique(albedo, dim=0)
        assert len(colours) == 2 and 0.3 < float((albedo == colours[0]).all(1).float().mean()) < 0.7
    centroid_x = sheet[faces.long()].mean(1)[:, 0]
    band = torch.floor((centroid_x + 0.4) / 0.2)
    same_parity = band[:, None] % 2 == band[None, :] % 2
    same_colour = (stripes[:, None] == stripes[None, :]).all(-1)
    assert torch.equal(same_parity, same_colour)  # stripes alternate along x, 0.2 m wide
    assert not torch.equal(stripes, checks)


def test_write_and_load_round_trip(device, tmp_path):
    capture, truth = _small_capture()
    path = write_capture(capture, tmp_path / "cap", truth)
    assert path.name == "transforms.json"
    meta = json.loads(path.read_text())
    assert len(meta["frames"]) == 2 * 3 and meta["w"] == 48 and meta["h"] == 40
    assert {"file_path", "mask_path", "transform_matrix", "camera", "time_index"} == set(meta["frames"][0])
    assert {"fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y"} <= set(meta)  # shared intrinsics
    for source in (tmp_path / "cap", path):
        loaded = load_capture(source)
        assert torch.equal(loaded.images, capture.images)
        assert torch.equal(loaded.masks, capture.masks)
        assert torch.equal(loaded.rig.c2w, capture.rig.c2w)
        assert (loaded.rig.width, loaded.rig.height) == (capture.rig.width, capture.rig.height)
        assert torch.equal(loaded.rig.intrinsics, capture.rig.intrinsics)
        assert loaded.fps == 25.0 and loaded.lighting == capture.lighting and loaded.background == (1.0, 1.0, 1.0)
    stored = load_truth(tmp_path / "cap")
    assert torch.equal(stored["garment_frames"], truth["garment_frames"])
    assert torch.equal(stored["garment_faces"], truth["garment_faces"])
    assert torch.equal(stored["albedo"], truth["albedo"])
    assert stored["params"] == truth["params"] and stored["fps"] == 25.0


def _calibrated_capture(frames: int = 2) -> Capture:
    """8-bit noise seen by :func:`_calibrated_rig` (the files only, no rendering)."""
    generator = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (frames, 3, 40, 48, 3), generator=generator).float() / 255.0
    return Capture(images, images[..., 0] > 0.5, _calibrated_rig(), 25.0, Lighting())


def test_per_camera_intrinsics_round_trip_in_each_frame(tmp_path):
    capture = _calibrated_capture()
    path = write_capture(capture, tmp_path / "cap")
    meta = json.loads(path.read_text())
    assert not {"fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y"} & set(meta)
    for frame in meta["frames"]:
        row = capture.rig.intrinsics[frame["camera"]].tolist()
        assert [frame[key] for key in ("fl_x", "fl_y", "cx", "cy")] == row
    loaded = load_capture(tmp_path / "cap")
    assert torch.equal(loaded.rig.intrinsics, capture.rig.intrinsics)  # float64 survives the json exactly
    assert torch.equal(loaded.rig.c2w, capture.rig.c2w) and torch.equal(loaded.images, capture.images)
    assert torch.equal(loaded.masks, capture.masks)


def test_per_frame_intrinsics_override_the_shared_ones_and_must_hold_for_all_time(tmp_path):
    capture = _calibrated_capture()
    calibrated = tmp_path / "calibrated"
    write_capture(capture, calibrated)
    shared = tmp_path / "shared"
    write_capture(Capture(capture.images, capture.masks, _rig(), 25.0, None), shared)

    def own_focal(meta):  # camera 2 gives its own focal length in every frame, the others keep the shared values
        for frame in meta["frames"]:
            if frame["camera"] == 2:
                frame["fl_x"] = 70.5

    _edit(shared, own_focal)
    rig = load_capture(shared).rig
    expected = _rig().intrinsics
    expected[2, 0] = 70.5
    assert torch.equal(rig.intrinsics, expected)

    def zoom(meta):
        for frame in meta["frames"]:
            if (frame["camera"], frame["time_index"]) == (1, 1):
                frame["fl_x"] *= 1.1

    _edit(calibrated, zoom)
    with pytest.raises(ValueError, match=r"camera 1 changes its intrinsics .* at 1; .*every frame of camera 1"):
        load_capture(calibrated)

    def zoom_once(meta):  # a shared focal length that one frame overrides is a change too
        next(f for f in meta["frames"] if (f["camera"], f["time_index"]) == (0, 1))["fl_y"] = 80.0

    _edit(shared, zoom_once)
    with pytest.raises(ValueError, match=r"camera 0 changes its intrinsics"):
        load_capture(shared)


def _edit(folder, change):
    meta = json.loads((folder / "transforms.json").read_text())
    change(meta)
    (folder / "transforms.json").write_text(json.dumps(meta))


def test_load_capture_names_what_is_wrong(device, tmp_path):
    capture, _ = _small_capture()
    good = tmp_path / "good"
    write_capture(capture, good)

    def copy(name):
        target = tmp_path / name
        shutil.copytree(good, target)
        return target

    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="transforms.json"):
        load_capture(tmp_path / "empty")

    folder = copy("short")
    _edit(folder, lambda m: m.update(frames=[f for f in m["frames"] if (f["camera"], f["time_index"]) != (2, 1)]))
    with pytest.raises(ValueError, match="camera 2 has 1 frames but camera 0 has 2"):
        load_capture(folder)

    def move(meta):
        for f in meta["frames"]:
            if (f["camera"], f["time_index"]) == (2, 1):
                f["time_index"] = 5

    folder = copy("gap")
    _edit(folder, move)
    with pytest.raises(ValueError, match=r"time index 1 lacks camera\(s\) \[2\]"):
        load_capture(folder)

    folder = copy("missing")
    (folder / "images" / "t0001_c01.png").unlink()
    with pytest.raises(FileNotFoundError, match="t0001_c01.png"):
        load_capture(folder)

    folder = copy("corrupt")
    (folder / "masks" / "t0000_c02.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="t0000_c02.png.*not a readable image"):
        load_capture(folder)

    folder = copy("size")
    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(folder / "images" / "t0001_c00.png")
    with pytest.raises(ValueError, match="t0001_c00.png.*12x10 pixels.*48x40"):
        load_capture(folder)


def test_bad_arguments_are_refused(device):
    with pytest.raises(ValueError, match="ambient"):
        Lighting((-0.1, 0.0, 0.0))
    with pytest.raises(ValueError, match="sun_direction"):
        Lighting(sun_direction=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="radius"):
        CameraRig.ring(4, 0.0, 1.0, (0, 0, 0), 32, 32)
    with pytest.raises(ValueError, match="up direction"):
        CameraRig.look_at([[0.0, 2.0, 0.0]], [0.0, 0.0, 0.0], 32, 32)
    sheet, faces = _sheet()
    with pytest.raises(ValueError, match=r"garment_albedo must be \[128, 3\]"):
        render_capture(sheet, faces, None, None, torch.ones(5, 3), None, _rig(), Lighting(), 25.0)
    ball, ball_faces = _ball()
    with pytest.raises(ValueError, match="one body pose per garment frame"):
        dressed_scene(sheet[None].repeat(2, 1, 1), faces, ball[None].repeat(3, 1, 1), ball_faces)
