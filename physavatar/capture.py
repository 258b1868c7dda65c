"""A synthetic multi-view capture of the dressed mannequin: cameras, a ray-traced renderer and the capture files.

PhysAvatar's input is "multiview videos of T frames and C views" of a person in loose clothes (§3.1). Here the
person is the project's mannequin wearing a garment simulated with known parameters (§3.2, Eq. 5), so every
later stage (tracking §3.1, physics estimation §3.2, appearance §3.3) can be scored against the truth. This
module films that scene with a static ring of pinhole cameras.

Image formation, per pixel ``p`` whose first hit lies on face ``f`` (a Lambertian surface, the model the
appearance stage of §3.3 inverts):

    I(p) = clamp(ρ_f ⊙ (L_a · AO(p) + L_s · max(0, n̂ · l̂) · V(p)), 0, 1)

* ``ρ_f`` is the face's RGB albedo (a per-face "texture"), ``L_a`` the uniform sky (ambient) radiance and
  ``L_s`` the sun's, both RGB multipliers of the albedo (:class:`Lighting`).
* ``n̂`` is the face's geometric normal turned toward the camera (surfaces are two-sided: a garment is a
  sheet), ``l̂`` the unit direction toward the sun.
* ``V(p)`` is 1 when a shadow ray from the hit toward the sun escapes the scene, else 0 (hard shadows).
* ``AO(p)`` is the fraction of ``S`` cosine-weighted hemisphere rays around ``n̂`` that escape the scene: the
  cosine-weighted visibility of a uniform sky, so an unoccluded surface receives exactly ``L_a``. The ``S``
  directions are one fixed low-discrepancy set (a rank-1 lattice on the unit square with a random shift drawn
  from ``seed``, mapped to the hemisphere by Malley's method), the same in every pixel's tangent frame: the
  image is a deterministic function of the geometry, without per-pixel noise.

All rays (primary, shadow, occlusion) go through one Warp BVH (:class:`kernels.raycast.MeshBVH`) holding the
garment and the body together and refitted every frame, so the body shadows and hides the garment and the
garment the body. Secondary rays leave the surface ``bias`` metres along ``n̂``.

Cameras (:class:`CameraRig`) follow the NeRF/OpenGL convention of the project's NeRF datasets: camera-to-world
matrices whose camera looks along its −z axis with x right and y up; pixel ``(i, j)`` (column, row from the
top-left corner) has its centre at ``(i + ½, j + ½)`` and its ray leaves along
``((i + ½ − c_x) / f_x, −(j + ½ − c_y) / f_y, −1)`` in camera axes.

Files (:func:`write_capture`): a NeRF-synthetic style ``transforms.json`` (shared intrinsics ``camera_angle_x``,
``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``; ``fps``; ``lighting``; one frame per (time, camera) with
``file_path``, ``mask_path``, ``transform_matrix``, ``camera`` and ``time_index``), 8-bit PNG images and masks,
and ``truth.npz`` holding what evaluation needs and the pipeline must not see (meshes, albedo, parameters). Each file
goes through a staging step passed in (:mod:`physavatar.result_files`), so a program can have every one written whole
or not at all; ``transforms.json``, the index a reader opens first, comes last.

Cost: a pixel that sees the scene costs 2 + ``ao_samples`` rays (figures in ``docs/benchmarks.md``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.result_files import Staging, write_arrays, write_json, write_png

__all__ = [
    "Capture",
    "CameraRig",
    "Lighting",
    "ViewShading",
    "dressed_scene",
    "garment_albedo",
    "hemisphere_directions",
    "load_capture",
    "load_truth",
    "render_capture",
    "shade_mesh",
    "write_capture",
]

_TRANSFORMS = "transforms.json"
_TRUTH = "truth.npz"
_JSON_KEY = "__json__"  # the truth file's entry holding its non-array values as JSON
_RAYS_PER_LAUNCH = 1 << 20  # occlusion rays per BVH launch: bounds the memory of one batch
_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)


# ---------------------------------------------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CameraRig:
    """A static rig of pinhole cameras sharing one intrinsic matrix.

    Attributes:
        c2w: ``[C, 4, 4]`` float64 camera-to-world transforms (CPU), metres; camera axes x right, y up, looking
            along −z (NeRF/OpenGL).
        width, height: image size, pixels.
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels from the image's top-left corner (pixel centres at ``i + ½``).

    Raises:
        ValueError: ``c2w`` is not a non-empty finite ``[C, 4, 4]`` tensor, a size is not a positive integer or an
            intrinsic is not finite (focal lengths positive).
    """

    c2w: torch.Tensor
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

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
            value = float(getattr(self, name))
            if not math.isfinite(value) or (name in ("fx", "fy") and value <= 0.0):
                raise ValueError(f"{name} must be finite (focal lengths positive), in pixels, got {value}")
            object.__setattr__(self, name, value)

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

    def world_to_camera(self) -> torch.Tensor:
        """``[C, 4, 4]`` float64 world-to-camera transforms (the inverses of :attr:`c2w`)."""
        return torch.linalg.inv(self.c2w)

    def rays(self, camera: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through every pixel centre of one camera, row-major (pixel ``(i, j)`` is row ``j·W + i``).

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
        local = torch.stack([(cols - self.cx) / self.fx, -(rows - self.cy) / self.fy, -torch.ones_like(rows)], -1)
        directions = local.reshape(-1, 3) @ self.c2w[c, :3, :3].T
        directions = directions / directions.norm(dim=1, keepdim=True)
        origins = self.c2w[c, :3, 3].expand_as(directions)
        return origins.to(device, torch.float32).contiguous(), directions.to(device, torch.float32).contiguous()

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pinhole projection of world points into every camera (differentiable, in the dtype of ``points``).

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
        x = self.cx + self.fx * local[..., 0] / depth
        y = self.cy - self.fy * local[..., 1] / depth
        return torch.stack([x, y], -1), depth

    def _index(self, camera: int) -> int:
        if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)) or not 0 <= camera < len(self):
            raise IndexError(f"camera must be an index in 0..{len(self) - 1}, got {camera!r}")
        return int(camera)


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
# Scene and shading
# ---------------------------------------------------------------------------------------------------------------


def garment_albedo(
    rest_vertices: torch.Tensor,
    faces: torch.Tensor,
    pattern: str = "stripes",
    colors=((0.80, 0.22, 0.20), (0.92, 0.86, 0.70)),
    bands: int = 8,
    axis: int | None = None,
) -> torch.Tensor:
    """A two-colour per-face albedo laid out on the rest geometry: the garment's printed "texture".

    The pattern is a function of each face's centroid in the rest shape, so it moves with the cloth. Stripes
    alternate along one axis; checks alternate along the two axes of largest extent.

    Args:
        rest_vertices: ``[V, 3]`` rest positions, m.
        faces: ``[F, 3]`` vertex indices.
        pattern: ``"stripes"`` or ``"checks"``.
        colors: two RGB albedos in [0, 1].
        bands: stripes (or checks per row) across the rest shape's largest extent.
        axis: axis the stripes alternate along (0, 1, 2); ``None``: the rest shape's longest axis.

    Returns:
        ``[F, 3]`` float32 albedo in [0, 1] (CPU).
    """
    if pattern not in ("stripes", "checks"):
        raise ValueError(f"pattern must be 'stripes' or 'checks', got {pattern!r}")
    if int(bands) < 1:
        raise ValueError(f"bands must be at least 1, got {bands}")
    palette = torch.as_tensor(colors, dtype=torch.float32)
    if palette.shape != (2, 3) or bool((palette < 0).any() | (palette > 1).any()):
        raise ValueError(f"colors must be two RGB albedos in [0, 1], got {colors!r}")
    rest = rest_vertices.detach().cpu().double()
    centroid = rest[faces.detach().cpu().long()].mean(1)
    lo = rest.amin(0)
    extent = rest.amax(0) - lo
    order = torch.argsort(extent, descending=True).tolist()
    if axis is not None:
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1, 2 or None, got {axis!r}")
        order = [axis] + [a for a in order if a != axis]
    period = max(float(extent.max()), 1e-12) / int(bands)
    cell = torch.floor((centroid - lo) / period * (1.0 - 1e-9)).long()
    parity = cell[:, order[0]] if pattern == "stripes" else cell[:, order[0]] + cell[:, order[1]]
    return palette[parity % 2].contiguous()


def dressed_scene(
    garment_frames: torch.Tensor,
    garment_faces: torch.Tensor,
    body_frames: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Garment and body as one mesh sequence (garment faces first), the scene one BVH holds.

    Args:
        garment_frames: ``[T, V, 3]`` (or ``[V, 3]`` for one frame) garment vertices, m.
        garment_faces: ``[F, 3]``.
        body_frames: ``[T, B, 3]`` (or ``[B, 3]``) body vertices, m, or ``None`` for the garment alone.
        body_faces: ``[Fb, 3]``, given with ``body_frames``.

    Returns:
        ``vertices [T, V + B, 3]`` float32, ``faces [F + Fb, 3]`` int64 and ``F``, the garment's face count
        (faces ``0..F−1`` are the garment's).
    """
    garment_frames = _frames(garment_frames, "garment_frames")
    garment_faces = _faces(garment_faces, garment_frames.shape[1], "garment_faces")
    if (body_frames is None) != (body_faces is None):
        raise ValueError("pass body_frames and body_faces together (or neither, for the garment alone)")
    if body_frames is None:
        return garment_frames.float(), garment_faces, garment_faces.shape[0]
    body_frames = _frames(body_frames, "body_frames")
    body_faces = _faces(body_faces, body_frames.shape[1], "body_faces")
    if body_frames.shape[0] != garment_frames.shape[0]:
        raise ValueError(
            f"garment_frames holds {garment_frames.shape[0]} frames but body_frames {body_frames.shape[0]}; "
            "pass one body pose per garment frame"
        )
    vertices = torch.cat([garment_frames.float(), body_frames.float()], 1)
    faces = torch.cat([garment_faces, body_faces + garment_frames.shape[1]])
    return vertices, faces, garment_faces.shape[0]


