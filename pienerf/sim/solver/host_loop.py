"""The host loop of a Q-GMLS step: Newton on the incremental potential, the host reading the device at each decision.

Each iteration assembles the Newton system of Eq. 18 (:meth:`QGMLSPotential.newton_system`), solves it by Cholesky
(``torch.linalg``: LAPACK on the CPU, cuSOLVER on CUDA) and backtracks along the direction until the incremental
potential decreases enough (Armijo, halving the step up to ``line_search_steps`` times); a trial that inverts a
quadrature point has Ψ = +∞ and is rejected, so the body never inverts. It stops as soon as the largest update at
the integrator points falls below ``newton_tolerance``. :class:`pienerf.sim.solver.SolverQGMLS` runs it, or the
device loop (:mod:`pienerf.sim.solver.device_loop`), which takes the same step with no host read.
"""

from __future__ import annotations

import functools
import time

import torch

from kernels import backend
from pienerf.sim.solver.potential import QGMLSPotential
from pienerf.sim.solver.state import QGMLSControl, QGMLSState, QGMLSStepReport

__all__ = ["HostLoop", "spd_factor", "spd_solve"]


class HostLoop:
    """Implicit Euler steps (Eq. 2) by Newton with a backtracking line search over a :class:`QGMLSPotential`.

    Args:
        potential: the incremental potential's terms (its material may change between steps).
    """

    def __init__(self, potential: QGMLSPotential):
        self.potential = potential

    def step(self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl, dt) -> QGMLSStepReport:
        """Advance one step of ``dt`` seconds from ``state_in`` into ``state_out`` (which may be ``state_in``).

        The report's times are seconds of assembly (the Newton system), solve (factor and substitution), line search
        (the trial energies) and other (the rest), each phase ended by a synchronisation of the device."""
        potential = self.potential
        config = potential.config
        integrator = potential.step_integrator
        report = QGMLSStepReport()
        clock = time.perf_counter()
        q_n = state_in.q
        ctx = potential.step_context(q_n, state_in.qd, potential.control_force(control), dt)
        damping_K = None
        q = q_n.clone()
        beta = config.rayleigh_beta
        spring_H = potential.spring_hessian(control.springs)  # constant: springs are quadratic

        def total_energy(x: torch.Tensor, elastic: torch.Tensor) -> torch.Tensor:
            energy = potential.incremental_energy(x, ctx, damping_K, elastic)
            energy = energy + potential.spring_terms(control.springs, x, hessian=False, gradient=False)[0]
            return energy + potential.contact_terms(control.colliders, x, hessian=False)[0]

        report.time_other += time.perf_counter() - clock
        factor = None
        for iteration in range(config.newton_iterations):
            clock = time.perf_counter()
            fresh = config.hessian_updates is None or iteration < config.hessian_updates
            elastic = integrator.evaluate(q, hessian=fresh, project=config.project_hessian)
            if beta and damping_K is None:
                damping_K = elastic.hessian.clone()  # K(q_n): Newton starts at q_n
            contact_E, contact_g, contact_H = potential.contact_terms(control.colliders, q, hessian=fresh)
            spring_E, spring_g, _ = potential.spring_terms(control.springs, q, hessian=False)
            gradients, hessians = (contact_g, spring_g), (spring_H, contact_H)
            grad, H = potential.newton_system(q, ctx, elastic, damping_K, gradients, hessians)
            backend.synchronize()
            report.time_assembly += time.perf_counter() - clock

            clock = time.perf_counter()
            if fresh:
                exact = None
                if integrator is not potential.integrator:  # float64 products, should float32 ones break H
                    exact = functools.partial(potential.exact_newton_matrix, q, ctx, damping_K, gradients, hessians)
                factor = spd_factor(H, exact)
            step = torch.cholesky_solve(-grad.reshape(-1, 1), factor).view_as(q)
            backend.synchronize()
            report.time_solve += time.perf_counter() - clock

            clock = time.perf_counter()
            energy = potential.incremental_energy(q, ctx, damping_K, elastic.energy)
            energy = energy + spring_E + contact_E
            slope = (grad * step).sum()
            t = 1.0
            trials = []  # each rejected trial energy: +inf for an inverted trial, NaN for a broken one
            for _ in range(config.line_search_steps):
                trial = q + t * step
                trial_elastic = integrator.evaluate(trial, gradient=False, hessian=False, project=False)
                trial_energy = total_energy(trial, trial_elastic.energy)
                if torch.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * t * slope:
                    break
                trials.append(trial_energy)
                t *= 0.5
                report.line_search_halvings += 1
            else:
                t = 0.0
                trial, trial_energy, trial_elastic = q, energy, elastic
            report.time_line_search += time.perf_counter() - clock

            clock = time.perf_counter()
            q = trial
            report.iterations += 1
            report.energy = float(trial_energy)
            report.min_det = float(trial_elastic.min_det)
            report.last_update = potential.displacement_norm(t * step)
            if t == 0.0:
                failure = potential.line_search_failure(step, slope, energy, trials)
                report.line_search_failure = failure
                report.converged = not failure
                report.time_other += time.perf_counter() - clock
                break
            report.time_other += time.perf_counter() - clock
            if report.last_update < config.newton_tolerance:
                report.converged = True
                break

        clock = time.perf_counter()
        state_out.qd.copy_((q - q_n) * ctx.inv_h)
        state_out.q.copy_(q)
        state_out.time = state_in.time + dt
        report.time_other += time.perf_counter() - clock
        return report


def spd_factor(H: torch.Tensor, exact=None) -> torch.Tensor:
    """Cholesky factor ``[N, N]`` of a Newton matrix ``H [N, N]``. Every term of H is PSD; should round-off (or an
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


def spd_solve(H: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """Newton direction −H⁻¹ g ``[nT, 3]`` for ``grad [nT, 3]`` (:func:`spd_factor`)."""
    return torch.cholesky_solve(-grad.reshape(-1, 1), spd_factor(H)).view_as(grad)
