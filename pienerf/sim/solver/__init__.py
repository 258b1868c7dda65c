"""The implicit Q-GMLS solver (PIE-NeRF Eq. 2, 18): settings, state and controls, the incremental potential, the host
and device Newton loops over it, and :class:`SolverQGMLS`, which composes them."""

from pienerf.sim.solver.config import SolverConfig
from pienerf.sim.solver.device_loop import PHASES, DeviceLoop, DeviceLoopStep, PhaseTimer, device_loop_key
from pienerf.sim.solver.host_loop import HostLoop
from pienerf.sim.solver.potential import LINE_SEARCH_FAILURES, QGMLSPotential, StepContext
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
    "LINE_SEARCH_FAILURES",
    "PHASES",
    "DeviceLoop",
    "DeviceLoopStep",
    "HostLoop",
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
    "device_loop_key",
]