def hemisphere_directions(count: int, seed: int = 0) -> torch.Tensor:
    """``[count, 3]`` float64 cosine-weighted directions about +z: the fixed occlusion rays of every pixel.

    Point ``k`` of the rank-1 lattice ``((k + ½) / S, k·φ mod 1)`` (φ the golden ratio's fraction) is shifted by
    one random offset drawn from ``seed`` (modulo 1, which keeps the lattice's stratification) and mapped to the
    unit disk and up to the hemisphere (Malley's method), so the directions' density is ``cos θ / π``.
    """
    if int(count) < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    shift = torch.rand(2, generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float64)
    k = torch.arange(int(count), dtype=torch.float64)
    u1 = torch.remainder((k + 0.5) / count + shift[0], 1.0)
    u2 = torch.remainder(k * _GOLDEN + shift[1], 1.0)
    r, phi = torch.sqrt(u1), 2.0 * math.pi * u2
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1.0 - u1).clamp_min(0.0))], 1)


class ViewShading(NamedTuple):
    """One rendered view and its light transport (every map row-major, ``[H, W]`` pixels).

    Attributes:
        rgb: ``[H, W, 3]`` float32 colour in [0, 1], the background where the ray misses.
        face: ``[H, W]`` int64 face of the first hit, −1 on a miss.
        ao: ``[H, W]`` float32 ambient occlusion ``AO`` in [0, 1] (fraction of sky rays escaping), 0 on a miss.
        sun: ``[H, W]`` float32 sun term ``max(0, n̂ · l̂) · V`` in [0, 1], 0 on a miss.
        depth: ``[H, W]`` float32 distance from the camera centre to the hit along the ray, m; inf on a miss.
    """

    rgb: torch.Tensor
    face: torch.Tensor
    ao: torch.Tensor
    sun: torch.Tensor
    depth: torch.Tensor


