"""Garment simulator (PhysAvatar §3.2, Appendix A.3): closed-form statics, contact safety, determinism, bad input."""

import pytest
import torch

from kernels import backend, cudss
from physavatar.cloth import PHASES, ClothConfig, ClothControl, ClothState, SolverCloth, bending_stiffness
from physavatar.cloth.newton_loop import NewtonLoop
from physavatar.shapes import grid_sheet, icosphere

F64 = torch.float64


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors run faster on one thread than on cores shared with other processes."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _on_device(*tensors):
    return [t.to(backend.torch_device()) for t in tensors]


def _pinned(x: torch.Tensor, index: torch.Tensor, body: torch.Tensor | None = None) -> ClothControl:
    body = torch.zeros(0, 3, dtype=F64) if body is None else body
    body, index, target = _on_device(body, index, x[index])
    return ClothControl(body, body, index, target)


def _static_solve(solver: SolverCloth, control: ClothControl) -> torch.Tensor:
    state = solver.initial_state()
    stats = solver.step(state, state, control, 1.0)
    assert stats.converged, "the static Newton solve did not converge"
    return (state.x - solver.x_rest).cpu()


def test_hanging_strip_stretches_as_a_bar_under_its_own_weight(device):
    """A strip hanging from its top row stretches by ``ρ g L² / (2E)`` (small strain).

    At height ``s`` above the free end the strip carries the weight below it, ``ρ h g s`` per unit width (N/m);
    the membrane's resultant ``E h ε`` (uniaxial plane stress: the narrow strip contracts freely sideways, so
    its modulus is Young's ``E = κ_s E₀``) balances it, ``ε(s) = ρ g s / E``, and the free end drops by
    ``∫₀ᴸ ε ds = ρ g L² / (2E)``: 2.8 mm for cotton over 1 m.
    """
    length, spacing = 1.0, 0.025
    x, faces = grid_sheet(3, round(length / spacing) + 1, spacing)  # 5 cm wide, y from 0 to L
    config = ClothConfig(static=True, newton_tolerance=1e-9, max_newton_iterations=30)
    solver = SolverCloth(x, faces, config, torch.zeros(0, 3, dtype=torch.int32))
    top = (x[:, 1] == x[:, 1].max()).nonzero().squeeze(1)
    displacement = _static_solve(solver, _pinned(x, top))
    bottom = x[:, 1] == 0.0
    expected = config.density * 9.81 * length**2 / (2.0 * config.young)
    measured = -float(displacement[bottom, 1].mean())
    assert measured == pytest.approx(expected, rel=0.05)
    assert float(displacement[:, 2].abs().max()) < 1e-3 * expected  # stays in its plane


