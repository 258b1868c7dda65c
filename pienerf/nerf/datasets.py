"""Multi-view RGBA datasets in the NeRF-synthetic / instant-NGP ``transforms*.json`` format: what a NeRF trains on.

PIE-NeRF's input (§3.1, Fig. 2) is a set of photos of a static scene with known cameras; a NeRF renders a pixel by
integrating density and colour along the pixel's ray. This module reads such a set into tensors and makes the
rays.

Format (one json per split, paths relative to the json's folder):

* ``frames``: a list of ``{"file_path": ..., "transform_matrix": 4×4}``; ``file_path`` may omit the extension
  (``./train/r_0`` means ``train/r_0.png``). ``transform_matrix`` is camera-to-world with OpenGL camera axes:
  x right, y up, the camera looking down −z (as Blender writes it).
* Intrinsics, top-level or per frame (per-frame values win): ``camera_angle_x`` (horizontal field of view,
  radians; ``fx = ½ W / tan(½ camera_angle_x)``) with optional ``camera_angle_y``, or instant-NGP's
  ``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` in pixels. Missing ``fy`` equals ``fx``; missing ``cx, cy`` are
  the image centre. Lens distortion (``k1``, ``k2``, ``p1``, ``p2``) is not modelled and must be zero.

Pixel ``(u, v)`` (column, row, from the top-left corner) has its centre at ``(u + ½, v + ½)``; its ray leaves
the camera centre along ``((u + ½ − cx) / fx, −(v + ½ − cy) / fy, −1)`` in camera axes. With this convention a
downscale by an integer ``k`` that averages ``k × k`` blocks divides ``fx, fy, cx, cy`` by exactly ``k``.

Image paths must stay inside the json's folder (no absolute paths, no ``..`` out of it) unless the caller passes
``allow_outside=True``; an image may have at most :data:`MAX_IMAGE_PIXELS` pixels, checked from its header before
it is decoded.

Splits: ``split="train"`` reads ``transforms_train.json`` (or instant-NGP's single ``transforms.json``);
``"val"``/``"test"`` read ``transforms_val.json``/``transforms_test.json`` when present, else hold out every
``holdout_every``-th view of the training json (views 0, k, 2k, …). The same views leave the training set with
:meth:`NerfDataset.held_out`, so the two never overlap.
"""

from __future__ import annotations

import json
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from pienerf.nerf.cameras import Cameras, check_downscale, view_index

__all__ = ["MAX_IMAGE_PIXELS", "NerfDataset", "load_nerf_dataset"]

MAX_IMAGE_PIXELS = 64_000_000
"""Most pixels (width × height) one dataset image may have: 64 Mpx, 1 GiB as float32 RGBA, eight times a 4K frame.
Larger images are refused from their header, before decoding (a small compressed file can claim 30000² pixels)."""

_LOAD_THREADS = 16  # most threads decoding images at once

_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


class _TooLargeError(Exception):
    """An image's header claims more than :data:`MAX_IMAGE_PIXELS` pixels."""


@dataclass
class NerfDataset:
    """Images, alphas and cameras of one split of a multi-view dataset.

    Attributes:
        images: ``[N, H, W, 3]`` float32 in [0, 1], composited over ``background``.
        alphas: ``[N, H, W]`` float32 coverage in [0, 1] (1 where an image has no alpha channel).
        cameras: the views' :class:`Cameras`.
        names: ``N`` frame names (``file_path`` as written in the json).
        split: the split that was read (``"train"``, ``"val"`` or ``"test"``).
        background: the colour composited under the images: an RGB triple, or ``"random"`` (uniform noise per
            pixel, redrawn at load with the given seed: a NeRF trained on it cannot bake a background colour
            into its density).
    """

    images: torch.Tensor
    alphas: torch.Tensor
    cameras: Cameras
    names: list[str]
    split: str
    background: tuple[float, float, float] | str = (1.0, 1.0, 1.0)

    def __len__(self) -> int:
        return self.images.shape[0]

    def select(self, index) -> NerfDataset:
        """The views ``index`` picks (an int, a slice, a list or a tensor of view indices)."""
        index = view_index(index, len(self))
        names = [self.names[i] for i in torch.arange(len(self))[index].tolist()]
        return replace(
            self, images=self.images[index], alphas=self.alphas[index], cameras=self.cameras.select(index), names=names
        )

    def over_background(self, background: tuple[float, float, float]) -> NerfDataset:
        """The same views composited over another solid ``background`` (RGB in [0, 1]), from their alphas: e.g. views
        loaded over black for training, scored over white (``image' = image + (1 − α)(background' − background)``).

        Raises:
            ValueError: the views lie over a ``"random"`` background (its colours are not kept) or ``background`` is
                not an RGB triple in [0, 1].
        """
        if isinstance(self.background, str):
            raise ValueError(
                "views over a 'random' background cannot be recomposited; load them over a solid one, e.g. "
                "background=(0, 0, 0)"
            )
        new = _check_background(background)
        if isinstance(new, str):
            raise ValueError("over_background needs an RGB triple, not 'random'")
        shift = torch.tensor(new, dtype=torch.float32) - torch.tensor(self.background, dtype=torch.float32)
        images = (self.images + (1.0 - self.alphas[..., None]) * shift).clamp(0.0, 1.0)
        return replace(self, images=images, background=new)

    def held_out(self, every: int = 8) -> tuple[NerfDataset, NerfDataset]:
        """Split into training views and held-out views 0, ``every``, 2·``every``, … (as ``split="test"`` does
        when a dataset has no test json).

        Returns:
            ``(train, held_out)``.
        """
        if not (isinstance(every, int) and every >= 2):
            raise ValueError(f"every must be an integer ≥ 2 (hold out one view in `every`), got {every!r}")
        held = torch.arange(len(self)) % every == 0
        train, test = self.select(torch.nonzero(~held).flatten()), self.select(torch.nonzero(held).flatten())
        return replace(train, split="train"), replace(test, split="test")


