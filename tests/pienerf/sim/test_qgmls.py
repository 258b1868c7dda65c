"""Q-GMLS shape functions (PIE-NeRF Eq. 5–9): patch test, partition of unity, exact derivatives, layout."""

from __future__ import annotations

import pytest
import torch

from kernels import backend
from pienerf.sim.cut import CutMask, CutPlane
from pienerf.sim.qgmls import (
    QUADRATIC_TERMS,
    QGMLSBasis,
    mls_weight,
    polynomial_terms,
    support_radii,
    voronoi_partition,
)

F64 = torch.float64


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _on(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.to(backend.torch_device())


def _quadratic_field(seed: int):
    """A random quadratic displacement ``u_a = c_a + B_aj x_j + C_ajk x_j x_k`` and its derivatives."""
    g = _generator(seed)
    c, b = torch.randn(3, generator=g, dtype=F64), torch.randn(3, 3, generator=g, dtype=F64)
    quad = torch.randn(3, 3, 3, generator=g, dtype=F64)
    quad = _on(0.5 * (quad + quad.transpose(1, 2)))
    c, b = _on(c), _on(b)

    def value(x):
        return c + x @ b.T + torch.einsum("ajk,mj,mk->ma", quad, x, x)

    def gradient(x):  # [M, a, j]
        return b + 2.0 * torch.einsum("ajk,mk->maj", quad, x)

    def hessian(x):  # [M, a, j, k]
        return (2.0 * quad).expand(x.shape[0], 3, 3, 3)

    return value, gradient, hessian


def _layout(name: str, seed: int = 0):
    """Kernel centres, radii and evaluation points for a 3D cloud, a plane (z = 0) or a line (x axis)."""
    g = _generator(seed)
    if name == "volume":
        centres = torch.rand(30, 3, generator=g, dtype=F64)
        points = 0.1 + 0.8 * torch.rand(200, 3, generator=g, dtype=F64)
        radius = support_radii(centres, points)
    elif name == "coplanar":
        grid = torch.linspace(0.0, 1.0, 5, dtype=F64)
        centres = torch.cartesian_prod(grid, grid, torch.zeros(1, dtype=F64))
        points = torch.rand(200, 3, generator=g, dtype=F64) * torch.tensor([1.0, 1.0, 0.3], dtype=F64)
        points[:, 2] -= 0.15  # off the plane on both sides
        radius = torch.full((centres.shape[0],), 0.4, dtype=F64)
    else:
        assert name == "colinear"
        centres = torch.zeros(6, 3, dtype=F64)
        centres[:, 0] = torch.linspace(0.0, 1.0, 6, dtype=F64)
        points = torch.rand(200, 3, generator=g, dtype=F64) * torch.tensor([1.0, 0.2, 0.2], dtype=F64)
        points[:, 1:] -= 0.1
        radius = torch.full((centres.shape[0],), 0.35, dtype=F64)
    return _on(centres), _on(radius), _on(points)


@pytest.mark.parametrize("layout", ["volume", "coplanar", "colinear"])
def test_patch_test_reproduces_quadratic_field(device, layout):
    centres, radius, points = _layout(layout)
    value, gradient, hessian = _quadratic_field(seed=1)
    basis = QGMLSBasis(centres, radius)
    q = basis.dof_from_field(value(centres), gradient(centres), hessian(centres))
    assert q.shape == (centres.shape[0], 10, 3)

    u = basis.displacement(q, points)
    exact = value(points)
    assert (u - exact).abs().max() <= 1e-6 * exact.abs().max()

    f = basis.deformation_gradient(q, points)
    exact_f = gradient(points) + torch.eye(3, dtype=F64, device=points.device)
    assert (f - exact_f).abs().max() <= 1e-6 * exact_f.abs().max()


def test_affine_mls_reproduces_affine_but_not_quadratic_fields(device):
    centres, radius, points = _layout("volume")
    basis = QGMLSBasis(centres, radius, order="affine")
    assert basis.terms == 1 and basis.dof_count == 3 * centres.shape[0]

    b = _on(torch.randn(3, 3, generator=_generator(2), dtype=F64))
    affine = basis.displacement(basis.dof_from_field(centres @ b.T + 1.0), points)
    assert torch.allclose(affine, points @ b.T + 1.0, rtol=0.0, atol=1e-10)

    value, _, _ = _quadratic_field(seed=1)
    u = basis.displacement(basis.dof_from_field(value(centres)), points)
    exact = value(points)
    assert (u - exact).abs().max() > 1e-2 * exact.abs().max()


@pytest.mark.parametrize("layout", ["coplanar", "colinear"])
def test_affine_mls_with_degenerate_centres_raises_singular_g(device, layout):
    centres, radius, points = _layout(layout)
    basis = QGMLSBasis(centres, radius, order="affine")
    with pytest.raises(ValueError, match=r"singular.*order='quadratic'"):
        basis.evaluate(points, derivatives=0)
    # The quadratic basis evaluates on the same points (test_patch_test_* checks its values).
    assert torch.isfinite(QGMLSBasis(centres, radius).evaluate(points, derivatives=0).value).all()


def test_single_kernel_in_support_suffices(device):
    centres = _on(torch.tensor([[0.0, 0.0, 0.0]], dtype=F64))
    basis = QGMLSBasis(centres, _on(torch.tensor([1.0], dtype=F64)))
    points = _on(torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.5, 0.5]], dtype=F64))
    value, gradient, hessian = _quadratic_field(seed=3)
    q = basis.dof_from_field(value(centres), gradient(centres), hessian(centres))
    assert torch.allclose(basis.displacement(q, points), value(points), rtol=1e-9, atol=1e-12)


