"""The implicit Q-GMLS solver (PIE-NeRF Eq. 2, 18): settings, state and controls, the incremental potential, the host
and device Newton loops over it, and :class:`SolverQGMLS`, which composes them."""

from pienerf.sim.solver.config import SolverConfig
from pienerf.sim.solver.device_loop import LOOP_STATS, PHASES, DeviceLoop, DeviceLoopStep, PhaseTimer, device_loop_key
from pienerf.sim.solver.host_loop import HostLoop, spd_factor, spd_solve
from pienerf.sim.solver.potential import (
    LINE_SEARCH_FAILURES,
    QGMLSPotential,
    StepContext,
    collider_distance,
    collider_placement,
)
from pienerf.sim.solver.solver import SolverQGMLS
from pienerf.sim.solver.state import (
    PlaneCollider,
    PointForces,
    PointTargets,
    QGMLSControl,
    QGMLSState,
    QGMLSStepReport,
    SphereCollider,
)

__all__ = [
    "DeviceLoop",
    "DeviceLoopStep",
    "HostLoop",
    "LINE_SEARCH_FAILURES",
    "LOOP_STATS",
    "PHASES",
    "PhaseTimer",
    "PlaneCollider",
    "PointForces",
    "PointTargets",
    "QGMLSControl",
    "QGMLSPotential",
    "QGMLSState",
    "QGMLSStepReport",
    "SolverConfig",
    "SolverQGMLS",
    "SphereCollider",
    "StepContext",
    "collider_distance",
    "collider_placement",
    "device_loop_key",
    "spd_factor",
    "spd_solve",
]
