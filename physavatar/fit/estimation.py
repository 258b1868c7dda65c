"""Garment physics estimation (PhysAvatar §3.2, Eq. 6–7, Appendix A.3, Algorithm 1): fit ``(ρ, κ_s, κ_b)`` so
that the simulated garment follows a reference mesh sequence.

The reference is a garment mesh sequence ``V̂_{0:T−1}`` (tracked, or simulated for a synthetic capture) whose
frame 0 is the start state, at rest; the garment is driven by its boundary vertices and the body collider
(Eq. 5). The loss is Eq. 6, the sum over frames of the squared vertex errors,

``L(θ) = Σ_{t=1}^{T−1} Σ_i ‖x_{t,i}(θ) − x̂_{t,i}‖²``  (m²).

Algorithm 1 accumulates an MSE per frame instead; the two differ by the constant factor ``3V`` per frame, which
changes neither the minimiser, nor Adam's steps (invariant to the loss scale up to its ``ε``), nor Gauss–Newton's.
Both estimators below use this one loss.

* :func:`estimate_finite_differences` is Algorithm 1: forward differences with ``δρ = 5``, ``δκ_s = δκ_b = 0.05``
  (Appendix A.3.3), Adam, 100 iterations, parameters clamped to the paper's ranges (``ρ`` 200–640 kg/m³, ``κ``
  0.1–8): ``1 + P`` simulations per iteration for ``P`` parameters.
* :func:`estimate_analytic` differentiates the simulation instead: each step's end state minimises the
  incremental potential, and the implicit function theorem carries ``∂x/∂θ`` through the step
  (:meth:`~physavatar.cloth.SolverCloth.sensitivity_step`, one extra sparse factorisation per step). With the
  residual Jacobian at hand it runs Levenberg–Marquardt (Gauss–Newton with adaptive damping) in ``log θ``,
  converging in a handful of simulations, or Adam on the exact gradients.

Identifiability. ``ρ`` scales the inertia, ``κ_s`` the membrane and ``κ_b`` the bending (:mod:`physavatar.cloth`),
and the barrier stiffness and friction follow the mass, so scaling all three by ``s`` scales the incremental
potential by ``s`` and leaves the motion unchanged: from geometry alone only ``κ_s/ρ`` and ``κ_b/ρ`` can be
recovered. The estimators therefore hold ``ρ`` at its initial value by default and fit ``(κ_s, κ_b)``; a result
reports the identifiable ratios. ``ρ`` can be included (``parameters=SENSITIVITY_PARAMETERS``), as in the paper:
the loss is then flat along the scaling direction, and Levenberg–Marquardt's damping keeps the step finite.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from kernels import backend
from physavatar.cloth import (
    DENSITY_RANGE,
    SENSITIVITY_PARAMETERS,
    STIFFNESS_RANGE,
    ClothConfig,
    ClothState,
    SolverCloth,
)
from physavatar.drive import BodyDriver
from physavatar.simulate import SimulationResult

__all__ = [
    "FD_STEPS",
    "SYNTHETIC_FABRIC",
    "EstimationProblem",
    "EstimationResult",
    "FabricParameters",
    "IterationRecord",
    "Rollout",
    "estimate_analytic",
    "estimate_finite_differences",
    "rollout",
    "sim_loss",
]

F64 = torch.float64

FD_STEPS = {"density": 5.0, "kappa_s": 0.05, "kappa_b": 0.05}
"""Forward-difference steps of Algorithm 1 (Appendix A.3.3), in each parameter's unit."""

_RANGES = {"density": DENSITY_RANGE, "kappa_s": STIFFNESS_RANGE, "kappa_b": STIFFNESS_RANGE}
_SYMBOLS = {"density": "ρ", "kappa_s": "κ_s", "kappa_b": "κ_b"}

