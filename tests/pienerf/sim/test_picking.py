"""Picking, dragging, pins and forces of pienerf.sim.picking, with no viewer."""

from __future__ import annotations

import math

import pytest
import torch

from kernels import backend
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.picking import (
    DragController,
    Interaction,
    PickSurface,
    clamp_target,
    inverse_effective_mass,
    ray_particle_pick,
    spring_damper_target,
)
from pienerf.sim.solver import SolverConfig, SolverQGMLS
from tests.pienerf.bodies import lattice

_MODELS: dict = {}


def _model() -> QGMLSModel:
    """A 40 × 10 × 10 cm bar of 32 particles and 4 kernels, cached per device."""
    device = backend.torch_device()
    if device not in _MODELS:
        position, volume = lattice((0.4, 0.1, 0.1), 0.05)
        _MODELS[device] = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=4), device=device)
    return _MODELS[device]


def test_ray_pick_takes_the_nearest_point_in_front_within_the_radius():
    points = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.01, -2.0], [0.0, 0.0, 1.0], [0.5, 0.0, -0.5]],
                          dtype=torch.float64)
    index, t = ray_particle_pick(torch.zeros(3), torch.tensor([0.0, 0.0, -2.0]), points, radius=0.05)
    assert index == 0 and t == pytest.approx(1.0)
    assert ray_particle_pick(torch.zeros(3), torch.tensor([0.0, 1.0, 0.0]), points, radius=0.05) is None
    with pytest.raises(ValueError, match="ray direction must be a finite non-zero"):
        ray_particle_pick(torch.zeros(3), torch.zeros(3), points, radius=0.05)


def test_clamp_limits_the_spring_acceleration_and_keeps_small_pulls():
    position = torch.zeros(2, 3, dtype=torch.float64)
    target = torch.tensor([[3.0, 4.0, 0.0], [0.001, 0.0, 0.0]], dtype=torch.float64)
    k, w, a_max = 100.0, torch.tensor([0.5, 0.5], dtype=torch.float64), 10.0
    clamped = clamp_target(target, position, k, w, a_max)
    acceleration = w * k * (clamped - position).norm(dim=1)
    assert acceleration[0] == pytest.approx(a_max)  # 0.5 · 100 · 5 = 250 m/s² → clamped to 10
    assert torch.allclose(clamped[0] / clamped[0].norm(), target[0] / 5.0)  # direction kept
    assert torch.equal(clamped[1], target[1])  # 0.05 m/s² is under the limit
    assert torch.equal(clamp_target(target, position, k, w, math.inf), target)


