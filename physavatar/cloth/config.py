"""Settings of the garment simulator (:class:`ClothConfig`) and the ranges PhysAvatar estimates its material in."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from kernels import backend

__all__ = ["DENSITY_RANGE", "LINEAR_SOLVERS", "STIFFNESS_RANGE", "ClothConfig"]

DENSITY_RANGE = (200.0, 640.0)
"""PhysAvatar's range of the volumetric density ``ρ``, kg/m³ (Appendix A.3)."""
STIFFNESS_RANGE = (0.1, 8.0)
"""PhysAvatar's range of the stiffness multipliers ``κ_s`` and ``κ_b`` (Appendix A.3)."""
LINEAR_SOLVERS = ("auto", "direct", "cudss", "dense", "cg")
"""The values of :attr:`ClothConfig.linear_solver` (:class:`physavatar.cloth.newton_system.LinearSolver`)."""


@dataclass(frozen=True)
class ClothConfig:
    """Material, contact and solver settings of :class:`~physavatar.cloth.solver.SolverCloth` (SI units; defaults:
    cotton, Appendix A.3).

    Attributes:
        density: volumetric density ``ρ``, kg/m³, in the paper's range 200–640 (areal density ``ρ h``).
        kappa_s: membrane stiffness ``κ_s``, 1, in 0.1–8: Young's modulus ``E = κ_s · base_young``.
        kappa_b: bending stiffness ``κ_b``, 1, in 0.1–8: hinge stiffness ``κ_b E₀ h³ / (24 (1 − ν²))``.
        base_young: base Young's modulus ``E₀``, Pa (C-IPC's isotropic cotton, 0.821 MPa).
        poisson: Poisson's ratio ``ν``, in ``[0, 0.5)``.
        thickness: sheet thickness ``h``, m.
        contact_distance: barrier activation distance ``d̂``, m (paper: 1 mm).
        barrier_stiffness: IPC barrier stiffness ``κ``, J/m⁴, fixed for the whole run; ``None`` takes C-IPC's
            choice from the mean vertex mass (:func:`~physavatar.cloth.potential.barrier_stiffness`).
        friction: friction coefficient ``μ`` (paper: 0.2); 0 switches friction off.
        friction_velocity: IPC's static-friction velocity ``ε_v``, m/s (C-IPC: 1e-3).
        newton_tolerance: stop when ``‖p‖_∞ / Δt`` falls below this, m/s.
        max_newton_iterations: cap on Newton iterations per step.
        elastic_projection: how the membrane and bending Hessians are made PSD for the Newton direction:
            ``"abs"`` flips their negative eigenvalues (absolute eigenvalue filtering, Chen et al. 2024), ``"clamp"``
            zeroes them (the nearest PSD matrix, as C-IPC); ``"auto"``: abs for dynamic steps, clamp for static
            solves. Flipping keeps the curvature of buckling modes and gets a dynamic step to C-IPC's tolerance sooner,
            while clamping converges faster in the tail of a tight solve. Measured with both filtered by their
            eigen-decomposition: the 3757-vertex ``skirt7271`` on the walking mannequin, default tolerance, first 4
            frames: 40 Newton iterations with abs, 66 with clamp; a 280-vertex skirt of the synthetic fabric of
            :mod:`physavatar.fit.estimation` at 1e-4 m/s, 5 frames: 143 with abs, 99 with clamp; a static hanging strip
            to 1e-9 m: clamp converges, abs does not within 30 iterations. Barrier Hessians are always clamped.
        membrane_filter: how ``elastic_projection`` is applied to the membrane: ``"eigen"`` to the eigenvalues of
            each 9×9 Hessian (a batched eigensolver), ``"stress"`` in the kernel, in closed form, to the stress in
            the Hessian's only indefinite term (``stress_filter`` of :func:`kernels.shell.membrane_energy`). The
            stress filter saves the eigensolver but converges more slowly: over the first 14 frames of the walk
            above 118 Newton iterations against 113; the 8×8 sheet dropped on a sphere of the tests, 8 frames: 137
            against 119. Its cheaper iterations then make a frame take about as long (``docs/benchmarks.md``); the
            eigen-decomposition stays the default for its steadier convergence.
        gravity: gravitational acceleration ``[3]``, m/s².
        static: minimise ``Ψ − Σ m g·x`` without inertia or friction (a static equilibrium solve; needs
            Dirichlet vertices); ``Δt`` then only scales the barrier stiffness and the tolerance.
        linear_solver: ``"direct"`` (SuperLU on the host), ``"cudss"`` (cuDSS's sparse Cholesky on CUDA, where
            ``nvidia-cudss-cu13`` or ``-cu12`` is installed), ``"dense"`` (dense Cholesky on the device, cuSOLVER on
            CUDA), ``"cg"`` (block-Jacobi CG in torch) or ``"auto"``: direct on the CPU; on CUDA cuDSS where it
            loads, else dense up to :data:`~physavatar.cloth.newton_system.DENSE_MAX_DOFS` garment DOFs (about 1 GB
            for the 3757-vertex skirt7271, where CG needed thousands of iterations), CG beyond.
        cg_tolerance: relative residual at which CG stops.
        cg_max_iterations: cap on CG iterations per Newton iteration.
        ccd_eta: ACCD's ``η``: a step may close at most ``1 − η`` of any pair's gap (Codim-IPC: 0.1).
        candidate_margin: how far, m, the contact candidates of a step reach beyond each vertex's predicted path
            (start to inertial target, or to its target for kinematic vertices). The candidates are found once and
            serve every Newton iteration whose sweep stays within that reach; a sweep that leaves it finds them
            anew. Larger margins mean fewer searches and more candidates to filter. ``None``: 5 mm on CUDA, 2 mm on
            the CPU, where filtering many candidates costs more than searching again: those were the fastest
            margins of skirt7271 walking on each device (``docs/benchmarks.md``).
        psd_precision: the dtype in which the PSD filter decomposes the float64 membrane and bending Hessians
            (the barrier's always in float64: :func:`physavatar.cloth.newton_system.filtered_elements`): ``"float32"``,
            ``"float64"`` or ``"auto"``: float32 on CUDA, where cuSOLVER's batched Jacobi is faster in float32 and the
            walk of skirt7271 took as many Newton iterations (489) in less time (``docs/benchmarks.md``); float64
            on the CPU. The filtered matrices stay PSD in either
            (:func:`kernels.element_terms.project_psd`).
    """

    density: float = 472.641509
    kappa_s: float = 1.0
    kappa_b: float = 1.0
    base_young: float = 0.821e6
    poisson: float = 0.243
    thickness: float = 0.318e-3
    contact_distance: float = 1e-3
    barrier_stiffness: float | None = None
    friction: float = 0.2
    friction_velocity: float = 1e-3
    newton_tolerance: float = 1e-2
    max_newton_iterations: int = 50
    elastic_projection: str = "auto"
    membrane_filter: str = "eigen"
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    static: bool = False
    linear_solver: str = "auto"
    cg_tolerance: float = 1e-8
    cg_max_iterations: int = 5000
    ccd_eta: float = 0.1
    candidate_margin: float | None = None
    psd_precision: str = "auto"

    def __post_init__(self):
        lo, hi = DENSITY_RANGE
        if not lo <= self.density <= hi:
            raise ValueError(
                f"density ({self.density}) must lie in the paper's range {lo:g}–{hi:g} kg/m³ (volumetric, as in "
                f"C-IPC); for another fabric change thickness or base_young instead"
            )
        lo, hi = STIFFNESS_RANGE
        for name in ("kappa_s", "kappa_b"):
            value = getattr(self, name)
            if not lo <= value <= hi:
                raise ValueError(f"{name} ({value}) must lie in the paper's range {lo:g}–{hi:g} (a multiplier)")
        for name in ("base_young", "thickness", "contact_distance", "friction_velocity", "newton_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} ({value}) must be a positive finite number")
        if not 0.0 <= self.poisson < 0.5:
            raise ValueError(f"poisson ({self.poisson}) must lie in [0, 0.5)")
        if self.barrier_stiffness is not None and not self.barrier_stiffness > 0.0:
            raise ValueError(f"barrier_stiffness ({self.barrier_stiffness}) must be positive, or None for C-IPC's")
        if not self.friction >= 0.0:
            raise ValueError(f"friction ({self.friction}) must be non-negative")
        if self.max_newton_iterations < 1 or self.cg_max_iterations < 1:
            raise ValueError("max_newton_iterations and cg_max_iterations must be at least 1")
        if len(self.gravity) != 3:
            raise ValueError(f"gravity must have 3 components, got {self.gravity}")
        if self.elastic_projection not in ("auto", "abs", "clamp"):
            raise ValueError(f"elastic_projection ({self.elastic_projection!r}) must be 'auto', 'abs' or 'clamp'")
        if self.psd_precision not in backend.PRECISIONS:
            raise ValueError(f"psd_precision ({self.psd_precision!r}) must be 'auto', 'float32' or 'float64'")
        if self.membrane_filter not in ("eigen", "stress"):
            raise ValueError(f"membrane_filter ({self.membrane_filter!r}) must be 'eigen' or 'stress'")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(
                f"linear_solver ({self.linear_solver!r}) must be one of {', '.join(map(repr, LINEAR_SOLVERS))}"
            )
        if not 0.0 < self.ccd_eta < 1.0:
            raise ValueError(f"ccd_eta ({self.ccd_eta}) must lie in (0, 1)")
        if self.candidate_margin is not None and not (
            math.isfinite(self.candidate_margin) and self.candidate_margin >= 0.0
        ):
            raise ValueError(f"candidate_margin ({self.candidate_margin}) must be a non-negative distance, m")

    def eigen_dtype(self, device: torch.device) -> torch.dtype:
        """The dtype the PSD filter decomposes the element Hessians in on ``device`` (``psd_precision``,
        :func:`kernels.backend.precision_dtype`)."""
        return backend.precision_dtype(self.psd_precision, device)

    @property
    def young(self) -> float:
        """Membrane Young's modulus ``E = κ_s E₀``, Pa."""
        return self.kappa_s * self.base_young
