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
    QGMLSStepReport,
    SolverConfig,
    SolverQGMLS,
    SphereCollider,
)


def grid_particles(size, spacing):
    """Cell-centred lattice filling the box [0, size]: positions [P, 3] and volumes [P]."""
    axes = [torch.arange(0.5 * spacing, s, spacing, dtype=torch.float64) for s in size]
    position = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return position, torch.full((position.shape[0],), spacing**3, dtype=torch.float64)


_MODELS = {}


def box_model(device, kernels=16):
    key = (device, kernels)
    if key not in _MODELS:
        position, volume = grid_particles((0.4, 0.2, 0.2), 0.05)
        _MODELS[key] = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=kernels), device=device)
    return _MODELS[key]


def momentum(solver, qd):
    """Linear momentum Σ ∫ρ v dΩ = t_aᵀ M q̇ for the unit translations t_a (N·s)."""
    model = solver.model
    return torch.stack([(model.translation(torch.eye(3)[a]) * (solver.mass @ qd)).sum() for a in range(3)])


def test_free_fall_follows_the_discrete_implicit_euler_trajectory(device):
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=2e5), SolverConfig(newton_iterations=4))
    state, h, g = solver.rest_state(), 1e-2, -9.81
    rest_centre = model.particles.positions(state.q).mean(0)
    for n in range(1, 9):
        solver.step(state, state, QGMLSControl(), h)
        drop = (model.particles.positions(state.q).mean(0) - rest_centre)[1].item()
        assert drop == pytest.approx(g * h * h * n * (n + 1) / 2, rel=1e-6)
    F = model.particle_deformation_gradient(state.q)
    assert (F - torch.eye(3, dtype=F.dtype, device=F.device)).abs().max().item() < 1e-9  # stays at rest shape


def test_linear_momentum_is_conserved_without_external_force(device):
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(gravity=(0, 0, 0), newton_iterations=6))
    state = solver.rest_state()
    generator = torch.Generator().manual_seed(0)
    state.qd.copy_(0.3 * torch.randn(state.qd.shape, generator=generator, dtype=torch.float64))
    start = momentum(solver, state.qd)
    assert start.abs().max().item() > 1e-3
    for _ in range(10):
        report = solver.step(state, state, QGMLSControl(), 5e-3)
        assert math.isfinite(report.energy) and report.min_det > 0
    torch.testing.assert_close(momentum(solver, state.qd), start, rtol=1e-8, atol=1e-10)


def test_released_drag_decays_with_damping(device):
    model = box_model(backend.torch_device())
    config = SolverConfig(gravity=(0, 0, 0), rayleigh_alpha=8.0, rayleigh_beta=0.005, newton_iterations=5)
    solver = SolverQGMLS(model, Material(young_modulus=5e4), config)
    state = solver.rest_state()
    corner = model.handle(torch.tensor([[0.375, 0.175, 0.175]]))
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    pin_springs = PointTargets(pin, pin.rest.clone(), 1e5)
    lift = torch.tensor([[0.0, 0.1, 0.0]], dtype=torch.float64, device=corner.rest.device)
    drag = PointTargets(corner, corner.rest + lift, 2e3)
    for _ in range(10):
        solver.step(state, state, QGMLSControl(springs=[pin_springs, drag]), 1e-2)
    pulled = corner.positions(state.q)[0, 1].item() - corner.rest[0, 1].item()
    assert pulled > 0.02

    def mechanical_energy():
        kinetic = 0.5 * (state.qd * (solver.mass @ state.qd)).sum()
        elastic = solver.integrator.evaluate(state.q, gradient=False, hessian=False).energy
        return (kinetic + elastic + solver.potential.spring_terms([pin_springs], state.q, False)[0]).item()

    energies = [mechanical_energy()]
    for _ in range(30):
        solver.step(state, state, QGMLSControl(springs=[pin_springs]), 1e-2)
        energies.append(mechanical_energy())
    assert all(b <= a * (1 + 1e-9) for a, b in zip(energies, energies[1:], strict=False))  # dissipates every step
    assert energies[-1] < 0.4 * energies[0]


