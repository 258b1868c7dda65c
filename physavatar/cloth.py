"""Garment simulator of PhysAvatar (§3.2, Appendix A.3): implicit Euler on the Codim-IPC incremental potential.

One step from ``x^t`` minimises, over the free garment vertices ``x``,

``E(x) = ½‖x − x̂‖²_M + Δt² (Ψ_s(x) + Ψ_b(x) + κ B(x) + D(x))``, ``x̂ = x^t + Δt v^t + Δt² g``

(inertia, StVK membrane, discrete-shell bending, IPC barrier, lagged friction), by projected Newton: PSD-projected
element Hessians assembled into a sparse matrix, a search direction from a sparse solve, a step bounded by additive
CCD and then backtracked on ``E``. Every accepted iterate is intersection-free, so the state after a step is too.

Paper parameters and their mapping. PhysAvatar estimates ``(ρ, κ_s, κ_b)`` with ``ρ`` in 200–640 and ``κ_s``,
``κ_b`` in 0.1–8, "scaled as in the C-IPC codebase" (Appendix A.3). In that codebase and PhysAvatar's driver:

* ``ρ`` is a volumetric density, kg/m³; a vertex carries ``m = ρ h Σ A_f / 3`` (``h`` the thickness, lumped mass);
* ``κ_s`` multiplies a base Young's modulus: ``E = κ_s E₀`` (cotton: ``E₀ = 0.821`` MPa, ``ν = 0.243``,
  ``h = 0.318`` mm); the membrane has the plane-stress Lamé parameters ``h μ``, ``h λ`` of ``E`` and ``ν``;
* ``κ_b`` multiplies the hinge stiffness of the base modulus, ``k = κ_b E₀ h³ / (24 (1 − ν²))``, independently of
  ``κ_s``, and each hinge stores ``k w̄ (θ − θ̄)²`` with ``w̄ = 3‖ē‖²/Ā``. Its continuum limit depends on the mesh:
  on a square grid with one diagonal direction it is ``3k [(c_x − c_xy)² + (c_y − c_xy)² + 4 c_xy²]`` per unit
  area (curvatures ``c``), so cylindrical bending has rigidity ``6k`` (3× the plate's
  ``D = κ_b E₀ h³/(12(1 − ν²))``) and a free narrow strip ``4.8 k`` per unit width (tests/physavatar/test_cloth.py
  derives both).

So ``ρ`` scales the inertia, ``κ_s`` the membrane and ``κ_b`` the bending alone. Scaling all three by ``s`` scales
the whole incremental potential by ``s`` (the barrier stiffness follows the mean mass, friction the barrier force,
gravity enters through the inertia) and leaves its minimiser, the motion, unchanged: only ``κ_s/ρ`` and ``κ_b/ρ``
can be told from geometry. :meth:`SolverCloth.sensitivity_step` differentiates one step with respect to them.

Kinematic vertices. The body collider and the garment's Dirichlet (boundary) vertices move on straight lines from
their start-of-step positions to their targets. They are eliminated from the linear system: each Newton
direction prescribes their remaining displacement ``p_k`` and solves ``H_ff p_f = −g_f − H_fk p_k`` for the free
ones, so the barrier's coupling pushes the garment ahead of the body; the CCD-bounded step moves both. Until the
kinematic vertices reach their targets the step is the CCD bound (the potential changes with them); from then on
it is backtracked on ``E``. Convergence: targets reached and ``‖p_f‖_∞ / Δt`` below the tolerance (IPC).

Precision: float64 throughout; contact distances of ``d̂ = 1`` mm on coordinates of 1 m need it (float32
resolves about 1e-7 m, the barrier's curvature near contact spans ten orders of magnitude).

Linear solver: a direct sparse LU on the CPU (SciPy's SuperLU on the host; the matrices are SPD, so a symmetric
ordering with diagonal pivots); on CUDA cuDSS's sparse Cholesky where it is installed (:mod:`kernels.cudss`; the
pattern is analysed once and refactored every Newton iteration), else a dense Cholesky (cuSOLVER) up to
:data:`DENSE_MAX_DOFS` and conjugate gradients with a 3×3 block-Jacobi preconditioner beyond. On skirt7271's 11k-DOF
Newton matrix cuDSS is the fastest by an order of magnitude (figures in ``docs/benchmarks.md``).
``ClothConfig.linear_solver`` overrides. Every Newton system is factored anew: the previous system's
Cholesky factor as a CG preconditioner reached a relative residual of 1e-8 within 6 iterations for only 2 of 75
systems of the 1252-face skirt walking (contacts and the filtered element Hessians change too much between
iterations). Nor does it serve an inexact Newton method: solving each system by CG preconditioned with the first
factor of the step, to a relative residual of 0.05 and factoring anew where 4 CG iterations do not reach it, took
skirt7271's first 10 frames of the walk from 96 Newton iterations (96 factorisations) to 111 (85 factorisations and
387 preconditioner solves); to 0.25, 343 iterations, several frames at the cap; to 0.01, 105 (101).

Execution: on CUDA the Newton iterations are four CUDA graphs over buffers of fixed capacity (:class:`_NewtonLoop`),
with the sparse solve between them and one read from the device per iteration; on the CPU the same phases are
plain calls over exact pair lists.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from kernels import assembly, backend, ccd, cudss, element_terms, ipc_barrier, shell
from kernels import contact as kernels_contact
from kernels import friction as kernels_friction
from kernels.broad_phase import BoxTree, OverlapQuery, find_overlaps
from kernels.raycast import MeshBVH

__all__ = [
    "ClothConfig",
    "ClothControl",
    "ClothEnergies",
    "ClothState",
    "DENSE_MAX_DOFS",
    "SENSITIVITY_PARAMETERS",
    "SolverCloth",
    "StepStats",
    "bending_stiffness",
    "barrier_stiffness",
    "friction_potential",
    "lumped_masses",
]

F64 = torch.float64
DENSITY_RANGE = (200.0, 640.0)
STIFFNESS_RANGE = (0.1, 8.0)
DENSE_MAX_DOFS = 30_000
"""Largest garment DOF count (3 per vertex) that ``linear_solver="auto"`` factors densely on CUDA where cuDSS is
not installed (a float64 matrix of up to 7.2 GB)."""
LINEAR_SOLVERS = ("auto", "direct", "cudss", "dense", "cg")
PHASES = ("broad_phase", "ccd", "assemble", "solve", "line_search", "friction")
SENSITIVITY_PARAMETERS = ("density", "kappa_s", "kappa_b")


@dataclass(frozen=True)
class ClothConfig:
    """Material, contact and solver settings of :class:`SolverCloth` (SI units; defaults: cotton, Appendix A.3).

    Attributes:
        density: volumetric density ``ρ``, kg/m³, in the paper's range 200–640 (areal density ``ρ h``).
        kappa_s: membrane stiffness ``κ_s``, 1, in 0.1–8: Young's modulus ``E = κ_s · base_young``.
        kappa_b: bending stiffness ``κ_b``, 1, in 0.1–8: hinge stiffness ``κ_b E₀ h³ / (24 (1 − ν²))``.
        base_young: base Young's modulus ``E₀``, Pa (C-IPC's isotropic cotton, 0.821 MPa).
        poisson: Poisson's ratio ``ν``, in ``[0, 0.5)``.
        thickness: sheet thickness ``h``, m.
        contact_distance: barrier activation distance ``d̂``, m (paper: 1 mm).
        barrier_stiffness: IPC barrier stiffness ``κ``, J/m⁴, fixed for the whole run; ``None`` takes C-IPC's
            choice from the mean vertex mass (:func:`barrier_stiffness`).
        friction: friction coefficient ``μ`` (paper: 0.2); 0 switches friction off.
        friction_velocity: IPC's static-friction velocity ``ε_v``, m/s (C-IPC: 1e-3).
        newton_tolerance: stop when ``‖p‖_∞ / Δt`` falls below this, m/s.
        max_newton_iterations: cap on Newton iterations per step.
        elastic_projection: how the membrane and bending Hessians are made PSD for the Newton direction:
            ``"abs"`` flips their negative eigenvalues (absolute eigenvalue filtering, Chen et al. 2024), ``"clamp"``
            zeroes them (the nearest PSD matrix, as C-IPC); ``"auto"``: abs for dynamic steps, clamp for static
            solves. Flipping keeps the curvature of buckling modes and gets a dynamic step to C-IPC's tolerance
            sooner, while clamping converges faster in the tail of a tight solve. Measured with both filtered by
            their eigen-decomposition: the 3757-vertex ``skirt7271`` on the walking mannequin, default tolerance,
            first 4 frames: 40 Newton iterations with abs, 66 with clamp; a 280-vertex skirt of the synthetic fabric
            of :mod:`physavatar.estimate` at 1e-4 m/s, 5 frames: 143 with abs, 99 with clamp; a static hanging strip
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
            loads, else dense up to :data:`DENSE_MAX_DOFS` garment DOFs (about 1 GB for the 3757-vertex skirt7271,
            where CG needed thousands of iterations), CG beyond.
        cg_tolerance: relative residual at which CG stops.
        cg_max_iterations: cap on CG iterations per Newton iteration.
        ccd_eta: ACCD's ``η``: a step may close at most ``1 − η`` of any pair's gap (Codim-IPC: 0.1).
        candidate_margin: how far, m, the contact candidates of a step reach beyond each vertex's predicted path
            (start to inertial target, or to its target for kinematic vertices). The candidates are found once and
            serve every Newton iteration whose sweep stays within that reach; a sweep that leaves it finds them
            anew. Larger margins mean fewer searches and more candidates to filter. ``None``: 5 mm on CUDA, 2 mm on
            the CPU, where filtering many candidates costs more than searching again: those were the fastest
            margins of skirt7271 walking on each device (``docs/benchmarks.md``).
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

    @property
    def young(self) -> float:
        """Membrane Young's modulus ``E = κ_s E₀``, Pa."""
        return self.kappa_s * self.base_young


@dataclass
class ClothState:
    """Garment state: positions ``x [V, 3]`` (m) and velocities ``v [V, 3]`` (m/s), float64 on the backend device."""

    x: torch.Tensor
    v: torch.Tensor


@dataclass
class ClothControl:
    """What moves the garment this step.

    Attributes:
        body_start: ``[B, 3]`` body collider vertices at the start of the step, m.
        body_end: ``[B, 3]`` body collider vertices at the end of the step, m (linear motion in between).
        boundary_index: ``[D]`` int64 garment vertices that follow their targets exactly (Dirichlet).
        boundary_target: ``[D, 3]`` their positions at the end of the step, m.
    """

    body_start: torch.Tensor
    body_end: torch.Tensor
    boundary_index: torch.Tensor
    boundary_target: torch.Tensor

    @staticmethod
    def free(device: torch.device | None = None) -> ClothControl:
        """No body and no boundary vertices."""
        empty = torch.zeros(0, 3, dtype=F64, device=device)
        return ClothControl(empty, empty, torch.zeros(0, dtype=torch.int64, device=device), empty)


