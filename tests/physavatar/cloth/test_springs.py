"""Springs in a garment step (a mouse drag, a pin): a term ``½ k ‖x_i − t‖²`` of the incremental potential."""

import pytest
import torch

from kernels import backend
from physavatar.cloth import ClothConfig, ClothControl, SolverCloth
from physavatar.shapes import grid_sheet

F64 = torch.float64
DT = 0.04


def _sheet():
    """A 5 × 5 sheet of 5 cm cells in the xy plane hanging from its top row, no body. (A pull out of a flat sheet's
    plane meets its degenerate bending at rest, where Newton takes many iterations to a tight tolerance: the tests
    pull within the plane.)"""
    x, faces = grid_sheet(5, 5, 0.05)
    config = ClothConfig(newton_tolerance=1e-10, max_newton_iterations=50, friction=0.0)
    solver = SolverCloth(x, faces, config, torch.zeros(0, 3, dtype=torch.int32))
    top = (x[:, 1] == x[:, 1].max()).nonzero().squeeze(1)
    return x, solver, top


def _control(x, top, springs=None):
    device = backend.torch_device()
    empty = torch.zeros(0, 3, dtype=F64, device=device)
    index, target = top.to(device), x[top].to(device, F64)
    if springs is None:
        return ClothControl(empty, empty, index, target)
    spring_index, spring_target, stiffness = (t.to(device) for t in springs)
    return ClothControl(empty, empty, index, target, spring_index, spring_target, stiffness)


def test_a_step_with_a_spring_is_stationary_for_the_potential_with_its_term(device):
    """The step's end minimises ``E + Δt² ½ k ‖x_i − t‖²``: on the free vertices the gradient of ``E`` (inertia,
    membrane, bending) balances the spring's ``−Δt² k (x_i − t)`` at its vertex and is zero elsewhere. At a Newton
    tolerance of 1e-10 m/s the last step moved no vertex by more than 4e-12 m, so the residual is that times the
    Hessian's norm (membrane: Δt² E h ≈ 0.4 N/m, inertia: a few mg): well below 1e-6 of the spring force (Δt² k
    times a pull of centimetres, 5e-5 N·s²)."""
    x, solver, top = _sheet()
    corner = int(((x[:, 1] == x[:, 1].min()) & (x[:, 0] == x[:, 0].max())).nonzero()[0])
    target = (x[corner] + torch.tensor([0.05, -0.02, 0.0], dtype=F64))[None]  # in the sheet's plane
    springs = (torch.tensor([corner]), target, torch.tensor([1.0], dtype=F64))
    control = _control(x, top, springs)
    mass = solver.potential.mass.clone()
    state_in, state_out = solver.initial_state(), solver.initial_state()
    report = solver.step(state_in, state_out, control, DT)
    assert report.converged
    assert torch.equal(solver.potential.mass, mass), "the step left the spring in the masses"
    plain = _control(x, top)
    linear = solver.linearise_step(state_in, state_out, plain, DT)
    residual = sum(linear.parts[name] for name in ("inertia", "membrane", "bending"))[linear.free].cpu()
    spring_force = torch.zeros_like(state_out.x).cpu()
    spring_force[corner] = -DT * DT * 1.0 * (state_out.x[corner].cpu() - target[0])
    expected = spring_force[linear.free.cpu()]
    scale = float(spring_force.abs().max())
    assert scale > 1e-5, "the spring barely pulled: the test would prove nothing"
    assert float((residual - expected).abs().max()) < 1e-6 * scale
    moved = state_out.x[corner].cpu() - x[corner]
    assert float(moved[0]) > 0.0, "the corner did not move toward the target"


def test_a_spring_on_a_boundary_vertex_changes_nothing(device):
    x, solver, top = _sheet()
    runs = []
    for springs in (None, (top[:1], x[top[:1]] + 0.1, torch.tensor([50.0], dtype=F64))):
        state_in, state_out = solver.initial_state(), solver.initial_state()
        solver.step(state_in, state_out, _control(x, top, springs), DT)
        runs.append(state_out.x.cpu())
    if backend.torch_device().type == "cpu":
        assert torch.equal(runs[0], runs[1])  # the same arithmetic in the same order
    else:
        # a GPU's sums run in its atomics' order, so the two runs' iterates differ in rounding; each run ends within
        # its last Newton step (below tolerance · Δt) of the step's exact minimiser, which the spring does not move
        bound = 2.0 * solver.config.newton_tolerance * DT
        assert float((runs[0] - runs[1]).abs().max()) <= bound


def test_malformed_springs_are_refused_naming_the_fix(device):
    x, solver, top = _sheet()
    state = solver.initial_state()
    one = torch.tensor([3])
    cases = [
        ((one, x[one], None), "go together"),
        ((one, x[:2], torch.ones(1, dtype=F64)), "spring_target \\[S, 3\\]"),
        ((torch.tensor([10_000]), x[one], torch.ones(1, dtype=F64)), "index garment vertices"),
        ((one, x[one] * float("nan"), torch.ones(1, dtype=F64)), "NaN"),
        ((one, x[one], -torch.ones(1, dtype=F64)), "positive"),
    ]
    for (index, target, stiffness), message in cases:
        device = backend.torch_device()
        control = _control(x, top)
        control.spring_index, control.spring_target = index.to(device), target.to(device)
        control.spring_stiffness = None if stiffness is None else stiffness.to(device)
        with pytest.raises(ValueError, match=message):
            solver.step(state, solver.initial_state(), control, DT)