SYNTHETIC_FABRIC = ClothConfig(
    density=320.0,
    kappa_s=1.0,
    kappa_b=1.0,
    base_young=1.25e5,
    poisson=0.243,
    thickness=2.0e-3,
    newton_tolerance=1e-4,
    elastic_projection="clamp",
)
"""A heavy, soft synthetic fabric whose stretch and bending both show in the motion of a 0.3–0.5 m garment.

Cotton (:class:`~physavatar.cloth.ClothConfig`'s default) stretches under its own weight by
``ε = ρ g L / E = 472 · 9.81 · 0.4 / 0.821e6 ≈ 2·10⁻³`` at the top of a 0.4 m hang: a 0.5 mm longer garment,
below what tracked geometry resolves, so ``κ_s`` would be unidentifiable. This preset (``κ_s = κ_b = 1``):

* ``ρ = 320`` kg/m³ and ``h = 2`` mm: an areal density ``ρh = 0.64`` kg/m² (a heavy wool felt or coating), with
  ``ρ`` in the middle of the paper's range, so that ``ρ`` and ``2ρ`` are both admissible;
* ``E₀ = 0.125`` MPa: ``ρ g L / E₀ = 320 · 9.81 · 0.4 / 1.25e5 = 1.0 %`` strain at the waist of a 0.4 m skirt
  (0.5 % on average, a 2 mm longer garment at rest and more when it swings). The membrane's areal stiffness
  ``E₀ h = 250`` N/m is close to cotton's 261 N/m: the fabric is soft for its weight, not absolutely;
* bending: the hinge stiffness ``k = E₀ h³ / (24 (1 − ν²)) = 4.4·10⁻⁵`` J gives, on a regular grid, a rigidity
  ``B = 4.8k``–``6k = 2.1``–``2.7·10⁻⁴`` N·m (free strip to cylindrical bending) against a weight
  ``w = ρ h g = 6.3`` N/m²: Peirce's bending length ``c = (B / w)^{1/3} = 3.2``–``3.5`` cm, a few cm as for a
  stiff woven fabric (cotton's here: 1.6 cm). ``c³ = B / w ∝ E₀ h² / ρ`` while the strain ``∝ ρ / E₀``:
  ``E₀`` set the strain, then ``h`` the bending length;
* ``newton_tolerance = 10⁻⁴`` m/s: each step's end state is within about ``Δt · 10⁻⁴ = 4·10⁻⁶`` m of the exact
  minimiser, 25× below the 0.1 mm that a finite-difference step ``δκ_s = 0.05`` moves the garment (the default
  10⁻² m/s would leave up to 0.4 mm of solver noise, larger than that signal). Measured on the 280-vertex
  procedural skirt walking (6 steps, CPU): 11–38 Newton iterations a step against 2–10 at the default, 4–23 at
  10⁻³ and 19–50 (one step stopping at the cap of 50) at 10⁻⁵.
"""


# ---------------------------------------------------------------------------------------------------------------
# Parameters and problem
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FabricParameters:
    """The garment's physical parameters (Eq. 5), in the paper's ranges.

    Attributes:
        density: volumetric density ``ρ``, kg/m³, in 200–640.
        kappa_s: membrane stiffness multiplier ``κ_s``, in 0.1–8.
        kappa_b: bending stiffness multiplier ``κ_b``, in 0.1–8.

    Raises:
        ValueError: a value outside its range (or not finite).
    """

    density: float
    kappa_s: float
    kappa_b: float

    def __post_init__(self):
        for name in SENSITIVITY_PARAMETERS:
            value = getattr(self, name)
            lo, hi = _RANGES[name]
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(
                    f"{name} ({value}) lies outside the paper's range {lo:g}–{hi:g} (Appendix A.3.3); start the "
                    "estimation inside it"
                )

    @staticmethod
    def from_config(config: ClothConfig) -> FabricParameters:
        """The parameters a :class:`~physavatar.cloth.ClothConfig` holds."""
        return FabricParameters(config.density, config.kappa_s, config.kappa_b)

    def config(self, base: ClothConfig) -> ClothConfig:
        """``base`` with these parameters."""
        return dataclasses.replace(base, density=self.density, kappa_s=self.kappa_s, kappa_b=self.kappa_b)

    def values(self, names: Sequence[str]) -> list[float]:
        """The values of the named parameters, in order."""
        return [float(getattr(self, name)) for name in names]

    def with_values(self, names: Sequence[str], values: Sequence[float]) -> FabricParameters:
        """These parameters with the named ones replaced."""
        return dataclasses.replace(self, **{n: float(v) for n, v in zip(names, values, strict=True)})

    @property
    def ratios(self) -> tuple[float, float]:
        """The identifiable ratios ``(κ_s / ρ, κ_b / ρ)``, m³/kg."""
        return self.kappa_s / self.density, self.kappa_b / self.density


