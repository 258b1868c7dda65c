"""The garment simulator's solver: :class:`SolverCloth`, its state, control and step statistics.

:class:`SolverCloth` builds the simulator from its parts (:mod:`physavatar.cloth`): the incremental potential
(:class:`~physavatar.cloth.potential.IncrementalPotential`), the contact
(:class:`~physavatar.cloth.contact.ClothContact`) and the Newton system
(:class:`~physavatar.cloth.newton_system.NewtonMatrices`, :class:`~physavatar.cloth.newton_system.LinearSolver`),
which the Newton loop (:class:`~physavatar.cloth.newton_loop.NewtonLoop`) runs through. It checks each step's
inputs, drives the loop and carries parameter sensitivities through a converged step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from kernels import backend, ccd, ipc_barrier, shell
from kernels import contact as contact_kernels
from kernels.raycast import MeshBVH
from physavatar.cloth.config import ClothConfig
from physavatar.cloth.contact import ClothContact, ContactPairs, LaggedFriction, friction_potential
from physavatar.cloth.newton_loop import NewtonLoop, PhaseTimer
from physavatar.cloth.newton_system import LinearSolver, NewtonElement, NewtonMatrices
from physavatar.cloth.potential import ClothEnergies, IncrementalPotential, StepContext, bending_stiffness

__all__ = [
    "SENSITIVITY_PARAMETERS",
    "ClothControl",
    "ClothState",
    "SolverCloth",
    "ClothStepReport",
    "StepLinearisation",
]

F64 = torch.float64
SENSITIVITY_PARAMETERS = ("density", "kappa_s", "kappa_b")
"""The material parameters :meth:`SolverCloth.sensitivity_step` differentiates with respect to."""


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
        spring_index: ``[S]`` int64 garment vertices pulled by a zero-rest-length spring (a mouse drag, a pin), or
            ``None``. Each adds ``½ k_s ‖x_i − t_s‖²`` to the step's potential (times ``Δt²``, as every force term),
            so the step stays a minimisation and its contact guarantees hold; a spring on a Dirichlet vertex
            does nothing.
        spring_target: ``[S, 3]`` where each spring pulls, m.
        spring_stiffness: ``[S]`` their stiffness ``k_s``, N/m (positive).
    """

    body_start: torch.Tensor
    body_end: torch.Tensor
    boundary_index: torch.Tensor
    boundary_target: torch.Tensor
    spring_index: torch.Tensor | None = None
    spring_target: torch.Tensor | None = None
    spring_stiffness: torch.Tensor | None = None

    @staticmethod
    def free(device: torch.device | None = None) -> ClothControl:
        """No body and no boundary vertices."""
        empty = torch.zeros(0, 3, dtype=F64, device=device)
        return ClothControl(empty, empty, torch.zeros(0, dtype=torch.int64, device=device), empty)