def test_a_far_target_clamps_like_a_near_one(device):
    position = torch.zeros(3, 3, dtype=torch.float64)
    target = torch.tensor([[1e3, 0.0, 0.0], [1e300, 1e300, 0.0], [1e200, 0.0, 0.0]], dtype=torch.float64)
    k, w, a_max = 100.0, torch.full((3,), 0.5, dtype=torch.float64), 10.0
    clamped = clamp_target(target, position, k, w, a_max)
    # Each is pulled to a_max / (w k) = 0.2 m along its own direction (‖t‖ would overflow for the last two).
    expected = 0.2 * torch.tensor([[1.0, 0.0, 0.0], [0.5**0.5, 0.5**0.5, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(clamped, expected, rtol=8 * torch.finfo(torch.float64).eps, atol=0.0)

    model = _model()
    drag = DragController(model, stiffness=500.0, damping=5.0, max_acceleration=20.0)
    q = torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device)
    assert drag.pick(torch.tensor([0.225, 0.075, 1.0]), torch.tensor([0.0, 0.0, -1.0]), q) is not None
    drag.update((1e300, 0.0, 0.0), (1.0, 0.0, 0.0))  # the ray of an absurd camera: clamped as 1e3 is
    (spring,) = drag.control_terms(q, dt=0.01)
    assert bool(torch.isfinite(spring.target).all()) and float(spring.target[0, 0]) > float(drag.position(q)[0])
    with pytest.raises(ValueError, match="finite"):
        drag.update((math.inf, 0.0, 0.0), (1.0, 0.0, 0.0))  # past float64: refused with the reason


def test_spring_damper_equals_one_implicit_spring():
    generator = torch.Generator().manual_seed(0)
    t, x_n, x = (torch.randn(5, 3, generator=generator, dtype=torch.float64) for _ in range(3))
    k, c, h = 300.0, 12.0, 0.02
    target, stiffness = spring_damper_target(t, x_n, k, c, h)
    assert stiffness == pytest.approx(k + c / h)
    assert torch.allclose(stiffness * (target - x), k * (t - x) - c * (x - x_n) / h)


def test_inverse_effective_mass_matches_a_dense_solve(device):
    model = _model()
    handle = model.handle(model.position[[0, 17]])
    density = 800.0
    w = inverse_effective_mass(model, handle, density)
    rows = torch.zeros(2, model.shape_count, dtype=torch.float64, device=model.device)
    rows.scatter_add_(1, handle.index, handle.value)
    expected = torch.einsum("ms,st,mt->m", rows, torch.linalg.inv(density * model.mass), rows)
    assert torch.allclose(w, expected, rtol=1e-8)
    total_mass = density * float(model.volume.sum())
    assert bool((w > 1.0 / total_mass).all())  # a point is lighter than the whole body


def test_pick_update_release_and_the_drag_spring(device):
    model = _model()
    drag = DragController(model, stiffness=500.0, damping=5.0, max_acceleration=20.0)
    q = torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device)
    origin = torch.tensor([0.225, 0.075, 1.0], dtype=torch.float64)
    hit = drag.pick(origin, torch.tensor([0.0, 0.0, -1.0]), q)
    assert hit is not None and drag.dragging
    assert hit.particle >= 0 and float((hit.world - hit.rest).norm()) < 1e-12  # at rest, x = X
    assert hit.distance == pytest.approx(float((hit.world - origin).norm()))
    # A new ray keeps the picked depth along the ray.
    new_origin = torch.tensor([0.5, 0.2, 1.0], dtype=torch.float64)
    direction = torch.tensor([0.1, 0.0, -1.0], dtype=torch.float64)
    target = drag.update(new_origin, direction)
    assert float((target - new_origin).norm()) == pytest.approx(hit.distance)
    (spring,) = drag.control_terms(q, dt=0.01)
    assert spring.stiffness == pytest.approx(500.0 + 5.0 / 0.01)
    # The spring force at the start of the step respects the acceleration clamp.
    x = drag.position(q)
    force = 500.0 * (clamp_target(target.to(x)[None], x[None], 500.0, drag.inverse_mass, 20.0)[0] - x)
    assert float(drag.inverse_mass[0] * force.norm()) <= 20.0 + 1e-9
    drag.release()
    assert not drag.dragging and drag.control_terms(q, 0.01) == []
    assert drag.pick(origin, torch.tensor([0.0, 1.0, 0.0]), q) is None  # a miss picks nothing
    with pytest.raises(RuntimeError, match="nothing is picked"):
        drag.update(target=(0.0, 0.0, 0.0))


def test_the_pick_surface_is_the_models_own_and_follows_q(device):
    """A pick surface built from the body's mesh alone (no renderer) is moved by q: a ray through the translated
    face hits the material point it carried there, and a ray where the face was at rest misses it."""
    model = _model()
    lo, hi = model.position.amin(0).cpu(), model.position.amax(0).cpu()
    z = float(hi[2])
    vertices = torch.tensor(
        [[lo[0], lo[1], z], [hi[0], lo[1], z], [hi[0], hi[1], z], [lo[0], hi[1], z]], dtype=torch.float64
    )
    surface = PickSurface(model, vertices, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    drag = DragController(model, surface=surface)
    shift = torch.tensor([0.0, 0.3, 0.02], dtype=torch.float64)
    q = model.translation(shift)
    rest = torch.tensor([0.5 * float(lo[0] + hi[0]), 0.5 * float(lo[1] + hi[1]), z], dtype=torch.float64)
    hit = drag.pick(rest + shift + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), (0.0, 0.0, -1.0), q)
    # float32 vertices and BVH: a few ulps of the 0.5 m coordinates
    assert hit is not None and hit.particle == -1
    assert torch.allclose(hit.rest, rest, atol=1e-5) and torch.allclose(hit.world, rest + shift, atol=1e-5)
    # At rest place the face is gone (0.3 m up, more than the bar's height): nothing is hit, not even a particle.
    assert drag.pick(rest + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), (0.0, 0.0, -1.0), q) is None
    with pytest.raises(ValueError, match="vertices \\[V, 3\\] and faces"):
        PickSurface(model, vertices[:, :2], torch.tensor([[0, 1, 2]]))


