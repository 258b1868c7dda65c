"""Physical validation of the Q-GMLS elastodynamics solver against closed-form mechanics (PIE-NeRF §4–5).

Each test builds a small lattice body, drives it with the public solver API and compares with theory:
Euler–Bernoulli and Kirchhoff plate-strip deflection (§4.2, Fig. 8–9), volume preservation of
Neo-Hookean against ARAP (Fig. 6), long random-drag runs (robustness of §4.5) and a cut (Fig. 7).
Loads are small (δ/L ≲ 1 %), so the nonlinear static solution is the linear one to within 1 %.
Clamps are stiff zero-rest-length springs on the end slab; their compliance is checked to be negligible.
"""

import math

import pytest
import torch

from kernels import backend
from pienerf.sim.cut import CutPlane
from pienerf.sim.materials import Material
from pienerf.sim.model import DiscretizationConfig, QGMLSModel
from pienerf.sim.solver import PlaneCollider, PointTargets, QGMLSControl, SolverConfig, SolverQGMLS
from tests.pienerf.bodies import (
    cantilever_tip_deflection,
    clamp,
    euler_bernoulli_tip_deflection,
    kirchhoff_strip_tip_deflection,
    lattice,
    mechanical_energy,
)

YOUNG = 1.0e7  # Pa
DENSITY = 1000.0  # kg/m³
CLAMP = 100.0  # clamp spring stiffness per point, in units of E·b (N/m per Pa·m)


def _cantilever(size, spacing, kernel_count, order="quadratic", gravity=1.0, clamp_scale=CLAMP, ip_count=None):
    """Static tip deflection (m) of a body clamped at x = 0 under gravity −y (ν = 0)."""
    position, volume = lattice(size, spacing)
    config = DiscretizationConfig(kernel_count=kernel_count, order=order, ip_count=ip_count)
    model = QGMLSModel(position, volume, config, device=backend.torch_device())
    material = Material(young_modulus=YOUNG, poisson_ratio=0.0, density=DENSITY)
    solver = SolverQGMLS(model, material, SolverConfig(gravity=(0.0, -gravity, 0.0)))
    control = QGMLSControl(springs=[clamp(model, spacing, clamp_scale * YOUNG * size[1])])
    q, update = solver.solve_static(control, iterations=60)
    assert update < 1e-4, f"static Newton did not converge: last update {update:.2e}"  # m, or 1/m for ∇ DOFs
    return cantilever_tip_deflection(model, q, size)


def test_cantilever_beam_matches_euler_bernoulli_and_converges(device):
    size, spacing, gravity = (1.0, 0.1, 0.1), 0.02, 0.5
    # Clamp at the centres of the end slab's particles: the beam is L' = L − s/2 long from there.
    theory = euler_bernoulli_tip_deflection(size[0] - 0.5 * spacing, size[1], YOUNG, DENSITY, gravity)
    assert theory / size[0] < 0.01  # linear regime
    errors = {}
    for n in (4, 8, 16, 32):
        errors[n] = _cantilever(size, spacing, n, gravity=gravity) / theory - 1.0
    softer_clamp = _cantilever(size, spacing, 16, gravity=gravity, clamp_scale=0.1 * CLAMP) / theory - 1.0
    report = ", ".join(f"n={n}: {e:+.1%}" for n, e in errors.items())
    assert abs(softer_clamp - errors[16]) < 0.02, f"clamp compliance matters: 10x softer clamp {softer_clamp:+.1%}"
    # 3D elasticity adds ~0.8 % of shear deflection to Euler–Bernoulli at L/b = 10 (Timoshenko, ν = 0).
    assert all(abs(e) < 0.10 for e in errors.values()), f"tip deflection vs Euler–Bernoulli (ν = 0): {report}"
    assert abs(errors[8]) < abs(errors[4]), f"error must fall from the coarsest discretisation: {report}"


def test_slender_beam_quadrature_has_no_spurious_zero_energy_modes(device):
    """The elastic Hessian at rest has exactly the 6 rigid-body zero modes (no hourglass modes)."""
    position, volume = lattice((1.0, 0.1, 0.1), 0.025)
    for n in (8, 16):
        model = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=n), device=backend.torch_device())
        solver = SolverQGMLS(model, Material(young_modulus=1.0, poisson_ratio=0.3))
        rest = torch.zeros(model.shape_count, 3, dtype=torch.float64, device=model.device)
        eigenvalues = torch.linalg.eigvalsh(solver.integrator.evaluate(rest, project=False).hessian)
        # DOFs of different units (m, 1, 1/m) spread the true spectrum over ~10 decades, so a zero mode
        # is one below 1e-13 of the largest eigenvalue, far under the softest physical mode (~1e-10).
        zero_modes = int((eigenvalues < 1e-13 * eigenvalues[-1]).sum())
        assert eigenvalues[6] > 1e-12 * eigenvalues[-1]
        assert zero_modes == 6, (
            f"{n} kernels, {model.ips.count} integrator points (default ip_count): {zero_modes} zero-energy "
            "modes, 6 expected (rigid motions); the IP quadrature under-integrates the Q-GMLS field"
        )