def test_partition_of_unity(device):
    centres, radius, points = _layout("volume", seed=4)
    basis = QGMLSBasis(centres, radius)
    shape = basis.evaluate(points, derivatives=2)
    is_value = (shape.index >= 0) & (shape.index % basis.terms == 0)
    mask = is_value.to(F64)
    assert torch.allclose((shape.value * mask).sum(1), torch.ones_like(points[:, 0]), atol=1e-12)
    assert (shape.grad * mask[..., None]).sum(1).abs().max() < 1e-9
    assert (shape.hess * mask[..., None, None]).sum(1).abs().max() < 1e-7


@pytest.mark.parametrize("order", ["quadratic", "affine"])
def test_derivatives_match_finite_differences(device, order):
    centres, radius, points = _layout("volume", seed=5)
    points = points[:40]
    basis = QGMLSBasis(centres, radius, order=order)
    shape = basis.evaluate(points, derivatives=2)
    n = basis.shape_count

    grad, hess = _dense(shape.index, shape.grad, n), _dense(shape.index, shape.hess, n)
    step = 1e-5
    for j in range(3):
        e = torch.zeros(3, dtype=F64, device=points.device)
        e[j] = step
        plus, minus = basis.evaluate(points + e, derivatives=1), basis.evaluate(points - e, derivatives=1)
        fd_value = (plus.dense_value(n) - minus.dense_value(n)) / (2 * step)
        assert (fd_value - grad[..., j]).abs().max() <= 1e-6 * grad.abs().max()
        fd_grad = (_dense(plus.index, plus.grad, n) - _dense(minus.index, minus.grad, n)) / (2 * step)
        assert (fd_grad - hess[..., j]).abs().max() <= 1e-5 * hess.abs().max()


def _dense(index: torch.Tensor, field: torch.Tensor, n: int) -> torch.Tensor:
    """Scatter a sparse ``[M, S, ...]`` shape-function field to dense ``[M, n, ...]``."""
    trailing = field.shape[2:]
    where = index.clamp_min(0).reshape(*index.shape, *(1,) * len(trailing)).expand_as(field)
    return torch.zeros(index.shape[0], n, *trailing, dtype=F64, device=field.device).scatter_add_(1, where, field)


