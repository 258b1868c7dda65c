"""The project's embedded scenes: procedural coloured meshes of PIE-NeRF's experiments, rendered into NeRF datasets.

PIE-NeRF (§5) trains its NeRFs on ~100 rendered views per scene and simulates a swaying plant (Fig. 1, 5), a
chocolate jelly (Fig. 6), a sculpture cut and falling on the floor (Fig. 7), an elastic rod attached to a teapot
(Fig. 8) and a cloth hitting a sphere (Fig. 9). The scenes here are stand-ins built from simple solids, in metres,
y up, resting on the ground ``y = 0``, about 1 m across:

* ``"plant"``: a pot with a soil mound, a stem and six thin ellipsoidal leaves (the leaves sway).
* ``"teapot"``: a lathed body and lid, a knob, a tilted spout, a toroidal handle and a thin striped rod sticking out.
* ``"jelly"``: a rounded chocolate block.
* ``"cloth"``: a hanging 1 m × 1 m sheet, 1 cm thick, for later code to pin at its top edge.
* ``"sculpture"``: a figure (legs, twisted torso, arms, a narrow neck and a head) on a plinth; a cut at the neck or
  waist separates it.

Each scene is a union of parts, every part one watertight solid that exists twice, with the same geometry: as a
triangle mesh (its vertices lie on the solid's surface) with per-vertex albedo, and as an analytic signed distance
(boxes, capsules and spheres of :mod:`pienerf.sim.density`; revolved profiles, tori, rounded boxes and ellipsoids
here). Parts overlap instead of being joined by booleans. The renderer (:func:`render_scene`) casts rays against
all parts' triangles: the first hit is the visible surface, wherever parts overlap. The simulator's density
(:func:`scene_density`) is the union of the analytic solids, ``d = min_i d_i``: exact, free of tessellation error,
and cheap, where a grid-sampled distance of each mesh (``MeshDensity``) would cost a grid of distance queries per
part and blur the 1 cm thin parts. A mesh-only union would also be wrong: distances to the buried faces of
overlapping parts would put density walls inside the solid.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from kernels import backend
from kernels.raycast import MeshBVH, shade
from kernels.spatial_hash import SpatialHash
from pienerf.nerf.cameras import Cameras, look_at_cameras
from pienerf.nerf.datasets import load_nerf_dataset
from pienerf.nerf.field import NGPConfig, NGPField, OccupancyGrid
from pienerf.nerf.fitting import NerfFit, Progress, fit_nerf
from pienerf.nerf.training import NerfCheckpoint, load_checkpoint, start_optimizer_import
from pienerf.paths import cache_root
from pienerf.render.deformed import LIGHT_DIRECTION
from pienerf.sim.density import Box, Capsule, SDFDensity, Sphere, Union, sigmoid_density

__all__ = [
    "GENERATOR_VERSION",
    "SCENES",
    "SCENE_SOFTNESS",
    "MeshAlbedoField",
    "SceneMesh",
    "cloth",
    "jelly",
    "plant",
    "render_scene",
    "scene_cameras",
    "scene_density",
    "scene_mesh",
    "scene_nerf",
    "sculpture",
    "teapot",
]

GENERATOR_VERSION = "1"
"""Bumped whenever the meshes, colours, cameras or shading change; part of every cache folder's name."""

SCENE_SOFTNESS = 0.002
"""Default density softness τ of :func:`scene_density`, metres: 2 mm keeps σ above 90 % of σ_max in the middle of
the thinnest parts (the 1 cm cloth and 1.4 cm leaves) while resolving their surfaces."""

CAMERA_ANGLE_X = 0.6911112070083618
"""Horizontal field of view of the rendered views, radians (that of the NeRF-synthetic scenes, about 39.6°)."""

