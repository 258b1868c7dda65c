"""Settings of the Q-GMLS solver (:class:`SolverConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kernels import backend
from pienerf.sim.settings import setting

__all__ = ["SolverConfig"]


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings.

    Attributes:
        gravity: acceleration of gravity (m/s²).
        rayleigh_alpha: mass-proportional damping α (1/s).
        rayleigh_beta: stiffness-proportional damping β (s).
        newton_iterations: most Newton iterations per step.
        hessian_updates: how many of a step's Newton iterations assemble and factor a fresh Hessian;
            later iterations reuse the last Cholesky factor with fresh gradients (modified Newton:
            linear instead of quadratic convergence, each iteration far cheaper). ``None``: all.
        newton_tolerance: stop when the largest displacement update at the integrator points
            (|J Δq|, m) is below this.
        line_search_steps: most halvings of a Newton step.
        contact_stiffness: penalty modulus of colliders (Pa); a particle of volume V gets a spring of
            stiffness contact_stiffness · V^(1/3) (N/m). ``None`` → 100 × Young's modulus.
        project_hessian: make every quadrature point's Hessian PSD (kernels.hyperelastic).
        device_loop: run each step's Newton loop with no host read inside it (:meth:`SolverQGMLS.step`), captured
            once per set of controls and replayed as one CUDA graph. ``None``: on CUDA only (on the CPU, where a
            launch costs little, the loop that stops early is faster); ``True`` on the CPU runs the same loop
            uncaptured.
        line_search_batch: trial steps (1, 1/2, 1/4, …) the device loop evaluates per Newton iteration; a step
            that needs more halvings is redone by the host loop.
        factor_reuse: later steps that may reuse a step's Cholesky factor instead of assembling and factoring
            their own (modified Newton across steps, device loop only): 0 never. A step that reuses it and then
            contracts slowly (its last Newton update above 2^-(iterations−1) of its first), halves a step, or
            (with ``newton_tolerance`` > 0) does not converge is taken again with its own factor, which is kept
            instead; a change of controls, dt or material drops it too. Every direction is a descent direction
            (the factor is of an SPD matrix) and the line search keeps the never-invert guarantee, so a step that
            reuses the factor ends where Newton's would, to the tolerance.
        hessian_precision: ``"auto"``, ``"float64"`` or ``"float32"``: the precision of the elastic Hessian's block
            products in steps (:class:`kernels.ip_integrate.IPIntegrator`'s ``product_dtype``); ``"auto"`` is float32
            on CUDA and float64 on the CPU (:meth:`hessian_product_dtype`). ``"float32"`` leaves the Hessian float64
            with a relative error of 1e-7 or less, the energy and gradient (and so Newton's fixed point) exact, and
            suits dynamic steps, whose mass term keeps the Newton matrix well away from singular. Where it does not
            (a force no body can bear), a Newton matrix whose factorisation fails is assembled again with float64
            products before the host loop shifts it, so such a step ends as a float64 one does.
            :meth:`SolverQGMLS.solve_static` (no mass term: the rigid modes, ~1e-13 of the largest eigenvalue, sit
            below float32 round-off) always assembles in float64. (What each costs: ``docs/benchmarks.md``, Q-GMLS.)
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    rayleigh_alpha: float = setting(0.0, unit="1/s", low=0.0, high=1e4, doc="mass-proportional damping α")
    rayleigh_beta: float = setting(0.0, unit="s", low=0.0, high=10.0, doc="stiffness-proportional damping β")
    newton_iterations: int = setting(3, low=1, high=1000, doc="most Newton iterations per step")
    hessian_updates: int | None = None
    newton_tolerance: float = 1e-8
    line_search_steps: int = 20
    contact_stiffness: float | None = None
    project_hessian: bool = True
    device_loop: bool | None = None
    line_search_batch: int = 3
    factor_reuse: int = 0
    hessian_precision: str = setting(
        "auto", choices=tuple(backend.PRECISIONS), doc="precision of the elastic Hessian's block products"
    )

    def __post_init__(self):
        values = [*self.gravity, self.rayleigh_alpha, self.rayleigh_beta, self.newton_tolerance]
        if self.contact_stiffness is not None:
            values.append(self.contact_stiffness)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise ValueError(f"solver settings must be finite numbers, got {self}")
        if self.rayleigh_alpha < 0 or self.rayleigh_beta < 0:
            raise ValueError("Rayleigh damping coefficients must be >= 0")
        if self.newton_iterations < 1 or self.line_search_steps < 1:
            raise ValueError("newton_iterations and line_search_steps must be >= 1")
        if self.contact_stiffness is not None and not self.contact_stiffness > 0:
            raise ValueError(f"contact_stiffness must be > 0 Pa (or None for 100 × Young's modulus), got "
                             f"{self.contact_stiffness!r}")
        if self.line_search_batch < 1:
            raise ValueError("line_search_batch must be >= 1")
        if self.factor_reuse < 0:
            raise ValueError(f"factor_reuse must be >= 0 steps, got {self.factor_reuse}")
        if self.factor_reuse and self.rayleigh_beta:
            raise ValueError("factor_reuse needs rayleigh_beta = 0: stiffness damping uses each step's own K(q_n)")
        if self.hessian_updates is not None and self.hessian_updates < 1:
            raise ValueError("hessian_updates must be >= 1 (or None for a fresh Hessian every iteration)")
        if self.hessian_precision not in backend.PRECISIONS:
            raise ValueError(f"hessian_precision must be one of {sorted(backend.PRECISIONS)}, got "
                             f"{self.hessian_precision!r}")

    def hessian_product_dtype(self, device: torch.device | str) -> torch.dtype:
        """The torch dtype of ``hessian_precision`` for a model on ``device``
        (:func:`kernels.backend.precision_dtype`)."""
        return backend.precision_dtype(self.hessian_precision, device)