def test_dense_kernels_on_a_slender_beam_build(device):
    """Every cuboid quadrature point of a slender body lies inside some kernel support (§4.4)."""
    position, volume = lattice((1.0, 0.1, 0.1), 0.025)
    model = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=32), device=backend.torch_device())
    assert model.summary()["kernels"] == 32


def test_thin_rod_bends_without_locking(device):
    size, spacing, gravity = (1.0, 0.05, 0.05), 0.0125, 0.1  # L/b = 20, 4 x 4 particles across
    theory = euler_bernoulli_tip_deflection(size[0] - 0.5 * spacing, size[1], YOUNG, DENSITY, gravity)
    assert theory / size[0] < 0.01
    for n in (4, 6):
        quadratic = _cantilever(size, spacing, n, "quadratic", gravity) / theory - 1.0
        linear = _cantilever(size, spacing, n, "linear", gravity) / theory - 1.0
        numbers = f"{n} kernels: Q-GMLS {quadratic:+.1%}, linear GMLS {linear:+.1%} vs Euler–Bernoulli"
        assert abs(quadratic) < 0.25, numbers
        assert abs(linear) > 2.0 * abs(quadratic), numbers
        assert linear < 0, f"the linear basis must lock (too stiff): {numbers}"
    with pytest.raises(ValueError, match="affine basis needs the kernel centres"):
        _cantilever(size, spacing, 6, "affine", gravity)  # classical MLS: G singular for colinear kernels


def test_thin_plate_bends_without_locking(device):
    size, spacing, gravity = (0.5, 0.025, 0.25), 0.0125, 0.1  # L/t = 20, two particles through the thickness
    theory = kirchhoff_strip_tip_deflection(size[0] - 0.5 * spacing, size[1], YOUNG, 0.0, DENSITY, gravity)
    assert theory / size[0] < 0.01
    quadratic = _cantilever(size, spacing, 6, "quadratic", gravity) / theory - 1.0
    linear = _cantilever(size, spacing, 6, "linear", gravity) / theory - 1.0
    numbers = f"6 kernels: Q-GMLS {quadratic:+.1%}, linear GMLS {linear:+.1%} vs Kirchhoff strip (ν = 0)"
    assert abs(quadratic) < 0.25, numbers
    assert abs(linear) > 2.0 * abs(quadratic), numbers


def _compressed_volume(model: QGMLSModel, kind: str, height: float, spacing: float, strain: float) -> float:
    """Volume ratio V/V₀ after a frictionless plate squeezes the lattice cube by ``strain`` (quasi-static)."""
    # A jelly is nearly incompressible; ARAP has no volume term, so ν does not enter it.
    solver = SolverQGMLS(model, Material(kind, young_modulus=1e5, poisson_ratio=0.48),
                         SolverConfig(gravity=(0.0, 0.0, 0.0)))
    floor = PlaneCollider((0.0, 0.5 * spacing, 0.0), (0.0, 1.0, 0.0))  # planes act on particle centres
    q = None
    span = height - spacing  # rest distance between the outer particle layers
    for fraction in torch.linspace(0.0, strain, 7)[1:].tolist():
        plate = PlaneCollider((0.0, 0.5 * spacing + (1.0 - fraction) * span, 0.0), (0.0, -1.0, 0.0))
        q, _ = solver.solve_static(QGMLSControl(colliders=[floor, plate]), q0=q, iterations=10)
    y = model.particles.positions(q)[:, 1]
    assert float(y.max() - y.min()) < (1.0 - strain + 0.03) * span, "the plate did not compress the cube"
    return float(model.deformed_volume(q) / model.volume.sum())


def test_jelly_compression_neo_hookean_keeps_volume_arap_loses_it(device):
    height, spacing, strain = 0.2, 0.025, 0.4
    position, volume = lattice((height,) * 3, spacing)
    config = DiscretizationConfig(kernel_count=12)
    model = QGMLSModel(position, volume, config, device=backend.torch_device())
    neo_hookean_loss = 1.0 - _compressed_volume(model, "neo_hookean", height, spacing, strain)
    arap_loss = 1.0 - _compressed_volume(model, "arap", height, spacing, strain)
    numbers = f"volume loss at {strain:.0%} compression: Neo-Hookean {neo_hookean_loss:.1%}, ARAP {arap_loss:.1%}"
    assert abs(neo_hookean_loss) < 0.05, numbers
    assert arap_loss > 0.15 and arap_loss > 3.0 * abs(neo_hookean_loss), numbers


