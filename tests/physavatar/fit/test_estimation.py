"""Garment physics estimation (PhysAvatar §3.2, Eq. 6–7, Algorithm 1): identifiability, step sensitivities against
finite differences, recovery of the material from exact meshes, and bad input."""

import dataclasses
import math

import pytest
import torch

from physavatar.cloth import ClothControl, ClothState, SolverCloth
from physavatar.fit.estimation import (
    FD_STEPS,
    SYNTHETIC_FABRIC,
    EstimationProblem,
    FabricParameters,
    estimate_analytic,
    estimate_finite_differences,
    rollout,
    sim_loss,
)
from physavatar.shapes import grid_sheet, icosphere
from physavatar.simulate import SimulationResult

F64 = torch.float64
FPS = 25.0
ALL = ("density", "kappa_s", "kappa_b")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors run faster on one thread than on cores shared with other processes."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def swing(frames: int, newton_tolerance: float | None = None, n: int = 8, length: float = 0.4) -> EstimationProblem:
    """A ``length``-square sheet of the synthetic fabric hanging from its top edge, which swings out of the sheet's
    plane (8 cm at 1.5 Hz) and along it (3 cm at 1 Hz): gravity stretches it, the swing bends it. The reference is
    a placeholder (the sheet at rest); tests replace it. Comparisons with finite differences of rollouts tighten
    the Newton tolerance: the differences must resolve 1e-4 relative parameter changes."""
    x, faces = grid_sheet(n, n, length / (n - 1))
    top = (x[:, 1] == x[:, 1].max()).nonzero().squeeze(1)
    t = torch.arange(frames, dtype=F64) / FPS
    targets = x[top][None].repeat(frames, 1, 1)
    targets[:, :, 2] += 0.08 * torch.sin(2.0 * math.pi * 1.5 * t)[:, None]
    targets[:, :, 0] += 0.03 * torch.sin(2.0 * math.pi * 1.0 * t)[:, None]
    no_body = torch.zeros(frames, 0, 3, dtype=F64)
    config = SYNTHETIC_FABRIC
    if newton_tolerance is not None:
        config = dataclasses.replace(config, newton_tolerance=newton_tolerance)
    return EstimationProblem(
        x,
        faces,
        x[None].repeat(frames, 1, 1),
        no_body,
        torch.zeros(0, 3, dtype=torch.int64),
        top,
        targets,
        FPS,
        config,
    )


def _push(frames: int, friction: float, newton_tolerance: float) -> EstimationProblem:
    """The same sheet with its top edge held still, pushed out of its plane by a sphere moving at 0.3 m/s."""
    n, length, radius = 8, 0.4, 0.08
    x, faces = grid_sheet(n, n, length / (n - 1))
    top = (x[:, 1] == x[:, 1].max()).nonzero().squeeze(1)
    sphere, sphere_faces = icosphere(1, radius)
    t = torch.arange(frames, dtype=F64) / FPS
    body = sphere[None].repeat(frames, 1, 1)
    body[:, :, 0] += 0.2
    body[:, :, 1] += 0.15
    body[:, :, 2] += -radius - 0.01 + 0.3 * t[:, None]  # 1 cm from the sheet at the start
    config = dataclasses.replace(SYNTHETIC_FABRIC, friction=friction, newton_tolerance=newton_tolerance)
    return EstimationProblem(
        x, faces, x[None].repeat(frames, 1, 1), body, sphere_faces, top, x[top][None].repeat(frames, 1, 1), FPS, config
    )


def _relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.norm(a - b) / torch.linalg.norm(b))


def test_scaling_density_and_stiffnesses_together_leaves_the_motion_unchanged(device):
    """Only κ_s/ρ and κ_b/ρ are identifiable: (ρ, κ_s, κ_b) and (2ρ, 2κ_s, 2κ_b) give the same rollout."""
    problem = swing(12)
    base = FabricParameters(300.0, 1.5, 1.2)
    frames = rollout(problem, base, device=device).frames
    doubled = rollout(problem, FabricParameters(600.0, 3.0, 2.4), device=device).frames
    assert float((frames - problem.reference[0]).norm(dim=2).max()) > 0.05  # the sheet really swings
    assert float((doubled - frames).abs().max()) < 1e-8
    stiffer = rollout(problem, FabricParameters(300.0, 3.0, 1.2), device=device).frames
    assert float((stiffer - frames).norm(dim=2).max()) > 1e-3  # while κ_s alone changes the motion by mm


