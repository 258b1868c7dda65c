"""The Q-GMLS solver says when a step fails and refuses inputs that are not finite."""

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


def test_an_ordinary_step_converges(device):
    solver = _solver()
    state = solver.rest_state()
    report = solver.step(state, state, QGMLSControl(), 1e-2)
    assert report.converged and not report.line_search_failed and report.line_search_failure == ""


def test_a_huge_point_force_reports_a_failed_line_search(device):
    """1e20 N: every trial along the Newton step inverts a quadrature point down to the smallest step."""
    model = _model()
    solver = _solver()
    state = solver.rest_state()
    _, tip = _ends(model)
    force = torch.zeros(tip.index.shape[0], 3, dtype=torch.float64, device=model.device)
    force[:, 1] = -1e20
    report = solver.step(state, state, QGMLSControl(forces=[PointForces(tip, force)]), 1e-2)
    assert report.line_search_failed and report.line_search_failure == "inversion"
    assert not report.converged
    assert report.min_det > 0  # the body stays uninverted, and the report says why it did not move


def test_arap_under_enormous_gravity_reports_no_convergence(device):
    """ARAP has no inversion barrier: −1e12 m/s² onto a floor crushes the bar through itself (det F ≈ −6e7 after
    three Newton iterations); the report must not claim a converged step."""
    config = SolverConfig(gravity=(0, -1e12, 0), newton_iterations=1)
    solver = SolverQGMLS(_model(), Material(model="arap"), config)
    state = solver.rest_state()
    report = solver.step(state, state, QGMLSControl(colliders=[PlaneCollider()]), 1e-2)
    assert not report.converged
    assert report.last_update > 1e3 * config.newton_tolerance


@pytest.mark.parametrize("where", ["target", "force", "q", "qd"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_inputs_are_refused_naming_the_input(device, where, bad):
    model = _model()
    solver = _solver()
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


@pytest.mark.parametrize("dt", [math.nan, math.inf, -1e-2, 0.0, "0.01", None])
def test_bad_dt_is_refused(device, dt):
    solver = _solver()
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
