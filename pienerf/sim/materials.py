"""Hyperelastic materials of the Q-GMLS solver, from engineering constants."""

from __future__ import annotations

import math
from dataclasses import dataclass

from kernels.hyperelastic import MaterialModel
from pienerf.sim.settings import setting

__all__ = ["MATERIAL_MODELS", "Material"]

MATERIAL_MODELS = {
    "neo_hookean": MaterialModel.NEO_HOOKEAN,
    "arap": MaterialModel.ARAP,
    "stvk": MaterialModel.STVK,
    "fixed_corotated": MaterialModel.FIXED_COROTATED,
}


@dataclass(frozen=True)
class Material:
    """An isotropic hyperelastic material.

    Attributes:
        model: ``"neo_hookean"`` (PIE-NeRF Eq. 22), ``"arap"``, ``"stvk"`` or ``"fixed_corotated"``;
            the energy densities are given in :mod:`kernels.hyperelastic`.
        young_modulus: E (Pa), > 0.
        poisson_ratio: ν (dimensionless), −1 < ν < 0.5.
        density: ρ (kg/m³), > 0.
    """

    model: str = setting("neo_hookean", choices=MATERIAL_MODELS, doc="hyperelastic model")
    young_modulus: float = setting(1.0e5, unit="Pa", low=0.0, high=1e12, low_open=True, doc="Young's modulus E")
    poisson_ratio: float = setting(0.3, low=-0.999, high=0.499, doc="Poisson's ratio ν")
    density: float = setting(1000.0, unit="kg/m³", low=0.0, high=1e5, low_open=True, doc="mass density ρ")

    def __post_init__(self):
        if self.model not in MATERIAL_MODELS:
            raise ValueError(f"unknown material model {self.model!r}; valid: {', '.join(MATERIAL_MODELS)}")
        for name in ("young_modulus", "poisson_ratio", "density"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"material {name} must be a finite number, got {value!r}")
        if self.young_modulus <= 0:
            raise ValueError(f"Young's modulus must be > 0 Pa, got {self.young_modulus}")
        if not -1.0 < self.poisson_ratio < 0.5:
            raise ValueError(
                f"Poisson ratio must lie in (-1, 0.5), got {self.poisson_ratio}; 0.5 is incompressible, "
                "use 0.45-0.49 for nearly incompressible materials"
            )
        if self.density <= 0:
            raise ValueError(f"density must be > 0 kg/m^3, got {self.density}")

    @property
    def kind(self) -> MaterialModel:
        """The kernel's model enumeration."""
        return MATERIAL_MODELS[self.model]

    @property
    def lame(self) -> tuple[float, float]:
        """Lamé parameters (μ, λ) in Pa: μ = E / (2(1+ν)), λ = Eν / ((1+ν)(1−2ν))."""
        E, nu = self.young_modulus, self.poisson_ratio
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