def _alternating_strip(nx: int, ny: int, width: float, length: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat ``width × length`` sheet (m) of ``nx × ny`` vertices whose cells alternate their diagonal, so
    diagonals two cells apart are exactly parallel and coplanar; faces counter-clockwise seen from +z."""
    gx, gy = torch.meshgrid(
        torch.linspace(0, width, nx, dtype=F64), torch.linspace(0, length, ny, dtype=F64), indexing="ij"
    )
    x = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(-1, 3)
    faces = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            v = i * ny + j
            if (i + j) % 2 == 0:
                faces += [(v, v + ny, v + ny + 1), (v, v + ny + 1, v + 1)]
            else:
                faces += [(v, v + ny, v + 1), (v + 1, v + ny, v + ny + 1)]
    return x, torch.tensor(faces, dtype=torch.int32)


def test_flat_strip_with_alternating_diagonals_hangs_and_stretches(device):
    """A flat 0.2 × 0.5 m cotton strip with alternating diagonals, top row fixed, moves under gravity and settles
    at the bar's stretch ``ρ g L² / (2E)`` (between that and ``(1 − ν²)`` of it, where the clamp stops the sideways
    contraction near the top); its exactly parallel coplanar diagonals, 14.6 mm apart and far from touching, must
    not stop the line search."""
    width, length = 0.2, 0.5
    x, faces = _alternating_strip(20, 50, width, length)
    top = (x[:, 1] == x[:, 1].max()).nonzero().squeeze(1)
    no_body = torch.zeros(0, 3, dtype=torch.int32)
    solver = SolverCloth(x, faces, ClothConfig(), no_body)
    state = solver.initial_state()
    stats = solver.step(state, state, _pinned(x, top), 1.0 / 30.0)
    assert not stats.line_search_stalled
    assert float((state.x.cpu() - x)[:, 1].min()) < 0.0, "the strip falls"

    config = ClothConfig(static=True, newton_tolerance=1e-9, max_newton_iterations=30)
    solver = SolverCloth(x, faces, config, no_body)
    displacement = _static_solve(solver, _pinned(x, top))
    uniaxial = config.density * 9.81 * length**2 / (2.0 * config.young)
    measured = -float(displacement[x[:, 1] == 0.0, 1].mean())
    assert (1.0 - config.poisson**2) * uniaxial * 0.98 <= measured <= uniaxial * 1.02
    assert float(displacement[:, 2].abs().max()) < 1e-3 * uniaxial  # stays in its plane


def test_cantilever_deflects_as_euler_bernoulli_predicts(device):
    """A clamped strip under a small distributed load deflects ``δ = w L⁴ / (8 B)`` at its tip (10 %).

    Bending stiffness from the discrete shell, each hinge storing ``k w̄ θ²`` with ``w̄ = 3‖ē‖²/Ā``: on this grid
    (square cells of side ``a``, one diagonal direction) the surface ``z = ½ c_x x² + ½ c_y y² + c_xy x y`` folds
    the edges across x by ``(c_x − c_xy) a``, those across y by ``(c_y − c_xy) a`` and the diagonals (``w̄ = 6``)
    by ``√2 c_xy a``, one of each per cell area ``a²``: the continuum limit of the energy density is
    ``3k [(c_x − c_xy)² + (c_y − c_xy)² + 4 c_xy²]``. Pure cylindrical bending gives ``½ (6k) c_x²``; a narrow
    strip is free to take the ``c_y`` and ``c_xy`` that minimise it, leaving ``½ B c_x²`` with ``B = 4.8 k``
    per unit width. Two clamped columns put the root at the middle of the first cell (the first hinge lumps the
    curvature of the dual cell), so the beam length is ``L + a/2``. The load is ``w = ρ h g`` per unit area.
    """
    spacing, length = 0.005, 0.1
    cells = round(length / spacing)
    x, faces = grid_sheet(cells + 2, 5, spacing)
    probe = ClothConfig(static=True)
    rigidity = 4.8 * bending_stiffness(probe)
    beam = length + 0.5 * spacing
    tip = 1e-3  # 1 % of the length: geometrically linear
    g = 8.0 * rigidity * tip / (probe.density * probe.thickness * beam**4)
    config = ClothConfig(static=True, gravity=(0.0, 0.0, -g), newton_tolerance=1e-10, max_newton_iterations=40)
    solver = SolverCloth(x, faces, config, torch.zeros(0, 3, dtype=torch.int32))
    clamped = (x[:, 0] <= spacing * 1.01).nonzero().squeeze(1)
    displacement = _static_solve(solver, _pinned(x, clamped))
    free_end = x[:, 0] == x[:, 0].max()
    assert -float(displacement[free_end, 2].mean()) == pytest.approx(tip, rel=0.10)
    assert float(displacement[clamped].abs().max()) == 0.0


def _sheet_over_sphere(n: int, config: ClothConfig | None = None):
    x, faces = grid_sheet(n, n, 0.5 / (n - 1))
    x = torch.stack([x[:, 0] - 0.25, torch.full_like(x[:, 0], 0.24), x[:, 1] - 0.25], 1)  # 4 cm above the top
    body, body_faces = icosphere(2, 0.2)
    solver = SolverCloth(x, faces, config or ClothConfig(), body_faces)
    body = body.to(backend.torch_device())
    control = ClothControl(body, body, *_on_device(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3, dtype=F64)))
    return solver, control, body, body_faces


def test_sheet_dropped_on_sphere_never_penetrates(device):
    """A 20×20 sheet falls onto a sphere mesh: every step stays intersection-free and it comes to rest on top."""
    solver, control, body, body_faces = _sheet_over_sphere(20)
    tri = body[body_faces.long()]
    normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inscribed = float(((tri[:, 0] * normal).sum(1) / torch.linalg.norm(normal, dim=1)).min())
    state = solver.initial_state()
    touched = False
    for _ in range(30):
        stats = solver.step(state, state, control, 0.04)
        assert bool(torch.isfinite(state.x).all()) and bool(torch.isfinite(state.v).all())
        assert stats.min_distance_body > 0.0 and stats.min_distance_self > 0.0
        assert float(torch.linalg.norm(state.x, dim=1).min()) > inscribed  # outside the polyhedron's inner ball
        touched |= stats.min_distance_body < solver.config.contact_distance
        assert set(stats.time) == set(PHASES) and min(stats.time.values()) >= 0.0
        assert stats.time["assemble"] > 0.0 and stats.time["solve"] > 0.0 and stats.time["broad_phase"] > 0.0
    assert touched, "the sheet never reached the sphere"
    centre = int(torch.linalg.norm(solver.x_rest[:, [0, 2]], dim=1).argmin())
    assert inscribed < float(state.x[centre, 1]) < float(body[:, 1].max()) + 2e-3  # resting on the sphere's top
    assert float(state.x[:, 1].min()) < 0.1  # the rim drapes down


def test_candidates_found_once_serve_every_sweep_they_cover(device):
    """A step searches for contact candidates once, along each vertex's predicted path plus a margin: for any sweep
    inside that reach, filtering them gives exactly the pairs a fresh search of the sweep finds."""
    solver, control, body, _ = _sheet_over_sphere(12)
    state = solver.initial_state()
    for _ in range(7):  # fall into contact
        solver.step(state, state, control, 0.04)
    lifted = body + torch.tensor([0.0, 4e-3, 0.0], dtype=F64, device=body.device)
    rising = ClothControl(body, lifted, control.boundary_index, control.boundary_target)
    X, target, ctx = solver.step_context(state, rising, 0.04)
    cover = solver.contact.cover(X, target, ctx.kinematic, ctx.x_rest, 5e-3)
    generator = torch.Generator().manual_seed(0)

    def rows(index: torch.Tensor) -> set:
        return set(map(tuple, index.cpu().tolist()))

    for scale in (1e-3, 4e-3, 3e-2):
        p = (2.0 * torch.rand(X.shape, generator=generator, dtype=F64) - 1.0).to(X.device) * scale
        p[solver.vertex_count :] = target[solver.vertex_count :] - X[solver.vertex_count :]
        assert solver.contact.covers(cover, X, p) == (scale < 5e-3)
        if scale > 5e-3:
            continue
        fresh = solver.contact.broad_phase(X, p, ctx.kinematic, ctx.x_rest)
        reused = solver.contact.swept(X, p, cover)
        assert fresh.pt.shape[0] > 0 and fresh.pt_body > 0  # the sheet lies on the sphere
        assert rows(reused.pt) == rows(fresh.pt) and rows(reused.ee) == rows(fresh.ee)
        assert (reused.pt_body, reused.ee_body) == (fresh.pt_body, fresh.ee_body)

    # A step whose candidates must be searched again at every sweep (no margin) takes the same path. Compared on the
    # CPU, where sums run in a fixed order: a GPU's run in its atomics' order, different from run to run, and their
    # rounding grows through 8 steps' Newton solves (the two paths ended 7.9e-8 m apart on an H200).
    if backend.torch_device().type != "cpu":
        return
    paths, searches = [], []
    for margin in (0.0, 5e-3):
        solver, control, _, _ = _sheet_over_sphere(8, ClothConfig(candidate_margin=margin))
        state, total = solver.initial_state(), 0
        for _ in range(8):
            total += solver.step(state, state, control, 0.04).candidate_searches
        paths.append(state.x.cpu())
        searches.append(total)
    torch.testing.assert_close(paths[1], paths[0], rtol=0.0, atol=1e-9)
    assert searches[1] < searches[0]


def test_linear_solvers_take_the_same_steps(device):
    """Sparse direct (SuperLU, and cuDSS where present), dense Cholesky and CG solve the same Newton system in
    contact alike, and the sheet lands on the sphere alike with each.

    The trajectories agree only to Newton's tolerance: where a step's last ``‖p‖_∞ / Δt`` lies within rounding of
    the tolerance, one solver stops and another takes one more iteration, so each step may differ by up to
    ``tol · Δt`` (0.4 mm here)."""
    names = ("direct", "dense", "cg") + (("cudss",) if device == "cuda" and cudss.available() else ())
    config = {name: ClothConfig(linear_solver=name, cg_tolerance=1e-12) for name in names}
    finals, solvers = {}, {}
    for name in names:
        solver, control, _, _ = _sheet_over_sphere(8, config[name])
        assert solver.linear_solver == name
        state = solver.initial_state()
        for _ in range(8):
            stats = solver.step(state, state, control, 0.04)
        assert stats.min_distance_body < solver.config.contact_distance  # in contact by the last step
        finals[name], solvers[name] = state, solver

    # one Newton system of the sheet in contact, solved by each
    solver = solvers["direct"]
    X, target, ctx = solver.step_context(finals["direct"], control, 0.04)
    pairs = solver.contact.broad_phase(X, torch.zeros_like(X), ctx.kinematic, ctx.x_rest)
    _, grad, elements = solver.potential.evaluate(X, solver.contact.near(X, pairs), ctx)
    assert any(element.reach is not None and element.index.shape[0] for element in elements)  # contacts
    matrix, rhs = solver.assemble(elements, grad, torch.zeros_like(X), ctx)
    reference = solver.linear.solve(matrix, rhs.reshape(-1))
    for name in names:
        p = solvers[name].linear.solve(matrix, rhs.reshape(-1))
        torch.testing.assert_close(p, reference, rtol=0.0, atol=1e-9 * float(reference.abs().max()))

    tol_step = solver.config.newton_tolerance * 0.04
    for name in names:
        torch.testing.assert_close(finals[name].x, finals["direct"].x, rtol=0.0, atol=8 * tol_step)


def test_membrane_stress_filter_lands_the_sheet_as_eigen_filtering(device):
    """The membrane's Hessians made PSD in the kernel (stress filter) instead of by their eigen-decomposition: every
    step converges without intersection, and the sheet comes to rest on the sphere at the same height."""
    finals = {}
    for membrane_filter in ("eigen", "stress"):
        solver, control, _, _ = _sheet_over_sphere(8, ClothConfig(membrane_filter=membrane_filter))
        state = solver.initial_state()
        for _ in range(8):
            stats = solver.step(state, state, control, 0.04)
            assert stats.converged and stats.min_distance_body > 0.0 and stats.min_distance_self > 0.0
        assert stats.min_distance_body < solver.config.contact_distance
        finals[membrane_filter] = state.x.cpu()
    # the folds of a sheet draped on a sphere may fall either way (the CG and direct paths part too), its height not
    heights = {name: float(x[:, 1].mean()) for name, x in finals.items()}
    assert abs(heights["stress"] - heights["eigen"]) < 2e-3, heights


def test_fixed_shape_newton_loop_takes_the_exact_lists_steps(device):
    """The Newton loop as it runs on CUDA (pair lists in buffers of fixed capacity, padded with a phantom pair, each
    phase one CUDA graph) takes the steps of the loop over exact pair lists: bit for bit on the CPU, to rounding on
    CUDA (sums in atomics order; 1.3e-7 m apart after 9 steps on an H100, against Newton's tolerance of 4e-4 m a
    step). Buffers start too small for the contacts, so that each kind of growth runs: the iteration whose active
    pairs overflow runs again, and so do the phases whose sweep candidates overflow."""
    runs = {}
    for static in (False, True):
        solver, control, _, _ = _sheet_over_sphere(10)
        parts = (solver.potential, solver.contact, solver.matrices, solver.linear)
        loop = solver.loop = NewtonLoop(*parts, solver.config.newton_tolerance, static=static)
        loop.capacity.update(active_pt=2, active_ee=2, swept_pt=2, swept_ee=2)
        state = solver.initial_state()
        trace = []
        for _ in range(9):
            stats = solver.step(state, state, control, 0.04)
            trace.append((stats.newton_iterations, stats.contacts, stats.candidate_searches))
        assert stats.contacts > 0  # in contact by the last step
        runs[static] = state.x.cpu(), trace, loop
    (exact, trace, _), (fixed, fixed_trace, loop) = runs[False], runs[True]
    assert fixed_trace == trace
    assert min(loop.capacity[name] for name in ("active_pt", "active_ee", "swept_pt", "swept_ee")) > 2
    if device == "cpu":
        assert torch.equal(fixed, exact)
    else:
        torch.testing.assert_close(fixed, exact, rtol=0.0, atol=1e-5)
        assert all(phase.captures >= 1 for phase in loop.phases)
        assert loop.phases[0].captures >= 2  # the assembly, captured anew as its active pairs outgrew their buffers


def test_cpu_steps_are_bitwise_reproducible(device):
    """Same inputs on the CPU give identical output, run to run."""
    if device != "cpu":
        pytest.skip("bitwise reproducibility is a CPU guarantee (GPU sums in atomics order)")
    results = []
    for _ in range(2):
        solver, control, _, _ = _sheet_over_sphere(8)
        state = solver.initial_state()
        for _ in range(5):
            solver.step(state, state, control, 0.04)
        results.append((state.x.clone(), state.v.clone()))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_double_buffered_steps_write_into_their_states_as_in_place_steps_do(device):
    """Stepping from one state into another, then swapping, gives what stepping a state in place gives (bit for bit
    on the CPU), and the step writes into the output state's own tensors: their storage never moves. The number of
    Dirichlet vertices changes on the way, so the solver's step buffers are made anew once.

    On CUDA, atomic sums make two runs of the same steps differ in their last bits, and such a difference can move a
    Newton loop's stop by one iteration: the states then agree to the Newton tolerance, not to rounding. The sheet
    is stepped to a tolerance whose last step, 1e-5 m/s × 0.04 s, lies well under the comparison's 1e-5 m."""
    runs = {}
    for buffered in (False, True):
        solver, control, body, _ = _sheet_over_sphere(8, ClothConfig(newton_tolerance=1e-5))
        pinned = _pinned(solver.x_rest.cpu(), torch.tensor([0, 7]), body.cpu())
        made = [solver.initial_state(), solver.initial_state()]
        storage = [(s.x.data_ptr(), s.v.data_ptr()) for s in made]
        states = list(made)
        for t in range(10):
            step_control = pinned if t < 3 else control
            if buffered:
                solver.step(states[0], states[1], step_control, 0.04)
                states.reverse()
            else:
                solver.step(states[0], states[0], step_control, 0.04)
        assert [(s.x.data_ptr(), s.v.data_ptr()) for s in made] == storage
        runs[buffered] = states[0].x.cpu(), states[0].v.cpu()
    (x, v), (x_buffered, v_buffered) = runs[False], runs[True]
    assert float(x[:, 1].min()) < 0.2  # fell into contact with the sphere's top
    if device == "cpu":
        assert torch.equal(x_buffered, x) and torch.equal(v_buffered, v)
    else:
        torch.testing.assert_close(x_buffered, x, rtol=0.0, atol=1e-5)
    state = solver.initial_state()
    for bad in (
        ClothState(state.x[:-1].clone(), state.v[:-1].clone()),
        ClothState(state.x.float(), state.v.clone()),
        ClothState(state.x.clone(), state.v.cpu() if device != "cpu" else state.v.to(torch.float32)),
    ):
        with pytest.raises(ValueError, match=r"state_out\.[xv] must be a float64 .* solver\.initial_state\(\)"):
            solver.step(state, bad, control, 0.04)
    shared = torch.zeros(2, *state.x.shape, dtype=F64, device=state.x.device)
    with pytest.raises(ValueError, match="share memory"):
        solver.step(state, ClothState(shared[0], shared[1]), control, 0.04)


