"""The device loop of a Q-GMLS step: the host loop's Newton iterations with no host read, replayed as a CUDA graph.

:class:`DeviceLoop` takes the step of :class:`~pienerf.sim.solver.host_loop.HostLoop` with every decision a tensor:
it runs every Newton iteration, masking those after convergence, tries ``config.line_search_batch`` step lengths
(1, 1/2, 1/4, …) at once and keeps the longest acceptable one, and is captured once per set of controls
(:class:`kernels.backend.CapturedCall`); the step's statistics are read once, at its end. Where the host loop would
do something else (more halvings, a failed line search, a singular Newton matrix, non-finite values) the step is
marked for the host loop to redo, so that both give the same state and the same report. It is built from the public
methods of :class:`~pienerf.sim.solver.potential.QGMLSPotential` only.

A timed step (:meth:`DeviceLoop.step` with ``timed=True``) runs the same loop uncaptured, charging assembly, solve,
line search and other to :class:`PhaseTimer` (CUDA events on CUDA, read once at the step's end).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import torch

from kernels import backend
from pienerf.sim.solver.potential import QGMLSPotential, collider_placement
from pienerf.sim.solver.state import PlaneCollider, QGMLSControl, QGMLSState, QGMLSStepReport

__all__ = ["LOOP_STATS", "PHASES", "DeviceLoop", "DeviceLoopStep", "PhaseTimer", "device_loop_key"]

PHASES = ("assembly", "solve", "line_search", "other")
"""The phases of a step that :class:`PhaseTimer` charges (``QGMLSStepReport.time_<phase>``)."""

LOOP_STATS = ("iterations", "energy", "last_update", "min_det", "halvings", "converged", "redo", "first_update")
"""The device loop's statistics, in the order of its ``stats`` tensor."""


class PhaseTimer:
    """Seconds per phase (:data:`PHASES`), each :meth:`lap` charging the time since the last to a phase.

    On CUDA each mark is an event recorded on the current stream, so that a phase is charged with its own kernels
    without the host waiting (a synchronising clock would stall the launch queue at every phase boundary); the times
    are read once, by :meth:`totals`. On the CPU it is ``time.perf_counter``.
    """

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.times = dict.fromkeys(PHASES, 0.0)
        self._spans: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []
        self._last = self._mark()

    def _mark(self):
        if not self.cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def lap(self, phase: str) -> None:
        """Charge the time since the last mark (or the timer's making) to ``phase``."""
        mark = self._mark()
        if self.cuda:
            self._spans.append((phase, self._last, mark))
        else:
            self.times[phase] += mark - self._last
        self._last = mark

    def totals(self) -> dict[str, float]:
        """Seconds charged to each phase (on CUDA, waits for the last mark)."""
        if self._spans:
            self._spans[-1][2].synchronize()
            for phase, start, end in self._spans:
                self.times[phase] += start.elapsed_time(end) * 1e-3
            self._spans.clear()
        return dict(self.times)


class _NoTimer:
    """The untimed (captured) loop's timer: marks nothing."""

    def lap(self, phase: str) -> None:
        pass


class DeviceLoopStep(NamedTuple):
    """What :meth:`DeviceLoop.step` did: its ``report`` (``None`` where the host loop must redo the step) and whether
    the kept factor was dropped and the step taken again with its own (``refreshed``)."""

    report: QGMLSStepReport | None
    refreshed: bool


def device_loop_key(control: QGMLSControl, dt: float) -> tuple:
    """What a captured loop holds as it was at capture, apart from the material and settings: ``dt``, the springs'
    and forces' handles (by identity: a :class:`~pienerf.sim.model.PointHandle` is frozen and its tensors are never
    written in place) and the colliders' kinds. Steps with equal keys replay one graph."""
    return (
        dt,
        tuple(id(s.handle) for s in control.springs),
        tuple(id(f.handle) for f in control.forces),
        tuple(type(c) for c in control.colliders),
    )


