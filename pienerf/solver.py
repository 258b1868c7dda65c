"""Implicit Q-GMLS elastodynamics: Newton's method on the incremental potential (PIE-NeRF §4.5).

Implicit Euler (Eq. 2) with q_{n+1} = q_n + h q̇_{n+1} is the minimiser of the incremental potential

    E(q) = 1/(2h²) ‖q − q_n − h q̇_n‖²_M + U(q) − fᵀq + 1/(2h) (q − q_n)ᵀ D (q − q_n) + E_c(q)

whose stationarity condition is Eq. 2 (with Rayleigh damping D = αM + βK(q_n) and constraint
energies E_c), and whose Newton step is Eq. 18: (M/h² + ∂²U/∂q² + D/h + ∂²E_c/∂q²) Δq = −∇E. Each
Newton system is dense, 30n × 30n, and is solved by Cholesky (``torch.linalg``: LAPACK on the CPU,
cuSOLVER on CUDA). A backtracking line search on E keeps every step a descent step and rejects any
step that inverts a Neo-Hookean quadrature point (Ψ = +∞ for det F ≤ 0), so the body never inverts.

External forces act at any point X through f_q = Jᵀ(X) f (Eq. 9); gravity is f_q = M q_g with q_g the
uniform translation g, exact because Q-GMLS reproduces constants. Pins and drags are zero-rest-length
springs from material points to targets; colliders (floors, spheres) push particles out with a
quadratic penalty. Everything runs in float64 on the model's device.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from kernels import backend
from kernels.ip_integrate import DENSE_ASSEMBLY_RATIO
from pienerf.materials import Material
from pienerf.model import PointHandle, QGMLSModel

__all__ = [
    "ControlQGMLS",
    "PlaneCollider",
    "PointForces",
    "PointTargets",
    "SolverConfig",
    "SolverQGMLS",
    "SphereCollider",
    "StateQGMLS",
    "StepReport",
]


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
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    rayleigh_alpha: float = 0.0
    rayleigh_beta: float = 0.0
    newton_iterations: int = 3
    hessian_updates: int | None = None
    newton_tolerance: float = 1e-8
    line_search_steps: int = 20
    contact_stiffness: float | None = None
    project_hessian: bool = True

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
        if self.hessian_updates is not None and self.hessian_updates < 1:
            raise ValueError("hessian_updates must be >= 1 (or None for a fresh Hessian every iteration)")


@dataclass
class StateQGMLS:
    """Generalized coordinates q and velocities q̇, both ``[nT, 3]`` float64 (Eq. 9 layout)."""

    q: torch.Tensor
    qd: torch.Tensor
    time: float = 0.0

    def copy_(self, other: StateQGMLS) -> StateQGMLS:
        self.q.copy_(other.q)
        self.qd.copy_(other.qd)
        self.time = other.time
        return self


@dataclass
class PointTargets:
    """Zero-rest-length springs pulling material points to targets (pins and drags).

    Attributes:
        handle: the material points (:meth:`QGMLSModel.handle`).
        target: ``[M, 3]`` world targets (m).
        stiffness: spring stiffness per point (N/m).
    """

    handle: PointHandle
    target: torch.Tensor
    stiffness: float


@dataclass
class PointForces:
    """Constant forces ``force [M, 3]`` (N) at material points (f_q = Jᵀ f)."""

    handle: PointHandle
    force: torch.Tensor


@dataclass(frozen=True)
class PlaneCollider:
    """Half-space boundary: particles stay where n·(x − point) ≥ 0."""

    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class SphereCollider:
    """Solid sphere: particles stay outside."""

    centre: tuple[float, float, float]
    radius: float


@dataclass
class ControlQGMLS:
    """What acts on the body this step."""

    springs: list[PointTargets] = field(default_factory=list)
    forces: list[PointForces] = field(default_factory=list)
    colliders: list[PlaneCollider | SphereCollider] = field(default_factory=list)


@dataclass
class StepReport:
    """Per-step statistics; times in seconds.

    Attributes:
        iterations: Newton iterations taken.
        energy: incremental potential at the step's end (J).
        last_update: largest |J Δq| of the last accepted update at the integrator points (m).
        min_det: smallest det F over the quadrature points at the step's end.
        line_search_halvings: halvings of Newton steps over the whole step.
        converged: the last Newton update fell below ``newton_tolerance`` (or the Newton step was already at
            round-off), with no failed line search; ``False`` when the iteration budget ran out first.
        line_search_failure: why the last line search found no acceptable step, ``""`` when none failed:
            ``"inversion"`` (every trial hit the never-invert bound, Ψ = +∞ for det F ≤ 0, down to the smallest
            step), ``"no decrease"`` (finite trials, none decreasing the energy enough) or ``"not finite"``
            (the Newton direction or the trial energies were NaN). The body then stays where the failed
            iteration started: the step is not a solution of Eq. 2.
    """

    iterations: int = 0
    energy: float = 0.0
    last_update: float = 0.0
    min_det: float = 1.0
    line_search_halvings: int = 0
    converged: bool = False
    line_search_failure: str = ""
    time_assembly: float = 0.0
    time_solve: float = 0.0
    time_other: float = 0.0

    @property
    def line_search_failed(self) -> bool:
        """Whether a line search of this step could not move (see ``line_search_failure``)."""
        return bool(self.line_search_failure)


class SolverQGMLS:
    """Implicit Euler with Newton and dense Cholesky on a :class:`QGMLSModel` (Eq. 2, 18).

    Args:
        model: the discretised body.
        material: its material.
        config: solver settings.
    """

    def __init__(self, model: QGMLSModel, material: Material, config: SolverConfig = SolverConfig()):
        self.model = model
        self.config = config
        self.integrator = model.integrator(material)
        self.set_material(material)

    def set_material(self, material: Material) -> None:
        """Change the material (Young's modulus, Poisson ratio, density, model) between steps."""
        self.material = material
        model = self.model
        if material.kind != self.integrator.model:
            self.integrator = model.integrator(material)
        self.integrator.set_material(*material.lame)
        n = model.shape_count
        self.mass = material.density * model.mass  # [nT, nT] scalar mass (Eq. 11)
        self.mass_flat = torch.kron(self.mass, torch.eye(3, dtype=torch.float64, device=model.device))
        gravity = model.translation(torch.tensor(self.config.gravity, dtype=torch.float64))
        self.gravity_force = self.mass @ gravity
        stiffness = self.config.contact_stiffness
        if stiffness is None:
            stiffness = 100.0 * material.young_modulus
        self.contact_spring = stiffness * model.volume.pow(1.0 / 3.0)
        self._eye3 = torch.eye(3, dtype=torch.float64, device=model.device)
        self._n = n
        self._spring_cache: dict[int, tuple] = {}

    def rest_state(self) -> StateQGMLS:
        """The undeformed body at rest."""
        zeros = torch.zeros(self._n, 3, dtype=torch.float64, device=self.model.device)
        return StateQGMLS(zeros.clone(), zeros.clone())

    def _displacement_norm(self, dq: torch.Tensor) -> float:
        """Largest displacement |J(x_k) dq| over the integrator points (m): the Newton stopping measure,
        in metres whatever the DOF (values, gradients and second derivatives have different units)."""
        shape = self.model.ip_shape
        return float(torch.einsum("ks,ksa->ka", shape.value, dq[shape.index.clamp_min(0)]).abs().max())

    # -- energies of the step ----------------------------------------------------------------

    def _point_gradient(self, grad: torch.Tensor, index, value, force) -> None:
        """grad += Jᵀ f for forces ``force [M, 3]`` at points with shape values ``value [M, S]``."""
        grad.index_add_(0, index.reshape(-1), (value[..., None] * force[:, None, :]).reshape(-1, 3))

    def _point_shape_matrix(self, index, value) -> torch.Tensor:
        """Shape values of points ``value [M, S]`` at ``index [M, S]`` scattered into ``[M, nT]`` (N_s(X_m))."""
        rows = value.new_zeros(value.shape[0], self._n)
        return rows.scatter_add_(1, index, value)

    def _isotropic_point_hessian(self, index, value, stiffness) -> torch.Tensor:
        """Σ_m k_m J_mᵀ J_m ``[3nT, 3nT]`` for stiffnesses ``[M]``: (Nᵀ diag(k) N) ⊗ I₃, one product."""
        rows = self._point_shape_matrix(index, value)
        return torch.kron((rows * stiffness[:, None]).T @ rows, self._eye3)

    def _normal_point_hessian(self, index, value, stiffness, normal) -> torch.Tensor:
        """Σ_m k_m J_mᵀ n_m n_mᵀ J_m ``[3nT, 3nT]`` for stiffnesses ``[M]`` and unit normals ``[M, 3]``.

        Points that see most shape functions (S close to nT): Wᵀ W with rows W_m = √k_m (N_m ⊗ n_m), one product.
        Otherwise (many narrow kernels, where that product's (3nT)² work per point would dominate) each point's
        [S, S] blocks are summed into place (:meth:`kernels.ip_integrate.IPIntegrator.assemble_blocks`).
        """
        if (self._n / max(index.shape[1], 1)) ** 2 >= DENSE_ASSEMBLY_RATIO:
            scale = stiffness[:, None, None] * value[:, :, None] * value[:, None, :]
            blocks = scale[..., None] * (normal[:, :, None] * normal[:, None, :]).reshape(-1, 1, 1, 9)
            block_index = (index[:, :, None] * self._n + index[:, None, :]).reshape(-1)
            return self.integrator.assemble_blocks(blocks.reshape(-1, 9), block_index)
        rows = self._point_shape_matrix(index, value)
        weighted = (stiffness.sqrt()[:, None, None] * rows[:, :, None] * normal[:, None, :]).reshape(len(rows), -1)
        return weighted.T @ weighted

    def _spring_hessian(self, springs: list[PointTargets]) -> torch.Tensor | None:
        """Σ over springs of k Jᵀ J (constant: the springs are quadratic, and their Hessian does not depend on the
        targets). Jᵀ J of each handle is kept between steps while the same handle object, unchanged in place, comes
        back, so pins held over many steps cost one product each, once; a drag moving its target reuses its own."""
        cache, H = {}, None
        for spring in springs:
            handle = spring.handle
            versions = (handle.index._version, handle.value._version)
            entry = cache.get(id(handle)) or self._spring_cache.get(id(handle))
            if entry is None or entry[0] is not handle or entry[1] != versions:
                ones = torch.ones_like(handle.value[:, 0])
                entry = (handle, versions, self._isotropic_point_hessian(handle.index, handle.value, ones))
            cache[id(handle)] = entry
            part = entry[2] * spring.stiffness
            H = part if H is None else H.add_(part)
        self._spring_cache = cache  # handles no longer used are let go
        return H

    def _spring_terms(self, springs: list[PointTargets], q: torch.Tensor, hessian: bool):
        energy = q.new_zeros(())
        grad = torch.zeros_like(q)
        for spring in springs:
            h = spring.handle
            r = h.positions(q) - spring.target
            energy = energy + 0.5 * spring.stiffness * (r * r).sum()
            self._point_gradient(grad, h.index, h.value, spring.stiffness * r)
        return energy, grad, self._spring_hessian(springs) if hessian else None

    def _contact_terms(self, colliders, q: torch.Tensor, hessian: bool):
        energy = q.new_zeros(())
        grad = torch.zeros_like(q)
        H = None
        if not colliders:
            return energy, grad, H
        particles = self.model.particles
        x = particles.positions(q)
        for collider in colliders:
            if isinstance(collider, PlaneCollider):
                normal = torch.tensor(collider.normal, dtype=q.dtype, device=q.device)
                normal = normal / normal.norm()
                phi = (x - torch.tensor(collider.point, dtype=q.dtype, device=q.device)) @ normal
                normals = normal.expand_as(x)
            elif isinstance(collider, SphereCollider):
                d = x - torch.tensor(collider.centre, dtype=q.dtype, device=q.device)
                dist = d.norm(dim=1).clamp_min(1e-12)
                phi = dist - collider.radius
                normals = d / dist[:, None]
            else:
                raise TypeError(f"unknown collider {collider!r}; use PlaneCollider or SphereCollider")
            active = phi < 0
            if not bool(active.any()):
                continue
            k, p, nrm = self.contact_spring[active], phi[active], normals[active]
            index, value = particles.index[active], particles.value[active]
            energy = energy + 0.5 * (k * p * p).sum()
            self._point_gradient(grad, index, value, (k * p)[:, None] * nrm)  # ∂E/∂x = k φ n
            if hessian:
                # Gauss–Newton block k n nᵀ (exact for planes; drops the sphere's curvature term)
                part = self._normal_point_hessian(index, value, k, nrm)
                H = part if H is None else H + part
        return energy, grad, H

    def _external_force(self, control: ControlQGMLS) -> torch.Tensor:
        f = self.gravity_force.clone()
        for forces in control.forces:
            self._point_gradient(f, forces.handle.index, forces.handle.value, forces.force)
        return f

    def _incremental_energy(self, x, q_hat, q_n, inv_h, f_ext, damping_K, elastic) -> torch.Tensor:
        """Inertia, elastic, external-force and damping terms of the incremental potential at x."""
        dx_hat, dx = x - q_hat, x - q_n
        energy = 0.5 * inv_h**2 * (dx_hat * (self.mass @ dx_hat)).sum() + elastic - (f_ext * x).sum()
        if self.config.rayleigh_alpha:
            energy = energy + 0.5 * inv_h * self.config.rayleigh_alpha * (dx * (self.mass @ dx)).sum()
        if damping_K is not None:
            energy = energy + 0.5 * inv_h * self.config.rayleigh_beta * (dx.reshape(-1) @ (damping_K @ dx.reshape(-1)))
        return energy

    # -- the step --------------------------------------------------------------------------

    @backend.one_torch_thread_on_cpu()
    def step(self, state_in: StateQGMLS, state_out: StateQGMLS, control: ControlQGMLS, dt: float) -> StepReport:
        """Advance one implicit Euler step of ``dt`` seconds from ``state_in`` into ``state_out``.

        ``state_out`` may be ``state_in``. Returns the step's statistics and time breakdown. On the CPU torch runs on
        one thread meanwhile (:func:`kernels.backend.one_torch_thread_on_cpu`): a step is a few hundred small tensor
        operations around one product and one factorisation of a few hundred rows, and waking, or on shared cores
        waiting for, a second thread at each of them costs more than it saves.
        """
        self._check_step_inputs(state_in, control, dt)
        report = StepReport()
        config = self.config
        clock = time.perf_counter()
        q_n, v_n = state_in.q, state_in.qd
        q_hat = q_n + dt * v_n
        f_ext = self._external_force(control)
        damping_K = None
        q = q_n.clone()
        inv_h2, inv_h = 1.0 / dt**2, 1.0 / dt
        alpha, beta = config.rayleigh_alpha, config.rayleigh_beta
        spring_H = self._spring_terms(control.springs, q, hessian=True)[2]  # constant: springs are quadratic

        def total_energy(x: torch.Tensor, elastic: torch.Tensor) -> torch.Tensor:
            energy = self._incremental_energy(x, q_hat, q_n, inv_h, f_ext, damping_K, elastic)
            energy = energy + self._spring_terms(control.springs, x, hessian=False)[0]
            return energy + self._contact_terms(control.colliders, x, hessian=False)[0]

        report.time_other += time.perf_counter() - clock
        factor = None
        for iteration in range(config.newton_iterations):
            clock = time.perf_counter()
            fresh = config.hessian_updates is None or iteration < config.hessian_updates
            elastic = self.integrator.evaluate(q, hessian=fresh, project=config.project_hessian)
            if beta and damping_K is None:
                damping_K = elastic.hessian.clone()  # K(q_n): Newton starts at q_n
            contact_E, contact_g, contact_H = self._contact_terms(control.colliders, q, hessian=fresh)
            spring_E, spring_g, _ = self._spring_terms(control.springs, q, hessian=False)
            dx_hat, dx = q - q_hat, q - q_n
            grad = inv_h2 * (self.mass @ dx_hat) + elastic.gradient - f_ext + contact_g + spring_g
            if alpha:
                grad = grad + alpha * inv_h * (self.mass @ dx)
            if damping_K is not None:
                grad = grad + beta * inv_h * (damping_K @ dx.reshape(-1)).view_as(q)
            if fresh:
                H = elastic.hessian
                H += (inv_h2 + alpha * inv_h) * self.mass_flat
                if damping_K is not None:
                    H += beta * inv_h * damping_K
                if spring_H is not None:
                    H += spring_H
                if contact_H is not None:
                    H += contact_H
            backend.synchronize()
            report.time_assembly += time.perf_counter() - clock

            clock = time.perf_counter()
            if fresh:
                factor = _spd_factor(H)
            step = torch.cholesky_solve(-grad.reshape(-1, 1), factor).view_as(q)
            backend.synchronize()
            report.time_solve += time.perf_counter() - clock

            clock = time.perf_counter()
            energy = self._incremental_energy(q, q_hat, q_n, inv_h, f_ext, damping_K, elastic.energy)
            energy = energy + spring_E + contact_E
            slope = (grad * step).sum()
            t = 1.0
            trials = []  # each rejected trial energy: +inf for an inverted trial, NaN for a broken one
            for _ in range(config.line_search_steps):
                trial = q + t * step
                trial_elastic = self.integrator.evaluate(trial, gradient=False, hessian=False, project=False)
                trial_energy = total_energy(trial, trial_elastic.energy)
                if torch.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * t * slope:
                    break
                trials.append(trial_energy)
                t *= 0.5
                report.line_search_halvings += 1
            else:
                t = 0.0
                trial, trial_energy, trial_elastic = q, energy, elastic
            q = trial
            report.iterations += 1
            report.energy = float(trial_energy)
            report.min_det = float(trial_elastic.min_det)
            report.last_update = self._displacement_norm(t * step)
            report.time_other += time.perf_counter() - clock
            if t == 0.0:
                failure = self._line_search_failure(step, slope, energy, trials)
                report.line_search_failure = failure
                report.converged = not failure
                break
            if report.last_update < config.newton_tolerance:
                report.converged = True
                break

        clock = time.perf_counter()
        state_out.qd.copy_((q - q_n) * inv_h)
        state_out.q.copy_(q)
        state_out.time = state_in.time + dt
        report.time_other += time.perf_counter() - clock
        return report

    def _check_step_inputs(self, state: StateQGMLS, control: ControlQGMLS, dt) -> None:
        """Refuse a step whose inputs are not finite (NaN/inf would reach the energy and freeze the body silently)
        or whose springs are not finite, non-negative stiffnesses; one host read for all tensors."""
        if not _finite_number(dt) or not float(dt) > 0:
            raise ValueError(f"dt must be a finite positive number of seconds, got {dt!r}")
        if not math.isfinite(state.time):
            raise ValueError(f"state time must be finite, got {state.time}; reset the state")
        named = [("state q", state.q), ("state qd", state.qd)]
        for k, spring in enumerate(control.springs):
            stiffness = spring.stiffness
            if not _finite_number(stiffness) or float(stiffness) < 0:
                raise ValueError(
                    f"springs[{k}] stiffness must be a finite number >= 0 N/m, got {stiffness!r}; "
                    "use a large finite stiffness for a stiff pin"
                )
            if tuple(spring.target.shape) != (spring.handle.index.shape[0], 3):
                raise ValueError(
                    f"springs[{k}] target must be [{spring.handle.index.shape[0]}, 3] (one per handle point), "
                    f"got {tuple(spring.target.shape)}"
                )
            named.append((f"springs[{k}] target", spring.target))
        for k, forces in enumerate(control.forces):
            if tuple(forces.force.shape) != (forces.handle.index.shape[0], 3):
                raise ValueError(
                    f"forces[{k}] force must be [{forces.handle.index.shape[0]}, 3] (one per handle point), "
                    f"got {tuple(forces.force.shape)}"
                )
            named.append((f"forces[{k}] force", forces.force))
        for k, collider in enumerate(control.colliders):
            numbers = [*collider.point, *collider.normal] if isinstance(collider, PlaneCollider) else []
            if isinstance(collider, SphereCollider):
                numbers = [*collider.centre, collider.radius]
            if not all(_finite_number(v) for v in numbers):
                raise ValueError(f"colliders[{k}] must have finite coordinates, got {collider!r}")
        finite = torch.stack([torch.isfinite(t).all() for _, t in named]).tolist()
        for (name, _), ok in zip(named, finite, strict=True):
            if not ok:
                raise ValueError(f"{name} holds NaN or inf; every input of a step must be finite")

    def _line_search_failure(self, step, slope, energy, trials) -> str:
        """Why no trial along ``step`` was accepted; ``""`` when the iterate is stationary to round-off (the Newton
        step is below ``newton_tolerance`` or its predicted decrease −slope below the energy's rounding)."""
        if not bool(torch.isfinite(step).all()) or not math.isfinite(float(energy)):
            return "not finite"
        if self._displacement_norm(step) < self.config.newton_tolerance:
            return ""
        if -float(slope) <= 64.0 * torch.finfo(torch.float64).eps * abs(float(energy)):
            return ""
        values = torch.stack(trials)
        if bool(torch.isnan(values).any()):
            return "not finite"
        if bool(torch.isinf(values).all()):
            return "inversion"
        return "no decrease"

    def solve_static(self, control: ControlQGMLS, q0: torch.Tensor | None = None, iterations: int = 50):
        """Static equilibrium ∇U(q) = f under ``control`` (Newton with line search, no inertia).

        Needs enough springs or colliders to remove the rigid motions. Returns (q ``[nT, 3]``,
        final update size).
        """
        q = q0.clone() if q0 is not None else torch.zeros(self._n, 3, dtype=torch.float64, device=self.model.device)
        self._check_step_inputs(StateQGMLS(q, torch.zeros_like(q)), control, 1.0)
        f_ext = self._external_force(control)

        def energy_at(x):
            elastic = self.integrator.evaluate(x, gradient=False, hessian=False, project=False)
            return (elastic.energy - (f_ext * x).sum() + self._spring_terms(control.springs, x, False)[0]
                    + self._contact_terms(control.colliders, x, False)[0])

        update = float("inf")
        for _ in range(iterations):
            elastic = self.integrator.evaluate(q, project=self.config.project_hessian)
            _, spring_g, spring_H = self._spring_terms(control.springs, q, hessian=True)
            _, contact_g, contact_H = self._contact_terms(control.colliders, q, hessian=True)
            grad = elastic.gradient - f_ext + spring_g + contact_g
            H = elastic.hessian
            for part in (spring_H, contact_H):
                if part is not None:
                    H += part
            step = _spd_solve(H, grad)
            energy, slope, t = energy_at(q), (grad * step).sum(), 1.0
            for _ in range(self.config.line_search_steps):
                trial_energy = energy_at(q + t * step)
                if torch.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * t * slope:
                    break
                t *= 0.5
            q = q + t * step
            update = self._displacement_norm(t * step)
            if update < self.config.newton_tolerance:
                break
        return q, update


def _finite_number(value) -> bool:
    """Whether ``value`` is a real, finite number (a Python or NumPy scalar, or a one-element tensor)."""
    if isinstance(value, (bool, str, bytes)):
        return False
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _spd_factor(H: torch.Tensor) -> torch.Tensor:
    """Cholesky factor of the Newton matrix. Every term of H is PSD; should round-off (or an
    unconstrained rigid motion in a static solve) make it singular, a shift of 1e-10 times the
    mean diagonal is added, small next to the physical stiffnesses."""
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0:
        shifted = H + 1e-10 * H.diagonal().mean() * torch.eye(H.shape[0], dtype=H.dtype, device=H.device)
        L = torch.linalg.cholesky(shifted)
    return L


def _spd_solve(H: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """Newton direction −H⁻¹ g."""
    return torch.cholesky_solve(-grad.reshape(-1, 1), _spd_factor(H)).view_as(grad)