_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking trimesh's z-axis solids (revolve, torus) to this module's y axis: (x, y, z) → (x, z, −y)."""


@dataclass(frozen=True)
class SceneMesh:
    """A scene's coloured triangle mesh: the union of its parts, which share no vertices.

    Attributes:
        vertices: ``[V, 3]`` float32, metres (y up, ground at y = 0).
        faces: ``[F, 3]`` int32 vertex indices, counter-clockwise seen from outside.
        colors: ``[V, 3]`` float32 albedo in [0, 1].
        name: the scene's name.
        part: ``[F]`` int64 index into ``part_names`` of each face's part.
        part_names: names of the parts (e.g. ``"leaf_3"``).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    colors: torch.Tensor
    name: str
    part: torch.Tensor
    part_names: tuple[str, ...]

    @property
    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis-aligned box ``(lo [3], hi [3])`` of the vertices, metres."""
        return self.vertices.amin(0), self.vertices.amax(0)

    def part_mesh(self, part: int | str):
        """One part as a ``trimesh.Trimesh`` (watertight, with its vertex colours)."""
        import trimesh

        index = self.part_names.index(part) if isinstance(part, str) else int(part)
        faces = self.faces[self.part == index].long()
        used, local = torch.unique(faces, return_inverse=True)
        colors = (self.colors[used].numpy() * 255.0).round().astype(np.uint8)
        return trimesh.Trimesh(self.vertices[used].numpy(), local.numpy(), vertex_colors=colors, process=False)


@dataclass(frozen=True)
class _Part:
    name: str
    mesh: object  # trimesh.Trimesh, watertight, metres
    colors: np.ndarray  # [V, 3] albedo
    solid: SDFDensity  # the same solid, analytically


# Analytic solids beyond pienerf.sim.density's boxes, capsules and spheres. Each is placed by a centre and a rotation
# whose columns are its local axes in world coordinates; signed distances are in metres, negative inside.


class _Placed(SDFDensity):
    def __init__(self, centre, rotation, **kwargs):
        self.centre = torch.as_tensor(np.asarray(centre, dtype=np.float64))
        self.rotation = torch.as_tensor(np.asarray(rotation, dtype=np.float64))
        super().__init__(**kwargs)

    def _local(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.centre.to(x)) @ self.rotation.to(x)

    def _world_bounds(self, lo: torch.Tensor, hi: torch.Tensor):
        middle, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        centre = self.centre + self.rotation @ middle
        half = self.rotation.abs() @ half
        return centre - half, centre + half


class _Lathe(_Placed):
    """Solid of revolution of a profile polygon ``(r, y)`` about the local y axis.

    The profile runs from a point on the axis (``r = 0``) through ``r > 0`` back to the axis. The distance to the
    solid is the 2-D distance, in the meridian half-plane through the point, to the profile's edges; the axis
    segment closing the polygon only decides inside from outside (crossing count). Exact.
    """

    def __init__(self, profile, centre=(0.0, 0.0, 0.0), rotation=np.eye(3), **kwargs):
        self.profile = torch.as_tensor(np.asarray(profile, dtype=np.float64))
        super().__init__(centre, rotation, **kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        local = self._local(x)
        q = torch.stack([torch.linalg.vector_norm(local[:, [0, 2]], dim=-1), local[:, 1]], dim=-1)[:, None]
        profile = self.profile.to(x)
        a, b = profile[:-1][None], profile[1:][None]  # profile edges, [1, E, 2]
        edge, offset = b - a, q - a
        s = ((offset * edge).sum(-1) / (edge * edge).sum(-1)).clamp(0.0, 1.0)
        distance = torch.linalg.vector_norm(offset - s[..., None] * edge, dim=-1).amin(dim=1)
        closed = torch.cat([profile, profile[:1]])
        a, b = closed[:-1][None], closed[1:][None]
        straddles = (a[..., 1] <= q[..., 1]) != (b[..., 1] <= q[..., 1])
        crossing_r = a[..., 0] + (q[..., 1] - a[..., 1]) * (b[..., 0] - a[..., 0]) / torch.where(
            straddles, b[..., 1] - a[..., 1], torch.ones_like(a[..., 1])
        )
        inside = (straddles & (q[..., 0] < crossing_r)).sum(dim=1) % 2 == 1
        return torch.where(inside, -distance, distance)

    def _tight_bounds(self):
        r = float(self.profile[:, 0].max())
        lo = torch.tensor([-r, float(self.profile[:, 1].min()), -r], dtype=torch.float64)
        hi = torch.tensor([r, float(self.profile[:, 1].max()), r], dtype=torch.float64)
        return self._world_bounds(lo, hi)

    def _feature_size(self):
        return 0.5 * min(float(self.profile[:, 0].max()), float(self.profile[:, 1].max() - self.profile[:, 1].min()))


class _Torus(_Placed):
    """Torus about the local y axis: ``d = ‖(‖(x, z)‖ − R, y)‖ − r``. Exact."""

    def __init__(self, major_radius, minor_radius, centre, rotation=np.eye(3), **kwargs):
        self.major_radius, self.minor_radius = float(major_radius), float(minor_radius)
        super().__init__(centre, rotation, **kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        local = self._local(x)
        ring = torch.linalg.vector_norm(local[:, [0, 2]], dim=-1) - self.major_radius
        return torch.sqrt(ring.square() + local[:, 1].square()) - self.minor_radius

    def _tight_bounds(self):
        outer = self.major_radius + self.minor_radius
        half = torch.tensor([outer, self.minor_radius, outer], dtype=torch.float64)
        return self._world_bounds(-half, half)

    def _feature_size(self):
        return self.minor_radius


class _RoundedBox(_Placed):
    """Box of half extents ``b`` with edges rounded by radius ``ρ``: ``d = d_box(x; b − ρ) − ρ``. Exact."""

    def __init__(self, half_extents, radius, centre, rotation=np.eye(3), **kwargs):
        self.half_extents = torch.as_tensor(np.asarray(half_extents, dtype=np.float64))
        self.radius = float(radius)
        super().__init__(centre, rotation, **kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        q = self._local(x).abs() - (self.half_extents - self.radius).to(x)
        outside = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1)
        return outside + q.amax(dim=-1).clamp_max(0.0) - self.radius

    def _tight_bounds(self):
        return self._world_bounds(-self.half_extents, self.half_extents)

    def _feature_size(self):
        return float(self.half_extents.min())


class _Ellipsoid(_Placed):
    """Ellipsoid of semi-axes ``a``: ``d ≈ k₀ (k₀ − 1) / k₁`` with ``k₀ = ‖x / a‖``, ``k₁ = ‖x / a²‖``.

    No closed form gives an ellipsoid's exact distance; this one is zero exactly on the surface, has the right
    sign everywhere and unit gradient on the surface, so it is accurate to first order within the few softness
    lengths where the density varies.
    """

    def __init__(self, radii, centre, rotation=np.eye(3), **kwargs):
        self.radii = torch.as_tensor(np.asarray(radii, dtype=np.float64))
        super().__init__(centre, rotation, **kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        local, radii = self._local(x), self.radii.to(x)
        k0 = torch.linalg.vector_norm(local / radii, dim=-1)
        k1 = torch.linalg.vector_norm(local / radii.square(), dim=-1)
        return k0 * (k0 - 1.0) / k1.clamp_min(1e-12)

    def _tight_bounds(self):
        return self._world_bounds(-self.radii, self.radii)

    def _feature_size(self):
        return float(self.radii.min())


# Part builders: mesh + colours + solid, all from the same parameters.


def _transformed(mesh, rotation, centre):
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, centre
    return mesh.apply_transform(transform)


def _lathe(name, profile, color_fn, centre=(0.0, 0.0, 0.0), rotation=np.eye(3), sections=48) -> _Part:
    import trimesh

    mesh = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    mesh = _transformed(mesh, np.asarray(rotation) @ _Y_UP, centre)
    return _Part(name, mesh, color_fn(mesh.vertices), _Lathe(profile, centre, rotation))


def _torus(name, major, minor, centre, rotation, color_fn) -> _Part:
    import trimesh

    mesh = trimesh.creation.torus(major, minor, major_sections=48, minor_sections=16)
    mesh = _transformed(mesh, np.asarray(rotation) @ _Y_UP, centre)
    return _Part(name, mesh, color_fn(mesh.vertices), _Torus(major, minor, centre, rotation))


def _ellipsoid(name, radii, centre, rotation, color_fn, subdivisions=3) -> _Part:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh.vertices *= np.asarray(radii)
    mesh = _transformed(mesh, rotation, centre)
    return _Part(name, mesh, color_fn(mesh.vertices), _Ellipsoid(radii, centre, rotation))


def _sphere(name, radius, centre, color_fn) -> _Part:
    import trimesh

    mesh = _transformed(trimesh.creation.icosphere(subdivisions=3, radius=radius), np.eye(3), centre)
    return _Part(name, mesh, color_fn(mesh.vertices), Sphere(centre, radius))


def _capsule(name, a, b, radius, color_fn) -> _Part:
    import trimesh

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    mesh = trimesh.creation.capsule(height=float(np.linalg.norm(b - a)), radius=radius, count=[24, 24])
    rotation = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], b - a)[:3, :3]
    mesh = _transformed(mesh, rotation, 0.5 * (a + b))
    return _Part(name, mesh, color_fn(mesh.vertices), Capsule(a, b, radius))


def _box(name, half_extents, centre, color_fn, rotation=np.eye(3)) -> _Part:
    import trimesh

    half = np.asarray(half_extents, dtype=np.float64)
    mesh = trimesh.creation.box(extents=2.0 * half).subdivide().subdivide()
    mesh = _transformed(mesh, rotation, centre)
    return _Part(name, mesh, color_fn(mesh.vertices), Box(centre, half, torch.as_tensor(rotation)))


def _rounded_box(name, half_extents, radius, centre, color_fn, rotation=np.eye(3), subdivisions=4) -> _Part:
    """A subdivided box whose vertices are moved onto the rounded box: ``p ↦ c + ρ (p − c) / ‖p − c‖`` with ``c``
    the nearest point of the inner box of half extents ``b − ρ`` (flat-face vertices stay put)."""
    import trimesh

    half = np.asarray(half_extents, dtype=np.float64)
    mesh = trimesh.creation.box(extents=2.0 * half)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    inner = np.clip(mesh.vertices, -(half - radius), half - radius)
    offset = mesh.vertices - inner
    mesh.vertices = inner + radius * offset / np.linalg.norm(offset, axis=1, keepdims=True)
    mesh = _transformed(mesh, rotation, centre)
    return _Part(name, mesh, color_fn(mesh.vertices), _RoundedBox(half, radius, centre, rotation))


def _slab(name, width, height, thickness, centre, color_fn, cells=(24, 24)) -> _Part:
    """A thin box in the xy plane, tessellated as a grid so per-vertex colour can vary across it."""
    import trimesh

    u, v = np.meshgrid(np.linspace(-0.5 * width, 0.5 * width, cells[0] + 1), np.linspace(-0.5, 0.5, cells[1] + 1))
    grid = np.stack([u.ravel(), height * v.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(cells[0]), np.arange(cells[1]))
    corner = (j * (cells[0] + 1) + i).ravel()
    triangles = np.concatenate(
        [
            np.stack([corner, corner + 1, corner + cells[0] + 2], 1),
            np.stack([corner, corner + cells[0] + 2, corner + cells[0] + 1], 1),
        ]
    )
    mesh = trimesh.creation.extrude_triangulation(grid, triangles, thickness)
    mesh.apply_translation(np.asarray(centre) - np.array([0.0, 0.0, 0.5 * thickness]))
    half = (0.5 * width, 0.5 * height, 0.5 * thickness)
    return _Part(name, mesh, color_fn(mesh.vertices), Box(centre, half))


# Colour fields: deterministic smooth patterns of the world position, so the NeRF sees texture.


def _noise(p: np.ndarray, frequency: float, seed: int = 0) -> np.ndarray:
    """Smooth pseudo-noise in about [−1, 1]: a sum of three plane waves of ``frequency`` (per metre)."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(3, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    phases = rng.uniform(0.0, 2.0 * math.pi, size=3)
    return np.sin(2.0 * math.pi * frequency * p @ directions.T + phases).mean(axis=1) * 1.5