@dataclass(frozen=True, eq=False)
class EstimationProblem:
    """A reference garment sequence and what drives it (Algorithm 1's input).

    Attributes:
        rest_vertices: ``[V, 3]`` rest shape of the garment (membrane and bending rest state), m.
        faces: ``[F, 3]`` garment triangles.
        reference: ``[T, V, 3]`` reference garment frames ``V̂`` (tracked meshes), m; frame 0 is the start state,
            at rest (zero velocity).
        body_frames: ``[T, B, 3]`` body collider vertices per frame, m (``B`` may be 0).
        body_faces: ``[Fb, 3]`` body triangles (may be empty).
        boundary_index: ``[D]`` Dirichlet garment vertices (Appendix A.3.2).
        boundary_targets: ``[T, D, 3]`` their positions per frame, m.
        fps: frames per second; one implicit step of ``Δt = 1 / fps`` per frame (paper: 25).
        config: material and solver settings; the estimated parameters replace its ``density``, ``kappa_s`` and
            ``kappa_b``.
        reference_faces: ``[F', 3]`` the reference meshes' triangles, when they come with their own; they must
            equal ``faces`` (the simulation needs the reference's topology).

    Raises:
        ValueError: frame counts that differ between reference, body and boundary targets; a reference whose
            vertex count or faces differ from the rest mesh (a topology change); malformed shapes or indices.
    """

    rest_vertices: torch.Tensor
    faces: torch.Tensor
    reference: torch.Tensor
    body_frames: torch.Tensor
    body_faces: torch.Tensor
    boundary_index: torch.Tensor
    boundary_targets: torch.Tensor
    fps: float
    config: ClothConfig
    reference_faces: torch.Tensor | None = None

    def __post_init__(self):
        def put(name: str, value) -> None:
            object.__setattr__(self, name, value)

        put("rest_vertices", torch.as_tensor(self.rest_vertices).detach().to("cpu", F64))
        put("reference", torch.as_tensor(self.reference).detach().to("cpu", F64))
        put("body_frames", torch.as_tensor(self.body_frames).detach().to("cpu", F64))
        put("boundary_targets", torch.as_tensor(self.boundary_targets).detach().to("cpu", F64))
        for name in ("faces", "body_faces", "boundary_index"):
            value = torch.as_tensor(getattr(self, name)).detach().cpu()
            if value.dtype.is_floating_point:
                raise ValueError(f"{name} must hold integer indices, got {value.dtype}")
            put(name, value.long())
        x, faces, ref = self.rest_vertices, self.faces, self.reference
        if x.dim() != 2 or x.shape[1] != 3:
            raise ValueError(f"rest_vertices must be [V, 3], got {list(x.shape)}")
        v = x.shape[0]
        if faces.dim() != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
            raise ValueError(f"faces must be a non-empty [F, 3] array, got {list(faces.shape)}")
        if int(faces.min()) < 0 or int(faces.max()) >= v:
            raise ValueError(f"faces index vertices 0..{int(faces.max())} but the rest mesh has {v} vertices")
        if ref.dim() != 3 or ref.shape[2] != 3:
            raise ValueError(f"reference must be [T, V, 3], got {list(ref.shape)}")
        if ref.shape[1] != v:
            raise ValueError(
                f"topology change: the reference frames hold {ref.shape[1]} vertices but the rest mesh {v}; "
                "estimation needs the reference in the simulation mesh's topology (same vertices, same faces)"
            )
        if self.reference_faces is not None:
            ref_faces = torch.as_tensor(self.reference_faces).detach().cpu().long()
            if tuple(ref_faces.shape) != tuple(faces.shape) or not torch.equal(ref_faces, faces):
                raise ValueError(
                    f"topology change: the reference meshes have {ref_faces.shape[0]} faces, the rest mesh "
                    f"{faces.shape[0]}"
                    + ("" if ref_faces.shape != faces.shape else " with different indices")
                    + "; estimation needs the reference in the simulation mesh's topology"
                )
            put("reference_faces", ref_faces)
        frames = ref.shape[0]
        if frames < 2:
            raise ValueError(f"reference must hold at least 2 frames (a start and one step), got {frames}")
        body, targets = self.body_frames, self.boundary_targets
        if body.dim() != 3 or body.shape[2] != 3:
            raise ValueError(f"body_frames must be [T, B, 3], got {list(body.shape)}")
        if targets.dim() != 3 or targets.shape[2] != 3:
            raise ValueError(f"boundary_targets must be [T, D, 3], got {list(targets.shape)}")
        for name, count in (("body_frames", body.shape[0]), ("boundary_targets", targets.shape[0])):
            if count != frames:
                raise ValueError(
                    f"{name} holds {count} frames but reference {frames}; give every sequence the same frames"
                )
        if self.body_faces.numel():
            if self.body_faces.dim() != 2 or self.body_faces.shape[1] != 3:
                raise ValueError(f"body_faces must be [Fb, 3], got {list(self.body_faces.shape)}")
            if int(self.body_faces.min()) < 0 or int(self.body_faces.max()) >= body.shape[1]:
                raise ValueError(
                    f"body_faces index vertices up to {int(self.body_faces.max())} but body_frames hold "
                    f"{body.shape[1]} vertices"
                )
        else:
            put("body_faces", self.body_faces.reshape(0, 3))
            if body.shape[1]:
                raise ValueError(f"body_frames hold {body.shape[1]} vertices but body_faces is empty")
        index = self.boundary_index
        if index.dim() != 1 or targets.shape[1] != index.numel():
            raise ValueError(
                f"boundary_index must be [D] and boundary_targets [T, D, 3]: got {list(index.shape)} and "
                f"{list(targets.shape)}"
            )
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= v):
            raise ValueError(f"boundary_index must index garment vertices 0..{v - 1}")
        if not (math.isfinite(self.fps) and self.fps > 0.0):
            raise ValueError(f"fps ({self.fps}) must be a positive number of frames per second (paper: 25)")
        for name in ("rest_vertices", "reference", "body_frames", "boundary_targets"):
            if not bool(torch.isfinite(getattr(self, name)).all()):
                raise ValueError(f"{name} holds NaN or inf values")

    @property
    def frames(self) -> int:
        """``T``, the number of frames (``T − 1`` simulation steps)."""
        return self.reference.shape[0]

    @property
    def dt(self) -> float:
        """Step size ``1 / fps``, s."""
        return 1.0 / self.fps

    def driver(self) -> BodyDriver:
        """The body and boundary targets of every frame, as the steps of a rollout take them."""
        return BodyDriver(self.body_frames, self.boundary_index, self.boundary_targets, self.fps)

    @staticmethod
    def from_simulation(
        result: SimulationResult, config: ClothConfig, rest_vertices: torch.Tensor | None = None
    ) -> EstimationProblem:
        """A problem whose reference is a simulated sequence (a synthetic capture, :func:`physavatar.simulate`).

        Args:
            result: the sequence; its boundary vertices' frames become the boundary targets.
            config: settings of the estimation's simulations (its density and stiffnesses are replaced).
            rest_vertices: ``[V, 3]`` rest shape; ``None`` takes the first frame (the simulator starts at rest).
        """
        frames = result.garment_frames
        rest = frames[0] if rest_vertices is None else rest_vertices
        return EstimationProblem(
            rest,
            result.garment_faces,
            frames,
            result.body_frames,
            result.body_faces,
            result.boundary_index,
            frames[:, result.boundary_index.long()],
            result.fps,
            config,
        )