def test_sensitivities_match_central_differences(device):
    """∂x/∂θ carried through the implicit steps equals central differences of whole rollouts, for ρ, κ_s, κ_b."""
    problem = swing(12, newton_tolerance=1e-7)
    params = FabricParameters(320.0, 1.0, 1.0)
    frames, sens = rollout(problem, params, sensitivities=True, parameters=ALL, device=device)
    assert sens.shape == (*frames.shape, 3)
    assert float(sens[0].abs().max()) == 0.0
    for j, name in enumerate(ALL):
        h = 1e-4 * getattr(params, name)
        plus = rollout(problem, dataclasses.replace(params, **{name: getattr(params, name) + h}), device=device)
        minus = rollout(problem, dataclasses.replace(params, **{name: getattr(params, name) - h}), device=device)
        central = (plus.frames - minus.frames) / (2.0 * h)
        assert float(central.norm()) * getattr(params, name) > 0.01  # a relative change moves the sheet by cm
        assert _relative_error(sens[..., j], central) < 1e-4, name  # measured: 4e-7–9e-7
    # and Euler's relation of the scale invariance: ρ ∂x/∂ρ + κ_s ∂x/∂κ_s + κ_b ∂x/∂κ_b = 0
    scaled = sens[..., 0] * params.density + sens[..., 1] * params.kappa_s + sens[..., 2] * params.kappa_b
    assert float(scaled.norm()) < 1e-4 * float(sens[..., 1].norm() * params.kappa_s)


def test_sensitivities_with_body_contact_match_central_differences(device):
    """With a sphere pushing the sheet, barrier terms enter the Hessian and the density derivative; without
    friction the sensitivities match differences closely, with IPC's lagged friction to within 2 %."""
    params = FabricParameters(320.0, 1.0, 1.0)
    direction = torch.tensor([0.3 * params.density, -0.5 * params.kappa_s, 0.8 * params.kappa_b], dtype=F64)
    h = 1e-4
    for friction, tolerance in ((0.0, 1e-4), (0.2, 2e-2)):  # measured: 4e-6 and 2.6e-3
        problem = _push(7, friction, newton_tolerance=1e-7)
        frames, sens = rollout(problem, params, sensitivities=True, parameters=ALL, device=device)
        assert float(frames[-1, :, 2].max()) > 0.04  # the sphere pushed the sheet 4 cm out of its plane
        along = sens @ direction
        values = torch.tensor(params.values(ALL), dtype=F64)
        plus = rollout(problem, params.with_values(ALL, (values + h * direction).tolist()), device=device)
        minus = rollout(problem, params.with_values(ALL, (values - h * direction).tolist()), device=device)
        assert _relative_error(along, (plus.frames - minus.frames) / (2.0 * h)) < tolerance, friction


def test_sensitivity_step_checks_its_inputs(device):
    problem = swing(3)
    solver = SolverCloth(problem.rest_vertices, problem.faces, SYNTHETIC_FABRIC, problem.body_faces)
    state = solver.initial_state()
    out = ClothState(state.x.clone(), state.v.clone())
    empty = torch.zeros(0, 3, dtype=F64, device=state.x.device)
    control = ClothControl(empty, empty, problem.boundary_index.to(state.x.device), state.x[problem.boundary_index])
    solver.step(state, out, control, 1.0 / FPS)
    s = torch.zeros(state.x.shape[0], 3, 2, dtype=F64)
    with pytest.raises(ValueError, match="s_x must have shape"):
        solver.sensitivity_step(state, out, control, 1.0 / FPS, s[:, :, :1], s)
    with pytest.raises(ValueError, match="distinct names"):
        solver.sensitivity_step(state, out, control, 1.0 / FPS, s, s, ("kappa_s", "young"))
    s_x, s_v = solver.sensitivity_step(state, out, control, 1.0 / FPS, s, s)
    assert s_x.shape == s.shape and float(s_x[problem.boundary_index].abs().max()) == 0.0  # Dirichlet: fixed


def test_levenberg_marquardt_recovers_the_ratios_from_a_two_fold_error(device):
    """From exact meshes, starting 2× off in both stiffnesses, the analytic method recovers κ_s/ρ and κ_b/ρ."""
    problem = swing(12)
    truth = FabricParameters(320.0, 1.5, 0.8)
    problem = dataclasses.replace(problem, reference=rollout(problem, truth, device=device).frames)
    start = FabricParameters(320.0, 3.0, 0.4)
    seen = []
    result = estimate_analytic(problem, start, device=device, progress=lambda i, r: seen.append((i, r.loss)))
    assert result.method == "levenberg_marquardt" and result.converged
    assert result.iterations <= 8 and result.simulations <= 12
    for got, expected in zip(result.ratios, truth.ratios, strict=True):
        assert got == pytest.approx(expected, rel=0.05)
    assert result.final.density == truth.density  # ρ is held fixed by default
    assert result.loss[-1] < 1e-6 * result.loss[0]
    assert len(result.history) == len(result.loss) == result.iterations + 1 == len(seen) + 1
    assert [i for i, _ in seen] == list(range(1, result.iterations + 1))
    assert result.loss[-1] == pytest.approx(sim_loss(rollout(problem, result.final).frames, problem.reference))