def shade_mesh(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    albedo: torch.Tensor,
    rig: CameraRig,
    camera: int,
    lighting: Lighting,
    ao_samples: int = 16,
    seed: int = 0,
    *,
    background=(1.0, 1.0, 1.0),
    bias: float = 1e-4,
    bvh: MeshBVH | None = None,
    device: str | None = None,
) -> ViewShading:
    """Render one camera's view of a mesh: first hits, sun with hard shadows, sky with ambient occlusion.

    ``rgb = clamp(albedo_f ⊙ (L_a · AO + L_s · max(0, n̂ · l̂) · V), 0, 1)`` (module docstring). All secondary rays
    go through :meth:`kernels.raycast.MeshBVH.cast`.

    Args:
        vertices: ``[V, 3]`` positions, m.
        faces: ``[F, 3]`` vertex indices.
        albedo: ``[F, 3]`` per-face RGB albedo in [0, 1].
        rig: the cameras.
        camera: index of the camera to render.
        lighting: sky and sun.
        ao_samples: occlusion rays per pixel ``S``; 0 skips them (``AO = 1``).
        seed: picks the shift of the occlusion directions (:func:`hemisphere_directions`).
        background: RGB of pixels that see nothing.
        bias: offset of secondary rays' origins along the normal, m (about 1e-4 of the scene's size).
        bvh: a :class:`MeshBVH` already holding ``vertices`` and ``faces`` (skips the build; refit it per frame).
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the kernels' device or picks the default.

    Returns:
        :class:`ViewShading` with maps on the kernels' device.
    """
    backend.init(device)
    dev = backend.torch_device()
    if bvh is None:
        vertices = _check_mesh_vertices(vertices)
        bvh = MeshBVH(vertices.to(dev, torch.float32), _faces(faces, vertices.shape[0], "faces").to(dev))
    elif tuple(bvh.vertices.shape) != tuple(vertices.shape) or bvh.faces.shape[0] != faces.shape[0]:
        raise ValueError(
            f"bvh holds {bvh.vertices.shape[0]} vertices and {bvh.faces.shape[0]} faces but the mesh has "
            f"{vertices.shape[0]} and {faces.shape[0]}; build the bvh from this mesh"
        )
    face_count = bvh.faces.shape[0]
    if not isinstance(albedo, torch.Tensor) or tuple(albedo.shape) != (face_count, 3):
        raise ValueError(f"albedo must be [{face_count}, 3] (one RGB per face), got {tuple(albedo.shape)}")
    if int(ao_samples) < 0 or not bias >= 0.0:
        raise ValueError(f"ao_samples must be >= 0 and bias (m) >= 0, got {ao_samples} and {bias}")

    origins, directions = rig.rays(camera, dev)
    hits = bvh.cast(origins, directions)
    pixel = torch.nonzero(hits.face >= 0).flatten()
    face = hits.face.long()[pixel]
    direction = directions[pixel]
    point = origins[pixel] + hits.t[pixel, None] * direction
    normal = _face_normals(bvh.vertices, bvh.faces)[face]
    normal = torch.where(((normal * direction).sum(1) > 0.0)[:, None], -normal, normal)  # toward the camera
    start = point + bias * normal

    toward_sun = torch.tensor(lighting.sun_direction, dtype=torch.float32, device=dev)
    sun = (normal @ toward_sun).clamp_min(0.0)
    lit = torch.nonzero(sun > 0.0).flatten()
    if len(lit):
        blocked = bvh.cast(start[lit], toward_sun.expand(len(lit), 3)).face >= 0
        sun[lit[blocked]] = 0.0
    ao = _ambient_occlusion(bvh, start, normal, int(ao_samples), seed)

    color = albedo.to(dev, torch.float32)[face] * (
        torch.tensor(lighting.ambient, device=dev) * ao[:, None] + torch.tensor(lighting.sun, device=dev) * sun[:, None]
    )
    count = origins.shape[0]
    rgb = torch.tensor(_rgb(background, "background"), dtype=torch.float32, device=dev).repeat(count, 1)
    rgb[pixel] = color.clamp(0.0, 1.0)
    face_map = torch.full((count,), -1, dtype=torch.int64, device=dev)
    face_map[pixel] = face
    ao_map = torch.zeros(count, device=dev)
    ao_map[pixel] = ao
    sun_map = torch.zeros(count, device=dev)
    sun_map[pixel] = sun
    shape = (rig.height, rig.width)
    return ViewShading(
        rgb.view(*shape, 3), face_map.view(shape), ao_map.view(shape), sun_map.view(shape), hits.t.view(shape)
    )


