"""A capture folder read file by file: the one parser behind every reader of captures.

:func:`~physavatar.capture.load_capture` (the project's synthetic captures),
:func:`~physavatar.capture.load_capture_folder` (a researcher's own capture) and
:func:`~physavatar.capture.check_capture` (its validation) all read ``transforms.json``, the images, the masks and
the meshes through the functions here. Each function tells a :class:`Findings` what is wrong: a strict one raises at
the first problem (what a loader wants), a collecting one gathers every problem and warning while the reader goes
on with what it could read (what a check wants).

Conventions of ``transforms.json`` (NeRF-synthetic and nerfstudio): one entry per image in ``frames``, each with its
camera's camera-to-world ``transform_matrix`` (OpenGL: the camera looks along its −z axis, x right, y up), the
camera number ``camera`` and the ``time_index``; intrinsics in pixels at the top level or per frame. Paths are
relative to the capture folder.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image

from physavatar.capture.rig import CameraRig
from physavatar.garment import Garment, load_garment

__all__ = [
    "FRAME_KEYS",
    "INTRINSIC_KEYS",
    "TRANSFORMS",
    "UP_AXES",
    "CaptureIndex",
    "Findings",
    "Problem",
    "body_paths",
    "boundary_path",
    "garment_path",
    "read_body",
    "read_boundary",
    "read_garment",
    "read_index",
    "read_view",
    "read_views",
]

TRANSFORMS = "transforms.json"
"""The index file of a capture folder."""
FRAME_KEYS = ("file_path", "mask_path", "transform_matrix", "camera", "time_index")
"""Keys every entry of ``frames`` needs."""
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")
"""Intrinsics in pixels, at the top level (shared by every camera) or in a frame (its camera's own)."""
UP_AXES = ("y", "z")
"""World up axes a capture may declare with ``"up"``."""
_MESH_SUFFIXES = (".obj", ".ply")
_STATIC_TOLERANCE = 1e-9  # relative change of a camera's pose or intrinsics that still counts as the same


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture (or, as a warning, suspicious in it).

    Attributes:
        where: the file, relative to the capture folder, or the part of ``transforms.json`` (``frames[3]``,
            ``camera 1``) it is about.
        what: what is wrong, one sentence.
        fix: how to fix it, one sentence.
    """

    where: str
    what: str
    fix: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}; {self.fix}"


class Findings:
    """What readers found wrong in one capture folder: raised at once (``strict``) or collected.

    Args:
        root: the capture folder (named in the messages of a strict one).
        strict: raise at the first problem (``FileNotFoundError`` for a missing file, else ``ValueError``); warnings
            are collected either way.

    Attributes:
        problems: the problems found, in order, each once.
        warnings: the warnings found, in order, each once.
    """

    def __init__(self, root: str | Path, strict: bool):
        self.root = Path(root)
        self.strict = strict
        self.problems: list[Problem] = []
        self.warnings: list[Problem] = []

    def problem(self, where: str, what: str, fix: str, missing: bool = False) -> None:
        """Record a problem, or raise it when strict (``missing``: a file that does not exist)."""
        problem = Problem(where, what, fix)
        if self.strict:
            raise (FileNotFoundError if missing else ValueError)(f"capture {self.root}: {problem}")
        if problem not in self.problems:
            self.problems.append(problem)

    def warning(self, where: str, what: str, fix: str) -> None:
        """Record a warning: the capture is usable, but this looks wrong."""
        warning = Problem(where, what, fix)
        if warning not in self.warnings:
            self.warnings.append(warning)

    def count(self) -> int:
        """How many problems so far (a reader compares counts to learn whether a step found any)."""
        return len(self.problems)


@dataclass(frozen=True, eq=False)
class CaptureIndex:
    """``transforms.json`` parsed, in the capture's own world axes (nothing rotated).

    Attributes:
        json_path: the file.
        meta: its top-level object as read.
        frames: its ``frames`` entries as read (index ``k`` is ``frames[k]``; entries that are not objects are
            empty dicts here).
        views: ``[T][C]`` the ``frames`` index of time index ``t`` seen by camera ``c``; ``None`` where the
            cameras and time indices do not form that grid.
        times: the distinct time indices of the sound frame entries, sorted (``T`` of them where ``views`` is known;
            a best guess of ``T`` where it is not).
        size: ``(w, h)`` image size in pixels, or ``None`` where unknown.
        rig: the cameras, or ``None`` where poses, intrinsics or the grid are broken.
        fps: frames per second, or ``None`` where missing or invalid.
        up: the declared world up axis, ``"y"`` or ``"z"`` (``"y"`` where the declaration is invalid).
        body_masks: whether the frames give ``body_mask_path``.
    """

    json_path: Path
    meta: dict
    frames: list[dict]
    views: list[list[int]] | None
    times: list[int]
    size: tuple[int, int] | None
    rig: CameraRig | None
    fps: float | None
    up: str
    body_masks: bool

    @property
    def folder(self) -> Path:
        """The capture folder."""
        return self.json_path.parent

    @property
    def frame_count(self) -> int | None:
        """``T``, the number of time indices, where the grid is sound."""
        return None if self.views is None else len(self.views)

    @property
    def camera_count(self) -> int | None:
        """``C``, the number of cameras, where the grid is sound."""
        return None if self.views is None else len(self.views[0])


# ---------------------------------------------------------------------------------------------------------------
# transforms.json
# ---------------------------------------------------------------------------------------------------------------


def read_index(folder: str | Path, findings: Findings, default_fps: float | None = None) -> CaptureIndex | None:
    """Parse ``transforms.json``: frames, the camera × time grid, static poses and intrinsics, fps, up axis, units.

    Images are not opened, except the first one when neither the top level nor the frames give ``w``/``h``.

    Args:
        folder: the capture folder, or its ``transforms.json``.
        findings: told every problem (a strict one raises at the first).
        default_fps: fps where the json gives none; ``None`` makes a missing ``fps`` a problem.

    Returns:
        The index, or ``None`` when the file is missing, not json or lists no frames.
    """
    path = Path(folder)
    json_path = path if path.suffix == ".json" else path / TRANSFORMS
    name = json_path.name
    if not json_path.is_file():
        if not json_path.parent.is_dir():
            findings.problem(
                json_path.parent.name or str(json_path.parent),
                f"the capture folder {json_path.parent} does not exist",
                "pass the folder that holds transforms.json",
                missing=True,
            )
        else:
            findings.problem(
                name,
                f"{json_path} does not exist: a capture folder needs its index",
                f"write {TRANSFORMS} (frames, cameras, intrinsics, fps) or pass the folder that holds it",
                missing=True,
            )
        return None
    try:
        meta = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        findings.problem(
            name, f"is not valid json ({error})", "fix the syntax at the place named (a json linter shows it)"
        )
        return None
    if not isinstance(meta, dict):
        findings.problem(
            name, f"holds a json {type(meta).__name__}, not an object", "make its top level an object {...}"
        )
        return None
    if "frames" not in meta:
        findings.problem(name, "lacks the key 'frames'", "list one entry per image under 'frames'")
        return None
    raw = meta["frames"]
    if not isinstance(raw, list) or not raw:
        findings.problem(name, "lists no frames", "give 'frames' a non-empty list with one entry per image")
        return None
    frames = [frame if isinstance(frame, dict) else {} for frame in raw]
    fps = _fps(meta, name, findings, default_fps)
    up = _up(meta, name, findings)
    _units(meta, name, findings)
    entries = _frame_entries(raw, name, findings)
    body_masks = _body_masks(frames, name, findings)
    views = _grid(entries, name, findings) if len(entries) == len(raw) else None
    size = _size(meta, frames, json_path, findings)
    rig = None
    if views is not None:
        c2w = _static_poses(entries, views, name, findings)
        intrinsics = _static_intrinsics(meta, frames, views, size, name, findings)
        if c2w is not None and intrinsics is not None and size is not None:
            try:
                rig = CameraRig(c2w, size[0], size[1], *intrinsics.unbind(1))
            except ValueError as error:
                findings.problem(name, f"its cameras are invalid: {error}", "fix the intrinsics and image size")
    times = sorted({time for _, _, time, _ in entries})
    return CaptureIndex(json_path, meta, frames, views, times, size, rig, fps, up, body_masks)


def _fps(meta: dict, name: str, findings: Findings, default: float | None) -> float | None:
    value = meta.get("fps", default)
    if value is None:
        findings.problem(name, "lacks the key 'fps'", 'add "fps": the video\'s frames per second (e.g. 30)')
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        findings.problem(
            name, f"fps is {value!r}, not a positive number", 'set "fps" to the video\'s frames per second'
        )
        return None
    return float(value)


def _up(meta: dict, name: str, findings: Findings) -> str:
    up = meta.get("up", "y")
    if up not in UP_AXES:
        findings.problem(
            name, f"up is {up!r}, not one of {', '.join(map(repr, UP_AXES))}", 'set "up" to the world axis pointing up'
        )
        return "y"
    return up


def _units(meta: dict, name: str, findings: Findings) -> None:
    units = meta.get("units", "m")
    if units != "m":
        findings.problem(
            name,
            f"units is {units!r}: captures are read in metres only",
            'convert meshes and camera positions to metres (millimetres: scale by 0.001) and set "units": "m"',
        )


def _frame_entries(raw: list, name: str, findings: Findings) -> list[tuple[int, int, int, np.ndarray]]:
    """``(k, camera, time_index, pose [4, 4])`` of every sound frame entry; each unsound one is a problem."""
    entries = []
    for k, frame in enumerate(raw):
        where = f"{name} frames[{k}]"
        if not isinstance(frame, dict):
            findings.problem(where, f"is a json {type(frame).__name__}, not an object", "make every frame an object")
            continue
        missing = [key for key in FRAME_KEYS if key not in frame]
        if missing:
            findings.problem(
                where, f"lacks {', '.join(missing)}", f"give every frame {', '.join(FRAME_KEYS[:-1])} and time_index"
            )
            continue
        sound = True
        for key in ("file_path", "mask_path", "body_mask_path"):
            if key in frame and not isinstance(frame[key], str):
                findings.problem(where, f"{key} is {frame[key]!r}, not a path", f"give {key} as a relative path")
                sound = False
        camera, time = _whole(frame["camera"]), _whole(frame["time_index"])
        for key, value in (("camera", camera), ("time_index", time)):
            if value is None:
                findings.problem(where, f"{key} is {frame[key]!r}", f"give {key} as a whole number 0, 1, ...")
                sound = False
        pose = _pose(frame["transform_matrix"])
        if pose is None:
            findings.problem(
                where,
                "transform_matrix is not a finite 4x4 (or 3x4) matrix",
                "give the camera-to-world matrix as 4 rows of 4 numbers",
            )
            sound = False
        if sound:
            entries.append((k, camera, time, pose))
    return entries


def _whole(value) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value if value >= 0 else None
    if isinstance(value, float) and value.is_integer() and value >= 0:
        return int(value)
    return None


def _pose(value) -> np.ndarray | None:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        return None
    return matrix


def _body_masks(frames: list[dict], name: str, findings: Findings) -> bool:
    given = [k for k, frame in enumerate(frames) if "body_mask_path" in frame]
    if given and len(given) != len(frames):
        lacking = [k for k in range(len(frames)) if k not in set(given)]
        findings.problem(
            name,
            f"{len(given)} of {len(frames)} frames give body_mask_path (frames {_few(lacking)} do not)",
            "give body_mask_path in every frame or in none",
        )
    return bool(given) and len(given) == len(frames)


def _grid(entries: list[tuple[int, int, int, np.ndarray]], name: str, findings: Findings) -> list[list[int]] | None:
    """``[T][C]`` frame numbers, or ``None`` (and problems) where cameras and time indices do not form a grid."""
    before = findings.count()
    by_camera: dict[int, dict[int, int]] = {}
    for k, camera, time, _ in entries:
        views = by_camera.setdefault(camera, {})
        if time in views:
            findings.problem(
                name,
                f"frames[{views[time]}] and frames[{k}] are both camera {camera} at time index {time}",
                "keep one image per camera and time index",
            )
        views[time] = k
    cameras = sorted(by_camera)
    if cameras != list(range(len(cameras))):
        absent = sorted(set(range(max(cameras) + 1)) - set(cameras))
        findings.problem(
            name,
            f"cameras {absent} are missing: cameras must be numbered 0..C-1, got {_few(cameras)}",
            "renumber the cameras 0, 1, ..., C-1",
        )
    counts = {c: len(by_camera[c]) for c in cameras}
    most = max(counts, key=counts.get)
    uneven = [c for c in cameras if counts[c] != counts[most]]
    for c in uneven:
        findings.problem(
            name,
            f"mismatched frame counts: camera {c} has {counts[c]} frames but camera {most} has {counts[most]}",
            "every camera needs one image per time index",
        )
    times = sorted(set().union(*(set(v) for v in by_camera.values())))
    if not uneven:
        for t in times:
            lacking = [c for c in cameras if t not in by_camera[c]]
            if lacking:
                findings.problem(
                    name, f"time index {t} lacks camera(s) {lacking}", "every camera needs one image per time index"
                )
    if times != list(range(len(times))):
        findings.problem(
            name, f"time indices must be 0..T-1, got {_few(times)}", "renumber the time indices 0, 1, ..., T-1"
        )
    if findings.count() > before:
        return None
    return [[by_camera[c][t] for c in cameras] for t in times]


def _static_poses(entries, views: list[list[int]], name: str, findings: Findings) -> torch.Tensor | None:
    """``[C, 4, 4]`` float64 camera-to-world matrices; a camera whose pose changes over time is a problem."""
    pose = {k: matrix for k, _, _, matrix in entries}
    c2w = torch.empty(len(views[0]), 4, 4, dtype=torch.float64)
    sound = True
    for c in range(len(views[0])):
        poses = torch.tensor(np.stack([pose[views[t][c]] for t in range(len(views))]))
        change = (poses - poses[0]).abs().amax((1, 2))
        moved = torch.nonzero(change > _STATIC_TOLERANCE * max(1.0, float(poses.abs().max())))
        if len(moved):
            t = int(moved[0])
            findings.problem(
                name,
                f"camera {c} moves between time indices: its transform_matrix at time index {t} differs from the one "
                f"at time index 0 by up to {float(change[t]):.3g}",
                f"cameras are static: give every frame of camera {c} the same transform_matrix",
            )
            sound = False
        c2w[c] = poses[0]
    return c2w if sound else None


def _static_intrinsics(meta, frames, views, size, name: str, findings: Findings) -> torch.Tensor | None:
    """``[C, 4]`` float64 ``(f_x, f_y, c_x, c_y)`` px per camera; a camera whose values change over time, or no
    focal length at all, is a problem."""
    if size is None:
        return None
    width, height = size
    intrinsics = torch.empty(len(views[0]), 4, dtype=torch.float64)
    for c in range(len(views[0])):
        rows = []
        for t in range(len(views)):
            try:
                rows.append(_intrinsics(meta, frames[views[t][c]], width, height))
            except (TypeError, ValueError) as error:
                findings.problem(
                    f"{name} frames[{views[t][c]}]",
                    f"its intrinsics are not numbers ({error})",
                    "give fl_x, fl_y, cx, cy in pixels (or camera_angle_x/_y in radians) as numbers",
                )
                return None
        if any(row[0] is None for row in rows):
            findings.problem(
                name,
                "gives no focal length",
                "add 'fl_x' (pixels) or 'camera_angle_x' (radians) at the top level or in every frame",
            )
            return None
        values = torch.tensor(rows, dtype=torch.float64)
        changed = (values - values[0]).abs().amax(1) > _STATIC_TOLERANCE * values[0].abs().amax().clamp_min(1.0)
        if bool(changed.any()):
            k = int(torch.nonzero(changed)[0])
            findings.problem(
                name,
                f"camera {c} changes its intrinsics (fl_x, fl_y, cx, cy) between time indices: {values[0].tolist()} "
                f"at time index 0, {values[k].tolist()} at {k}",
                f"a camera is calibrated once, so give every frame of camera {c} the same values",
            )
            return None
        intrinsics[c] = values[0]
    return intrinsics


def _intrinsics(meta: dict, frame: dict, width: int, height: int) -> tuple[float | None, ...]:
    """``(fx, fy, cx, cy)`` px of one frame: its own values where it gives them, else the top-level ones; ``fx`` is
    ``None`` where neither gives a focal length."""
    fx = _first(_focal(frame, "x", width), _focal(meta, "x", width))
    fy = _first(_focal(frame, "y", height), _focal(meta, "y", height), fx)
    cx = _first(frame.get("cx"), meta.get("cx"), 0.5 * width)
    cy = _first(frame.get("cy"), meta.get("cy"), 0.5 * height)
    return fx, fy, _number(cx), _number(cy)


def _first(*values):
    return next((value for value in values if value is not None), None)


def _number(value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"{value!r} is not a number")
    return float(value)


def _focal(values: dict, axis: str, size: int) -> float | None:
    """Focal length along ``axis`` in px from ``fl_{axis}`` or ``camera_angle_{axis}`` of ``values``, or ``None``."""
    if values.get(f"fl_{axis}") is not None:
        return _number(values[f"fl_{axis}"])
    if values.get(f"camera_angle_{axis}") is not None:
        return 0.5 * size / math.tan(0.5 * _number(values[f"camera_angle_{axis}"]))
    return None


def _size(meta: dict, frames: list[dict], json_path: Path, findings: Findings) -> tuple[int, int] | None:
    """``(w, h)`` px: the top-level ``w``/``h``, else every frame's (all equal), else the first image's size."""
    name = json_path.name
    if "w" in meta or "h" in meta:
        width, height = meta.get("w"), meta.get("h")
        if _whole(width) in (None, 0) or _whole(height) in (None, 0):
            findings.problem(
                name, f"w, h are {width!r}, {height!r}", "give w and h as the image width and height in pixels"
            )
            return None
        return int(width), int(height)
    if all("w" in frame and "h" in frame for frame in frames):
        sizes = {(_whole(frame["w"]), _whole(frame["h"])) for frame in frames}
        if len(sizes) > 1 or any(value in (None, 0) for value in next(iter(sizes))):
            findings.problem(
                name,
                f"the frames give different or invalid image sizes {_few(sorted(sizes, key=str))}",
                "all cameras share one image size: give the same w and h (pixels) everywhere",
            )
            return None
        width, height = next(iter(sizes))
        return width, height
    first = frames[0].get("file_path")
    if not isinstance(first, str):
        return None
    pixels = read_view(json_path.parent, frames[0], "file_path", None, "RGB", findings, 0)
    return None if pixels is None else (pixels.shape[1], pixels.shape[0])


# ---------------------------------------------------------------------------------------------------------------
# Images and masks
# ---------------------------------------------------------------------------------------------------------------


def read_view(
    folder: Path,
    frame: dict,
    key: str,
    size: tuple[int, int] | None,
    mode: str,
    findings: Findings,
    number: int,
) -> np.ndarray | None:
    """The pixels of one image a frame lists: ``[H, W, 3]`` uint8 (``mode="RGB"``) or ``[H, W]`` uint8 (``"L"``).

    A path without an extension means ``.png``.

    Args:
        folder: the capture folder.
        frame: the frame entry.
        key: which of its paths: ``file_path``, ``mask_path`` or ``body_mask_path``.
        size: ``(w, h)`` px it must have, or ``None`` for any.
        mode: PIL mode to convert to.
        findings: told a missing, unreadable or wrongly sized image.
        number: the frame's index in ``frames`` (named in messages).

    Returns:
        The pixels, or ``None`` after a problem.
    """
    relative = frame[key]
    path = folder / relative
    if not path.suffix and not path.is_file():
        path = path.with_name(path.name + ".png")
    where = path.relative_to(folder).as_posix() if path.is_relative_to(folder) else str(path)
    view = f"time index {frame.get('time_index')}, camera {frame.get('camera')}"
    if not path.is_file():
        findings.problem(
            where,
            f"{path} does not exist ({key} of frames[{number}] in {TRANSFORMS}, {view})",
            f"add the image or correct {key} (a path relative to the capture folder)",
            missing=True,
        )
        return None
    try:
        with Image.open(path) as image:
            image.load()
            found = image.size
            pixels = np.asarray(image.convert(mode))
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        findings.problem(where, f"is not a readable image ({error})", "export it again as PNG or JPEG")
        return None
    if size is not None and found != tuple(size):
        findings.problem(
            where,
            f"is {found[0]}x{found[1]} pixels but {TRANSFORMS} says {size[0]}x{size[1]} ({view})",
            "export every image and mask at the capture's one size, or fix w/h",
        )
        return None
    return pixels


def read_views(
    index: CaptureIndex, findings: Findings, progress: Callable[[int, int], None] | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Every image and mask of a sound index, in its ``[T, C]`` grid.

    Args:
        index: an index whose ``views`` and ``rig`` are known.
        findings: told missing, unreadable or wrongly sized images.
        progress: called as ``progress(done, total)`` after each view (image, mask and body mask).

    Returns:
        ``images [T, C, H, W, 3]`` float32 in [0, 1], ``masks [T, C, H, W]`` bool (pixels >= 128) and body masks
        like ``masks`` or ``None`` where the frames give none. With a collecting ``findings``, a view that could
        not be read stays black and unmasked.
    """
    if index.views is None or index.rig is None:
        raise ValueError("read_views needs an index whose cameras and time indices are sound; check the capture")
    frames, cameras = index.frame_count, index.camera_count
    shape = (frames, cameras, index.rig.height, index.rig.width)
    images = torch.zeros(*shape, 3, dtype=torch.float32)
    masks = torch.zeros(shape, dtype=torch.bool)
    body_masks = torch.zeros(shape, dtype=torch.bool) if index.body_masks else None
    size = (index.rig.width, index.rig.height)
    for t in range(frames):
        for c in range(cameras):
            k = index.views[t][c]
            frame = index.frames[k]
            pixels = read_view(index.folder, frame, "file_path", size, "RGB", findings, k)
            if pixels is not None:
                images[t, c] = torch.from_numpy(pixels.astype(np.float32) / 255.0)
            for key, out in (("mask_path", masks), ("body_mask_path", body_masks)):
                if out is not None:
                    pixels = read_view(index.folder, frame, key, size, "L", findings, k)
                    if pixels is not None:
                        out[t, c] = torch.from_numpy(pixels >= 128)
            if progress is not None:
                progress(t * cameras + c + 1, frames * cameras)
    return images, masks, body_masks


# ---------------------------------------------------------------------------------------------------------------
# Meshes
# ---------------------------------------------------------------------------------------------------------------


def garment_path(folder: Path, meta: dict, findings: Findings) -> Path | None:
    """The garment mesh: ``meta["garment"]``, else ``garment.obj``, else ``garment.ply``; ``None`` after a problem."""
    if "garment" in meta:
        if not isinstance(meta["garment"], str):
            findings.problem(TRANSFORMS, f"garment is {meta['garment']!r}", "give 'garment' as a relative path")
            return None
        path = folder / meta["garment"]
    else:
        path = next((folder / name for name in ("garment.obj", "garment.ply") if (folder / name).is_file()), None)
        path = folder / "garment.obj" if path is None else path
    if not path.is_file():
        findings.problem(
            _where(folder, path),
            f"{path} does not exist: the capture needs the garment at time index 0",
            "add the garment mesh (OBJ or PLY) as garment.obj, or name it with 'garment' in transforms.json",
            missing=True,
        )
        return None
    return path


def boundary_path(folder: Path, meta: dict, findings: Findings) -> Path | None:
    """The boundary vertex file: ``meta["boundary"]`` (which must exist), else ``boundary.txt`` where present."""
    if "boundary" not in meta:
        path = folder / "boundary.txt"
        return path if path.is_file() else None
    if not isinstance(meta["boundary"], str):
        findings.problem(TRANSFORMS, f"boundary is {meta['boundary']!r}", "give 'boundary' as a relative path")
        return None
    path = folder / meta["boundary"]
    if not path.is_file():
        findings.problem(
            _where(folder, path),
            f"{path} does not exist but transforms.json names it as the boundary",
            "add the file, or remove 'boundary' to have the boundary chosen automatically",
            missing=True,
        )
        return None
    return path


def body_paths(folder: Path, meta: dict, frame_count: int | None, findings: Findings) -> list[Path] | None:
    """The body meshes, one per time index: ``meta["body"]``, else ``body/*.obj|*.ply`` in natural name order.

    Args:
        folder: the capture folder.
        meta: ``transforms.json``'s object.
        frame_count: ``T`` where known: a different number of meshes is a problem.
        findings: told problems.

    Returns:
        The paths (existing or not: :func:`read_body` names the missing ones), or ``None`` after a problem.
    """
    if "body" in meta:
        listed = meta["body"]
        if not isinstance(listed, list) or not all(isinstance(p, str) for p in listed):
            findings.problem(TRANSFORMS, "body is not a list of paths", "give 'body' as a list of relative paths")
            return None
        paths, where = [folder / p for p in listed], f"{TRANSFORMS} body"
    else:
        directory = folder / "body"
        if not directory.is_dir():
            findings.problem(
                "body/",
                f"{directory} does not exist: the capture needs one body mesh per time index",
                "put the body meshes (OBJ or PLY, one per time index) in body/, or list them as 'body' in "
                "transforms.json",
                missing=True,
            )
            return None
        paths = sorted((p for p in directory.iterdir() if p.suffix.lower() in _MESH_SUFFIXES), key=_natural)
        where = "body/"
    if not paths:
        findings.problem(where, "lists no body mesh", "give one OBJ or PLY body mesh per time index")
        return None
    if frame_count is not None and len(paths) != frame_count:
        findings.problem(
            where,
            f"{len(paths)} body meshes for {frame_count} time indices",
            "give exactly one body mesh per time index, in time order (file names sort naturally: 2 before 10)",
        )
    return paths


def _natural(path: Path) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def read_body(folder: Path, paths: list[Path], findings: Findings) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Read the body meshes (trimesh, unprocessed): one topology in every frame.

    Returns:
        ``vertices [T, B, 3]`` float64 (the files' axes and units) and ``faces [G, 3]`` int64, or ``None`` after a
        problem.
    """
    before = findings.count()
    frames, faces, first = [], None, None
    for path in paths:
        where = _where(folder, path)
        if not path.is_file():
            findings.problem(
                where, f"{path} does not exist", "add the body mesh of this time index or fix the list", missing=True
            )
            continue
        try:
            mesh = trimesh.load(path, process=False, force="mesh")
            v = np.asarray(mesh.vertices, dtype=np.float64)
            f = np.asarray(mesh.faces, dtype=np.int64)
        except Exception as error:  # trimesh raises many types for unreadable files
            findings.problem(where, f"is not a readable triangle mesh ({error})", "export it again as OBJ or PLY")
            continue
        if f.ndim != 2 or f.shape[1:] != (3,) or not len(f) or v.ndim != 2 or v.shape[1:] != (3,):
            findings.problem(where, "holds no triangles", "export the body as a triangle mesh")
            continue
        if not np.isfinite(v).all():
            findings.problem(where, "holds NaN or infinite coordinates", "export the body mesh again")
            continue
        if faces is None:
            frames, faces, first = [v], f, where
        elif v.shape != frames[0].shape:
            findings.problem(
                where,
                f"has {len(v)} vertices but {first} has {len(frames[0])}: the body's topology changes",
                "export every body frame from one mesh (same vertices and faces in the same order)",
            )
        elif not np.array_equal(f, faces):
            findings.problem(
                where,
                f"its faces differ from those of {first}: the body's topology changes",
                "export every body frame from one mesh (same vertices and faces in the same order)",
            )
        else:
            frames.append(v)
    if findings.count() > before or faces is None:
        return None
    return torch.from_numpy(np.stack(frames)), torch.from_numpy(faces)


def read_garment(folder: Path, path: Path, findings: Findings) -> Garment | None:
    """The garment at time index 0 in the file's coordinates (:func:`~physavatar.garment.load_garment`, unscaled):
    welded, validated (no zero-area or non-manifold triangles); ``None`` after a problem."""
    where = _where(folder, path)
    try:
        return load_garment(path, scale=None)
    except FileNotFoundError as error:
        findings.problem(where, str(error), "add the garment mesh", missing=True)
    except ValueError as error:
        what = str(error).removeprefix(f"{path.name}: ").removeprefix(f"{path.name}:")
        findings.problem(where, what, "repair the garment mesh where the message says and export it again")
    return None


def read_boundary(folder: Path, path: Path, garment: Garment | None, findings: Findings) -> torch.Tensor | None:
    """The boundary vertices of ``boundary.txt``: 0-based indices into the garment file's vertices, whitespace
    separated, ``#`` starting a comment, remapped to ``garment``'s (welded) vertices.

    Returns:
        ``[D]`` int64 sorted unique indices into ``garment.vertices``, or ``None`` after a problem or without a
        garment to check them against.
    """
    where = _where(folder, path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        findings.problem(where, f"is not readable text ({error})", "write the indices as plain text")
        return None
    indices = []
    for number, line in enumerate(text.splitlines(), start=1):
        for token in line.split("#", 1)[0].split():
            if not (token.isascii() and token.lstrip("-").isdigit()):
                findings.problem(
                    where,
                    f"line {number}: {token!r} is not a vertex index",
                    "list 0-based integer vertex indices separated by spaces or newlines ('#' starts a comment)",
                )
                return None
            indices.append(int(token))
    if not indices:
        findings.problem(
            where,
            "lists no vertex index",
            "list the vertices that follow the body, or delete the file to have them chosen automatically",
        )
        return None
    if garment is None:
        return None
    indices = np.asarray(indices, dtype=np.int64)
    vertex_map = garment.vertex_map.numpy()
    count = len(vertex_map)
    outside = indices[(indices < 0) | (indices >= count)]
    if outside.size:
        findings.problem(
            where,
            f"{outside.size} indices are outside 0..{count - 1} (e.g. {_few(outside)})",
            f"indices are 0-based positions in the garment file's list of {count} vertices",
        )
        return None
    mapped = vertex_map[indices]
    loose = indices[mapped < 0]
    if loose.size:
        findings.problem(
            where,
            f"vertices {_few(loose)} belong to no triangle of the garment",
            "list vertices of the garment's triangles",
        )
        return None
    return torch.unique(torch.from_numpy(mapped))


def _where(folder: Path, path: Path) -> str:
    return path.relative_to(folder).as_posix() if path.is_relative_to(folder) else str(path)


def _few(values, count: int = 5) -> str:
    values = list(values)
    return ", ".join(str(v) for v in values[:count]) + (", ..." if len(values) > count else "")
