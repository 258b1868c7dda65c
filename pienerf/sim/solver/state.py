"""What a Q-GMLS step reads and writes: the state, the controls acting on the body, and the step's report."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from pienerf.sim.model import PointHandle

__all__ = [
    "PlaneCollider",
    "PointForces",
    "PointTargets",
    "QGMLSControl",
    "QGMLSState",
    "QGMLSStepReport",
    "SphereCollider",
]


@dataclass
class QGMLSState:
    """Generalized coordinates q and velocities q̇, both ``[nT, 3]`` float64 (Eq. 9 layout)."""

    q: torch.Tensor
    qd: torch.Tensor
    time: float = 0.0

    def copy_(self, other: QGMLSState) -> QGMLSState:
        self.q.copy_(other.q)
        self.qd.copy_(other.qd)
        self.time = other.time
        return self


@dataclass
class PointTargets:
    """Zero-rest-length springs pulling material points to targets (pins and drags).

    Attributes:
        handle: the material points (:meth:`QGMLSModel.handle`).
        target: ``[M, 3]`` world targets (m).
        stiffness: spring stiffness per point (N/m).
    """

    handle: PointHandle
    target: torch.Tensor
    stiffness: float


@dataclass
class PointForces:
    """Constant forces ``force [M, 3]`` (N) at material points (f_q = Jᵀ f)."""

    handle: PointHandle
    force: torch.Tensor


@dataclass(frozen=True)
class PlaneCollider:
    """Half-space boundary: particles stay where n·(x − point) ≥ 0."""

    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class SphereCollider:
    """Solid sphere: particles stay outside."""

    centre: tuple[float, float, float]
    radius: float


@dataclass
class QGMLSControl:
    """What acts on the body this step."""

    springs: list[PointTargets] = field(default_factory=list)
    forces: list[PointForces] = field(default_factory=list)
    colliders: list[PlaneCollider | SphereCollider] = field(default_factory=list)


@dataclass
class QGMLSStepReport:
    """Per-step statistics; times in seconds.

    Attributes:
        iterations: Newton iterations taken.
        energy: incremental potential at the step's end (J).
        last_update: largest |J Δq| of the last accepted update at the integrator points (m).
        min_det: smallest det F over the quadrature points at the step's end.
        line_search_halvings: halvings of Newton steps over the whole step.
        converged: the last Newton update fell below ``newton_tolerance`` (or the Newton step was already at
            round-off), with no failed line search; ``False`` when the iteration budget ran out first.
        line_search_failure: why the last line search found no acceptable step, ``""`` when none failed:
            ``"inversion"`` (every trial hit the never-invert bound, Ψ = +∞ for det F ≤ 0, down to the smallest
            step), ``"no decrease"`` (finite trials, none decreasing the energy enough) or ``"not finite"``
            (the Newton direction or the trial energies were NaN). The body then stays where the failed
            iteration started: the step is not a solution of Eq. 2.
        time_assembly, time_solve, time_line_search, time_other: seconds of the step's phases: assembling the Newton
            system (Eq. 18), factoring and solving it, the line search's trial energies, and the rest. A device-loop
            step has them only where it was timed (``SolverQGMLS.step(..., timed=True)``), else zeros.
        device_loop: the step ran as the device loop (:meth:`SolverQGMLS.step`); ``time_device_loop`` then holds the
            whole step (its wall time, the phases' sum at most).
        factor_reused: the step reused an earlier step's Cholesky factor (``SolverConfig.factor_reuse``).
    """

    iterations: int = 0
    energy: float = 0.0
    last_update: float = 0.0
    min_det: float = 1.0
    line_search_halvings: int = 0
    converged: bool = False
    line_search_failure: str = ""
    time_assembly: float = 0.0
    time_solve: float = 0.0
    time_line_search: float = 0.0
    time_other: float = 0.0
    device_loop: bool = False
    factor_reused: bool = False
    time_device_loop: float = 0.0

    @property
    def time_step(self) -> float:
        """Seconds the whole step took: the device loop's time when it ran as one, else its phases together."""
        if self.device_loop:
            return self.time_device_loop
        return self.time_assembly + self.time_solve + self.time_line_search + self.time_other

    @property
    def timed(self) -> bool:
        """Whether the step's phases were timed (always for the host loop; for the device loop on request)."""
        return not self.device_loop or (self.time_assembly + self.time_solve + self.time_line_search
                                        + self.time_other) > 0

    @property
    def line_search_failed(self) -> bool:
        """Whether a line search of this step could not move (see ``line_search_failure``)."""
        return bool(self.line_search_failure)