def _ambient_occlusion(bvh: MeshBVH, start: torch.Tensor, normal: torch.Tensor, samples: int, seed: int):
    """``[P]`` fraction of ``samples`` cosine-weighted rays from ``start [P, 3]`` about ``normal`` that escape."""
    if samples == 0 or not len(start):
        return torch.ones(len(start), dtype=torch.float32, device=start.device)
    local = hemisphere_directions(samples, seed).to(start.device, torch.float32)
    tangent, bitangent = _tangent_frame(normal)
    escaped = torch.empty(len(start), dtype=torch.float32, device=start.device)
    rows = max(1, _RAYS_PER_LAUNCH // samples)
    for lo in range(0, len(start), rows):
        hi = min(lo + rows, len(start))
        world = (
            local[None, :, 0:1] * tangent[lo:hi, None]
            + local[None, :, 1:2] * bitangent[lo:hi, None]
            + local[None, :, 2:3] * normal[lo:hi, None]
        )
        origin = start[lo:hi, None].expand_as(world)
        miss = bvh.cast(origin.reshape(-1, 3), world.reshape(-1, 3)).face < 0
        escaped[lo:hi] = miss.view(hi - lo, samples).float().mean(1)
    return escaped


def _tangent_frame(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents completing unit ``normal [P, 3]`` to a right-handed frame (Duff et al. 2017)."""
    x, y, z = normal.unbind(1)
    sign = torch.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    tangent = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], 1)
    bitangent = torch.stack([b, sign + y * y * a, -y], 1)
    return tangent, bitangent


def _face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``[F, 3]`` unit geometric normals ``(v1 − v0) × (v2 − v0)`` (zero for degenerate faces)."""
    v = vertices[faces.long()]
    return torch.nn.functional.normalize(torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], dim=1), dim=1)