def _mottled(rgb, amount=0.12, frequency=6.0, seed=0) -> Callable[[np.ndarray], np.ndarray]:
    base = np.asarray(rgb, dtype=np.float64)
    return lambda p: np.clip(base * (1.0 + amount * _noise(p, frequency, seed)[:, None]), 0.0, 1.0)


def _banded(rgb, band_rgb, axis, period, width=0.25) -> Callable[[np.ndarray], np.ndarray]:
    """Stripes of ``band_rgb`` across ``axis`` (a world direction) every ``period`` metres, softened by a sine."""
    base, band, axis = (np.asarray(c, dtype=np.float64) for c in (rgb, band_rgb, axis))

    def colors(p):
        phase = np.cos(2.0 * math.pi * (p @ axis) / period)
        weight = np.clip((phase - (1.0 - 2.0 * width)) / (2.0 * width), 0.0, 1.0)[:, None]
        return base * (1.0 - weight) + band * weight

    return colors


def _frame(x_axis, up_hint=(0.0, 1.0, 0.0)) -> np.ndarray:
    """A rotation whose first column is ``x_axis`` and third column is horizontal-ish (perpendicular to it)."""
    x = np.asarray(x_axis, dtype=np.float64)
    x = x / np.linalg.norm(x)
    z = np.cross(x, up_hint)
    z = z / np.linalg.norm(z)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _axis_frame(y_axis) -> np.ndarray:
    """A rotation whose second column (a lathe's axis) is ``y_axis``."""
    y = np.asarray(y_axis, dtype=np.float64)
    y = y / np.linalg.norm(y)
    helper = np.array([1.0, 0.0, 0.0]) if abs(y[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)], axis=1)


