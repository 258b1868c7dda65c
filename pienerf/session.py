"""An interactive simulation session: scene → density → particles → Q-GMLS model → solver, with the user's
controls, material changes, re-sampling, cuts and previews (PIE-NeRF §5). The viewer (``apps.demo``) and the
scripted renders (``apps.render``) both drive a :class:`Simulation`.

Previews come from render backends behind one small interface, :class:`RenderBackend`
(``render(q, cameras, view) -> Frame``):

* ``"mesh"``: the scene's mesh carried by the Q-GMLS displacement field, x(X) = X + Σ_s N_s(X) q_s (Eq. 9),
  whose shape functions at the rest vertices are precomputed once; each frame moves the vertices, refits the
  BVH and shades RGBA + depth with a shadow ray onto a ground plane (:func:`kernels.raycast.shade`).
* ``"particles"``: the deformed particles splatted as discs with the colour of the nearest mesh vertex.

* ``"nerf"``: a NeRF of the scene rendered by quadratic (or linear) ray warping, Eq. 19–21
  (:class:`pienerf.nerf_backend.NerfRenderBackend`), added by :meth:`Simulation.add_nerf_render` from a trained
  field, e.g. :func:`pienerf.nerf_backend.scene_nerf` of an embedded scene.

A scene may also be a trained NeRF checkpoint (``scene="path/to/ngp.pt"``, :func:`pienerf.train.save_checkpoint`):
the body is then sampled from the NeRF's solid (:class:`pienerf.nerf_backend.NerfSceneDensity`), picking and the
mesh preview use a blocky surface extracted from it (:func:`pienerf.nerf_backend.nerf_proxy_mesh`), and the
``"nerf"`` mode is there from the start. Backends that hold the discretised body (a ``rebind(model)`` method) follow
it through re-sampling and cuts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import NamedTuple, Protocol

import torch

from kernels import backend
from kernels.raycast import MeshBVH, shade
from pienerf.cut import CutPlane
from pienerf.data import Cameras
from pienerf.materials import MATERIAL_MODELS, Material
from pienerf.model import DiscretizationConfig, QGMLSModel
from pienerf.picking import DragController, Interaction, PickHit, PickSurface
from pienerf.reports import TimeBreakdown
from pienerf.sampling import poisson_disk_sample
from pienerf.scenes import LIGHT_DIRECTION, SCENES, scene_density, scene_mesh
from pienerf.solver import PlaneCollider, SolverConfig, SolverQGMLS, SphereCollider, StateQGMLS, StepReport

__all__ = [
    "SCENE_SETUPS",
    "Frame",
    "MeshRenderBackend",
    "ParticleRenderBackend",
    "RenderBackend",
    "SceneSetup",
    "Simulation",
    "SimulationConfig",
    "look_at_cameras",
    "orbit_cameras",
    "project_state",
]

Progress = Callable[[str, float], None]
"""Progress callback: ``(stage, fraction in [0, 1])``."""


@dataclass(frozen=True)
class SceneSetup:
    """Defaults of an embedded scene.

    Attributes:
        material: the body's material.
        kernel_count: Q-GMLS kernels n.
        particle_radius: r̄ of the Poisson-disk sampling (m).
        pins: boxes ``(lo, hi)`` (m, rest space) whose particles are pinned where they rest.
    """

    material: Material
    kernel_count: int
    particle_radius: float
    pins: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()


SCENE_SETUPS: dict[str, SceneSetup] = {
    "plant": SceneSetup(Material("neo_hookean", 2.0e4, 0.3, 500.0), 16, 0.03, (((-1, -1, -1), (1, 0.3, 1)),)),
    "teapot": SceneSetup(Material("neo_hookean", 1.0e5, 0.3, 1000.0), 16, 0.02, (((-1, -1, -1), (1, 1, 0.27)),)),
    "jelly": SceneSetup(Material("neo_hookean", 1.0e4, 0.45, 1100.0), 16, 0.05),
    "cloth": SceneSetup(Material("neo_hookean", 1.0e5, 0.3, 300.0), 24, 0.025),
    "sculpture": SceneSetup(Material("neo_hookean", 1.0e6, 0.3, 2000.0), 16, 0.04),
}
"""Defaults per embedded scene: the plant's pot and the teapot's body are pinned, so leaves and rod move."""

_GENERIC_SETUP = SceneSetup(Material("neo_hookean", 5.0e4, 0.3, 1000.0), 16, 0.0)


@dataclass(frozen=True)
class SimulationConfig:
    """A session's settings; ``None`` fields take the scene's :data:`SCENE_SETUPS` default.

    Attributes:
        scene: an embedded scene name (:data:`pienerf.scenes.SCENES`) or the path of a watertight mesh (m).
        material: the body's material.
        kernel_count: Q-GMLS kernels n.
        particle_radius: r̄ of the Poisson-disk sampling (m); for a mesh path, 1/40 of its largest extent.
        order: shape-function order, ``"quadratic"`` (Q-GMLS) or ``"linear"``/``"affine"`` for comparison.
        lloyd_iterations: Lloyd steps of the kernels and the integrator points.
        dt: time step h (s).
        gravity: acceleration of gravity (m/s²).
        rayleigh_alpha: mass-proportional damping α (1/s).
        rayleigh_beta: stiffness-proportional damping β (s).
        newton_iterations: most Newton iterations per step.
        floor: a ground plane collider at y = 0 (and the ground of the mesh preview).
        colliders: further colliders.
        default_pins: pin the scene's default pin boxes at reset.
        drag_stiffness: k of the drag spring (N/m); ``None`` → Young's modulus × 0.05 m.
        drag_damping: c of the drag damper (N·s/m); ``None`` → k × 0.1 s.
        max_acceleration: a_max of the drag (m/s²).
        pin_stiffness: stiffness of each pin spring (N/m); ``None`` → Young's modulus × r̄ × 20.
        seed: seed of the particle sampling.
        cuts: planes the body is cut along (rest space).
        nerf_solid_resolution: for a NeRF checkpoint scene, cells along the longest edge of the grid on which its
            solid and proxy mesh are found (:class:`pienerf.nerf_backend.NerfSceneDensity`).
    """

    scene: str = "plant"
    material: Material | None = None
    kernel_count: int | None = None
    particle_radius: float | None = None
    order: str = "quadratic"
    lloyd_iterations: int = 2
    dt: float = 1.0 / 30.0
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    rayleigh_alpha: float = 2.0
    rayleigh_beta: float = 0.0
    newton_iterations: int = 2
    floor: bool = True
    colliders: tuple[PlaneCollider | SphereCollider, ...] = ()
    default_pins: bool = True
    drag_stiffness: float | None = None
    drag_damping: float | None = None
    max_acceleration: float = 30.0
    pin_stiffness: float | None = None
    seed: int = 0
    cuts: tuple[CutPlane, ...] = field(default_factory=tuple)
    nerf_solid_resolution: int = 96

    def __post_init__(self):
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"dt must be a finite positive number of seconds, got {self.dt!r}")
        if self.particle_radius is not None and not (0 < self.particle_radius < math.inf):
            raise ValueError(f"particle_radius must be a positive length in metres, got {self.particle_radius!r}")
        if self.scene not in SCENES and not Path(self.scene).is_file():
            raise ValueError(
                f"unknown scene {self.scene!r}: use one of {', '.join(SCENES)}, a mesh file path or a "
                "trained NeRF checkpoint (.pt)"
            )


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
    """Pinhole cameras at ``positions [N, 3]`` looking at ``targets [N, 3]`` (m), y up, OpenGL axes."""
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


class MeshRenderBackend:
    """The scene mesh deformed by the Q-GMLS field, ray traced with shadows onto a ground plane.

    Args:
        model: the discretised body.
        vertices: ``[V, 3]`` rest vertices (m).
        faces: ``[F, 3]`` vertex indices.
        colors: ``[V, 3]`` albedo in [0, 1].
        ground_height: y of the ground plane (m), or ``None`` for none.
        ground_color: albedo of the ground.
    """

    def __init__(
        self,
        model: QGMLSModel,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        colors: torch.Tensor,
        ground_height: float | None = 0.0,
        ground_color=(0.82, 0.82, 0.8),
    ):
        device = backend.torch_device()
        self.handle = model.handle(vertices)
        self.body_vertices = vertices.shape[0]
        vertices, faces, colors = vertices.float(), faces.long(), colors.float()
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

    def deform(self, q: torch.Tensor) -> torch.Tensor:
        """Move the body's vertices to x(X) at ``q`` (Eq. 9) and refit the BVH; returns the ``[V, 3]`` vertices."""
        self._vertices[: self.body_vertices] = self.handle.positions(q).to(self._vertices)
        self.bvh.refit(self._vertices)
        return self._vertices[: self.body_vertices]

    def surface(self) -> PickSurface:
        """The deformed mesh to pick on (kept current by :meth:`deform`)."""
        return PickSurface(self.bvh, self.rest_vertices, self.body_vertices)

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
        c2w = cameras.c2w[view].cpu()
        local = (x - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame, looking down −z
        z = -local[:, 2]
        front = z > 1e-3
        u = cameras.fx[view] * local[:, 0] / z.clamp_min(1e-3) + cameras.cx[view]
        v = -cameras.fy[view] * local[:, 1] / z.clamp_min(1e-3) + cameras.cy[view]
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


def project_state(source: QGMLSModel, target: QGMLSModel, state: StateQGMLS) -> StateQGMLS:
    """Carry a state onto another discretisation of the same particles: q' minimises
    Σ_p V_p ‖Σ_s N'_s(X_p) q'_s − u_p‖², u_p the displacement of particle p under ``state`` (and alike for q̇)."""
    rows = torch.zeros(target.position.shape[0], target.shape_count, dtype=torch.float64, device=target.device)
    rows.scatter_add_(1, target.particles.index, target.particles.value)
    weight = target.volume.sqrt()[:, None]
    moved = [
        source.particles.positions(state.q) - source.position,
        source.particles.positions(state.qd) - source.position,
    ]
    solution = torch.linalg.lstsq(weight * rows, torch.cat([weight * m for m in moved], dim=1)).solution
    return StateQGMLS(solution[:, :3].contiguous(), solution[:, 3:].contiguous(), state.time)


class Simulation:
    """A running simulation of one scene, with the user's controls and previews.

    Args:
        config: the session's settings.
        progress: called with ``(stage, fraction)`` while the body is discretised.
    """

    def __init__(self, config: SimulationConfig = SimulationConfig(), progress: Progress | None = None):
        backend.init()
        self.config = config
        setup = SCENE_SETUPS.get(config.scene, _GENERIC_SETUP)
        self.material = config.material or setup.material
        self.setup = setup
        self._progress(progress, "loading scene", 0.0)
        self._load_scene()
        self.render_backends: dict[str, RenderBackend] = {}
        self.breakdown = TimeBreakdown()
        self.last_report = StepReport()
        self.particle_radius = config.particle_radius or setup.particle_radius or self._extent / 40.0
        self.discretization = DiscretizationConfig(
            kernel_count=config.kernel_count or setup.kernel_count,
            order=config.order,
            kernel_lloyd_iterations=config.lloyd_iterations,
            ip_lloyd_iterations=config.lloyd_iterations,
            cuts=tuple(config.cuts),
        )
        self._progress(progress, "sampling particles", 0.1)
        self.particles = poisson_disk_sample(self.density, self.particle_radius, seed=config.seed)
        self._build(progress)
        self.reset()

    # -- building ------------------------------------------------------------------------------

    @staticmethod
    def _progress(progress: Progress | None, stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    def _load_scene(self) -> None:
        name = self.config.scene
        self.nerf = None
        if name not in SCENES and Path(name).suffix == ".pt":
            from pienerf.nerf_backend import NerfSceneDensity, nerf_proxy_mesh
            from pienerf.train import load_checkpoint

            self.nerf = load_checkpoint(name)
            self.density = NerfSceneDensity(self.nerf.field, self.nerf.grid, self.config.nerf_solid_resolution)
            self.mesh_vertices, self.mesh_faces, self.mesh_colors = nerf_proxy_mesh(self.density)
        elif name in SCENES:
            mesh = scene_mesh(name)
            self.mesh_vertices, self.mesh_faces, self.mesh_colors = mesh.vertices, mesh.faces, mesh.colors
            self.density = scene_density(name)
        else:
            import trimesh

            from pienerf.density import MeshDensity

            loaded = trimesh.load(name, force="mesh")
            self.density = MeshDensity(loaded)
            self.mesh_vertices = torch.as_tensor(loaded.vertices, dtype=torch.float32)
            self.mesh_faces = torch.as_tensor(loaded.faces, dtype=torch.int32)
            colors = getattr(loaded.visual, "vertex_colors", None)
            if colors is not None and len(colors) == len(loaded.vertices):
                self.mesh_colors = torch.as_tensor(colors[:, :3], dtype=torch.float32) / 255.0
            else:
                self.mesh_colors = torch.full_like(self.mesh_vertices, 0.7)
        lo, hi = self.mesh_vertices.amin(0), self.mesh_vertices.amax(0)
        self._extent = float((hi - lo).max())
        self.centre = 0.5 * (lo + hi)

    def _build(self, progress: Progress | None) -> None:
        self._progress(progress, "placing kernels and integrator points", 0.4)
        device = backend.torch_device()
        self.model = QGMLSModel(
            self.particles.position.to(device), self.particles.volume.to(device), self.discretization, device=device
        )
        self._progress(progress, "building the solver", 0.8)
        self._make_solver()
        self.render_backends = {
            name: b
            for name, b in self.render_backends.items()
            if not isinstance(b, (MeshRenderBackend, ParticleRenderBackend))
        }
        for renderer in self.render_backends.values():
            if hasattr(renderer, "rebind"):
                renderer.rebind(self.model)
        if self.nerf is not None and "nerf" not in self.render_backends:
            self.add_nerf_render(self.nerf.field, self.nerf.grid)
        self._mesh_backend = MeshRenderBackend(
            self.model, self.mesh_vertices, self.mesh_faces, self.mesh_colors, 0.0 if self.config.floor else None
        )
        self.render_backends["mesh"] = self._mesh_backend
        self.particle_colors = self._nearest_vertex_colors(self.particles.position.cpu())
        self.render_backends["particles"] = ParticleRenderBackend(self.model, self.particle_colors)
        E = self.material.young_modulus
        stiffness = self.config.drag_stiffness or 0.05 * E
        drag = DragController(
            self.model,
            stiffness=stiffness,
            damping=self.config.drag_damping if self.config.drag_damping is not None else 0.1 * stiffness,
            max_acceleration=self.config.max_acceleration,
            density=self.material.density,
            surface=self._mesh_backend.surface(),
        )
        if getattr(self, "interaction", None) is None:
            pin_stiffness = self.config.pin_stiffness or 20.0 * E * self.particle_radius
            self.interaction = Interaction(drag, pin_stiffness=pin_stiffness)
        else:
            self.interaction.drag = drag
            self.interaction.bind(self.model)
        self._progress(progress, "ready", 1.0)

    def _make_solver(self) -> None:
        config = self.config
        solver_config = SolverConfig(
            gravity=tuple(config.gravity),
            rayleigh_alpha=config.rayleigh_alpha,
            rayleigh_beta=config.rayleigh_beta,
            newton_iterations=config.newton_iterations,
        )
        self.solver = SolverQGMLS(self.model, self.material, solver_config)

    def _nearest_vertex_colors(self, points: torch.Tensor) -> torch.Tensor:
        vertices = self.mesh_vertices.float()
        nearest = torch.cat([torch.cdist(chunk, vertices).argmin(1) for chunk in points.float().split(2048)])
        return self.mesh_colors[nearest]

    @property
    def colliders(self) -> list[PlaneCollider | SphereCollider]:
        """The floor (when on) and the configured colliders."""
        return ([PlaneCollider()] if self.config.floor else []) + list(self.config.colliders)

    # -- state and stepping --------------------------------------------------------------------

    def reset(self) -> None:
        """Back to the rest state; drag and forces cleared, the scene's default pins applied."""
        self.state = self.solver.rest_state()
        self.interaction.clear()
        if self.config.default_pins:
            for lo, hi in self.setup.pins:
                self.interaction.pin_region(lo, hi, self.state.q)

    def step(self, count: int = 1, colliders=None) -> StepReport:
        """Advance ``count`` steps of ``config.dt`` under the current controls; returns the last report."""
        colliders = self.colliders if colliders is None else colliders
        for _ in range(count):
            control = self.interaction.control(self.state.q, self.config.dt, colliders)
            self.last_report = self.solver.step(self.state, self.state, control, self.config.dt)
            self.breakdown.add(self.last_report)
        return self.last_report

    @property
    def time(self) -> float:
        """Simulated time (s)."""
        return self.state.time

    def set_material(
        self, young_modulus=None, poisson_ratio=None, density=None, model=None, damping=None, gravity=None
    ) -> Material:
        """Change material (E Pa, ν, ρ kg/m³, model name), Rayleigh α (1/s) or gravity (m/s², a 3-vector)."""
        if model is not None and model not in MATERIAL_MODELS:
            raise ValueError(f"unknown material model {model!r}; valid: {', '.join(MATERIAL_MODELS)}")
        changes = {
            k: v
            for k, v in (
                ("young_modulus", young_modulus),
                ("poisson_ratio", poisson_ratio),
                ("density", density),
                ("model", model),
            )
            if v is not None
        }
        material = replace(self.material, **changes)
        config_changes = {}
        if damping is not None:
            config_changes["rayleigh_alpha"] = float(damping)
        if gravity is not None:
            config_changes["gravity"] = tuple(float(g) for g in gravity)
        if config_changes:
            config = replace(self.config, **config_changes)
            SolverConfig(gravity=config.gravity, rayleigh_alpha=config.rayleigh_alpha)  # validates first
            self.config = config
            self.material = material
            self._make_solver()
        else:
            self.solver.set_material(material)
            self.material = material
        self.interaction.drag.density = material.density
        return material

    def resample(self, kernel_count: int, progress: Progress | None = None) -> None:
        """Re-discretise with ``kernel_count`` kernels, carrying the current state over (:func:`project_state`)."""
        self.discretization = replace(self.discretization, kernel_count=int(kernel_count), ip_count=None)
        self._rebuild(progress)

    def cut(self, plane: CutPlane, progress: Progress | None = None) -> None:
        """Cut the body along ``plane`` (rest space): kernels stop acting across it (Fig. 7)."""
        self.discretization = replace(self.discretization, cuts=(*self.discretization.cuts, plane))
        self._rebuild(progress)

    def cut_picked(self, normal=(0.0, 1.0, 0.0), progress: Progress | None = None) -> CutPlane:
        """Cut through the picked point with a plane of ``normal``."""
        plane = self.interaction.cut_through_picked(normal)
        self.cut(plane, progress)
        return plane

    def _rebuild(self, progress: Progress | None) -> None:
        old_model, old_state = self.model, self.state
        self._build(progress)
        self.state = project_state(old_model, self.model, old_state)

    # -- interaction ---------------------------------------------------------------------------

    def pick(self, ray_origin, ray_direction) -> PickHit | None:
        """Pick on the deformed mesh (else the particles) with a ray; starts a drag."""
        self._mesh_backend.deform(self.state.q)
        return self.interaction.drag.pick(ray_origin, ray_direction, self.state.q)

    def drag_to(self, ray_origin=None, ray_direction=None, *, target=None) -> torch.Tensor:
        """Move the drag target along a new ray at the picked depth, or to ``target`` (m)."""
        return self.interaction.drag.update(ray_origin, ray_direction, target=target)

    def release(self) -> None:
        self.interaction.drag.release()

    # -- output --------------------------------------------------------------------------------

    def set_render_backend(self, mode: str, renderer: RenderBackend) -> None:
        """Add a render mode (e.g. a warped-NeRF renderer) beside ``"mesh"`` and ``"particles"``."""
        self.render_backends[mode] = renderer

    def add_nerf_render(
        self,
        field,
        grid,
        name: str = "nerf",
        warp: str = "quadratic",
        downscale: int = 1,
        ground: bool | None = None,
        shadow_resolution: int = 64,
    ):
        """Add a warped-NeRF render mode (:class:`pienerf.nerf_backend.NerfRenderBackend`) of a trained field.

        Args:
            field, grid: the rest-space NeRF (:class:`pienerf.nerf.NGPField`) and its occupancy grid, in this
                scene's coordinates (metres, y up).
            name: the mode's name in :attr:`render_backends`.
            warp: ``"quadratic"`` (Eq. 20), ``"linear"`` or ``"rest"``.
            downscale: rendered pixels are blocks of this many camera pixels per side (the viewer changes it).
            ground: render the floor with the body's shadow (default: when the floor collider is on).
            shadow_resolution: texels per side of the ground's shadow map.

        Returns:
            The backend (its ``downscale`` and ``mode`` may be changed later).
        """
        from pienerf.nerf_backend import NerfRenderBackend
        from pienerf.render import GroundPlane

        plane = None
        if self.config.floor if ground is None else ground:
            plane = GroundPlane(height=0.0, extent=max(1.5, 2.0 * self._extent), shadow_resolution=shadow_resolution)
        renderer = NerfRenderBackend(field, grid, self.model, mode=warp, downscale=downscale, ground=plane)
        self.set_render_backend(name, renderer)
        return renderer

    def render(self, cameras: Cameras, view: int = 0, mode: str = "mesh", shadow: bool = False) -> Frame:
        """Render the current state in ``mode``; the time goes to the breakdown under ``"render (mode)"``."""
        if mode not in self.render_backends:
            raise ValueError(f"unknown render mode {mode!r}; available: {', '.join(self.render_backends)}")
        clock = time.perf_counter()
        frame = self.render_backends[mode].render(self.state.q, cameras, view, shadow)
        backend.synchronize()
        self.breakdown.add_phase(f"render ({mode})", time.perf_counter() - clock)
        return frame

    def deformed_mesh_vertices(self) -> torch.Tensor:
        """``[V, 3]`` float32 scene mesh vertices at the current state (m)."""
        return self._mesh_backend.deform(self.state.q).cpu()

    def particle_positions(self) -> torch.Tensor:
        """``[P, 3]`` deformed particle positions (m)."""
        return self.model.particles.positions(self.state.q).float().cpu()

    def integrator_positions(self) -> torch.Tensor:
        """``[K, 3]`` deformed integrator points (m); the first n are the kernel centres."""
        return self.model.ip_state(self.state.q)[0].float().cpu()

    def volume(self) -> float:
        """Volume of the deformed body (m³)."""
        return float(self.model.deformed_volume(self.state.q))

    def time_breakdown(self) -> dict:
        """Accumulated time per phase (:class:`pienerf.reports.TimeBreakdown`) as a dict."""
        return self.breakdown.to_dict()

    def summary(self) -> dict:
        """Scene, material and discretisation sizes."""
        return {
            "scene": self.config.scene,
            "material": asdict(self.material),
            "particle_radius_m": self.particle_radius,
            **self.model.summary(),
        }

    # -- verbs the viewers use (they never reach into :attr:`interaction`) -------------------------

    def grab(self, point) -> None:
        """Grab the material point ``point [3]`` (m, rest space) directly, as a scripted drag does."""
        self.interaction.drag.grab(point, self.state.q)

    @property
    def dragging(self) -> bool:
        """Whether a point is picked (a drag is on)."""
        return self.interaction.drag.dragging

    @property
    def drag_target(self) -> torch.Tensor | None:
        """``[3]`` the drag target (m), or ``None`` when nothing is picked."""
        return self.interaction.drag.target

    def pin_picked(self) -> None:
        """Pin the region around the picked point where it is now; releases the drag."""
        self.interaction.pin_picked(self.state.q)

    def push_picked(self, force=None) -> None:
        """A constant force ``force [3]`` (N) at the picked point, by default half the body's weight along -z;
        releases the drag."""
        if force is None:
            weight = self.material.density * float(self.model.volume.sum()) * 9.81
            force = (0.0, 0.0, -0.5 * weight)
        self.interaction.push_picked(force)

    @property
    def material_models(self) -> tuple[str, ...]:
        """Names of the material models the solver knows (for menus)."""
        return tuple(MATERIAL_MODELS)