@dataclass
class StepStats:
    """What one step did.

    Attributes:
        newton_iterations: Newton iterations taken.
        converged: the tolerance was met with every kinematic vertex on its target.
        min_distance_body: smallest garment–body distance among pairs within ``d̂`` after the step, m (inf if none).
        min_distance_self: smallest garment–garment distance among non-adjacent pairs within ``d̂``, m (inf if none).
        contacts: active barrier pairs after the step.
        time: seconds spent per phase (:data:`PHASES`).
        candidate_searches: broad-phase searches of the step (1 unless a sweep left the candidates' reach).
        line_search_stalled: the line search could not move (CCD bound or backtracking reached zero step), so the
            step ended where it stood without converging.
    """

    newton_iterations: int
    converged: bool
    min_distance_body: float
    min_distance_self: float
    contacts: int
    time: dict[str, float] = field(default_factory=dict)
    candidate_searches: int = 1
    line_search_stalled: bool = False


class ClothEnergies(NamedTuple):
    """Per-element energy evaluators (signatures of :func:`kernels.shell.membrane_energy`, ``bending_energy``,
    ``contact_energy`` and their energy-only ``*_value`` twins, which the line search calls); the benchmark swaps
    in the autograd references."""

    membrane: Callable = shell.membrane_energy
    bending: Callable = shell.bending_energy
    contact: Callable = kernels_contact.contact_energy
    membrane_value: Callable = shell.membrane_energy_value
    bending_value: Callable = shell.bending_energy_value
    contact_value: Callable = kernels_contact.contact_energy_value


class _Pairs(NamedTuple):
    """Contact candidates: ``pt [P, 4]``, ``ee [Q, 4]`` int32, how many of each lead (garment–body first), and the
    edge pairs' mollifier thresholds ``ε_x [Q]`` (:func:`kernels.ipc_barrier.edge_edge_mollifier_threshold`, found with
    the candidates and carried along with them)."""

    pt: torch.Tensor
    ee: torch.Tensor
    pt_body: int
    ee_body: int
    ee_eps: torch.Tensor


class _Cover(NamedTuple):
    """Contact candidates valid while every vertex sweeps inside its box ``[lo, hi]`` (``[V + B, 3]`` each)."""

    lo: torch.Tensor
    hi: torch.Tensor
    pairs: _Pairs


class _Friction(NamedTuple):
    """Lagged friction data of the contacts at the start of the step (IPC §5)."""

    index: torch.Tensor  # [K, 4] long
    weight: torch.Tensor  # [K, 4] closest-point weights: Δ = Σ w_i x_i is the gap vector
    projector: torch.Tensor  # [K, 3, 3] I − n nᵀ
    force: torch.Tensor  # [K] μ λ, N


# ---------------------------------------------------------------------------------------------------------------
# Material and contact parameters
# ---------------------------------------------------------------------------------------------------------------


def lumped_masses(x: torch.Tensor, faces: torch.Tensor, areal_density: float) -> torch.Tensor:
    """Lumped vertex masses ``m_i = ρ h Σ_{f ∋ i} A_f / 3`` (C-IPC's shell mass).

    Args:
        x: ``[V, 3]`` rest positions, m.
        faces: ``[F, 3]`` vertex indices.
        areal_density: ``ρ h``, kg/m².

    Returns:
        ``[V]`` masses, kg.
    """
    tri = x[faces.long()]
    area = 0.5 * torch.linalg.norm(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=1)
    mass = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
    return mass.index_add_(0, faces.long().reshape(-1), (areal_density * area / 3.0).repeat_interleave(3))


def bending_stiffness(config: ClothConfig) -> float:
    """Hinge stiffness ``k = κ_b E₀ h³ / (24 (1 − ν²))``, J (PhysAvatar's κ_b, §3.2).

    ``κ_b`` multiplies the base modulus ``E₀`` directly, independently of the membrane's ``κ_s``, so that
    ``(ρ, κ_s, κ_b)`` enter mass, membrane and bending separately. The hinge energy is ``k w̄ (θ − θ̄)²``
    (:func:`kernels.shell.bending_energy`); on a square grid bent about a grid axis its continuum limit has
    bending rigidity ``6 k`` per unit width (``4.8 k`` for a free strip).
    """
    e, h, nu = config.base_young, config.thickness, config.poisson
    return config.kappa_b * e * h**3 / (24.0 * (1.0 - nu * nu))


def barrier_stiffness(config: ClothConfig, mean_mass: float, dt: float) -> float:
    """IPC barrier stiffness ``κ``, J/m⁴: the configured one, or C-IPC's rule from the mean vertex mass.

    C-IPC sets the barrier's curvature in the distance at a separation of 10⁻⁸ m, ``4·10⁻¹⁶ b″(10⁻¹⁶)``, to
    ``3·10¹¹ m̄`` in the incremental potential; here the barrier enters as ``Δt² κ B``, hence the ``Δt²``.
    """
    if config.barrier_stiffness is not None:
        return config.barrier_stiffness
    dhat2 = config.contact_distance**2
    d = torch.tensor([1e-16], dtype=F64, device=backend.torch_device())
    curvature = float(ipc_barrier.barrier(d, dhat2)[2][0])
    return 3.0e11 * mean_mass / (dt * dt * 4.0e-16 * curvature)