# ---------------------------------------------------------------------------------------------------------------
# Simulation and loss
# ---------------------------------------------------------------------------------------------------------------


class Rollout(NamedTuple):
    """A simulated sequence: ``frames [T, V, 3]`` (m) and, when asked, ``sensitivities [T, V, 3, P]``
    (``∂x_t / ∂θ_p``, m per parameter unit; zero at frame 0)."""

    frames: torch.Tensor
    sensitivities: torch.Tensor | None


def rollout(
    problem: EstimationProblem,
    params: FabricParameters,
    sensitivities: bool = False,
    parameters: Sequence[str] = ("kappa_s", "kappa_b"),
    device: str | None = None,
) -> Rollout:
    """Simulate the problem's sequence with ``params`` (Eq. 5), from the reference's first frame at rest.

    Args:
        problem: reference, body and boundary.
        params: the garment's parameters.
        sensitivities: also carry ``∂x/∂θ`` through every step
            (:meth:`~physavatar.cloth.SolverCloth.sensitivity_step`).
        parameters: the ``θ`` of the sensitivities, from ``("density", "kappa_s", "kappa_b")``.
        device: ``"cpu"`` or ``"cuda"``; ``None`` keeps the backend's device or picks the default.

    Returns:
        :class:`Rollout`, on the CPU, float64.

    Raises:
        ValueError: a step that produced NaN or inf.
    """
    backend.init(device)
    dev = backend.torch_device()
    parameters = tuple(parameters)
    solver = SolverCloth(problem.rest_vertices, problem.faces, params.config(problem.config), problem.body_faces)
    driver = problem.driver().to(dev)
    x0 = problem.reference[0].to(dev)
    # double-buffered: each step writes the other state, and the sensitivities read both
    state, new = ClothState(x0.clone(), torch.zeros_like(x0)), ClothState(x0.clone(), torch.zeros_like(x0))
    frames = [x0.cpu()]
    if sensitivities:
        s_x = torch.zeros(*x0.shape, len(parameters), dtype=F64, device=dev)
        s_v = torch.zeros_like(s_x)
        sens = [s_x.cpu()]
    dt = driver.dt
    for t in range(problem.frames - 1):
        control = driver.control(t)
        solver.step(state, new, control, dt)
        if not bool(torch.isfinite(new.x).all()):
            raise ValueError(f"step {t + 1} produced NaN or inf positions with {params}; check the inputs")
        if sensitivities:
            s_x, s_v = solver.sensitivity_step(state, new, control, dt, s_x, s_v, parameters)
            sens.append(s_x.cpu())
        state, new = new, state
        frames.append(state.x.to("cpu", copy=True))  # a copy: the state's tensors are written again
    return Rollout(torch.stack(frames), torch.stack(sens) if sensitivities else None)


