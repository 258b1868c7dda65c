"""Pinhole cameras built from what a caller knows: a circle about a point, positions and targets, or a browser
client's camera. All return :class:`pienerf.data.Cameras` (OpenGL axes: x right, y up, looking down −z, metres),
whose :meth:`~pienerf.data.Cameras.pixel_rays` is the one place pixel rays are made.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pienerf.data import Cameras

__all__ = ["look_at_cameras", "orbit_cameras", "pinhole_camera", "quaternion_matrix", "viser_cameras"]


def orbit_cameras(
    centre, distance: float, azimuths_deg, elevation_deg: float, width: int, height: int, fov_deg: float = 40.0
) -> Cameras:
    """Pinhole cameras on a circle about ``centre [3]`` (m), y up, all looking at the centre.

    Args:
        centre: the point looked at (m).
        distance: distance from the centre (m).
        azimuths_deg: azimuth of each camera about +y, degrees (0 looks from +z).
        elevation_deg: elevation above the horizontal plane, degrees.
        width, height: image size (pixels).
        fov_deg: vertical field of view, degrees.
    """
    centre = torch.as_tensor(centre, dtype=torch.float64)
    positions = []
    for azimuth in azimuths_deg:
        a, e = math.radians(float(azimuth)), math.radians(float(elevation_deg))
        offset = torch.tensor([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)], dtype=torch.float64)
        positions.append(centre + distance * offset)
    return look_at_cameras(torch.stack(positions), centre.expand(len(positions), 3), width, height, fov_deg)


def look_at_cameras(positions, targets, width: int, height: int, fov_deg: float = 40.0) -> Cameras:
    """Pinhole cameras at ``positions [N, 3]`` looking at ``targets [N, 3]`` (m), y up, OpenGL axes.

    ``fov_deg`` is the vertical field of view in degrees; the principal point is the image centre.
    """
    positions = torch.as_tensor(positions, dtype=torch.float64).reshape(-1, 3)
    targets = torch.as_tensor(targets, dtype=torch.float64).reshape(-1, 3)
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise ValueError(f"image size must be positive integers, got {width} x {height}")
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must lie in (0, 180) degrees, got {fov_deg}")
    c2w = torch.zeros(len(positions), 4, 4, dtype=torch.float64)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    for i, (position, target) in enumerate(zip(positions, targets, strict=True)):
        forward = torch.nn.functional.normalize(target - position, dim=0)
        right = torch.linalg.cross(forward, up)
        if float(right.norm()) < 1e-8:  # looking straight up or down
            right = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        right = torch.nn.functional.normalize(right, dim=0)
        c2w[i, :3, 0], c2w[i, :3, 1], c2w[i, :3, 2] = right, torch.linalg.cross(right, forward), -forward
        c2w[i, :3, 3], c2w[i, 3, 3] = position, 1.0
    focal = 0.5 * height / math.tan(0.5 * math.radians(fov_deg))
    n = len(positions)
    f = torch.full((n,), focal, dtype=torch.float32)
    return Cameras(
        c2w.float(), f, f.clone(), torch.full((n,), 0.5 * width), torch.full((n,), 0.5 * height), width, height
    )


def quaternion_matrix(wxyz) -> np.ndarray:
    """The ``[3, 3]`` rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    q = _finite(wxyz, 4, "quaternion wxyz")
    norm = float(np.linalg.norm(q))
    if norm < 1e-12:
        raise ValueError(f"quaternion wxyz must not be zero, got {wxyz!r}")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def viser_cameras(position, wxyz, fov: float, aspect: float, height: int) -> Cameras:
    """One view (OpenGL axes) of a browser client's camera, ``height`` pixels high.

    Args:
        position: camera centre ``[3]``, metres.
        wxyz: camera-to-world rotation as a quaternion in OpenCV axes (x right, y down, looking along +z), as
            viser reports it.
        fov: vertical field of view, radians.
        aspect: image width over height.
        height: image height, pixels (the width follows from ``aspect``).
    """
    if not (height >= 1 and aspect > 0 and 0 < fov < math.pi):
        raise ValueError(f"need height >= 1 px, aspect > 0 and 0 < fov < pi rad, got {height}, {aspect}, {fov}")
    rotation = quaternion_matrix(wxyz) @ np.diag([1.0, -1.0, -1.0])  # OpenCV → OpenGL camera axes
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rotation, _finite(position, 3, "camera position")
    return pinhole_camera(c2w, fov, aspect, height)


def pinhole_camera(c2w, fov: float, aspect: float, height: int) -> Cameras:
    """One centred pinhole view of camera-to-world ``c2w [4, 4]`` (OpenGL axes: looking along −z, y up, m).

    Args:
        c2w: the camera's pose.
        fov: vertical field of view, radians.
        aspect: image width over height.
        height: image height, pixels (the width follows from ``aspect``).
    """
    width = max(1, int(round(height * aspect)))
    focal = torch.tensor([0.5 * height / math.tan(0.5 * fov)])
    return Cameras(
        torch.as_tensor(np.asarray(c2w), dtype=torch.float32)[None],
        focal,
        focal.clone(),
        torch.tensor([0.5 * width]),
        torch.tensor([0.5 * height]),
        width,
        height,
    )


def _finite(value, size: int, what: str) -> np.ndarray:
    """``size`` finite float64 numbers from ``value``, or a ValueError naming ``what``."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} is not {size} numbers: {value!r}") from None
    if array.shape != (size,) or not np.isfinite(array).all():
        raise ValueError(f"{what} must be {size} finite numbers, got {value!r}")
    return array
