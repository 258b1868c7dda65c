"""The Newton iterations of a garment step, as four phases over buffers that stay put (CUDA graphs on CUDA).

:class:`NewtonLoop` is built from the three parts of the simulator a Newton iteration runs through: the incremental
potential (:class:`~physavatar.cloth.potential.IncrementalPotential`: ``E``, its gradient and element Hessians), the
contact (:class:`~physavatar.cloth.contact.ClothContact`: sweeps, their candidates and CCD bounds) and the Newton
system (:class:`~physavatar.cloth.newton_system.NewtonMatrices` and
:class:`~physavatar.cloth.newton_system.LinearSolver`). :class:`physavatar.cloth.SolverCloth` drives it: one
:meth:`NewtonLoop.begin` per step, then per iteration assemble, solve, look, backtrack and accept.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch

from kernels import backend
from physavatar.cloth.contact import ClothContact, ContactCover, ContactPairs, LaggedFriction, compact_rows
from physavatar.cloth.newton_system import LinearSolver, NewtonElement, NewtonMatrices, NewtonMatrix, filtered_elements
from physavatar.cloth.potential import ClothEnergies, IncrementalPotential, StepContext

__all__ = ["PHASES", "AssembledSystem", "LoopRead", "NewtonLoop", "PhaseTimer"]

F64 = torch.float64
PHASES = ("broad_phase", "ccd", "assemble", "solve", "line_search", "friction")
"""The phases of a step that :class:`PhaseTimer` charges time to (:attr:`physavatar.cloth.ClothStepReport.time`)."""


class PhaseTimer:
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
        """Mark the start of a phase."""
        self._start = self._mark()

    def stop(self, phase: str) -> None:
        """Charge the time since :meth:`start` to ``phase`` (one of :data:`PHASES`)."""
        end = self._mark()
        if self.cuda:
            self.spans.append((phase, self._start, end))
        else:
            self.times[phase] += end - self._start

    def totals(self) -> dict[str, float]:
        """Seconds charged to each phase so far (on CUDA, waits for the last mark)."""
        if self.spans:
            self.spans[-1][2].synchronize()
            for phase, start, end in self.spans:
                self.times[phase] += start.elapsed_time(end) * 1e-3
            self.spans.clear()
        return dict(self.times)


_PHANTOM = ((1000.0, 1000.0, 1000.0), (1001.0, 1000.0, 1000.0), (1010.0, 1010.0, 1010.0), (1010.0, 1011.0, 1010.0))
"""Four kinematic vertices that :class:`NewtonLoop` appends to the positions, km away from any garment: the phantom
pair over them (point 0 against triangle 1-2-3, and edge 0-1 against edge 2-3) pads the pair buffers on CUDA. Its
boxes lie metres apart, its distance is far beyond ``d̂`` and nothing moves it, so every kernel gives it zeros."""


def _capacity(count: int) -> int:
    """Rows of a pair buffer that holds ``count`` pairs and a phantom one, with a quarter to spare: a power of two
    (at least 256), so that a buffer grows, and its graphs are captured anew, a few times at most."""
    return max(256, 1 << math.ceil(math.log2(1.25 * (count + 1))))


class LoopRead(NamedTuple):
    """What the host reads of a Newton iteration, in one read from the device (:meth:`NewtonLoop.look`)."""

    energy: float  # E at X
    missing: bool  # blocks outside the pattern were bounded on the diagonal
    overflow: bool  # more active pairs than their buffers hold: the iteration must run again (CUDA)
    reached: bool  # every kinematic vertex is on its target
    covered: bool  # the sweep X → X + p stays inside the candidates' cover
    step: float  # ‖p_f‖_∞, m
    alpha: float  # the sweep's CCD bound (nan where not needed)
    trial_energy: float  # E at X + α p (nan where not needed)


class AssembledSystem(NamedTuple):
    """One Newton system (:meth:`NewtonLoop.assemble`)."""

    energy: torch.Tensor  # 0-d
    grad: torch.Tensor  # [N, 3]
    elements: list[NewtonElement]  # as the potential gave them
    filtered: list[NewtonElement]  # PSD-filtered, as scattered
    matrix: NewtonMatrix
    rhs: torch.Tensor  # [n, 3]
    missing: torch.Tensor  # [1] int32
    p_kin: torch.Tensor  # [N, 3]
    active: torch.Tensor | None  # [2] active pairs (CUDA)


class NewtonLoop:
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
    candidates, the active contacts) are compacted into such buffers on the device
    (:func:`~physavatar.cloth.contact.compact_rows`). A count beyond its buffer grows the buffer (:func:`_capacity`)
    and runs the phases again; new buffers, a new pattern or a new ``Δt`` capture the graphs anew. On the CPU the
    lists have their exact sizes and the flags are read between the phases, so the CCD and the trial run only when
    needed.

    Args:
        potential: the incremental potential the iterations minimise.
        contact: the contact candidates, sweeps and CCD bounds.
        matrices: the Newton matrices' pattern and assembly.
        linear: the linear solver of the Newton systems.
        newton_tolerance: the step's convergence test, ``‖p_f‖_∞ / Δt`` below it, m/s.
        static: fixed-shape buffers (and CUDA graphs on CUDA); default: on CUDA with the project's own kernels.
    """

    def __init__(
        self,
        potential: IncrementalPotential,
        contact: ClothContact,
        matrices: NewtonMatrices,
        linear: LinearSolver,
        newton_tolerance: float,
        static: bool | None = None,
    ):
        self.potential = potential
        self.contact = contact
        self.matrices = matrices
        self.linear = linear
        self.newton_tolerance = newton_tolerance  # m/s, as ClothConfig.newton_tolerance
        device = potential.x_rest.device
        if static is None:  # graphs of the project's kernels (other element evaluators may not capture)
            static = device.type == "cuda" and potential.energies == ClothEnergies()
        self.static = static  # fixed shapes, and CUDA graphs on CUDA
        self.capacity: dict[str, int] = {}
        phases = (self._assemble, self._sweep, self._ccd, self._trial)
        self.phases = [backend.CapturedCall(f, capture=self.static) for f in phases]
        self._key: tuple | None = None
        self._phantom = torch.tensor(_PHANTOM, dtype=F64, device=device)
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

    def begin(
        self, X: torch.Tensor, target: torch.Tensor, ctx: StepContext, cover: ContactCover, pairs: ContactPairs
    ) -> None:
        """Load a step: positions ``X [V + B, 3]`` and targets at its start, its context, candidates' cover and the
        candidates at ``X``; the pattern of the step's Newton matrices."""
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
            friction = LaggedFriction(self.f_index, self.f_weight, self.f_projector, self.f_force)
        self.ctx = ctx._replace(
            x_start=self.x_start, x_hat=self.x_hat, kinematic=self.kinematic, dof=self.dof, free=self.free,
            friction=friction,
        )  # fmt: skip
        self.matrices.begin_step(ctx.dof, ctx.free.numel())
        if self.static:
            for name in ("active_pt", "active_ee"):
                self.capacity.setdefault(name, _capacity(0))
        key = (ctx.dt, ctx.kappa, friction is None, self.matrices.version)
        if self._key is None or key[:-1] != self._key[:-1]:
            self._reset()  # Python scalars the graphs hold
        elif key != self._key:
            self._reset([0])  # a new pattern: the assembly's
        self._key = key

    def set_cover(self, cover: ContactCover) -> None:
        """Load new candidates (a search along a sweep that left the last ones' reach)."""
        one = torch.ones(1, dtype=F64, device=cover.lo.device)
        pairs = cover.pairs
        self._put("cover_lo", cover.lo)
        self._put("cover_hi", cover.hi)
        self._put("cover_pt", self._padded("cover_pt", pairs.pt, self.pair_pad))
        self._put("cover_ee", self._padded("cover_ee", pairs.ee, self.pair_pad))
        self._put("cover_eps", self._padded("cover_ee", pairs.ee_eps, one))

    def _put_pairs(self, name: str, pairs: ContactPairs) -> None:
        one = torch.ones(1, dtype=F64, device=pairs.pt.device)
        self._put(f"{name}_pt", self._padded(f"{name}_pt", pairs.pt, self.pair_pad))
        self._put(f"{name}_ee", self._padded(f"{name}_ee", pairs.ee, self.pair_pad))
        self._put(f"{name}_eps", self._padded(f"{name}_ee", pairs.ee_eps, one))

    def _swept_pairs(self) -> ContactPairs:
        return ContactPairs(self.swept_pt, self.swept_ee, 0, 0, self.swept_eps)

    def positions(self) -> torch.Tensor:
        """``X [V + B, 3]``, the current iterate."""
        return self.X[: self.rows]

    def direction(self) -> torch.Tensor:
        """``p [V + B, 3]``, the last direction."""
        return self.p[: self.rows]

    # -- phases -----------------------------------------------------------------------------------------------

    def _assemble(self) -> AssembledSystem:
        X = self.X
        swept = self._swept_pairs()
        active = counts = None
        if self.static:
            capacity = (self.capacity["active_pt"], self.capacity["active_ee"])
            *active, counts = self.potential.active_rows(X, swept, capacity)
        energy, grad, elements = self.potential.evaluate(X, swept, self.ctx, active=active)
        filtered = filtered_elements(elements, self.matrices.eigen_dtype)
        p_kin = torch.where(self.kinematic[:, None], self.target - X, torch.zeros_like(X))
        mass = self.potential.inertia_diagonal(self.free)
        matrix, rhs, missing = self.matrices.scatter(filtered, -grad[self.free], self.dof, p_kin, mass)
        return AssembledSystem(energy, grad, elements, filtered, matrix, rhs, missing, p_kin, counts)

    def _sweep(self) -> torch.Tensor:
        X = self.X
        p = torch.where(self.kinematic[:, None], self.target - X, torch.zeros_like(X))
        reached = (p == 0).all()
        p.index_copy_(0, self.free, self.p_free.view(-1, 3))
        step = self.p_free.abs().max() if self.p_free.numel() else p.new_zeros(())
        n = self.rows
        cover = ContactCover(
            self.cover_lo, self.cover_hi, ContactPairs(self.cover_pt, self.cover_ee, 0, 0, self.cover_eps)
        )
        covered = self.contact.covers(cover, X[:n], p[:n])
        pt_keep, ee_keep = self.contact.sweep_masks(X, p, cover)
        if self.static:
            self.p.copy_(p)
            pt_rows = compact_rows(pt_keep, self.capacity["swept_pt"])
            ee_rows = compact_rows(ee_keep, self.capacity["swept_ee"])
            self.swept_pt.copy_(self.cover_pt[pt_rows])
            self.swept_ee.copy_(self.cover_ee[ee_rows])
            self.swept_eps.copy_(self.cover_eps[ee_rows])
        else:
            self.p = p
            pt_rows, ee_rows = compact_rows(pt_keep), compact_rows(ee_keep)
            self.swept_pt, self.swept_ee = self.cover_pt[pt_rows], self.cover_ee[ee_rows]
            self.swept_eps = self.cover_eps[ee_rows]
        counts = [pt_keep.sum(), ee_keep.sum()]
        return torch.stack([reached.to(F64), covered.to(F64), step.to(F64), *(c.to(F64) for c in counts)])

    def _ccd(self) -> torch.Tensor:
        bound = self.contact.ccd_bound(self.X, self.p, self._swept_pairs())
        if self.static:
            self.alpha.copy_(bound)
        else:
            self.alpha = bound
        return bound

    def _trial(self) -> tuple[torch.Tensor, torch.Tensor]:
        trial = self.X + self.alpha * self.p
        return trial, self.potential.energy(trial, self._swept_pairs(), self.ctx)

    # -- what the step calls ----------------------------------------------------------------------------------

    def assemble(self) -> AssembledSystem:
        """The Newton system at ``X``."""
        return self.phases[0]()

    def solve(self, assembled: AssembledSystem, wait: bool) -> None:
        """Its direction on the free vertices (:meth:`LinearSolver.solve`)."""
        p_free = self.linear.solve(assembled.matrix, assembled.rhs.reshape(-1), wait=wait)
        if self.static:
            self.p_free.copy_(p_free)
        else:
            self.p_free = p_free

    def look(self, assembled: AssembledSystem, timer: PhaseTimer) -> LoopRead:
        """The sweep, its CCD bound and the trial at the bound, and what the host needs of them and of
        ``assembled``, in one read. On CUDA the three phases run before the read (CCD and trial are wasted where the
        step has converged or the sweep leaves the cover); on the CPU the flags are read first."""
        a, dt, tolerance = assembled, self.ctx.dt, self.newton_tolerance
        while True:
            timer.start()
            flags = self.phases[1]()
            timer.stop("broad_phase")
            head = [a.energy.reshape(1), a.missing.to(F64), flags]
            if not self.static:
                energy, missing, reached, covered, step, _, _ = torch.cat(head).tolist()
                if not covered or reached and step / dt < tolerance:  # the step's own test
                    return LoopRead(
                        energy, missing > 0, False, reached == 1.0, covered == 1.0, step, math.nan, math.nan
                    )
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
            return LoopRead(energy, missing > 0, overflow, reached, covered, step, alpha, trial_energy)

    def _regrow(self) -> None:
        """New swept buffers at their grown capacities (their contents are the sweep phase's to write)."""
        for name, width in (("swept_pt", 4), ("swept_ee", 4)):
            setattr(self, name, self.pair_pad.expand(self.capacity[name], width).clone())
        self.swept_eps = torch.ones(self.capacity["swept_ee"], dtype=F64, device=self.X.device)
        self._reset()

    def trial_energy(self, alpha: float, timer: PhaseTimer) -> float:
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

    def _with_reach(self, elements: list[NewtonElement]) -> list[NewtonElement]:
        """``elements`` with each contact element's reach the candidates within ``REACH · d̂`` (on CUDA the loop's
        contact elements carry their own pairs)."""
        if not self.static:
            return elements
        swept = self._swept_pairs()
        _, _, pt_reach, ee_reach = self.potential.active_rows(self.X, swept, reach=True)
        reach = iter([swept.pt[pt_reach], swept.ee[ee_reach]])
        return [e._replace(reach=next(reach)) if e.reach is not None else e for e in elements]

    def defer(self, assembled: AssembledSystem) -> None:
        """Grow the pattern by the blocks of ``assembled`` at the next step (:meth:`NewtonMatrices.defer`)."""
        self.matrices.defer(self._with_reach(assembled.elements), self.dof, self.free.numel())

    def complete(self, assembled: AssembledSystem) -> AssembledSystem:
        """``assembled`` on a pattern grown until it holds every block (:meth:`NewtonMatrices.complete`)."""
        a = assembled
        mass = self.potential.inertia_diagonal(self.free)
        elements = self._with_reach(a.elements)
        matrix, rhs = self.matrices.complete(a.filtered, elements, -a.grad[self.free], self.dof, a.p_kin, mass)
        self._reset([0])  # the assembly's graph holds the old pattern
        self._key = (*self._key[:-1], self.matrices.version)
        return a._replace(matrix=matrix, rhs=rhs, missing=torch.zeros_like(a.missing))