def test_drag_pulls_the_body_toward_the_target(device):
    model = _model()
    solver = SolverQGMLS(model, Material(young_modulus=2e4), SolverConfig(gravity=(0.0, 0.0, 0.0)))
    state = solver.rest_state()
    interaction = Interaction(DragController(model, stiffness=2e3, damping=20.0, max_acceleration=math.inf))
    start = interaction.drag.grab((0.375, 0.05, 0.05), state.q).world
    interaction.drag.update(target=start + torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64))
    for _ in range(5):
        solver.step(state, state, interaction.control(state.q, 0.02), 0.02)
    moved = interaction.drag.position(state.q).cpu() - start
    assert 0.02 < float(moved[1]) < 0.15  # toward the target, at most a spring's overshoot past it
    assert float(moved[1]) > 3.0 * float(moved[[0, 2]].abs().max())


def test_pins_hold_and_forces_push(device):
    model = _model()
    solver = SolverQGMLS(model, Material(young_modulus=2e4), SolverConfig(gravity=(0.0, -9.81, 0.0)))
    state = solver.rest_state()
    interaction = Interaction(DragController(model), pin_stiffness=1e5)
    assert interaction.pin_region((-1, -1, -1), (0.05, 1, 1), state.q) == 4
    interaction.add_force((0.375, 0.05, 0.05), (0.0, 0.0, 5.0))
    control = interaction.control(state.q, 0.02)
    assert len(control.springs) == 1 and len(control.forces) == 1
    for _ in range(5):
        solver.step(state, state, control, 0.02)
    pinned = interaction.pins[0]
    assert float((pinned.handle.positions(state.q) - pinned.target).norm(dim=1).max()) < 2e-3
    tip = model.handle(torch.tensor([[0.375, 0.05, 0.05]], dtype=torch.float64))
    assert float(tip.positions(state.q)[0, 2] - 0.05) > 1e-4  # pushed along +z
    with pytest.raises(ValueError, match="no particle lies in the pin box"):
        interaction.pin_region((5, 5, 5), (6, 6, 6), state.q)
    with pytest.raises(RuntimeError, match="click on the body first"):
        interaction.cut_through_picked((0, 1, 0))
    interaction.drag.grab((0.2, 0.05, 0.05), state.q)
    plane = interaction.cut_through_picked((0.0, 0.0, 2.0))
    assert plane.point == pytest.approx((0.2, 0.05, 0.05)) and plane.normal == pytest.approx((0.0, 0.0, 1.0))
    assert interaction.pin_picked(state.q) >= 1 and not interaction.drag.dragging


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"stiffness": 0.0}, "drag stiffness must be"), ({"damping": -1.0}, "drag damping must be"),
     ({"max_acceleration": float("nan")}, "drag max_acceleration must be"), ({"density": 0}, "drag density")],
)
def test_bad_drag_settings_are_refused_clearly(device, kwargs, message):
    with pytest.raises(ValueError, match=message):
        DragController(_model(), **kwargs)