def _shape(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    if name == "box":
        return lattice((0.2, 0.1, 0.1), 0.025)
    if name == "rod":
        return lattice((0.4, 0.05, 0.05), 0.0125)
    return lattice((0.2, 0.2, 0.1), 0.025, keep=lambda x: (x[:, 0] < 0.1) | (x[:, 1] < 0.1))  # L-shape


@pytest.mark.parametrize("shape, windows, seed", [("box", 40, 0), ("rod", 12, 1), ("l_shape", 12, 2)])
def test_random_drags_for_many_steps_stay_finite_uninverted_and_bounded(device, shape, windows, seed):
    """Implicit Euler does not create energy: E_kin + U stays below the work the drags and gravity can do.

    Targets are constant within each 50-step window, so a drag spring is conservative there and does
    at most its potential at the window's start, ½ k Σ|x − target|², of work on the body; gravity
    does m g (ȳ₀ − ȳ) = f_gᵀ(q − q₀); the penalty floor and the elastic energy are conservative. The box takes
    2000 steps, the rod and the L-shape 600 each.
    """
    position, volume = _shape(shape)
    position = position + torch.tensor([0.0, 0.05, 0.0], dtype=torch.float64)  # above the floor y = 0
    model = QGMLSModel(position, volume, DiscretizationConfig(kernel_count=8), device=backend.torch_device())
    solver = SolverQGMLS(model, Material(young_modulus=5e4, poisson_ratio=0.4), SolverConfig(newton_iterations=2))
    state, floor, dt = solver.rest_state(), PlaneCollider(), 1.0 / 60.0
    generator = torch.Generator().manual_seed(seed)
    stiffness = 20.0  # N/m per dragged point: drags bend the body by centimetres
    budget, lowest_det = 0.0, math.inf
    for window in range(windows):
        picks = torch.randperm(position.shape[0], generator=generator)[:3]
        handle = model.handle(position[picks])
        offset = (torch.rand(3, 3, generator=generator, dtype=torch.float64) - 0.5) * torch.tensor([0.6, 0.4, 0.6])
        target = handle.positions(state.q) + offset.to(model.device)
        target[:, 1].clamp_(min=0.02)
        drag = PointTargets(handle, target, stiffness)
        budget += 0.5 * stiffness * float(((handle.positions(state.q) - target) ** 2).sum())
        control = QGMLSControl(springs=[drag], colliders=[floor])
        for _ in range(50):
            report = solver.step(state, state, control, dt)
            assert math.isfinite(report.energy) and torch.isfinite(state.q).all(), f"NaN in window {window}"
            assert report.min_det > 0, f"inverted quadrature point (det F = {report.min_det:.3g}) in window {window}"
            lowest_det = min(lowest_det, report.min_det)
            kinetic, elastic = mechanical_energy(solver, state.q, state.qd)
            gravity_work = float((solver.gravity_force * state.q).sum())
            assert kinetic + elastic <= budget + gravity_work + 1e-9, (
                f"energy {kinetic + elastic:.4g} J exceeds the work bound {budget + gravity_work:.4g} J "
                f"in window {window}"
            )
    assert lowest_det < 0.99  # the drags did deform the body


def test_cut_piece_falls_freely_while_uncut_bar_stays_attached(device):
    size, spacing, h, steps = (0.4, 0.1, 0.1), 0.025, 0.01, 10
    position, volume = lattice(size, spacing)
    cut = CutPlane(point=(0.5 * size[0], 0.0, 0.0), normal=(1.0, 0.0, 0.0))
    free = position[:, 0] > 0.5 * size[0]
    drops = {}
    for cuts in ((), (cut,)):
        config = DiscretizationConfig(kernel_count=8, cuts=cuts)
        model = QGMLSModel(position, volume, config, device=backend.torch_device())
        material = Material(young_modulus=YOUNG, poisson_ratio=0.3, density=DENSITY)
        solver = SolverQGMLS(model, material, SolverConfig(newton_iterations=6))
        control = QGMLSControl(springs=[clamp(model, spacing, CLAMP * YOUNG * size[1])])
        state = solver.rest_state()
        for _ in range(steps):
            solver.step(state, state, control, h)
        x = model.particles.positions(state.q)
        drops[bool(cuts)] = float((model.volume[free] * (model.particles.rest[free] - x[free])[:, 1]).sum()
                                  / model.volume[free].sum())
    free_fall = 9.81 * h * h * steps * (steps + 1) / 2  # discrete implicit-Euler free fall (m)
    assert drops[True] == pytest.approx(free_fall, rel=0.02), f"cut piece dropped {drops[True]:.4g} m"
    assert drops[False] < 0.1 * free_fall, f"uncut bar's far half dropped {drops[False]:.4g} m"
