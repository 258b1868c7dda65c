"""Pinhole cameras: :class:`Cameras` (the one place pixel rays are made and points projected) and the
constructors that build them from what a caller knows: a circle about a point, positions and targets, or a
browser client's camera. OpenGL axes: x right, y up, the camera looking down −z; metres.

Pixel ``(u, v)`` (column, row, from the top-left corner) has its centre at ``(u + ½, v + ½)``; its ray leaves
the camera centre along ``((u + ½ − cx) / fx, −(v + ½ − cy) / fy, −1)`` in camera axes. With this convention a
downscale by an integer ``k`` that averages ``k × k`` blocks divides ``fx, fy, cx, cy`` by exactly ``k``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

__all__ = [
    "Cameras",
    "check_downscale",
    "look_at_cameras",
    "orbit_cameras",
    "pinhole_camera",
    "quaternion_matrix",
    "view_index",
    "viser_cameras",
]


@dataclass(frozen=True)
class Cameras:
    """Pinhole cameras of a dataset's views.

    Attributes:
        c2w: ``[N, 4, 4]`` float32 camera-to-world transforms, metres (OpenGL axes: x right, y up, looking down −z).
        fx, fy: ``[N]`` float32 focal lengths, pixels (a shared value is repeated per view).
        cx, cy: ``[N]`` float32 principal point, pixels from the image's top-left corner.
        width, height: image size, pixels.
    """

    c2w: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: int
    height: int

    def __len__(self) -> int:
        return self.c2w.shape[0]

    @property
    def centers(self) -> torch.Tensor:
        """``[N, 3]`` camera centres in world coordinates, metres."""
        return self.c2w[:, :3, 3]

    def to(self, device) -> Cameras:
        """The same cameras with every tensor on ``device``."""
        return replace(self, **{k: getattr(self, k).to(device) for k in ("c2w", "fx", "fy", "cx", "cy")})

    def select(self, index) -> Cameras:
        """The cameras ``index`` picks (an int, a slice, a list or a tensor of view indices)."""
        index = view_index(index, len(self))
        return replace(self, **{k: getattr(self, k)[index] for k in ("c2w", "fx", "fy", "cx", "cy")})

    def scaled(self, downscale: int) -> Cameras:
        """Cameras of images downscaled by the integer factor ``downscale`` (``k × k`` pixel blocks averaged).

        Raises:
            ValueError: ``downscale`` is not a positive integer dividing both image sides.
        """
        check_downscale(downscale, self.width, self.height, "the cameras' images")
        k = float(downscale)
        return replace(
            self,
            fx=self.fx / k,
            fy=self.fy / k,
            cx=self.cx / k,
            cy=self.cy / k,
            width=self.width // downscale,
            height=self.height // downscale,
        )

    def pixel_rays(self, index, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space rays through continuous pixel coordinates of chosen views.

        Args:
            index: ``[P]`` view index per ray (tensor) or one int for all.
            u, v: ``[P]`` pixel coordinates, pixels from the top-left corner (the centre of pixel
                ``(col, row)`` is ``(col + ½, row + ½)``).

        Returns:
            ``origins [P, 3]`` (metres) and unit ``directions [P, 3]``, on the cameras' device.
        """
        u = torch.as_tensor(u, dtype=self.c2w.dtype, device=self.c2w.device)
        v = torch.as_tensor(v, dtype=self.c2w.dtype, device=self.c2w.device)
        view = torch.as_tensor(index, device=self.c2w.device).long().expand_as(u)
        local = torch.stack(
            [(u - self.cx[view]) / self.fx[view], -(v - self.cy[view]) / self.fy[view], -torch.ones_like(u)], dim=-1
        )
        rotation = self.c2w[view, :3, :3]
        directions = torch.nn.functional.normalize((rotation @ local[..., None])[..., 0], dim=-1)
        return self.c2w[view, :3, 3], directions

    def rays(self, index=None, downscale: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through every pixel centre of one view or of all views.

        Args:
            index: a view index, or ``None`` for all views (rays of view ``i`` follow those of view ``i − 1``).
            downscale: integer factor: rays through the centres of ``downscale × downscale`` pixel blocks.

        Returns:
            ``origins [M·H'·W', 3]`` (metres) and unit ``directions [M·H'·W', 3]``, row-major per view, where
            ``H' = height / downscale``, ``W' = width / downscale`` and ``M`` is 1 or the number of views.
        """
        cameras = self.scaled(downscale) if downscale != 1 else self
        views = torch.arange(len(cameras), device=self.c2w.device) if index is None else torch.tensor([int(index)])
        views = views.to(self.c2w.device)
        rows, cols = torch.meshgrid(
            torch.arange(cameras.height, dtype=self.c2w.dtype, device=self.c2w.device) + 0.5,
            torch.arange(cameras.width, dtype=self.c2w.dtype, device=self.c2w.device) + 0.5,
            indexing="ij",
        )
        pixels = rows.numel()
        view = views.repeat_interleave(pixels)
        u = cols.reshape(-1).repeat(views.numel())
        v = rows.reshape(-1).repeat(views.numel())
        return cameras.pixel_rays(view, u, v)

    def grid_rays(self, view: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through the centres of a ``width × height`` grid of blocks covering view ``view``'s image.

        The grid need not divide the image: block ``(col, row)`` is centred on pixel coordinates
        ``((col + ½) W / width, (row + ½) H / height)``, so a preview of any size sees the camera's whole view.

        Returns:
            ``origins [height·width, 3]`` (metres, expanded) and unit ``directions [height·width, 3]``, row-major,
            on the cameras' device.
        """
        if not (width >= 1 and height >= 1):
            raise ValueError(f"the ray grid needs a positive number of pixels, got {width} x {height}")
        rows, cols = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
        u = cols.reshape(-1) * (self.width / width)
        v = rows.reshape(-1) * (self.height / height)
        origins, directions = self.pixel_rays(view, u, v)
        return origins.expand_as(directions), directions

    def project(self, view: int, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel coordinates of world points seen by view ``view``: the inverse of :meth:`pixel_rays`.

        Args:
            view: the view index.
            points: ``[P, 3]`` world points, metres.

        Returns:
            ``u, v [P]`` pixel coordinates from the top-left corner and ``depth [P]`` along the optical axis
            (metres, positive in front of the camera); ``u, v`` are meaningful only where ``depth > 0``.
        """
        c2w = self.c2w[view].to(points)
        local = (points - c2w[:3, 3]) @ c2w[:3, :3]  # camera axes, looking down −z
        depth = -local[:, 2]
        z = depth.clamp_min(1e-6)
        u = self.fx[view].to(points) * local[:, 0] / z + self.cx[view].to(points)
        v = -self.fy[view].to(points) * local[:, 1] / z + self.cy[view].to(points)
        return u, v, depth

    def axial_depth(self, view: int, ray_depth: torch.Tensor) -> torch.Tensor:
        """Depth along the optical axis of a ``[h, w]`` image of distances along the rays of :meth:`grid_rays`.

        A ray's length times the cosine of its angle to the optical axis; what a z-buffer (e.g. a browser's
        compositing) expects. Non-finite distances stay non-finite.
        """
        height, width = ray_depth.shape
        _, directions = self.grid_rays(view, width, height)
        forward = -self.c2w[view, :3, 2]
        cosine = (directions @ forward).reshape(height, width).to(ray_depth)
        return ray_depth * cosine


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


def check_downscale(downscale: int, width: int, height: int, what: str) -> None:
    """Refuse a downscale factor that is not a positive integer dividing both sides of ``what``'s images."""
    if not (isinstance(downscale, int) and downscale >= 1):
        raise ValueError(f"downscale must be a positive integer, got {downscale!r}")
    if width % downscale or height % downscale:
        raise ValueError(
            f"downscale {downscale} does not divide {what} ({width}x{height} pixels); pick a factor of both sides"
        )


def view_index(index, count: int):
    """An index of ``count`` views (an int, a list or a tensor) as a slice or tensor that keeps the view axis."""
    if isinstance(index, int):
        if not -count <= index < count:
            raise IndexError(f"view {index} is out of range for {count} views")
        return slice(index % count, index % count + 1)
    if isinstance(index, (list, tuple)):
        return torch.tensor(index, dtype=torch.long)
    return index
