"""Bad transforms jsons and images end in the loader's own clear errors, never in a raw traceback."""

import json
import math
import random
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from pienerf.nerf.datasets import MAX_IMAGE_PIXELS, NerfDataset, load_nerf_dataset

ANGLE_X = 0.6911112070083618


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
