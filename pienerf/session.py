"""An interactive simulation session: scene → density → particles → Q-GMLS model → solver, with the user's
controls, material changes, re-sampling, cuts and previews (PIE-NeRF §5). The viewer (``apps.demo``) and the
scripted renders (``apps.render``) both drive a :class:`Simulation`.

Previews come from the render backends of :mod:`pienerf.render.previews`: ``"mesh"`` and ``"particles"`` always, and
``"nerf"``, a NeRF of the scene warped by the body (Eq. 19–21), added by :meth:`Simulation.add_nerf_render` from a
trained field, e.g. :func:`pienerf.scenes.scene_nerf` of an embedded scene.

A scene may also be a trained NeRF checkpoint (``scene="path/to/ngp.pt"``, :func:`pienerf.nerf.save_checkpoint`):
the body is then sampled from the NeRF's solid (:class:`pienerf.nerf.solid.NerfSceneDensity`), picking and the
mesh preview use a blocky surface extracted from it (:func:`pienerf.nerf.solid.nerf_proxy_mesh`), and the
``"nerf"`` mode is there from the start. Backends that hold the discretised body (a ``rebind(model)`` method) follow
it through re-sampling and cuts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import torch

from kernels import backend
from pienerf.nerf.cameras import Cameras
from pienerf.nerf.solid import NerfSceneDensity, nerf_proxy_mesh
from pienerf.nerf.training import load_checkpoint
from pienerf.render.deformed import GroundPlane
from pienerf.render.previews import (
    Frame,
    MeshRenderBackend,
    NerfRenderBackend,
    ParticleRenderBackend,
    RenderBackend,
)
from pienerf.reports import TimeBreakdown
from pienerf.scenes import SCENES, scene_density, scene_mesh
from pienerf.sim.cut import CutPlane
from pienerf.sim.density import MeshDensity, load_mesh_file
from pienerf.sim.materials import MATERIAL_MODELS, Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.picking import DragConfig, DragController, Interaction, PickHit, PickSurface
from pienerf.sim.sampling import poisson_disk_sample
from pienerf.sim.settings import setting
from pienerf.sim.solver import (
    PlaneCollider,
    QGMLSState,
    QGMLSStepReport,
    SolverConfig,
    SolverQGMLS,
    SphereCollider,
)

__all__ = [
    "INTERACTIVE_DISCRETIZATION",
    "INTERACTIVE_SOLVER",
    "SCENE_SETUPS",
    "SceneSetup",
    "Simulation",
    "SimulationConfig",
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

    The plant is stiff (E = 1 MPa) so its stem carries its leaves instead of sinking to the ground, and its whole pot
    (y < 0.29 m, the pot's rim) is pinned, as PIE-NeRF's plant keeps its pot still: with only the pot's floor pinned
    a leaf dragged hard sheared and tilted the pot like rubber.
    """

    material: Material
    kernel_count: int
    particle_radius: float
    pins: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()


SCENE_SETUPS: dict[str, SceneSetup] = {
    "plant": SceneSetup(Material("neo_hookean", 1.0e6, 0.3, 500.0), 16, 0.03, (((-1, -1, -1), (1, 0.29, 1)),)),
    "teapot": SceneSetup(Material("neo_hookean", 1.0e5, 0.3, 1000.0), 16, 0.02, (((-1, -1, -1), (1, 1, 0.27)),)),
    "jelly": SceneSetup(Material("neo_hookean", 1.0e4, 0.45, 1100.0), 16, 0.05),
    "cloth": SceneSetup(Material("neo_hookean", 1.0e5, 0.3, 300.0), 24, 0.025),
    "sculpture": SceneSetup(Material("neo_hookean", 1.0e6, 0.3, 2000.0), 16, 0.04),
}
"""Defaults per embedded scene: the plant's pot and the teapot's body are pinned, so leaves and rod move."""

_GENERIC_SETUP = SceneSetup(Material("neo_hookean", 5.0e4, 0.3, 1000.0), 16, 0.0)