def test_floor_stops_a_falling_body(device):
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=1e5), SolverConfig(newton_iterations=6, rayleigh_alpha=5.0))
    state = solver.rest_state()
    floor = PlaneCollider(point=(0.0, -0.05, 0.0), normal=(0.0, 1.0, 0.0))
    for _ in range(60):
        report = solver.step(state, state, QGMLSControl(colliders=[floor]), 1e-2)
        assert report.min_det > 0
    lowest = model.particles.positions(state.q)[:, 1].min().item()
    assert -0.06 < lowest < -0.045  # resting on the floor up to the penalty's compliance
    particle_velocity = model.particles.positions(state.qd) - model.particles.rest  # J q̇
    assert particle_velocity.abs().max().item() < 0.05


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"young_modulus": 0.0}, "Young's modulus must be > 0"),
        ({"young_modulus": -5.0}, "Young's modulus must be > 0"),
        ({"poisson_ratio": 0.5}, "Poisson ratio must lie in"),
        ({"poisson_ratio": -1.0}, "Poisson ratio must lie in"),
        ({"density": float("nan")}, "finite"),
        ({"model": "rubber"}, "unknown material model 'rubber'; valid: neo_hookean"),
    ],
)
def test_bad_material_is_refused_clearly(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Material(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"kernel_count": 0}, "kernel_count must be a positive integer"),
        ({"kernel_count": 8, "ip_count": 4}, "must be >= kernel_count"),
        ({"order": "cubic"}, "unknown order 'cubic'"),
        ({"support_scale": float("nan")}, "support_scale must be a finite number > 1"),
        ({"user_kernels": ((0.0, float("nan"), 0.0),)}, "user_kernels must be finite"),
    ],
)
def test_bad_discretization_is_refused_clearly(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DiscretizationConfig(**kwargs)


def test_bad_solver_config_and_model_inputs(device):
    with pytest.raises(ValueError, match="finite"):
        SolverConfig(gravity=(0.0, float("nan"), 0.0))
    position, volume = grid_particles((0.1, 0.1, 0.1), 0.05)
    with pytest.raises(ValueError, match="exceeds the particle count"):
        QGMLSModel(position, volume, DiscretizationConfig(kernel_count=100))
    with pytest.raises(ValueError, match="no particles"):
        QGMLSModel(position[:0], volume[:0])
    position[0, 0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        QGMLSModel(position, volume, DiscretizationConfig(kernel_count=2))
    solver = SolverQGMLS(box_model(backend.torch_device()), Material())
    state = solver.rest_state()
    with pytest.raises(ValueError, match="dt must be"):
        solver.step(state, state, QGMLSControl(), 0.0)


def test_float32_hessian_products_take_the_float64_steps(device):
    """hessian_precision="float32" changes only the Newton matrix: ten momentum-conserving steps end where the
    float64 ones do, to the Newton tolerance (1e-8), and conserve momentum as tightly; an unknown precision is
    refused."""
    model = box_model(backend.torch_device())
    generator = torch.Generator().manual_seed(0)
    qd = 0.3 * torch.randn(model.shape_count, 3, generator=generator, dtype=torch.float64)
    ends = {}
    for precision in ("float64", "float32"):
        config = SolverConfig(gravity=(0, 0, 0), newton_iterations=6, hessian_precision=precision)
        solver = SolverQGMLS(model, Material(young_modulus=5e4), config)
        assert solver.step_integrator.product_dtype == config.hessian_product_dtype(model.device)
        assert solver.integrator.product_dtype == torch.float64  # the exact one, for static solves and checks
        state = solver.rest_state()
        state.qd.copy_(qd)
        start = momentum(solver, state.qd)
        for _ in range(10):
            report = solver.step(state, state, QGMLSControl(), 5e-3)
            assert math.isfinite(report.energy) and report.min_det > 0
        torch.testing.assert_close(momentum(solver, state.qd), start, rtol=1e-8, atol=1e-10)
        ends[precision] = state.q
    torch.testing.assert_close(ends["float32"], ends["float64"], rtol=1e-6, atol=SolverConfig().newton_tolerance)
    with pytest.raises(ValueError, match="hessian_precision must be one of"):
        SolverConfig(hessian_precision="float16")


def test_float32_products_fall_back_to_float64_where_the_newton_matrix_breaks(device):
    """A near-massless body over a long step: its Newton matrix is its stiffness, whose rigid modes float32 products'
    round-off makes indefinite, so the factorisation fails; the step assembles that matrix again with float64 products
    and ends where the float64 solver's step does."""
    model = box_model(backend.torch_device())
    generator = torch.Generator().manual_seed(0)
    qd = (0.3 * torch.randn(model.shape_count, 3, generator=generator, dtype=torch.float64)).to(model.device)
    ends = {}
    for precision in ("float64", "float32"):
        config = SolverConfig(gravity=(0, 0, 0), hessian_precision=precision, device_loop=False)
        solver = SolverQGMLS(model, Material(young_modulus=5e4, density=1e-3), config)
        state = solver.rest_state()
        state.qd.copy_(qd)
        report = solver.step(state, state, QGMLSControl(), 1.0)
        assert math.isfinite(report.energy) and report.min_det > 0
        ends[precision] = state.q
    rest = torch.zeros_like(qd)  # the first Newton matrix (at q_n = 0; dt = 1 s), with the step's float32 products:
    newton_matrix = solver.step_integrator.evaluate(rest).hessian + solver.mass_flat
    assert torch.linalg.cholesky_ex(newton_matrix).info != 0  # not positive definite: the fallback was needed
    if ends["float64"].is_cuda:  # CUDA's atomics sum the gradient in no fixed order
        torch.testing.assert_close(ends["float32"], ends["float64"], rtol=1e-9, atol=1e-12)
    else:
        assert torch.equal(ends["float32"], ends["float64"])


def test_static_solve_assembles_in_float64_when_steps_use_float32(device):
    """solve_static has no mass term to keep its Newton matrix away from singular: it assembles with float64 block
    products whatever the steps use, so its equilibrium is the float64 solver's."""
    model = box_model(backend.torch_device())
    pin = model.handle(model.position[model.position[:, 0] < model.position[:, 0].min() + 0.03])
    control = QGMLSControl(springs=[PointTargets(pin, pin.rest.clone(), 1e6)])
    ends = {}
    for precision in ("float64", "float32"):
        solver = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(hessian_precision=precision))
        ends[precision], _ = solver.solve_static(control, iterations=20)
    assert solver.step_integrator.product_dtype == torch.float32 and solver.integrator.product_dtype == torch.float64
    if ends["float64"].is_cuda:  # the same arithmetic, but CUDA's atomics sum the gradient in no fixed order
        torch.testing.assert_close(ends["float32"], ends["float64"], rtol=1e-9, atol=1e-12)
    else:
        assert torch.equal(ends["float32"], ends["float64"])


def test_modified_newton_reaches_the_same_step(device):
    """Reusing the first Cholesky factor (hessian_updates=1) converges to Newton's solution."""
    model = box_model(backend.torch_device())
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    control = QGMLSControl(springs=[PointTargets(pin, pin.rest.clone(), 1e5)])
    results = []
    for config in (SolverConfig(newton_iterations=12, newton_tolerance=1e-12),
                   SolverConfig(newton_iterations=60, newton_tolerance=1e-12, hessian_updates=1)):
        solver = SolverQGMLS(model, Material(young_modulus=5e4), config)
        state = solver.rest_state()
        for _ in range(3):
            report = solver.step(state, state, control, 1e-2)
        assert report.last_update < 1e-10
        results.append(model.particles.positions(state.q))
    torch.testing.assert_close(results[1], results[0], rtol=0, atol=1e-8)


def test_contact_hessian_is_the_same_by_product_and_by_blocks(device):
    """Both assemblies of Σ k Jᵀ n nᵀ J, the one product over shape rows and the per-point blocks, agree."""
    model = box_model(device, kernels=6)
    solver = SolverQGMLS(model, Material())
    particles = model.particles
    generator = torch.Generator().manual_seed(1)
    stiffness = torch.rand(len(particles.index), generator=generator, dtype=torch.float64).to(model.device)
    normal = torch.nn.functional.normalize(
        torch.randn(len(particles.index), 3, generator=generator, dtype=torch.float64), dim=1
    ).to(model.device)
    potential = solver.potential
    by_product = potential.normal_point_hessian(particles.index, particles.value, stiffness, normal, by_blocks=False)
    by_blocks = potential.normal_point_hessian(particles.index, particles.value, stiffness, normal, by_blocks=True)
    torch.testing.assert_close(by_product, by_blocks, rtol=1e-12, atol=1e-12 * float(by_blocks.abs().max()))


def _device_loop_pair(config, model):
    """The same solver twice, one on the host loop and one on the device loop (uncaptured on the CPU).

    Both form the Hessian's block products in float64: CUDA's default float32 products are summed by atomics in an
    order that changes from run to run, so two runs of the *same* loop already differ by ε₃₂ times the Newton
    matrix's condition number (1e-10 m in q here), which says nothing about the loops being the same."""
    config = {"hessian_precision": "float64", **config}
    host = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(**config, device_loop=False))
    device = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(**config, device_loop=True))
    return host, device


