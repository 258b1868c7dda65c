"""The Q-GMLS solver says when a step fails and refuses inputs that are not finite, with the host loop and with the
device loop alike (``SolverConfig.device_loop``; uncaptured on the CPU)."""

import dataclasses
import math

import pytest
import torch

from kernels import backend
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.solver import (
    PlaneCollider,
    PointForces,
    PointTargets,
    QGMLSControl,
    QGMLSPotential,
    QGMLSState,
    QGMLSStepReport,
    SolverConfig,
    SolverQGMLS,
    SphereCollider,
)
from tests.pienerf.bodies import lattice

_BUILT = {}


def _model() -> QGMLSModel:
    """A 20 × 10 × 10 cm bar of 32 particles and 8 kernels, built once per device."""
    device = backend.torch_device()
    if device not in _BUILT:
        position, volume = lattice((0.2, 0.1, 0.1), 0.05)
        _BUILT[device] = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=8), device=device)
    return _BUILT[device]


def _solver(material: Material = Material(), config: SolverConfig = SolverConfig()) -> SolverQGMLS:
    """A solver on :func:`_model`, built once per material and settings (its precomputation dominates the cost)."""
    key = (backend.torch_device(), material, config)
    if key not in _BUILT:
        _BUILT[key] = SolverQGMLS(_model(), material, config)
    return _BUILT[key]


def _ends(model: QGMLSModel):
    """Handles on the particles of the near (x < 5 cm) and far (x > 15 cm) ends."""
    x = model.position[:, 0]
    return model.handle(model.position[x < 0.05]), model.handle(model.position[x > 0.15])


LOOPS = pytest.mark.parametrize("device_loop", [False, True], ids=["host loop", "device loop"])
"""Each test of a step's outcome runs with both Newton loops."""


def _outcome(report: QGMLSStepReport) -> tuple:
    """What a step's report says of its outcome (everything but its times and which loop took it)."""
    return (report.iterations, report.energy, report.last_update, report.min_det, report.line_search_halvings,
            report.converged, report.line_search_failure)


def _both_loops(material: Material, config: SolverConfig, control: QGMLSControl, dt: float, steps: int = 1,
                start: torch.Tensor | None = None) -> list[tuple[QGMLSStepReport, QGMLSState]]:
    """The last report and the state after ``steps`` steps from rest (or from ``q = start``), with the host loop
    and with the device loop."""
    results = []
    for device_loop in (False, True):
        solver = _solver(material, dataclasses.replace(config, device_loop=device_loop))
        state = solver.rest_state()
        if start is not None:
            state.q.copy_(start)
        for _ in range(steps):
            report = solver.step(state, state, control, dt)
        results.append((report, state))
    return results


def _assert_same_outcome(results) -> QGMLSStepReport:
    """Both loops' reports say the same (to the bit: the device loop hands the failing step to the host loop, and
    the loops' arithmetic is the same where both take a step) and their states are equal."""
    (host, host_state), (device, device_state) = results
    assert _outcome(device) == _outcome(host)
    assert torch.equal(device_state.q, host_state.q) and torch.equal(device_state.qd, host_state.qd)
    return host


def _inverted_start(model: QGMLSModel) -> torch.Tensor:
    """q ``[nT, 3]`` closest (least squares at the integrator points) to the body mirrored in x = 0: every
    quadrature point is inverted (det F < 0), so the Neo-Hookean energy is +∞ at the step's start."""
    potential = QGMLSPotential(model, Material(), SolverConfig())
    shape = model.ip_shape
    rows = potential.point_shape_matrix(shape.index.clamp_min(0), shape.value * (shape.index >= 0))
    rest = model.ip_state(torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device))[0]
    mirror = torch.zeros_like(rest)
    mirror[:, 0] = -2.0 * rest[:, 0]
    q = torch.linalg.lstsq(rows.cpu(), mirror.cpu()).solution.to(model.device)
    assert float(potential.integrator.evaluate(q, gradient=False, hessian=False).min_det) < 0
    return q


@LOOPS
def test_an_ordinary_step_converges(device, device_loop):
    solver = _solver(config=SolverConfig(device_loop=device_loop))
    state = solver.rest_state()
    report = solver.step(state, state, QGMLSControl(), 1e-2)
    assert report.converged and not report.line_search_failed and report.line_search_failure == ""


def test_a_huge_point_force_reports_an_inversion_from_either_loop(device):
    """1e20 N: every trial along the Newton step inverts a quadrature point down to the smallest step."""
    model = _model()
    _, tip = _ends(model)
    force = torch.zeros(tip.index.shape[0], 3, dtype=torch.float64, device=model.device)
    force[:, 1] = -1e20
    results = _both_loops(Material(), SolverConfig(), QGMLSControl(forces=[PointForces(tip, force)]), 1e-2)
    report = _assert_same_outcome(results)
    assert report.line_search_failed and report.line_search_failure == "inversion"
    assert not report.converged
    assert report.min_det > 0  # the body stays uninverted, and the report says why it did not move


