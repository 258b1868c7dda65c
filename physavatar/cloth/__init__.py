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
  ``D = κ_b E₀ h³/(12(1 − ν²))``) and a free narrow strip ``4.8 k`` per unit width
  (tests/physavatar/cloth/test_solver.py derives both).

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

Execution: on CUDA the Newton iterations are four CUDA graphs over buffers of fixed capacity
(:class:`~physavatar.cloth.newton_loop.NewtonLoop`), with the sparse solve between them and one read from the device
per iteration; on the CPU the same phases are plain calls over exact pair lists.

The package's modules, each built from the ones before it:

* :mod:`~physavatar.cloth.config`: :class:`ClothConfig`, the settings every part reads;
* :mod:`~physavatar.cloth.contact`: contact candidates, their covers, the broad phase, the CCD bound, lagged friction;
* :mod:`~physavatar.cloth.newton_system`: the Newton matrices on their block pattern and the linear solver;
* :mod:`~physavatar.cloth.potential`: the incremental potential, its gradient and element Hessians, the material;
* :mod:`~physavatar.cloth.newton_loop`: the Newton iterations of a step, over those three parts;
* :mod:`~physavatar.cloth.solver`: :class:`SolverCloth`, its state, control, statistics and sensitivities;
* :mod:`~physavatar.cloth.rollout`: :class:`ClothRollout`, a rollout as a torch operation with an adjoint backward;
* :mod:`~physavatar.cloth.picking`: :class:`GarmentDrag`, a garment vertex picked by a ray and dragged or pinned by
  springs of the step's potential (:attr:`ClothControl.spring_index`).
"""

from physavatar.cloth.config import DENSITY_RANGE, LINEAR_SOLVERS, STIFFNESS_RANGE, ClothConfig
from physavatar.cloth.contact import (
    PARALLEL_SIN2,
    REACH,
    TREE_REBUILD,
    ClothContact,
    ContactCover,
    ContactPairs,
    GarmentDistances,
    LaggedFriction,
    compact_rows,
    friction_potential,
    garment_distances,
    keep_pairs,
)
from physavatar.cloth.newton_loop import PHASES, AssembledSystem, LoopRead, NewtonLoop, PhaseTimer
from physavatar.cloth.newton_system import (
    DENSE_MAX_DOFS,
    LinearSolver,
    NewtonElement,
    NewtonMatrices,
    NewtonMatrix,
    filtered_elements,
)
from physavatar.cloth.picking import GarmentDrag, GarmentPick
from physavatar.cloth.potential import (
    ClothEnergies,
    IncrementalPotential,
    StepContext,
    barrier_stiffness,
    bending_stiffness,
    lumped_masses,
)
from physavatar.cloth.rollout import ClothRollout, RolloutScene, rollout
from physavatar.cloth.solver import (
    SENSITIVITY_PARAMETERS,
    ClothControl,
    ClothState,
    ClothStepReport,
    SolverCloth,
    StepLinearisation,
)

__all__ = [
    "AssembledSystem",
    "ClothConfig",
    "ClothContact",
    "ClothControl",
    "ClothEnergies",
    "ClothRollout",
    "ClothState",
    "ClothStepReport",
    "ContactCover",
    "ContactPairs",
    "DENSE_MAX_DOFS",
    "DENSITY_RANGE",
    "GarmentDistances",
    "GarmentDrag",
    "GarmentPick",
    "IncrementalPotential",
    "LINEAR_SOLVERS",
    "LaggedFriction",
    "LinearSolver",
    "LoopRead",
    "NewtonElement",
    "NewtonLoop",
    "NewtonMatrices",
    "NewtonMatrix",
    "PARALLEL_SIN2",
    "PHASES",
    "PhaseTimer",
    "REACH",
    "RolloutScene",
    "SENSITIVITY_PARAMETERS",
    "STIFFNESS_RANGE",
    "SolverCloth",
    "StepContext",
    "StepLinearisation",
    "TREE_REBUILD",
    "barrier_stiffness",
    "bending_stiffness",
    "compact_rows",
    "filtered_elements",
    "friction_potential",
    "garment_distances",
    "keep_pairs",
    "lumped_masses",
    "rollout",
]