# The scenes.


def _plant_parts() -> list[_Part]:
    parts = [
        _lathe(
            "pot",
            [(0.0, 0.0), (0.15, 0.0), (0.19, 0.24), (0.215, 0.25), (0.215, 0.29), (0.0, 0.29)],
            _banded((0.72, 0.36, 0.2), (0.55, 0.25, 0.14), (0.0, 1.0, 0.0), 0.07, width=0.15),
        ),
        _lathe(
            "soil",
            [(0.0, 0.27), (0.2, 0.27), (0.2, 0.3), (0.12, 0.315), (0.0, 0.32)],
            _mottled((0.3, 0.2, 0.12), amount=0.35, frequency=25.0, seed=1),
        ),
        _capsule("stem", (0.0, 0.28, 0.0), (0.015, 0.95, 0.01), 0.014, _mottled((0.2, 0.42, 0.12), seed=2)),
    ]
    # Leaves: (height on the stem, azimuth, elevation, length), each an ellipsoid whose base sinks into the stem.
    leaves = [
        (0.45, 0.0, 0.35, 0.19),
        (0.55, 2.1, 0.4, 0.18),
        (0.65, 4.2, 0.45, 0.17),
        (0.74, 1.0, 0.5, 0.16),
        (0.83, 3.1, 0.55, 0.14),
        (0.9, 5.2, 0.65, 0.12),
    ]
    for i, (height, azimuth, elevation, length) in enumerate(leaves):
        direction = np.array(
            [math.cos(azimuth) * math.cos(elevation), math.sin(elevation), math.sin(azimuth) * math.cos(elevation)]
        )
        base = np.array([0.015 * (height - 0.28) / 0.67, height, 0.01 * (height - 0.28) / 0.67])
        centre = base + 0.9 * length * direction
        rotation = _frame(direction)

        def leaf_colors(p, centre=centre, direction=direction, length=length, rotation=rotation):
            along = np.clip(((p - centre) @ direction) / length, -1.0, 1.0)  # −1 at the base, 1 at the tip
            across = np.abs((p - centre) @ rotation[:, 2]) / (0.3 * length)
            vein = np.exp(-((across / 0.12) ** 2))[:, None]
            green = np.array([0.16, 0.5, 0.12]) + 0.12 * (along[:, None] + 1.0) * np.array([0.35, 0.4, 0.1])
            return np.clip(green * (1.0 - 0.3 * vein) + 0.3 * vein * np.array([0.55, 0.7, 0.35]), 0.0, 1.0)

        parts.append(_ellipsoid(f"leaf_{i}", (length, 0.007, 0.3 * length), centre, rotation, leaf_colors))
    return parts


def _teapot_parts() -> list[_Part]:
    porcelain = _banded((0.92, 0.9, 0.84), (0.16, 0.3, 0.62), (0.0, 1.0, 0.0), 0.09, width=0.12)
    body = [
        (0.0, 0.0),
        (0.16, 0.0),
        (0.2, 0.03),
        (0.24, 0.09),
        (0.26, 0.16),
        (0.25, 0.22),
        (0.22, 0.28),
        (0.17, 0.32),
        (0.13, 0.335),
        (0.0, 0.335),
    ]
    lid = [(0.0, 0.32), (0.135, 0.32), (0.13, 0.345), (0.1, 0.37), (0.05, 0.385), (0.0, 0.388)]
    spout_axis = np.array([math.cos(math.radians(50.0)), math.sin(math.radians(50.0)), 0.0])

    def rod_colors(p):
        # A helical stripe, so bending and twisting of the rod show in the images (Fig. 8).
        angle = np.arctan2(p[:, 1] - 0.2, p[:, 0])
        stripe = 0.5 + 0.5 * np.cos(angle + 2.0 * math.pi * p[:, 2] / 0.12)
        return np.stack([0.85 - 0.2 * stripe, 0.25 + 0.5 * stripe, 0.15 + 0.1 * stripe], axis=1)

    return [
        _lathe("body", body, porcelain),
        _lathe("lid", lid, porcelain),
        _sphere("knob", 0.03, (0.0, 0.41, 0.0), _mottled((0.16, 0.3, 0.62), seed=3)),
        _lathe(
            "spout",
            [(0.0, 0.0), (0.05, 0.0), (0.024, 0.28), (0.0, 0.28)],
            porcelain,
            centre=(0.18, 0.1, 0.0),
            rotation=_axis_frame(spout_axis),
            sections=32,
        ),
        _torus(
            "handle", 0.11, 0.022, (-0.25, 0.19, 0.0), _axis_frame((0.0, 0.0, 1.0)), _mottled((0.16, 0.3, 0.62), seed=4)
        ),
        _capsule("rod", (0.0, 0.2, 0.12), (0.0, 0.2, 0.72), 0.015, rod_colors),
    ]


