"""Mouse interaction with a garment: pick a vertex with a ray, drag it with a clamped spring-damper, pin it.

Pure logic, no UI: a viewer turns its events into rays (``origin [3]``, ``direction [3]``, metres, world frame) and
calls :class:`GarmentDrag`; what :meth:`GarmentDrag.springs` returns goes into the step's
:class:`~physavatar.cloth.solver.ClothControl` as springs, terms ``½ k ‖x_i − t‖²`` of the incremental potential,
so a drag or a pin never breaks the step's contact guarantees (the barrier and the CCD line search see them as any
other energy).

The drag has the semantics of the PIE-NeRF bodies' drag (:mod:`pienerf.sim.picking`): an implicit spring-damper
between the picked vertex x and the target t, ``f = k (t − x) − c ẋ`` with ``ẋ = (x − x_n) / h``, which equals one
zero-rest-length spring of stiffness ``k' = k + c / h`` toward ``t' = (k t + (c / h) x_n) / k'``; the target is first
pulled toward the vertex until the spring's force ``k ‖t − x_n‖`` is at most ``max_force``, so a wild jump of the
pointer cannot yank the garment through its own inertia. A pin is a stiff spring holding a vertex where it was
pinned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kernels import backend
from kernels.raycast import MeshBVH

__all__ = ["GarmentDrag", "GarmentPick"]

F64 = torch.float64


@dataclass(frozen=True)
class GarmentPick:
    """A picked garment vertex.

    Attributes:
        vertex: the garment vertex the drag pulls (the hit triangle's corner nearest the hit).
        world: ``[3]`` float64 the hit point (m) at pick time.
        distance: distance from the ray origin to ``world`` along the unit ray (m): the drag keeps this depth.
    """

    vertex: int
    world: torch.Tensor
    distance: float


def _vec3(value, what: str) -> torch.Tensor:
    vector = torch.as_tensor(value, dtype=F64).detach().cpu().reshape(-1)
    if vector.shape != (3,) or not bool(torch.isfinite(vector).all()):
        raise ValueError(f"{what} must be 3 finite numbers (x, y, z), got {value!r}")
    return vector


def _unit(value, what: str) -> torch.Tensor:
    vector = _vec3(value, what)
    norm = float(vector.norm())
    if norm == 0.0:
        raise ValueError(f"{what} must be a non-zero 3-vector, got {vector.tolist()}")
    return vector / norm


class GarmentDrag:
    """Pick a garment vertex with a ray, drag it toward a target with a clamped spring-damper, pin vertices.

    Args:
        faces: ``[F, 3]`` garment triangles.
        stiffness: drag spring ``k``, N/m.
        damping: drag damper ``c``, N·s/m.
        max_force: largest force of the drag spring, N (the target is pulled toward the vertex to hold it).
        pin_stiffness: stiffness of each pin's spring, N/m.

    Raises:
        ValueError: a non-positive or non-finite setting.
    """

    def __init__(self, faces: torch.Tensor, stiffness: float, damping: float, max_force: float, pin_stiffness: float):
        for name, value, low_open in (
            ("stiffness", stiffness, True),
            ("damping", damping, False),
            ("max_force", max_force, True),
            ("pin_stiffness", pin_stiffness, True),
        ):
            if not (
                isinstance(value, (int, float)) and math.isfinite(value) and (value > 0 or not low_open and value == 0)
            ):
                raise ValueError(f"drag {name} must be a finite number {'>' if low_open else '>='} 0, got {value!r}")
        self.faces = faces.detach().to(backend.torch_device(), torch.int32).contiguous()
        self.stiffness, self.damping = float(stiffness), float(damping)
        self.max_force, self.pin_stiffness = float(max_force), float(pin_stiffness)
        self._bvh: MeshBVH | None = None
        self.pins: dict[int, torch.Tensor] = {}  # vertex -> [3] float64 where it is held (m)
        self.release()

    @property
    def dragging(self) -> bool:
        """Whether a vertex is picked."""
        return self.hit is not None

    def pick(self, ray_origin, ray_direction, x: torch.Tensor) -> GarmentPick | None:
        """Pick the garment's first surface hit along the ray; starts a drag with the target at the hit point.

        Args:
            ray_origin: ``[3]`` (m).
            ray_direction: ``[3]`` (normalised here).
            x: ``[V, 3]`` the garment's vertices now (m).

        Returns:
            The :class:`GarmentPick`, or ``None`` (a miss releases any drag).
        """
        origin = _vec3(ray_origin, "ray origin")
        direction = _unit(ray_direction, "ray direction")
        points = x.detach().to(backend.torch_device(), torch.float32)
        if self._bvh is None or self._bvh.vertices.shape != points.shape:
            self._bvh = MeshBVH(points, self.faces)
        else:
            self._bvh.refit(points)
        device = points.device
        hits = self._bvh.cast(origin[None].float().to(device), direction[None].float().to(device))
        face = int(hits.face[0])
        if face < 0:
            self.release()
            return None
        b1, b2 = (float(b) for b in hits.bary[0])
        corner = max(range(3), key=lambda k: (1.0 - b1 - b2, b1, b2)[k])
        vertex = int(self.faces[face, corner])
        distance = float(hits.t[0])
        return self._start(GarmentPick(vertex, origin + distance * direction, distance))

    def grab(self, vertex: int, x: torch.Tensor) -> GarmentPick:
        """Pick garment vertex ``vertex`` directly, as a script does; the target starts where the vertex is."""
        if not 0 <= int(vertex) < x.shape[0]:
            raise ValueError(f"vertex {vertex} is not a garment vertex (0..{x.shape[0] - 1})")
        world = x[int(vertex)].detach().to("cpu", F64).clone()
        return self._start(GarmentPick(int(vertex), world, 0.0))

    def _start(self, hit: GarmentPick) -> GarmentPick:
        self.hit, self.target = hit, hit.world.clone()
        return hit

    def update(self, ray_origin=None, ray_direction=None, *, target=None) -> torch.Tensor:
        """Move the drag target onto a new ray at the picked depth, or to ``target [3]`` (m); returns the target."""
        if self.hit is None:
            raise RuntimeError("nothing is picked: pick a garment vertex before moving the drag target")
        if target is not None:
            self.target = _vec3(target, "drag target")
        elif ray_origin is not None and ray_direction is not None:
            self.target = _vec3(ray_origin, "ray origin") + self.hit.distance * _unit(ray_direction, "ray direction")
        else:
            raise ValueError("update needs a ray (ray_origin and ray_direction) or a target point")
        return self.target

    def release(self) -> None:
        """Let go of the picked vertex (pins stay)."""
        self.hit: GarmentPick | None = None
        self.target: torch.Tensor | None = None

    def pin_picked(self, x: torch.Tensor) -> int:
        """Pin the picked vertex where it is now (a stiff spring holding it); releases the drag; returns the vertex."""
        if self.hit is None:
            raise RuntimeError("nothing is picked to pin: click on the garment first")
        vertex = self.hit.vertex
        self.pins[vertex] = x[vertex].detach().to("cpu", F64).clone()
        self.release()
        return vertex

    def clear(self) -> None:
        """Remove the pins and release the drag."""
        self.pins.clear()
        self.release()

    def clamped_target(self, position: torch.Tensor) -> torch.Tensor:
        """``[3]`` the drag target pulled toward ``position [3]`` (m) until ``k ‖t − x‖ ≤ max_force``."""
        extension = self.target.to(position) - position
        length = float(extension.norm())
        allowed = self.max_force / self.stiffness
        return position + extension * min(1.0, allowed / length) if length > 0.0 else position.clone()

    def springs(self, x: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The springs of this step: the drag (clamped, damped) and the pins.

        Args:
            x: ``[V, 3]`` garment vertices at the start of the step (m).
            dt: step ``h``, s.

        Returns:
            ``(index [S] int64, target [S, 3] float64 m, stiffness [S] float64 N/m)`` on ``x``'s device, or ``None``
            when nothing is dragged or pinned.
        """
        if not dt > 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        index, targets, stiffness = [], [], []
        for vertex, held in self.pins.items():
            index.append(vertex)
            targets.append(held)
            stiffness.append(self.pin_stiffness)
        if self.hit is not None:
            vertex = self.hit.vertex
            position = x[vertex].detach().to("cpu", F64)
            clamped = self.clamped_target(position)
            rate = self.damping / dt
            combined = self.stiffness + rate
            index.append(vertex)
            targets.append((self.stiffness * clamped + rate * position) / combined)
            stiffness.append(combined)
        if not index:
            return None
        device = x.device
        return (
            torch.tensor(index, dtype=torch.int64, device=device),
            torch.stack(targets).to(device),
            torch.tensor(stiffness, dtype=F64, device=device),
        )

    def position(self, x: torch.Tensor) -> torch.Tensor | None:
        """``[3]`` where the picked vertex is now (m), or ``None``."""
        return None if self.hit is None else x[self.hit.vertex].detach().to("cpu", F64)
