"""The implicit Q-GMLS solver (PIE-NeRF Eq. 2, 18): settings, state and controls, and :class:`SolverQGMLS`."""

from pienerf.sim.solver.config import SolverConfig
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
    "PlaneCollider",
    "PointForces",
    "PointTargets",
    "QGMLSControl",
    "QGMLSState",
    "QGMLSStepReport",
    "SolverConfig",
    "SolverQGMLS",
    "SphereCollider",
]