def _assert_same_step(host_report, device_report, host_state, device_state):
    torch.testing.assert_close(device_state.q, host_state.q, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(device_state.qd, host_state.qd, rtol=1e-10, atol=1e-10)
    assert device_report.iterations == host_report.iterations
    assert device_report.line_search_halvings == host_report.line_search_halvings
    assert device_report.converged == host_report.converged
    assert device_report.line_search_failure == host_report.line_search_failure
    assert device_report.energy == pytest.approx(host_report.energy, rel=1e-10)
    assert device_report.min_det == pytest.approx(host_report.min_det, rel=1e-10)


@pytest.mark.parametrize("config", [
    {"newton_iterations": 3, "newton_tolerance": 0.0, "rayleigh_alpha": 1.0},
    {"newton_iterations": 5, "newton_tolerance": 1e-7, "rayleigh_beta": 0.01},  # converges early: masked iterations
    {"newton_iterations": 4, "newton_tolerance": 1e-9, "hessian_updates": 1},
])
def test_device_loop_takes_the_host_loops_step(device, config):
    """Springs that move, a point force, a floor the body is pressed into and a sphere it falls on: the loop with no
    host read gives the host loop's state and report, step after step, and re-uses one graph for them all."""
    model = box_model(backend.torch_device())
    host, device_solver = _device_loop_pair(config, model)
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    tip = model.handle(model.position[model.position[:, 0].argmax()][None])
    states, redone = [host.rest_state(), device_solver.rest_state()], 0
    for i in range(4):
        lift = torch.tensor([[0.0, 0.02 * (i + 1), 0.0]], dtype=torch.float64, device=model.device)
        control = QGMLSControl(
            springs=[PointTargets(pin, pin.rest.clone(), 1e5), PointTargets(tip, tip.rest + lift, 2e3 * (i + 1))],
            forces=[PointForces(tip, torch.tensor([[0.0, 0.0, 3.0 * i]], dtype=torch.float64, device=model.device))],
            colliders=[PlaneCollider(point=(0.0, 0.01 * i, 0.0)), SphereCollider((0.35, -0.05, 0.1), 0.07)],
        )
        reports = [solver.step(state, state, control, 1e-2) for solver, state in zip((host, device_solver), states,
                                                                                      strict=True)]
        assert not reports[0].device_loop
        if reports[0].line_search_halvings == 0:  # more halvings than the device loop tries go to the host loop
            assert reports[1].device_loop
        _assert_same_step(*reports, *states)
        redone += not reports[1].device_loop
    assert device_solver.device_loop_redos == redone < 4
    assert len(device_solver.device_loops) == 1  # new targets, stiffnesses, forces and placements: same graph


def test_device_loop_hands_steps_it_cannot_take_to_the_host_loop(device):
    """A step whose line search needs more halvings than the device loop tries, and one that fails (a force no body
    can bear inverts every trial), are redone by the host loop: the same state and the same failure report."""
    model = box_model(backend.torch_device())
    tip = model.handle(model.position[model.position[:, 0].argmax()][None])
    config = {"newton_iterations": 2, "line_search_batch": 1}
    for force in (2e3, 1e20):
        host, device_solver = _device_loop_pair(config, model)
        states = [host.rest_state(), device_solver.rest_state()]
        push = torch.tensor([[0.0, -force, 0.0]], dtype=torch.float64, device=model.device)
        control = QGMLSControl(forces=[PointForces(tip, push)])
        reports = [solver.step(state, state, control, 1e-2) for solver, state in zip((host, device_solver), states,
                                                                                      strict=True)]
        assert reports[0].line_search_halvings > 0
        assert device_solver.device_loop_redos == 1 and not reports[1].device_loop
        _assert_same_step(*reports, *states)
    assert reports[1].line_search_failure == "inversion"


def test_device_loops_follow_the_controls_and_the_material(device):
    """A new set of material points (a drag starts) takes a new loop, the old one is kept for when it ends; a new
    material drops them all (they hold the old one)."""
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(), SolverConfig(device_loop=True))
    state = solver.rest_state()
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    tip = model.handle(model.position[model.position[:, 0].argmax()][None])
    pins = PointTargets(pin, pin.rest.clone(), 1e5)
    for springs in ([pins], [pins, PointTargets(tip, tip.rest.clone(), 1e3)], [pins]):
        solver.step(state, state, QGMLSControl(springs=springs), 1e-2)
    assert len(solver.device_loops) == 2
    solver.set_material(Material(young_modulus=2e5))
    assert len(solver.device_loops) == 0
    report = solver.step(state, state, QGMLSControl(springs=[pins]), 1e-2)
    assert report.device_loop and report.iterations >= 1


