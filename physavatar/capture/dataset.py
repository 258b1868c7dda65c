"""The capture's files: a multi-view video on disk, written and read back (PhysAvatar §3.1 input).

Files (:func:`write_capture`): a NeRF-synthetic style ``transforms.json`` (image size ``w``, ``h``; ``fps``;
``lighting``; one frame per (time, camera) with ``file_path``, ``mask_path``, ``transform_matrix``, ``camera`` and
``time_index``; intrinsics ``camera_angle_x``/``_y``, ``fl_x``, ``fl_y``, ``cx``, ``cy`` at the top level when every
camera shares them, else ``fl_x``, ``fl_y``, ``cx``, ``cy`` in each frame, nerfstudio's per-frame convention), 8-bit
PNG images and masks, and ``truth.npz`` holding what evaluation needs and the pipeline must not see (meshes, albedo,
parameters). Each file goes through a staging step passed in (:mod:`physavatar.result_files`), so a program can have
every one written whole or not at all; ``transforms.json``, the index a reader opens first, comes last.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from physavatar.capture.rig import CameraRig, Lighting
from physavatar.result_files import Staging, write_arrays, write_json, write_png

_TRANSFORMS = "transforms.json"
_TRUTH = "truth.npz"
_JSON_KEY = "__json__"  # the truth file's entry holding its non-array values as JSON
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")  # px, at the top level (shared) or in each frame (per camera)

__all__ = [
    "Capture",
    "load_capture",
    "load_truth",
    "write_capture",
]


@dataclass
class Capture:
    """A multi-view video of the dressed body.

    Attributes:
        images: ``[T, C, H, W, 3]`` float32 in [0, 1] (CPU): frame ``t`` as camera ``c`` saw it.
        masks: ``[T, C, H, W]`` bool: pixels whose first hit is the garment.
        rig: the cameras.
        fps: frames per second of the video.
        lighting: the light the images were rendered under; ``None`` for a capture whose light is unknown.
        background: RGB of pixels that see nothing.
    """

    images: torch.Tensor
    masks: torch.Tensor
    rig: CameraRig
    fps: float
    lighting: Lighting | None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self):
        expected = (len(self.rig), self.rig.height, self.rig.width)
        if self.images.dim() != 5 or tuple(self.images.shape[1:]) != (*expected, 3):
            raise ValueError(
                f"images must be [T, {expected[0]}, {expected[1]}, {expected[2]}, 3] for this rig, "
                f"got {tuple(self.images.shape)}"
            )
        if tuple(self.masks.shape) != tuple(self.images.shape[:-1]) or self.masks.dtype != torch.bool:
            raise ValueError(
                f"masks must be bool {tuple(self.images.shape[:-1])}, got {self.masks.dtype} {tuple(self.masks.shape)}"
            )
        if not self.fps > 0.0:
            raise ValueError(f"fps must be positive, got {self.fps}")

    @property
    def frame_count(self) -> int:
        """``T``, the number of time steps."""
        return self.images.shape[0]

    @property
    def camera_count(self) -> int:
        """``C``, the number of cameras."""
        return self.images.shape[1]


# ---------------------------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------------------------


def write_capture(
    capture: Capture, folder: str | Path, truth: dict | None = None, staging: Staging = contextlib.nullcontext
) -> Path:
    """Write a capture as ``images/*.png`` + ``masks/*.png`` (+ ``truth.npz``) + ``transforms.json``, in that order.

    Args:
        capture: the capture (images are stored as 8-bit PNG: exact for a capture rendered with ``quantize``).
        folder: created if missing.
        truth: values for evaluation only (e.g. ``garment_frames``, ``body_frames``, faces, albedo, simulation
            parameters): tensors and arrays are stored as arrays, other values (numbers, strings, dicts,
            dataclasses) as JSON; read back with :func:`load_truth`.
        staging: the step every file is written through (:data:`physavatar.result_files.Staging`); the default
            writes each path itself.

    Returns:
        The path of ``transforms.json``.

    Raises:
        ValueError: a truth key or value that cannot be stored (before any file is written).
    """
    folder = Path(folder)
    truth_arrays = None if truth is None else _encode_truth(truth)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    rig = capture.rig
    images = torch.round(capture.images.clamp(0.0, 1.0) * 255.0).to(torch.uint8).numpy()
    masks = capture.masks.numpy()
    intrinsics = rig.intrinsics.tolist()
    shared, per_frame = {}, [dict(zip(_INTRINSIC_KEYS, row, strict=True)) for row in intrinsics]
    if rig.shared_intrinsics:
        shared = {
            "camera_angle_x": 2.0 * math.atan(0.5 * rig.width / intrinsics[0][0]),
            "camera_angle_y": 2.0 * math.atan(0.5 * rig.height / intrinsics[0][1]),
            **per_frame[0],
        }
        per_frame = [{} for _ in intrinsics]
    frames = []
    for t in range(capture.frame_count):
        for c in range(capture.camera_count):
            name = f"t{t:04d}_c{c:02d}.png"
            write_png(folder / "images" / name, images[t, c], staging)
            write_png(folder / "masks" / name, masks[t, c].astype(np.uint8) * 255, staging)
            frames.append(
                {
                    "file_path": f"images/{name}",
                    "mask_path": f"masks/{name}",
                    "transform_matrix": rig.c2w[c].tolist(),
                    "camera": c,
                    "time_index": t,
                    **per_frame[c],
                }
            )
    meta = {
        **shared,
        "w": rig.width,
        "h": rig.height,
        "fps": capture.fps,
        "background": list(capture.background),
        "lighting": None if capture.lighting is None else capture.lighting.to_dict(),
        "frames": frames,
    }
    if truth_arrays is not None:
        write_arrays(folder / _TRUTH, staging, **truth_arrays)
    return write_json(folder / _TRANSFORMS, meta, staging, indent=1)


def load_capture(folder: str | Path) -> Capture:
    """Read a capture written by :func:`write_capture` (or any such ``transforms.json`` with ``camera`` and
    ``time_index`` per frame).

    Intrinsics are the top-level ``fl_x``/``fl_y`` (or ``camera_angle_x``/``camera_angle_y``), ``cx``, ``cy``,
    ``w``, ``h``; a frame's own ``fl_x``, ``fl_y`` (or ``camera_angle_x``/``_y``), ``cx``, ``cy`` override them for
    its camera (nerfstudio's per-frame intrinsics), and must be the same at every time index of that camera; a
    missing ``fl_y`` means ``fl_x``, a missing principal point the image centre. A frame path without extension
    means ``.png``; ``fps`` defaults to 25.

    Args:
        folder: the capture's folder, or its ``transforms.json``.

    Raises:
        FileNotFoundError: ``transforms.json`` or an image or mask it lists is missing.
        ValueError: the json is malformed; the cameras are not numbered ``0..C−1``; a camera has fewer frames
            than another; a time index lacks some camera (or holds one twice); a camera moves or changes its
            intrinsics between frames; an image or mask is corrupt or not ``w × h``.
    """
    from PIL import Image

    path = Path(folder)
    path = path if path.suffix == ".json" else path / _TRANSFORMS
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: a capture folder needs its {_TRANSFORMS}")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid json: {error}") from error
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames:
        raise ValueError(f"{path} lists no frames; it needs a non-empty 'frames' list")
    for k, frame in enumerate(frames):
        missing = [
            key for key in ("file_path", "mask_path", "transform_matrix", "camera", "time_index") if key not in frame
        ]
        if missing:
            raise ValueError(f"frame {k} of {path.name} lacks {', '.join(missing)}")

    by_camera: dict[int, dict[int, dict]] = {}
    for frame in frames:
        c, t = int(frame["camera"]), int(frame["time_index"])
        views = by_camera.setdefault(c, {})
        if t in views:
            raise ValueError(f"{path.name} lists camera {c} twice at time index {t}; keep one image per view")
        views[t] = frame
    cameras = sorted(by_camera)
    if cameras != list(range(len(cameras))):
        absent = sorted(set(range(max(cameras) + 1)) - set(cameras))
        raise ValueError(f"cameras missing from {path.name}: {absent} (cameras must be numbered 0..C-1)")
    counts = {c: len(by_camera[c]) for c in cameras}
    most = max(counts, key=counts.get)
    for c in cameras:
        if counts[c] != counts[most]:
            raise ValueError(
                f"mismatched frame counts in {path.name}: camera {c} has {counts[c]} frames but camera {most} has "
                f"{counts[most]}; every camera needs one image per time index"
            )
    times = sorted(set().union(*(set(v) for v in by_camera.values())))
    for t in times:
        lacking = [c for c in cameras if t not in by_camera[c]]
        if lacking:
            raise ValueError(f"cameras missing in {path.name}: time index {t} lacks camera(s) {lacking}")
    if times != list(range(len(times))):
        raise ValueError(f"time indices in {path.name} must be 0..T-1, got {times[:8]}")

    c2w = torch.empty(len(cameras), 4, 4, dtype=torch.float64)
    for c in cameras:
        poses = torch.tensor(np.stack([_pose(by_camera[c][t], path) for t in times]))
        if float((poses - poses[0]).abs().max()) > 1e-9 * max(1.0, float(poses.abs().max())):
            raise ValueError(f"camera {c} moves between time indices in {path.name}; a CameraRig is static")
        c2w[c] = poses[0]

    width, height = meta.get("w"), meta.get("h")
    if width is None or height is None:
        with _open_image(path, by_camera[0][0]["file_path"], Image) as first:
            width, height = first.size
    width, height = int(width), int(height)
    intrinsics = torch.empty(len(cameras), 4, dtype=torch.float64)
    for c in cameras:
        values = torch.tensor(
            [_intrinsics(meta, by_camera[c][t], width, height, path) for t in times], dtype=torch.float64
        )
        changed = (values - values[0]).abs().amax(1) > 1e-9 * values[0].abs().amax().clamp_min(1.0)
        if bool(changed.any()):
            k = int(torch.nonzero(changed)[0])
            raise ValueError(
                f"camera {c} changes its intrinsics (fl_x, fl_y, cx, cy) between time indices in {path.name}: "
                f"{values[0].tolist()} at time index {times[0]}, {values[k].tolist()} at {times[k]}; a CameraRig "
                f"calibrates each camera once, so give every frame of camera {c} the same values"
            )
        intrinsics[c] = values[0]
    rig = CameraRig(c2w, width, height, *intrinsics.unbind(1))

    images = torch.empty(len(times), len(cameras), rig.height, rig.width, 3, dtype=torch.float32)
    masks = torch.empty(len(times), len(cameras), rig.height, rig.width, dtype=torch.bool)
    for t in times:
        for c in cameras:
            frame = by_camera[c][t]
            for key, out, mode in (("file_path", images, "RGB"), ("mask_path", masks, "L")):
                with _open_image(path, frame[key], Image) as image:
                    if image.size != (rig.width, rig.height):
                        raise ValueError(
                            f"{image.filename} (time {t}, camera {c}) is {image.size[0]}x{image.size[1]} pixels but "
                            f"{path.name} says {rig.width}x{rig.height}; re-render it or fix w/h"
                        )
                    pixels = np.asarray(image.convert(mode))
                if mode == "RGB":
                    out[t, c] = torch.from_numpy(pixels.astype(np.float32) / 255.0)
                else:
                    out[t, c] = torch.from_numpy(pixels >= 128)
    lighting = meta.get("lighting")
    lighting = None if lighting is None else Lighting.from_dict(lighting)
    background = tuple(float(x) for x in meta.get("background", (1.0, 1.0, 1.0)))
    return Capture(images, masks, rig, float(meta.get("fps", 25.0)), lighting, background)


def load_truth(folder: str | Path) -> dict:
    """The evaluation values :func:`write_capture` stored: arrays as CPU tensors, other values as written."""
    path = Path(folder)
    path = path.parent / _TRUTH if path.suffix == ".json" else (path if path.suffix == ".npz" else path / _TRUTH)
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: write the capture with truth=... to evaluate against it")
    with np.load(path, allow_pickle=False) as data:
        out = {key: torch.from_numpy(np.array(data[key])) for key in data.files if key != _JSON_KEY}
        if _JSON_KEY in data.files:
            out.update(json.loads(str(data[_JSON_KEY])))
    return out


def _encode_truth(truth: dict) -> dict[str, np.ndarray]:
    """The arrays of ``truth.npz``: each tensor or array as itself, every other value in one JSON string."""
    arrays, other = {}, {}
    for key, value in truth.items():
        if not isinstance(key, str) or key == _JSON_KEY:
            raise ValueError(f"truth keys must be strings other than {_JSON_KEY!r}, got {key!r}")
        if isinstance(value, torch.Tensor):
            arrays[key] = value.detach().cpu().numpy()
        elif isinstance(value, np.ndarray):
            arrays[key] = value
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            other[key] = dataclasses.asdict(value)
        else:
            other[key] = value
    try:
        encoded = json.dumps(other)
    except TypeError as error:
        raise ValueError(f"truth values must be tensors, arrays or JSON-serialisable values: {error}") from error
    return {**arrays, _JSON_KEY: np.asarray(encoded)}


def _open_image(json_path: Path, relative: str, image_module):
    path = json_path.parent / relative
    if not path.suffix and not path.is_file():
        path = path.with_name(path.name + ".png")
    if not path.is_file():
        raise FileNotFoundError(f"{path} listed in {json_path.name} does not exist")
    try:
        image = image_module.open(path)
        image.load()
    except (OSError, SyntaxError, ValueError) as error:
        raise ValueError(
            f"{path} listed in {json_path.name} is not a readable image ({error}); re-render it"
        ) from error
    return image


def _pose(frame: dict, json_path: Path) -> np.ndarray:
    matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"{frame['file_path']} in {json_path.name} needs a finite 4x4 transform_matrix")
    return matrix


def _intrinsics(meta: dict, frame: dict, width: int, height: int, json_path: Path) -> tuple[float, ...]:
    """``(fx, fy, cx, cy)`` px of one frame: its own values where it gives them, else the top-level ones."""
    fx = _first(_focal(frame, "x", width), _focal(meta, "x", width))
    if fx is None:
        raise ValueError(f"{json_path.name} gives no intrinsics: add 'fl_x' (pixels) or 'camera_angle_x' (radians)")
    fy = _first(_focal(frame, "y", height), _focal(meta, "y", height), fx)
    cx = _first(frame.get("cx"), meta.get("cx"), 0.5 * width)
    cy = _first(frame.get("cy"), meta.get("cy"), 0.5 * height)
    return fx, fy, float(cx), float(cy)


def _first(*values):
    return next((value for value in values if value is not None), None)


def _focal(values: dict, axis: str, size: int) -> float | None:
    """Focal length along ``axis`` in px from ``fl_{axis}`` or ``camera_angle_{axis}`` of ``values``, or ``None``."""
    if values.get(f"fl_{axis}") is not None:
        return float(values[f"fl_{axis}"])
    if values.get(f"camera_angle_{axis}") is not None:
        return 0.5 * size / math.tan(0.5 * float(values[f"camera_angle_{axis}"]))
    return None
