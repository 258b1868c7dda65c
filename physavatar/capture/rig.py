"""The capture's cameras and light: a static ring of pinhole cameras and a sky-and-sun light (PhysAvatar §3.1).

Cameras (:class:`CameraRig`) follow the NeRF/OpenGL convention of the project's NeRF datasets: camera-to-world
matrices whose camera looks along its −z axis with x right and y up; pixel ``(i, j)`` (column, row from the
top-left corner) has its centre at ``(i + ½, j + ½)`` and its ray leaves along
``((i + ½ − c_x) / f_x, −(j + ½ − c_y) / f_y, −1)`` in camera axes, with that camera's own intrinsics (each camera of
a studio rig is calibrated on its own; all share one image size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from kernels import backend

__all__ = [
    "CameraRig",
    "Lighting",
]

# ---------------------------------------------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CameraRig:
    """A static rig of pinhole cameras, each with its own intrinsics, all with one image size.

    Each of ``fx``, ``fy``, ``cx``, ``cy`` is given as one number shared by every camera or as ``C`` numbers (a
    sequence or tensor, one per camera); either way it is stored as a ``[C]`` tensor.

    Attributes:
        c2w: ``[C, 4, 4]`` float64 camera-to-world transforms (CPU), metres; camera axes x right, y up, looking
            along −z (NeRF/OpenGL).
        width, height: image size of every camera, pixels.
        fx, fy: ``[C]`` float64 focal lengths (CPU), pixels.
        cx, cy: ``[C]`` float64 principal points (CPU), pixels from the image's top-left corner (pixel centres at
            ``i + ½``).

    Raises:
        ValueError: ``c2w`` is not a non-empty finite ``[C, 4, 4]`` tensor, a size is not a positive integer, or an
            intrinsic is neither one number nor ``C`` numbers, or is not finite (focal lengths positive).
    """

    c2w: torch.Tensor
    width: int
    height: int
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor

    def __post_init__(self):
        c2w = self.c2w
        if not isinstance(c2w, torch.Tensor) or c2w.dim() != 3 or tuple(c2w.shape[1:]) != (4, 4) or not len(c2w):
            raise ValueError(f"c2w must be a [C, 4, 4] tensor with C >= 1, got {tuple(getattr(c2w, 'shape', ()))}")
        c2w = c2w.detach().to("cpu", torch.float64).contiguous()
        if not bool(torch.isfinite(c2w).all()):
            raise ValueError("c2w holds NaN or inf entries; every camera needs a finite pose")
        object.__setattr__(self, "c2w", c2w)
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive number of pixels, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, _per_camera(name, getattr(self, name), len(c2w)))

    @classmethod
    def look_at(
        cls,
        eyes,
        target,
        width: int,
        height: int,
        fov_deg: float = 40.0,
        up=(0.0, 1.0, 0.0),
    ) -> CameraRig:
        """Cameras at ``eyes`` looking at ``target``, square pixels, principal point at the image centre.

        Args:
            eyes: ``[C, 3]`` camera centres, m.
            target: ``[3]`` point every camera looks at, or ``[C, 3]`` one per camera, m.
            width, height: image size, pixels.
            fov_deg: vertical field of view, degrees (``f_y = ½ H / tan(½ fov)``, ``f_x = f_y``).
            up: ``[3]`` world direction that appears upward in the images.

        Raises:
            ValueError: a camera sits on its target, looks along ``up``, or the field of view is not in (0, 180).
        """
        eyes = torch.as_tensor(eyes, dtype=torch.float64).reshape(-1, 3)
        target = torch.as_tensor(target, dtype=torch.float64).reshape(-1, 3).expand_as(eyes)
        world_up = torch.as_tensor(up, dtype=torch.float64).reshape(3)
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"fov_deg must lie in (0, 180) degrees, got {fov_deg}")
        forward = target - eyes
        if bool((forward.norm(dim=1) < 1e-12).any()):
            raise ValueError("a camera sits on its target; move the eye away from the point it looks at")
        forward = forward / forward.norm(dim=1, keepdim=True)
        right = torch.linalg.cross(forward, world_up.expand_as(forward), dim=1)
        if bool((right.norm(dim=1) < 1e-9).any()):
            raise ValueError(f"a camera looks along the up direction {tuple(up)}; tilt it or pass another `up`")
        right = right / right.norm(dim=1, keepdim=True)
        cam_up = torch.linalg.cross(right, forward, dim=1)
        c2w = torch.zeros(len(eyes), 4, 4, dtype=torch.float64)
        c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, -forward, eyes
        c2w[:, 3, 3] = 1.0
        focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
        return cls(c2w, width, height, focal, focal, 0.5 * width, 0.5 * height)

    @classmethod
    def ring(
        cls,
        count: int,
        radius: float,
        height: float,
        target,
        width: int,
        height_px: int,
        fov_deg: float = 40.0,
        phase_deg: float = 0.0,
    ) -> CameraRig:
        """``count`` cameras evenly spaced on a horizontal circle about ``target``, all looking at it.

        Camera ``k`` sits at ``target + (r sin θ_k, height, r cos θ_k)`` with ``θ_k = phase + 360° k / count``:
        camera 0 faces a body that faces +z, the next ones follow counter-clockwise seen from above.

        Args:
            count: number of cameras (≥ 1).
            radius: circle radius ``r``, m (> 0).
            height: height of the circle above ``target``, m (negative: below it).
            target: ``[3]`` point the cameras look at, m.
            width, height_px: image size, pixels.
            fov_deg: vertical field of view, degrees.
            phase_deg: azimuth of camera 0, degrees.
        """
        if int(count) < 1 or not radius > 0.0:
            raise ValueError(f"a ring needs count >= 1 cameras and a positive radius (m), got {count} and {radius}")
        theta = torch.deg2rad(phase_deg + 360.0 * torch.arange(int(count), dtype=torch.float64) / int(count))
        centre = torch.as_tensor(target, dtype=torch.float64).reshape(3)
        offset = torch.stack(
            [radius * torch.sin(theta), torch.full_like(theta, float(height)), radius * torch.cos(theta)], 1
        )
        return cls.look_at(centre + offset, centre, width, height_px, fov_deg)

    def __len__(self) -> int:
        return self.c2w.shape[0]

    @property
    def centers(self) -> torch.Tensor:
        """``[C, 3]`` float64 camera centres, m."""
        return self.c2w[:, :3, 3]

    @property
    def intrinsics(self) -> torch.Tensor:
        """``[C, 4]`` float64 rows ``(f_x, f_y, c_x, c_y)`` (CPU), pixels, one per camera."""
        return torch.stack([self.fx, self.fy, self.cx, self.cy], 1)

    @property
    def shared_intrinsics(self) -> bool:
        """Whether every camera has the same ``(f_x, f_y, c_x, c_y)``."""
        intrinsics = self.intrinsics
        return bool((intrinsics == intrinsics[0]).all())

    def world_to_camera(self) -> torch.Tensor:
        """``[C, 4, 4]`` float64 world-to-camera transforms (the inverses of :attr:`c2w`)."""
        return torch.linalg.inv(self.c2w)

    def rays(self, camera: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through every pixel centre of one camera, with its intrinsics, row-major (pixel ``(i, j)`` is row
        ``j·W + i``).

        Args:
            camera: camera index.
            device: torch device of the result; ``None``: the kernels' device when initialised, else the CPU.

        Returns:
            ``origins [H·W, 3]`` (m) and unit ``directions [H·W, 3]``, float32.
        """
        c = self._index(camera)
        if device is None:
            device = backend.torch_device() if backend.current_device() else "cpu"
        rows, cols = torch.meshgrid(
            torch.arange(self.height, dtype=torch.float64) + 0.5,
            torch.arange(self.width, dtype=torch.float64) + 0.5,
            indexing="ij",
        )
        fx, fy, cx, cy = self.intrinsics[c].tolist()
        local = torch.stack([(cols - cx) / fx, -(rows - cy) / fy, -torch.ones_like(rows)], -1)
        directions = local.reshape(-1, 3) @ self.c2w[c, :3, :3].T
        directions = directions / directions.norm(dim=1, keepdim=True)
        origins = self.c2w[c, :3, 3].expand_as(directions)
        return origins.to(device, torch.float32).contiguous(), directions.to(device, torch.float32).contiguous()

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pinhole projection of world points into every camera, each with its own intrinsics (differentiable, in
        the dtype of ``points``).

        Args:
            points: ``[N, 3]`` world points, m, on any device.

        Returns:
            ``pixels [C, N, 2]``: ``(x, y)`` image coordinates, pixels, x right and y down from the top-left corner
            (the centre of pixel ``(i, j)`` is ``(i + ½, j + ½)``), and ``depth [C, N]``: distance in front of the
            camera along its view axis, m (> 0 in front; points on the camera plane project to ±inf).
        """
        if not isinstance(points, torch.Tensor) or points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be an [N, 3] tensor, got {tuple(getattr(points, 'shape', ()))}")
        dtype = points.dtype if points.is_floating_point() else torch.float64
        w2c = self.world_to_camera().to(points.device, dtype)
        local = torch.einsum("cij,nj->cni", w2c[:, :3, :3], points.to(dtype)) + w2c[:, None, :3, 3]
        depth = -local[..., 2]
        fx, fy, cx, cy = self.intrinsics.to(points.device, dtype)[:, :, None].unbind(1)  # [C, 1] each
        x = cx + fx * local[..., 0] / depth
        y = cy - fy * local[..., 1] / depth
        return torch.stack([x, y], -1), depth

    def _index(self, camera: int) -> int:
        if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)) or not 0 <= camera < len(self):
            raise IndexError(f"camera must be an index in 0..{len(self) - 1}, got {camera!r}")
        return int(camera)


def _per_camera(name: str, value, count: int) -> torch.Tensor:
    """``[count]`` float64 CPU copy of intrinsic ``name`` (px), given as one number or one per camera; validated."""
    try:
        values = torch.as_tensor(value, dtype=torch.float64).detach().to("cpu")
    except (TypeError, ValueError, RuntimeError) as error:
        raise ValueError(
            f"{name} must be numbers in pixels ({error}); pass a float or a length-{count} sequence (one per camera)"
        ) from error
    if values.dim() == 0:
        values = values.expand(count)
    if tuple(values.shape) != (count,):
        raise ValueError(
            f"{name} must be one number for every camera or {count} numbers (one per camera), in pixels, "
            f"got shape {tuple(values.shape)}; pass a float or a length-{count} sequence"
        )
    if not bool(torch.isfinite(values).all()) or (name in ("fx", "fy") and not bool((values > 0.0).all())):
        raise ValueError(
            f"{name} must be finite (focal lengths positive), in pixels, got {values.tolist()}; fix the calibration"
        )
    return values.clone()


# ---------------------------------------------------------------------------------------------------------------
# Light, capture
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lighting:
    """Studio light: a uniform sky plus one directional sun (the image formation of the module docstring).

    Attributes:
        ambient: ``L_a``, RGB radiance multiplier of the albedo from the uniform sky (occluded by the geometry:
            ambient occlusion), ≥ 0.
        sun: ``L_s``, RGB multiplier from the sun on a surface facing it, ≥ 0.
        sun_direction: unit vector toward the sun (normalised on construction).
    """

    ambient: tuple[float, float, float] = (0.5, 0.5, 0.5)
    sun: tuple[float, float, float] = (0.5, 0.5, 0.5)
    sun_direction: tuple[float, float, float] = (0.35, 1.0, 0.55)

    def __post_init__(self):
        for name in ("ambient", "sun"):
            value = tuple(float(c) for c in np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
            if len(value) != 3 or not all(math.isfinite(c) and c >= 0.0 for c in value):
                raise ValueError(f"{name} must be 3 finite non-negative RGB multipliers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        direction = np.asarray(self.sun_direction, dtype=np.float64).reshape(-1)
        norm = float(np.linalg.norm(direction)) if direction.shape == (3,) else 0.0
        if not (math.isfinite(norm) and norm > 0.0):
            raise ValueError(f"sun_direction must be 3 finite numbers, not all zero, got {self.sun_direction!r}")
        if abs(norm - 1.0) > 1e-12:  # normalising a unit vector again may move its last bit (equality after I/O)
            direction = direction / norm
        object.__setattr__(self, "sun_direction", tuple(float(c) for c in direction))

    def to_dict(self) -> dict:
        """``{"ambient": [3], "sun": [3], "sun_direction": [3]}`` (the ``lighting`` entry of ``transforms.json``)."""
        return {"ambient": list(self.ambient), "sun": list(self.sun), "sun_direction": list(self.sun_direction)}

    @classmethod
    def from_dict(cls, values: dict) -> Lighting:
        """The inverse of :meth:`to_dict`."""
        try:
            return cls(values["ambient"], values["sun"], values["sun_direction"])
        except (KeyError, TypeError) as error:
            raise ValueError(f"lighting needs 'ambient', 'sun' and 'sun_direction' lists, got {values!r}") from error
