"""Garment kernels (kernels.shell, .ipc_barrier, .contact, .ccd, .element_terms) against autograd references, finite
differences and ipctk: one module, as their oracle kernels.reference.cloth is one."""

import math

import numpy as np
import pytest
import torch

from kernels import backend, ccd, contact, element_terms, ipc_barrier, shell
from kernels.reference import cloth as ref

try:  # the IPC Toolkit is the external oracle for barrier, distances and mollifier where it is installed
    import ipctk
except ImportError:
    ipctk = None

needs_ipctk = pytest.mark.skipif(ipctk is None, reason="ipctk is not installed (pip install ipctk==1.6.1)")

F64 = torch.float64


def _dev(t: torch.Tensor) -> torch.Tensor:
    return t.to(backend.torch_device()).contiguous()


def _host(t):
    if isinstance(t, tuple):
        values = [_host(v) for v in t]
        return type(t)(*values) if hasattr(t, "_fields") else tuple(values)
    return t.detach().cpu()


def _sheet(n: int = 4, curved: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """An ``n × n`` vertex sheet of 10 cm cells, consistently oriented; optionally draped over a bump."""
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    x = torch.stack([0.1 * i.reshape(-1).to(F64), 0.1 * j.reshape(-1).to(F64), torch.zeros(n * n, dtype=F64)], 1)
    if curved:
        x[:, 2] = 0.03 * torch.sin(7.0 * x[:, 0]) * torch.cos(5.0 * x[:, 1])
    v = (i * n + j)[:-1, :-1].reshape(-1)
    faces = torch.cat([torch.stack([v, v + n, v + 1], 1), torch.stack([v + 1, v + n, v + n + 1], 1)])
    return x, faces.to(torch.int32)


def _rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(seed)))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _fd_grad(fn, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """Central differences of the scalar (or per-row) ``fn`` over every coordinate of ``x``."""
    cols = []
    flat = x.reshape(-1)
    for k in range(flat.numel()):
        plus, minus = flat.clone(), flat.clone()
        plus[k] += h
        minus[k] -= h
        cols.append((fn(plus.reshape(x.shape)) - fn(minus.reshape(x.shape))) / (2 * h))
    return torch.stack(cols, dim=-1)


def _assemble_grad(grad: torch.Tensor, index: torch.Tensor, nv: int) -> torch.Tensor:
    out = torch.zeros(nv, 3, dtype=grad.dtype)
    out.index_add_(0, index.long().reshape(-1), grad.reshape(-1, 3))
    return out


def _deformed_sheet(seed: int = 0):
    x_rest, faces = _sheet()
    hinges, _ = shell.hinges_from_faces(faces)
    rest = _host(shell.rest_state(_dev(x_rest), _dev(faces), _dev(hinges)))
    g = torch.Generator().manual_seed(seed)
    x = x_rest * torch.tensor([1.1, 0.95, 1.0], dtype=F64) + 0.02 * torch.randn(x_rest.shape, dtype=F64, generator=g)
    return x_rest, x, faces, hinges, rest


# ------------------------------------------------------------------------------------------------------------
# Material parameters and mesh topology
# ------------------------------------------------------------------------------------------------------------


def test_plane_stress_lame_values_and_bad_input():
    mu, lam = shell.plane_stress_lame(1.0e6, 0.3, 2.0e-3)
    assert mu == pytest.approx(2.0e-3 * 1.0e6 / 2.6)
    assert lam == pytest.approx(2.0e-3 * 1.0e6 * 0.3 / 0.91)
    with pytest.raises(ValueError, match="poisson"):
        shell.plane_stress_lame(1.0e6, 0.5, 1e-3)
    with pytest.raises(ValueError, match="thickness"):
        shell.plane_stress_lame(1.0e6, 0.3, 0.0)


def test_hinges_from_faces_finds_interior_edges_with_outward_wings(device):
    x, faces = _sheet(4, curved=False)
    hinges, hinge_faces = shell.hinges_from_faces(faces)
    n = 4
    interior = (n - 1) * (n - 2) * 2 + (n - 1) ** 2  # axis-aligned interior edges + diagonals
    assert hinges.shape == (interior, 4) and hinges.dtype == torch.int32
    f = faces.long()
    for (v0, v1, v2, v3), (fa, fb) in zip(hinges.long().tolist(), hinge_faces.tolist(), strict=True):
        assert {v0, v1, v2} == set(f[fa].tolist()) and {v0, v1, v3} == set(f[fb].tolist())
    rest = shell.rest_state(_dev(x), _dev(faces), _dev(hinges))
    torch.testing.assert_close(_host(rest.rest_angle), torch.zeros(interior, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(_host(rest.rest_area), torch.full((faces.shape[0],), 0.005, dtype=F64))
    # flat unit hinge of two right triangles: ē = 0.1·√2 (diagonal) or 0.1, Ā = 0.01
    assert set(np.round(_host(rest.rest_weight).numpy(), 9)) <= {6.0, 3.0}


def test_hinges_from_faces_rejects_bad_meshes():
    with pytest.raises(ValueError, match="more than two faces"):
        shell.hinges_from_faces(torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]], dtype=torch.int32))
    with pytest.raises(ValueError, match="orient all faces consistently"):
        shell.hinges_from_faces(torch.tensor([[0, 1, 2], [0, 1, 3]], dtype=torch.int32))
    with pytest.raises(ValueError, match=r"\[F, 3\]"):
        shell.hinges_from_faces(torch.zeros(4, 4, dtype=torch.int32))