INTERACTIVE_SOLVER = SolverConfig(rayleigh_alpha=2.0, newton_iterations=1)
"""A session's solver defaults: some damping and one line-searched Newton iteration a step, so a frame stays
interactive; on the plant a second iteration changed a dragged leaf's path by less than a millimetre (soft bodies
such as the jelly move a little more slowly under one iteration than under two)."""

INTERACTIVE_DISCRETIZATION = DiscretizationConfig(kernel_lloyd_iterations=2, ip_lloyd_iterations=2)
"""A session's discretisation defaults (the kernel count comes from the scene): two Lloyd steps, so a re-sampling
stays quick."""


@dataclass(frozen=True)
class SimulationConfig:
    """A session's settings, composed of the solver's, the discretisation's and the drag's.

    :meth:`create` builds one from flat keyword settings (``kernel_count=6, rayleigh_alpha=1.0, ...``).

    Attributes:
        scene: an embedded scene name (:data:`pienerf.scenes.SCENES`), the path of a watertight mesh (m) or a
            trained NeRF checkpoint (``.pt``).
        material: the body's material; ``None`` → the scene's :data:`SCENE_SETUPS` default.
        particle_radius: r̄ of the Poisson-disk sampling (m); ``None`` → the scene's default, for a mesh path 1/40 of
            its largest extent.
        dt: time step h (s).
        solver: gravity, damping and Newton settings (:class:`pienerf.sim.solver.SolverConfig`).
        discretization: kernels, order, Lloyd steps and cuts (:class:`pienerf.sim.model.DiscretizationConfig`);
            ``None`` → :data:`INTERACTIVE_DISCRETIZATION` with the scene's kernel count.
        drag: the drag spring (:class:`pienerf.sim.picking.DragConfig`).
        floor: a ground plane collider at y = 0 (and the ground of the mesh preview).
        colliders: further colliders.
        default_pins: pin the scene's default pin boxes at reset.
        pin_stiffness: stiffness of each pin spring (N/m); ``None`` → Young's modulus × r̄ × 20.
        seed: seed of the particle sampling.
        nerf_solid_resolution: for a NeRF checkpoint scene, cells along the longest edge of the grid on which its
            solid and proxy mesh are found (:class:`pienerf.nerf.solid.NerfSceneDensity`).
        mesh_edge_fraction: the ``"mesh"`` preview splits the mesh's edges until each is shorter than this fraction
            of the smallest kernel support radius (the length over which the Q-GMLS field bends), so a bent thin
            part shows its bend (:func:`pienerf.render.split_long_edges`); ``None`` renders the scene's mesh as
            it is. :meth:`deformed_mesh_vertices` keeps the scene's vertices; picking uses the scene's mesh
            (:class:`pienerf.sim.picking.PickSurface`).
    """

    scene: str = "plant"
    material: Material | None = None
    particle_radius: float | None = setting(None, unit="m", low=0.0, high=10.0, low_open=True, doc="sampling r̄")
    dt: float = setting(1.0 / 30.0, unit="s", low=0.0, high=1.0, low_open=True, doc="time step h")
    solver: SolverConfig = INTERACTIVE_SOLVER
    discretization: DiscretizationConfig | None = None
    drag: DragConfig = DragConfig()
    floor: bool = True
    colliders: tuple[PlaneCollider | SphereCollider, ...] = ()
    default_pins: bool = True
    pin_stiffness: float | None = None
    seed: int = setting(0, low=0, high=2**32 - 1, doc="seed of the particle sampling")
    nerf_solid_resolution: int = 96
    mesh_edge_fraction: float | None = None

    def __post_init__(self):
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"dt must be a finite positive number of seconds, got {self.dt!r}")
        if self.pin_stiffness is not None and not (0 < self.pin_stiffness < math.inf):
            raise ValueError(f"pin_stiffness must be a finite positive N/m (or None), got {self.pin_stiffness!r}")
        if self.particle_radius is not None and not (0 < self.particle_radius < math.inf):
            raise ValueError(f"particle_radius must be a positive length in metres, got {self.particle_radius!r}")
        if self.mesh_edge_fraction is not None and not (0 < self.mesh_edge_fraction < math.inf):
            raise ValueError(
                f"mesh_edge_fraction must be a finite number > 0 (or None), got {self.mesh_edge_fraction!r}"
            )
        if self.scene not in SCENES and not Path(self.scene).is_file():
            raise ValueError(
                f"unknown scene {self.scene!r}: use one of {', '.join(SCENES)}, a mesh file path or a "
                "trained NeRF checkpoint (.pt)"
            )

    @property
    def setup(self) -> SceneSetup:
        """The scene's defaults (a generic body for a mesh or checkpoint path)."""
        return SCENE_SETUPS.get(self.scene, _GENERIC_SETUP)

    def body_discretization(self) -> DiscretizationConfig:
        """:attr:`discretization`, or the interactive defaults with the scene's kernel count."""
        if self.discretization is not None:
            return self.discretization
        return replace(INTERACTIVE_DISCRETIZATION, kernel_count=self.setup.kernel_count)

    @classmethod
    def create(cls, scene: str = "plant", **settings) -> SimulationConfig:
        """A config from flat keyword settings, each sent to the part that has the field.

        Keys are this class's fields, :class:`~pienerf.sim.solver.SolverConfig`'s, :class:`~pienerf.sim.model.
        DiscretizationConfig`'s, ``drag_`` + :class:`~pienerf.sim.picking.DragConfig`'s (``drag_stiffness``) and
        ``lloyd_iterations`` (both Lloyd counts). A setting of ``None`` keeps the default; the kernel count defaults to
        the scene's.

        Raises:
            ValueError: a key no part has.
        """
        own, solver, discretization, drag = {}, {}, {}, {}
        for key, value in settings.items():
            if value is None:
                continue
            if key == "lloyd_iterations":
                discretization.update(kernel_lloyd_iterations=value, ip_lloyd_iterations=value)
            elif key in _field_names(cls):
                own[key] = value
            elif key in _field_names(SolverConfig):
                solver[key] = value
            elif key in _field_names(DiscretizationConfig):
                discretization[key] = value
            elif key.startswith("drag_") and key[5:] in _field_names(DragConfig):
                drag[key[5:]] = value
            else:
                raise ValueError(
                    f"unknown simulation setting {key!r}; valid: lloyd_iterations, the fields of SimulationConfig, "
                    "SolverConfig and DiscretizationConfig, and drag_stiffness, drag_damping, drag_max_acceleration"
                )
        config = cls(scene=scene, **own)
        return replace(
            config,
            solver=replace(config.solver, **solver),
            drag=replace(config.drag, **drag),
            discretization=replace(config.body_discretization(), **discretization)
            if discretization
            else config.discretization,
        )