def test_matches_unshifted_equation_7(device):
    """The centred, scaled basis gives exactly Eq. 7–8 written in world coordinates."""
    centres, radius, points = _layout("volume", seed=6)
    basis = QGMLSBasis(centres, radius)
    x = points[:5]
    shape = basis.evaluate(x, derivatives=0).dense_value(basis.shape_count)
    for m in range(x.shape[0]):
        w = mls_weight((x[m] - centres) / radius[:, None])  # [n]
        b = polynomial_terms(centres)  # [n, T, P] in world coordinates
        gram = torch.einsum("i,itp,itq->pq", w, b, b)  # Eq. 8
        p_x = polynomial_terms(x[m])[0]
        reference = torch.einsum("p,itp->it", torch.linalg.solve(gram, p_x), b) * w[:, None]  # Eq. 7
        assert torch.allclose(shape[m], reference.reshape(-1), rtol=0.0, atol=1e-10)


def test_mls_weight_values_and_support(device):
    d = _on(torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.6, 0.8], [2.0, 0.0, 0.0]], dtype=F64))
    expected = _on(torch.tensor([1.0, 0.75**3, 0.0, 0.0], dtype=F64))
    assert torch.allclose(mls_weight(d), expected, rtol=0.0, atol=1e-15)


def test_polynomial_terms_are_the_derivatives_of_the_basis(device):
    y = _on(torch.tensor([0.3, -0.7, 1.1], dtype=F64, requires_grad=True))
    terms = polynomial_terms(y)
    assert terms.shape == (10, 10)
    jac = torch.autograd.functional.jacobian(lambda v: polynomial_terms(v)[0], y)  # [P, 3]
    hess = torch.stack(
        [torch.autograd.functional.hessian(lambda v, p=p: polynomial_terms(v)[0, p], y) for p in range(10)]
    )
    assert torch.allclose(terms[1:4], jac.T)
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    for t, (j, k) in enumerate(pairs, start=4):
        assert QUADRATIC_TERMS[t] == "d" + "xyz"[j] + "xyz"[k]
        assert torch.allclose(terms[t], hess[:, j, k])


def test_layout_dense_jacobian_and_dofs(device):
    centres, radius, points = _layout("volume", seed=7)
    basis = QGMLSBasis(centres, radius)
    n, t = basis.kernel_count, basis.terms
    shape = basis.evaluate(points, derivatives=0)
    assert shape.grad is None and shape.hess is None
    assert shape.index.shape == shape.value.shape and shape.index.shape[1] % t == 0
    padded = shape.index < 0
    assert bool((shape.value[padded] == 0).all())
    assert int(shape.index.max()) < n * t

    q = _on(torch.randn(n, t, 3, generator=_generator(8), dtype=F64))
    jacobian = basis.dense_jacobian(points)
    assert jacobian.shape == (points.shape[0], 3, 3 * n * t)
    assert torch.allclose(jacobian @ q.reshape(-1), basis.displacement(q, points), atol=1e-12)

    grad = _on(torch.randn(n, 3, 3, generator=_generator(9), dtype=F64))
    hess = _on(torch.randn(n, 3, 3, 3, generator=_generator(10), dtype=F64))
    q = basis.dof_from_field(torch.zeros_like(centres), grad, hess)
    assert torch.equal(q[:, 2, 0], grad[:, 0, 1])  # ∂u_x/∂y
    assert torch.equal(q[:, 5, 2], hess[:, 2, 0, 1])  # ∂²u_z/∂x∂y, the mixed second derivative itself
    assert torch.equal(q[:, 9, 1], hess[:, 1, 2, 2])  # ∂²u_y/∂z²


def test_support_radii_cover_every_point(device):
    g = _generator(11)
    points = _on(torch.rand(500, 3, generator=g, dtype=F64))
    centres = points[:12]
    radius = support_radii(centres, points, neighbours=3, scale=1.25)
    cell, distance = voronoi_partition(points, centres)
    assert bool((distance * 1.25 <= radius[cell] + 1e-12).all())
    between = torch.cdist(centres, centres).sort(1).values[:, 3]
    assert bool((radius >= 1.25 * between - 1e-12).all())
    QGMLSBasis(centres, radius).evaluate(points, derivatives=0)  # no uncovered point
    with pytest.raises(ValueError, match="scale must be > 1"):
        support_radii(centres, points, scale=1.0)