def friction_potential(
    displacement: torch.Tensor, friction: _Friction, eps: float, hessian: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """IPC's smoothed lagged friction potential ``D = Σ_k μλ_k f₀(‖u_k‖)`` (Li et al. 2020, Eq. 14–16) of the lagged
    contacts, by the Warp kernel :func:`kernels.friction.friction_potential`.

    Args:
        displacement: ``[N, 3]`` displacement of every vertex since the start of the step, m.
        friction: lagged contacts.
        eps: ``ε_v Δt``, m.
        hessian: also return the ``[K, 12, 12]`` Hessians (PSD).

    Returns:
        ``(energy [K] (J), grad [K, 4, 3] (N), hess [K, 12, 12] or None)``.
    """
    f = friction
    return kernels_friction.friction_potential(displacement, f.index, f.weight, f.projector, f.force, eps, hessian)


# ---------------------------------------------------------------------------------------------------------------
# Broad phase
# ---------------------------------------------------------------------------------------------------------------


PARALLEL_SIN2 = 1e-8
"""Edge pairs closer to parallel than ``sin²θ < 10⁻⁸`` over a whole sweep leave the edge–edge candidates.

Their distance is the smallest end point–segment distance, which the point–triangle pairs of the edges' triangles
already bound; the edge-edge kernels classify such pairs by a machine-epsilon test and can report a line-line
distance of 0 for parallel, separated edges."""

REACH = 2.0
"""Contact pairs within ``REACH · d̂`` of each other join the Newton matrix's sparsity pattern when it grows (active
or not yet), so that pairs that close in later seldom change it (each change costs cuDSS a new analysis)."""


def _keep(pairs: _Pairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor) -> _Pairs:
    """The pairs selected by the masks (one read from the device: the counts size the selections)."""
    return _select(pairs, pt_keep, ee_keep, _counts(pairs, pt_keep, ee_keep).tolist())


def _counts(pairs: _Pairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor) -> torch.Tensor:
    """``[4]`` on the device: the garment–body and all point–triangle pairs the masks select, then the same for the
    edge–edge pairs."""
    return torch.stack([pt_keep[: pairs.pt_body].sum(), pt_keep.sum(), ee_keep[: pairs.ee_body].sum(), ee_keep.sum()])


def _select(pairs: _Pairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor, counts: list[int]) -> _Pairs:
    """The pairs selected by the masks, given their :func:`_counts` as read from the device."""
    pt_body, pt, ee_body, ee = counts
    pt_rows = torch.nonzero_static(pt_keep, size=pt).squeeze(1)
    ee_rows = torch.nonzero_static(ee_keep, size=ee).squeeze(1)
    return _Pairs(
        pairs.pt.index_select(0, pt_rows),
        pairs.ee.index_select(0, ee_rows),
        pt_body,
        ee_body,
        pairs.ee_eps.index_select(0, ee_rows),
    )


def _unique_edges(faces: torch.Tensor) -> torch.Tensor:
    f = faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    return torch.unique(e, dim=0)


# ---------------------------------------------------------------------------------------------------------------
# Solver
# ---------------------------------------------------------------------------------------------------------------


class SolverCloth:
    """Codim-IPC garment simulator (PhysAvatar §3.2, Appendix A.3): one implicit step per frame.

    Args:
        vertices: ``[V, 3]`` garment rest positions, m (the rest shape of membrane and bending).
        faces: ``[F, 3]`` garment triangles, consistently oriented, manifold.
        config: material and solver settings.
        body_faces: ``[Fb, 3]`` body collider triangles indexing ``ClothControl.body_start``; may be empty.
        energies: element evaluators (default: the Warp kernels of :mod:`kernels.shell` and :mod:`kernels.contact`;
            with others the Newton loop runs on CUDA as plain calls, not as CUDA graphs, which other evaluators may
            not allow).

    Raises:
        ValueError: malformed meshes; a non-manifold or inconsistently oriented garment (from
            :func:`kernels.shell.hinges_from_faces`).
    """

    def __init__(
        self,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        config: ClothConfig,
        body_faces: torch.Tensor,
        energies: ClothEnergies | None = None,
    ):
        device = backend.torch_device()
        if vertices.dim() != 2 or vertices.shape[1] != 3 or vertices.shape[0] < 3:
            raise ValueError(f"vertices must be a [V, 3] tensor with V >= 3, got {tuple(vertices.shape)}")
        for name, f in (("faces", faces), ("body_faces", body_faces)):
            if f.dim() != 2 or f.shape[1] != 3 or f.dtype.is_floating_point:
                raise ValueError(f"{name} must be an integer [F, 3] tensor, got {f.dtype} {tuple(f.shape)}")
        if faces.shape[0] == 0 or int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]:
            raise ValueError("faces must be non-empty and index the garment vertices")
        self.config = config
        self.energies = energies or ClothEnergies()
        self.vertex_count = vertices.shape[0]
        self.body_vertex_count = int(body_faces.max()) + 1 if body_faces.numel() else 0
        self.x_rest = vertices.to(device, F64).contiguous()
        self.faces = faces.to(device, torch.int32).contiguous()
        self.hinges, _ = shell.hinges_from_faces(self.faces)
        self.rest = shell.rest_state(self.x_rest, self.faces, self.hinges)
        self.mass = lumped_masses(self.x_rest, self.faces, config.density * config.thickness)
        mu, lam = shell.plane_stress_lame(config.young, config.poisson, config.thickness)
        self.membrane_mu, self.membrane_lambda = mu, lam
        self.k_bend = bending_stiffness(config)
        self.gravity = torch.tensor(config.gravity, dtype=F64, device=device)
        self.edges = _unique_edges(self.faces)
        v = self.vertex_count
        self.body_faces = (body_faces.to(device).long() + v).contiguous()
        self.body_edges = _unique_edges(body_faces.to(device)) + v if body_faces.numel() else self.edges[:0]
        # the primitives of the broad phase, as int32 vertex tuples
        self._points = torch.arange(v, dtype=torch.int32, device=device)[:, None].contiguous()
        self._edges = self.edges.to(torch.int32).contiguous()
        self._body_points = torch.arange(v, v + self.body_vertex_count, dtype=torch.int32, device=device)[:, None]
        self._body_faces = self.body_faces.to(torch.int32).contiguous()
        self._body_edges = self.body_edges.to(torch.int32).contiguous()
        solver = config.linear_solver
        if solver == "auto":
            if device.type != "cuda":
                solver = "direct"
            elif cudss.available():
                solver = "cudss"
            else:
                solver = "dense" if 3 * v <= DENSE_MAX_DOFS else "cg"
        self._cudss = cudss.SparseSPDSolver(device) if solver == "cudss" else None  # raises where cuDSS cannot load
        self._unchecked = False  # the last solve queued an unchecked cuDSS factorisation (:meth:`_solved`)
        self._matrices = _NewtonMatrices([self.faces, self.hinges])
        self._loop = _NewtonLoop(self)
        self._kappa: dict[float, float] = {}  # barrier stiffness by step size
        self.linear_solver = solver
        margin = config.candidate_margin
        self.candidate_margin = margin if margin is not None else (5e-3 if device.type == "cuda" else 2e-3)
        self._checked_inside = False

    def initial_state(self) -> ClothState:
        """The rest shape at rest."""
        return ClothState(self.x_rest.clone(), torch.zeros_like(self.x_rest))

    # -- one step ---------------------------------------------------------------------------------------------

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float) -> StepStats:
        """Advance the garment by ``dt`` seconds (one implicit Euler step of the incremental potential).

        Args:
            state_in: garment state at the start of the step.
            state_out: receives the state at the end of the step (may be ``state_in``).
            control: body collider motion and Dirichlet targets of this step.
            dt: step size, s (paper: 0.04).

        Returns:
            :class:`StepStats`.

        Raises:
            ValueError: malformed inputs, a static solve without boundary vertices, or a garment that starts
                inside or touching the body collider.
        """
        with backend.one_torch_thread_on_cpu():
            return self._step(state_in, state_out, control, dt)

    def _context(self, state_in: ClothState, control: ClothControl, dt: float):
        """Checked inputs of a step: ``(X [V + B, 3] at its start, target [V + B, 3], context)`` (no friction yet)."""
        x_start, b0, b1, fixed, target_fixed = self._check_step(state_in, control, dt)
        v, nb = self.vertex_count, self.body_vertex_count
        device = x_start.device
        X = torch.cat([x_start, b0]).contiguous()
        kinematic = torch.zeros(v + nb, dtype=torch.bool, device=device)
        kinematic[fixed] = True
        kinematic[v:] = True
        target = X.clone()
        target[fixed] = target_fixed
        target[v:] = b1
        dof = torch.full((v + nb,), -1, dtype=torch.int32, device=device)
        free = torch.nonzero_static(~kinematic, size=v - fixed.numel()).squeeze(1)  # the boundary holds no repeats
        dof[free] = torch.arange(free.numel(), dtype=torch.int32, device=device)
        x_hat = x_start + dt * state_in.v.to(device, F64) + dt * dt * self.gravity
        if dt not in self._kappa:
            self._kappa[dt] = barrier_stiffness(self.config, float(self.mass.mean()), dt)
        kappa = self._kappa[dt]
        x_rest_all = torch.cat([self.x_rest, b0])
        ctx = _StepContext(dt, kappa, X.clone(), x_hat, x_rest_all, kinematic, dof, free, None)
        return X, target, ctx

    def _step(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float) -> StepStats:
        cfg = self.config
        X, target, ctx = self._context(state_in, control, dt)
        v, kinematic = self.vertex_count, ctx.kinematic
        x_start, b0 = ctx.x_start[:v], ctx.x_start[v:]
        timer = _PhaseTimer(X.device)

        timer.start()
        # the candidates reach from each vertex's start along its predicted path (inertial target, or kinematic
        # target) and a margin beyond: usually every Newton sweep of the step stays inside
        predicted = target.clone()
        if not cfg.static:
            predicted[:v] = torch.where(kinematic[:v, None], target[:v], ctx.x_hat)
        cover = self._cover(X, predicted, ctx, self.candidate_margin)
        searches = 1
        pairs = self._swept(X, torch.zeros_like(X), cover)
        timer.stop("broad_phase")
        self._check_separated(X, pairs, b0)
        if cfg.friction > 0.0 and not cfg.static:
            timer.start()
            ctx = ctx._replace(friction=self._lagged_friction(X, pairs, ctx))
            timer.stop("friction")

        loop = self._loop
        loop.begin(X, target, ctx, cover, pairs)
        converged = False
        stalled = False
        iterations = 0
        while iterations < cfg.max_newton_iterations:
            iterations += 1
            timer.start()
            assembled = loop.assemble()
            timer.stop("assemble")
            for checked in (False, True):
                if checked:  # the factorisation failed: grow the pattern now, then again, waiting on each
                    timer.start()
                    assembled = loop.complete(assembled)
                    timer.stop("assemble")
                timer.start()
                loop.solve(assembled, wait=checked)
                timer.stop("solve")
                read = loop.look(assembled, timer)
                if not self._solved():
                    continue
                if read.missing:  # blocks outside the pattern, bounded on the diagonal: grow it next step
                    loop.defer(assembled)
                break
            if read.overflow:  # more active contacts than the buffers hold: the same iteration with larger ones
                iterations -= 1
                continue
            if read.reached and read.step / dt < cfg.newton_tolerance:
                converged = True
                break
            if not read.covered:  # the sweep left the candidates' reach: search along it
                timer.start()
                X = loop.positions()
                cover = self._cover(X, X + loop.direction(), ctx, self.candidate_margin)
                searches += 1
                loop.set_cover(cover)
                timer.stop("broad_phase")
                read = loop.look(assembled, timer)
            alpha = read.alpha
            if read.reached:
                # backtrack from the CCD bound on E; every trial lies on the sweep, whose candidates hold its contacts
                while alpha > 1e-12 and not read.trial_energy <= read.energy:
                    alpha *= 0.5
                    read = read._replace(trial_energy=loop.trial_energy(alpha, timer))
            if alpha <= 1e-12:
                stalled = True
                break
            loop.accept(snap=alpha == 1.0 and not read.reached)  # once reached, the kinematic vertices stay there

        X = loop.positions().clone()
        state_out.x = X[:v].clone()
        state_out.v = torch.zeros_like(state_out.x) if cfg.static else (state_out.x - x_start) / dt
        # the pairs whose boxes at X lie within d̂ (the cover holds them all: X is on the last sweep)
        near = self._sweep_masks(X, torch.zeros_like(X), cover)
        d_body, d_self, contacts = self._min_distances(X, cover.pairs, near)
        return StepStats(iterations, converged, d_body, d_self, contacts, timer.totals(), searches, stalled)

    # -- parameter sensitivities ------------------------------------------------------------------------------

    def sensitivity_step(
        self,
        state_in: ClothState,
        state_out: ClothState,
        control: ClothControl,
        dt: float,
        s_x: torch.Tensor,
        s_v: torch.Tensor,
        parameters: tuple[str, ...] = SENSITIVITY_PARAMETERS[1:],
        exact_hessian: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Carry the derivatives of the state with respect to material parameters through one step (Eq. 5).

        Call it right after :meth:`step` with the same ``state_in`` (kept unchanged: pass a separate
        ``state_out`` to the step), ``control`` and ``dt``, and with the step's result as ``state_out``. The end
        state ``x⁺`` is a minimiser of the incremental potential ``E(x⁺; x, v, θ)``, so on the free vertices
        ``∇E(x⁺) = 0``; differentiating that identity with respect to ``θ`` (implicit function theorem) gives,
        with ``S = ∂x/∂θ`` and ``S_v = ∂v/∂θ`` at the start of the step,

        ``H S⁺ = M (S + Δt S_v) + Δt² H_D S − ∂_θ ∇E``  on the free DOFs,  ``S⁺ = 0`` on Dirichlet DOFs,
        ``S_v⁺ = (S⁺ − S) / Δt``,

        where ``H`` is the Hessian of ``E`` at ``x⁺`` (inertia, membrane, bending, barrier and friction, without
        the PSD projection of the Newton solve unless ``exact_hessian`` is False: the implicit function theorem
        needs the true Hessian, which at a minimiser is positive definite as a whole even where single elements
        are not), ``H_D`` the friction Hessian (friction depends on the displacement ``x⁺ − x`` of the step, hence
        the ``S`` term) and ``∂_θ ∇E`` the explicit derivative of the gradient:

        * ``κ_s``: ``Δt² ∇Ψ_s / κ_s`` (the membrane is linear in ``κ_s``);
        * ``κ_b``: ``Δt² ∇Ψ_b / κ_b`` (the bending is linear in ``κ_b``);
        * ``ρ``: ``(M (x⁺ − x̂) + Δt² (κ∇B + ∇D)) / ρ``: the inertia (gravity included) is linear in ``ρ``, and so
          are barrier and friction while :attr:`ClothConfig.barrier_stiffness` is ``None`` (``κ ∝`` mean mass);
          with a fixed barrier stiffness only the inertia term remains.

        In a static solve there is no inertia or friction: ``H S⁺ = −∂_θ ∇E`` and ``S_v⁺ = 0``.

        Approximations, all of the simulator's own model: friction's lagged quantities (normal forces, contact
        normals and closest-point weights, evaluated at the start of the step) are held constant; the contact
        set is that of ``x⁺``; the body and the Dirichlet targets do not depend on ``θ``. The identity holds at
        an exact minimiser, so the sensitivities are as accurate as the step's Newton tolerance allows. Cost:
        one assembly and one sparse factorisation (direct solver; one CG solve per parameter on CUDA) per step.

        Args:
            state_in: garment state at the start of the step.
            state_out: the state :meth:`step` returned.
            control: the step's control.
            dt: the step's size, s.
            s_x: ``[V, 3, P]`` ``∂x/∂θ`` at the start of the step, m per parameter unit.
            s_v: ``[V, 3, P]`` ``∂v/∂θ`` at the start of the step, m/s per parameter unit.
            parameters: the ``P`` parameters, in the order of the last axis, from :data:`SENSITIVITY_PARAMETERS`
                (``"density"`` in kg/m³, ``"kappa_s"``, ``"kappa_b"``).
            exact_hessian: solve with the exact Hessian (True) or the PSD-projected one of the Newton solve.

        Returns:
            ``(s_x_out [V, 3, P], s_v_out [V, 3, P])`` at the end of the step.

        Raises:
            ValueError: malformed inputs or unknown parameter names.
        """
        with backend.one_torch_thread_on_cpu():
            return self._sensitivity_step(state_in, state_out, control, dt, s_x, s_v, tuple(parameters), exact_hessian)

    def _sensitivity_step(self, state_in, state_out, control, dt, s_x, s_v, parameters, exact_hessian):
        cfg = self.config
        v, nb = self.vertex_count, self.body_vertex_count
        unknown = [name for name in parameters if name not in SENSITIVITY_PARAMETERS]
        if unknown or not parameters or len(set(parameters)) != len(parameters):
            raise ValueError(
                f"parameters {parameters} must be distinct names from {SENSITIVITY_PARAMETERS}, at least one"
            )
        count = len(parameters)
        X_start, X, ctx = self._context(state_in, control, dt)  # X: the targets, body at the end of the step
        device = X.device
        for name, t in (("s_x", s_x), ("s_v", s_v)):
            if tuple(t.shape) != (v, 3, count):
                raise ValueError(
                    f"{name} must have shape [{v}, 3, {count}] (vertices, xyz, parameters), got {list(t.shape)}"
                )
        if tuple(state_out.x.shape) != (v, 3):
            raise ValueError(f"state_out.x must have shape [{v}, 3], got {list(state_out.x.shape)}")
        X[:v] = torch.where(ctx.kinematic[:v, None], X[:v], state_out.x.to(device, F64))
        s_x = s_x.to(device, F64)
        s_v = s_v.to(device, F64)
        dynamic = not cfg.static
        if cfg.friction > 0.0 and dynamic:
            pairs_start = self._broad_phase(X_start, torch.zeros_like(X_start), ctx)
            ctx = ctx._replace(friction=self._lagged_friction(X_start, pairs_start, ctx))
        pairs = self._broad_phase(X, torch.zeros_like(X), ctx)
        parts: dict[str, torch.Tensor] = {}
        _, grad, elements = self._potential(X, self._near(X, pairs, ctx), ctx, project=not exact_hessian, parts=parts)
        matrix, _ = self._assemble(elements, grad, torch.zeros_like(X), ctx)

        rhs = X.new_zeros(v + nb, 3, count)
        if dynamic:
            rhs[:v] = self.mass[:, None, None] * (s_x + dt * s_v)
            friction = ctx.friction
            if friction is not None and friction.index.shape[0]:
                _, _, f_hess = friction_potential(X - X_start, friction, cfg.friction_velocity * dt, True)
                s_all = torch.cat([s_x, s_x.new_zeros(nb, 3, count)])
                k = friction.index.shape[0]
                coupled = torch.bmm(dt * dt * f_hess, s_all[friction.index].reshape(k, 12, count))
                rhs.index_add_(0, friction.index.reshape(-1), coupled.reshape(k * 4, 3, count))
        zero = torch.zeros_like(X)
        for j, name in enumerate(parameters):
            if name == "kappa_s":
                explicit = parts.get("membrane", zero) / cfg.kappa_s
            elif name == "kappa_b":
                explicit = parts.get("bending", zero) / cfg.kappa_b
            else:
                explicit = parts.get("inertia", zero)
                if cfg.barrier_stiffness is None:
                    explicit = explicit + parts.get("contact", zero) + parts.get("friction", zero)
                explicit = explicit / cfg.density
            rhs[:, :, j] -= explicit
        free = ctx.free
        solution = self._solve(matrix, rhs[free].reshape(-1, count))
        s_x_out = s_x.new_zeros(v, 3, count)
        s_x_out[free] = solution.view(-1, 3, count)
        s_v_out = (s_x_out - s_x) / dt if dynamic else torch.zeros_like(s_x_out)
        return s_x_out, s_v_out

    # -- pieces of a step -------------------------------------------------------------------------------------

    def _check_step(self, state_in: ClothState, control: ClothControl, dt: float):
        device = backend.torch_device()
        v, nb = self.vertex_count, self.body_vertex_count
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt ({dt}) must be a positive number of seconds (paper: 0.04)")
        for name, t in (("state_in.x", state_in.x), ("state_in.v", state_in.v)):
            if tuple(t.shape) != (v, 3):
                raise ValueError(f"{name} must have shape [{v}, 3], got {list(t.shape)}")
        for name, t in (("control.body_start", control.body_start), ("control.body_end", control.body_end)):
            if tuple(t.shape) != (nb, 3):
                raise ValueError(f"{name} must have shape [{nb}, 3] (the body mesh's vertices), got {list(t.shape)}")
        fixed = control.boundary_index.to(device).long()
        if fixed.dim() != 1 or tuple(control.boundary_target.shape) != (fixed.numel(), 3):
            raise ValueError("boundary_index must be [D] and boundary_target [D, 3]")
        if self.config.static and fixed.numel() == 0:
            raise ValueError(
                "a static solve needs boundary vertices: with boundary_index empty the garment has no equilibrium "
                "under gravity; pin the vertices attached to the body (e.g. the shoulder region)"
            )
        x = state_in.x.to(device, F64).contiguous()
        # the checks of values, in one read from the device
        checks = [torch.isfinite(x).all(), torch.isfinite(state_in.v.to(device)).all()]
        if fixed.numel():
            ordered = fixed.sort().values
            checks += [(ordered[0] >= 0) & (ordered[-1] < v), (ordered[1:] != ordered[:-1]).all()]
        finite_x, finite_v, *index = torch.stack(checks).tolist()
        for name, finite in (("state_in.x", finite_x), ("state_in.v", finite_v)):
            if not finite:
                raise ValueError(f"{name} holds NaN or inf values")
        if index and not index[0]:
            raise ValueError(f"boundary_index must index garment vertices 0..{v - 1}")
        if index and not index[1]:
            raise ValueError("boundary_index holds repeated vertices; pass each Dirichlet vertex once")
        b0 = control.body_start.to(device, F64).contiguous()
        b1 = control.body_end.to(device, F64).contiguous()
        return x, b0, b1, fixed, control.boundary_target.to(device, F64)

    def _check_separated(self, X: torch.Tensor, pairs: _Pairs, b0: torch.Tensor) -> None:
        """Refuse a start state that touches the body or lies inside it (the barrier needs a positive gap)."""
        v = self.vertex_count
        if not self._checked_inside and self.body_faces.numel():
            inside = MeshBVH(b0, self.body_faces - v, winding_numbers=True).inside(X[:v])
            if bool(inside.any()):
                raise ValueError(
                    f"{int(inside.sum())} garment vertices start inside the body collider (e.g. vertex "
                    f"{int(inside.nonzero()[0])}); place the garment outside the body, at least d̂ away"
                )
            self._checked_inside = True
        d_body, d_self, _ = self._min_distances(X, pairs)
        if not (d_body > 0.0 and d_self > 0.0):
            raise ValueError(
                "the garment touches or intersects "
                + ("the body" if not d_body > 0.0 else "itself")
                + " at the start of the step; start from an intersection-free state"
            )

    def _broad_phase(self, X: torch.Tensor, p: torch.Tensor, ctx: _StepContext) -> _Pairs:
        """Contact candidates whose boxes, swept over ``X → X + p`` and grown by ``d̂``, overlap (IPC)."""
        return self._swept(X, p, self._cover(X, X + p, ctx, 0.0))

    def _cover(self, X: torch.Tensor, end: torch.Tensor, ctx: _StepContext, margin: float) -> _Cover:
        """Candidates of every sweep that keeps each vertex inside the box of its segment ``X → end`` grown by
        ``margin``: pairs whose primitives' boxes (unions of their vertices' boxes, the query side grown by ``d̂``)
        overlap. Pairs of kinematic vertices only are left out.

        Growing each box by its segment's own extent as well (so that Newton may overshoot the prediction) halved
        the searches of the 1252-face skirt walking but tripled the candidates; filtering them then cost more on
        the CPU than the searches saved."""
        lo, hi = torch.minimum(X, end) - margin, torch.maximum(X, end) + margin
        return _Cover(lo, hi, self._box_pairs(lo, hi, ctx))

    @staticmethod
    def _covers(cover: _Cover, X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Whether the sweep ``X → X + p`` keeps every vertex inside its box of ``cover`` (0-d bool, on the device:
        the caller reads it with the step's other flags)."""
        end = X + p
        inside = (torch.minimum(X, end) >= cover.lo) & (torch.maximum(X, end) <= cover.hi)
        return inside.all()

    def _swept(self, X: torch.Tensor, p: torch.Tensor, cover: _Cover) -> _Pairs:
        """The candidates of ``cover`` whose boxes, swept over ``X → X + p`` and grown by ``d̂``, overlap, less
        edge pairs parallel at both ends of the sweep (:data:`PARALLEL_SIN2`). Equal to a fresh search of the sweep
        when ``cover`` covers it (:meth:`_covers`)."""
        return _keep(cover.pairs, *self._sweep_masks(X, p, cover))

    def _sweep_masks(self, X: torch.Tensor, p: torch.Tensor, cover: _Cover) -> tuple[torch.Tensor, torch.Tensor]:
        """The masks of :meth:`_swept` over ``cover``'s point–triangle and edge–edge candidates (no read)."""
        dhat = self.config.contact_distance
        pairs = cover.pairs
        pt_keep = kernels_contact.pair_boxes_overlap(X, p, pairs.pt, 1, dhat)
        return pt_keep, kernels_contact.pair_boxes_overlap(X, p, pairs.ee, 2, dhat, parallel=PARALLEL_SIN2)

    def _box_pairs(self, lo: torch.Tensor, hi: torch.Tensor, ctx: _StepContext) -> _Pairs:
        """Pairs whose primitives' boxes overlap, given each vertex's box ``[lo, hi]`` (the query side grown by
        ``d̂``): garment vertices and edges against body triangles and edges, then the garment against itself.
        Pairs that share a vertex or whose vertices are all kinematic are left out.

        The BVHs are over the garment's primitives only: a body primitive far from the garment stops at the root
        (a skirt meets the hips, not the 15k triangles of the whole body)."""
        dhat = self.config.contact_distance
        lo, hi = lo.contiguous(), hi.contiguous()
        kinematic = ctx.kinematic
        points = BoxTree(lo, hi, self._points)
        triangles = BoxTree(lo, hi, self.faces)
        edges = BoxTree(lo, hi, self._edges)
        pt_vb, pt_bv, ee_b, pt_self, ee_self = find_overlaps(
            [  # garment vertices against body triangles, body vertices against garment triangles, body edges
                OverlapQuery(points, self._body_faces, dhat, kinematic, tree_first=True),
                OverlapQuery(triangles, self._body_points, dhat, kinematic),
                OverlapQuery(edges, self._body_edges, dhat, kinematic, tree_first=True),
                # then the garment against itself
                OverlapQuery(triangles, self._points, dhat, kinematic),
                OverlapQuery(edges, self._edges, dhat, kinematic, same=True),
            ]
        )
        pt_body, ee_body = pt_vb.shape[0] + pt_bv.shape[0], ee_b.shape[0]
        ee = torch.cat([ee_b, ee_self])
        eps = ipc_barrier.edge_edge_mollifier_threshold(ctx.x_rest, ee)
        return _Pairs(torch.cat([pt_vb, pt_bv, pt_self]), ee, pt_body, ee_body, eps)

    def _near(self, X: torch.Tensor, pairs: _Pairs, ctx: _StepContext) -> _Pairs:
        """The candidates whose boxes at ``X`` lie within ``d̂`` (a superset of the active barrier pairs)."""
        dhat = self.config.contact_distance
        pt_keep = kernels_contact.pair_boxes_overlap(X, None, pairs.pt, 1, dhat)
        return _keep(pairs, pt_keep, kernels_contact.pair_boxes_overlap(X, None, pairs.ee, 2, dhat))

    def _ccd_bound(self, X: torch.Tensor, p: torch.Tensor, pairs: _Pairs) -> torch.Tensor:
        """Largest step fraction in ``[0, 1]`` that additive CCD certifies intersection-free (Li et al. 2021), 0-d on
        the device."""
        eta = self.config.ccd_eta
        times = [X.new_ones(1)]
        if pairs.pt.shape[0]:
            times.append(ccd.point_triangle_ccd(X, p, pairs.pt, eta=eta))
        if pairs.ee.shape[0]:
            times.append(ccd.edge_edge_ccd(X, p, pairs.ee, eta=eta))
        return torch.cat(times).min()

    def _potential(
        self,
        X: torch.Tensor,
        candidates: _Pairs,
        ctx: _StepContext,
        project: bool = True,
        parts: dict[str, torch.Tensor] | None = None,
        active: tuple[torch.Tensor, torch.Tensor] | None = None,
    ):
        """Incremental potential ``E(X)``, its gradient ``[V + B, 3]`` and the element Hessians (:meth:`_energy` is
        ``E`` alone). ``candidates`` may be any superset of the contact pairs within ``d̂`` of ``X``. ``active``, when
        given, is :meth:`_active_rows` of ``X`` and ``candidates`` (a fixed number of rows, padded: the Newton loop on
        CUDA); each contact element's ``reach`` is then its own pairs, not the pairs within ``REACH · d̂``.

        The element Hessians are to be PSD-filtered as they are assembled (:class:`_Element`), unless ``project`` is
        False (friction's are PSD by construction).
        ``parts``, when given, receives the gradient ``[V + B, 3]`` of each term that is present, by name:
        ``"inertia"`` (``M (x − x̂)``, or ``−Δt² M g`` in a static solve), and, scaled by ``Δt²``, ``"membrane"``,
        ``"bending"``, ``"contact"`` and ``"friction"``.

        Returns ``(energy, grad, elements)`` with ``elements`` a list of :class:`_Element`.
        """
        cfg, dt2 = self.config, ctx.dt * ctx.dt
        v = self.vertex_count
        x = X[:v].contiguous()
        # every element term is scaled by Δt²: their energies and gradients are summed unscaled, then scaled once
        term_energies: list[torch.Tensor] = []
        term_grad = torch.zeros_like(X)
        elements: list[_Element] = []
        free_mask = ~ctx.kinematic[:v]

        def add(index, terms, name: str, projection: str = "none", reach=None) -> None:
            term_energies.append(terms.energy)
            term_grad.index_add_(0, index.reshape(-1), terms.grad.reshape(-1, 3))
            if index.shape[0] or reach is not None and reach.shape[0]:
                elements.append(_Element(index, terms.hess, dt2, projection, reach))
            if parts is not None:
                part = parts.setdefault(name, torch.zeros_like(X))
                part.index_add_(0, index.reshape(-1), dt2 * terms.grad.reshape(-1, 3))

        if cfg.static:
            energy = -dt2 * (self.mass[:, None] * self.gravity * x).sum()
            inertia = -dt2 * self.mass[:, None] * self.gravity
        else:
            r = (x - ctx.x_hat) * free_mask[:, None]
            energy = 0.5 * (self.mass[:, None] * r * r).sum()
            inertia = self.mass[:, None] * r
        if parts is not None:
            parts["inertia"] = torch.zeros_like(X)
            parts["inertia"][:v] = inertia
        absolute = cfg.elastic_projection == "abs" or (cfg.elastic_projection == "auto" and not cfg.static)
        elastic_projection = ("abs" if absolute else "clamp") if project else "none"

        e = self.energies
        rest = self.rest
        in_kernel = cfg.membrane_filter == "stress"  # the membrane's Hessians are made PSD in the kernel
        membrane = e.membrane(
            x, self.faces, rest.rest_inv, rest.rest_area, self.membrane_mu, self.membrane_lambda,
            stress_filter=elastic_projection if in_kernel else "none",
        )  # fmt: skip
        add(self.faces, membrane, "membrane", "none" if in_kernel else elastic_projection)
        bending = e.bending(x, self.hinges, rest.rest_angle, rest.rest_weight, self.k_bend)
        add(self.hinges, bending, "bending", elastic_projection)
        if candidates.pt.shape[0] or candidates.ee.shape[0]:
            # Derivatives only for the active pairs (within d̂), which the distance-only kernels pick, with the pairs
            # within REACH · d̂ that a pattern miss grows the sparsity pattern by. On skirt7271 walking the active
            # pairs are a tenth of those whose boxes lie within d̂ of X.
            dhat2 = cfg.contact_distance**2
            c = candidates
            if active is None:
                pt_active, ee_active, pt_reach, ee_reach = self._active_rows(X, c, reach=True)
                pt_reach, ee_reach = c.pt[pt_reach], c.ee[ee_reach]
            else:
                pt_active, ee_active = active
            pt_pairs, ee_pairs = c.pt[pt_active], c.ee[ee_active]
            if active is not None:
                pt_reach, ee_reach = pt_pairs, ee_pairs
            pt, ee = e.contact(X, pt_pairs, ee_pairs, c.ee_eps[ee_active], dhat2, ctx.kappa)
            for index, reach, terms in ((pt_pairs, pt_reach, pt), (ee_pairs, ee_reach, ee)):
                add(index, terms, "contact", "clamp" if project else "none", reach=reach)
        if ctx.friction is not None and ctx.friction.index.shape[0]:
            f_energy, f_grad, f_hess = friction_potential(
                X - ctx.x_start, ctx.friction, cfg.friction_velocity * ctx.dt, True
            )
            index = ctx.friction.index.to(torch.int32)
            add(index, element_terms.ElementTerms(f_energy, f_grad, f_hess), "friction", "none")  # PSD already
        # the element terms scaled once, as :meth:`_energy` sums them
        energy = energy + dt2 * torch.cat(term_energies).sum()
        grad = term_grad.mul_(dt2)
        grad[:v] += inertia
        return energy, grad, elements

    def _active_rows(
        self, X: torch.Tensor, candidates: _Pairs, capacity: tuple[int, int] | None = None, reach: bool = False
    ) -> tuple[torch.Tensor, ...]:
        """Rows of ``candidates``' point–triangle and edge–edge pairs within ``d̂`` at ``X`` (the active barrier pairs),
        by the distance-only kernels; with ``reach``, then the rows within ``REACH · d̂``.

        With ``capacity`` (no reach), exactly that many rows of each, the last candidate row (a phantom pair:
        :class:`_NewtonLoop`) filling the rest, and then the ``[2]`` counts of active pairs, all without a read from
        the device; else exactly the rows selected (a read)."""
        dhat2 = self.config.contact_distance**2
        d_pt = ipc_barrier.point_triangle_distance_value(X, candidates.pt)
        d_ee = ipc_barrier.edge_edge_distance_value(X, candidates.ee)
        if capacity is not None:
            masks = (d_pt < dhat2, d_ee < dhat2)
            rows = [_compact(mask, size) for mask, size in zip(masks, capacity, strict=True)]
            return *rows, torch.stack([mask.sum() for mask in masks])
        limits = (dhat2, REACH**2 * dhat2) if reach else (dhat2,)
        return tuple(_compact(d < limit) for limit in limits for d in (d_pt, d_ee))

    def _energy(self, X: torch.Tensor, near: _Pairs, ctx: _StepContext) -> torch.Tensor:
        """The incremental potential ``E(X)`` of :meth:`_potential` alone (0-d), from the energy-only kernels: what
        the line search compares, without the element derivatives. ``near`` may be any superset of the pairs within
        ``d̂`` (the others add exact zeros): the line search passes the sweep's candidates unfiltered."""
        cfg, dt2 = self.config, ctx.dt * ctx.dt
        v = self.vertex_count
        x = X[:v].contiguous()
        if cfg.static:
            energy = -dt2 * (self.mass[:, None] * self.gravity * x).sum()
        else:
            r = (x - ctx.x_hat) * (~ctx.kinematic[:v])[:, None]
            energy = 0.5 * (self.mass[:, None] * r * r).sum()
        e, rest = self.energies, self.rest
        terms = [
            e.membrane_value(x, self.faces, rest.rest_inv, rest.rest_area, self.membrane_mu, self.membrane_lambda),
            e.bending_value(x, self.hinges, rest.rest_angle, rest.rest_weight, self.k_bend),
        ]
        if near.pt.shape[0] or near.ee.shape[0]:
            terms.extend(e.contact_value(X, near.pt, near.ee, near.ee_eps, cfg.contact_distance**2, ctx.kappa))
        if ctx.friction is not None and ctx.friction.index.shape[0]:
            terms.append(friction_potential(X - ctx.x_start, ctx.friction, cfg.friction_velocity * ctx.dt, False)[0])
        return energy + dt2 * torch.cat(terms).sum()

    def _assemble(self, elements: list[_Element], grad: torch.Tensor, p_kin: torch.Tensor, ctx: _StepContext):
        """The Newton matrix of the free DOFs and the right-hand side ``−g_f − H_fk p_k`` (``[n, 3]``).

        ``p_kin`` is zero on the free vertices: the blocks that join a free vertex to a kinematic one push
        ``H_fk p_k`` to the right-hand side, the others land in the matrix (:mod:`kernels.assembly`).
        """
        mass = None if self.config.static else self.mass[ctx.free]
        return self._matrices.assemble(elements, -grad[ctx.free], ctx.dof, p_kin, mass)

    def _solve(self, matrix: _Matrix, rhs: torch.Tensor, wait: bool = True) -> torch.Tensor:
        """Solve ``H p = rhs`` for the free DOFs (``H`` SPD; ``rhs`` ``[3n]`` or ``[3n, P]``).

        With ``wait`` False, cuDSS's factorisation is not checked before its solve is queued: :meth:`_solved` says
        afterwards whether the result holds (a failed factorisation leaves garbage, which the check then catches).
        """
        self._unchecked = False
        n = matrix.pattern.n
        if n == 0:
            return rhs.new_zeros(rhs.shape)
        if rhs.dim() == 2 and self.linear_solver == "cg":
            return torch.stack([self._solve(matrix, rhs[:, j]) for j in range(rhs.shape[1])], 1)
        if self.linear_solver == "dense":
            return _dense_solve(matrix, rhs)
        if self.linear_solver == "cudss":
            pattern = matrix.pattern
            if not wait:
                self._cudss.queue_factor(pattern.crow, pattern.col, matrix.values)
                self._unchecked = True
            elif not self._cudss.factor(pattern.crow, pattern.col, matrix.values):
                return _dense_solve(matrix, rhs)
            return self._cudss.solve(rhs)
        if self.linear_solver == "direct":
            return torch.from_numpy(_sparse_spd_solve(matrix.to_scipy(), rhs.cpu().numpy())).to(rhs.device)
        return _block_jacobi_cg(matrix, rhs, self.config.cg_tolerance, self.config.cg_max_iterations)

    def _solved(self) -> bool:
        """Whether the last :meth:`_solve` holds (only an unchecked cuDSS factorisation can fail silently)."""
        return not self._unchecked or self._cudss.positive_definite()

    def _lagged_friction(self, X: torch.Tensor, pairs: _Pairs, ctx: _StepContext) -> _Friction:
        """Normal forces ``μλ_k``, closest-point weights and tangent projectors of the contacts at ``x^t`` (IPC §5),
        by the Warp kernel :func:`kernels.friction.lagged_contacts`."""
        dhat2, mu = self.config.contact_distance**2, self.config.friction
        return _Friction(*kernels_friction.lagged_contacts(X, pairs.pt, pairs.ee, pairs.ee_eps, dhat2, ctx.kappa, mu))

    def _min_distances(
        self, X: torch.Tensor, pairs: _Pairs, masks: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[float, float, int]:
        """Smallest garment–body and garment–garment distances among the pairs (those ``masks`` select, when given),
        m (inf where there are none), and the number of pairs within ``d̂``; one read from the device."""
        dhat2 = self.config.contact_distance**2
        d_pt = ipc_barrier.point_triangle_distance_value(X, pairs.pt)
        d_ee = ipc_barrier.edge_edge_distance_value(X, pairs.ee)
        if masks is not None:
            d_pt, d_ee = (torch.where(mask, d, math.inf) for mask, d in zip(masks, (d_pt, d_ee), strict=True))
        inf = X.new_full((1,), math.inf)
        body = torch.cat([d_pt[: pairs.pt_body], d_ee[: pairs.ee_body], inf])
        own = torch.cat([d_pt[pairs.pt_body :], d_ee[pairs.ee_body :], inf])
        contacts = (body < dhat2).sum() + (own < dhat2).sum()
        body, own, contacts = torch.stack([body.min(), own.min(), contacts.to(X.dtype)]).tolist()
        return math.sqrt(max(body, 0.0)), math.sqrt(max(own, 0.0)), int(contacts)


class _StepContext(NamedTuple):
    dt: float
    kappa: float
    x_start: torch.Tensor  # [V + B, 3] positions at the start of the step
    x_hat: torch.Tensor  # [V, 3] inertial target
    x_rest: torch.Tensor  # [V + B, 3] rest positions (mollifier thresholds)
    kinematic: torch.Tensor  # [V + B] bool
    dof: torch.Tensor  # [V + B] int32 free index or −1
    free: torch.Tensor  # [n] free vertices
    friction: _Friction | None


class _PhaseTimer:
    """Seconds per phase of a step (:data:`PHASES`), charged between :meth:`start` and :meth:`stop`.

    On CUDA each mark is an event recorded on the stream, so that a phase is charged with its own kernels without
    the host waiting for them (a synchronising clock would stall the launch queue at every phase boundary); the
    elapsed times are read once, by :meth:`totals` at the end of the step. On the CPU it is ``time.perf_counter``.
    """

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.times = dict.fromkeys(PHASES, 0.0)
        self.spans: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []
        self._start: float | torch.cuda.Event = 0.0

    def _mark(self) -> float | torch.cuda.Event:
        if not self.cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def start(self) -> None:
        self._start = self._mark()

    def stop(self, phase: str) -> None:
        end = self._mark()
        if self.cuda:
            self.spans.append((phase, self._start, end))
        else:
            self.times[phase] += end - self._start

    def totals(self) -> dict[str, float]:
        if self.spans:
            self.spans[-1][2].synchronize()
            for phase, start, end in self.spans:
                self.times[phase] += start.elapsed_time(end) * 1e-3
            self.spans.clear()
        return dict(self.times)


def _sparse_spd_solve(h: scipy.sparse.csc_matrix, rhs):
    """Solve ``h x = rhs`` for a sparse SPD ``h`` by SuperLU with a symmetric ordering and diagonal pivots.

    The fill-reducing ordering of ``hᵀ + h`` only pays off if the factorisation keeps to the diagonal: with
    SuperLU's default threshold pivoting it swaps rows of this matrix, loses the ordering and fills in ~8× slower
    (``docs/benchmarks.md``). An SPD matrix needs no pivoting, so the diagonal pivot
    threshold is 0 (a Cholesky-like LDU); should a pivot vanish in floating point, the solve is repeated with
    SuperLU's partial pivoting.
    """
    try:
        lu = scipy.sparse.linalg.splu(
            h, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        x = lu.solve(rhs)
        if np.isfinite(x).all():
            return x
    except RuntimeError:  # "Factor is exactly singular"
        pass
    return scipy.sparse.linalg.splu(h, permc_spec="COLAMD").solve(rhs)


class _Element(NamedTuple):
    """One kind of element of the incremental potential, as the Newton matrix receives it."""

    index: torch.Tensor  # [N, k] int32 vertices (garment and body)
    hess: torch.Tensor  # [N, 3k, 3k] Hessians, unscaled and unfiltered
    scale: float  # factor on each Hessian (Δt²)
    projection: str  # PSD filter: "none", "clamp" (eigenvalues at least zero) or "abs" (their absolute values)
    reach: torch.Tensor | None  # [M, k] contacts: the candidates within REACH · d̂, the active ones among them; a
    # pattern miss grows the pattern by all their blocks, so that pairs that come within d̂ later seldom change it


class _Matrix(NamedTuple):
    """A Newton matrix of the free vertices: its block pattern and the values in the pattern's scalar CSR order."""

    pattern: assembly.BlockPattern
    values: torch.Tensor

    def to_dense(self) -> torch.Tensor:
        size = 3 * self.pattern.n
        crow = self.pattern.crow.long()
        rows = torch.repeat_interleave(torch.arange(size, device=crow.device), crow[1:] - crow[:-1])
        h = torch.zeros(size, size, dtype=self.values.dtype, device=self.values.device)
        h[rows, self.pattern.col.long()] = self.values
        return h

    def to_scipy(self) -> scipy.sparse.csc_matrix:
        """As SciPy's CSC matrix: the CSR arrays of a symmetric matrix read as CSC arrays give the same matrix."""
        size = 3 * self.pattern.n
        arrays = (self.values, self.pattern.col, self.pattern.crow)
        return scipy.sparse.csc_matrix(tuple(t.cpu().numpy() for t in arrays), shape=(size, size))


class _NewtonMatrices:
    """Assembles each Newton matrix on a block pattern that only grows while the free vertices stay the same.

    The pattern starts as that of the garment's elements (membrane and bending join each vertex to its
    neighbours; body contacts add no block of their own, since only one garment vertex or one garment edge takes
    part). Self-contacts come and go: an assembly that meets a block outside the pattern (a pair of vertices joined
    for the first time) bounds it on the diagonal (:mod:`kernels.assembly`: the matrix stays SPD, its direction a
    descent direction), and the Newton loop, which reads the count of such blocks with its other flags, keeps that
    matrix and defers the growth (:meth:`defer`): at the next step's :meth:`prepare` the pattern grows by every
    block of the elements at hand and of the contact candidates within :data:`REACH` · d̂. cuDSS analyses a pattern
    anew whenever it changes, at some 30 times the cost of a numeric factorisation (``docs/benchmarks.md``), so the
    pattern grows at most once a step and outlives the step: it restarts from the garment's elements only when the
    free vertices change or when contacts have doubled it.

    Each element kind's Hessians are PSD-filtered by one batched eigensolver call
    (:func:`kernels.element_terms.project_psd`), then scattered by one Warp launch (:mod:`kernels.assembly`).
    """

    def __init__(self, elastic: list[torch.Tensor]):
        self.elastic = elastic
        self.pattern: assembly.BlockPattern | None = None
        self.version = 0  # counts the patterns set
        self._mass_slots: torch.Tensor | None = None
        self.dof: torch.Tensor | None = None  # the last step's free DOFs, as begin_step was given them
        self._copy: torch.Tensor | None = None  # and their values then
        self.elastic_blocks = 0
        self._pending: list[torch.Tensor] = []  # block keys that the next step's pattern takes (:meth:`defer`)

    def _set_pattern(self, pattern: assembly.BlockPattern) -> None:
        self.pattern = pattern
        self.version += 1
        self._mass_slots = pattern.diagonal[:, [0, 1, 2], [0, 1, 2]].reshape(-1)  # each free DOF's diagonal entry

    def begin_step(self, dof: torch.Tensor, n: int) -> None:
        """The pattern for a step's free DOFs ``dof`` (``n`` free vertices): the last one, grown by the blocks
        deferred to it, if the free vertices are the same and it has not doubled, else the garment's elements'."""
        same = self._copy is not None and self._copy.shape == dof.shape and bool(torch.equal(self._copy, dof))
        if not same or self.pattern.block_col.numel() > 2 * self.elastic_blocks:
            keys = torch.cat([assembly.block_keys(index, dof, n) for index in self.elastic])
            self._set_pattern(assembly.block_pattern(keys, n))
            self.elastic_blocks = self.pattern.block_col.numel()
        elif self._pending:
            self._set_pattern(assembly.block_pattern(torch.cat([self.pattern.keys(), *self._pending]), n))
        self._pending = []
        self.dof, self._copy = dof, dof.clone()

    def prepare(self, elements: list[_Element], dof: torch.Tensor, n: int) -> list[_Element]:
        """The pattern for this step's free DOFs ``dof`` (``n`` free vertices; a ``dof`` tensor other than the last
        one starts a step: :meth:`begin_step`), and ``elements`` as :meth:`scatter` takes them: the non-empty ones,
        PSD-filtered (:func:`_filtered`)."""
        if dof is not self.dof:
            self.begin_step(dof, n)
        return _filtered(elements)

    def scatter(self, active: list[_Element], rhs: torch.Tensor, dof: torch.Tensor, p_kin, mass):
        """``(_Matrix, rhs [n, 3], missing)``: ``Σ`` scaled element Hessians of ``active`` (from :meth:`prepare`)
        plus ``diag(mass)`` (when given), ``rhs`` less the kinematic pushes, and the number of blocks that fell
        outside the pattern (1-element int32 tensor, left on the device: nonzero means the matrix is incomplete;
        :meth:`grow` the pattern and scatter again)."""
        p_kin = p_kin.contiguous()
        values = rhs.new_zeros(self.pattern.col.numel())
        out = rhs.clone()
        missing = torch.zeros(1, dtype=torch.int32, device=rhs.device)
        if mass is not None:
            values[self._mass_slots] = mass.repeat_interleave(3)
        for element in active:
            index, hess, scale = element.index, element.hess, element.scale
            assembly.scatter_hessians(self.pattern, values, out, missing, index, hess, dof, p_kin, scale)
        return _Matrix(self.pattern, values), out, missing

    def grow(self, elements: list[_Element], dof: torch.Tensor, n: int) -> None:
        """Add every block of ``elements`` and of their reach (:class:`_Element`) to the pattern."""
        self._set_pattern(assembly.block_pattern(torch.cat([self.pattern.keys(), *_keys(elements, dof, n)]), n))

    def defer(self, elements: list[_Element], dof: torch.Tensor, n: int) -> None:
        """:meth:`grow` at the next step's :meth:`prepare` (if the pattern does not restart then), not now. The
        garment's elements are in the pattern already: only the contacts' and friction's blocks are kept."""
        others = [e for e in elements if not any(e.index is index for index in self.elastic)]
        self._pending = [torch.unique(torch.cat([*self._pending, *_keys(others, dof, n)]))]

    def assemble(self, elements: list[_Element], rhs: torch.Tensor, dof: torch.Tensor, p_kin, mass):
        """``(_Matrix, rhs [n, 3])`` of :meth:`scatter`, the pattern grown until it holds every block."""
        return self.complete(self.prepare(elements, dof, rhs.shape[0]), elements, rhs, dof, p_kin, mass)

    def complete(self, active: list[_Element], elements: list[_Element], rhs: torch.Tensor, dof, p_kin, mass):
        """:meth:`assemble` from the prepared ``active`` elements: :meth:`scatter` them, :meth:`grow` the pattern by
        ``elements`` (from which they were prepared) while blocks fall outside it, and scatter again."""
        while True:
            matrix, out, missing = self.scatter(active, rhs, dof, p_kin, mass)
            if int(missing) == 0:
                return matrix, out
            self.grow(elements, dof, rhs.shape[0])


# ---------------------------------------------------------------------------------------------------------------
# The Newton loop on buffers that stay put
# ---------------------------------------------------------------------------------------------------------------


_PHANTOM = ((1000.0, 1000.0, 1000.0), (1001.0, 1000.0, 1000.0), (1010.0, 1010.0, 1010.0), (1010.0, 1011.0, 1010.0))
"""Four kinematic vertices that :class:`_NewtonLoop` appends to the positions, km away from any garment: the phantom
pair over them (point 0 against triangle 1-2-3, and edge 0-1 against edge 2-3) pads the pair buffers on CUDA. Its
boxes lie metres apart, its distance is far beyond ``d̂`` and nothing moves it, so every kernel gives it zeros."""


def _capacity(count: int) -> int:
    """Rows of a pair buffer that holds ``count`` pairs and a phantom one, with a quarter to spare: a power of two
    (at least 256), so that a buffer grows, and its graphs are captured anew, a few times at most."""
    return max(256, 1 << math.ceil(math.log2(1.25 * (count + 1))))


def _compact(mask: torch.Tensor, size: int | None = None) -> torch.Tensor:
    """Rows where ``mask`` holds, in order: all of them (their number is read from the device), or exactly ``size``
    rows with the last row of the masked array filling the rest (no read: the caller checks the count)."""
    if size is None:
        return mask.nonzero().squeeze(1)
    return torch.nonzero_static(mask, size=size, fill_value=mask.shape[0] - 1).squeeze(1)


class _Read(NamedTuple):
    """What the host reads of a Newton iteration, in one read from the device (:meth:`_NewtonLoop.look`)."""

    energy: float  # E at X
    missing: bool  # blocks outside the pattern were bounded on the diagonal
    overflow: bool  # more active pairs than their buffers hold: the iteration must run again (CUDA)
    reached: bool  # every kinematic vertex is on its target
    covered: bool  # the sweep X → X + p stays inside the candidates' cover
    step: float  # ‖p_f‖_∞, m
    alpha: float  # the sweep's CCD bound (nan where not needed)
    trial_energy: float  # E at X + α p (nan where not needed)


class _Assembled(NamedTuple):
    """One Newton system (:meth:`_NewtonLoop.assemble`)."""

    energy: torch.Tensor  # 0-d
    grad: torch.Tensor  # [N, 3]
    elements: list[_Element]  # as the potential gave them
    filtered: list[_Element]  # PSD-filtered, as scattered
    matrix: _Matrix
    rhs: torch.Tensor  # [n, 3]
    missing: torch.Tensor  # [1] int32
    p_kin: torch.Tensor  # [N, 3]
    active: torch.Tensor | None  # [2] active pairs (CUDA)


class _NewtonLoop:
    """The Newton iterations of a step as four phases over buffers that stay put: each is one CUDA graph on CUDA
    (:class:`kernels.backend.CapturedCall`), a plain call on the CPU.

    * ``assemble``: the potential at ``X``, its gradient, the PSD-filtered element Hessians, and the Newton matrix and
      right-hand side (the sparse solve follows, outside any graph: cuDSS does not capture);
    * ``sweep``: the direction ``p``, the candidates whose boxes meet over the sweep ``X → X + p`` (kept: they hold
      every pair within d̂ of any point of the sweep, so the next iteration's contacts too), and the flags;
    * ``ccd``: the sweep's CCD bound ``α``;
    * ``trial``: ``E`` at ``X + α p``.

    An iteration launches about 270 torch operations and 30 Warp kernels. On an H100 their launches from Python cost
    more than their kernels (``docs/benchmarks.md``); replayed as four graphs, they cost the host a few launches. A
    graph keeps the shapes, addresses and Python scalars it was captured with, so on CUDA every pair list lives in a
    buffer of fixed capacity, padded with the phantom pair (:data:`_PHANTOM`), and the selections (the sweep's
    candidates, the active contacts) are compacted into such buffers on the device (:func:`_compact`). A count
    beyond its buffer grows the buffer (:func:`_capacity`) and runs the phases again; new buffers, a new pattern or a
    new ``Δt`` capture the graphs anew. On the CPU the lists have their exact sizes and the flags are read between
    the phases, so the CCD and the trial run only when needed.
    """

    def __init__(self, solver: SolverCloth, static: bool | None = None):
        self.solver = solver
        if static is None:  # graphs of the project's kernels (other element evaluators may not capture)
            static = solver.x_rest.device.type == "cuda" and solver.energies == ClothEnergies()
        self.static = static  # fixed shapes, and CUDA graphs on CUDA
        self.capacity: dict[str, int] = {}
        phases = (self._assemble, self._sweep, self._ccd, self._trial)
        self.phases = [backend.CapturedCall(f, capture=self.static) for f in phases]
        self._key: tuple | None = None
        self._phantom = torch.tensor(_PHANTOM, dtype=F64, device=solver.x_rest.device)
        self._trial_x: torch.Tensor | None = None

    # -- buffers ----------------------------------------------------------------------------------------------

    # the phases (assemble 0, sweep 1, CCD 2, trial 3) that read or write each buffer other than those all four do
    _READERS = {
        "x_start": (0, 3),
        "x_hat": (0, 3),
        "free": (0, 1),
        "dof": (0,),
        "p_free": (1,),
        "p": (1, 2, 3),
        "alpha": (2, 3),
        **{name: (1,) for name in ("cover_lo", "cover_hi", "cover_pt", "cover_ee", "cover_eps")},
        **{name: (0, 3) for name in ("f_index", "f_weight", "f_projector", "f_force")},
    }

    def _put(self, name: str, value: torch.Tensor) -> None:
        """Store ``value`` as buffer ``name``: on CUDA in place where the shapes agree (the graphs read it there),
        else as new storage, which the phases that use it must be captured anew for."""
        old = getattr(self, name, None)
        if not self.static:
            setattr(self, name, value)
        elif isinstance(old, torch.Tensor) and old.shape == value.shape and old.dtype == value.dtype:
            old.copy_(value)
        else:
            setattr(self, name, value.clone())
            self._reset(self._READERS.get(name, range(4)))

    def _padded(self, name: str, rows: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """``rows`` on CUDA padded with ``pad`` to the capacity of buffer ``name`` (grown if they do not fit)."""
        if not self.static:
            return rows
        if rows.shape[0] + 1 > self.capacity.get(name, 0):
            self.capacity[name] = _capacity(rows.shape[0])
        return torch.cat([rows, pad.expand(self.capacity[name] - rows.shape[0], *pad.shape[1:])])

    def _grow(self, name: str, count: int) -> bool:
        """Grow buffer ``name``'s capacity if ``count`` pairs and a phantom do not fit; whether it grew."""
        if count + 1 <= self.capacity[name]:
            return False
        self.capacity[name] = _capacity(count)
        return True

    def _reset(self, phases=range(4)) -> None:
        for k in phases:
            self.phases[k].reset()

    def begin(self, X: torch.Tensor, target: torch.Tensor, ctx: _StepContext, cover: _Cover, pairs: _Pairs) -> None:
        """Load a step: positions ``X [V + B, 3]`` and targets at its start, its context, candidates' cover and the
        candidates at ``X``; the pattern of the step's Newton matrices."""
        s = self.solver
        device = X.device
        phantom = self._phantom
        self.rows = X.shape[0]  # garment and body vertices: the phantoms follow
        self._put("X", torch.cat([X, phantom]))
        self._put("x_start", torch.cat([ctx.x_start, phantom]))
        self._put("target", torch.cat([target, phantom]))
        self._put("kinematic", torch.cat([ctx.kinematic, torch.ones(4, dtype=torch.bool, device=device)]))
        self._put("dof", torch.cat([ctx.dof, torch.full((4,), -1, dtype=torch.int32, device=device)]))
        self._put("free", ctx.free)
        self._put("x_hat", ctx.x_hat)
        self._put("p", torch.zeros_like(self.X))
        self._put("p_free", torch.zeros(3 * ctx.free.numel(), dtype=F64, device=device))
        self._put("alpha", torch.ones((), dtype=F64, device=device))
        n = self.rows
        self.pair_pad = torch.arange(n, n + 4, dtype=torch.int32, device=device)[None]
        self.set_cover(cover)
        self._put_pairs("swept", pairs)
        friction = ctx.friction
        if friction is not None:
            zero = torch.zeros((), dtype=F64, device=device)
            self._put("f_index", self._padded("friction", friction.index, self.pair_pad.long()))
            self._put("f_weight", self._padded("friction", friction.weight, zero.expand(1, 4)))
            self._put("f_projector", self._padded("friction", friction.projector, zero.expand(1, 3, 3)))
            self._put("f_force", self._padded("friction", friction.force, zero.expand(1)))
            friction = _Friction(self.f_index, self.f_weight, self.f_projector, self.f_force)
        self.ctx = ctx._replace(
            x_start=self.x_start, x_hat=self.x_hat, kinematic=self.kinematic, dof=self.dof, free=self.free,
            friction=friction,
        )  # fmt: skip
        s._matrices.begin_step(ctx.dof, ctx.free.numel())
        if self.static:
            for name in ("active_pt", "active_ee"):
                self.capacity.setdefault(name, _capacity(0))
        key = (ctx.dt, ctx.kappa, friction is None, s._matrices.version)
        if self._key is None or key[:-1] != self._key[:-1]:
            self._reset()  # Python scalars the graphs hold
        elif key != self._key:
            self._reset([0])  # a new pattern: the assembly's
        self._key = key

    def set_cover(self, cover: _Cover) -> None:
        """Load new candidates (a search along a sweep that left the last ones' reach)."""
        one = torch.ones(1, dtype=F64, device=cover.lo.device)
        pairs = cover.pairs
        self._put("cover_lo", cover.lo)
        self._put("cover_hi", cover.hi)
        self._put("cover_pt", self._padded("cover_pt", pairs.pt, self.pair_pad))
        self._put("cover_ee", self._padded("cover_ee", pairs.ee, self.pair_pad))
        self._put("cover_eps", self._padded("cover_ee", pairs.ee_eps, one))

    def _put_pairs(self, name: str, pairs: _Pairs) -> None:
        one = torch.ones(1, dtype=F64, device=pairs.pt.device)
        self._put(f"{name}_pt", self._padded(f"{name}_pt", pairs.pt, self.pair_pad))
        self._put(f"{name}_ee", self._padded(f"{name}_ee", pairs.ee, self.pair_pad))
        self._put(f"{name}_eps", self._padded(f"{name}_ee", pairs.ee_eps, one))

    def _swept_pairs(self) -> _Pairs:
        return _Pairs(self.swept_pt, self.swept_ee, 0, 0, self.swept_eps)

    def positions(self) -> torch.Tensor:
        """``X [V + B, 3]``, the current iterate."""
        return self.X[: self.rows]

    def direction(self) -> torch.Tensor:
        """``p [V + B, 3]``, the last direction."""
        return self.p[: self.rows]

    # -- phases -----------------------------------------------------------------------------------------------

    def _assemble(self) -> _Assembled:
        s, X = self.solver, self.X
        swept = self._swept_pairs()
        active = counts = None
        if self.static:
            *active, counts = s._active_rows(X, swept, (self.capacity["active_pt"], self.capacity["active_ee"]))
        energy, grad, elements = s._potential(X, swept, self.ctx, active=active)
        filtered = _filtered(elements)
        p_kin = torch.where(self.kinematic[:, None], self.target - X, torch.zeros_like(X))
        mass = None if s.config.static else s.mass[self.free]
        matrix, rhs, missing = s._matrices.scatter(filtered, -grad[self.free], self.dof, p_kin, mass)
        return _Assembled(energy, grad, elements, filtered, matrix, rhs, missing, p_kin, counts)

    def _sweep(self) -> torch.Tensor:
        s, X = self.solver, self.X
        p = torch.where(self.kinematic[:, None], self.target - X, torch.zeros_like(X))
        reached = (p == 0).all()
        p.index_copy_(0, self.free, self.p_free.view(-1, 3))
        step = self.p_free.abs().max() if self.p_free.numel() else p.new_zeros(())
        n = self.rows
        cover = _Cover(self.cover_lo, self.cover_hi, _Pairs(self.cover_pt, self.cover_ee, 0, 0, self.cover_eps))
        covered = s._covers(cover, X[:n], p[:n])
        pt_keep, ee_keep = s._sweep_masks(X, p, cover)
        if self.static:
            self.p.copy_(p)
            pt_rows = _compact(pt_keep, self.capacity["swept_pt"])
            ee_rows = _compact(ee_keep, self.capacity["swept_ee"])
            self.swept_pt.copy_(self.cover_pt[pt_rows])
            self.swept_ee.copy_(self.cover_ee[ee_rows])
            self.swept_eps.copy_(self.cover_eps[ee_rows])
        else:
            self.p = p
            pt_rows, ee_rows = _compact(pt_keep), _compact(ee_keep)
            self.swept_pt, self.swept_ee = self.cover_pt[pt_rows], self.cover_ee[ee_rows]
            self.swept_eps = self.cover_eps[ee_rows]
        counts = [pt_keep.sum(), ee_keep.sum()]
        return torch.stack([reached.to(F64), covered.to(F64), step.to(F64), *(c.to(F64) for c in counts)])

    def _ccd(self) -> torch.Tensor:
        bound = self.solver._ccd_bound(self.X, self.p, self._swept_pairs())
        if self.static:
            self.alpha.copy_(bound)
        else:
            self.alpha = bound
        return bound

    def _trial(self) -> tuple[torch.Tensor, torch.Tensor]:
        trial = self.X + self.alpha * self.p
        return trial, self.solver._energy(trial, self._swept_pairs(), self.ctx)

    # -- what the step calls ----------------------------------------------------------------------------------

    def assemble(self) -> _Assembled:
        """The Newton system at ``X``."""
        return self.phases[0]()

    def solve(self, assembled: _Assembled, wait: bool) -> None:
        """Its direction on the free vertices (:meth:`SolverCloth._solve`)."""
        p_free = self.solver._solve(assembled.matrix, assembled.rhs.reshape(-1), wait=wait)
        if self.static:
            self.p_free.copy_(p_free)
        else:
            self.p_free = p_free

    def look(self, assembled: _Assembled, timer: _PhaseTimer) -> _Read:
        """The sweep, its CCD bound and the trial at the bound, and what the host needs of them and of
        ``assembled``, in one read. On CUDA the three phases run before the read (CCD and trial are wasted where the
        step has converged or the sweep leaves the cover); on the CPU the flags are read first."""
        a, dt, tolerance = assembled, self.ctx.dt, self.solver.config.newton_tolerance
        while True:
            timer.start()
            flags = self.phases[1]()
            timer.stop("broad_phase")
            head = [a.energy.reshape(1), a.missing.to(F64), flags]
            if not self.static:
                energy, missing, reached, covered, step, _, _ = torch.cat(head).tolist()
                if not covered or reached and step / dt < tolerance:  # the step's own test
                    return _Read(energy, missing > 0, False, reached == 1.0, covered == 1.0, step, math.nan, math.nan)
            timer.start()
            self.phases[2]()
            timer.stop("ccd")
            timer.start()
            self._trial_x, trial_energy = self.phases[3]()
            timer.stop("line_search")
            tail = [self.alpha.reshape(1), trial_energy.reshape(1)]
            if a.active is not None:
                tail.append(a.active.to(F64))
            energy, missing, reached, covered, step, swept_pt, swept_ee, alpha, trial_energy, *active = torch.cat(
                head + tail
            ).tolist()
            if self.static:
                grew = [self._grow(name, int(c)) for name, c in (("swept_pt", swept_pt), ("swept_ee", swept_ee))]
                if any(grew):  # the sweep's candidates did not fit: larger buffers, the same phases again
                    self._regrow()
                    continue
            overflow = False
            if active:
                grew = [self._grow(name, int(c)) for name, c in zip(("active_pt", "active_ee"), active, strict=True)]
                overflow = any(grew)
                if overflow:
                    self._reset([0])
            reached, covered = reached == 1.0, covered == 1.0
            return _Read(energy, missing > 0, overflow, reached, covered, step, alpha, trial_energy)

    def _regrow(self) -> None:
        """New swept buffers at their grown capacities (their contents are the sweep phase's to write)."""
        for name, width in (("swept_pt", 4), ("swept_ee", 4)):
            setattr(self, name, self.pair_pad.expand(self.capacity[name], width).clone())
        self.swept_eps = torch.ones(self.capacity["swept_ee"], dtype=F64, device=self.X.device)
        self._reset()

    def trial_energy(self, alpha: float, timer: _PhaseTimer) -> float:
        """``E`` at ``X + α p`` (a backtracking step of the line search)."""
        if self.static:
            self.alpha.fill_(alpha)
        else:
            self.alpha = torch.tensor(alpha, dtype=F64, device=self.X.device)
        timer.start()
        self._trial_x, energy = self.phases[3]()
        energy = float(energy)
        timer.stop("line_search")
        return energy

    def accept(self, snap: bool) -> None:
        """Move ``X`` to the last trial; ``snap`` puts the kinematic vertices on their targets exactly."""
        X = self._trial_x
        if snap:
            X = torch.where(self.kinematic[:, None], self.target, X)
        if self.static:
            self.X.copy_(X)
        else:
            self.X = X

    def _with_reach(self, elements: list[_Element]) -> list[_Element]:
        """``elements`` with each contact element's reach the candidates within ``REACH · d̂`` (on CUDA the loop's
        contact elements carry their own pairs)."""
        if not self.static:
            return elements
        swept = self._swept_pairs()
        _, _, pt_reach, ee_reach = self.solver._active_rows(self.X, swept, reach=True)
        reach = iter([swept.pt[pt_reach], swept.ee[ee_reach]])
        return [e._replace(reach=next(reach)) if e.reach is not None else e for e in elements]

    def defer(self, assembled: _Assembled) -> None:
        """Grow the pattern by the blocks of ``assembled`` at the next step (:meth:`_NewtonMatrices.defer`)."""
        self.solver._matrices.defer(self._with_reach(assembled.elements), self.dof, self.free.numel())

    def complete(self, assembled: _Assembled) -> _Assembled:
        """``assembled`` on a pattern grown until it holds every block (:meth:`_NewtonMatrices.complete`)."""
        s, a = self.solver, assembled
        mass = None if s.config.static else s.mass[self.free]
        elements = self._with_reach(a.elements)
        matrix, rhs = s._matrices.complete(a.filtered, elements, -a.grad[self.free], self.dof, a.p_kin, mass)
        self._reset([0])  # the assembly's graph holds the old pattern
        self._key = (*self._key[:-1], s._matrices.version)
        return a._replace(matrix=matrix, rhs=rhs, missing=torch.zeros_like(a.missing))


def _keys(elements: list[_Element], dof: torch.Tensor, n: int) -> list[torch.Tensor]:
    """The block keys of ``elements`` and of their reach (:class:`_Element`)."""
    return [assembly.block_keys(e.index if e.reach is None else e.reach, dof, n) for e in elements]


def _filtered(elements: list[_Element]) -> list[_Element]:
    """The non-empty ``elements`` with their Hessians PSD-filtered.

    One batched eigensolver call per element kind: one call over bending and contact Hessians together (contact
    Hessians many orders of magnitude stiffer than the bending's) slowed cuSOLVER's batched ``syevd`` down
    (``docs/benchmarks.md``)."""
    out = []
    for element in elements:
        if not element.index.shape[0]:
            continue
        if element.projection != "none":
            hess = element_terms.project_psd(element.hess, absolute=element.projection == "abs")
            element = element._replace(hess=hess, projection="none")
        out.append(element)
    return out


def _dense_solve(matrix: _Matrix, rhs: torch.Tensor) -> torch.Tensor:
    """Solve ``H x = rhs`` densely on the device: Cholesky, or LU where ``H`` is not positive definite (the exact
    Hessians of a sensitivity step may not be)."""
    h = matrix.to_dense()
    factor, info = torch.linalg.cholesky_ex(h)
    column = rhs if rhs.dim() == 2 else rhs[:, None]
    x = torch.cholesky_solve(column, factor) if int(info) == 0 else torch.linalg.solve(h, column)
    return x if rhs.dim() == 2 else x[:, 0]


def _block_jacobi_cg(matrix: _Matrix, rhs: torch.Tensor, tol: float, max_iterations: int) -> torch.Tensor:
    """Conjugate gradients on the sparse SPD ``H`` with the inverse 3×3 diagonal blocks as preconditioner."""
    pattern, values = matrix
    n = pattern.n
    with warnings.catch_warnings():  # "sparse CSR support is in beta": mv on CSR is all this needs
        warnings.simplefilter("ignore", UserWarning)
        h = torch.sparse_csr_tensor(pattern.crow, pattern.col, values, (3 * n, 3 * n), check_invariants=False)
    d_inv = torch.linalg.inv(values[pattern.diagonal])

    def precondition(res: torch.Tensor) -> torch.Tensor:
        return torch.bmm(d_inv, res.view(n, 3, 1)).reshape(-1)

    x = torch.zeros_like(rhs)
    res = rhs.clone()
    z = precondition(res)
    p = z.clone()
    rz = torch.dot(res, z)
    stop = tol * tol * float(torch.dot(rhs, rhs))
    for k in range(max_iterations):
        hp = torch.mv(h, p)
        step = rz / torch.dot(p, hp)
        x += step * p
        res -= step * hp
        # the residual test reads the device's value back: every 8th iteration, so a GPU is not stalled each time
        if k % 8 == 7 and float(torch.dot(res, res)) <= stop:
            break
        z = precondition(res)
        rz_next = torch.dot(res, z)
        p = z + (rz_next / rz) * p
        rz = rz_next
    return x