class DeviceLoop:
    """One step of the host loop with no host read, over buffers that stay put, captured on CUDA.

    What changes from step to step is copied into the buffers by :meth:`load`: the state, the spring targets and
    stiffnesses, the point forces and the collider placements. What the graph holds as it was at capture (and what
    therefore needs another loop, :func:`device_loop_key`): ``dt``, the material, the settings, the springs' and
    forces' material points and the colliders' kinds.

    Args:
        potential: the incremental potential's terms.
        control: the controls whose points and collider kinds the loop holds.
        dt: the time step (s).
    """

    def __init__(self, potential: QGMLSPotential, control: QGMLSControl, dt: float):
        model, config = potential.model, potential.config
        n, device = model.shape_count, model.device
        self.potential, self.dt = potential, dt
        self.q_n = torch.zeros(n, 3, dtype=torch.float64, device=device)
        self.v_n = torch.zeros_like(self.q_n)
        self.spring_handles = [s.handle for s in control.springs]  # kept alive: the key holds their identities
        self.targets = [torch.zeros_like(s.target, dtype=torch.float64) for s in control.springs]
        self.stiffness = torch.zeros(len(control.springs), dtype=torch.float64, device=device)
        # Jᵀ J of each spring (unit stiffness): the springs are quadratic, so this is all their Hessian needs
        self.spring_jtj = [potential.handle_jtj(h) for h in self.spring_handles]
        self.force_handles = [f.handle for f in control.forces]
        self.forces = [torch.zeros_like(f.force, dtype=torch.float64) for f in control.forces]
        self.collider_kinds = [type(c) for c in control.colliders]
        self.colliders = [torch.zeros(6 if kind is PlaneCollider else 4, dtype=torch.float64, device=device)
                          for kind in self.collider_kinds]
        trials = min(config.line_search_batch, config.line_search_steps)
        self.trial_lengths = [0.5**j for j in range(trials)]  # 1, 1/2, 1/4, …: the host loop's first trials
        self.step_lengths = torch.tensor(self.trial_lengths, dtype=torch.float64, device=device)
        self.call = backend.CapturedCall(lambda: self.newton(reuse=False))
        # factor_reuse: the inverse L⁻¹ of the last fresh Cholesky factor, kept for the steps that reuse it
        # (call_reuse). Made once (a triangular solve against I), it turns each later solve into two matrix-vector
        # products instead of two triangular solves, and -L⁻ᵀ(L⁻¹ g) is a descent direction whatever L⁻¹'s
        # rounding: gᵀ d = -|L⁻¹ g|².
        self.factor_age: int | None = None  # steps since the kept factor was made; None: nothing kept
        self.kept_inverse = self._identity = None
        if config.factor_reuse:
            self.kept_inverse = torch.zeros(3 * n, 3 * n, dtype=torch.float64, device=device)
            self._identity = torch.eye(3 * n, dtype=torch.float64, device=device)
            self.call_reuse = backend.CapturedCall(lambda: self.newton(reuse=True))

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
            buffer.copy_(collider_placement(collider))

    def step(self, state_in: QGMLSState, state_out: QGMLSState, control: QGMLSControl,
             timed: bool = False) -> DeviceLoopStep:
        """Take the step from ``state_in`` into ``state_out`` under ``control`` (of this loop's key).

        Returns the report, or ``None`` (``state_out`` untouched) where the host loop must redo the step. ``timed``:
        run the loop uncaptured with its phases timed (:class:`PhaseTimer`) into the report's ``time_assembly``,
        ``time_solve``, ``time_line_search`` and ``time_other``; ``time_device_loop`` is the step's wall time.
        """
        config = self.potential.config
        clock = time.perf_counter()
        timer = PhaseTimer(self.q_n.device) if timed else None
        self.load(state_in, control)
        reuse = self.factor_age is not None and self.factor_age < config.factor_reuse
        q, qd, stats = self._run(reuse, timer)
        refreshed = False
        if reuse and not stats["redo"]:
            iterations = stats["iterations"]
            slow = stats["halvings"] > 0 or (
                iterations > 1 and stats["last_update"] > 0.5 ** (iterations - 1) * stats["first_update"])
            if slow or (config.newton_tolerance > 0 and not stats["converged"]):
                # The kept factor no longer serves: this step is taken again with its own, which is then kept.
                refreshed, reuse = True, False
                q, qd, stats = self._run(reuse, timer)
        if stats["redo"]:
            self.factor_age = None
            return DeviceLoopStep(None, refreshed)
        if config.factor_reuse:
            self.factor_age = self.factor_age + 1 if reuse else 0
        state_out.q.copy_(q)
        state_out.qd.copy_(qd)
        state_out.time = state_in.time + self.dt
        phases = timer.totals() if timer is not None else dict.fromkeys(PHASES, 0.0)
        report = QGMLSStepReport(
            iterations=int(stats["iterations"]), energy=stats["energy"], last_update=stats["last_update"],
            min_det=stats["min_det"], line_search_halvings=int(stats["halvings"]), converged=bool(stats["converged"]),
            device_loop=True, factor_reused=reuse, time_assembly=phases["assembly"], time_solve=phases["solve"],
            time_line_search=phases["line_search"], time_other=phases["other"],
            time_device_loop=time.perf_counter() - clock,
        )
        return DeviceLoopStep(report, refreshed)

    def _run(self, reuse: bool, timer: PhaseTimer | None):
        """The loop's q, q̇ and statistics by name, read from the device at once (the step's one read): the captured
        graph, or with ``timer`` the loop uncaptured and timed."""
        if timer is None:
            q, qd, stats = (self.call_reuse if reuse else self.call)()
        else:
            q, qd, stats = self.newton(reuse, timer)
        values = stats.tolist()
        if timer is not None:
            timer.lap("other")
        return q, qd, dict(zip(LOOP_STATS, values, strict=True))

    def _springs(self, x: torch.Tensor, gradient: bool):
        """Energy (and gradient) of the springs at ``x``, from the buffers."""
        springs = zip(self.spring_handles, self.targets, self.stiffness.unbind(0), strict=True)
        return self.potential.spring_energy(x, springs, gradient)

    def _contacts(self, x: torch.Tensor, gradient: bool, hessian: bool):
        """The collider penalty at ``x`` from the buffers (:meth:`QGMLSPotential.collider_penalty`)."""
        return self.potential.collider_penalty(self.collider_kinds, self.colliders, x, gradient, hessian)

    def newton(self, reuse: bool, timer: PhaseTimer | None = None):
        """The Newton loop of the host loop, every decision a tensor: returns q ``[nT, 3]``, q̇ ``[nT, 3]`` and the
        step's statistics ``[len(LOOP_STATS)]`` (float64). ``reuse``: every iteration solves with the kept factor (no
        assembly of a Hessian, no factorisation). ``timer``: charge each phase's time to it (uncaptured runs only)."""
        potential = self.potential
        config = potential.config
        timer = timer if timer is not None else _NoTimer()
        integrator = potential.step_integrator
        beta = config.rayleigh_beta
        q_n = self.q_n
        f_ext = potential.external_force(zip(self.force_handles, self.forces, strict=True))
        ctx = potential.step_context(q_n, self.v_n, f_ext, self.dt)
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
        timer.lap("other")
        for iteration in range(config.newton_iterations):
            fresh = not reuse and (config.hessian_updates is None or iteration < config.hessian_updates)
            elastic = integrator.evaluate(q, hessian=fresh, project=config.project_hessian)
            if beta and damping_K is None:
                damping_K = elastic.hessian.clone()
            contact_E, contact_g, contact_H = self._contacts(q, True, fresh)
            spring_E, spring_g = self._springs(q, True)
            grad, H = potential.newton_system(q, ctx, elastic, damping_K, (contact_g, spring_g), (spring_H, contact_H))
            timer.lap("assembly")

            if fresh:
                factor, info = torch.linalg.cholesky_ex(H)
                redo = redo | (info != 0)  # the host loop shifts a singular matrix
                if self.kept_inverse is not None and iteration == last_fresh:  # the factor nearest the next step
                    torch.linalg.solve_triangular(factor, self._identity, upper=False, out=self.kept_inverse)
            if reuse:
                step = -(self.kept_inverse.T @ (self.kept_inverse @ grad.reshape(-1, 1))).view_as(q)
            else:
                step = torch.cholesky_solve(-grad.reshape(-1, 1), factor).view_as(q)
            timer.lap("solve")

            energy = potential.incremental_energy(q, ctx, damping_K, elastic.energy)
            energy = energy + spring_E + contact_E
            slope = (grad * step).sum()
            trial_energy, trial_det = [], []
            for t in self.trial_lengths:
                trial = q + t * step
                trial_elastic = integrator.evaluate(trial, gradient=False, hessian=False, project=False)
                value = potential.incremental_energy(trial, ctx, damping_K, trial_elastic.energy)
                trial_energy.append(value + self._springs(trial, False)[0] + self._contacts(trial, False, False)[0])
                trial_det.append(trial_elastic.min_det)
            trial_energy, trial_det = torch.stack(trial_energy), torch.stack(trial_det)
            accepted = torch.isfinite(trial_energy) & (trial_energy <= energy + 1e-4 * lengths * slope)
            found = accepted.any()
            first = accepted.to(zero.dtype).argmax()  # the longest acceptable step (the first maximum)
            t = torch.where(found, _pick(lengths, first), zero)
            # A line search that finds nothing at a stationary iterate (finite, the step at round-off) ends the host
            # loop as converged; anywhere else the host loop would halve further or report a failure (non-finite
            # values among them): it redoes the step.
            stationary = potential.is_stationary(step, slope, energy)
            timer.lap("line_search")

            active = ~done
            redo = redo | (active & ~found & ~stationary)
            q = torch.where(active, q + t * step, q)
            update = potential.displacement(t * step)
            iterations = iterations + active
            halvings = halvings + torch.where(active, torch.where(found, first, config.line_search_steps), 0)
            energy_out = torch.where(active, torch.where(found, _pick(trial_energy, first), energy), energy_out)
            min_det = torch.where(active, torch.where(found, _pick(trial_det, first), elastic.min_det), min_det)
            last_update = torch.where(active, update, last_update)
            if iteration == 0:
                first_update = update
            done = done | (active & (~found | (update < config.newton_tolerance)))
            timer.lap("other")
        qd = (q - q_n) * ctx.inv_h
        stats = torch.stack([iterations, energy_out, last_update, min_det, halvings.to(zero.dtype),  # LOOP_STATS
                             (done & ~redo).to(zero.dtype), redo.to(zero.dtype), first_update])
        return q, qd, stats


def _pick(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` for a 0-d index tensor, with no read of the index on the host (``values[index]`` reads it)."""
    return values.gather(0, index.view(1)).squeeze(0)