def _jelly_parts() -> list[_Part]:
    def chocolate(p):
        base = np.array([0.36, 0.2, 0.11]) * (0.8 + 0.4 * np.clip(p[:, 1:2] / 0.5, 0.0, 1.0))
        return np.clip(base * (1.0 + 0.15 * _noise(p, 5.0, 5)[:, None]), 0.0, 1.0)

    return [_rounded_box("jelly", (0.35, 0.25, 0.35), 0.08, (0.0, 0.25, 0.0), chocolate, subdivisions=5)]


def _cloth_parts() -> list[_Part]:
    def plaid(p):
        u = 0.5 + 0.5 * np.cos(2.0 * math.pi * p[:, 0] / 0.25)
        v = 0.5 + 0.5 * np.cos(2.0 * math.pi * p[:, 1] / 0.25)
        return np.stack([0.7 * (0.4 + 0.6 * u), 0.15 + 0.3 * u * v, 0.2 + 0.5 * v], axis=1)

    return [_slab("sheet", 1.0, 1.0, 0.01, (0.0, 0.6, 0.0), plaid)]


def _sculpture_parts() -> list[_Part]:
    def marble(p):
        veins = np.abs(np.sin(9.0 * (p[:, 0] + 0.6 * p[:, 1] + 0.3 * _noise(p, 3.0, 6))))
        return np.clip(np.array([0.86, 0.84, 0.8]) - 0.3 * (veins[:, None] ** 8) * np.array([1.0, 1.0, 0.9]), 0, 1)

    bronze = _mottled((0.55, 0.38, 0.2), amount=0.18, frequency=8.0, seed=7)
    twist = math.radians(15.0)
    torso_rotation = np.array(
        [[math.cos(twist), 0.0, math.sin(twist)], [0.0, 1.0, 0.0], [-math.sin(twist), 0.0, math.cos(twist)]]
    )
    return [
        _box("plinth", (0.22, 0.1, 0.22), (0.0, 0.1, 0.0), marble),
        _capsule("leg_left", (-0.065, 0.2, 0.0), (-0.075, 0.52, 0.0), 0.045, bronze),
        _capsule("leg_right", (0.065, 0.2, 0.0), (0.075, 0.52, 0.0), 0.045, bronze),
        _rounded_box("torso", (0.12, 0.16, 0.07), 0.04, (0.0, 0.66, 0.0), bronze, torso_rotation, subdivisions=4),
        _capsule("arm_left", (-0.13, 0.77, 0.0), (-0.25, 0.56, 0.07), 0.034, bronze),
        _capsule("arm_right", (0.13, 0.77, 0.0), (0.3, 0.95, 0.05), 0.034, bronze),
        _capsule("neck", (0.0, 0.8, 0.0), (0.0, 0.86, 0.0), 0.03, bronze),
        _ellipsoid("head", (0.075, 0.09, 0.08), (0.0, 0.93, 0.0), np.eye(3), bronze),
    ]


_BUILDERS: dict[str, Callable[[], list[_Part]]] = {
    "plant": _plant_parts,
    "teapot": _teapot_parts,
    "jelly": _jelly_parts,
    "cloth": _cloth_parts,
    "sculpture": _sculpture_parts,
}

SCENES = tuple(_BUILDERS)
"""Names of the embedded scenes."""


def _parts(name: str) -> list[_Part]:
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; embedded scenes: {', '.join(SCENES)}")
    return _BUILDERS[name]()


def _assemble(name: str, parts: Sequence[_Part]) -> SceneMesh:
    vertices, faces, colors, part = [], [], [], []
    offset = 0
    for index, p in enumerate(parts):
        vertices.append(np.asarray(p.mesh.vertices))
        faces.append(np.asarray(p.mesh.faces) + offset)
        colors.append(p.colors)
        part.append(np.full(len(p.mesh.faces), index))
        offset += len(p.mesh.vertices)
    return SceneMesh(
        vertices=torch.from_numpy(np.concatenate(vertices)).float(),
        faces=torch.from_numpy(np.concatenate(faces)).int(),
        colors=torch.from_numpy(np.concatenate(colors)).float(),
        name=name,
        part=torch.from_numpy(np.concatenate(part)).long(),
        part_names=tuple(p.name for p in parts),
    )


def scene_mesh(name: str) -> SceneMesh:
    """The coloured mesh of the embedded scene ``name`` (one of :data:`SCENES`)."""
    return _assemble(name, _parts(name))


def plant() -> SceneMesh:
    """Swaying plant (Fig. 1, 5): pot, soil, stem and six leaves ``leaf_0`` … ``leaf_5``; about 1 m tall."""
    return scene_mesh("plant")


def teapot() -> SceneMesh:
    """Teapot with an elastic rod (Fig. 8): body, lid, knob, spout, handle and ``rod`` (1.5 cm radius, 60 cm)."""
    return scene_mesh("teapot")


def jelly() -> SceneMesh:
    """Chocolate jelly (Fig. 6): a 70 × 50 × 70 cm block with 8 cm rounded edges."""
    return scene_mesh("jelly")


