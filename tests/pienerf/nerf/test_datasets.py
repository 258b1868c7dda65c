import json
import math
import random
import struct
import zlib

import numpy as np
import pytest
import torch
from PIL import Image

from pienerf.nerf.datasets import MAX_IMAGE_PIXELS, NerfDataset, load_nerf_dataset

ANGLE_X = 0.6911112070083618


def _c2w(position, target=(0.0, 0.0, 0.0)) -> list:
    position, target = np.asarray(position, dtype=float), np.asarray(target, dtype=float)
    back = (position - target) / np.linalg.norm(position - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, np.cross(back, right), back, position
    return matrix.tolist()


def _write_dataset(folder, count=3, size=8, meta=None, name="transforms_train.json"):
    """``count`` RGBA views: pixel (0, 0) opaque red, (0, 1) transparent green, the rest half-transparent blue."""
    (folder / "train").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(count):
        rgba = np.zeros((size, size, 4), dtype=np.uint8)
        rgba[...] = (0, 0, 255, 128)
        rgba[0, 0] = (255, 0, 0, 255)
        rgba[0, 1] = (0, 255, 0, 0)
        Image.fromarray(rgba, mode="RGBA").save(folder / "train" / f"r_{i}.png")
        angle = 2 * math.pi * i / count
        frames.append(
            {"file_path": f"./train/r_{i}", "transform_matrix": _c2w((4 * math.cos(angle), 4 * math.sin(angle), 1))}
        )
    content = {"camera_angle_x": ANGLE_X} if meta is None else dict(meta)
    content["frames"] = frames
    (folder / name).write_text(json.dumps(content))
    return folder


def test_loads_images_alphas_and_cameras(tmp_path):
    data = load_nerf_dataset(_write_dataset(tmp_path))
    assert data.images.shape == (3, 8, 8, 3) and data.alphas.shape == (3, 8, 8) and len(data) == 3
    assert data.split == "train" and data.names == ["./train/r_0", "./train/r_1", "./train/r_2"]
    torch.testing.assert_close(data.images[0, 0, 0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(data.images[0, 0, 1], torch.ones(3))  # transparent: the white background
    a = 128 / 255
    torch.testing.assert_close(data.images[0, 3, 3], torch.tensor([1 - a, 1 - a, 1.0]))
    assert float(data.alphas[0, 0, 1]) == 0.0 and float(data.alphas[0, 3, 3]) == pytest.approx(a)
    focal = 0.5 * 8 / math.tan(0.5 * ANGLE_X)
    torch.testing.assert_close(data.cameras.fx, torch.full((3,), focal))
    torch.testing.assert_close(data.cameras.fy, data.cameras.fx)
    torch.testing.assert_close(data.cameras.cx, torch.full((3,), 4.0))
    black = load_nerf_dataset(tmp_path, background=(0, 0, 0))
    torch.testing.assert_close(black.images[0, 0, 1], torch.zeros(3))
    torch.testing.assert_close(black.images[0, 3, 3], torch.tensor([0.0, 0.0, a]))
    noisy = load_nerf_dataset(tmp_path, background="random", seed=3)
    assert noisy.images[:, 0, 1].std() > 0.1  # transparent pixels take random colours
    torch.testing.assert_close(noisy.images[:, 0, 0], data.images[:, 0, 0])  # opaque pixels keep theirs


def test_downscale_averages_premultiplied_colour_and_scales_intrinsics(tmp_path):
    full = load_nerf_dataset(_write_dataset(tmp_path))
    half = load_nerf_dataset(tmp_path, downscale=2, background=(0, 0, 0))
    assert half.images.shape == (3, 4, 4, 3) and half.cameras.width == 4
    # Block (0, 0): opaque red, transparent green, two half-transparent blue pixels.
    a = 128 / 255
    assert float(half.alphas[0, 0, 0]) == pytest.approx((1 + 0 + 2 * a) / 4)
    torch.testing.assert_close(half.images[0, 0, 0], torch.tensor([0.25, 0.0, 2 * a / 4]))  # no green bleeds in
    for key in ("fx", "fy", "cx", "cy"):
        torch.testing.assert_close(getattr(half.cameras, key), getattr(full.cameras, key) / 2)
    # The coarse pixel's ray is the mean direction of its fine pixels' rays (same centre, same view).
    _, coarse = half.cameras.rays(1)
    _, fine = full.cameras.rays(1)
    block = torch.nn.functional.normalize(fine.reshape(4, 2, 4, 2, 3).mean(dim=(1, 3)).reshape(-1, 3), dim=-1)
    torch.testing.assert_close(coarse, block, atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="downscale 3 does not divide"):
        load_nerf_dataset(tmp_path, downscale=3)


def test_rays_follow_opengl_camera_axes(tmp_path):
    cameras = load_nerf_dataset(_write_dataset(tmp_path)).cameras
    origins, directions = cameras.pixel_rays(torch.arange(3), cameras.cx, cameras.cy)
    torch.testing.assert_close(origins, cameras.centers)
    torch.testing.assert_close(directions, -cameras.c2w[:, :3, 2])  # the centre ray looks down −z
    # Pixels to the right and above the centre look along +x and +y of the camera.
    _, right = cameras.pixel_rays(0, cameras.cx[:1] + 2, cameras.cy[:1])
    _, up = cameras.pixel_rays(0, cameras.cx[:1], cameras.cy[:1] - 2)
    assert float(right[0] @ cameras.c2w[0, :3, 0]) > 0 and float(up[0] @ cameras.c2w[0, :3, 1]) > 0
    origins, directions = cameras.rays()
    assert origins.shape == (3 * 64, 3)
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(3 * 64))


def test_instant_ngp_intrinsics_and_explicit_extensions(tmp_path):
    meta = {"fl_x": 10.0, "fl_y": 12.0, "cx": 3.5, "cy": 4.5, "w": 8, "h": 8}
    _write_dataset(tmp_path, meta=meta, name="transforms.json")
    content = json.loads((tmp_path / "transforms.json").read_text())
    content["frames"][0]["file_path"] = "train/r_0.png"
    content["frames"][1]["fl_x"] = 20.0  # per-frame intrinsics win
    (tmp_path / "transforms.json").write_text(json.dumps(content))
    cameras = load_nerf_dataset(tmp_path).cameras
    torch.testing.assert_close(cameras.fx, torch.tensor([10.0, 20.0, 10.0]))
    torch.testing.assert_close(cameras.fy, torch.full((3,), 12.0))
    torch.testing.assert_close(cameras.cy, torch.full((3,), 4.5))
    content["w"] = 16
    (tmp_path / "transforms.json").write_text(json.dumps(content))
    with pytest.raises(ValueError, match="w=16 but its images are 8x8"):
        load_nerf_dataset(tmp_path)


def test_held_out_views_without_a_test_json(tmp_path):
    _write_dataset(tmp_path, count=10)
    train = load_nerf_dataset(tmp_path)
    test = load_nerf_dataset(tmp_path, split="test", holdout_every=4)
    assert test.names == ["./train/r_0", "./train/r_4", "./train/r_8"] and test.split == "test"
    kept, held = train.held_out(4)
    assert held.names == test.names
    assert set(kept.names) | set(held.names) == set(train.names) and not set(kept.names) & set(held.names)
    torch.testing.assert_close(held.cameras.c2w, test.cameras.c2w)
    assert len(load_nerf_dataset(tmp_path, max_views=2)) == 2
    _write_dataset(tmp_path, count=2, name="transforms_test.json")
    assert len(load_nerf_dataset(tmp_path, split="test")) == 2  # a test json, when present, is used


def test_views_recomposited_over_another_background_match_a_load_over_it(tmp_path):
    _write_dataset(tmp_path)
    black, white = load_nerf_dataset(tmp_path, background=(0, 0, 0)), load_nerf_dataset(tmp_path)
    moved = black.over_background((1.0, 1.0, 1.0))
    assert moved.background == (1.0, 1.0, 1.0) and black.background == (0.0, 0.0, 0.0)
    torch.testing.assert_close(moved.images, white.images)
    with pytest.raises(ValueError, match="cannot be recomposited; load them over a solid one"):
        load_nerf_dataset(tmp_path, background="random").over_background((1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="RGB triple in"):
        black.over_background((2.0, 0.0, 0.0))


def test_missing_image_names_the_file_and_the_json(tmp_path):
    _write_dataset(tmp_path, count=4)
    (tmp_path / "train" / "r_3.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"r_3\.png listed in transforms_train\.json does not exist"):
        load_nerf_dataset(tmp_path)


def test_corrupt_image_names_the_file(tmp_path):
    _write_dataset(tmp_path)
    path = tmp_path / "train" / "r_1.png"
    path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(ValueError, match=r"r_1\.png listed in transforms_train\.json is not a readable image"):
        load_nerf_dataset(tmp_path)


def test_views_of_different_sizes_are_refused(tmp_path):
    _write_dataset(tmp_path)
    Image.fromarray(np.zeros((6, 8, 4), dtype=np.uint8), mode="RGBA").save(tmp_path / "train" / "r_2.png")
    with pytest.raises(ValueError, match=r"r_2\.png is 8x6 pixels but r_0\.png is 8x8"):
        load_nerf_dataset(tmp_path)


def test_json_without_frames_or_intrinsics_is_refused(tmp_path):
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": []}))
    with pytest.raises(ValueError, match="transforms_train.json lists no frames"):
        load_nerf_dataset(tmp_path)
    _write_dataset(tmp_path, meta={})
    with pytest.raises(ValueError, match="gives no intrinsics: add 'camera_angle_x'"):
        load_nerf_dataset(tmp_path)
    with pytest.raises(FileNotFoundError, match="neither transforms_train.json"):
        load_nerf_dataset(tmp_path / "train")
    with pytest.raises(ValueError, match="split must be"):
        load_nerf_dataset(tmp_path, split="validation")


def test_lego(shared_data):
    folder = shared_data / "nerf_synthetic_lego"
    data = load_nerf_dataset(folder, downscale=8)
    assert data.images.shape == (90, 100, 100, 3) and data.alphas.shape == (90, 100, 100)
    meta = json.loads((folder / "transforms_train.json").read_text())
    focal = 0.5 * 100 / math.tan(0.5 * meta["camera_angle_x"])
    torch.testing.assert_close(data.cameras.fx, torch.full((90,), focal))
    assert (data.cameras.width, data.cameras.height) == (100, 100)
    radius = data.cameras.centers.norm(dim=-1)
    assert float((radius - 4.031).abs().max()) < 0.01  # every camera on one sphere about the origin
    origins, directions = data.cameras.pixel_rays(torch.arange(90), data.cameras.cx, data.cameras.cy)
    closest = origins - (origins * directions).sum(-1, keepdim=True) * directions
    assert float(closest.norm(dim=-1).max()) < 1e-3  # the centre rays aim at the origin
    assert 0.05 < float(data.alphas.mean()) < 0.5 and float(data.alphas[:, 0, 0].max()) == 0.0


# -- hostile inputs: bad transforms jsons and images end in the loader's own clear errors, never in a raw traceback


def _frame(i: int) -> dict:
    matrix = np.eye(4)
    matrix[:3, 3] = (0.0, 0.0, 4.0 + i)
    return {"file_path": f"./train/r_{i}", "transform_matrix": matrix.tolist()}


def _dataset(folder, count: int = 2, size: int = 4, meta: dict | None = None, frames: list | None = None):
    """``count`` ``size²`` RGBA views under ``folder/train`` and their ``transforms_train.json``."""
    (folder / "train").mkdir(parents=True, exist_ok=True)
    for i in range(count):
        Image.fromarray(np.full((size, size, 4), 200, dtype=np.uint8), mode="RGBA").save(
            folder / "train" / f"r_{i}.png"
        )
    content = {"camera_angle_x": ANGLE_X} if meta is None else dict(meta)
    content["frames"] = [_frame(i) for i in range(count)] if frames is None else frames
    (folder / "transforms_train.json").write_text(json.dumps(content))
    return folder


def _claim_size(png: bytes, width: int, height: int) -> bytes:
    """The PNG ``png`` with its IHDR claiming ``width × height`` pixels (a decompression bomb's header)."""
    start = 8 + 8  # signature, then the IHDR chunk's length and type
    data = struct.pack(">II", width, height) + png[start + 8 : start + 13]
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + data))
    return png[:start] + data + crc + png[start + 17 :]


def test_a_decompression_bomb_is_refused_from_its_header(tmp_path):
    folder = _dataset(tmp_path)
    image = folder / "train" / "r_1.png"
    image.write_bytes(_claim_size(image.read_bytes(), 30000, 30000))
    assert struct.unpack(">II", image.read_bytes()[16:24]) == (30000, 30000)  # what the header claims
    with pytest.raises(
        ValueError, match=rf"r_1\.png listed in transforms_train\.json is too large .*{MAX_IMAGE_PIXELS}"
    ):
        load_nerf_dataset(folder)


@pytest.mark.parametrize(
    ("meta", "frames", "message"),
    [
        ({"camera_angle_x": 0}, None, r"'camera_angle_x' .* is 0; a field of view must lie in \(0, π\)"),
        ({"camera_angle_x": "wide"}, None, r"'camera_angle_x' .* must be a finite number, got 'wide'"),
        ({"camera_angle_x": ANGLE_X, "fl_x": float("nan")}, None, r"'fl_x' .* must be a finite number"),
        (None, [{"file_path": 7, "transform_matrix": np.eye(4).tolist()}], r"'file_path' 7 in .* must be a non-empty"),
        (None, [{"file_path": "./train/r_0", "transform_matrix": "eye"}], r"'transform_matrix' of frame './train/r_0'"),
        (None, [{"file_path": "./train/r_0", "transform_matrix": [["a"] * 4] * 4}], r"must be a 4x4 list of numbers"),
        (None, ["./train/r_0"], r"frame 0 in .*transforms_train\.json is str, not an object"),
        (None, {"file_path": "./train/r_0"}, r"lists no frames"),
    ],
)
def test_malformed_fields_name_the_file_and_the_field(tmp_path, meta, frames, message):
    folder = _dataset(tmp_path, meta=meta, frames=frames)
    with pytest.raises(ValueError, match=message) as error:
        load_nerf_dataset(folder)
    assert "transforms_train.json" in str(error.value)


def test_paths_leaving_the_dataset_folder_need_consent(tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    Image.fromarray(np.full((4, 4, 4), 9, dtype=np.uint8), mode="RGBA").save(outside / "secret.png")
    matrix = np.eye(4).tolist()
    for file_path in (str(outside / "secret.png"), "../elsewhere/secret", "./train/../../elsewhere/secret.png"):
        folder = _dataset(tmp_path / "data", frames=[{"file_path": file_path, "transform_matrix": matrix}])
        with pytest.raises(ValueError, match="leads outside the dataset folder .* pass allow_outside=True"):
            load_nerf_dataset(folder)
        data = load_nerf_dataset(folder, allow_outside=True)
        assert data.images.shape == (1, 4, 4, 3)
    inside = _dataset(tmp_path / "data", frames=[{"file_path": "./train/../train/r_0", "transform_matrix": matrix}])
    assert len(load_nerf_dataset(inside)) == 1


# ------------------------------------------------------------------------------------------------------------
# Fuzzing: seeded random corruptions of a valid dataset
# ------------------------------------------------------------------------------------------------------------

_ODD_VALUES = [
    None, True, 0, -1, 1, 2**70, -(10**400), 1e308, float("nan"), float("inf"), -0.0, "", "x", "./train/r_0", "../r_0",
    "/etc/passwd", [], [1, 2], [[1.0] * 4] * 3, [[1.0] * 4] * 4, [[0.0] * 3] * 4, {}, {"a": 1}, "\x00", "r_0\n",
]  # fmt: skip
_KEYS = ["camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "frames", "file_path",
         "transform_matrix", "p2"]  # fmt: skip


def _mutate(content: dict, rng: random.Random) -> dict:
    """One to three random edits: a key set to an odd value, deleted, or a frame duplicated or replaced."""
    for _ in range(rng.randint(1, 3)):
        frames = content.get("frames")
        where = content
        if isinstance(frames, list) and frames and rng.random() < 0.6:
            where = rng.choice(frames)
        if not isinstance(where, dict):
            continue
        action = rng.random()
        key = rng.choice(_KEYS)
        if action < 0.6:
            where[key] = rng.choice(_ODD_VALUES)
        elif action < 0.8:
            where.pop(key, None)
        elif isinstance(frames, list):
            frames.append(rng.choice([*_ODD_VALUES, dict(frames[0]) if frames else {}]))
    return content


def _expected(error: Exception) -> bool:
    """The loader's own errors: ValueError or FileNotFoundError whose message names the json or an image."""
    if type(error) not in (ValueError, FileNotFoundError):
        return False
    text = str(error)
    return "transforms_train.json" in text or ".png" in text or "r_0" in text or "r_1" in text


def test_fuzzed_jsons_load_or_fail_clearly(tmp_path):
    rng = random.Random(20260)
    folder = _dataset(tmp_path)
    json_path = folder / "transforms_train.json"
    valid = json.loads(json_path.read_text())
    outcomes = {"loaded": 0, "refused": 0}
    for case in range(120):
        content = _mutate(json.loads(json.dumps(valid)), rng)
        text = json.dumps(content)
        if case % 4 == 3:  # byte-level damage: truncation or a flipped byte
            raw = bytearray(text.encode())
            cut = rng.randrange(len(raw))
            raw = raw[:cut] if rng.random() < 0.5 else raw[:cut] + bytes([rng.randrange(256)]) + raw[cut + 1 :]
            json_path.write_bytes(bytes(raw))
        else:
            json_path.write_text(text)
        try:
            data = load_nerf_dataset(folder)
        except Exception as error:  # noqa: BLE001 - the point is to see every type that escapes
            assert _expected(error), f"case {case}: {type(error).__name__}: {error}\n{text[:400]}"
            outcomes["refused"] += 1
        else:
            assert isinstance(data, NerfDataset) and len(data) >= 1
            assert all(math.isfinite(v) for v in data.cameras.fx.tolist())
            outcomes["loaded"] += 1
    assert outcomes["loaded"] > 5 and outcomes["refused"] > 50, outcomes


def test_fuzzed_images_load_or_fail_clearly(tmp_path):
    rng = random.Random(7)
    folder = _dataset(tmp_path)
    image = folder / "train" / "r_1.png"
    original = image.read_bytes()
    for case in range(40):
        raw = bytearray(original)
        if case % 3 == 0:
            raw = raw[: rng.randrange(len(raw))]
        else:
            for _ in range(rng.randint(1, 8)):
                raw[rng.randrange(len(raw))] = rng.randrange(256)
        image.write_bytes(bytes(raw))
        try:
            load_nerf_dataset(folder)
        except Exception as error:  # noqa: BLE001
            assert _expected(error), f"case {case}: {type(error).__name__}: {error}"
