"""Previews of a simulated body: render backends behind one small interface.

A :class:`RenderBackend` renders the body at generalized coordinates ``q`` seen by one view of some
:class:`pienerf.nerf.Cameras` into a :class:`Frame` (straight-alpha RGBA, depth along each ray, optional shadow):

* :class:`MeshRenderBackend`: the scene's mesh carried by the Q-GMLS displacement field, x(X) = X + Σ_s N_s(X) q_s
  (Eq. 9), whose shape functions at the rest vertices are precomputed once; each frame moves the vertices, refits
  the BVH and shades RGBA + depth with a shadow ray onto a ground plane (:func:`kernels.raycast.shade`); the
  colliders it is given (spheres as balls, planes as square plates) are drawn beside the body and cast shadows.
  Given ``max_edge``, it first splits the mesh's longer edges (:func:`pienerf.render.mesh_refine.split_long_edges`), so
  that a bend of the field shows as a bend and not as a straight chord between distant vertices (Fig. 8's rod).
* :class:`ParticleRenderBackend`: the deformed particles splatted as discs with the colour of the nearest mesh
  vertex.
* :class:`NerfRenderBackend`: a trained NeRF rendered by quadratic (or linear) ray warping, Eq. 19–21
  (:class:`pienerf.render.DeformedRenderer`), at a ``downscale`` a viewer raises while the user drags, as far as a
  frame budget asks, and lowers to 1 to refine a still view, as
  :class:`pienerf.render.refinement.RefinementSchedule` decides.

Backends that hold the discretised body (a ``rebind(model)`` method) follow it through re-sampling and cuts.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import torch

from kernels import backend
from kernels.raycast import MeshBVH, shade
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.field import OccupancyGrid
from pienerf.render.deformed import LIGHT_DIRECTION, MODES, DeformedRenderer, GroundPlane
from pienerf.render.mesh_refine import split_long_edges
from pienerf.sim.model import QGMLSModel
from pienerf.sim.solver import PlaneCollider, SphereCollider

__all__ = [
    "Frame",
    "MeshRenderBackend",
    "NerfRenderBackend",
    "ParticleRenderBackend",
    "RenderBackend",
    "ViewRays",
]


class Frame(NamedTuple):
    """One rendered view.

    Attributes:
        rgba: ``[H, W, 4]`` float32 in [0, 1], straight alpha.
        depth: ``[H, W]`` float32 distance along each pixel ray (m), ``inf`` where nothing is hit.
        shadow: ``[H, W]`` float32 in [0, 1], share of the direct light blocked at each visible point, or ``None``.
    """

    rgba: torch.Tensor
    depth: torch.Tensor
    shadow: torch.Tensor | None = None


class RenderBackend(Protocol):
    """Renders the body at generalized coordinates ``q [nT, 3]`` seen by one view of ``cameras``."""

    def render(self, q: torch.Tensor, cameras: Cameras, view: int, shadow: bool = False) -> Frame: ...


class MeshRenderBackend:
    """The scene mesh deformed by the Q-GMLS field, ray traced with shadows onto a ground plane.

    Args:
        model: the discretised body.
        vertices: ``[V, 3]`` rest vertices (m).
        faces: ``[F, 3]`` vertex indices.
        colors: ``[V, 3]`` albedo in [0, 1].
        ground_height: y of the ground plane (m), or ``None`` for none.
        ground_color: albedo of the ground.
        max_edge: split the body's edges until none is longer than this (m); ``None`` renders the mesh as given.
            The rest surface and its colours stay exactly as they were; the original vertices come first, so
            :meth:`deform`'s first ``V`` rows are the given vertices.
    """

    def __init__(
        self,
        model: QGMLSModel,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        colors: torch.Tensor,
        ground_height: float | None = 0.0,
        ground_color=(0.82, 0.82, 0.8),
        max_edge: float | None = None,
    ):
        device = backend.torch_device()
        vertices, faces, colors = vertices.float(), faces.long(), colors.float()
        self.max_edge = max_edge
        if max_edge is not None:
            vertices, faces, colors = split_long_edges(vertices, faces, colors, max_edge)
        self.handle = model.handle(vertices)
        self.body_vertices = vertices.shape[0]
        self._body_faces = faces.shape[0]
        if ground_height is not None:
            lo, hi = vertices.amin(0), vertices.amax(0)
            centre, half = 0.5 * (lo + hi), 4.0 * float((hi - lo).max())
            corners = torch.tensor([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=torch.float32) * half
            ground = torch.stack(
                [corners[:, 0] + centre[0], torch.full((4,), float(ground_height)), corners[:, 1] + centre[2]], dim=1
            )
            base = vertices.shape[0]
            faces = torch.cat([faces, torch.tensor([[0, 2, 1], [0, 3, 2]]) + base])
            vertices = torch.cat([vertices, ground])
            colors = torch.cat([colors, torch.tensor(ground_color, dtype=torch.float32).expand(4, 3)])
        self.rest_vertices = vertices.to(device)
        self.colors = colors.to(device).contiguous()
        self.bvh = MeshBVH(self.rest_vertices, faces.to(device=device, dtype=torch.int32))
        self._vertices = self.rest_vertices.clone()
        self._scene_faces, self._scene_colors, self._scene_vertices = faces, colors, vertices.shape[0]
        lo, hi = vertices[: self.body_vertices].amin(0), vertices[: self.body_vertices].amax(0)
        self._body_centre, self._plate_half = 0.5 * (lo + hi), 0.6 * float((hi - lo).max())
        self._collider_kinds: tuple = ()

    def set_colliders(self, colliders) -> None:
        """Draw ``colliders`` (:class:`pienerf.sim.SphereCollider`, :class:`pienerf.sim.PlaneCollider`) from
        the next render on, in the place each has now; a plane becomes a square plate about the body's rest centre,
        1.2 × the body's largest extent wide. Leave the floor out: the ground plane already draws it.

        Changing the number or kind of colliders rebuilds the BVH (call :meth:`surface` again to pick on it);
        moving them only refits it.
        """
        shapes = [_collider_mesh(c, self._body_centre, self._plate_half) for c in colliders]
        kinds = tuple(type(c).__name__ for c in colliders)
        base = self.rest_vertices[: self._scene_vertices]
        if kinds != self._collider_kinds:
            device = backend.torch_device()
            faces, colors, offset = [self._scene_faces], [self._scene_colors], base.shape[0]
            for vertices, shape_faces, color in shapes:
                faces.append(shape_faces + offset)
                colors.append(torch.tensor(color, dtype=torch.float32).expand(vertices.shape[0], 3))
                offset += vertices.shape[0]
            self.colors = torch.cat(colors).to(device).contiguous()
            self.rest_vertices = torch.cat([base.cpu()] + [v for v, _, _ in shapes]).to(device)
            self.bvh = MeshBVH(self.rest_vertices, torch.cat(faces).to(device=device, dtype=torch.int32))
            body = self._vertices[: self.body_vertices]
            self._vertices = self.rest_vertices.clone()
            self._vertices[: self.body_vertices] = body
            self._collider_kinds = kinds
        elif shapes:
            moved = torch.cat([v for v, _, _ in shapes]).to(self._vertices)
            self._vertices[base.shape[0] :] = moved
            self.bvh.refit(self._vertices)

    def deform(self, q: torch.Tensor) -> torch.Tensor:
        """Move the body's vertices to x(X) at ``q`` (Eq. 9) and refit the BVH; returns the ``[V, 3]`` vertices."""
        self._vertices[: self.body_vertices] = self.handle.positions(q).to(self._vertices)
        self.bvh.refit(self._vertices)
        return self._vertices[: self.body_vertices]

    def body_mesh(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The body's rest mesh as this backend renders it (refined when ``max_edge`` was given), on the CPU:
        ``(vertices [V, 3] float32 m, faces [F, 3] int64, colors [V, 3] albedo)``."""
        return (
            self.rest_vertices[: self.body_vertices].cpu(),
            self._scene_faces[: self._body_faces].cpu(),
            self._scene_colors[: self.body_vertices].cpu(),
        )

    def render(self, q: torch.Tensor, cameras: Cameras, view: int, shadow: bool = False) -> Frame:
        self.deform(q)
        device = backend.torch_device()
        origins, directions = cameras.rays(view)
        origins, directions = origins.to(device), directions.to(device)
        lit = shade(self.bvh, origins, directions, self.colors, light_direction=LIGHT_DIRECTION)
        shape = (cameras.height, cameras.width)
        blocked = None
        if shadow:
            unlit = shade(self.bvh, origins, directions, self.colors, light_direction=LIGHT_DIRECTION, shadows=False)
            bright = unlit.rgba[:, :3].mean(1)
            blocked = torch.where(bright > 0, 1.0 - lit.rgba[:, :3].mean(1) / bright.clamp_min(1e-6), 0.0)
            blocked = blocked.clamp(0, 1).reshape(shape)
        return Frame(lit.rgba.reshape(*shape, 4), lit.depth.reshape(shape), blocked)


_SPHERE_COLOR = (0.45, 0.55, 0.7)
_PLATE_COLOR = (0.5, 0.52, 0.56)


def _collider_mesh(collider, centre: torch.Tensor, half: float) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """``(vertices [V, 3], faces [F, 3], albedo)`` of a collider to draw: a sphere as a 16 × 32 UV sphere, a plane
    as a square of half-width ``half`` (m) about ``centre [3]`` projected onto it."""
    if isinstance(collider, SphereCollider):
        rings, segments = 16, 32
        theta = torch.linspace(0.0, math.pi, rings + 1)[:, None]
        phi = torch.linspace(0.0, 2.0 * math.pi, segments + 1)[None, :-1]
        ring = torch.sin(theta)
        unit = torch.stack([ring * torch.cos(phi), torch.cos(theta).expand(-1, segments), ring * torch.sin(phi)], -1)
        unit = unit.reshape(-1, 3)
        vertices = torch.tensor(collider.centre, dtype=torch.float32) + float(collider.radius) * unit
        i, j = torch.meshgrid(torch.arange(rings), torch.arange(segments), indexing="ij")
        a, b = i * segments + j, i * segments + (j + 1) % segments
        c, d = a + segments, b + segments
        faces = torch.cat([torch.stack([a, c, b], -1), torch.stack([b, c, d], -1)]).reshape(-1, 3)
        return vertices, faces, _SPHERE_COLOR
    if isinstance(collider, PlaneCollider):
        normal = torch.nn.functional.normalize(torch.tensor(collider.normal, dtype=torch.float32), dim=0)
        point = torch.tensor(collider.point, dtype=torch.float32)
        middle = centre.float() - float((centre.float() - point) @ normal) * normal
        helper = torch.tensor([1.0, 0.0, 0.0]) if abs(float(normal[0])) < 0.9 else torch.tensor([0.0, 0.0, 1.0])
        u = torch.nn.functional.normalize(torch.linalg.cross(normal, helper), dim=0)
        v = torch.linalg.cross(normal, u)
        corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * half
        vertices = middle + corners[:, :1] * u + corners[:, 1:] * v
        return vertices, torch.tensor([[0, 1, 2], [0, 2, 3]]), _PLATE_COLOR
    raise TypeError(f"cannot draw collider {collider!r}; use PlaneCollider or SphereCollider")


class ParticleRenderBackend:
    """The deformed particles splatted as discs of their radius, nearest first, in the colour of the nearest
    mesh vertex.

    Args:
        model: the discretised body.
        colors: ``[P, 3]`` albedo per particle.
    """

    def __init__(self, model: QGMLSModel, colors: torch.Tensor, max_radius_px: int = 4):
        self.model = model
        self.colors = colors.float()
        self.radius = (3.0 * model.volume / (4.0 * math.pi)).pow(1.0 / 3.0).float()
        self.max_radius_px = max_radius_px

    def render(self, q: torch.Tensor, cameras: Cameras, view: int, shadow: bool = False) -> Frame:
        W, H = cameras.width, cameras.height
        x = self.model.particles.positions(q).float().cpu()
        cameras = cameras.to("cpu")
        c2w = cameras.c2w[view]
        u, v, z = cameras.project(view, x)
        front = z > 1e-3
        radius_px = (cameras.fx[view] * self.radius.cpu() / z.clamp_min(1e-3)).clamp(0.5, self.max_radius_px)
        depth = torch.full((H * W,), math.inf)
        owner = torch.full((H * W,), -1, dtype=torch.long)
        distance = (x - c2w[:3, 3]).norm(dim=1)
        reach = int(math.ceil(float(radius_px.max()))) if len(radius_px) else 0
        for dy in range(-reach, reach + 1):
            for dx in range(-reach, reach + 1):
                col, row = torch.floor(u).long() + dx, torch.floor(v).long() + dy
                inside = front & (col >= 0) & (col < W) & (row >= 0) & (row < H) & (dx * dx + dy * dy <= radius_px**2)
                pixel = (row * W + col)[inside]
                depth.scatter_reduce_(0, pixel, distance[inside], reduce="amin")
        for dy in range(-reach, reach + 1):
            for dx in range(-reach, reach + 1):
                col, row = torch.floor(u).long() + dx, torch.floor(v).long() + dy
                inside = front & (col >= 0) & (col < W) & (row >= 0) & (row < H) & (dx * dx + dy * dy <= radius_px**2)
                pixel = (row * W + col)[inside]
                nearest = depth[pixel] == distance[inside]
                owner[pixel[nearest]] = torch.nonzero(inside)[:, 0][nearest]
        rgba = torch.zeros(H * W, 4)
        hit = owner >= 0
        rgba[hit, :3] = self.colors.cpu()[owner[hit]]
        rgba[hit, 3] = 1.0
        return Frame(rgba.reshape(H, W, 4), depth.reshape(H, W), None)


class NerfRenderBackend:
    """The ``"nerf"`` render mode: the trained NeRF warped by the body's deformation (PIE-NeRF §4.6, Eq. 19–21).

    Renders one view at ``1 / downscale`` of its pixels (pixel centres of the coarse grid) and repeats each coarse
    pixel to the camera's size, so a viewer can set ``downscale`` to 4 while the user drags and back to 1 to refine
    a still view. RGBA is straight alpha: the object's opacity, and 1 on the ground square when a ground is set.

    Args:
        field: the rest-space radiance field (:class:`pienerf.nerf.NGPField`).
        grid: its occupancy grid.
        model: the discretised body whose integrator points drive the warp (:meth:`rebind` after a re-sampling).
        mode: ``"quadratic"`` (Eq. 20), ``"linear"`` (first-order warp, Fig. 8) or ``"rest"`` (no warp).
        downscale: integer factor of the rendered resolution (1: every pixel).
        ground: a lit ground plane that receives the object's shadow, or ``None``.
        cutoff_scale: see :class:`pienerf.render.DeformedRenderer`.
    """

    def __init__(
        self,
        field,
        grid: OccupancyGrid,
        model,
        *,
        mode: str = "quadratic",
        downscale: int = 1,
        ground: GroundPlane | None = None,
        cutoff_scale: float = 1.5,
    ):
        if mode not in MODES:
            raise ValueError(f"unknown warping mode {mode!r}; valid modes: {', '.join(MODES)}")
        self.field, self.grid, self.mode, self.ground = field, grid, mode, ground
        self.cutoff_scale = cutoff_scale
        self.downscale = downscale
        self._rays = ViewRays()
        self.rebind(model)

    @property
    def downscale(self) -> int:
        """Rendered pixels are ``downscale × downscale`` blocks of the camera's pixels."""
        return self._downscale

    @downscale.setter
    def downscale(self, value: int) -> None:
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
            raise ValueError(f"downscale must be an integer >= 1, got {value!r}")
        self._downscale = value

    def rebind(self, model) -> None:
        """Warp by another discretisation of the body (after a re-sampling or a cut)."""
        self.model = model
        self.renderer = DeformedRenderer(self.field, self.grid, model, cutoff_scale=self.cutoff_scale)
        self._frame_q: torch.Tensor | None = None
        self._frame = None

    def _deformed_frame(self, q: torch.Tensor):
        """The renderer's per-q state, rebuilt only when q changes (a still body renders several views cheaply)."""
        if self._frame is None or self._frame_q.shape != q.shape or not torch.equal(self._frame_q, q.detach()):
            self._frame = self.renderer.frame(self.renderer.check_q(q))
            self._frame_q = q.detach().clone()
        return self._frame

    def render(
        self, q: torch.Tensor, cameras: Cameras, view: int, shadow: bool = False, downscale: int | None = None
    ) -> Frame:
        """Render the body at ``q [nT, 3]`` seen by view ``view``, at ``downscale`` (default :attr:`downscale`).

        ``depth`` is the object's expected depth where its opacity exceeds ½, else the ground's distance on the
        ground square, else ``inf``; ``shadow`` (when asked, with a ground) is the share of light the object
        blocks on the visible ground, 0 on the object.
        """
        if downscale is None:
            downscale = self.downscale
        elif not (isinstance(downscale, int) and not isinstance(downscale, bool) and downscale >= 1):
            raise ValueError(f"downscale must be an integer >= 1, got {downscale!r}")
        width, height = cameras.width, cameras.height
        w, h = max(1, math.ceil(width / downscale)), max(1, math.ceil(height / downscale))
        origins, directions = self._rays(cameras, view, w, h)
        frame = None if self.mode == "rest" and self.ground is None else self._deformed_frame(q)
        out = self.renderer.render(
            q, rays=(origins, directions), mode=self.mode, background=(0.0, 0.0, 0.0), ground=self.ground, frame=frame
        )
        opacity = out["alpha"].clamp(0.0, 1.0)
        depth = torch.where(opacity > 0.5, out["depth"], math.inf)
        if self.ground is not None:
            on_ground = out["on_ground"]
            t_ground = (self.ground.height - origins[:, 1]) / directions[:, 1]
            depth = torch.where((opacity <= 0.5) & on_ground, t_ground, depth)
            alpha = opacity + (1.0 - opacity) * on_ground.float()
        else:
            alpha = opacity
        straight = torch.where(alpha[:, None] > 1e-6, out["rgb"] / alpha.clamp_min(1e-6)[:, None], 0.0)
        rgba = torch.cat([straight.clamp(0.0, 1.0), alpha[:, None]], dim=1)
        blocked = None
        if shadow and self.ground is not None:
            blocked = ((1.0 - out["ground_transmittance"]) * (1.0 - opacity) * out["on_ground"].float()).clamp(0, 1)
        frame = [rgba.reshape(h, w, 4), depth.reshape(h, w)] + ([blocked.reshape(h, w)] if blocked is not None else [])
        if (h, w) != (height, width):
            frame = [_upsample(image, height, width) for image in frame]
        return Frame(frame[0], frame[1], frame[2] if blocked is not None else None)


class ViewRays:
    """The rays through a grid of blocks over one camera view (:meth:`pienerf.nerf.Cameras.grid_rays`), on the backend
    device, made again only when something they depend on changes.

    While the camera stays still (the user drags the body, not the view) every call hands back the very same
    tensors, so nothing is generated on the host or uploaded per frame, and the renderer keeps their encoded
    directions too (:meth:`pienerf.render.DeformedRenderer.render`). The key is the view's pose and intrinsics as
    stored (their bytes, so even the sign of a zero counts), the view index, the image and grid sizes and the device.
    The returned tensors are shared between calls: read them, never write to them.
    """

    def __init__(self):
        self._key = None
        self._rays: tuple[torch.Tensor, torch.Tensor] | None = None

    def __call__(self, cameras: Cameras, view: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Float32 contiguous ``origins [height·width, 3]`` (metres) and unit ``directions [height·width, 3]`` of
        view ``view`` seen as a ``width × height`` grid (row-major)."""
        device = backend.torch_device()
        view = int(view)
        pose = [cameras.c2w[view]] + [getattr(cameras, k)[view : view + 1] for k in ("fx", "fy", "cx", "cy")]
        values = torch.cat([t.detach().reshape(-1) for t in pose]).cpu()
        key = (view, width, height, cameras.width, cameras.height, str(device), values.dtype, values.numpy().tobytes())
        if key != self._key:
            origins, directions = cameras.to("cpu").grid_rays(view, width, height)
            self._rays = tuple(t.float().to(device).contiguous() for t in (origins, directions))
            self._key = key
        return self._rays


def _upsample(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Nearest-neighbour resize of ``[h, w, ...]`` to ``[height, width, ...]``."""
    rows = (torch.arange(height, device=image.device) * image.shape[0]) // height
    cols = (torch.arange(width, device=image.device) * image.shape[1]) // width
    return image[rows][:, cols]