def cloth() -> SceneMesh:
    """Hanging cloth (Fig. 9): a 1 × 1 m sheet, 1 cm thick, in the xy plane, its top edge at y = 1.1 m."""
    return scene_mesh("cloth")


def sculpture() -> SceneMesh:
    """Sculpture on a plinth (Fig. 7): a figure whose narrow neck and legs a cut can separate."""
    return scene_mesh("sculpture")


def scene_density(name: str, softness: float = SCENE_SOFTNESS, max_density: float = 50.0) -> Union:
    """The simulator's density field of the scene ``name``: the union of its parts' analytic solids.

    ``σ(x) = σ_max · sigmoid(−min_i d_i(x) / τ)`` (see :mod:`pienerf.sim.density`), the parts being the same solids
    the scene's mesh tessellates.

    Args:
        name: one of :data:`SCENES`.
        softness: ``τ``, metres.
        max_density: ``σ_max``, per metre.
    """
    return Union(*(p.solid for p in _parts(name)), max_density=max_density, softness=softness)


def scene_cameras(name: str, views: int = 64, resolution: int = 200, seed: int = 0) -> Cameras:
    """Cameras around the scene's object, looking at the centre of its bounding box.

    Centres lie on the upper hemisphere about that centre, evenly by area (elevation from 3° to 72°, azimuth by
    the golden angle, the whole pattern turned by a random angle from ``seed``), far enough that the object's
    bounding sphere fills 90 % of the field of view :data:`CAMERA_ANGLE_X`.

    Returns:
        :class:`~pienerf.nerf.Cameras` of ``views`` square images of ``resolution`` pixels.
    """
    if views < 1 or resolution < 1:
        raise ValueError(f"views and resolution must be positive, got views={views}, resolution={resolution}")
    mesh = scene_mesh(name)
    lo, hi = mesh.bounds
    centre = 0.5 * (lo + hi).double()
    radius = float(torch.linalg.vector_norm(mesh.vertices.double() - centre, dim=-1).max())
    distance = radius / (0.9 * math.sin(0.5 * CAMERA_ANGLE_X))
    turn = float(np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi))
    golden = math.pi * (3.0 - math.sqrt(5.0))
    low, high = math.sin(math.radians(3.0)), math.sin(math.radians(72.0))
    positions = []
    for i in range(views):
        elevation = math.asin(low + (high - low) * (i + 0.5) / views)
        azimuth = turn + golden * i
        offset = torch.tensor(
            [math.cos(elevation) * math.cos(azimuth), math.sin(elevation), math.cos(elevation) * math.sin(azimuth)],
            dtype=torch.float64,
        )
        positions.append(centre + distance * offset)
    return look_at_cameras(
        torch.stack(positions), centre.expand(views, 3), resolution, resolution, math.degrees(CAMERA_ANGLE_X)
    )


def render_scene(
    name: str,
    views: int = 64,
    resolution: int = 200,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    supersample: int = 2,
    test_every: int = 8,
    progress: bool = True,
) -> Path:
    """Render the scene ``name`` into a NeRF-synthetic dataset folder, or return the cached one.

    Views come from :func:`scene_cameras`; each pixel averages ``supersample²`` shaded rays (premultiplied, so
    edges get fractional alpha) of :func:`kernels.raycast.shade` under :data:`LIGHT_DIRECTION` with shadows,
    over a transparent background. Views ``0, test_every, 2·test_every, …`` go to ``transforms_test.json``,
    the others to ``transforms_train.json``; images are ``<split>/r_<view>.png`` (8-bit RGBA, straight alpha)
    beside float32 depth maps ``<split>/r_<view>_depth.npy`` (metres along each pixel-centre ray, ``inf`` where
    the ray misses; listed as ``depth_file_path``).

    The folder is ``<cache>/scenes/<name>-<resolution>-<views>-<hash>``, the hash covering
    :data:`GENERATOR_VERSION` and every argument that changes the images; ``<cache>`` is ``cache_dir``, else
    ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``. It is written into a temporary folder beside it and
    renamed when complete, so an interrupted render leaves no partial scene; an existing folder is reused as is.

    Args:
        name: one of :data:`SCENES`.
        views: number of views (PIE-NeRF used 100).
        resolution: image width and height, pixels.
        seed: turns the camera pattern (:func:`scene_cameras`).
        cache_dir: root of the cache (see above).
        supersample: rays per pixel along each axis.
        test_every: one view in ``test_every`` is held out for testing.
        progress: show a progress bar when rendering more than 8 views.

    Returns:
        The dataset folder, readable by :func:`pienerf.nerf.datasets.load_nerf_dataset`.
    """
    if not (isinstance(supersample, int) and supersample >= 1):
        raise ValueError(f"supersample must be a positive integer (rays per pixel per axis), got {supersample!r}")
    if not (isinstance(test_every, int) and test_every >= 2):
        raise ValueError(f"test_every must be an integer ≥ 2, got {test_every!r}")
    mesh = scene_mesh(name)
    settings = {
        "generator": GENERATOR_VERSION,
        "name": name,
        "views": views,
        "resolution": resolution,
        "seed": seed,
        "supersample": supersample,
        "test_every": test_every,
    }
    digest = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:10]
    folder = cache_root(cache_dir) / "scenes" / f"{name}-{resolution}-{views}-{digest}"
    if (folder / "transforms_train.json").is_file():
        return folder

    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        _render_into(staging, mesh, scene_cameras(name, views, resolution, seed), settings, progress)
        try:
            staging.rename(folder)
        except OSError:
            if not (folder / "transforms_train.json").is_file():
                raise
            shutil.rmtree(staging)  # another process finished the same scene first
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return folder


