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

The solver is composed of three parts: the potential's terms (:class:`~pienerf.sim.solver.potential.QGMLSPotential`)
and the two loops that minimise it (:class:`~pienerf.sim.solver.host_loop.HostLoop`,
:class:`~pienerf.sim.solver.device_loop.DeviceLoop`); :class:`SolverQGMLS` builds them and dispatches each step.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict

import torch

from kernels import backend
from kernels.ip_integrate import IPIntegrator
from pienerf.sim.materials import Material
from pienerf.sim.model import QGMLSModel
from pienerf.sim.solver.config import SolverConfig
from pienerf.sim.solver.device_loop import DeviceLoop, device_loop_key
from pienerf.sim.solver.host_loop import HostLoop, spd_solve
from pienerf.sim.solver.potential import QGMLSPotential
from pienerf.sim.solver.state import (
    PlaneCollider,
    QGMLSControl,
    QGMLSState,
    QGMLSStepReport,
    SphereCollider,
)

__all__ = ["SolverQGMLS"]

DEVICE_LOOPS_KEPT = 3
"""Captured device loops a solver keeps (each holds its own copy of the Newton matrix and its factor)."""


class SolverQGMLS:
    """Implicit Euler with Newton and dense Cholesky on a :class:`QGMLSModel` (Eq. 2, 18).

    Args:
        model: the discretised body.
        material: its material.
        config: solver settings.

    Attributes:
        potential: the incremental potential's terms (:class:`QGMLSPotential`); ``integrator``,
            ``step_integrator``, ``mass``, ``mass_flat`` and ``gravity_force`` are its own.
        host_loop: the loop with the host in it (:class:`HostLoop`).
        device_loops: the captured device loops kept, by :func:`device_loop_key`, most recently used last.
        device_loop_redos: device-loop steps the host loop redid (:meth:`step`).
        factor_refreshes: steps retaken with their own factor, the kept one no longer serving.
    """

    def __init__(self, model: QGMLSModel, material: Material, config: SolverConfig = SolverConfig()):
        self.model = model
        self.config = config
        self.device_loop_redos = 0
        self.factor_refreshes = 0
        self.potential = QGMLSPotential(model, material, config)
        self.host_loop = HostLoop(self.potential)
        self.device_loops: OrderedDict[tuple, DeviceLoop] = OrderedDict()

    def set_material(self, material: Material) -> None:
        """Change the material (Young's modulus, Poisson ratio, density, model) between steps.

        Sets :attr:`integrator`, the material's IP integrator with float64 block products (exact to round-off: what
        :meth:`solve_static` and checks of the energy use), and :attr:`step_integrator`, the one steps use, whose
        products are in ``config.hessian_precision`` (the same object where that is float64). Drops the captured
        device loops, which hold the material as it was."""
        self.potential.set_material(material)
        self.device_loops.clear()

    @property
    def material(self) -> Material:
        """The body's material."""
        return self.potential.material

    @property
    def integrator(self) -> IPIntegrator:
        """The material's IP integrator with float64 block products."""
        return self.potential.integrator

    @property
    def step_integrator(self) -> IPIntegrator:
        """The IP integrator steps use (block products in ``config.hessian_precision``)."""
        return self.potential.step_integrator

    @property
    def mass(self) -> torch.Tensor:
        """``[nT, nT]`` scalar mass matrix ρ M (kg, Eq. 11)."""
        return self.potential.mass

    @property
    def mass_flat(self) -> torch.Tensor:
        """``[3nT, 3nT]`` mass matrix M ⊗ I₃ (kg)."""
        return self.potential.mass_flat

    @property
    def gravity_force(self) -> torch.Tensor:
        """``[nT, 3]`` generalized gravity M q_g (N)."""
        return self.potential.gravity_force

    def rest_state(self) -> QGMLSState:
        """The undeformed body at rest."""
        zeros = torch.zeros(self.potential.shape_count, 3, dtype=torch.float64, device=self.model.device)
        return QGMLSState(zeros.clone(), zeros.clone())

    @backend.one_torch_thread_on_cpu()
    def step(self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl, dt: float,
             timed: bool = False) -> QGMLSStepReport:
        """Advance one implicit Euler step of ``dt`` seconds from ``state_in`` into ``state_out``.

        ``state_out`` may be ``state_in``. Returns the step's statistics and time breakdown. On the CPU torch runs on
        one thread meanwhile (:func:`kernels.backend.one_torch_thread_on_cpu`): a step is a few hundred small tensor
        operations around one product and one factorisation of a few hundred rows, and waking, or on shared cores
        waiting for, a second thread at each of them costs more than it saves.

        Two loops compute the same step. The host loop (:class:`HostLoop`) stops as soon as Newton converges and
        halves a rejected step until one is accepted, reading the device at each decision. The device loop
        (:class:`DeviceLoop`, ``config.device_loop``, on CUDA by default) makes no read: it runs every Newton
        iteration, masking those after convergence, tries ``config.line_search_batch`` step lengths at once and keeps
        the longest acceptable one, and is replayed as one CUDA graph; the step's statistics are read once, at its
        end. Where the host loop would do something else (more halvings, a failed line search of any kind, a singular
        Newton matrix, non-finite values) the device loop's result is dropped and the host loop redoes the step, so
        both give the same state and the same report.

        ``timed``: the host loop always times its phases (assembly, solve, line search, other); a device-loop step
        times them only when asked, by running its loop uncaptured with the phases marked (CUDA events on CUDA),
        slower than the graph's replay: ask for one step in many (e.g. one per frame) for a time breakdown.
        """
        self._check_step_inputs(state_in, control, dt)
        use_device_loop = self.config.device_loop
        if use_device_loop is None:
            use_device_loop = self.model.device.type == "cuda"
        if use_device_loop:
            clock = time.perf_counter()
            loop = self._device_loop_for(control, float(dt))
            taken = loop.step(state_in, state_out, control, timed=timed)
            self.factor_refreshes += taken.refreshed
            if taken.report is not None:
                return taken.report
            self.device_loop_redos += 1
            report = self.host_loop.step(state_in, state_out, control, dt)
            report.time_other += time.perf_counter() - clock - report.time_step  # the dropped device-loop run
            return report
        return self.host_loop.step(state_in, state_out, control, dt)

    def _device_loop_for(self, control: QGMLSControl, dt: float) -> DeviceLoop:
        """The captured loop for this set of springs, forces and collider kinds at this ``dt`` (built on first use;
        the last few are kept, so that a drag that starts and stops switches between two graphs)."""
        key = device_loop_key(control, dt)
        loop = self.device_loops.pop(key, None)
        if loop is None:
            loop = DeviceLoop(self.potential, control, dt)
            while len(self.device_loops) >= DEVICE_LOOPS_KEPT:
                self.device_loops.popitem(last=False)
        self.device_loops[key] = loop  # most recently used last
        return loop

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


    def solve_static(self, control: QGMLSControl, q0: torch.Tensor | None = None, iterations: int = 50):
        """Static equilibrium ∇U(q) = f under ``control`` (Newton with line search, no inertia).

        Needs enough springs or colliders to remove the rigid motions. Returns (q ``[nT, 3]``,
        final update size).
        """
        q = q0.clone() if q0 is not None else self.rest_state().q
        self._check_step_inputs(QGMLSState(q, torch.zeros_like(q)), control, 1.0)
        potential = self.potential
        f_ext = potential.control_force(control)
        integrator = potential.integrator  # no mass term here: the Hessian's products in float64

        def energy_at(x):
            elastic = integrator.evaluate(x, gradient=False, hessian=False, project=False)
            return (elastic.energy - (f_ext * x).sum() + potential.spring_terms(control.springs, x, False, False)[0]
                    + potential.contact_terms(control.colliders, x, False)[0])

        update = float("inf")
        for _ in range(iterations):
            elastic = integrator.evaluate(q, project=self.config.project_hessian)
            _, spring_g, spring_H = potential.spring_terms(control.springs, q, hessian=True)
            _, contact_g, contact_H = potential.contact_terms(control.colliders, q, hessian=True)
            grad = elastic.gradient - f_ext + spring_g + contact_g
            H = elastic.hessian
            for part in (spring_H, contact_H):
                if part is not None:
                    H += part
            step = spd_solve(H, grad)
            energy, slope, t = energy_at(q), (grad * step).sum(), 1.0
            for _ in range(self.config.line_search_steps):
                trial_energy = energy_at(q + t * step)
                if torch.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * t * slope:
                    break
                t *= 0.5
            q = q + t * step
            update = potential.displacement_norm(t * step)
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