def test_bad_input_raises_clear_errors(device):
    x, faces = grid_sheet(4, 4, 0.1)
    no_body = torch.zeros(0, 3, dtype=torch.int32)
    for field, value, words in (
        ("density", 100.0, "density"),
        ("kappa_s", 10.0, "kappa_s"),
        ("kappa_b", 0.05, "kappa_b"),
        ("thickness", -1e-3, "thickness"),
        ("poisson", 0.5, "poisson"),
        ("candidate_margin", -1e-3, "candidate_margin"),
        ("membrane_filter", "flip", "membrane_filter"),
        ("psd_precision", "float16", "psd_precision"),
    ):
        with pytest.raises(ValueError, match=words):
            ClothConfig(**{field: value})
    with pytest.raises(ValueError, match="boundary"):
        solver = SolverCloth(x, faces, ClothConfig(static=True), no_body)
        solver.step(solver.initial_state(), solver.initial_state(), ClothControl.free(backend.torch_device()), 1.0)
    with pytest.raises(ValueError, match="more than two faces"):
        SolverCloth(x, torch.cat([faces, torch.tensor([[0, 1, 5]], dtype=torch.int32)]), ClothConfig(), no_body)
    # a garment inside the body: the sheet sits within the sphere, far from its surface
    body, body_faces = icosphere(1, 1.0)
    solver = SolverCloth(x - 0.15, faces, ClothConfig(), body_faces)
    body = body.to(backend.torch_device())
    control = ClothControl(body, body, *_on_device(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3, dtype=F64)))
    with pytest.raises(ValueError, match="inside the body"):
        solver.step(solver.initial_state(), solver.initial_state(), control, 0.04)
    with pytest.raises(ValueError, match="shape"):
        state = solver.initial_state()
        solver.step(ClothState(state.x[:-1], state.v[:-1]), state, control, 0.04)