def sim_loss(frames: torch.Tensor, reference: torch.Tensor) -> float:
    """Eq. 6: ``Σ_{t≥1} Σ_i ‖x_{t,i} − x̂_{t,i}‖²``, m², over ``[T, V, 3]`` sequences (frame 0 is shared)."""
    if frames.shape != reference.shape:
        raise ValueError(f"frames {list(frames.shape)} and reference {list(reference.shape)} must have one shape")
    return float(((frames[1:] - reference[1:]) ** 2).sum())


# ---------------------------------------------------------------------------------------------------------------
# Estimation
# ---------------------------------------------------------------------------------------------------------------


class IterationRecord(NamedTuple):
    """What one iteration ended with: the parameters, their loss (m²), its wall time (s) and simulations so far."""

    parameters: FabricParameters
    loss: float
    wall_time: float
    simulations: int


@dataclass
class EstimationResult:
    """An estimation run.

    Attributes:
        method: ``"finite_differences"``, ``"levenberg_marquardt"`` or ``"adam"`` (analytic gradients).
        parameter_names: the estimated parameters; the others kept their initial values.
        history: parameters after each iteration, the initial ones first (``iterations + 1`` entries).
        loss: Eq. 6 at each entry of ``history``, m².
        wall_time: seconds per iteration (``iterations`` entries; the first includes the initial evaluation).
        simulations: rollouts run in total (with sensitivities, for the analytic methods).
        converged: Levenberg–Marquardt stopped on its tolerance or its noise floor (False for the fixed-length
            Adam runs).
        total_time: seconds for the whole run, rejected Levenberg–Marquardt tries included.
    """

    method: str
    parameter_names: tuple[str, ...]
    history: list[FabricParameters]
    loss: list[float]
    wall_time: list[float]
    simulations: int
    converged: bool = False
    total_time: float = 0.0

    @property
    def final(self) -> FabricParameters:
        """The parameters of the last iteration."""
        return self.history[-1]

    @property
    def ratios(self) -> tuple[float, float]:
        """The identifiable ratios ``(κ_s / ρ, κ_b / ρ)`` of the final parameters, m³/kg."""
        return self.final.ratios

    @property
    def iterations(self) -> int:
        return len(self.wall_time)