def _render_into(folder: Path, mesh: SceneMesh, cameras: Cameras, settings: dict, progress: bool) -> None:
    from PIL import Image
    from rich.progress import track

    backend.init()
    device = backend.torch_device()
    bvh = MeshBVH(mesh.vertices.to(device), mesh.faces.to(device))
    colors = mesh.colors.to(device)
    k, size = settings["supersample"], settings["resolution"]
    frames = {"train": [], "test": []}
    for split in frames:
        (folder / split).mkdir()
    views = range(len(cameras))
    for view in track(views, description=f"rendering {mesh.name}", disable=not progress or len(cameras) <= 8):
        origins, directions = cameras.rays(view, downscale=1) if k == 1 else _fine_rays(cameras, view, k)
        shaded = shade(bvh, origins.to(device), directions.to(device), colors, light_direction=LIGHT_DIRECTION)
        rgba = shaded.rgba.reshape(size, k, size, k, 4) if k > 1 else shaded.rgba.reshape(size, 1, size, 1, 4)
        premultiplied = torch.cat([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], dim=-1).mean(dim=(1, 3))
        alpha = premultiplied[..., 3:]
        straight = torch.where(alpha > 0, premultiplied[..., :3] / alpha.clamp_min(1e-8), 0.0)
        pixels = (torch.cat([straight, alpha], dim=-1).clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
        centre_origins, centre_directions = cameras.rays(view)
        depth = bvh.cast(centre_origins.to(device), centre_directions.to(device)).t.reshape(size, size)

        split = "test" if view % settings["test_every"] == 0 else "train"
        stem = f"{split}/r_{view}"
        Image.fromarray(pixels, mode="RGBA").save(folder / f"{stem}.png")
        np.save(folder / f"{stem}_depth.npy", depth.cpu().numpy().astype(np.float32))
        frames[split].append(
            {
                "file_path": f"./{stem}",
                "depth_file_path": f"./{stem}_depth.npy",
                "transform_matrix": cameras.c2w[view].tolist(),
            }
        )
    for split, split_frames in frames.items():
        meta = {
            "camera_angle_x": CAMERA_ANGLE_X,
            "scene": mesh.name,
            "light_direction": list(LIGHT_DIRECTION),
            "settings": settings,
            "frames": split_frames,
        }
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def _fine_rays(cameras: Cameras, view: int, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through a ``k × k`` grid of sub-pixel centres of each pixel, ordered ``[row, sub-row, col, sub-col]``."""
    rows, cols = torch.meshgrid(
        torch.arange(k * cameras.height) + 0.5, torch.arange(k * cameras.width) + 0.5, indexing="ij"
    )
    return cameras.pixel_rays(view, cols.reshape(-1) / k, rows.reshape(-1) / k)


_COLOR_RADIUS = 0.02
"""Metres; points of :class:`MeshAlbedoField` farther than this from the surface are grey (they lie deep inside
a solid, behind its opaque surface, or far outside it, where σ is negligible)."""


class MeshAlbedoField:
    """An embedded scene as a radiance field without training: σ from its analytic solids, colour the albedo of
    the nearest mesh vertex (view-independent). Has the interface the renderer reads from
    :class:`pienerf.nerf.NGPField`: ``aabb``, ``config``, ``density(x)``, ``field(x, d) → (σ, rgb)``
    and its split ``radiance(x, encode_directions(d))``.

    Args:
        name: one of :data:`pienerf.scenes.SCENES`.
        max_density: ``σ_max`` of the solids, per metre; 5000 makes a surface opaque within a 2 mm step.
        softness: ``τ`` of the solids, metres; 0.5 mm keeps silhouettes within a march step of the mesh's.
        padding: the box is the mesh's bounds grown by this, metres (room for the deformed body).
        config: marching settings (``NGPConfig()`` by default: ~1000 steps per box diagonal).
        max_edge: the scene mesh is subdivided until no edge is longer than this, metres, with colours
            interpolated linearly; this refined mesh (:attr:`mesh`) gives the colours, and deforming its
            vertices gives a ground truth that bends with the body (the rod's faces are 60 cm long as built).
    """

    def __init__(
        self,
        name: str,
        max_density: float = 5000.0,
        softness: float = 5e-4,
        padding: float = 0.35,
        config: NGPConfig | None = None,
        max_edge: float = 0.01,
    ):
        device = backend.torch_device()
        self.mesh = _refined(scene_mesh(name), max_edge)
        self.solids = scene_density(name, softness=softness, max_density=max_density)
        lo, hi = self.mesh.bounds
        self.aabb = torch.stack([lo - padding, hi + padding]).float().to(device)
        self.config = config or NGPConfig()
        self.vertices = self.mesh.vertices.to(device).contiguous()
        self.colors = self.mesh.colors.to(device)
        self._vertex_hash = SpatialHash(self.vertices, cell_size=max_edge)

    def _density_and_distance(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        distance = self.solids.signed_distance(x)
        inside = ((x >= self.aabb[0]) & (x <= self.aabb[1])).all(dim=-1)
        sigma = sigmoid_density(distance, self.solids.max_density, self.solids.softness)
        return torch.where(inside, sigma, 0.0), distance

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """σ ``[N]`` per metre at ``x [N, 3]`` (metres); 0 outside the box."""
        return self._density_and_distance(x)[0]

    def __call__(self, x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(σ [N], rgb [N, 3])`` at points ``x [N, 3]``; the direction ``d`` is ignored (Lambertian albedo).

        Only points within :data:`_COLOR_RADIUS` of the surface look up a vertex colour; the others are grey.
        """
        sigma, distance = self._density_and_distance(x)
        rgb = torch.full((x.shape[0], 3), 0.5, device=x.device)
        near = distance.abs() < _COLOR_RADIUS
        if bool(near.any()):
            nearest, _ = self._vertex_hash.knn(x[near].contiguous(), 1, max_radius=_COLOR_RADIUS)
            found = nearest[:, 0] >= 0
            rgb[near] = torch.where(found[:, None], self.colors[nearest[:, 0].long().clamp_min(0)], 0.5)
        return sigma, rgb

    def encode_directions(self, d: torch.Tensor) -> torch.Tensor:
        """Directions as :meth:`radiance` takes them: unchanged (the albedo is view-independent)."""
        return d

    def radiance(self, x: torch.Tensor, encoded_directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``self(x, d)`` for directions from :meth:`encode_directions` (the interface of :class:`NGPField`)."""
        return self(x, encoded_directions)

    def occupancy_grid(self, resolution: int = 128) -> OccupancyGrid:
        """The field's occupancy grid, every cell evaluated once (threshold as :meth:`OccupancyGrid.for_field`)."""
        threshold = self.config.grid_threshold / self.config.min_step(self.aabb.cpu())
        grid = OccupancyGrid(self.aabb, resolution, decay=1.0, threshold=threshold).to(self.aabb.device)
        grid.update(self.density, generator=torch.Generator(device=self.aabb.device).manual_seed(0))
        return grid


def _refined(mesh: SceneMesh, max_edge: float) -> SceneMesh:
    """``mesh`` with every edge bisected until shorter than ``max_edge`` (metres), colours interpolated linearly."""
    from trimesh import remesh

    faces = mesh.faces.long().numpy()
    vertices, new_faces, origin = remesh.subdivide_to_size(
        mesh.vertices.double().numpy(), faces, max_edge, max_iter=12, return_index=True
    )
    vertices, new_faces = torch.from_numpy(vertices), torch.from_numpy(new_faces).long()
    origin = torch.from_numpy(origin).long()
    # Barycentric coordinates of each new face's corners in its original triangle.
    a, b, c = (mesh.vertices.double()[torch.from_numpy(faces[:, i])][origin] for i in range(3))
    e1, e2 = b - a, c - a
    gram = torch.stack(
        [
            torch.stack([(e1 * e1).sum(-1), (e1 * e2).sum(-1)], -1),
            torch.stack([(e1 * e2).sum(-1), (e2 * e2).sum(-1)], -1),
        ],
        -2,
    )
    colors = torch.zeros(vertices.shape[0], 3, dtype=torch.float64)
    original_colors = mesh.colors.double()[torch.from_numpy(faces)][origin]  # [Q, 3 corners, 3]
    for corner in range(3):
        p = vertices[new_faces[:, corner]] - a
        rhs = torch.stack([(p * e1).sum(-1), (p * e2).sum(-1)], -1)
        b1, b2 = torch.linalg.solve(gram, rhs[..., None])[..., 0].unbind(-1)
        weights = torch.stack([1.0 - b1 - b2, b1, b2], -1)
        colors[new_faces[:, corner]] = (weights[..., None] * original_colors).sum(1)
    return SceneMesh(
        vertices=vertices.float(),
        faces=new_faces.int(),
        colors=colors.clamp(0.0, 1.0).float(),
        name=mesh.name,
        part=mesh.part[origin],
        part_names=mesh.part_names,
    )


def scene_nerf(
    scene: str, fit: NerfFit = NerfFit(), cache_dir: str | Path | None = None, progress: Progress | None = None
) -> NerfCheckpoint:
    """The NeRF of an embedded scene, trained on its rendered views, or loaded from the cache.

    The views come from :func:`pienerf.scenes.render_scene` (``fit.views`` views of ``fit.resolution`` pixels,
    cached under ``<cache>/scenes``); the checkpoint is ``ngp-<hash>.pt`` beside them. The scene box is the scene
    mesh's bounds grown by ``fit.padding``.

    Args:
        scene: one of :data:`pienerf.scenes.SCENES`.
        fit: the fitting settings.
        cache_dir: cache root (default ``$PIE_CACHE_DIR``, else ``~/.cache/pie-physavatar``).
        progress: called with ``(stage, fraction)`` while rendering and training.

    Returns:
        The trained field (eval mode, backend device) and its occupancy grid.
    """
    backend.init()
    if progress is not None:
        progress(f"rendering {fit.views} views of {scene}", 0.0)
    folder = render_scene(
        scene,
        views=fit.views,
        resolution=fit.resolution,
        seed=fit.seed,
        cache_dir=cache_root(cache_dir),
        progress=False,
    )
    path = folder / f"ngp-{fit.digest(scene=scene)}.pt"
    if path.is_file():
        return load_checkpoint(path)
    start_optimizer_import()  # a fit follows: its optimizer's import overlaps with the loading
    dataset = load_nerf_dataset(folder, "train", background=(0.0, 0.0, 0.0))
    lo, hi = scene_mesh(scene).bounds
    torch.manual_seed(fit.seed)
    field_ = NGPField(fit.ngp, torch.stack([lo - fit.padding, hi + fit.padding]))
    return fit_nerf(field_, dataset, fit, path, progress, scene)
