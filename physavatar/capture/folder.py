"""A researcher's own capture, read from its folder: the multi-view video, the body sequence and the garment.

The folder (``docs/capture.md``)::

    CAPTURE/
      transforms.json   the index: fps, up axis, intrinsics, one frame per (camera, time index)
      images/, masks/   the RGB images and garment masks it lists (body_masks/ optionally)
      body/             one body mesh per time index, one topology (or listed as "body" in transforms.json)
      garment.obj       the garment at time index 0 (or named by "garment")
      boundary.txt      optional: garment vertices that follow the body (or named by "boundary")

Everything is in metres. Inside the project the world is y-up: a capture declaring ``"up": "z"`` is turned by the
rotation ``(x, y, z) → (x, z, −y)`` on load, meshes and camera-to-world matrices alike (so every point projects to
the same pixel as before), and :meth:`CaptureFolder.to_capture_axes` turns results back for the user.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from physavatar.capture.dataset import Capture
from physavatar.capture.layout import (
    Findings,
    body_paths,
    boundary_path,
    garment_path,
    read_body,
    read_boundary,
    read_garment,
    read_index,
    read_views,
)
from physavatar.capture.rig import CameraRig

__all__ = [
    "CaptureFolder",
    "from_capture_axes",
    "load_capture_folder",
    "to_capture_axes",
]


def _z_up_to_y_up() -> torch.Tensor:
    """``[3, 3]`` float64 rotation taking z-up world coordinates to the project's y-up ones: ``(x, y, z) → (x, z,
    −y)`` (a signed permutation, so exact in floating point)."""
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


def to_capture_axes(points: torch.Tensor, up: str) -> torch.Tensor:
    """``[..., 3]`` points (or directions) in the project's y-up axes turned into a capture's whose up axis is ``up``
    (``"y"``: unchanged; ``"z"``: ``(x, y, z) → (x, −z, y)``)."""
    return points if up == "y" else points @ _z_up_to_y_up().to(points)


def from_capture_axes(points: torch.Tensor, up: str) -> torch.Tensor:
    """``[..., 3]`` points (or directions) in a capture's axes (up axis ``up``) turned into the project's y-up axes:
    the inverse of :func:`to_capture_axes`."""
    return points if up == "y" else points @ _z_up_to_y_up().to(points).T


@dataclass(frozen=True, eq=False)
class CaptureFolder:
    """A user capture in the project's axes (y up, metres).

    Attributes:
        path: the capture folder.
        film: the video: images ``[T, C, H, W, 3]`` float32, garment masks ``[T, C, H, W]`` bool, the cameras (y-up
            world), fps; ``lighting`` is ``None`` (unknown). ``None`` when loaded without views.
        body_frames: ``[T, B, 3]`` float64 body vertices per time index, m.
        body_faces: ``[G, 3]`` int64 body triangles (one topology for every frame).
        garment_vertices: ``[V, 3]`` float64 garment at time index 0, m (welded).
        garment_faces: ``[F, 3]`` int64 garment triangles.
        boundary: ``[D]`` int64 sorted indices into ``garment_vertices`` of the vertices that follow the body (the
            file's indices remapped through the weld), or ``None`` where the capture gives none.
        up: the capture's declared up axis, ``"y"`` or ``"z"``.
        body_masks: ``[T, C, H, W]`` bool body masks, or ``None`` where the capture gives none (or it was loaded
            without views).
        fps: frames per second of the video and the body sequence.
    """

    path: Path
    film: Capture | None
    body_frames: torch.Tensor
    body_faces: torch.Tensor
    garment_vertices: torch.Tensor
    garment_faces: torch.Tensor
    boundary: torch.Tensor | None
    up: str
    body_masks: torch.Tensor | None
    fps: float

    def to_capture_axes(self, points: torch.Tensor) -> torch.Tensor:
        """``[..., 3]`` points (or directions) in the project's y-up axes turned into the capture's declared axes."""
        return to_capture_axes(points, self.up)

    def from_capture_axes(self, points: torch.Tensor) -> torch.Tensor:
        """``[..., 3]`` points (or directions) in the capture's declared axes turned into the project's y-up axes."""
        return from_capture_axes(points, self.up)


def load_capture_folder(
    path: str | Path, progress: Callable[[int, int], None] | None = None, views: bool = True
) -> CaptureFolder:
    """Read a capture folder into the project's y-up axes.

    ``transforms.json`` and the meshes are read and checked before any image is: a broken folder fails fast.
    :func:`~physavatar.capture.check_capture` finds every problem at once and the ones this does not look for
    (a garment far from the body, millimetres, cameras that miss the garment); run it first on a new capture.

    Args:
        path: the capture folder (or its ``transforms.json``).
        progress: called as ``progress(done, total)`` after each of the ``T·C`` views (image and masks) is read.
        views: read the images and masks; without them (a program that plays the body sequence) ``film`` and
            ``body_masks`` are ``None`` and no image is opened.

    Returns:
        The :class:`CaptureFolder`.

    Raises:
        FileNotFoundError: the folder, ``transforms.json``, or a file it names or implies is missing.
        ValueError: anything else in the folder breaks the format (the message names the file and the fix).
    """
    path = Path(path)
    folder = path.parent if path.suffix == ".json" else path
    findings = Findings(folder, strict=True)
    index = read_index(path, findings)
    paths = body_paths(folder, index.meta, index.frame_count, findings)
    body, body_faces = read_body(folder, paths, findings)
    garment = read_garment(folder, garment_path(folder, index.meta, findings), findings)
    boundary_file = boundary_path(folder, index.meta, findings)
    boundary = None if boundary_file is None else read_boundary(folder, boundary_file, garment, findings)
    images, masks, body_masks = read_views(index, findings, progress) if views else (None, None, None)

    rig, garment_vertices = index.rig, garment.vertices
    if index.up == "z":
        turn = torch.eye(4, dtype=torch.float64)
        turn[:3, :3] = _z_up_to_y_up()
        rig = CameraRig(turn @ rig.c2w, rig.width, rig.height, rig.fx, rig.fy, rig.cx, rig.cy)
        body = body @ turn[:3, :3].T
        garment_vertices = garment_vertices @ turn[:3, :3].T
    film = Capture(images, masks, rig, index.fps, None) if views else None
    return CaptureFolder(
        folder, film, body, body_faces, garment_vertices, garment.faces, boundary, index.up, body_masks, index.fps
    )