# ------------------------------------------------------------------------------------------------------------
# Membrane and bending
# ------------------------------------------------------------------------------------------------------------


def test_membrane_matches_autograd_reference_and_finite_differences(device):
    x_rest, x, faces, _, rest = _deformed_sheet()
    mu = torch.linspace(1.0, 3.0, faces.shape[0], dtype=F64)
    out = _host(shell.membrane_energy(_dev(x), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), _dev(mu), 0.7))
    energy, grad, hess = ref.membrane_energy(x, faces, rest.rest_inv, rest.rest_area, mu, 0.7)
    assert energy.min() > 0
    torch.testing.assert_close(out.energy, energy, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(out.grad, grad, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(out.hess, hess, rtol=1e-9, atol=1e-10)

    def kernel_grad(xx):
        terms = shell.membrane_energy(_dev(xx), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), _dev(mu), 0.7)
        return _host(terms.grad).reshape(faces.shape[0], -1)

    def kernel_energy(xx):
        return _host(shell.membrane_energy(_dev(xx), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 2.0, 0.7))[
            0
        ].sum()

    fd = _fd_grad(kernel_energy, x).reshape(-1, 3)
    analytic = _host(shell.membrane_energy(_dev(x), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 2.0, 0.7))
    torch.testing.assert_close(_assemble_grad(analytic.grad, faces, x.shape[0]), fd, rtol=1e-6, atol=1e-8)
    # Hessian of element 3 against differences of its gradient, moving that element's own vertices
    e = 3
    fd_h = _fd_grad(lambda xx: kernel_grad(xx)[e], x)  # [9, V*3]
    cols = (faces[e].long()[:, None] * 3 + torch.arange(3)).reshape(-1)
    torch.testing.assert_close(out.hess[e], fd_h[:, cols], rtol=1e-5, atol=1e-6)


def test_bending_matches_autograd_reference_and_finite_differences(device):
    x_rest, x, faces, hinges, rest = _deformed_sheet(1)
    k = torch.linspace(0.5, 2.0, hinges.shape[0], dtype=F64)
    args = (_dev(hinges), _dev(rest.rest_angle), _dev(rest.rest_weight), _dev(k))
    out = _host(shell.bending_energy(_dev(x), *args))
    energy, grad, hess = ref.bending_energy(x, hinges, rest.rest_angle, rest.rest_weight, k)
    assert energy.max() > 1e-4
    torch.testing.assert_close(out.energy, energy, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(out.grad, grad, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(out.hess, hess, rtol=1e-7, atol=1e-7)

    fd = _fd_grad(lambda xx: _host(shell.bending_energy(_dev(xx), *args)).energy.sum(), x).reshape(-1, 3)
    torch.testing.assert_close(_assemble_grad(out.grad, hinges, x.shape[0]), fd, rtol=1e-6, atol=1e-8)
    h = 5
    fd_h = _fd_grad(lambda xx: _host(shell.bending_energy(_dev(xx), *args)).grad[h].reshape(-1), x)
    cols = (hinges[h].long()[:, None] * 3 + torch.arange(3)).reshape(-1)
    torch.testing.assert_close(out.hess[h], fd_h[:, cols], rtol=1e-5, atol=1e-6)


def test_dihedral_angle_sign_convention(device):
    # hinge edge along x, wing v2 at +y, wing v3 at -y; normals point to +z
    x = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]], dtype=F64)
    hinge = torch.tensor([[0, 1, 2, 3]], dtype=torch.int32)
    faces = torch.tensor([[0, 1, 2], [1, 0, 3]], dtype=torch.int32)
    for lift, sign in ((0.3, -1.0), (-0.3, 1.0)):
        bent = x.clone()
        bent[2:, 2] = lift  # wings fold towards +z (the normal side) or away from it
        angle = _host(shell.rest_state(_dev(bent), _dev(faces), _dev(hinge)).rest_angle)[0]
        assert math.copysign(1.0, angle.item()) == sign
        assert abs(angle.item()) == pytest.approx(2 * math.atan(0.3), rel=1e-12)
        assert angle.item() == pytest.approx(ref.dihedral_angle(bent).item(), rel=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rest_state_has_zero_energy_and_gradient(device, dtype):
    x_rest, _, faces, hinges, _ = _deformed_sheet()
    x = _dev(x_rest.to(dtype))
    rest = shell.rest_state(x, _dev(faces), _dev(hinges))
    m = _host(shell.membrane_energy(x, _dev(faces), rest.rest_inv, rest.rest_area, 10.0, 5.0))
    b = _host(shell.bending_energy(x, _dev(hinges), rest.rest_angle, rest.rest_weight, 1.0))
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    assert m.energy.abs().max() < tol * 1e-2 and m.grad.abs().max() < tol
    assert b.energy.abs().max() < tol * 1e-2 and b.grad.abs().max() < tol
    # at rest only the Gauss-Newton term survives: PSD bending, and a PSD membrane Hessian
    for hess in (m.hess, b.hess):
        assert torch.linalg.eigvalsh(hess.double()).min() > -tol * 100


def test_rigid_motion_leaves_energies_unchanged(device):
    _, x, faces, hinges, rest = _deformed_sheet(2)
    rot = _rotation(3)
    moved = x @ rot.T + torch.tensor([0.3, -2.0, 1.5], dtype=F64)

    def energies(xx):
        m = shell.membrane_energy(_dev(xx), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 3.0, 1.0)
        b = shell.bending_energy(_dev(xx), _dev(hinges), _dev(rest.rest_angle), _dev(rest.rest_weight), 0.1)
        return _host(m), _host(b)

    (ma, ba), (mb, bb) = energies(x), energies(moved)
    assert ma.energy.min() > 0 and ba.energy.max() > 0
    torch.testing.assert_close(ma.energy, mb.energy, rtol=1e-11, atol=1e-15)
    torch.testing.assert_close(ba.energy, bb.energy, rtol=1e-10, atol=1e-15)
    # gradients rotate with the body: g' = g Rᵀ per vertex
    torch.testing.assert_close(ma.grad @ rot.T, mb.grad, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ba.grad @ rot.T, bb.grad, rtol=1e-9, atol=1e-12)


def test_projected_hessians_are_psd_and_unchanged_when_psd(device):
    _, x, faces, hinges, rest = _deformed_sheet(4)
    x = x * torch.tensor([0.8, 0.8, 1.0], dtype=F64)  # compression makes StVK indefinite
    m = _host(shell.membrane_energy(_dev(x), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 1.0, 1.0))
    mp = m._replace(hess=_host(element_terms.project_psd(_dev(m.hess))))
    b = _host(shell.bending_energy(_dev(x), _dev(hinges), _dev(rest.rest_angle), _dev(rest.rest_weight), 1.0))
    bp = b._replace(hess=_host(element_terms.project_psd(_dev(b.hess))))
    assert torch.linalg.eigvalsh(m.hess).min() < -1e-3, "the test needs an indefinite membrane Hessian"
    for hess in (mp.hess, bp.hess):
        assert torch.linalg.eigvalsh(hess).min() > -1e-10
    spd = torch.eye(9, dtype=F64) * 2 + 0.1
    torch.testing.assert_close(element_terms.project_psd(spd[None])[0], spd)
    # decomposed in float32: float64 out, PSD still, within float32 precision of the float64 filter
    for hess, projected in ((m.hess, mp.hess), (b.hess, bp.hess)):
        for absolute in (False, True):
            single = _host(element_terms.project_psd(_dev(hess), absolute, eigen_dtype=torch.float32))
            exact = projected if not absolute else _host(element_terms.project_psd(_dev(hess), True))
            assert single.dtype == F64 and torch.linalg.eigvalsh(single).min() > -1e-10
            scale = hess.abs().amax((1, 2), keepdim=True)
            assert ((single - exact).abs() / scale).max() < 1e-5
    torch.testing.assert_close(mp.energy, m.energy)


@pytest.mark.parametrize("stress_filter", ["clamp", "abs"])
def test_membrane_stress_filters_match_reference_and_are_psd(device, stress_filter):
    """Filtered Hessians: the reference's (autograd stress, its eigen-decomposition) on a sheet whose triangles are
    under tension, under mixed and under full compression; PSD; the exact Hessian where the triangle is stretched;
    energies and gradients untouched."""
    _, x, faces, _, rest = _deformed_sheet(4)
    g = torch.Generator().manual_seed(3)
    # per-vertex scalings that stretch some triangles and compress others along one or both axes
    x = x * (0.75 + 0.5 * torch.rand(x.shape[0], 3, generator=g, dtype=F64))
    args = (_dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 1.3, 0.6)
    exact = _host(shell.membrane_energy(_dev(x), *args))
    got = _host(shell.membrane_energy(_dev(x), *args, stress_filter=stress_filter))
    _, _, want = ref.membrane_energy(x, faces, rest.rest_inv, rest.rest_area, 1.3, 0.6, stress_filter=stress_filter)
    torch.testing.assert_close(got.hess, want, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(got.energy, exact.energy, rtol=0, atol=0)
    torch.testing.assert_close(got.grad, exact.grad, rtol=0, atol=0)
    exact_low = torch.linalg.eigvalsh(exact.hess)[:, 0]
    assert exact_low.min() < -1e-3, "the test needs indefinite Hessians"
    assert torch.linalg.eigvalsh(got.hess)[:, 0].min() > -1e-10
    unchanged = (got.hess == exact.hess).all(2).all(1)
    assert 0 < int(unchanged.sum()) < faces.shape[0], "the test needs triangles with and without compression"
    assert bool((exact_low[unchanged] > -1e-10).all())
    with pytest.raises(ValueError, match="stress_filter"):
        shell.membrane_energy(_dev(x), *args, stress_filter="flip")


def test_float32_kernels_agree_with_float64(device):
    _, x, faces, hinges, rest = _deformed_sheet(5)
    out = {}
    for dtype in (torch.float64, torch.float32):
        xx, r = _dev(x.to(dtype)), [_dev(t.to(dtype)) for t in rest]
        m = shell.membrane_energy(xx, _dev(faces), r[0], r[1], 2.0, 1.0)
        b = shell.bending_energy(xx, _dev(hinges), r[2], r[3], 1.0)
        out[dtype] = [_host(t).double() for t in (*m, *b)]
    for a, b in zip(out[torch.float32], out[torch.float64], strict=True):
        torch.testing.assert_close(a, b, rtol=2e-3, atol=2e-3 * b.abs().max().item())


# ------------------------------------------------------------------------------------------------------------
# IPC barrier and distances
# ------------------------------------------------------------------------------------------------------------


def test_barrier_matches_reference_and_vanishes_beyond_dhat(device):
    dhat = 1e-6
    d = torch.tensor([1e-12, 1e-9, 3e-7, 9.99e-7, 1e-6, 2e-6], dtype=F64)
    b, b1, b2 = _host(ipc_barrier.barrier(_dev(d), dhat))
    torch.testing.assert_close(b, ref.barrier(d, dhat), rtol=1e-12, atol=0)
    db = torch.func.vmap(torch.func.grad(lambda t: ref.barrier(t, dhat)))
    torch.testing.assert_close(b1, db(d), rtol=1e-10, atol=0)
    torch.testing.assert_close(b2, torch.func.vmap(torch.func.grad(lambda t: db(t[None])[0]))(d), rtol=1e-10, atol=0)
    assert (b[:4] > 0).all() and (b1[:4] < 0).all() and (b2[:4] > 0).all()
    assert b[-2:].abs().max() == 0 and b1[-2:].abs().max() == 0 and b2[-2:].abs().max() == 0
    with pytest.raises(ValueError, match="squared activation distance"):
        ipc_barrier.barrier(_dev(d), -1.0)


@needs_ipctk
def test_barrier_matches_ipctk(device):
    dhat = 1e-6
    d = torch.tensor([1e-12, 1e-9, 3e-7, 9.99e-7], dtype=F64)
    b, b1, b2 = _host(ipc_barrier.barrier(_dev(d), dhat))
    for k, dk in enumerate(d.tolist()):
        expect = [ipctk.barrier(dk, dhat), ipctk.barrier_first_derivative(dk, dhat)]
        expect.append(ipctk.barrier_second_derivative(dk, dhat))
        assert [b[k].item(), b1[k].item(), b2[k].item()] == pytest.approx(expect, rel=1e-10, abs=1e-30)


def _random_pt(n: int, seed: int, near: bool) -> torch.Tensor:
    """``[n, 4, 3]`` point-triangle configurations; ``near`` puts points just off the triangle's features."""
    g = torch.Generator().manual_seed(seed)
    q = torch.rand(n, 4, 3, dtype=F64, generator=g) * 2 - 1
    if near:
        t = q[:, 1:]
        bary = torch.rand(n, 3, dtype=F64, generator=g)
        mode = torch.arange(n) % 3
        bary[mode == 1, 0] = 1e-9 * torch.randn(int((mode == 1).sum()), dtype=F64, generator=g)  # near an edge
        bary[mode == 2, 1:] = 1e-9 * torch.rand(int((mode == 2).sum()), 2, dtype=F64, generator=g)  # near a vertex
        bary = bary / bary.sum(1, keepdim=True)
        normal = torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        normal = normal / torch.linalg.norm(normal, dim=1, keepdim=True)
        height = 10 ** (-6 * torch.rand(n, 1, dtype=F64, generator=g)) * torch.sign(torch.randn(n, 1, generator=g))
        q[:, 0] = (bary[:, :, None] * t).sum(1) + height * normal
    return q


def _random_ee(n: int, seed: int, near_parallel: bool) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.rand(n, 4, 3, dtype=F64, generator=g) * 2 - 1
    if near_parallel:
        direction = q[:, 1] - q[:, 0]
        tilt = torch.randn(n, 3, dtype=F64, generator=g) * 10 ** (-8 * torch.rand(n, 1, dtype=F64, generator=g))
        shift = 1e-3 * torch.randn(n, 3, dtype=F64, generator=g) + 0.5 * direction * torch.rand(n, 1, generator=g)
        q[:, 2] = q[:, 0] + shift
        q[:, 3] = q[:, 2] + direction * (0.5 + torch.rand(n, 1, dtype=F64, generator=g)) + tilt
    return q


def _pairs_of(q: torch.Tensor):
    return q.reshape(-1, 3).contiguous(), torch.arange(q.shape[0] * 4, dtype=torch.int32).reshape(-1, 4)


@needs_ipctk
@pytest.mark.parametrize("kind", ["point_triangle", "edge_edge"])
@pytest.mark.parametrize("near", [False, True])
def test_distances_match_ipctk(device, kind, near):
    q = _random_pt(300, 7, near) if kind == "point_triangle" else _random_ee(300, 8, near)
    fn = ipc_barrier.point_triangle_distance if kind == "point_triangle" else ipc_barrier.edge_edge_distance
    name = "point_triangle_distance" if kind == "point_triangle" else "edge_edge_distance"
    dist_fn, grad_fn, hess_fn, type_fn = (getattr(ipctk, name + end) for end in ("", "_gradient", "_hessian", "_type"))
    x, pairs = _pairs_of(q)
    types, terms = fn(_dev(x), _dev(pairs))
    types, terms = _host(types), _host(terms)
    brute = torch.func.vmap(ref.point_triangle_sq_distance if kind == "point_triangle" else ref.edge_edge_sq_distance)
    torch.testing.assert_close(terms.energy, brute(q), rtol=1e-9, atol=1e-20)
    agree = 0
    for k, qk in enumerate(q.numpy()):
        d = dist_fn(*qk)
        # near-parallel edges: ipctk's parallel branch may report an end-point distance slightly above the minimum
        assert terms.energy[k].item() <= d * (1 + 1e-9) + 1e-20
        assert terms.energy[k].item() == pytest.approx(d, rel=1e-7 if not near else 1e-4, abs=1e-20)
        if int(type_fn(*qk)) == types[k].item():
            agree += 1
            g = torch.from_numpy(grad_fn(*qk)).reshape(4, 3)
            torch.testing.assert_close(terms.grad[k], g, rtol=1e-6, atol=1e-9 * max(1.0, g.abs().max().item()))
            h = torch.from_numpy(hess_fn(*qk))
            torch.testing.assert_close(terms.hess[k], h, rtol=1e-5, atol=1e-7 * max(1.0, h.abs().max().item()))
    # generic configurations classify identically; near features and near-parallel lines may legitimately
    # pick the neighbouring type (same distance), but most still agree
    assert agree >= (300 if not near else 150)


@pytest.mark.parametrize("kind", ["point_triangle", "edge_edge"])
@pytest.mark.parametrize("near", [False, True])
def test_distance_values_equal_the_distances_of_the_derivative_kernels(device, kind, near):
    """The value-only distance kernels (the solver's statistics) give the derivative kernels' distances, of every
    closest-feature type (near-parallel edges among them)."""
    q = _random_pt(300, 11, near) if kind == "point_triangle" else _random_ee(300, 12, near)
    x, pairs = _pairs_of(q)
    x, pairs = _dev(x), _dev(pairs)
    full = ipc_barrier.point_triangle_distance if kind == "point_triangle" else ipc_barrier.edge_edge_distance
    value = (
        ipc_barrier.point_triangle_distance_value if kind == "point_triangle" else ipc_barrier.edge_edge_distance_value
    )
    kinds, terms = full(x, pairs)
    assert len(set(kinds.tolist())) >= (2 if near else 3)
    # one code path against another: CUDA fuses multiply-adds differently per kernel, and near-contact distances
    # (down to 1e-8 of the coordinates' squares) cancel digits: 6e-11 relative seen on an H100
    torch.testing.assert_close(value(x, pairs), terms.energy, rtol=1e-9, atol=1e-20)
    assert value(x, pairs[:0]).shape == (0,)


@pytest.mark.parametrize("kind", ["point_triangle", "edge_edge"])
def test_distances_match_brute_force_reference(device, kind):
    q = _random_pt(60, 9, False) if kind == "point_triangle" else _random_ee(60, 10, False)
    x, pairs = _pairs_of(q)
    fn = ipc_barrier.point_triangle_distance if kind == "point_triangle" else ipc_barrier.edge_edge_distance
    rfn = ref.point_triangle_distance if kind == "point_triangle" else ref.edge_edge_distance
    _, terms = fn(_dev(x), _dev(pairs))
    terms = _host(terms)
    d, g, h = rfn(x, pairs)
    torch.testing.assert_close(terms.energy, d, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(terms.grad, g, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(terms.hess, h, rtol=1e-7, atol=1e-8)


def _contact_configs(seed: int, dhat: float):
    """Point-triangle and edge-edge pairs within ``√d̂`` of contact, including near-parallel edges."""
    g = torch.Generator().manual_seed(seed)
    r = math.sqrt(dhat)
    pt = _random_pt(24, seed, False)
    t = pt[:, 1:]
    normal = torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    normal = normal / torch.linalg.norm(normal, dim=1, keepdim=True)
    bary = torch.rand(24, 3, dtype=F64, generator=g) + torch.tensor([0.0, 0.0, 0.0], dtype=F64)
    bary[12:, 0] = -0.2 * r  # just outside an edge: point-edge and point-vertex types
    bary = bary / bary.sum(1, keepdim=True)
    height = r * (0.05 + 0.9 * torch.rand(24, 1, dtype=F64, generator=g))
    pt[:, 0] = (bary[:, :, None] * t).sum(1) + height * normal
    ee = _random_ee(24, seed + 1, False)
    da, db = ee[:, 1] - ee[:, 0], ee[:, 3] - ee[:, 2]
    db[12:] = da[12:] + 0.01 * torch.randn(12, 3, dtype=F64, generator=g)  # mollified, nearly parallel
    n = torch.linalg.cross(da, db)
    n = n / torch.linalg.norm(n, dim=1, keepdim=True)
    mid = ee[:, 0] + 0.4 * da
    sep = r * (0.1 + 0.8 * torch.rand(24, 1, dtype=F64, generator=g))
    ee[:, 2] = mid + sep * n - 0.45 * db
    ee[:, 3] = ee[:, 2] + db
    return pt, ee


def _contact_scene(dhat: float):
    pt, ee = _contact_configs(11, dhat)
    x = torch.cat([pt.reshape(-1, 3), ee.reshape(-1, 3)]).contiguous()
    pt_pairs = torch.arange(96, dtype=torch.int32).reshape(-1, 4)
    ee_pairs = pt_pairs + 96
    stretch = torch.tensor([1.0, 1.3], dtype=F64)[:, None]  # rest edges 30% longer at their far end
    rest = torch.cat([x[:96], (x[96:].reshape(-1, 2, 3) * stretch).reshape(-1, 3)])
    eps_x = _host(ipc_barrier.edge_edge_mollifier_threshold(_dev(rest), _dev(ee_pairs)))
    return pt, ee, x, rest, pt_pairs, ee_pairs, eps_x


@needs_ipctk
def test_contact_energy_matches_ipctk(device):
    dhat, kappa = 1e-4, 1e3
    pt, ee, x, rest, pt_pairs, ee_pairs, eps_x = _contact_scene(dhat)
    a, b = _host(contact.contact_energy(_dev(x), _dev(pt_pairs), _dev(ee_pairs), _dev(eps_x), dhat, kappa))
    for k, qk in enumerate(ee.numpy()):
        expect_eps = ipctk.edge_edge_mollifier_threshold(*(rest[96 + 4 * k : 100 + 4 * k].numpy()))
        assert eps_x[k].item() == pytest.approx(expect_eps, rel=1e-12)
        m = ipctk.edge_edge_mollifier(*qk, expect_eps)
        expect = kappa * m * ipctk.barrier(ipctk.edge_edge_distance(*qk), dhat)
        assert b.energy[k].item() == pytest.approx(expect, rel=1e-8)
    assert sum(ipctk.edge_edge_mollifier(*qk, eps_x[k].item()) < 1 for k, qk in enumerate(ee.numpy())) >= 6
    for k, qk in enumerate(pt.numpy()):
        expect = kappa * ipctk.barrier(ipctk.point_triangle_distance(*qk), dhat)
        assert a.energy[k].item() == pytest.approx(expect, rel=1e-8)


def test_contact_terms_of_no_pairs_are_empty_like_the_reference(device):
    """The solver passes only the active pairs, so one kind often has none: kernels and references alike give empty
    energies ``[0]``, gradients ``[0, 4, 3]`` and Hessians ``[0, 12, 12]``."""
    dhat, kappa = 1e-4, 1e3
    _, _, x, _, pt_pairs, ee_pairs, eps_x = _contact_scene(dhat)
    kernel = _host(
        contact.contact_energy(_dev(x), _dev(pt_pairs[:0]), _dev(ee_pairs[:1]), _dev(eps_x[:1]), dhat, kappa)
    )
    reference = (
        ref.point_triangle_barrier(x, pt_pairs[:0], dhat, kappa),
        ref.edge_edge_barrier(x, ee_pairs[:0], eps_x[:0], dhat, kappa),
    )
    for got in (kernel[0], *reference):
        assert [tuple(t.shape) for t in got] == [(0,), (0, 4, 3), (0, 12, 12)]
    assert kernel[1].energy.shape == (1,)


def test_contact_energy_matches_reference_and_finite_differences(device):
    dhat, kappa = 1e-4, 1e3
    pt, ee, x, rest, pt_pairs, ee_pairs, eps_x = _contact_scene(dhat)
    a, b = _host(contact.contact_energy(_dev(x), _dev(pt_pairs), _dev(ee_pairs), _dev(eps_x), dhat, kappa))
    assert (a.energy > 0).all() and (b.energy > 0).all()
    assert (torch.func.vmap(ref.edge_edge_mollifier)(ee, eps_x) < 1).sum() >= 6, "some pairs must be mollified"
    for got, (energy, grad, hess) in (
        (a, ref.point_triangle_barrier(x, pt_pairs, dhat, kappa)),
        (b, ref.edge_edge_barrier(x, ee_pairs, eps_x, dhat, kappa)),
    ):
        torch.testing.assert_close(got.energy, energy, rtol=1e-9, atol=0)
        torch.testing.assert_close(got.grad, grad, rtol=1e-7, atol=1e-9 * grad.abs().max().item())
        torch.testing.assert_close(got.hess, hess, rtol=1e-6, atol=1e-8 * hess.abs().max().item())
    # Hessian of one mollified edge-edge pair against differences of the kernel gradient
    k = 15
    cols = (ee_pairs[k].long()[:, None] * 3 + torch.arange(3)).reshape(-1)

    def pair_grad(xx):
        out = contact.contact_energy(
            _dev(xx), _dev(pt_pairs[:0]), _dev(ee_pairs[k : k + 1]), _dev(eps_x[k : k + 1]), dhat, kappa
        )
        return _host(out[1].grad[0]).reshape(-1)

    fd = _fd_grad(pair_grad, x, h=1e-9)[:, cols]
    torch.testing.assert_close(b.hess[k], fd, rtol=1e-4, atol=1e-5 * b.hess[k].abs().max().item())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_energy_values_equal_the_energies_of_the_derivative_kernels(device, dtype):
    """The energy-only kernels of the line search give the energies of the full kernels: membrane and bending on a
    deformed sheet, every point-triangle and edge-edge distance type (mollified pairs among them), pairs beyond d̂."""
    x_rest, x, faces, hinges, rest = _deformed_sheet(3)
    xx = _dev(x.to(dtype))
    r = [_dev(t.to(dtype)) for t in rest]

    def same(got, want):
        """Equal up to the rounding of one code path against another (CUDA fuses multiply-adds per kernel). In
        float32, strains and gaps of about 1e-2 cancel two of its seven digits before they are squared, so the two
        paths agree to about 1e-5 (2.2e-5 seen on an H100): compared at 1e-4, with a floor of 1e-5 of the largest
        element energy."""
        if dtype == torch.float64:
            torch.testing.assert_close(got, want, rtol=1e-13, atol=0.0)
        else:
            torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5 * float(want.abs().max()))

    m = shell.membrane_energy(xx, _dev(faces), r[0], r[1], 2.0, 0.7)
    same(shell.membrane_energy_value(xx, _dev(faces), r[0], r[1], 2.0, 0.7), m.energy)
    b = shell.bending_energy(xx, _dev(hinges), r[2], r[3], 0.3)
    same(shell.bending_energy_value(xx, _dev(hinges), r[2], r[3], 0.3), b.energy)
    assert bool((m.energy > 0).all()) and bool((b.energy > 0).any())
    dhat, kappa = 1e-4, 1e3
    pt, ee, x, rest_x, pt_pairs, ee_pairs, eps_x = _contact_scene(dhat)
    args = (_dev(x.to(dtype)), _dev(pt_pairs), _dev(ee_pairs), _dev(eps_x.to(dtype)))
    beyond = 0
    for d in (dhat, dhat / 4):  # the smaller d̂ leaves some pairs beyond it
        full = contact.contact_energy(*args, d, kappa)
        values = contact.contact_energy_value(*args, d, kappa)
        for got, want in zip(values, full, strict=True):
            same(got, want.energy)
            beyond += int((want.energy == 0).sum())
    assert 0 < beyond < 2 * pt_pairs.shape[0]
    assert contact.contact_energy_value(*args[:1], _dev(pt_pairs[:0]), _dev(ee_pairs[:0]), args[3][:0], dhat, 1.0)[
        0
    ].shape == (0,)


# ------------------------------------------------------------------------------------------------------------
# Additive CCD
# ------------------------------------------------------------------------------------------------------------


def _colliding(kind: str, n: int, seed: int):
    """Trajectories that touch at some ``t* ∈ (0.2, 0.8)``: ``(q0 [n, 4, 3], dq [n, 4, 3])``."""
    g = torch.Generator().manual_seed(seed)
    q = torch.rand(n, 4, 3, dtype=F64, generator=g) * 2 - 1
    s = 0.2 + 0.6 * torch.rand(n, 3, 1, dtype=F64, generator=g)
    if kind == "point_triangle":
        bary = torch.rand(n, 3, 1, dtype=F64, generator=g)
        q[:, 0] = (bary / bary.sum(1, keepdim=True) * q[:, 1:]).sum(1)
    else:
        hit = q[:, 0] + s[:, 0] * (q[:, 1] - q[:, 0])
        db = q[:, 3] - q[:, 2]
        q[:, 2] = hit - s[:, 1] * db
        q[:, 3] = q[:, 2] + db
    dq = 0.5 * torch.randn(n, 4, 3, dtype=F64, generator=g)
    t_star = s[:, 2:]  # [n, 1, 1]
    return q - t_star * dq, dq


def _ccd(kind, q0, dq, **kw):
    x, pairs = _pairs_of(q0)
    fn = ccd.point_triangle_ccd if kind == "point_triangle" else ccd.edge_edge_ccd
    return _host(fn(_dev(x), _dev(dq.reshape(-1, 3)), _dev(pairs), **kw))


@pytest.mark.parametrize("kind", ["point_triangle", "edge_edge"])
def test_ccd_is_conservative_and_separating(device, kind):
    q0, dq = _colliding(kind, 64, 12 if kind == "point_triangle" else 13)
    toi = _ccd(kind, q0, dq)
    first = ref.point_triangle_first_contact if kind == "point_triangle" else ref.edge_edge_first_contact
    dist = ref.point_triangle_sq_distance if kind == "point_triangle" else ref.edge_edge_sq_distance
    for k in range(q0.shape[0]):
        t_true = first(q0[k].numpy(), dq[k].numpy())
        assert t_true < 0.8 + 1e-9, "the trajectory was built to touch by t*"
        assert 0.0 < toi[k].item() <= t_true
        assert dist(q0[k] + toi[k] * dq[k]).item() > 0.0
        if ipctk is not None:
            narrow = ipctk.AdditiveCCD()
            narrow_fn = narrow.point_triangle_ccd if kind == "point_triangle" else narrow.edge_edge_ccd
            assert narrow_fn(*q0[k].numpy(), *(q0[k] + dq[k]).numpy())[0], "ipctk's additive CCD agrees on a hit"
    # not needlessly early: on average the step reaches most of the way to contact
    t_true = torch.tensor([first(q0[k].numpy(), dq[k].numpy()) for k in range(q0.shape[0])], dtype=F64)
    assert (toi / t_true).median() > 0.5


def test_ccd_straight_approach_and_separation(device):
    # a point falls straight onto a static triangle from h = 0.2 at speed 1 (per step)
    q0 = torch.tensor([[[0.2, 0.2, 0.2], [0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=F64)
    dq = torch.zeros_like(q0)
    dq[0, 0, 2] = -1.0
    toi = _ccd("point_triangle", q0, dq).item()
    assert 0.85 * 0.2 <= toi <= 0.2
    toi_xi = _ccd("point_triangle", q0, dq, min_distance=0.05).item()
    assert 0.85 * 0.15 <= toi_xi <= 0.15
    assert ref.point_triangle_sq_distance(q0[0] + toi_xi * dq[0]).item() > 0.05**2
    # moving apart, or not moving at all, never collides
    assert _ccd("point_triangle", q0, -dq).item() == 1.0
    assert _ccd("point_triangle", q0, torch.zeros_like(dq)).item() == 1.0
    # crossing edges: ea along x at z = 0, eb along y at z = 0.1 falling at 0.5 per step
    q0 = torch.tensor([[[-1, 0, 0], [1, 0, 0], [0, -1, 0.1], [0, 1, 0.1]]], dtype=F64)
    dq = torch.zeros_like(q0)
    dq[0, 2:, 2] = -0.5
    toi = _ccd("edge_edge", q0, dq).item()
    assert 0.85 * 0.2 <= toi <= 0.2
    assert _ccd("edge_edge", q0, -dq).item() == 1.0


def test_ccd_float32_stays_conservative(device):
    q0, dq = _colliding("point_triangle", 32, 14)
    x, pairs = _pairs_of(q0)
    toi = _host(ccd.point_triangle_ccd(_dev(x.float()), _dev(dq.reshape(-1, 3).float()), _dev(pairs)))
    for k in range(q0.shape[0]):
        assert 0.0 < toi[k].item() <= ref.point_triangle_first_contact(q0[k].numpy(), dq[k].numpy()) + 1e-6


# ------------------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------------------


def test_bad_input_raises_clear_errors(device):
    x_rest, _, faces, hinges, rest = _deformed_sheet()
    x = _dev(x_rest)
    with pytest.raises(ValueError, match=r"int32 \[N, 3\].*\.to\(torch\.int32\)"):
        shell.membrane_energy(x, _dev(faces.long()), _dev(rest.rest_inv), _dev(rest.rest_area), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"positions must be a float32 or float64 \[V, 3\]"):
        shell.membrane_energy(x[:, :2].contiguous(), _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"rest_area is torch.float32 but positions are torch.float64"):
        shell.membrane_energy(x, _dev(faces), _dev(rest.rest_inv), _dev(rest.rest_area.float()), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"rest_angle must have shape"):
        shell.bending_energy(x, _dev(hinges), _dev(rest.rest_angle[:-1]), _dev(rest.rest_weight), 1.0)
    with pytest.raises(ValueError, match="k_bend"):
        shell.bending_energy(x, _dev(hinges), _dev(rest.rest_angle), _dev(rest.rest_weight), -1.0)
    pairs = _dev(torch.zeros(1, 4, dtype=torch.int32))
    with pytest.raises(ValueError, match="eta"):
        ccd.point_triangle_ccd(x, torch.zeros_like(x), pairs, eta=1.5)
    with pytest.raises(ValueError, match="squared activation distance"):
        contact.contact_energy(x, pairs, pairs, _dev(torch.ones(1, dtype=F64)), 0.0, 1.0)
    degenerate = x_rest.clone()
    degenerate[1] = degenerate[0]
    with pytest.raises(ValueError, match="zero area"):
        shell.rest_state(_dev(degenerate), _dev(faces), _dev(hinges))


@pytest.mark.parametrize("split", [1, 2])
def test_pair_boxes_overlap_matches_the_reference(device, split):
    """The swept-box test of contact pairs agrees with the torch boxes exactly, at rest and over a sweep."""
    g = torch.Generator().manual_seed(split)
    x = (0.05 * torch.rand(200, 3, generator=g, dtype=torch.float64)).to(device)
    dx = (0.01 * torch.randn(200, 3, generator=g, dtype=torch.float64)).to(device)
    pairs = torch.randint(0, 200, (3000, 4), generator=g, dtype=torch.int32).to(device)
    for sweep in (None, dx):
        for dhat in (1e-3, 5e-3):
            got = contact.pair_boxes_overlap(x, sweep, pairs, split, dhat)
            want = ref.pair_boxes_overlap(x, sweep, pairs, split, dhat)
            assert got.dtype == torch.bool
            assert torch.equal(got, want)
            assert 0 < int(got.sum()) < pairs.shape[0]  # both outcomes occur
    assert contact.pair_boxes_overlap(x, None, pairs[:0], split, 1e-3).shape == (0,)
    with pytest.raises(ValueError, match="split"):
        contact.pair_boxes_overlap(x, None, pairs, 3, 1e-3)
    with pytest.raises(ValueError, match="parallel"):
        contact.pair_boxes_overlap(x, None, pairs, split, 1e-3, parallel=1.0)


def test_pair_boxes_overlap_drops_edges_parallel_over_the_whole_sweep(device):
    """Edge pairs parallel at both ends of the sweep are rejected, those that turn away at one end kept; the test
    agrees with the torch reference and leaves point-triangle pairs alone."""
    g = torch.Generator().manual_seed(7)
    n = 300
    a0 = 0.05 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    direction = torch.randn(n, 3, generator=g, dtype=torch.float64)
    offset = 2e-4 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    # edge b: edge a shifted by under 0.2 mm on each axis, so that every box overlaps; parallel at the start
    x = torch.cat([a0, a0 + 0.01 * direction, a0 + offset, a0 + offset + 0.01 * direction])
    idx = torch.arange(n, dtype=torch.int32)
    pairs = torch.stack([idx, idx + n, idx + 2 * n, idx + 3 * n], 1)
    dx = torch.zeros_like(x)
    turned = torch.arange(n) % 2 == 1  # every other edge b turns away from parallel during the sweep
    dx[3 * n :][turned] = 0.004 * torch.randn(int(turned.sum()), 3, generator=g, dtype=torch.float64)
    x, dx, pairs = x.to(device), dx.to(device), pairs.to(device)
    got = contact.pair_boxes_overlap(x, dx, pairs, 2, 1e-3, parallel=1e-8)
    assert torch.equal(got, ref.pair_boxes_overlap(x, dx, pairs, 2, 1e-3, parallel=1e-8))
    assert torch.equal(got.cpu(), turned)
    assert bool(contact.pair_boxes_overlap(x, dx, pairs, 2, 1e-3).all())  # parallel=0 keeps them
    assert bool(contact.pair_boxes_overlap(x, dx, pairs, 1, 1e-3, parallel=1e-8).all())
