"""Mouse interaction with a Q-GMLS body: pick a material point with a ray, drag it with a clamped
spring-damper, pin it, push it with a constant force or cut the body through it (PIE-NeRF §5, Fig. 1, 5, 7).

Pure logic: no UI imports. A viewer turns its events into rays (``origin [3]``, ``direction [3]``, metres, world
frame) and calls :class:`DragController` / :class:`Interaction`; what these return is what the solver reads
(:class:`pienerf.sim.solver.PointTargets` and :class:`pienerf.sim.solver.PointForces`), mapped onto the generalized
coordinates by f_q = Jᵀ f (Eq. 9).

The drag is an implicit spring-damper between the picked material point x and the target t,

    f = k (t − x) − c ẋ,      ẋ = (x − x_n) / h  (implicit Euler),

which equals a single zero-rest-length spring of stiffness k' = k + c/h toward t' = (k t + (c/h) x_n) / k'
(:func:`spring_damper_target`), so the solver treats it implicitly and it stays stable for any k, c and h. The
spring is clamped so that the picked point's acceleration at the start of the step stays below ``a_max``: a force
f at the point accelerates it by a = w f, w = J M⁻¹ Jᵀ the inverse effective mass (1/kg) of the point
(:func:`inverse_effective_mass`), so the target is pulled toward x_n until k ‖t − x_n‖ w ≤ a_max
(:func:`clamp_target`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from kernels import backend
from kernels.raycast import MeshBVH
from pienerf.sim.cut import CutPlane
from pienerf.sim.model import PointHandle, QGMLSModel
from pienerf.sim.settings import setting
from pienerf.sim.solver import PointForces, PointTargets, QGMLSControl

__all__ = [
    "DragConfig",
    "DragController",
    "Interaction",
    "PickHit",
    "PickSurface",
    "clamp_target",
    "inverse_effective_mass",
    "ray_particle_pick",
    "spring_damper_target",
]


@dataclass(frozen=True)
class PickHit:
    """A picked material point.

    Attributes:
        rest: ``[3]`` float64 rest-space position X (m): the material point that stays picked as the body moves.
        world: ``[3]`` float64 deformed position x(X) at pick time (m).
        distance: distance from the ray origin to ``world`` along the unit ray (m).
        particle: index of the picked particle, or −1 when the hit came from the surface mesh.
    """

    rest: torch.Tensor
    world: torch.Tensor
    distance: float
    particle: int


class PickSurface:
    """The body's own surface to pick on: its rest mesh deformed by the model (Eq. 9), with a BVH refitted to q.

    Independent of what the viewer draws (a mesh, the particles or a warped NeRF): built from the scene mesh and the
    discretised body, refitted only when a pick asks for a new q.

    Args:
        model: the discretised body whose field moves the vertices.
        vertices: ``[V, 3]`` rest vertices of the body's surface (m).
        faces: ``[F, 3]`` vertex indices.

    Attributes:
        rest_vertices: ``[V, 3]`` float64 rest positions (m) on the CPU, the order of ``vertices``.
        bvh: :class:`kernels.raycast.MeshBVH` of the surface at the last q given to :meth:`at`.
    """

    def __init__(self, model: QGMLSModel, vertices: torch.Tensor, faces: torch.Tensor):
        vertices = torch.as_tensor(vertices)
        faces = torch.as_tensor(faces)
        if vertices.dim() != 2 or vertices.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
            raise ValueError(
                f"a pick surface needs vertices [V, 3] and faces [F, 3], got {tuple(vertices.shape)} and "
                f"{tuple(faces.shape)}: pass the scene mesh's rest vertices and triangles"
            )
        device = backend.torch_device()
        self.rest_vertices = vertices.detach().double().cpu()
        self.handle: PointHandle = model.handle(self.rest_vertices)
        self.bvh = MeshBVH(self.rest_vertices.float().to(device), faces.to(device=device, dtype=torch.int32))
        self._q: torch.Tensor | None = None

    def at(self, q: torch.Tensor):
        """The BVH with the vertices at x(X) for ``q [nT, 3]`` (refitted unless q is the last one's)."""
        if self._q is None or self._q.shape != q.shape or not torch.equal(self._q, q.detach()):
            self.bvh.refit(self.handle.positions(q).to(self.bvh.vertices))
            self._q = q.detach().clone()
        return self.bvh


def _unit(vector: torch.Tensor, what: str) -> torch.Tensor:
    norm = float(vector.norm())
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{what} must be a finite non-zero 3-vector, got {vector.tolist()}")
    return vector / norm


def _vec3(value, what: str) -> torch.Tensor:
    vector = torch.as_tensor(value, dtype=torch.float64).detach().cpu().reshape(-1)
    if vector.shape != (3,) or not bool(torch.isfinite(vector).all()):
        raise ValueError(f"{what} must be 3 finite numbers (x, y, z), got {value!r}")
    return vector


def ray_particle_pick(
    origin: torch.Tensor, direction: torch.Tensor, points: torch.Tensor, radius: float
) -> tuple[int, float] | None:
    """The point nearest to the ray origin among those within ``radius`` of the ray.

    A point p is a candidate when its distance to the ray, ‖(p − o) − ((p − o)·d̂) d̂‖, is below ``radius`` and it
    lies in front of the origin ((p − o)·d̂ > 0).

    Args:
        origin: ``[3]`` ray origin (m).
        direction: ``[3]`` ray direction (normalised here).
        points: ``[P, 3]`` candidate positions (m).
        radius: pick radius (m).

    Returns:
        ``(index, t)`` with t the distance along the unit ray to the point's projection (m), or ``None``.
    """
    origin = _vec3(origin, "ray origin").to(points)
    direction = _unit(_vec3(direction, "ray direction"), "ray direction").to(points)
    offset = points - origin
    t = offset @ direction
    distance = (offset - t[:, None] * direction).norm(dim=1)
    candidate = (distance < radius) & (t > 0)
    if not bool(candidate.any()):
        return None
    index = int(torch.where(candidate, t, torch.full_like(t, math.inf)).argmin())
    return index, float(t[index])


def inverse_effective_mass(model: QGMLSModel, handle: PointHandle, density: float) -> torch.Tensor:
    """Inverse effective mass w = N M⁻¹ Nᵀ (1/kg) of material points: a force f (N) applied at the point
    alone accelerates it by a = w f (m/s²) at the instant it is applied.

    The mass matrix is scalar per component (Eq. 11), so the 3×3 block J M⁻¹ Jᵀ is w I₃ with N the ``[nT]`` row of
    shape values of the point and M = ρ M₁ (``model.mass`` is per unit density).

    Args:
        model: the discretised body.
        handle: the points (:meth:`QGMLSModel.handle`), M of them.
        density: ρ (kg/m³).

    Returns:
        ``[M]`` float64 w per point (1/kg).
    """
    rows = torch.zeros(handle.rest.shape[0], model.shape_count, dtype=torch.float64, device=model.device)
    rows.scatter_add_(1, handle.index, handle.value)
    L, info = torch.linalg.cholesky_ex(model.mass)
    if int(info) != 0:
        shift = 1e-12 * model.mass.diagonal().mean()
        L = torch.linalg.cholesky(model.mass + shift * torch.eye(model.shape_count, dtype=torch.float64,
                                                                  device=model.device))
    solved = torch.cholesky_solve(rows.t(), L)  # M₁⁻¹ Nᵀ, [nT, M]
    return (rows * solved.t()).sum(1) / density


def clamp_target(target: torch.Tensor, position: torch.Tensor, stiffness: float, inverse_mass: torch.Tensor,
                 max_acceleration: float) -> torch.Tensor:
    """Pull spring targets toward their points so the spring accelerates no point by more than ``a_max``.

    The spring force k (t − x) accelerates its point by w k ‖t − x‖ (see :func:`inverse_effective_mass`), so

        t̂ = x + (t − x) · min(1, a_max / (w k ‖t − x‖)).

    Args:
        target: ``[M, 3]`` spring targets t (m).
        position: ``[M, 3]`` current point positions x (m).
        stiffness: k (N/m).
        inverse_mass: ``[M]`` w (1/kg).
        max_acceleration: a_max (m/s²); ``inf`` disables the clamp.

    Returns:
        ``[M, 3]`` clamped targets t̂ (m).
    """
    extension = target - position
    length = extension.norm(dim=1)
    # ‖t − x‖ overflows past ~1e154 m; scaled by its largest component it doesn't, so a far target clamps as a near
    # one does instead of leaving the point where it is (finite lengths keep the plain norm, bit for bit).
    scale = extension.abs().amax(dim=1).clamp_min(1e-300)
    length = torch.where(torch.isfinite(length), length, scale * (extension / scale[:, None]).norm(dim=1))
    length = length.clamp_min(1e-300)
    allowed = max_acceleration / (inverse_mass * stiffness)
    return position + extension * (allowed / length).clamp(max=1.0)[:, None]


def spring_damper_target(target: torch.Tensor, previous: torch.Tensor, stiffness: float, damping: float,
                         dt: float) -> tuple[torch.Tensor, float]:
    """A spring-damper under implicit Euler as one zero-rest-length spring.

    k (t − x) − c (x − x_n)/h = k' (t' − x)  with  k' = k + c/h,  t' = (k t + (c/h) x_n) / k'.

    Args:
        target: ``[M, 3]`` spring targets t (m).
        previous: ``[M, 3]`` positions x_n at the start of the step (m).
        stiffness: k (N/m).
        damping: c (N·s/m).
        dt: step h (s).

    Returns:
        ``(t' [M, 3], k')``.
    """
    rate = damping / dt
    combined = stiffness + rate
    return (stiffness * target + rate * previous) / combined, combined


@dataclass(frozen=True)
class DragConfig:
    """The drag spring of an interactive session, scaled to the body's stiffness unless given.

    Attributes:
        stiffness: k of the drag spring (N/m); ``None`` → Young's modulus × 0.05 m.
        damping: c of the drag damper (N·s/m); ``None`` → k × 0.1 s.
        max_acceleration: a_max of the drag (m/s²), the largest acceleration the spring may give the picked point.
            It only guards against a wild jump of the target: a plant leaf's effective mass is about 0.1 kg, so a clamp
            near g would cap the pull at a few newtons and a body stiff enough to stand would not follow the mouse.
    """

    stiffness: float | None = setting(None, unit="N/m", low=0.0, high=1e12, low_open=True, doc="drag spring k")
    damping: float | None = setting(None, unit="N·s/m", low=0.0, high=1e12, doc="drag damper c")
    max_acceleration: float = setting(1.0e5, unit="m/s²", low=0.0, high=1e6, low_open=True, doc="drag a_max")

    def __post_init__(self):
        if self.stiffness is not None and not (0 < self.stiffness < math.inf):
            raise ValueError(f"drag stiffness must be a finite number > 0 N/m (or None), got {self.stiffness!r}")
        if self.damping is not None and not (0 <= self.damping < math.inf):
            raise ValueError(f"drag damping must be a finite number >= 0 N·s/m (or None), got {self.damping!r}")
        if not self.max_acceleration > 0:
            raise ValueError(f"drag max_acceleration must be > 0 m/s², got {self.max_acceleration!r}")

    def spring(self, young_modulus: float) -> tuple[float, float]:
        """``(k N/m, c N·s/m)`` for a body of Young's modulus ``young_modulus`` (Pa)."""
        stiffness = 0.05 * young_modulus if self.stiffness is None else self.stiffness
        return stiffness, self.damping if self.damping is not None else 0.1 * stiffness


class DragController:
    """Pick a material point with a ray and drag it toward a target with a clamped spring-damper.

    Args:
        model: the discretised body.
        stiffness: spring stiffness k (N/m).
        damping: damper coefficient c (N·s/m).
        max_acceleration: a_max (m/s²), largest acceleration the spring may give the picked point.
        density: ρ of the body (kg/m³), for the effective mass; update it with the material.
        pick_radius: particles within this distance of the ray can be picked (m); default 1.5 times the median
            particle spacing V^(1/3).
        surface: optional :class:`PickSurface` of the body to pick on first (the particles are the fallback).
    """

    def __init__(
        self,
        model: QGMLSModel,
        stiffness: float = 1.0e3,
        damping: float = 10.0,
        max_acceleration: float = 50.0,
        density: float = 1000.0,
        pick_radius: float | None = None,
        surface: PickSurface | None = None,
    ):
        checks = {
            "stiffness": (stiffness, "a finite number > 0 N/m", lambda v: 0 < v < math.inf),
            "damping": (damping, "a finite number >= 0 N·s/m", lambda v: 0 <= v < math.inf),
            "max_acceleration": (max_acceleration, "a number > 0 m/s² (inf disables the clamp)", lambda v: v > 0),
            "density": (density, "a finite number > 0 kg/m³", lambda v: 0 < v < math.inf),
        }
        for name, (value, requirement, valid) in checks.items():
            if not (isinstance(value, (int, float)) and valid(value)):
                raise ValueError(f"drag {name} must be {requirement}, got {value!r}")
        self.stiffness = float(stiffness)
        self.damping = float(damping)
        self.max_acceleration = float(max_acceleration)
        self.density = float(density)
        self.surface = surface
        self.bind(model, pick_radius)

    def bind(self, model: QGMLSModel, pick_radius: float | None = None) -> None:
        """Use another discretisation of the body (after a resample or a cut); releases any drag."""
        self.model = model
        spacing = float(model.volume.pow(1.0 / 3.0).median())
        self.pick_radius = float(pick_radius) if pick_radius is not None else 1.5 * spacing
        self.release()

    @property
    def dragging(self) -> bool:
        """Whether a point is picked."""
        return self.hit is not None

    def pick(self, ray_origin, ray_direction, q: torch.Tensor) -> PickHit | None:
        """Pick the first surface hit of the ray, else the particle nearest the origin within the pick radius.

        Args:
            ray_origin: ``[3]`` (m).
            ray_direction: ``[3]`` (normalised here).
            q: ``[nT, 3]`` current generalized coordinates.

        Returns:
            The :class:`PickHit`, which starts a drag with the target at the picked point, or ``None`` (a miss
            releases any drag).
        """
        origin = _vec3(ray_origin, "ray origin")
        direction = _unit(_vec3(ray_direction, "ray direction"), "ray direction")
        hit = self._pick_surface(origin, direction, q) if self.surface is not None else None
        if hit is None:
            world = self.model.particles.positions(q).cpu()
            found = ray_particle_pick(origin, direction, world, self.pick_radius)
            if found is not None:
                index, _ = found
                point = world[index]
                hit = PickHit(self.model.position[index].cpu(), point, float((point - origin).norm()), index)
        if hit is None:
            self.release()
            return None
        return self._start(hit)

    def grab(self, rest_point, q: torch.Tensor) -> PickHit:
        """Pick the material point ``rest_point [3]`` (m, rest space) directly, as a script does."""
        rest = _vec3(rest_point, "grabbed point")
        world = self.model.handle(rest).positions(q)[0].cpu()
        return self._start(PickHit(rest, world, 0.0, -1))

    def _start(self, hit: PickHit) -> PickHit:
        self.release()
        self.hit = hit
        self.handle = self.model.handle(hit.rest)
        self.inverse_mass = inverse_effective_mass(self.model, self.handle, self.density)
        self.target = hit.world.clone()
        return hit

    def _pick_surface(self, origin: torch.Tensor, direction: torch.Tensor, q: torch.Tensor) -> PickHit | None:
        bvh = self.surface.at(q)
        device = bvh.vertices.device
        hits = bvh.cast(origin[None].float().to(device), direction[None].float().to(device))
        face = int(hits.face[0])
        if face < 0:
            return None
        corners = bvh.faces[face].long().cpu()
        b1, b2 = (float(v) for v in hits.bary[0])
        weights = torch.tensor([1.0 - b1 - b2, b1, b2], dtype=torch.float64)
        rest = weights @ self.surface.rest_vertices[corners]
        world = origin + float(hits.t[0]) * direction
        return PickHit(rest, world, float(hits.t[0]), -1)

    def update(self, ray_origin=None, ray_direction=None, *, target=None) -> torch.Tensor:
        """Move the drag target: onto a new camera ray at the picked point's depth, or to a given point.

        Args:
            ray_origin, ray_direction: the mouse ray; the target is origin + s d̂ with s the distance from the ray
                origin to the picked point when it was picked, so the point stays at its depth along the ray.
            target: ``[3]`` world target (m), instead of a ray.

        Returns:
            ``[3]`` the target (m).
        """
        if self.hit is None:
            raise RuntimeError("nothing is picked: call pick(ray_origin, ray_direction, q) before update()")
        if target is not None:
            self.target = _vec3(target, "drag target")
        elif ray_origin is not None and ray_direction is not None:
            origin = _vec3(ray_origin, "ray origin")
            direction = _unit(_vec3(ray_direction, "ray direction"), "ray direction")
            self.target = origin + self.hit.distance * direction  # any finite target: the spring clamps it
        else:
            raise ValueError("update needs a ray (ray_origin and ray_direction) or a target point")
        return self.target

    def release(self) -> None:
        """Let go of the picked point."""
        self.hit: PickHit | None = None
        self.handle: PointHandle | None = None
        self.inverse_mass: torch.Tensor | None = None
        self.target: torch.Tensor | None = None

    def control_terms(self, q: torch.Tensor, dt: float) -> list[PointTargets]:
        """The spring of this step: clamped (:func:`clamp_target`) and damped (:func:`spring_damper_target`).

        Args:
            q: ``[nT, 3]`` generalized coordinates at the start of the step.
            dt: step h (s).

        Returns:
            ``[]`` when nothing is picked, else one :class:`PointTargets` for the solver.
        """
        if self.hit is None:
            return []
        if not dt > 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        position = self.handle.positions(q)
        target = self.target.to(position)[None]
        clamped = clamp_target(target, position, self.stiffness, self.inverse_mass.to(position),
                               self.max_acceleration)
        spring_target, spring_stiffness = spring_damper_target(clamped, position, self.stiffness, self.damping, dt)
        return [PointTargets(self.handle, spring_target, spring_stiffness)]

    def position(self, q: torch.Tensor) -> torch.Tensor | None:
        """``[3]`` current position of the picked point (m), or ``None``."""
        return None if self.handle is None else self.handle.positions(q)[0]


@dataclass
class _Pin:
    rest: torch.Tensor  # [M, 3]
    target: torch.Tensor  # [M, 3]
    handle: PointHandle | None = None


@dataclass
class _Force:
    rest: torch.Tensor  # [1, 3]
    force: torch.Tensor  # [1, 3]
    handle: PointHandle | None = None


@dataclass
class Interaction:
    """Everything the user does to the body: the drag, pins, constant forces and cuts through the picked point.

    Args:
        drag: the :class:`DragController`.
        pin_stiffness: stiffness of each pin spring (N/m).
    """

    drag: DragController
    pin_stiffness: float = 1.0e5
    pins: list[_Pin] = field(default_factory=list)
    forces: list[_Force] = field(default_factory=list)

    def __post_init__(self):
        if not (self.pin_stiffness > 0 and math.isfinite(self.pin_stiffness)):
            raise ValueError(f"pin_stiffness must be a finite number > 0 N/m, got {self.pin_stiffness!r}")

    @property
    def model(self) -> QGMLSModel:
        return self.drag.model

    def bind(self, model: QGMLSModel) -> None:
        """Re-attach pins and forces to a new discretisation (they are stored at rest positions); drops the drag."""
        self.drag.bind(model)
        for item in (*self.pins, *self.forces):
            item.handle = model.handle(item.rest)

    def pin(self, rest_points: torch.Tensor, q: torch.Tensor) -> int:
        """Pin material points ``[M, 3]`` (rest, m) where they are now (x(X) at ``q``); returns M."""
        rest = torch.as_tensor(rest_points, dtype=torch.float64, device=self.model.device).reshape(-1, 3)
        if rest.shape[0] == 0:
            raise ValueError("nothing to pin: the selection holds no material point; widen the region")
        handle = self.model.handle(rest)
        self.pins.append(_Pin(rest, handle.positions(q).clone(), handle))
        return rest.shape[0]

    def pin_region(self, lo, hi, q: torch.Tensor) -> int:
        """Pin every particle whose rest position lies in the box ``[lo, hi]`` (m); returns how many."""
        lo = _vec3(lo, "pin box lower corner").to(self.model.position)
        hi = _vec3(hi, "pin box upper corner").to(self.model.position)
        inside = ((self.model.position >= lo) & (self.model.position <= hi)).all(1)
        if not bool(inside.any()):
            raise ValueError(f"no particle lies in the pin box {lo.tolist()} .. {hi.tolist()}; widen the box")
        return self.pin(self.model.position[inside], q)

    def pin_picked(self, q: torch.Tensor) -> int:
        """Pin the particles within the pick radius of the picked point (rest space) where they are now."""
        hit = self._require_hit("pin")
        near = (self.model.position - hit.rest.to(self.model.position)).norm(dim=1) <= self.drag.pick_radius
        points = self.model.position[near] if bool(near.any()) else hit.rest.to(self.model.position)[None]
        count = self.pin(points, q)
        self.drag.release()
        return count

    def add_force(self, rest_point, force) -> None:
        """A constant force ``force [3]`` (N) at the material point ``rest_point [3]`` (m)."""
        rest = _vec3(rest_point, "force point").to(self.model.position)[None]
        value = _vec3(force, "force").to(self.model.position)[None]
        self.forces.append(_Force(rest, value, self.model.handle(rest)))

    def push_picked(self, force) -> None:
        """A constant force ``force [3]`` (N) at the picked point; releases the drag."""
        hit = self._require_hit("push")
        self.add_force(hit.rest, force)
        self.drag.release()

    def cut_through_picked(self, normal) -> CutPlane:
        """A cut plane (rest space) through the picked point with ``normal [3]``; the caller re-discretises."""
        hit = self._require_hit("cut")
        normal = _unit(_vec3(normal, "cut normal"), "cut normal")
        return CutPlane(tuple(hit.rest.tolist()), tuple(normal.tolist()))

    def clear(self) -> None:
        """Remove pins and forces and release the drag."""
        self.pins.clear()
        self.forces.clear()
        self.drag.release()

    def control(self, q: torch.Tensor, dt: float, colliders=()) -> QGMLSControl:
        """What acts on the body this step: pins, the drag spring, constant forces, ``colliders``."""
        springs = [PointTargets(p.handle, p.target, self.pin_stiffness) for p in self.pins]
        springs += self.drag.control_terms(q, dt)
        forces = [PointForces(f.handle, f.force) for f in self.forces]
        return QGMLSControl(springs=springs, forces=forces, colliders=list(colliders))

    def _require_hit(self, action: str) -> PickHit:
        if self.drag.hit is None:
            raise RuntimeError(f"nothing is picked to {action}: click on the body first")
        return self.drag.hit