def render_capture(
    garment_frames: torch.Tensor,
    garment_faces: torch.Tensor,
    body_frames: torch.Tensor | None,
    body_faces: torch.Tensor | None,
    garment_albedo: torch.Tensor,
    body_albedo,
    rig: CameraRig,
    lighting: Lighting,
    fps: float,
    background=(1.0, 1.0, 1.0),
    progress: bool | Callable[[int, int], None] | None = None,
    *,
    ao_samples: int = 16,
    seed: int = 0,
    quantize: bool = True,
    device: str | None = None,
) -> Capture:
    """Film the dressed body with every camera of ``rig`` at every frame (:func:`shade_mesh` per view).

    Args:
        garment_frames: ``[T, V, 3]`` garment vertices per frame, m (e.g. ``SimulationResult.garment_frames``).
        garment_faces: ``[F, 3]``.
        body_frames: ``[T, B, 3]`` body vertices per frame, m, or ``None`` to film the garment alone.
        body_faces: ``[Fb, 3]`` (``None`` with ``body_frames``).
        garment_albedo: ``[F, 3]`` per-face RGB albedo in [0, 1] (:func:`garment_albedo`).
        body_albedo: ``[Fb, 3]`` per-face albedo or one RGB ``[3]`` for the whole body.
        rig: the cameras.
        lighting: sky and sun.
        fps: frames per second of the sequence.
        background: RGB of pixels that see nothing.
        progress: ``True`` writes one line per frame to stderr; a callable receives ``(frame, frame_count)``
            after each frame; ``None``/``False`` is silent.
        ao_samples, seed: occlusion rays per pixel and the shift of their directions (:func:`shade_mesh`).
        quantize: round images to 8 bits as a camera does (then :func:`write_capture` stores them exactly).
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the kernels' device or picks the default.

    Returns:
        :class:`Capture` on the CPU; masks mark pixels whose first hit is the garment.
    """
    backend.init(device)
    dev = backend.torch_device()
    vertices, faces, garment_face_count = dressed_scene(garment_frames, garment_faces, body_frames, body_faces)
    albedo = _scene_albedo(garment_albedo, body_albedo, garment_face_count, faces.shape[0])
    albedo = albedo.to(dev)
    frames = vertices.shape[0]
    faces = faces.to(dev)
    bvh = MeshBVH(vertices[0].to(dev), faces)
    images = torch.empty(frames, len(rig), rig.height, rig.width, 3, dtype=torch.float32)
    masks = torch.empty(frames, len(rig), rig.height, rig.width, dtype=torch.bool)
    for t in range(frames):
        if t:
            bvh.refit(vertices[t].to(dev))
        for c in range(len(rig)):
            view = shade_mesh(
                bvh.vertices, faces, albedo, rig, c, lighting, ao_samples, seed, background=background, bvh=bvh
            )
            images[t, c] = view.rgb.cpu()
            masks[t, c] = ((view.face >= 0) & (view.face < garment_face_count)).cpu()
        if callable(progress):
            progress(t + 1, frames)
        elif progress:
            covered = float(masks[t].float().mean())
            print(f"frame {t + 1}/{frames}: {len(rig)} views, garment covers {covered:.1%} of pixels", file=sys.stderr)
    if quantize:
        images = torch.round(images * 255.0) / 255.0
    return Capture(images, masks, rig, float(fps), lighting, _rgb(background, "background"))