class _Reporter:
    """Records iterations and reports them (simulate.py's convention: ``True`` prints to stderr)."""

    def __init__(self, method, names, initial, progress, total):
        self.result = EstimationResult(method, tuple(names), [initial], [], [], 0)
        self.progress = progress
        self.total = total

    def record(self, params: FabricParameters, loss: float, wall: float, simulations: int) -> None:
        r = self.result
        if r.loss:
            r.history.append(params)
            r.wall_time.append(wall)
        r.loss.append(loss)
        r.simulations = simulations
        if not r.wall_time:
            return
        record = IterationRecord(params, loss, wall, simulations)
        if callable(self.progress):
            self.progress(r.iterations, record)
        elif self.progress:
            values = ", ".join(f"{_SYMBOLS[n]} {getattr(params, n):.4g}" for n in SENSITIVITY_PARAMETERS)
            print(
                f"{r.method} iteration {r.iterations}/{self.total}: loss {loss:.4e} m², {values}, "
                f"{simulations} simulations, {wall:.2f} s",
                file=sys.stderr,
            )


def _check_names(parameters: Sequence[str]) -> tuple[str, ...]:
    names = tuple(parameters)
    if not names or len(set(names)) != len(names) or any(n not in SENSITIVITY_PARAMETERS for n in names):
        raise ValueError(f"parameters {names} must be distinct names from {SENSITIVITY_PARAMETERS}")
    return names


def _clamp(names: Sequence[str], values: Sequence[float]) -> list[float]:
    return [min(max(float(v), _RANGES[n][0]), _RANGES[n][1]) for n, v in zip(names, values, strict=True)]


class _Adam:
    """Adam (Kingma and Ba 2015) on a few scalars with per-parameter step sizes."""

    def __init__(self, lr: list[float], betas: tuple[float, float], eps: float):
        self.lr, (self.b1, self.b2), self.eps = lr, betas, eps
        self.m = [0.0] * len(lr)
        self.v = [0.0] * len(lr)
        self.t = 0

    def step(self, values: list[float], grad: list[float]) -> list[float]:
        self.t += 1
        out = []
        for i, (x, g) in enumerate(zip(values, grad, strict=True)):
            self.m[i] = self.b1 * self.m[i] + (1.0 - self.b1) * g
            self.v[i] = self.b2 * self.v[i] + (1.0 - self.b2) * g * g
            m_hat = self.m[i] / (1.0 - self.b1**self.t)
            v_hat = self.v[i] / (1.0 - self.b2**self.t)
            out.append(x - self.lr[i] * m_hat / (math.sqrt(v_hat) + self.eps))
        return out


def _learning_rates(names, learning_rate: float | dict[str, float] | None) -> list[float]:
    """Adam step sizes: one number for every parameter, a dict by name, or ``None`` for the FD steps."""
    if learning_rate is None:
        return [FD_STEPS[n] for n in names]
    if isinstance(learning_rate, dict):
        return [float(learning_rate.get(n, FD_STEPS[n])) for n in names]
    return [float(learning_rate)] * len(names)