def test_a_stiff_body_under_huge_gravity_reports_no_decrease_from_either_loop(device):
    """E = 1e13 Pa at ν = 0.499 stepped 1 s at a time under 1e6 m/s²: the Newton direction is so ill-conditioned
    that no step along it lowers the energy (the trials stay finite), in every step."""
    config = SolverConfig(gravity=(0.0, -1e6, 0.0), rayleigh_alpha=2.0, newton_iterations=1)
    results = _both_loops(Material(young_modulus=1e13, poisson_ratio=0.499), config, QGMLSControl(), 1.0, steps=2)
    report = _assert_same_outcome(results)
    assert report.line_search_failure == "no decrease" and not report.converged
    assert report.line_search_halvings == config.line_search_steps


def test_an_inverted_start_reports_a_non_finite_step_from_either_loop(device):
    """A state whose every quadrature point is inverted has Ψ = +∞: no trial can be compared with it, and both
    loops say so (the device loop used to take the infinite energy for a stationary iterate and report a converged
    step)."""
    start = _inverted_start(_model())
    results = _both_loops(Material(), SolverConfig(newton_iterations=2), QGMLSControl(), 1e-2, start=start)
    report = _assert_same_outcome(results)
    assert report.line_search_failure == "not finite" and not report.converged
    assert report.energy == math.inf


@LOOPS
def test_arap_under_enormous_gravity_reports_no_convergence(device, device_loop):
    """ARAP has no inversion barrier: −1e12 m/s² onto a floor crushes the bar through itself (det F ≈ −6e7 after
    three Newton iterations); the report must not claim a converged step."""
    config = SolverConfig(gravity=(0, -1e12, 0), newton_iterations=1, device_loop=device_loop)
    solver = SolverQGMLS(_model(), Material(model="arap"), config)
    state = solver.rest_state()
    report = solver.step(state, state, QGMLSControl(colliders=[PlaneCollider()]), 1e-2)
    assert not report.converged
    assert report.last_update > 1e3 * config.newton_tolerance


@LOOPS
@pytest.mark.parametrize("where", ["target", "force", "q", "qd"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_inputs_are_refused_naming_the_input(device, where, bad, device_loop):
    model = _model()
    solver = _solver(config=SolverConfig(device_loop=device_loop))
    state = solver.rest_state()
    pin, tip = _ends(model)
    target = pin.rest.clone()
    force = torch.zeros(tip.index.shape[0], 3, dtype=torch.float64, device=model.device)
    if where == "target":
        target[0, 1] = bad
    elif where == "force":
        force[-1, 2] = bad
    else:
        getattr(state, where)[0, 0] = bad
    control = QGMLSControl(springs=[PointTargets(pin, target, 1e4)], forces=[PointForces(tip, force)])
    name = {"target": r"springs\[0\] target", "force": r"forces\[0\] force", "q": "state q", "qd": "state qd"}[where]
    with pytest.raises(ValueError, match=name + " holds NaN or inf"):
        solver.step(state, state, control, 1e-2)


@LOOPS
@pytest.mark.parametrize("dt", [math.nan, math.inf, -1e-2, 0.0, "0.01", None])
def test_bad_dt_is_refused(device, dt, device_loop):
    solver = _solver(config=SolverConfig(device_loop=device_loop))
    state = solver.rest_state()
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        solver.step(state, state, QGMLSControl(), dt)


@pytest.mark.parametrize("stiffness", [math.inf, -1.0, math.nan])
def test_bad_spring_stiffness_is_a_clear_error(device, stiffness):
    model = _model()
    solver = _solver()
    state = solver.rest_state()
    pin, _ = _ends(model)
    control = QGMLSControl(springs=[PointTargets(pin, pin.rest.clone(), stiffness)])
    with pytest.raises(ValueError, match=r"springs\[0\] stiffness must be a finite number >= 0"):
        solver.step(state, state, control, 1e-2)
    with pytest.raises(ValueError, match=r"springs\[0\] stiffness"):
        solver.solve_static(control)


def test_mis_shaped_targets_and_colliders_are_refused(device):
    model = _model()
    solver = _solver()
    state = solver.rest_state()
    pin, _ = _ends(model)
    with pytest.raises(ValueError, match=r"springs\[0\] target must be"):
        solver.step(state, state, QGMLSControl(springs=[PointTargets(pin, pin.rest[:1].clone(), 1e3)]), 1e-2)
    with pytest.raises(ValueError, match=r"colliders\[0\] must have finite coordinates"):
        solver.step(state, state, QGMLSControl(colliders=[SphereCollider((0.0, math.nan, 0.0), 0.1)]), 1e-2)