def _scene_albedo(garment, body, garment_face_count: int, face_count: int) -> torch.Tensor:
    garment = torch.as_tensor(garment, dtype=torch.float32).cpu()
    if tuple(garment.shape) != (garment_face_count, 3):
        raise ValueError(
            f"garment_albedo must be [{garment_face_count}, 3] (one RGB per garment face), got {tuple(garment.shape)}"
        )
    body_count = face_count - garment_face_count
    body = torch.as_tensor(body if body is not None else (0.7, 0.7, 0.7), dtype=torch.float32).cpu()
    if body.shape == (3,):
        body = body.expand(body_count, 3)
    if tuple(body.shape) != (body_count, 3):
        raise ValueError(f"body_albedo must be one RGB [3] or [{body_count}, 3] per body face, got {tuple(body.shape)}")
    albedo = torch.cat([garment, body])
    if not bool(torch.isfinite(albedo).all() & (albedo >= 0).all()):
        raise ValueError("albedo values must be finite and non-negative (a physical albedo lies in [0, 1])")
    return albedo.contiguous()


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
                }
            )
    meta = {
        "camera_angle_x": 2.0 * math.atan(0.5 * rig.width / rig.fx),
        "camera_angle_y": 2.0 * math.atan(0.5 * rig.height / rig.fy),
        "fl_x": rig.fx,
        "fl_y": rig.fy,
        "cx": rig.cx,
        "cy": rig.cy,
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
    ``w``, ``h``; a frame path without extension means ``.png``; ``fps`` defaults to 25.

    Args:
        folder: the capture's folder, or its ``transforms.json``.

    Raises:
        FileNotFoundError: ``transforms.json`` or an image or mask it lists is missing.
        ValueError: the json is malformed; the cameras are not numbered ``0..C−1``; a camera has fewer frames
            than another; a time index lacks some camera (or holds one twice); a camera moves between frames;
            an image or mask is corrupt or not ``w × h``.
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
    fx, fy = _focal(meta, "x", int(width), path), _focal(meta, "y", int(height), path)
    rig = CameraRig(
        c2w,
        int(width),
        int(height),
        fx,
        fy if fy is not None else fx,
        float(meta.get("cx", 0.5 * int(width))),
        float(meta.get("cy", 0.5 * int(height))),
    )

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


def _focal(meta: dict, axis: str, size: int, json_path: Path) -> float | None:
    if meta.get(f"fl_{axis}") is not None:
        return float(meta[f"fl_{axis}"])
    if meta.get(f"camera_angle_{axis}") is not None:
        return 0.5 * size / math.tan(0.5 * float(meta[f"camera_angle_{axis}"]))
    if axis == "y":
        return None
    raise ValueError(f"{json_path.name} gives no intrinsics: add 'fl_x' (pixels) or 'camera_angle_x' (radians)")


# ---------------------------------------------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------------------------------------------


def _frames(frames: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(frames, torch.Tensor) or not frames.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {getattr(frames, 'dtype', type(frames))}")
    if frames.dim() == 2:
        frames = frames[None]
    if frames.dim() != 3 or frames.shape[2] != 3 or frames.shape[0] == 0 or frames.shape[1] == 0:
        raise ValueError(f"{name} must be [T, N, 3] vertex positions (m) with T, N >= 1, got {tuple(frames.shape)}")
    if not bool(torch.isfinite(frames).all()):
        raise ValueError(f"{name} holds NaN or inf positions")
    return frames.detach().cpu()


def _faces(faces: torch.Tensor, vertex_count: int, name: str) -> torch.Tensor:
    faces = torch.as_tensor(faces)
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point() or faces.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty integer [F, 3] tensor, got {faces.dtype} {tuple(faces.shape)}")
    faces = faces.long()
    if int(faces.min()) < 0 or int(faces.max()) >= vertex_count:
        raise ValueError(f"{name} index vertices {int(faces.min())}..{int(faces.max())} but there are {vertex_count}")
    return faces


def _check_mesh_vertices(vertices: torch.Tensor) -> torch.Tensor:
    if not isinstance(vertices, torch.Tensor) or vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be a [V, 3] tensor, got {tuple(getattr(vertices, 'shape', ()))}")
    return vertices


def _rgb(value, name: str) -> tuple[float, float, float]:
    rgb = tuple(float(c) for c in np.asarray(value, dtype=np.float64).reshape(-1))
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"{name} must be an RGB triple in [0, 1], got {value!r}")
    return rgb