def test_bad_input_raises_clear_errors(device):
    centres, radius, points = _layout("volume")
    with pytest.raises(ValueError, match="unknown order"):
        QGMLSBasis(centres, radius, order="cubic")
    with pytest.raises(ValueError, match=r"support_radius must be \[n\]"):
        QGMLSBasis(centres, radius[:-1])
    with pytest.raises(ValueError, match="support_radii"):
        QGMLSBasis(centres, -radius)
    basis = QGMLSBasis(centres, radius)
    with pytest.raises(ValueError, match=r"1 of 2 points lie outside.*larger support radii"):
        basis.evaluate(_on(torch.tensor([[0.5, 0.5, 0.5], [9.0, 9.0, 9.0]], dtype=F64)))
    with pytest.raises(ValueError, match=r"q must be \[n, T, 3\]"):
        basis.displacement(torch.zeros(basis.dof_count, dtype=F64), points)
    with pytest.raises(ValueError, match=r"x must be \[N, 3\]"):
        basis.evaluate(points[:, :2])
    with pytest.raises(ValueError, match="derivatives must be"):
        basis.evaluate(points, derivatives=3)


@pytest.mark.parametrize("layout", ["coplanar", "colinear"])
def test_linear_gmls_reproduces_affine_fields_with_degenerate_centres(device, layout):
    centres, radius, points = _layout(layout)
    basis = QGMLSBasis(centres, radius, order="linear")
    assert basis.terms == 4 and basis.dof_count == 12 * centres.shape[0]
    b = _on(torch.randn(3, 3, generator=_generator(4), dtype=F64))
    gradient = b.expand(centres.shape[0], 3, 3)
    q = basis.dof_from_field(centres @ b.T + 1.0, gradient)
    assert torch.allclose(basis.displacement(q, points), points @ b.T + 1.0, rtol=0.0, atol=1e-9)
    value, grad, hess = _quadratic_field(seed=1)
    u = basis.displacement(basis.dof_from_field(value(centres), grad(centres), hess(centres)), points)
    assert (u - value(points)).abs().max() > 1e-3 * value(points).abs().max()  # first order only


def test_cut_plane_hides_kernels_across_it(device):
    centres = _on(torch.tensor([[0.2, 0.0, 0.0], [0.8, 0.0, 0.0]], dtype=F64))
    points = _on(torch.tensor([[0.4, 0.0, 0.0], [0.6, 0.0, 0.0], [0.6, 0.9, 0.0]], dtype=F64))
    plane = CutPlane((0.5, 0.0, 0.0), (1.0, 0.0, 0.0))
    expected = torch.tensor([[True, False], [False, True], [False, True]], device=points.device)
    assert torch.equal(plane.visibility(points, centres), expected)
    disc = CutPlane((0.5, 0.0, 0.0), (1.0, 0.0, 0.0), radius=0.3)  # the segment from the third point passes above
    assert torch.equal(disc.visibility(points, centres)[2], torch.tensor([True, True], device=points.device))
    labels = CutMask(points[:2], torch.tensor([0, 1]))
    assert torch.equal(labels.visibility(points[:2], centres), expected[:2])
    basis = QGMLSBasis(centres, _on(torch.tensor([1.0, 1.0], dtype=F64)), visibility=plane.visibility)
    shape = basis.evaluate(points[:2], derivatives=0)
    kernel_of = shape.index // basis.terms
    assert set(kernel_of[0][shape.value[0] != 0].tolist()) == {0}
    assert set(kernel_of[1][shape.value[1] != 0].tolist()) == {1}
    with pytest.raises(ValueError, match="finite point"):
        CutPlane((0.0, float("nan"), 0.0), (1.0, 0.0, 0.0))
