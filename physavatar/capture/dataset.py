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

from physavatar.capture.layout import INTRINSIC_KEYS, TRANSFORMS, Findings, read_index, read_views
from physavatar.capture.rig import CameraRig, Lighting
from physavatar.result_files import Staging, write_arrays, write_json, write_png

_TRUTH = "truth.npz"
_JSON_KEY = "__json__"  # the truth file's entry holding its non-array values as JSON
_DEFAULT_FPS = 25.0  # frames per second of a capture whose transforms.json gives none

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
    shared, per_frame = {}, [dict(zip(INTRINSIC_KEYS, row, strict=True)) for row in intrinsics]
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
    return write_json(folder / TRANSFORMS, meta, staging, indent=1)


def load_capture(folder: str | Path) -> Capture:
    """Read a capture written by :func:`write_capture` (or any such ``transforms.json`` with ``camera`` and
    ``time_index`` per frame), through the parser of :mod:`physavatar.capture.layout`.

    Intrinsics are the top-level ``fl_x``/``fl_y`` (or ``camera_angle_x``/``camera_angle_y``), ``cx``, ``cy``,
    ``w``, ``h``; a frame's own ``fl_x``, ``fl_y`` (or ``camera_angle_x``/``_y``), ``cx``, ``cy`` override them for
    its camera (nerfstudio's per-frame intrinsics), and must be the same at every time index of that camera; a
    missing ``fl_y`` means ``fl_x``, a missing principal point the image centre, a missing ``w``/``h`` the first
    image's size. A frame path without extension means ``.png``; ``fps`` defaults to 25.

    Args:
        folder: the capture's folder, or its ``transforms.json``.

    Raises:
        FileNotFoundError: ``transforms.json`` or an image or mask it lists is missing.
        ValueError: the json is malformed; the cameras are not numbered ``0..C−1``; a camera has fewer frames
            than another; a time index lacks some camera (or holds one twice); a camera moves or changes its
            intrinsics between frames; an image or mask is corrupt or not ``w × h``.
    """
    path = Path(folder)
    findings = Findings(path.parent if path.suffix == ".json" else path, strict=True)
    index = read_index(path, findings, default_fps=_DEFAULT_FPS)
    images, masks, _ = read_views(index, findings)
    lighting = index.meta.get("lighting")
    lighting = None if lighting is None else Lighting.from_dict(lighting)
    background = tuple(float(x) for x in index.meta.get("background", (1.0, 1.0, 1.0)))
    return Capture(images, masks, index.rig, index.fps, lighting, background)


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