def _field_names(cls) -> set[str]:
    return {f.name for f in fields(cls)}


def project_state(source: QGMLSModel, target: QGMLSModel, state: QGMLSState) -> QGMLSState:
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
    return QGMLSState(solution[:, :3].contiguous(), solution[:, 3:].contiguous(), state.time)


class Simulation:
    """A running simulation of one scene, with the user's controls and previews.

    Args:
        config: the session's settings.
        progress: called with ``(stage, fraction)`` while the body is discretised.
    """

    def __init__(self, config: SimulationConfig = SimulationConfig(), progress: Progress | None = None):
        backend.init()
        self.config = config
        setup = config.setup
        self.material = config.material or setup.material
        self.setup = setup
        self._progress(progress, "loading scene", 0.0)
        self._load_scene()
        self.render_backends: dict[str, RenderBackend] = {}
        self.breakdown = TimeBreakdown()
        self.last_report = QGMLSStepReport()
        self.particle_radius = config.particle_radius or setup.particle_radius or self._extent / 40.0
        self.discretization = config.body_discretization()
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
            self.nerf = load_checkpoint(name)
            self.density = NerfSceneDensity(self.nerf.field, self.nerf.grid, self.config.nerf_solid_resolution)
            self.mesh_vertices, self.mesh_faces, self.mesh_colors = nerf_proxy_mesh(self.density)
        elif name in SCENES:
            mesh = scene_mesh(name)
            self.mesh_vertices, self.mesh_faces, self.mesh_colors = mesh.vertices, mesh.faces, mesh.colors
            self.density = scene_density(name)
        else:
            loaded = load_mesh_file(name)
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
        fraction = self.config.mesh_edge_fraction
        self._mesh_backend = MeshRenderBackend(
            self.model,
            self.mesh_vertices,
            self.mesh_faces,
            self.mesh_colors,
            0.0 if self.config.floor else None,
            max_edge=None if fraction is None else fraction * float(self.model.basis.support_radius.min()),
        )
        self.render_backends["mesh"] = self._mesh_backend
        self.particle_colors = self._nearest_vertex_colors(self.particles.position.cpu())
        self.render_backends["particles"] = ParticleRenderBackend(self.model, self.particle_colors)
        E = self.material.young_modulus
        stiffness, damping = self.config.drag.spring(E)
        drag = DragController(
            self.model,
            stiffness=stiffness,
            damping=damping,
            max_acceleration=self.config.drag.max_acceleration,
            density=self.material.density,
            surface=PickSurface(self.model, self.mesh_vertices, self.mesh_faces),
        )
        if getattr(self, "interaction", None) is None:
            pin_stiffness = self.config.pin_stiffness
            if pin_stiffness is None:
                pin_stiffness = 20.0 * E * self.particle_radius
            self.interaction = Interaction(drag, pin_stiffness=pin_stiffness)
        else:
            self.interaction.drag = drag
            self.interaction.bind(self.model)
        self._progress(progress, "ready", 1.0)

    def _make_solver(self) -> None:
        self.solver = SolverQGMLS(self.model, self.material, self.config.solver)

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
        self._spare: QGMLSState | None = None  # the other half of the double buffer, made at the first step
        self.interaction.clear()
        if self.config.default_pins:
            for lo, hi in self.setup.pins:
                self.interaction.pin_region(lo, hi, self.state.q)

    def step(self, count: int = 1, colliders=None) -> QGMLSStepReport:
        """Advance ``count`` steps of ``config.dt`` under the current controls; returns the last report.

        The state is double-buffered: each step reads :attr:`state` and writes the other buffer, and the two swap
        (so a tensor of :attr:`state` read before a step still holds the state before it)."""
        colliders = self.colliders if colliders is None else colliders
        for _ in range(count):
            spare = self._spare
            if spare is None or spare.q.shape != self.state.q.shape or spare.q.device != self.state.q.device:
                spare = QGMLSState(torch.empty_like(self.state.q), torch.empty_like(self.state.qd), self.state.time)
            control = self.interaction.control(self.state.q, self.config.dt, colliders)
            self.last_report = self.solver.step(self.state, spare, control, self.config.dt)
            self.state, self._spare = spare, self.state
            self.breakdown.add(self.last_report)
        return self.last_report

    def max_speed(self) -> float:
        """The largest particle speed of the current state (m/s): how still the body is."""
        velocity = self.model.particles.positions(self.state.qd) - self.model.particles.rest
        return float(velocity.norm(dim=1).max())

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
        solver_changes = {}
        if damping is not None:
            solver_changes["rayleigh_alpha"] = float(damping)
        if gravity is not None:
            solver_changes["gravity"] = tuple(float(g) for g in gravity)
        if solver_changes:
            config = replace(self.config, solver=replace(self.config.solver, **solver_changes))  # validates first
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
        """Pick on the body's surface (its scene mesh deformed by the model, else the particles) with a ray; starts a
        drag. What the viewer draws (mesh, particles or NeRF) plays no part."""
        return self.interaction.drag.pick(ray_origin, ray_direction, self.state.q)

    def drag_to(self, ray_origin=None, ray_direction=None, *, target=None) -> torch.Tensor:
        """Move the drag target along a new ray at the picked depth, or to ``target`` (m)."""
        return self.interaction.drag.update(ray_origin, ray_direction, target=target)

    def grab(self, point) -> None:
        """Start a drag at the material point nearest ``point [3]`` (m, rest space), as a scripted mouse does."""
        self.interaction.drag.grab(point, self.state.q)

    def release(self) -> None:
        """Let go of the dragged point."""
        self.interaction.drag.release()

    @property
    def dragging(self) -> bool:
        """Whether a point is picked and dragged."""
        return self.interaction.drag.dragging

    @property
    def drag_target(self) -> torch.Tensor | None:
        """``[3]`` where the drag spring pulls the picked point (m), or ``None`` when nothing is dragged."""
        return self.interaction.drag.target if self.dragging else None

    def pin_picked(self) -> int:
        """Pin the material around the picked point where it is now; returns how many particles."""
        return self.interaction.pin_picked(self.state.q)

    def push_picked(self, force=None) -> None:
        """A constant force at the picked point (N, ``[3]``); default half the body's weight along −z."""
        if force is None:
            weight = self.material.density * float(self.model.volume.sum()) * 9.81
            force = (0.0, 0.0, -0.5 * weight)
        self.interaction.push_picked(force)

    def pin_region(self, lo, hi) -> int:
        """Pin every particle resting in the box ``[lo, hi]`` (m) where it is now; returns how many."""
        return self.interaction.pin_region(lo, hi, self.state.q)

    def add_force(self, point, force) -> None:
        """A constant force ``force [3]`` (N) at the material point ``point [3]`` (m, rest space)."""
        self.interaction.add_force(point, force)

    def clear_forces(self) -> None:
        """Remove every constant force (pins and the drag stay)."""
        self.interaction.forces.clear()

    @property
    def material_models(self) -> tuple[str, ...]:
        """The material models the solver knows (:data:`pienerf.sim.materials.MATERIAL_MODELS`), for menus."""
        return tuple(MATERIAL_MODELS)

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
        """Add a warped-NeRF render mode (:class:`pienerf.render.previews.NerfRenderBackend`) of a trained field.

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
        plane = None
        if self.config.floor if ground is None else ground:
            plane = GroundPlane(height=0.0, extent=max(1.5, 2.0 * self._extent), shadow_resolution=shadow_resolution)
        renderer = NerfRenderBackend(field, grid, self.model, mode=warp, downscale=downscale, ground=plane)
        self.set_render_backend(name, renderer)
        return renderer

    def render(
        self, cameras: Cameras, view: int = 0, mode: str = "mesh", shadow: bool = False, downscale: int | None = None
    ) -> Frame:
        """Render the current state in ``mode``; the time goes to the breakdown under ``"render (mode)"``.

        ``downscale`` (a warped-NeRF mode only) renders blocks of that many camera pixels per side this once,
        instead of the backend's own setting."""
        if mode not in self.render_backends:
            raise ValueError(f"unknown render mode {mode!r}; available: {', '.join(self.render_backends)}")
        options = {} if downscale is None else {"downscale": downscale}
        if options and not isinstance(self.render_backends[mode], NerfRenderBackend):
            raise ValueError(f"render mode {mode!r} has no downscale; only warped-NeRF modes do")
        clock = time.perf_counter()
        frame = self.render_backends[mode].render(self.state.q, cameras, view, shadow, **options)
        backend.synchronize()
        self.breakdown.add_phase(f"render ({mode})", time.perf_counter() - clock)
        return frame

    def deformed_mesh_vertices(self) -> torch.Tensor:
        """``[V, 3]`` float32 scene mesh vertices at the current state (m), a new tensor the caller owns (the mesh
        backend deforms its vertices in place, so a view of them would change under the caller). With
        ``mesh_edge_fraction`` these are the leading vertices of the refined preview mesh: the scene's own, which
        :attr:`mesh_faces` index."""
        return self._mesh_backend.deform(self.state.q)[: self.mesh_vertices.shape[0]].to("cpu", copy=True)

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