def estimate_finite_differences(
    problem: EstimationProblem,
    initial: FabricParameters,
    parameters: Sequence[str] = ("kappa_s", "kappa_b"),
    iterations: int = 100,
    steps: dict[str, float] | None = None,
    learning_rate: float | dict[str, float] | None = None,
    betas: tuple[float, float] = (0.9, 0.999),
    eps: float = 1e-8,
    device: str | None = None,
    progress: bool | Callable[[int, IterationRecord], None] = True,
) -> EstimationResult:
    """Algorithm 1: Adam on forward-difference gradients of Eq. 6 (Eq. 7), parameters clamped to their ranges.

    Each iteration runs the simulation at ``θ`` and at ``θ + δ_p e_p`` for every estimated parameter ``p``
    (``1 + P`` rollouts) and takes one Adam step. Where ``θ_p + δ_p`` would leave the range, the difference is
    taken backwards. After the last iteration one more rollout evaluates the final parameters.

    Args:
        problem: the reference sequence.
        initial: starting parameters (the ones not estimated keep these values).
        parameters: which of ``("density", "kappa_s", "kappa_b")`` to estimate; ``ρ`` is fixed by default (only
            ``κ_s/ρ`` and ``κ_b/ρ`` are identifiable, see the module docstring).
        iterations: Adam steps (paper: 100).
        steps: forward-difference steps by name (default :data:`FD_STEPS`: ``δρ = 5``, ``δκ = 0.05``).
        learning_rate: Adam's step size: one number, a dict by name, or ``None`` for the difference steps
            (``ρ``: 5 kg/m³, ``κ``: 0.05 per iteration; the paper does not give its value).
        betas: Adam's moment decay rates.
        eps: Adam's ``ε`` (the loss is in m²).
        device: ``"cpu"`` or ``"cuda"`` (``None``: the backend's).
        progress: ``True`` writes one line per iteration to stderr; a callable receives
            ``(iteration, IterationRecord)``.

    Returns:
        :class:`EstimationResult` with ``method="finite_differences"``.

    Raises:
        ValueError: unknown parameter names, non-positive steps, fewer than one iteration.
    """
    names = _check_names(parameters)
    if iterations < 1:
        raise ValueError(f"iterations ({iterations}) must be at least 1")
    steps = {**FD_STEPS, **(steps or {})}
    if any(not steps[n] > 0.0 for n in names):
        raise ValueError(f"finite-difference steps {steps} must be positive")
    adam = _Adam(_learning_rates(names, learning_rate), betas, eps)
    report = _Reporter("finite_differences", names, initial, progress, iterations)
    params, sims = initial, 0

    def loss_at(p: FabricParameters) -> float:
        nonlocal sims
        sims += 1
        return sim_loss(rollout(problem, p, device=device).frames, problem.reference)

    start = begin = time.perf_counter()
    loss = loss_at(params)
    report.record(params, loss, 0.0, sims)
    for _ in range(iterations):
        values = params.values(names)
        grad = []
        for i, name in enumerate(names):
            delta = steps[name] if values[i] + steps[name] <= _RANGES[name][1] else -steps[name]
            probe = list(values)
            probe[i] += delta
            grad.append((loss_at(params.with_values(names, probe)) - loss) / delta)
        params = params.with_values(names, _clamp(names, adam.step(values, grad)))
        loss = loss_at(params)
        now = time.perf_counter()
        report.record(params, loss, now - start, sims)
        start = now
    report.result.total_time = time.perf_counter() - begin
    return report.result