def test_kept_factor_reaches_newtons_steps_and_is_renewed_when_it_stops_serving(device):
    """factor_reuse: along a moving drag, steps that reuse an earlier factor converge to the steps of Newton with its
    own factor each step, to the tolerance; a step that does not converge with the kept factor is taken again with
    its own, which is kept from then on."""
    model = box_model(backend.torch_device())
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    tip = model.handle(model.position[model.position[:, 0].argmax()][None])
    common = {"newton_iterations": 12, "newton_tolerance": 1e-9, "rayleigh_alpha": 1.0}
    newton = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(**common, device_loop=False))
    reusing = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(**common, device_loop=True, factor_reuse=3))
    states, reused = [newton.rest_state(), reusing.rest_state()], []
    for i in range(8):
        lift = torch.tensor([[0.0, 0.01 * (i + 1), 0.0]], dtype=torch.float64, device=model.device)
        springs = [PointTargets(pin, pin.rest.clone(), 1e5), PointTargets(tip, tip.rest + lift, 5e3)]
        control = QGMLSControl(springs=springs)
        reports = [solver.step(state, state, control, 1e-2) for solver, state in zip((newton, reusing), states,
                                                                                      strict=True)]
        assert reports[0].converged and reports[1].converged
        torch.testing.assert_close(states[1].q, states[0].q, rtol=0, atol=1e-6)
        reused.append(reports[1].factor_reused)
    assert reused[0] is False and sum(reused) >= 3  # the first step makes the factor; later ones reuse it
    assert reusing.factor_refreshes >= 1  # at least one step stopped converging with the kept factor
    assert all(not reused[i] for i in range(len(reused)) if i >= 3 and all(reused[i - 3:i]))  # at most 3 reuses
    with pytest.raises(ValueError, match="factor_reuse needs rayleigh_beta = 0"):
        SolverConfig(factor_reuse=2, rayleigh_beta=0.1)