def load_nerf_dataset(
    folder: str | Path,
    split: str = "train",
    downscale: int = 1,
    background: tuple[float, float, float] | str = (1.0, 1.0, 1.0),
    max_views: int | None = None,
    holdout_every: int = 8,
    seed: int = 0,
    allow_outside: bool = False,
) -> NerfDataset:
    """Read one split of a NeRF-synthetic / instant-NGP dataset.

    Args:
        folder: the dataset's folder (holding ``transforms_<split>.json``) or a path to a transforms json.
        split: ``"train"``, ``"val"`` or ``"test"`` (see the module docstring for missing jsons).
        downscale: integer factor; ``k × k`` blocks are averaged with premultiplied alpha (colour weighted by
            coverage, so transparent pixels' colours do not bleed into edges) and intrinsics divided by ``k``.
        background: RGB triple in [0, 1] (``(1, 1, 1)`` white, ``(0, 0, 0)`` black) or ``"random"`` (see
            :class:`NerfDataset`).
        max_views: read only the first ``max_views`` views of the split.
        holdout_every: ``k`` of the held-out views when a val/test json is missing.
        seed: seed of the ``"random"`` background.
        allow_outside: accept ``file_path`` entries that lead outside the json's folder (absolute paths, ``..``);
            off by default, so a dataset cannot make the loader read arbitrary files.

    Returns:
        A :class:`NerfDataset` on the CPU.

    Raises:
        FileNotFoundError: the json or an image it lists does not exist.
        ValueError: the json is malformed (no frames, a field of the wrong type, no or invalid intrinsics), an image
            is corrupt or too large, images differ in size, or a path leaves the dataset folder.
    """
    json_path, hold_out = _split_json(Path(folder), split, holdout_every)
    try:
        meta = json.loads(json_path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{json_path} is not valid json: {error}") from error
    except RecursionError as error:
        raise ValueError(f"{json_path} nests too deeply to be a transforms json") from error
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames or not isinstance(frames, list):
        raise ValueError(f"{json_path} lists no frames; a transforms json needs a non-empty 'frames' list")
    for k, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise ValueError(
                f"frame {k} in {json_path} is {type(frame).__name__}, not an object with 'file_path' and "
                "'transform_matrix'"
            )
    if hold_out:
        frames = [frames[i] for i in range(len(frames)) if i % holdout_every == 0]
    if max_views is not None:
        if not isinstance(max_views, int) or isinstance(max_views, bool) or max_views < 1:
            raise ValueError(f"max_views must be an integer of at least 1, got {max_views!r}")
        frames = frames[:max_views]
    background_rgb = _check_background(background)

    paths = [_image_path(json_path, frame, allow_outside) for frame in frames]
    (width, height), first = _read_premultiplied(paths[0], json_path, downscale)
    images = torch.empty(len(paths), *first.shape[:2], 3)
    alphas = torch.empty(len(paths), *first.shape[:2])
    if isinstance(background_rgb, str):
        generator = torch.Generator().manual_seed(seed)
        under = torch.rand(images.shape, generator=generator).numpy()
    else:
        under = np.asarray(background_rgb, dtype=np.float32)
    image_array, alpha_array = images.numpy(), alphas.numpy()

    def composite(k: int, rgba: np.ndarray | None = None) -> None:
        """Decode view ``k`` (unless given) and composite it straight into its slot of the outputs."""
        if rgba is None:
            size, rgba = _read_premultiplied(paths[k], json_path, downscale)
            if size != (width, height):
                raise ValueError(
                    f"{paths[k].name} is {size[0]}x{size[1]} pixels but {paths[0].name} is {width}x{height}; "
                    f"every view in {json_path.name} must have one size (resize the images to match)"
                )
        alpha = rgba[..., 3]
        alpha_array[k] = alpha
        view_under = under[k] if isinstance(background_rgb, str) else under
        out = image_array[k]
        np.multiply(1.0 - alpha[..., None], view_under, out=out)
        out += rgba[..., :3]
        np.clip(out, 0.0, 1.0, out=out)

    composite(0, first)
    # Decoding (zlib) and NumPy's arithmetic release the GIL: threads decode on every core, each writing its own
    # slot of the preallocated outputs (stacking the decoded views afterwards cost more than decoding them).
    with ThreadPoolExecutor(max_workers=max(1, min(len(paths) - 1, os.cpu_count() or 1, _LOAD_THREADS))) as pool:
        list(pool.map(composite, range(1, len(paths))))

    intrinsics = [_intrinsics(meta, frame, width, height, json_path) for frame in frames]
    fx, fy, cx, cy = (torch.tensor([k[i] for k in intrinsics], dtype=torch.float32) for i in range(4))
    c2w = torch.tensor(np.stack([_transform(frame, json_path) for frame in frames]), dtype=torch.float32)
    cameras = Cameras(c2w, fx, fy, cx, cy, width, height).scaled(downscale)

    return NerfDataset(
        images=images,
        alphas=alphas,
        cameras=cameras,
        names=[str(frame.get("file_path", "")) for frame in frames],
        split=split,
        background=background_rgb,
    )


def _split_json(folder: Path, split: str, holdout_every: int) -> tuple[Path, bool]:
    """The json to read and whether to keep only every ``holdout_every``-th of its frames."""
    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be 'train', 'val' or 'test', got {split!r}")
    if folder.is_file():
        return folder, False
    if not folder.is_dir():
        raise FileNotFoundError(f"dataset folder {folder} does not exist")
    own = folder / f"transforms_{split}.json"
    if own.is_file():
        return own, False
    training = next((p for p in (folder / "transforms_train.json", folder / "transforms.json") if p.is_file()), None)
    if training is None:
        raise FileNotFoundError(
            f"{folder} holds neither transforms_{split}.json nor transforms_train.json / transforms.json"
        )
    if split == "train":
        return training, False
    if not (isinstance(holdout_every, int) and holdout_every >= 2):
        raise ValueError(f"holdout_every must be an integer ≥ 2, got {holdout_every!r}")
    return training, True


def _image_path(json_path: Path, frame: dict, allow_outside: bool) -> Path:
    if "file_path" not in frame:
        raise ValueError(f"a frame in {json_path.name} has no 'file_path'")
    file_path = frame["file_path"]
    if not isinstance(file_path, str) or not file_path or "\x00" in file_path:
        raise ValueError(
            f"'file_path' {file_path!r} in {json_path} must be a non-empty string naming an image, "
            "relative to the json's folder"
        )
    folder = os.path.normpath(os.path.abspath(json_path.parent))
    joined = os.path.normpath(os.path.join(folder, file_path))
    if not allow_outside and os.path.commonpath([folder, joined]) != folder:
        raise ValueError(
            f"'file_path' {file_path!r} in {json_path} leads outside the dataset folder {folder}; move the image "
            "into the folder (paths relative to the json), or pass allow_outside=True if you trust this dataset"
        )
    path = Path(joined).resolve()
    if path.suffix in _IMAGE_EXTENSIONS and path.is_file():
        return path
    for extension in _IMAGE_EXTENSIONS:
        candidate = path.with_name(path.name + extension)
        if candidate.is_file():
            return candidate
    shown = path if path.suffix in _IMAGE_EXTENSIONS else path.with_name(path.name + ".png")
    raise FileNotFoundError(f"{shown} listed in {json_path.name} does not exist")


def _read_premultiplied(path: Path, json_path: Path, downscale: int) -> tuple[tuple[int, int], np.ndarray]:
    """Full-size ``(width, height)`` and the premultiplied RGBA ``[H / k, W / k, 4]`` float32 image of ``path``.

    Colour is multiplied by alpha before ``k × k`` blocks are averaged, so the average is the block's true
    coverage-weighted colour; an image without alpha has alpha 1.
    """
    from PIL import Image

    try:
        with Image.open(path) as image:
            width, height = image.size
            if width * height > MAX_IMAGE_PIXELS:
                raise _TooLargeError(f"{width}x{height} pixels")
            image.load()
            if image.mode in ("I;16", "I;16B", "I"):
                grey = np.asarray(image, dtype=np.float32) / 65535.0
                rgba = np.concatenate([np.repeat(grey[..., None], 3, -1), np.ones_like(grey)[..., None]], -1)
            else:
                rgba = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
    except (_TooLargeError, Image.DecompressionBombError) as error:
        raise ValueError(
            f"{path.name} listed in {json_path.name} is too large ({error}); images may have at most "
            f"{MAX_IMAGE_PIXELS} pixels: downscale it"
        ) from error
    except (OSError, SyntaxError, ValueError, EOFError) as error:
        raise ValueError(
            f"{path.name} listed in {json_path.name} is not a readable image ({error}); re-export or re-download it"
        ) from error
    height, width = rgba.shape[:2]
    check_downscale(downscale, width, height, f"{path.name}")
    rgba[..., :3] *= rgba[..., 3:4]
    if downscale > 1:
        rgba = rgba.reshape(height // downscale, downscale, width // downscale, downscale, 4).mean(axis=(1, 3))
    return (width, height), np.ascontiguousarray(rgba, dtype=np.float32)


def _intrinsics(meta: dict, frame: dict, width: int, height: int, json_path: Path) -> tuple[float, ...]:
    """``(fx, fy, cx, cy)`` in pixels of the full-size image, per-frame keys overriding top-level ones."""

    def get(key):
        value = frame.get(key, meta.get(key))
        if value is None:
            return None
        finite = isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) < 1e300
        if not finite or not math.isfinite(value):  # (abs first: math.isfinite overflows on a huge int)
            raise ValueError(
                f"'{key}' of frame {frame.get('file_path')!r} in {json_path} must be a finite number, got {value!r}"
            )
        return value

    for key in _DISTORTION_KEYS:
        if get(key) not in (None, 0, 0.0):
            raise ValueError(
                f"{json_path.name} has lens distortion {key}={get(key)}; only undistorted pinhole images are "
                "supported: undistort the images and drop the k/p coefficients"
            )
    for key, size in (("w", width), ("h", height)):
        if get(key) is not None and get(key) != size:
            raise ValueError(
                f"{json_path.name} says {key}={get(key)} but its images are {width}x{height} pixels; "
                "fix the json or the images"
            )
    for key in ("camera_angle_x", "camera_angle_y"):
        angle = get(key)
        if angle is not None and not 0.0 < angle < math.pi:
            raise ValueError(
                f"'{key}' of frame {frame.get('file_path')!r} in {json_path} is {angle}; a field of view must lie "
                "in (0, π) radians"
            )
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
    elif get("camera_angle_x") is not None:
        fx = 0.5 * width / math.tan(0.5 * get("camera_angle_x"))
    else:
        raise ValueError(
            f"{json_path.name} gives no intrinsics: add 'camera_angle_x' (radians) or instant-NGP's 'fl_x' (pixels)"
        )
    if get("fl_y") is not None:
        fy = float(get("fl_y"))
    elif get("camera_angle_y") is not None:
        fy = 0.5 * height / math.tan(0.5 * get("camera_angle_y"))
    else:
        fy = fx
    cx = float(get("cx")) if get("cx") is not None else 0.5 * width
    cy = float(get("cy")) if get("cy") is not None else 0.5 * height
    if not all(math.isfinite(x) for x in (fx, fy, cx, cy)) or fx <= 0.0 or fy <= 0.0:
        raise ValueError(f"{json_path.name} has invalid intrinsics fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return fx, fy, cx, cy


def _transform(frame: dict, json_path: Path) -> np.ndarray:
    matrix = frame.get("transform_matrix")
    try:
        matrix = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as error:
        raise ValueError(
            f"'transform_matrix' of frame {frame.get('file_path')!r} in {json_path} must be a 4x4 list of numbers "
            f"({error})"
        ) from error
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(
            f"frame {frame.get('file_path')!r} in {json_path.name} needs a finite 4x4 'transform_matrix', "
            f"got shape {matrix.shape}"
        )
    return matrix


def _check_background(background) -> tuple[float, float, float] | str:
    if isinstance(background, str):
        if background != "random":
            raise ValueError(f"background must be an RGB triple in [0, 1] or 'random', got {background!r}")
        return background
    rgb = tuple(float(c) for c in background)
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"background must be an RGB triple in [0, 1] or 'random', got {background!r}")
    return rgb