def estimate_analytic(
    problem: EstimationProblem,
    initial: FabricParameters,
    parameters: Sequence[str] = ("kappa_s", "kappa_b"),
    method: str = "levenberg_marquardt",
    iterations: int | None = None,
    tolerance: float = 1e-5,
    damping: float = 1e-3,
    learning_rate: float | dict[str, float] | None = None,
    betas: tuple[float, float] = (0.9, 0.999),
    eps: float = 1e-8,
    device: str | None = None,
    progress: bool | Callable[[int, IterationRecord], None] = True,
) -> EstimationResult:
    """Fit Eq. 6 with gradients from the simulation's sensitivities instead of finite differences.

    One rollout with sensitivities gives the residuals ``r = x(θ) − x̂`` (frames 1…T−1, flattened) and their
    Jacobian ``J = ∂x/∂θ``; the gradient is ``∇L = 2 Jᵀ r``.

    * ``"levenberg_marquardt"``: Gauss–Newton in ``u = log θ`` (a step scaled to the parameters' size, positive
      by construction), damped as ``(J_uᵀJ_u + λ diag(J_uᵀJ_u)) δu = −J_uᵀ r`` with ``J_u = J diag(θ)``, then
      clamped to the ranges. A step that lowers the loss is taken and ``λ`` divided by 10; otherwise ``λ`` is
      multiplied by 10 and the step retried (each try is one rollout). Stops when ``‖δu‖_∞ < tolerance``
      (relative parameter change), when ten tries in a row fail to lower the loss (the solver's noise floor),
      or after ``iterations`` steps (default 20).
    * ``"adam"``: Algorithm 1's Adam on the exact gradient, one rollout per iteration (default 100 iterations,
      step sizes as in :func:`estimate_finite_differences`).

    Args:
        problem: the reference sequence.
        initial: starting parameters (the ones not estimated keep these values).
        parameters: which of ``("density", "kappa_s", "kappa_b")`` to estimate; ``ρ`` is fixed by default (only
            ``κ_s/ρ`` and ``κ_b/ρ`` are identifiable, see the module docstring).
        method: ``"levenberg_marquardt"`` or ``"adam"``.
        iterations: iteration cap (``None``: 20 for Levenberg–Marquardt, 100 for Adam).
        tolerance: Levenberg–Marquardt's stopping step in ``log θ``.
        damping: Levenberg–Marquardt's initial ``λ``.
        learning_rate: Adam's step size (see :func:`estimate_finite_differences`).
        betas: Adam's moment decay rates.
        eps: Adam's ``ε``.
        device: ``"cpu"`` or ``"cuda"`` (``None``: the backend's).
        progress: ``True`` writes one line per iteration to stderr; a callable receives
            ``(iteration, IterationRecord)``.

    Returns:
        :class:`EstimationResult`.

    Raises:
        ValueError: unknown method or parameter names, fewer than one iteration.
    """
    names = _check_names(parameters)
    if method not in ("levenberg_marquardt", "adam"):
        raise ValueError(f"method ({method!r}) must be 'levenberg_marquardt' or 'adam'")
    iterations = (20 if method == "levenberg_marquardt" else 100) if iterations is None else int(iterations)
    if iterations < 1:
        raise ValueError(f"iterations ({iterations}) must be at least 1")
    report = _Reporter(method, names, initial, progress, iterations)
    sims = 0
    reference = problem.reference[1:].reshape(-1)

    def evaluate(p: FabricParameters) -> tuple[float, torch.Tensor, torch.Tensor]:
        nonlocal sims
        sims += 1
        frames, sens = rollout(problem, p, sensitivities=True, parameters=names, device=device)
        residual = frames[1:].reshape(-1) - reference
        return float(residual @ residual), residual, sens[1:].reshape(-1, len(names))

    start = begin = time.perf_counter()
    params = initial
    loss, residual, jacobian = evaluate(params)
    report.record(params, loss, 0.0, sims)
    if method == "adam":
        adam = _Adam(_learning_rates(names, learning_rate), betas, eps)
        for _ in range(iterations):
            grad = (2.0 * jacobian.T @ residual).tolist()
            params = params.with_values(names, _clamp(names, adam.step(params.values(names), grad)))
            loss, residual, jacobian = evaluate(params)
            now = time.perf_counter()
            report.record(params, loss, now - start, sims)
            start = now
        report.result.total_time = time.perf_counter() - begin
        return report.result

    lam = damping
    log_lo = torch.tensor([math.log(_RANGES[n][0]) for n in names], dtype=F64)
    log_hi = torch.tensor([math.log(_RANGES[n][1]) for n in names], dtype=F64)
    for _ in range(iterations):
        theta = torch.tensor(params.values(names), dtype=F64)
        j_u = jacobian * theta
        a = j_u.T @ j_u
        g = j_u.T @ residual
        accepted = False
        for _ in range(10):
            lhs = a + lam * torch.diag(torch.diagonal(a).clamp_min(1e-300))
            step = -torch.linalg.lstsq(lhs, g[:, None]).solution[:, 0]
            u = (theta.log() + step).clamp(log_lo, log_hi)
            trial = params.with_values(names, _clamp(names, u.exp().tolist()))
            step_size = float((u - theta.log()).abs().max())
            trial_loss, trial_residual, trial_jacobian = evaluate(trial)
            if trial_loss < loss:
                accepted = True
                params, loss, residual, jacobian = trial, trial_loss, trial_residual, trial_jacobian
                lam = max(lam / 10.0, 1e-12)
                break
            lam *= 10.0
        if not accepted:
            report.result.converged = True  # no step lowers the loss: the solver's noise floor
            break
        now = time.perf_counter()
        report.record(params, loss, now - start, sims)
        start = now
        if step_size < tolerance:
            report.result.converged = True
            break
    report.result.total_time = time.perf_counter() - begin
    return report.result