def test_finite_difference_adam_lowers_the_loss(device):
    """Algorithm 1 (forward differences, Adam): a few iterations already move toward the truth and lower Eq. 6."""
    problem = swing(10)
    truth = FabricParameters(320.0, 1.0, 1.0)
    problem = dataclasses.replace(problem, reference=rollout(problem, truth, device=device).frames)
    start = FabricParameters(320.0, 2.0, 0.5)
    result = estimate_finite_differences(
        problem, start, iterations=3, learning_rate=0.25, device=device, progress=False
    )
    assert result.simulations == 1 + 3 * 3  # a base and a probe per parameter each iteration, and the last one
    assert len(result.history) == 4 and len(result.wall_time) == 3
    assert result.loss[-1] < 0.3 * result.loss[0]
    assert result.final.kappa_s < start.kappa_s and result.final.kappa_b > start.kappa_b
    # the analytic gradient at the start agrees in sign and roughly in size with the forward differences
    frames, sens = rollout(problem, start, sensitivities=True, device=device)
    residual = (frames - problem.reference)[1:].reshape(-1)
    gradient = 2.0 * sens[1:].reshape(-1, 2).T @ residual
    base = sim_loss(frames, problem.reference)
    for j, name in enumerate(("kappa_s", "kappa_b")):
        probe = dataclasses.replace(start, **{name: getattr(start, name) + FD_STEPS[name]})
        forward = (sim_loss(rollout(problem, probe).frames, problem.reference) - base) / FD_STEPS[name]
        assert float(gradient[j]) == pytest.approx(forward, rel=0.3), name


def test_problem_from_a_simulation_result(device):
    problem = swing(4)
    frames = rollout(problem, FabricParameters.from_config(SYNTHETIC_FABRIC), device=device).frames
    result = SimulationResult(
        frames, problem.body_frames, problem.faces, problem.body_faces, problem.boundary_index, FPS, [], []
    )
    built = EstimationProblem.from_simulation(result, SYNTHETIC_FABRIC)
    assert torch.equal(built.boundary_targets, frames[:, problem.boundary_index])
    assert torch.equal(built.rest_vertices, frames[0]) and built.frames == 4 and built.dt == pytest.approx(0.04)


def test_bad_input_raises_clear_errors():
    problem = swing(6)
    fields = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}

    def build(**changes):
        return EstimationProblem(**{**fields, **changes})

    with pytest.raises(ValueError, match="body_frames holds 5 frames but reference 6"):
        build(body_frames=problem.body_frames[:5])
    with pytest.raises(ValueError, match="boundary_targets holds 7 frames but reference 6"):
        build(boundary_targets=torch.cat([problem.boundary_targets, problem.boundary_targets[:1]]))
    with pytest.raises(ValueError, match="topology change.*63 vertices but the rest mesh 64"):
        build(reference=problem.reference[:, :63])
    with pytest.raises(ValueError, match="topology change.*97 faces, the rest mesh 98"):
        build(reference_faces=problem.faces[:97])
    with pytest.raises(ValueError, match="different indices"):
        build(reference_faces=problem.faces.flip(1))
    with pytest.raises(ValueError, match="at least 2 frames"):
        build(
            reference=problem.reference[:1],
            body_frames=problem.body_frames[:1],
            boundary_targets=problem.boundary_targets[:1],
        )
    with pytest.raises(ValueError, match="fps"):
        build(fps=0.0)
    with pytest.raises(ValueError, match="boundary_index"):
        build(boundary_index=problem.boundary_index + 100)
    for values, name in (
        ((100.0, 1.0, 1.0), "density"),
        ((320.0, 10.0, 1.0), "kappa_s"),
        ((320.0, 1.0, 0.05), "kappa_b"),
    ):
        with pytest.raises(ValueError, match=f"{name} .* outside the paper's range"):
            FabricParameters(*values)
    start = FabricParameters(320.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="distinct names"):
        estimate_finite_differences(problem, start, parameters=("kappa_s", "bend"), progress=False)
    with pytest.raises(ValueError, match="method"):
        estimate_analytic(problem, start, method="newton", progress=False)
    with pytest.raises(ValueError, match="iterations"):
        estimate_finite_differences(problem, start, iterations=0, progress=False)
    with pytest.raises(ValueError, match="one shape"):
        sim_loss(problem.reference[:3], problem.reference)
