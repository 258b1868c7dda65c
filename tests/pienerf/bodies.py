"""Lattice bodies and closed-form reference solutions for the physical validation of the Q-GMLS solver.

Bodies are cell-centred cubic lattices of particles (each particle owns a cube of side ``spacing``), so
the particle volumes sum to the exact volume of the shape and the centres of the outer layer sit half a
spacing inside its faces.
"""

from __future__ import annotations

import torch

from pienerf.sim.model import QGMLSModel
from pienerf.sim.solver import PointTargets

__all__ = [
    "cantilever_tip_deflection",
    "clamp",
    "euler_bernoulli_tip_deflection",
    "kirchhoff_strip_tip_deflection",
    "lattice",
    "mechanical_energy",
]


def lattice(size: tuple[float, float, float], spacing: float, keep=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell-centred lattice filling the box ``[0, size]`` (m).

    Args:
        size: box edge lengths (m), multiples of ``spacing``.
        spacing: particle spacing (m).
        keep: optional predicate ``[P, 3] -> [P] bool`` carving a shape out of the box.

    Returns:
        ``(position [P, 3] (m), volume [P] (m³))`` in float64.
    """
    axes = [torch.arange(0.5 * spacing, s - 1e-9, spacing, dtype=torch.float64) for s in size]
    position = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    if keep is not None:
        position = position[keep(position)]
    return position, torch.full((position.shape[0],), spacing**3, dtype=torch.float64)


def clamp(model: QGMLSModel, spacing: float, stiffness: float) -> PointTargets:
    """Zero-rest-length springs (N/m each) holding the end slab ``x < spacing`` at its rest position."""
    handle = model.handle(model.position[model.position[:, 0] < spacing])
    return PointTargets(handle, handle.rest.clone(), stiffness)


def cantilever_tip_deflection(model: QGMLSModel, q: torch.Tensor, size: tuple[float, float, float]) -> float:
    """Downward (−y) displacement (m) of the centre of the free end face ``x = size[0]``."""
    tip = model.handle(torch.tensor([[size[0], 0.5 * size[1], 0.5 * size[2]]], dtype=torch.float64))
    return -float((tip.positions(q) - tip.rest)[0, 1])


def euler_bernoulli_tip_deflection(length, side, young_modulus, density, gravity) -> float:
    """Tip deflection δ = q L⁴ / (8 E I) (m) of a clamped square beam under its own weight.

    q = ρ g A is the load per unit length (N/m), A = b² and I = b⁴/12 for the side b; shear is
    neglected (Timoshenko adds the fraction (E/G)(b/L)²/(3κ), 0.8 % for ν = 0, L/b = 10, κ = 5/6).
    """
    load = density * gravity * side**2
    return load * length**4 / (8.0 * young_modulus * side**4 / 12.0)


def kirchhoff_strip_tip_deflection(length, thickness, young_modulus, poisson_ratio, density, gravity) -> float:
    """Free-edge deflection δ = q L⁴ / (8 D) (m) of a plate strip clamped along one edge under its own weight.

    q = ρ g t per unit area (Pa) and D = E t³ / (12 (1 − ν²)) is the flexural rigidity (N·m).
    """
    rigidity = young_modulus * thickness**3 / (12.0 * (1.0 - poisson_ratio**2))
    return density * gravity * thickness * length**4 / (8.0 * rigidity)


def mechanical_energy(solver, q: torch.Tensor, qd: torch.Tensor) -> tuple[float, float]:
    """Kinetic ½ q̇ᵀ M q̇ and elastic U(q) energies (J) of a solver's body."""
    kinetic = 0.5 * float((qd * (solver.mass @ qd)).sum())
    elastic = float(solver.integrator.evaluate(q, gradient=False, hessian=False, project=False).energy)
    return kinetic, elastic