def test_a_step_report_times_the_whole_step_either_way():
    host = QGMLSStepReport(time_assembly=0.25, time_solve=0.5, time_line_search=0.0625, time_other=0.125)
    assert host.time_step == 0.9375, "the host loop's phases together"
    assert host.timed
    untimed = QGMLSStepReport(device_loop=True, time_device_loop=0.3)
    assert untimed.time_step == 0.3 and not untimed.timed, "the device loop as a whole"


@pytest.mark.parametrize("device_loop", [False, True], ids=["host loop", "device loop"])
def test_a_pin_held_over_many_steps_costs_one_product_once(device, device_loop):
    """The springs' Hessian k JᵀJ is formed once per handle object: a pin held and a drag moving its target over many
    steps cost one JᵀJ each; a new handle (another set of points) costs one more."""
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(device_loop=device_loop))
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    tip = model.handle(model.position[model.position[:, 0].argmax()][None])
    state = solver.rest_state()
    for i in range(5):
        lift = torch.tensor([[0.0, 0.01 * i, 0.0]], dtype=torch.float64, device=model.device)
        springs = [PointTargets(pin, pin.rest.clone(), 1e5), PointTargets(tip, tip.rest + lift, 1e3 * (i + 1))]
        report = solver.step(state, state, QGMLSControl(springs=springs), 1e-2)
        assert report.device_loop == device_loop
    assert solver.potential.jtj_products == 2
    again = model.handle(model.position[model.position[:, 0] < 0.05])  # the same points, another handle
    solver.step(state, state, QGMLSControl(springs=[PointTargets(again, again.rest.clone(), 1e5)]), 1e-2)
    assert solver.potential.jtj_products == 3
    assert len(solver.device_loops) == (2 if device_loop else 0)


