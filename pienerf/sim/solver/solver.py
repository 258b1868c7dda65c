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
quadratic penalty. Everything runs in float64 on the model's device (the elastic Hessian's block products in float32
where :attr:`SolverConfig.hessian_precision` asks, the Hessian still float64).
"""

from __future__ import annotations

import functools
import math
import time
from collections import OrderedDict

import torch

from kernels import backend
from kernels.ip_integrate import DENSE_ASSEMBLY_RATIO, IPIntegrator
from pienerf.sim.materials import Material
from pienerf.sim.model import QGMLSModel
from pienerf.sim.solver.config import SolverConfig
from pienerf.sim.solver.state import (
    PlaneCollider,
    PointTargets,
    QGMLSControl,
    QGMLSState,
    QGMLSStepReport,
    SphereCollider,
)

__all__ = ["SolverQGMLS"]


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
        self.integrator: IPIntegrator | None = None
        self.step_integrator: IPIntegrator | None = None
        self.device_loop_redos = 0  # device-loop steps the host loop redid (:meth:`step`)
        self.factor_refreshes = 0  # steps retaken with their own factor, the kept one no longer serving
        self.set_material(material)

    def _integrator(self, product_dtype: torch.dtype) -> IPIntegrator:
        """The integrator of the material whose Hessian's block products are formed in ``product_dtype``, made once
        per material."""
        integrator = self._integrators.get(product_dtype)
        if integrator is None:
            integrator = self._integrators[product_dtype] = self.model.integrator(self.material, product_dtype)
        return integrator

    def set_material(self, material: Material) -> None:
        """Change the material (Young's modulus, Poisson ratio, density, model) between steps.

        Sets :attr:`integrator`, the material's IP integrator with float64 block products (exact to round-off: what
        :meth:`solve_static` and checks of the energy use), and :attr:`step_integrator`, the one steps use, whose
        products are in ``config.hessian_precision`` (the same object where that is float64)."""
        self.material = material
        model = self.model
        if self.integrator is None or material.kind != self.integrator.model:
            self._integrators: dict[torch.dtype, IPIntegrator] = {}  # by block-product dtype (:meth:`_integrator`)
        for integrator in self._integrators.values():
            integrator.set_material(*material.lame)
        self.integrator = self._integrator(torch.float64)
        self.step_integrator = self._integrator(self.config.hessian_product_dtype(model.device))
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
        self._device_loops: OrderedDict[tuple, _DeviceLoop] = OrderedDict()  # graphs hold the material as it was

    def rest_state(self) -> QGMLSState:
        """The undeformed body at rest."""
        zeros = torch.zeros(self._n, 3, dtype=torch.float64, device=self.model.device)
        return QGMLSState(zeros.clone(), zeros.clone())

    def _displacement_norm(self, dq: torch.Tensor) -> float:
        """Largest displacement |J(x_k) dq| over the integrator points (m): the Newton stopping measure,
        in metres whatever the DOF (values, gradients and second derivatives have different units)."""
        return float(self._displacement_tensor(dq))

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

    def _spring_terms(self, springs: list[PointTargets], q: torch.Tensor, hessian: bool, gradient: bool = True):
        """Energy, gradient (``None`` without ``gradient``) and Hessian (``None`` without ``hessian``) of the
        springs at ``q``."""
        energy, grad = self._spring_energy(q, ((s.handle, s.target, s.stiffness) for s in springs), gradient)
        return energy, grad, self._spring_hessian(springs) if hessian else None

    def _spring_energy(self, q: torch.Tensor, springs, gradient: bool):
        """Energy ½ k Σ|x − target|² and its gradient (``None`` without ``gradient``) of springs given as
        ``(handle, target [M, 3], stiffness)`` (a number or a 0-d tensor: the device loop's buffers)."""
        energy, grad = q.new_zeros(()), torch.zeros_like(q) if gradient else None
        for handle, target, stiffness in springs:
            r = handle.positions(q) - target
            energy = energy + 0.5 * stiffness * (r * r).sum()
            if gradient:
                self._point_gradient(grad, handle.index, handle.value, stiffness * r)
        return energy, grad

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
                point = torch.tensor(collider.point, dtype=q.dtype, device=q.device)
                phi, normals = _collider_distance(PlaneCollider, x, point, normal / normal.norm())
            elif isinstance(collider, SphereCollider):
                centre = torch.tensor(collider.centre, dtype=q.dtype, device=q.device)
                phi, normals = _collider_distance(SphereCollider, x, centre, collider.radius)
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

    def _external_force(self, control: QGMLSControl) -> torch.Tensor:
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
    def step(self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl, dt: float) -> QGMLSStepReport:
        """Advance one implicit Euler step of ``dt`` seconds from ``state_in`` into ``state_out``.

        ``state_out`` may be ``state_in``. Returns the step's statistics and time breakdown. On the CPU torch runs on
        one thread meanwhile (:func:`kernels.backend.one_torch_thread_on_cpu`): a step is a few hundred small tensor
        operations around one product and one factorisation of a few hundred rows, and waking, or on shared cores
        waiting for, a second thread at each of them costs more than it saves.

        Two loops compute the same step. The host loop stops as soon as Newton converges and halves a rejected
        step until one is accepted, reading the device at each decision. The device loop (``config.device_loop``,
        on CUDA by default) makes no read: it runs every Newton iteration, masking those after convergence, tries
        ``config.line_search_batch`` step lengths at once and keeps the longest acceptable one, and is replayed as
        one CUDA graph; the step's statistics are read once, at its end. Where the host loop would do something
        else (more halvings, a failed line search, a singular Newton matrix) the device loop's result is dropped
        and the host loop redoes the step, so both give the same state and the same report.
        """
        self._check_step_inputs(state_in, control, dt)
        use_device_loop = self.config.device_loop
        if use_device_loop is None:
            use_device_loop = self.model.device.type == "cuda"
        if use_device_loop:
            report = self._device_loop_step(state_in, state_out, control, dt)
            if report is not None:
                return report
        return self._host_loop_step(state_in, state_out, control, dt)

    def _host_loop_step(
        self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl, dt
    ) -> QGMLSStepReport:
        """The step with the host in the loop (:meth:`step`)."""
        report = QGMLSStepReport()
        config = self.config
        clock = time.perf_counter()
        q_n, v_n = state_in.q, state_in.qd
        q_hat = q_n + dt * v_n
        f_ext = self._external_force(control)
        damping_K = None
        q = q_n.clone()
        inv_h2, inv_h = 1.0 / dt**2, 1.0 / dt
        beta = config.rayleigh_beta
        spring_H = self._spring_hessian(control.springs)  # constant: springs are quadratic

        def total_energy(x: torch.Tensor, elastic: torch.Tensor) -> torch.Tensor:
            energy = self._incremental_energy(x, q_hat, q_n, inv_h, f_ext, damping_K, elastic)
            energy = energy + self._spring_terms(control.springs, x, hessian=False, gradient=False)[0]
            return energy + self._contact_terms(control.colliders, x, hessian=False)[0]

        report.time_other += time.perf_counter() - clock
        factor = None
        for iteration in range(config.newton_iterations):
            clock = time.perf_counter()
            fresh = config.hessian_updates is None or iteration < config.hessian_updates
            elastic = self.step_integrator.evaluate(q, hessian=fresh, project=config.project_hessian)
            if beta and damping_K is None:
                damping_K = elastic.hessian.clone()  # K(q_n): Newton starts at q_n
            contact_E, contact_g, contact_H = self._contact_terms(control.colliders, q, hessian=fresh)
            spring_E, spring_g, _ = self._spring_terms(control.springs, q, hessian=False)
            grad, H = self._newton_system(
                q, q_hat, q_n, inv_h2, inv_h, f_ext, elastic, damping_K, (contact_g, spring_g), (spring_H, contact_H)
            )
            backend.synchronize()
            report.time_assembly += time.perf_counter() - clock

            clock = time.perf_counter()
            if fresh:
                exact = None
                if self.step_integrator is not self.integrator:  # float64 products, should float32 ones break H
                    exact = functools.partial(self._float64_newton_matrix, q, (q_hat, q_n, inv_h2, inv_h, f_ext),
                                              damping_K, (contact_g, spring_g), (spring_H, contact_H))
                factor = _spd_factor(H, exact)
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
                trial_elastic = self.step_integrator.evaluate(trial, gradient=False, hessian=False, project=False)
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

    def _newton_system(self, q, q_hat, q_n, inv_h2, inv_h, f_ext, elastic, damping_K, gradients, hessians):
        """The incremental potential's gradient at ``q`` and, where ``elastic`` carries the elastic Hessian, the
        Newton matrix of Eq. 18, M/h² + αM/h + ∂²U/∂q² + βK/h + the ``hessians`` of springs and contacts (built in
        the elastic Hessian's storage; ``None`` otherwise). ``gradients``: the springs' and contacts' gradients."""
        alpha, beta = self.config.rayleigh_alpha, self.config.rayleigh_beta
        dx_hat, dx = q - q_hat, q - q_n
        grad = inv_h2 * (self.mass @ dx_hat) + elastic.gradient - f_ext
        for part in gradients:
            grad = grad + part
        if alpha:
            grad = grad + alpha * inv_h * (self.mass @ dx)
        if damping_K is not None:
            grad = grad + beta * inv_h * (damping_K @ dx.reshape(-1)).view_as(q)
        H = elastic.hessian
        if H is not None:
            H.add_(self.mass_flat, alpha=inv_h2 + alpha * inv_h)
            if damping_K is not None:
                H.add_(damping_K, alpha=beta * inv_h)
            for part in hessians:
                if part is not None:
                    H += part
        return grad, H

    def _float64_newton_matrix(self, q, step, damping_K, gradients, hessians) -> torch.Tensor:
        """:meth:`_newton_system`'s matrix at ``q`` with float64 block products; ``step``: (q̂, q_n, 1/h², 1/h, f)."""
        elastic = self.integrator.evaluate(q, hessian=True, project=self.config.project_hessian)
        q_hat, q_n, inv_h2, inv_h, f_ext = step
        return self._newton_system(q, q_hat, q_n, inv_h2, inv_h, f_ext, elastic, damping_K, gradients, hessians)[1]

    # -- the device loop ----------------------------------------------------------------------

    def _device_loop_step(self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl, dt):
        """The step by the device loop (:meth:`step`); ``None`` where the host loop must redo it."""
        clock = time.perf_counter()
        loop = self._device_loop_for(control, float(dt))
        loop.load(state_in, control)
        reuse = loop.factor_age is not None and loop.factor_age < self.config.factor_reuse
        q, qd, stats = _replay(loop.call_reuse if reuse else loop.call)
        if reuse and not stats["redo"]:
            iterations = stats["iterations"]
            slow = stats["halvings"] > 0 or (
                iterations > 1 and stats["last_update"] > 0.5 ** (iterations - 1) * stats["first_update"])
            if slow or (self.config.newton_tolerance > 0 and not stats["converged"]):
                # The kept factor no longer serves: this step is taken again with its own, which is then kept.
                self.factor_refreshes += 1
                reuse = False
                q, qd, stats = _replay(loop.call)
        if stats["redo"]:
            self.device_loop_redos += 1
            loop.factor_age = None
            return None
        if self.config.factor_reuse:
            loop.factor_age = loop.factor_age + 1 if reuse else 0
        state_out.q.copy_(q)
        state_out.qd.copy_(qd)
        state_out.time = state_in.time + dt
        return QGMLSStepReport(
            iterations=int(stats["iterations"]), energy=stats["energy"], last_update=stats["last_update"],
            min_det=stats["min_det"], line_search_halvings=int(stats["halvings"]), converged=bool(stats["converged"]),
            device_loop=True, factor_reused=reuse, time_device_loop=time.perf_counter() - clock,
        )

    def _device_loop_for(self, control: QGMLSControl, dt: float) -> _DeviceLoop:
        """The captured loop for this set of springs, forces and collider kinds at this ``dt`` (built on first use;
        the last few are kept, so that a drag that starts and stops switches between two graphs)."""
        key = (
            dt,
            tuple((id(s.handle), s.handle.index._version, s.handle.value._version) for s in control.springs),
            tuple((id(f.handle), f.handle.index._version, f.handle.value._version) for f in control.forces),
            tuple(type(c) for c in control.colliders),
        )
        loop = self._device_loops.pop(key, None)
        if loop is None:
            loop = _DeviceLoop(self, control, dt)
            while len(self._device_loops) >= _DEVICE_LOOPS_KEPT:
                self._device_loops.popitem(last=False)
        self._device_loops[key] = loop  # most recently used last
        return loop

    def _displacement_tensor(self, dq: torch.Tensor) -> torch.Tensor:
        """:meth:`_displacement_norm` as a 0-d tensor, not read on the host (the device loop's)."""
        shape = self.model.ip_shape
        return torch.einsum("ks,ksa->ka", shape.value, dq[shape.index.clamp_min(0)]).abs().max()

    def _check_step_inputs(self, state: QGMLSState, control: QGMLSControl, dt) -> None:
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

    def solve_static(self, control: QGMLSControl, q0: torch.Tensor | None = None, iterations: int = 50):
        """Static equilibrium ∇U(q) = f under ``control`` (Newton with line search, no inertia).

        Needs enough springs or colliders to remove the rigid motions. Returns (q ``[nT, 3]``,
        final update size).
        """
        q = q0.clone() if q0 is not None else torch.zeros(self._n, 3, dtype=torch.float64, device=self.model.device)
        self._check_step_inputs(QGMLSState(q, torch.zeros_like(q)), control, 1.0)
        f_ext = self._external_force(control)
        integrator = self.integrator  # no mass term here: the Hessian's products in float64

        def energy_at(x):
            elastic = integrator.evaluate(x, gradient=False, hessian=False, project=False)
            return (elastic.energy - (f_ext * x).sum() + self._spring_terms(control.springs, x, False, False)[0]
                    + self._contact_terms(control.colliders, x, False)[0])

        update = float("inf")
        for _ in range(iterations):
            elastic = integrator.evaluate(q, project=self.config.project_hessian)
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


_DEVICE_LOOPS_KEPT = 3
"""Captured device loops a solver keeps (each holds its own copy of the Newton matrix and its factor)."""


class _DeviceLoop:
    """One step of :meth:`SolverQGMLS.step` with no host read, over buffers that stay put, captured on CUDA.

    What changes from step to step is copied into the buffers by :meth:`load`: the state, the spring targets and
    stiffnesses, the point forces and the collider placements. What the graph holds as it was at capture (and what
    therefore picks another loop, :meth:`SolverQGMLS._device_loop_for`): ``dt``, the material, the settings, the
    springs' and forces' material points and the colliders' kinds.
    """

    def __init__(self, solver: SolverQGMLS, control: QGMLSControl, dt: float):
        model = solver.model
        n, device = model.shape_count, model.device
        self.solver, self.dt = solver, dt
        self.q_n = torch.zeros(n, 3, dtype=torch.float64, device=device)
        self.v_n = torch.zeros_like(self.q_n)
        self.spring_handles = [s.handle for s in control.springs]
        self.targets = [torch.zeros_like(s.target, dtype=torch.float64) for s in control.springs]
        self.stiffness = torch.zeros(len(control.springs), dtype=torch.float64, device=device)
        # Jᵀ J of each spring (unit stiffness): the springs are quadratic, so this is all their Hessian needs
        self.spring_jtj = [
            solver._isotropic_point_hessian(h.index, h.value, torch.ones_like(h.value[:, 0]))
            for h in self.spring_handles
        ]
        self.force_handles = [f.handle for f in control.forces]
        self.forces = [torch.zeros_like(f.force, dtype=torch.float64) for f in control.forces]
        self.collider_kinds = [type(c) for c in control.colliders]
        self.colliders = [torch.zeros(6 if kind is PlaneCollider else 4, dtype=torch.float64, device=device)
                          for kind in self.collider_kinds]
        trials = min(solver.config.line_search_batch, solver.config.line_search_steps)
        self.trial_lengths = [0.5**j for j in range(trials)]  # 1, 1/2, 1/4, …: the host loop's first trials
        self.step_lengths = torch.tensor(self.trial_lengths, dtype=torch.float64, device=device)
        self.call = backend.CapturedCall(lambda: self._newton(reuse=False))
        # factor_reuse: the inverse L⁻¹ of the last fresh Cholesky factor, kept for the steps that reuse it
        # (call_reuse). Made once (a triangular solve against I, ~1.7 ms at 2,340 DOF on an H100), it turns each later
        # solve into two matrix-vector products (0.04 ms against 0.37 ms for the two triangular solves), and
        # -L⁻ᵀ(L⁻¹ g) is a descent direction whatever L⁻¹'s rounding: gᵀ d = -|L⁻¹ g|².
        self.factor_age: int | None = None  # steps since the kept factor was made; None: nothing kept
        self.kept_inverse = self._identity = None
        if solver.config.factor_reuse:
            self.kept_inverse = torch.zeros(3 * n, 3 * n, dtype=torch.float64, device=device)
            self._identity = torch.eye(3 * n, dtype=torch.float64, device=device)
            self.call_reuse = backend.CapturedCall(lambda: self._newton(reuse=True))

    def load(self, state: QGMLSState, control: QGMLSControl) -> None:
        """Copy this step's inputs into the buffers the graph reads."""
        self.q_n.copy_(state.q)
        self.v_n.copy_(state.qd)
        for buffer, spring in zip(self.targets, control.springs, strict=True):
            buffer.copy_(spring.target)
        if control.springs:
            stiffness = [float(s.stiffness) for s in control.springs]
            self.stiffness.copy_(torch.tensor(stiffness, dtype=torch.float64))
        for buffer, forces in zip(self.forces, control.forces, strict=True):
            buffer.copy_(forces.force)
        for buffer, collider in zip(self.colliders, control.colliders, strict=True):
            if isinstance(collider, PlaneCollider):
                normal = torch.tensor(collider.normal, dtype=torch.float64)
                values = torch.cat([torch.tensor(collider.point, dtype=torch.float64), normal / normal.norm()])
            else:
                values = torch.tensor([*collider.centre, collider.radius], dtype=torch.float64)
            buffer.copy_(values)

    def _springs(self, x: torch.Tensor, gradient: bool):
        """Energy (and gradient) of the springs at ``x``, from the buffers."""
        springs = zip(self.spring_handles, self.targets, self.stiffness.unbind(0), strict=True)
        return self.solver._spring_energy(x, springs, gradient)

    def _contacts(self, x_q: torch.Tensor, gradient: bool, hessian: bool):
        """The collider penalty of :meth:`SolverQGMLS._contact_terms` over every particle, the ones not in contact
        contributing zero, so that no mask is read."""
        solver, particles = self.solver, self.solver.model.particles
        energy, grad, H = x_q.new_zeros(()), torch.zeros_like(x_q) if gradient else None, None
        if not self.colliders:
            return energy, grad, H
        x = particles.positions(x_q)
        k = solver.contact_spring
        for kind, values in zip(self.collider_kinds, self.colliders, strict=True):
            phi, normals = _collider_distance(kind, x, values[:3], values[3:] if kind is PlaneCollider else values[3])
            depth = phi.clamp(max=0.0)
            energy = energy + 0.5 * (k * depth * depth).sum()
            if gradient:
                solver._point_gradient(grad, particles.index, particles.value, (k * depth)[:, None] * normals)
            if hessian:
                part = solver._normal_point_hessian(particles.index, particles.value, k * (phi < 0), normals)
                H = part if H is None else H + part
        return energy, grad, H

    def _newton(self, reuse: bool):
        """The Newton loop of the host loop, every decision a tensor: returns q, q̇ and the step's statistics.
        ``reuse``: every iteration solves with the kept factor (no assembly of a Hessian, no factorisation)."""
        solver, config = self.solver, self.solver.config
        dt, integrator = self.dt, solver.step_integrator
        inv_h2, inv_h = 1.0 / dt**2, 1.0 / dt
        beta = config.rayleigh_beta
        q_n = self.q_n
        q_hat = q_n + dt * self.v_n
        f_ext = solver.gravity_force.clone()
        for handle, force in zip(self.force_handles, self.forces, strict=True):
            solver._point_gradient(f_ext, handle.index, handle.value, force)
        spring_H = None
        for k, jtj in enumerate(self.spring_jtj):
            part = self.stiffness[k] * jtj
            spring_H = part if spring_H is None else spring_H.add_(part)

        zero = q_n.new_zeros(())
        done, redo = torch.zeros((), dtype=torch.bool, device=q_n.device), torch.zeros_like(zero, dtype=torch.bool)
        iterations, halvings, energy_out, last_update, min_det = (zero.clone() for _ in range(5))
        min_det += 1.0
        lengths = self.step_lengths
        q, damping_K, factor = q_n.clone(), None, None
        last_fresh = min(config.newton_iterations, config.hessian_updates or config.newton_iterations) - 1
        first_update = zero
        for iteration in range(config.newton_iterations):
            fresh = not reuse and (config.hessian_updates is None or iteration < config.hessian_updates)
            elastic = integrator.evaluate(q, hessian=fresh, project=config.project_hessian)
            if beta and damping_K is None:
                damping_K = elastic.hessian.clone()
            contact_E, contact_g, contact_H = self._contacts(q, True, fresh)
            spring_E, spring_g = self._springs(q, True)
            grad, H = solver._newton_system(
                q, q_hat, q_n, inv_h2, inv_h, f_ext, elastic, damping_K, (contact_g, spring_g), (spring_H, contact_H)
            )
            if fresh:
                factor, info = torch.linalg.cholesky_ex(H)
                redo = redo | (info != 0)  # the host loop shifts a singular matrix
                if self.kept_inverse is not None and iteration == last_fresh:  # the factor nearest the next step
                    torch.linalg.solve_triangular(factor, self._identity, upper=False, out=self.kept_inverse)
            if reuse:
                step = -(self.kept_inverse.T @ (self.kept_inverse @ grad.reshape(-1, 1))).view_as(q)
            else:
                step = torch.cholesky_solve(-grad.reshape(-1, 1), factor).view_as(q)

            energy = solver._incremental_energy(q, q_hat, q_n, inv_h, f_ext, damping_K, elastic.energy)
            energy = energy + spring_E + contact_E
            slope = (grad * step).sum()
            trial_energy, trial_det = [], []
            for t in self.trial_lengths:
                trial = q + t * step
                trial_elastic = integrator.evaluate(trial, gradient=False, hessian=False, project=False)
                value = solver._incremental_energy(trial, q_hat, q_n, inv_h, f_ext, damping_K, trial_elastic.energy)
                trial_energy.append(value + self._springs(trial, False)[0] + self._contacts(trial, False, False)[0])
                trial_det.append(trial_elastic.min_det)
            trial_energy, trial_det = torch.stack(trial_energy), torch.stack(trial_det)
            accepted = torch.isfinite(trial_energy) & (trial_energy <= energy + 1e-4 * lengths * slope)
            found = accepted.any()
            first = accepted.to(zero.dtype).argmax()  # the longest acceptable step (the first maximum)
            t = torch.where(found, _pick(lengths, first), zero)
            # A line search that finds nothing at a stationary iterate ends the host loop as converged; anywhere
            # else the host loop would halve further or report a failure: it redoes the step.
            stationary = (solver._displacement_tensor(step) < config.newton_tolerance) | (
                -slope <= 64.0 * torch.finfo(torch.float64).eps * energy.abs())
            active = ~done
            redo = redo | (active & ~found & ~stationary)
            q = torch.where(active, q + t * step, q)
            update = solver._displacement_tensor(t * step)
            iterations = iterations + active
            halvings = halvings + torch.where(active, torch.where(found, first, config.line_search_steps), 0)
            energy_out = torch.where(active, torch.where(found, _pick(trial_energy, first), energy), energy_out)
            min_det = torch.where(active, torch.where(found, _pick(trial_det, first), elastic.min_det), min_det)
            last_update = torch.where(active, update, last_update)
            if iteration == 0:
                first_update = update
            done = done | (active & (~found | (update < config.newton_tolerance)))
        qd = (q - q_n) * inv_h
        stats = torch.stack([iterations, energy_out, last_update, min_det, halvings.to(zero.dtype),  # _LOOP_STATS
                             (done & ~redo).to(zero.dtype), redo.to(zero.dtype), first_update])
        return q, qd, stats


_LOOP_STATS = ("iterations", "energy", "last_update", "min_det", "halvings", "converged", "redo", "first_update")
"""The device loop's statistics, in the order of its ``stats`` tensor."""


def _replay(call) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """Run a device loop's graph: q, q̇ and its statistics by name, read from the device at once (the step's read)."""
    q, qd, stats = call()
    return q, qd, dict(zip(_LOOP_STATS, stats.tolist(), strict=True))


def _collider_distance(kind, x: torch.Tensor, a: torch.Tensor, b) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distances ``[P]`` of points ``x [P, 3]`` to a collider and its outward unit normals ``[P, 3]``: for
    :class:`PlaneCollider`, the plane through ``a [3]`` with unit normal ``b [3]``; for :class:`SphereCollider`, the
    sphere of centre ``a [3]`` and radius ``b``."""
    if kind is PlaneCollider:
        return (x - a) @ b, b.expand_as(x)
    d = x - a
    dist = d.norm(dim=1).clamp_min(1e-12)
    return dist - b, d / dist[:, None]


def _pick(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` for a 0-d index tensor, with no read of the index on the host (``values[index]`` reads it)."""
    return values.gather(0, index.view(1)).squeeze(0)


def _finite_number(value) -> bool:
    """Whether ``value`` is a real, finite number (a Python or NumPy scalar, or a one-element tensor)."""
    if isinstance(value, (bool, str, bytes)):
        return False
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _spd_factor(H: torch.Tensor, exact=None) -> torch.Tensor:
    """Cholesky factor of the Newton matrix. Every term of H is PSD; should round-off (or an
    unconstrained rigid motion in a static solve) make it singular, the matrix ``exact()`` gives (the same one with
    float64 block products, where H has float32 ones) is tried first, then a shift of 1e-10 times the mean diagonal is
    added, small next to the physical stiffnesses."""
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0 and exact is not None:
        H = exact()
        L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0:
        shifted = H + 1e-10 * H.diagonal().mean() * torch.eye(H.shape[0], dtype=H.dtype, device=H.device)
        L = torch.linalg.cholesky(shifted)
    return L


def _spd_solve(H: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """Newton direction −H⁻¹ g."""
    return torch.cholesky_solve(-grad.reshape(-1, 1), _spd_factor(H)).view_as(grad)