@dataclass
class ClothStepReport:
    """What one step did.

    Attributes:
        newton_iterations: Newton iterations taken.
        converged: the tolerance was met with every kinematic vertex on its target.
        min_distance_body: smallest garment–body distance among pairs within ``d̂`` after the step, m (inf if none).
        min_distance_self: smallest garment–garment distance among non-adjacent pairs within ``d̂``, m (inf if none).
        contacts: active barrier pairs after the step.
        time: seconds spent per phase (:data:`~physavatar.cloth.newton_loop.PHASES`).
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


@dataclass
class StepLinearisation:
    """One converged step's incremental potential, linearised at its end state (:meth:`SolverCloth.linearise_step`).

    Attributes:
        matrix: the Hessian ``H`` of ``E`` on the free DOFs at ``x⁺`` (the linear solver's matrix, for
            ``solver.linear.solve(matrix, rhs [3n, P])``); valid until the solver assembles again.
        free: ``[n]`` the free garment vertices, in the order of the matrix's block rows.
        positions: ``[V + B, 3]`` ``x⁺`` with the body at the end of the step, m.
        parts: the gradient ``[V + B, 3]`` of each term of ``E`` at ``x⁺`` by name (``IncrementalPotential.evaluate``).
        friction: the lagged friction of the step (``None`` without friction or contacts at its start).
        friction_hessian: ``[K, 12, 12]`` Hessian ``H_D`` of the friction potential at ``x⁺ − x`` (unscaled, N/m),
            ``None`` with ``friction``.
    """

    matrix: object
    free: torch.Tensor
    positions: torch.Tensor
    parts: dict[str, torch.Tensor]
    friction: LaggedFriction | None
    friction_hessian: torch.Tensor | None


@dataclass
class _StepBuffers:
    """What a step of :class:`SolverCloth` fills in place rather than allocating (``N = V + B``): the positions at
    its start ``X`` and a copy of them ``x_start`` ``[N, 3]``, the ``target`` and ``predicted`` end positions
    ``[N, 3]``, the zero sweep ``[N, 3]``, the rest positions of garment and body ``x_rest_all [N, 3]`` (m), the
    inertial target ``x_hat [V, 3]`` (m) and ``Δt² g [3]``, the ``kinematic`` mask and its complement ``moving``
    ``[N]``, the free DOF map ``dof [N]`` int32, the ``V − D`` free vertices ``free_rows [V − D, 1]`` (``free`` is
    their column) and ``counting`` ``0 … V − 1`` int32."""

    X: torch.Tensor
    x_start: torch.Tensor
    target: torch.Tensor
    predicted: torch.Tensor
    zero: torch.Tensor
    x_rest_all: torch.Tensor
    x_hat: torch.Tensor
    gravity_step: torch.Tensor
    kinematic: torch.Tensor
    moving: torch.Tensor
    dof: torch.Tensor
    free_rows: torch.Tensor
    free: torch.Tensor
    counting: torch.Tensor

    @staticmethod
    def make(vertex_count: int, body_vertex_count: int, boundary_count: int, device: torch.device) -> _StepBuffers:
        """The buffers of a garment of ``V`` vertices, a body of ``B`` and ``D`` Dirichlet vertices."""
        v, n = vertex_count, vertex_count + body_vertex_count
        points = [torch.zeros(n, 3, dtype=F64, device=device) for _ in range(6)]
        free_rows = torch.zeros(v - boundary_count, 1, dtype=torch.int64, device=device)
        return _StepBuffers(
            *points,
            x_hat=torch.zeros(v, 3, dtype=F64, device=device),
            gravity_step=torch.zeros(3, dtype=F64, device=device),
            kinematic=torch.zeros(n, dtype=torch.bool, device=device),
            moving=torch.zeros(n, dtype=torch.bool, device=device),
            dof=torch.zeros(n, dtype=torch.int32, device=device),
            free_rows=free_rows,
            free=free_rows[:, 0],
            counting=torch.arange(v, dtype=torch.int32, device=device),
        )


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
        # the garment's kernels are built now, not at the first contact (each kernel module builds at its first launch)
        backend.load_warp_modules(shell, ipc_barrier, contact_kernels, ccd)
        self.config = config
        self.vertex_count = vertices.shape[0]
        self.body_vertex_count = int(body_faces.max()) + 1 if body_faces.numel() else 0
        self.x_rest = vertices.to(device, F64).contiguous()
        self.faces = faces.to(device, torch.int32).contiguous()
        self.potential = IncrementalPotential(self.x_rest, self.faces, config, energies or ClothEnergies())
        self.contact = ClothContact(self.faces, body_faces, self.vertex_count, self.body_vertex_count, config)
        self.linear = LinearSolver(config, device, self.vertex_count)  # raises where cuDSS is asked for and cannot load
        self.linear_solver = self.linear.kind
        self.matrices = NewtonMatrices([self.faces, self.potential.hinges], config.eigen_dtype(device))
        self.loop = NewtonLoop(self.potential, self.contact, self.matrices, self.linear, config.newton_tolerance)
        margin = config.candidate_margin
        self.candidate_margin = margin if margin is not None else (5e-3 if device.type == "cuda" else 2e-3)
        self._checked_inside = False
        self._step_buffers: _StepBuffers | None = None  # made at the first step (:meth:`_buffers`)

    def initial_state(self) -> ClothState:
        """The rest shape at rest."""
        return ClothState(self.x_rest.clone(), torch.zeros_like(self.x_rest))

    # -- one step ---------------------------------------------------------------------------------------------

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float) -> ClothStepReport:
        """Advance the garment by ``dt`` seconds (one implicit Euler step of the incremental potential).

        Args:
            state_in: garment state at the start of the step.
            state_out: receives the state at the end of the step, written into its own tensors (float64 ``[V, 3]``
                on the backend device, as :meth:`initial_state` makes them); may be ``state_in``. Callers keep two
                states and swap them after each step.
            control: body collider motion and Dirichlet targets of this step.
            dt: step size, s (paper: 0.04).

        Returns:
            :class:`ClothStepReport`.

        Raises:
            ValueError: malformed inputs (``state_out`` included), a static solve without boundary vertices, or a
                garment that starts inside or touching the body collider.
        """
        with backend.one_torch_thread_on_cpu():
            return self._step(state_in, state_out, control, dt)

    def step_context(self, state_in: ClothState, control: ClothControl, dt: float, state_out: ClothState | None = None):
        """Checked inputs of a step: ``(X [V + B, 3] at its start, target [V + B, 3], context)`` (no friction yet).

        Everything it returns lives in the solver's step buffers (:meth:`_buffers`), filled in place: valid until the
        next call, which overwrites them. All of ``state_in`` is read here, so a step may write its result into the
        same state; ``state_out``, when given, is checked as the step's output (:meth:`_check_step`)."""
        x_start, b0, b1, fixed, target_fixed = self._check_step(state_in, control, dt, state_out)
        v = self.vertex_count
        buf = self._buffers(fixed.numel())
        X = torch.cat([x_start, b0], out=buf.X)
        kinematic = buf.kinematic
        kinematic.fill_(False)
        kinematic[fixed] = True
        kinematic[v:] = True
        target = buf.target.copy_(X)
        target[fixed] = target_fixed
        target[v:] = b1
        dof = buf.dof.fill_(-1)
        # the boundary holds no repeats: exactly V - D free vertices
        torch.nonzero_static(torch.logical_not(kinematic, out=buf.moving), size=buf.free.numel(), out=buf.free_rows)
        free = buf.free
        dof[free] = buf.counting[: free.numel()]
        # x̂ = x + Δt v + Δt² g, in the order of the sums as written
        x_hat = torch.mul(state_in.v.to(x_start.device, F64), dt, out=buf.x_hat)
        torch.add(x_start, x_hat, out=x_hat)
        x_hat.add_(torch.mul(self.potential.gravity, dt * dt, out=buf.gravity_step))
        kappa = self.potential.kappa(dt)
        x_rest_all = torch.cat([self.x_rest, b0], out=buf.x_rest_all)
        # the start is a buffer of its own, not X: X goes back to the caller, and the step reads the start again
        # after its Newton loop (the velocity), so nothing done with X may reach it
        ctx = StepContext(dt, kappa, buf.x_start.copy_(X), x_hat, x_rest_all, kinematic, dof, free, None)
        return X, target, ctx

    def _buffers(self, boundary_count: int) -> _StepBuffers:
        """The step's buffers for ``boundary_count`` Dirichlet vertices, made at the first step and anew only when
        that count changes (the free vertices' list is ``V − D`` long)."""
        buf = self._step_buffers
        if buf is None or buf.free.numel() != self.vertex_count - boundary_count:
            buf = _StepBuffers.make(self.vertex_count, self.body_vertex_count, boundary_count, self.x_rest.device)
            self._step_buffers = buf
        return buf

    def _step(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float) -> ClothStepReport:
        springs = self._check_springs(control)
        X, target, ctx = self.step_context(state_in, control, dt, state_out)
        if springs is None:
            return self._newton(state_out, X, target, ctx, dt)
        # ½ m ‖x − x̂‖² + Δt² ½ k ‖x − t‖² = ½ (m + Δt² k) ‖x − x̂'‖² + const with x̂' = (m x̂ + Δt² k t) / (m + Δt² k):
        # each spring folds into its vertex's inertia term, in place (the Newton loop's buffers and CUDA graphs read
        # the masses and x̂ where they are); the masses are restored when the step ends
        index, spring_target, stiffness = springs
        mass = self.potential.mass
        kept = mass[index]
        weight = torch.zeros_like(mass).index_add_(0, index, dt * dt * stiffness)[index]
        pull = torch.zeros_like(ctx.x_hat).index_add_(0, index, (dt * dt * stiffness)[:, None] * spring_target)[index]
        ctx.x_hat[index] = (kept[:, None] * ctx.x_hat[index] + pull) / (kept + weight)[:, None]
        mass[index] = kept + weight
        try:
            return self._newton(state_out, X, target, ctx, dt)
        finally:
            mass[index] = kept

    def _check_springs(self, control: ClothControl):
        """``(index [S], target [S, 3], stiffness [S])`` of the control's springs on the device, or ``None``."""
        index, target, stiffness = control.spring_index, control.spring_target, control.spring_stiffness
        if index is None and target is None and stiffness is None:
            return None
        if index is None or target is None or stiffness is None:
            raise ValueError("spring_index, spring_target and spring_stiffness go together: give all three or none")
        device = self.x_rest.device
        index = index.to(device).long()
        count = index.numel()
        if index.dim() != 1 or tuple(target.shape) != (count, 3) or tuple(stiffness.shape) != (count,):
            raise ValueError(
                f"springs must be spring_index [S], spring_target [S, 3] and spring_stiffness [S], got "
                f"{list(index.shape)}, {list(target.shape)} and {list(stiffness.shape)}"
            )
        if count == 0:
            return None
        if self.config.static:
            raise ValueError("a static solve has no inertia to fold springs into; pin vertices as boundary instead")
        target = target.to(device, F64)
        stiffness = stiffness.to(device, F64)
        valid = torch.stack(
            [(index.min() >= 0) & (index.max() < self.vertex_count), torch.isfinite(target).all(),
             (torch.isfinite(stiffness) & (stiffness > 0)).all()]
        ).tolist()  # fmt: skip
        for ok, problem in zip(valid, ("spring_index must index garment vertices", "spring_target holds NaN or inf",
                                       "spring_stiffness must be positive and finite, N/m"), strict=True):  # fmt: skip
            if not ok:
                raise ValueError(problem)
        return index, target, stiffness

    def _newton(self, state_out: ClothState, X, target, ctx, dt: float) -> ClothStepReport:
        cfg = self.config
        v, kinematic = self.vertex_count, ctx.kinematic
        x_start, b0 = ctx.x_start[:v], ctx.x_start[v:]
        buf = self._step_buffers
        timer = PhaseTimer(X.device)

        timer.start()
        # the candidates reach from each vertex's start along its predicted path (inertial target, or kinematic
        # target) and a margin beyond: usually every Newton sweep of the step stays inside
        predicted = buf.predicted.copy_(target)
        if not cfg.static:
            torch.where(kinematic[:v, None], target[:v], ctx.x_hat, out=predicted[:v])
        cover = self.contact.cover(X, predicted, ctx.kinematic, ctx.x_rest, self.candidate_margin)
        searches = 1
        pairs = self.contact.swept(X, buf.zero, cover)
        timer.stop("broad_phase")
        self._check_separated(X, pairs, b0)
        if cfg.friction > 0.0 and not cfg.static:
            timer.start()
            ctx = ctx._replace(friction=self.contact.lagged_friction(X, pairs, ctx.kappa))
            timer.stop("friction")

        loop = self.loop
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
                if not self.linear.solved():
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
                cover = self.contact.cover(X, X + loop.direction(), ctx.kinematic, ctx.x_rest, self.candidate_margin)
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

        # the end state goes into state_out's own tensors; x_start is the solver's copy, so state_out may be state_in
        X = loop.positions()
        state_out.x.copy_(X[:v])
        if cfg.static:
            state_out.v.zero_()
        else:
            torch.sub(state_out.x, x_start, out=state_out.v).div_(dt)
        # the pairs whose boxes at X lie within d̂ (the cover holds them all: X is on the last sweep)
        near = self.contact.sweep_masks(X, buf.zero, cover)
        d_body, d_self, contacts = self.contact.min_distances(X, cover.pairs, near)
        return ClothStepReport(iterations, converged, d_body, d_self, contacts, timer.totals(), searches, stalled)

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
        X_start, X, ctx = self.step_context(state_in, control, dt)  # X: the targets, body at the end of the step
        # NewtonMatrices takes a dof tensor other than the last step's for the start of a new step (its pending blocks
        # join the pattern): the step's dof buffer would be that same tensor, so the solve here gets its own copy
        ctx = ctx._replace(dof=ctx.dof.clone())
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
            pairs_start = self.contact.broad_phase(X_start, torch.zeros_like(X_start), ctx.kinematic, ctx.x_rest)
            ctx = ctx._replace(friction=self.contact.lagged_friction(X_start, pairs_start, ctx.kappa))
        pairs = self.contact.broad_phase(X, torch.zeros_like(X), ctx.kinematic, ctx.x_rest)
        parts: dict[str, torch.Tensor] = {}
        near = self.contact.near(X, pairs)
        _, grad, elements = self.potential.evaluate(X, near, ctx, project=not exact_hessian, parts=parts)
        matrix, _ = self.assemble(elements, grad, torch.zeros_like(X), ctx)

        rhs = X.new_zeros(v + nb, 3, count)
        if dynamic:
            rhs[:v] = self.potential.mass[:, None, None] * (s_x + dt * s_v)
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
        solution = self.linear.solve(matrix, rhs[free].reshape(-1, count))
        s_x_out = s_x.new_zeros(v, 3, count)
        s_x_out[free] = solution.view(-1, 3, count)
        s_v_out = (s_x_out - s_x) / dt if dynamic else torch.zeros_like(s_x_out)
        return s_x_out, s_v_out

    def linearise_step(
        self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float, exact_hessian: bool = True
    ) -> StepLinearisation:
        """The step's potential linearised at its end: what :meth:`sensitivity_step` solves with, for adjoints.

        Call it with a step's ``state_in``, its result ``state_out``, ``control`` and ``dt``, as
        :meth:`sensitivity_step`; the same approximations hold (lagged friction from the start of the step, contact
        set of ``x⁺``). Cost: one broad phase, one assembly.
        """
        with backend.one_torch_thread_on_cpu():
            v = self.vertex_count
            X_start, X, ctx = self.step_context(state_in, control, dt)
            ctx = ctx._replace(dof=ctx.dof.clone(), free=ctx.free.clone())  # the step's buffers are reused
            if tuple(state_out.x.shape) != (v, 3):
                raise ValueError(f"state_out.x must have shape [{v}, 3], got {list(state_out.x.shape)}")
            X[:v] = torch.where(ctx.kinematic[:v, None], X[:v], state_out.x.to(X.device, F64))
            X = X.clone()
            friction_hessian = None
            if self.config.friction > 0.0 and not self.config.static:
                pairs_start = self.contact.broad_phase(X_start, torch.zeros_like(X_start), ctx.kinematic, ctx.x_rest)
                ctx = ctx._replace(friction=self.contact.lagged_friction(X_start, pairs_start, ctx.kappa))
                if ctx.friction.index.shape[0]:
                    velocity = self.config.friction_velocity * dt
                    friction_hessian = friction_potential(X - X_start, ctx.friction, velocity, True)[2]
            if friction_hessian is None:
                ctx = ctx._replace(friction=None)
            pairs = self.contact.broad_phase(X, torch.zeros_like(X), ctx.kinematic, ctx.x_rest)
            parts: dict[str, torch.Tensor] = {}
            _, grad, elements = self.potential.evaluate(
                X, self.contact.near(X, pairs), ctx, project=not exact_hessian, parts=parts
            )
            matrix, _ = self.assemble(elements, grad, torch.zeros_like(X), ctx)
            return StepLinearisation(matrix, ctx.free, X, parts, ctx.friction, friction_hessian)

    def set_stiffness_fields(self, membrane: torch.Tensor | None = None, bending: torch.Tensor | None = None) -> None:
        """Scale the membrane and the bending face by face: ``κ_s s_f`` and ``κ_b b_f`` in place of ``κ_s``, ``κ_b``.

        Args:
            membrane: ``[F]`` positive factors ``s_f`` of the faces' Lamé parameters (``None``: all 1).
            bending: ``[F]`` positive factors ``b_f``; a hinge takes the mean of its two faces' (``None``: all 1).

        Raises:
            ValueError: a field of the wrong shape or with non-positive or non-finite values.
        """
        face_count = self.faces.shape[0]
        device = self.x_rest.device
        fields = []
        for name, f in (("membrane", membrane), ("bending", bending)):
            if f is not None:
                f = f.detach().to(device, F64)
                if tuple(f.shape) != (face_count,) or not bool(torch.isfinite(f).all() and (f > 0).all()):
                    raise ValueError(f"the {name} field must be [{face_count}] positive finite factors, one a face")
            fields.append(f)
        cfg = self.config
        mu, lam = shell.plane_stress_lame(cfg.young, cfg.poisson, cfg.thickness)
        self.potential.membrane_mu = mu if fields[0] is None else mu * fields[0]
        self.potential.membrane_lambda = lam if fields[0] is None else lam * fields[0]
        k = bending_stiffness(cfg)
        hinge_faces = shell.hinges_from_faces(self.faces)[1]
        self.potential.k_bend = k if fields[1] is None else k * 0.5 * fields[1][hinge_faces].sum(dim=1)

    # -- pieces of a step -------------------------------------------------------------------------------------

    def _check_step(self, state_in: ClothState, control: ClothControl, dt: float, state_out: ClothState | None = None):
        device = backend.torch_device()
        v, nb = self.vertex_count, self.body_vertex_count
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt ({dt}) must be a positive number of seconds (paper: 0.04)")
        for name, t in (("state_in.x", state_in.x), ("state_in.v", state_in.v)):
            if tuple(t.shape) != (v, 3):
                raise ValueError(f"{name} must have shape [{v}, 3], got {list(t.shape)}")
        if state_out is not None:
            self._check_state_out(state_out, device)
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

    def _check_state_out(self, state_out: ClothState, device: torch.device) -> None:
        """Refuse an output state the step cannot write its result into in place."""
        v = self.vertex_count
        tensors = (("state_out.x", state_out.x), ("state_out.v", state_out.v))
        for name, t in tensors:
            if not (isinstance(t, torch.Tensor) and tuple(t.shape) == (v, 3) and t.dtype == F64 and t.device == device):
                got = f"{t.dtype} {list(t.shape)} on {t.device}" if isinstance(t, torch.Tensor) else type(t).__name__
                raise ValueError(
                    f"{name} must be a float64 [{v}, 3] tensor on {device} (the step writes into it), got {got}; "
                    "make the states with solver.initial_state()"
                )
        x, vel = state_out.x, state_out.v
        if x.untyped_storage().data_ptr() == vel.untyped_storage().data_ptr():
            raise ValueError(
                "state_out.x and state_out.v share memory, so one would overwrite the other; "
                "make the states with solver.initial_state()"
            )

    def _check_separated(self, X: torch.Tensor, pairs: ContactPairs, b0: torch.Tensor) -> None:
        """Refuse a start state that touches the body or lies inside it (the barrier needs a positive gap)."""
        v = self.vertex_count
        if not self._checked_inside and self.contact.body_faces.numel():
            inside = MeshBVH(b0, self.contact.body_faces - v, winding_numbers=True).inside(X[:v])
            if bool(inside.any()):
                raise ValueError(
                    f"{int(inside.sum())} garment vertices start inside the body collider (e.g. vertex "
                    f"{int(inside.nonzero()[0])}); place the garment outside the body, at least d̂ away"
                )
            self._checked_inside = True
        d_body, d_self, _ = self.contact.min_distances(X, pairs)
        if not (d_body > 0.0 and d_self > 0.0):
            raise ValueError(
                "the garment touches or intersects "
                + ("the body" if not d_body > 0.0 else "itself")
                + " at the start of the step; start from an intersection-free state"
            )

    def assemble(self, elements: list[NewtonElement], grad: torch.Tensor, p_kin: torch.Tensor, ctx: StepContext):
        """The Newton matrix of the free DOFs and the right-hand side ``−g_f − H_fk p_k`` (``[n, 3]``).

        ``p_kin`` is zero on the free vertices: the blocks that join a free vertex to a kinematic one push
        ``H_fk p_k`` to the right-hand side, the others land in the matrix (:mod:`kernels.assembly`).
        """
        mass = self.potential.inertia_diagonal(ctx.free)
        return self.matrices.assemble(elements, -grad[ctx.free], ctx.dof, p_kin, mass)