def test_a_timed_device_loop_step_reports_its_phases_and_the_same_step(device):
    """``timed=True``: the device loop runs uncaptured with its phases timed; each phase takes time, together no more
    than the step's wall time, and the step is the untimed one's: to the bit on the CPU; on CUDA, where the captured
    graph and the uncaptured launches sum their atomics in other orders, both are Newton iterates converged to the
    tolerance τ (last update below τ, quadratic convergence), so they lie within 2τ of each other at the integrator
    points. Untimed steps report no phases."""
    model = box_model(backend.torch_device())
    tolerance = 1e-7
    config = SolverConfig(device_loop=True, newton_iterations=8, newton_tolerance=tolerance, rayleigh_alpha=1.0)
    solvers = [SolverQGMLS(model, Material(young_modulus=5e4), config) for _ in range(2)]
    states = [solver.rest_state() for solver in solvers]
    pin = model.handle(model.position[model.position[:, 0] < 0.05])
    control = QGMLSControl(springs=[PointTargets(pin, pin.rest.clone(), 1e5)], colliders=[PlaneCollider()])
    for _ in range(3):
        states[1].copy_(states[0])  # both steps start alike (on CUDA the last ones ended within 2τ, not equal)
        untimed, timed = (solver.step(state, state, control, 1e-2, timed=timed)
                          for solver, state, timed in zip(solvers, states, (False, True), strict=True))
        assert untimed.device_loop and timed.device_loop
        if device == "cpu":
            assert torch.equal(states[1].q, states[0].q) and torch.equal(states[1].qd, states[0].qd)
            assert _same_outcome(untimed, timed)
        else:
            assert untimed.converged and timed.converged
            assert solvers[0].potential.displacement(states[1].q - states[0].q) <= 2 * tolerance
        phases = (timed.time_assembly, timed.time_solve, timed.time_line_search, timed.time_other)
        assert all(phase > 0 for phase in phases) and timed.timed
        assert sum(phases) <= timed.time_device_loop == timed.time_step
        assert (untimed.time_assembly, untimed.time_solve, untimed.time_line_search, untimed.time_other) == (0,) * 4
        assert not untimed.timed and untimed.time_device_loop > 0


def test_a_host_loop_step_times_its_line_search_apart(device):
    model = box_model(backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=5e4), SolverConfig(device_loop=False))
    state = solver.rest_state()
    report = solver.step(state, state, QGMLSControl(colliders=[PlaneCollider()]), 1e-2)
    assert min(report.time_assembly, report.time_solve, report.time_line_search, report.time_other) > 0


def _same_outcome(a: QGMLSStepReport, b: QGMLSStepReport) -> bool:
    return all(getattr(a, name) == getattr(b, name) for name in (
        "iterations", "energy", "last_update", "min_det", "line_search_halvings", "converged", "line_search_failure",
        "device_loop", "factor_reused"))
