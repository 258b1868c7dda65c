"""IPC lagged friction kernels (potential, lagged contact data) against their torch references and closed forms."""

import math

import pytest
import torch

from kernels import backend, ipc_barrier
from kernels.friction import friction_potential, lagged_contacts
from kernels.reference import friction as ref

F64 = torch.float64
EPS = 1e-3  # ε_v Δt, m


def _dev(t: torch.Tensor) -> torch.Tensor:
    return t.to(backend.torch_device())


def _projectors(k: int, g: torch.Generator) -> torch.Tensor:
    """``[k, 3, 3]`` tangent projectors ``I − n nᵀ`` of random unit normals."""
    n = torch.nn.functional.normalize(torch.randn(k, 3, dtype=F64, generator=g), dim=1)
    return torch.eye(3, dtype=F64) - n[:, :, None] * n[:, None, :]


def _contacts(seed: int = 0, k: int = 240, still: int = 8):
    """Random contacts whose tangential slip ``y`` spans ``(0, 3ε)``; the first ``still`` have ``y = 0`` exactly.

    Weights are point-triangle-like, ``(1, −a, −b, −c)`` with ``a + b + c = 1``, as the simulator's contacts are.
    Each contact has its own four vertices (so its slip can be set), stored in a shuffled order.
    """
    g = torch.Generator().manual_seed(seed)
    bary = torch.rand(k, 3, dtype=F64, generator=g) + 0.1
    weight = torch.cat([torch.ones(k, 1, dtype=F64), -bary / bary.sum(1, keepdim=True)], dim=1)
    projector = _projectors(k, g)
    force = 0.1 + torch.rand(k, dtype=F64, generator=g)
    direction = torch.randn(k, 4, 3, dtype=F64, generator=g)
    slip = torch.linalg.norm(torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * direction).sum(1)), dim=1)
    target = EPS * torch.linspace(0.02, 3.0, k, dtype=F64)[torch.randperm(k, generator=g)]
    target[:still] = 0.0
    order = torch.randperm(4 * k, generator=g)
    displacement = torch.empty(4 * k, 3, dtype=F64)
    displacement[order] = (direction * (target / slip)[:, None, None]).reshape(-1, 3)
    return displacement, order.reshape(k, 4), weight, projector, force


def _relative_error(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got.cpu() - want.cpu()).abs().max() / want.cpu().abs().max())


@pytest.mark.parametrize("hessian", [True, False])
@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
def test_matches_the_torch_reference(device, hessian, index_dtype):
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts())
    index = index.to(index_dtype)
    energy, grad, hess = friction_potential(displacement, index, weight, projector, force, EPS, hessian)
    want = ref.friction_potential(displacement, index, weight, projector, force, EPS, hessian)

    slip = torch.linalg.norm(
        torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * displacement[index.long()]).sum(1)), dim=1
    )
    assert int((slip == 0).sum()) == 8 and int((slip > EPS).sum()) > 60 and int((slip < EPS).sum()) > 60
    assert energy.shape == (240,) and grad.shape == (240, 4, 3)
    assert energy.dtype == grad.dtype == F64 and energy.device == displacement.device
    assert _relative_error(energy, want[0]) < 1e-12
    assert _relative_error(grad, want[1]) < 1e-12
    if hessian:
        assert hess.shape == (240, 12, 12)
        assert bool(torch.isfinite(hess).all())
        assert _relative_error(hess, want[2]) < 1e-12
    else:
        assert hess is None


def test_zero_slip_closed_form(device):
    """At ``y = 0``: energy ``μλ ε/3``, zero gradient, Hessian ``w_i w_j μλ (2/ε) P`` (the ``u uᵀ`` term vanishes)."""
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts(seed=3, k=8, still=8))
    energy, grad, hess = friction_potential(displacement, index, weight, projector, force, EPS, True)
    torch.testing.assert_close(energy, force * EPS / 3.0, rtol=1e-14, atol=0.0)
    assert bool((grad == 0).all())
    blocks = (2.0 / EPS) * force[:, None, None, None, None] * weight[:, :, None, None, None]
    blocks = blocks * weight[:, None, :, None, None] * projector[:, None, None]
    torch.testing.assert_close(hess, blocks.permute(0, 1, 3, 2, 4).reshape(-1, 12, 12), rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize("hessian", [True, False])
def test_no_contacts(device, hessian):
    d = backend.torch_device()
    energy, grad, hess = friction_potential(
        torch.zeros(5, 3, dtype=F64, device=d),
        torch.zeros(0, 4, dtype=torch.int64, device=d),
        torch.zeros(0, 4, dtype=F64, device=d),
        torch.zeros(0, 3, 3, dtype=F64, device=d),
        torch.zeros(0, dtype=F64, device=d),
        EPS,
        hessian,
    )
    assert energy.shape == (0,) and grad.shape == (0, 4, 3)
    assert hess is None if not hessian else hess.shape == (0, 12, 12)


def test_non_contiguous_inputs(device):
    displacement, index, weight, projector, force = (_dev(t) for t in _contacts(seed=5, k=32))
    want = friction_potential(displacement, index, weight, projector, force, EPS, True)
    got = friction_potential(
        displacement.T.contiguous().T, index.T.contiguous().T, weight.T.contiguous().T, projector, force, EPS, True
    )
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)


def test_finite_differences_and_psd(device):
    """Central differences of the kernel's own energy and gradient, on contacts below and above ``ε``."""
    g = torch.Generator().manual_seed(7)
    k = 6
    projector = _projectors(k, g)
    weight = torch.cat([torch.ones(k, 1, dtype=F64), -torch.softmax(torch.randn(k, 3, dtype=F64, generator=g), 1)], 1)
    force = 0.5 + torch.rand(k, dtype=F64, generator=g)
    index = torch.arange(4 * k).reshape(k, 4)
    direction = torch.randn(k, 4, 3, dtype=F64, generator=g)
    slip = torch.linalg.norm(torch.einsum("kab,kb->ka", projector, (weight[:, :, None] * direction).sum(1)), dim=1)
    target = EPS * torch.tensor([0.2, 0.5, 0.8, 1.3, 2.0, 4.0], dtype=F64)  # clear of y = 0 and of y = ε
    displacement = (direction * (target / slip)[:, None, None]).reshape(-1, 3)
    args = [_dev(t) for t in (index, weight, projector, force)]

    def evaluate(x: torch.Tensor):
        return friction_potential(_dev(x), *args, EPS, True)

    _, grad, hess = (t.cpu() for t in evaluate(displacement))
    h = 1e-8
    fd_grad = torch.empty(k, 12, dtype=F64)
    fd_hess = torch.empty(k, 12, 12, dtype=F64)
    for column in range(12):
        plus, minus = displacement.clone().reshape(k, 12), displacement.clone().reshape(k, 12)
        plus[:, column] += h
        minus[:, column] -= h
        e_plus, g_plus, _ = evaluate(plus.reshape(-1, 3))
        e_minus, g_minus, _ = evaluate(minus.reshape(-1, 3))
        fd_grad[:, column] = ((e_plus - e_minus) / (2 * h)).cpu()
        fd_hess[:, :, column] = ((g_plus - g_minus).reshape(k, 12) / (2 * h)).cpu()
    torch.testing.assert_close(grad.reshape(k, 12), fd_grad, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(hess, fd_hess, rtol=1e-6, atol=1e-6 * float(hess.abs().max()))
    torch.testing.assert_close(hess, hess.transpose(1, 2), rtol=0.0, atol=1e-12 * float(hess.abs().max()))
    assert float(torch.linalg.eigvalsh(hess).min()) > -1e-9 * float(hess.abs().max())


def _valid(k: int = 3, n: int = 6) -> dict:
    d = backend.torch_device()
    return {
        "displacement": torch.zeros(n, 3, dtype=F64, device=d),
        "index": torch.zeros(k, 4, dtype=torch.int64, device=d),
        "weight": torch.zeros(k, 4, dtype=F64, device=d),
        "projector": torch.zeros(k, 3, 3, dtype=F64, device=d),
        "force": torch.zeros(k, dtype=F64, device=d),
        "eps": EPS,
        "hessian": True,
    }


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("displacement", lambda a: a.float(), r"displacement must be a float64 \[N, 3\].*to\(torch.float64\)"),
        ("displacement", lambda a: a[:, :2], r"displacement must have shape \[N, 3\]"),
        ("index", lambda a: a.double(), r"index must be an int32 or int64 \[K, 4\]"),
        ("index", lambda a: a[:, :3], r"index must be an int32 or int64 \[K, 4\]"),
        ("weight", lambda a: a[:2], r"weight must have shape \[K, 4\], here \[3, 4\], got \[2, 4\]"),
        ("weight", lambda a: a.float(), r"weight must be a float64"),
        ("projector", lambda a: a.reshape(3, 9), r"projector must have shape \[K, 3, 3\]"),
        ("force", lambda a: a[:, None], r"force must have shape \[K\]"),
        ("force", lambda a: a.to(torch.int64), r"force must be a float64"),
        ("eps", lambda a: 0.0, r"eps \(0.0\) must be a positive finite length"),
        ("eps", lambda a: float("nan"), r"eps \(nan\) must be a positive finite length"),
    ],
)
def test_bad_inputs(device, name, make, message):
    args = _valid()
    args[name] = make(args[name])
    with pytest.raises(ValueError, match=message):
        friction_potential(**args)


def test_inputs_on_another_device(device):
    args = _valid()
    args["force"] = torch.zeros(3, dtype=F64, device="meta")
    with pytest.raises(ValueError, match=r"force is on meta but displacement is on .*move it with"):
        friction_potential(**args)


# ---------------------------------------------------------------------------------------------------------------
# Lagged contact data (closest-point weights, tangent projectors, normal forces)
# ---------------------------------------------------------------------------------------------------------------

DHAT2 = 1e-6  # d̂² for d̂ = 1 mm, m²
KAPPA = 3.0e3  # barrier stiffness, J/m⁴
MU = 0.2
SIDE = 1e-2  # length of the constructed triangles and edges, m


def _rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(seed)))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _point_triangle_scene(frames: int = 3):
    """Point-triangle pairs of every closest-feature type, each once active and once beyond ``d̂``.

    Triangle ``(0, 0, 0), (L, 0, 0), (0, L, 0)``; the points sit just off its features. Frame 0 is as built, the
    others are rigid motions of it. Returns ``(x [V, 3], pairs [P, 4] int32, expected kind [P])``.
    """
    length = SIDE
    spots = [  # (x, y) of the point per type, for an offset δ; height h above the plane
        lambda o: (-o, -o),
        lambda o: (length + o, -0.5 * o),
        lambda o: (-0.5 * o, length + o),
        lambda o: (0.5 * length, -o),
        lambda o: (0.5 * length + o, 0.5 * length + o),
        lambda o: (-o, 0.5 * length),
        lambda o: (length / 3.0, length / 4.0),
    ]
    xs, pairs, kinds = [], [], []
    for frame in range(frames):
        local = [[0.0, 0.0, 0.0], [length, 0.0, 0.0], [0.0, length, 0.0]]
        for kind, spot in enumerate(spots):
            for offset, height in ((3e-4, 2e-4), (1.5e-3, -1e-3)):  # active (d ≤ 2.3e-7 m²), then beyond d̂
                local.append([*spot(offset), height])
                kinds.append(kind)
        local = torch.tensor(local, dtype=F64)
        if frame:
            local = local @ _rotation(frame).T + torch.randn(
                3, dtype=F64, generator=torch.Generator().manual_seed(frame)
            )
        base = sum(len(v) for v in xs)
        xs.append(local)
        pairs += [[base + 3 + i, base, base + 1, base + 2] for i in range(len(local) - 3)]
    return torch.cat(xs), torch.tensor(pairs, dtype=torch.int32), torch.tensor(kinds, dtype=torch.int32)


def _edge_edge_scene(frames: int = 3):
    """Edge-edge pairs of every closest-feature type, near-parallel ones under the mollifier threshold included.

    Edge a runs from ``(0, 0, 0)`` to ``(L, 0, 0)``; each edge b lies just off one of its features. Every
    configuration comes once active and once beyond ``d̂``. Frame 0 is as built and also holds an exactly parallel
    pair (zero mollifier); the others are rigid motions. Returns ``(x, pairs, expected kind, ε_x [Q])``.
    """
    length = SIDE

    def configs(o: float, h: float):
        return [  # (eb0, eb1, kind)
            ((-o, -o, h), (-o - 0.6 * length, -o - 0.8 * length, h), 0),
            ((-o - 0.6 * length, -o - 0.8 * length, h), (-o, -o, h), 1),
            ((length + o, -o, h), (length + o + 0.6 * length, -o - 0.8 * length, h), 2),
            ((length + o + 0.6 * length, -o - 0.8 * length, h), (length + o, -o, h), 3),
            ((0.5 * length, -o, h), (0.5 * length, -o - length, h + 0.5 * length), 4),
            ((0.5 * length, -o - length, h + 0.5 * length), (0.5 * length, -o, h), 5),
            ((-o, -0.5 * length, h), (-o, 0.5 * length, h), 6),
            ((length + o, -0.5 * length, h), (length + o, 0.5 * length, h), 7),
            ((0.5 * length, -0.5 * length, h), (0.5 * length, 0.5 * length, h), 8),
            # nearly parallel, sin² = 1e-4 (threshold 1e-3), crossing over edge a in projection
            ((0.2 * length, 2e-5, h), (1.2 * length, 2e-5 - 0.01 * length, h), 8),
            # sin² = 1e-6, beside edge a: eb0 against it
            ((0.3 * length, o, h), (1.3 * length, o + 1e-3 * length, h), 4),
        ]

    xs, pairs, kinds = [], [], []
    for frame in range(frames):
        local = [[0.0, 0.0, 0.0], [length, 0.0, 0.0]]
        for o, h in ((2e-4, 2e-4), (1e-3, 1e-3)):  # active (d ≤ 8e-8 m²), then beyond d̂
            for eb0, eb1, kind in configs(o, h):
                local += [list(eb0), list(eb1)]
                kinds.append(kind)
            if frame == 0:  # exactly parallel, sin² = 0: the end point–segment distance of ea1
                local += [[0.3 * length, o, h], [1.3 * length, o, h]]
                kinds.append(7)
        local = torch.tensor(local, dtype=F64)
        if frame:
            local = local @ _rotation(10 + frame).T + torch.rand(
                3, dtype=F64, generator=torch.Generator().manual_seed(frame)
            )
        base = sum(len(v) for v in xs)
        xs.append(local)
        pairs += [[base, base + 1, base + 2 + 2 * i, base + 3 + 2 * i] for i in range((len(local) - 2) // 2)]
    x, pairs = torch.cat(xs), torch.tensor(pairs, dtype=torch.int32)
    return x, pairs, torch.tensor(kinds, dtype=torch.int32), ipc_barrier.edge_edge_mollifier_threshold(x, pairs)


def _random_scene(seed: int, pt: int = 400, ee: int = 400, vertices: int = 300):
    """Random pairs over ``vertices`` shared points in a 3 mm cube at 1 m from the origin (~half within ``d̂``)."""
    g = torch.Generator().manual_seed(seed)
    x = 1.0 + 3e-3 * torch.rand(vertices, 3, dtype=F64, generator=g)

    def pairs(k: int) -> torch.Tensor:
        return torch.argsort(torch.rand(k, vertices, generator=g), dim=1)[:, :4].to(torch.int32)

    ee_pairs = pairs(ee)
    return x, pairs(pt), ee_pairs, ipc_barrier.edge_edge_mollifier_threshold(x, ee_pairs)


def _lagged_both(x, pt_pairs, ee_pairs, eps_x, dhat2=DHAT2):
    args = [_dev(t).contiguous() for t in (x, pt_pairs, ee_pairs, eps_x)]
    got = lagged_contacts(*args, dhat2, KAPPA, MU)
    want = ref.lagged_contacts(*args, dhat2, KAPPA, MU)
    return got, want


def _assert_matches(got, want, rtol: float = 1e-10):
    index, weight, projector, force = got
    assert index.dtype == torch.int64 and weight.dtype == projector.dtype == force.dtype == F64
    k = want[0].shape[0]
    assert index.shape == (k, 4) and weight.shape == (k, 4) and projector.shape == (k, 3, 3) and force.shape == (k,)
    assert torch.equal(index.cpu(), want[0].cpu())
    for a, b in zip(got[1:], want[1:], strict=True):
        assert a.device == b.device
        if k:
            assert _relative_error(a, b) < rtol
    # each force to rtol, down to the cancellation noise of the mollifier of (nearly) parallel edges, where CUDA's
    # fused multiply-adds round differently from the CPU's
    scale = float(want[3].abs().max()) if k else 0.0
    torch.testing.assert_close(force, want[3], rtol=rtol, atol=1e-14 * scale)


def _active(x, pt_pairs, ee_pairs) -> torch.Tensor:
    d_pt = ipc_barrier.point_triangle_distance(_dev(x), _dev(pt_pairs))[1].energy.cpu()
    d_ee = ipc_barrier.edge_edge_distance(_dev(x), _dev(ee_pairs))[1].energy.cpu()
    return torch.cat([d_pt, d_ee]) < DHAT2


def test_lagged_contacts_cover_every_closest_feature_type(device):
    x_pt, pt_pairs, pt_kinds = _point_triangle_scene()
    x_ee, ee_pairs, ee_kinds, eps_x = _edge_edge_scene()
    assert torch.equal(ipc_barrier.point_triangle_distance(_dev(x_pt), _dev(pt_pairs))[0].cpu(), pt_kinds)
    assert torch.equal(ipc_barrier.edge_edge_distance(_dev(x_ee), _dev(ee_pairs))[0].cpu(), ee_kinds)
    # both kinds of pairs in one position array
    x = torch.cat([x_pt, x_ee])
    ee_pairs = ee_pairs + x_pt.shape[0]
    active = _active(x, pt_pairs, ee_pairs)
    kinds = torch.cat([pt_kinds, ee_kinds + 7])
    assert set(kinds[active].tolist()) == set(range(16)) and set(kinds[~active].tolist()) == set(range(16))
    q = x[ee_pairs.long()]
    sin2 = (torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]) ** 2).sum(1) / eps_x * 1e-3
    assert int(((sin2 < 1e-3) & active[pt_pairs.shape[0] :]).sum()) >= 7  # mollified pairs, one exactly parallel

    got, want = _lagged_both(x, pt_pairs, ee_pairs, eps_x)
    _assert_matches(got, want)
    rows = torch.cat([pt_pairs, ee_pairs]).long()
    assert torch.equal(got[0].cpu(), rows[active])  # active pairs only, point-triangle first, in input order
    force = got[3].cpu()
    parallel = int(active[: pt_pairs.shape[0] + 11].sum())  # frame 0's exactly parallel pair: its mollifier is 0
    assert float(force[parallel]) == 0.0
    assert bool((force[:parallel] > 0).all()) and bool((force[parallel + 1 :] > 0).all())


def test_lagged_contacts_match_the_reference_on_random_pairs(device):
    x, pt_pairs, ee_pairs, eps_x = _random_scene(seed=1)
    active = _active(x, pt_pairs, ee_pairs)
    assert 200 < int(active.sum()) < 700
    kinds = torch.cat(
        [
            ipc_barrier.point_triangle_distance(_dev(x), _dev(pt_pairs))[0].cpu(),
            ipc_barrier.edge_edge_distance(_dev(x), _dev(ee_pairs))[0].cpu() + 7,
        ]
    )
    assert set(kinds[active].tolist()) == set(range(16))
    got, want = _lagged_both(x, pt_pairs, ee_pairs, eps_x)
    _assert_matches(got, want)
    rows = torch.cat([pt_pairs, ee_pairs]).long()
    assert torch.equal(got[0].cpu(), rows[active])


def test_lagged_contacts_closed_forms(device):
    """A point over a face and two crossing edges at height ``h``: ``n = ±e_z``, ``μλ = −μ κ b′(h²) 2h``."""
    h = 3e-4
    x = torch.tensor(
        [[0.0, 0.0, 0.0], [SIDE, 0.0, 0.0], [0.0, SIDE, 0.0], [0.002, 0.003, h], [0.004, -0.005, h], [0.004, 0.005, h]],
        dtype=F64,
    )
    pt_pairs = torch.tensor([[3, 0, 1, 2]], dtype=torch.int32)
    ee_pairs = torch.tensor([[0, 1, 4, 5]], dtype=torch.int32)
    eps_x = ipc_barrier.edge_edge_mollifier_threshold(x, ee_pairs)
    index, weight, projector, force = (
        t.cpu() for t in lagged_contacts(*map(_dev, (x, pt_pairs, ee_pairs, eps_x)), DHAT2, KAPPA, MU)
    )
    d = h * h
    b1 = (DHAT2 - d) * (2.0 * math.log(d / DHAT2) - DHAT2 / d + 1.0)
    torch.testing.assert_close(force, torch.full((2,), -MU * KAPPA * b1 * 2.0 * h, dtype=F64), rtol=1e-12, atol=0.0)
    tangent = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    torch.testing.assert_close(projector, tangent.expand(2, 3, 3), rtol=0.0, atol=1e-12)
    torch.testing.assert_close(weight[0], torch.tensor([1.0, -0.5, -0.2, -0.3], dtype=F64), rtol=0.0, atol=1e-12)
    torch.testing.assert_close(weight[1], torch.tensor([0.6, 0.4, -0.5, -0.5], dtype=F64), rtol=0.0, atol=1e-12)
    assert index.tolist() == [[3, 0, 1, 2], [0, 1, 4, 5]]


@pytest.mark.parametrize("which", ["point_triangle", "edge_edge"])
def test_weights_give_the_closest_point_difference(device, which):
    """``‖Σ w_i q_i‖²`` is the squared distance of the pair, for the reference's weights and the kernel's."""
    x, pt_pairs, ee_pairs, eps_x = _random_scene(seed=2, pt=300, ee=300)
    x_pt, pt_c, _ = _point_triangle_scene(frames=2)
    x_ee, ee_c, _, eps_c = _edge_edge_scene(frames=2)
    if which == "point_triangle":
        x, pairs = torch.cat([x, x_pt]), torch.cat([pt_pairs, pt_c + x.shape[0]])
        ee_pairs, eps_x = ee_pairs[:0], eps_x[:0]
        kind, terms = ipc_barrier.point_triangle_distance(_dev(x), _dev(pairs))
        weight = ref.point_triangle_weights(_dev(x)[_dev(pairs).long()], kind)
        lagged = lagged_contacts(*map(_dev, (x, pairs, ee_pairs, eps_x)), DHAT2, KAPPA, MU)
    else:
        x, pairs = torch.cat([x, x_ee]), torch.cat([ee_pairs, ee_c + x.shape[0]])
        eps_x = torch.cat([eps_x, eps_c])
        kind, terms = ipc_barrier.edge_edge_distance(_dev(x), _dev(pairs))
        weight = ref.edge_edge_weights(_dev(x)[_dev(pairs).long()], kind)
        lagged = lagged_contacts(*map(_dev, (x, pt_pairs[:0], pairs, eps_x)), DHAT2, KAPPA, MU)
    d = terms.energy.cpu()
    gap = (weight.cpu()[:, :, None] * x[pairs.long()]).sum(1)
    torch.testing.assert_close((gap * gap).sum(1), d, rtol=1e-8, atol=1e-20)
    index, weight, _, _ = (t.cpu() for t in lagged)
    gap = (weight[:, :, None] * x[index]).sum(1)
    active = d < DHAT2
    assert index.shape[0] == int(active.sum()) > 100
    torch.testing.assert_close((gap * gap).sum(1), d[active], rtol=1e-8, atol=1e-20)


@pytest.mark.parametrize(("pt", "ee"), [(0, 0), (5, 0), (0, 5), (5, 5)])
def test_lagged_contacts_empty(device, pt, ee):
    """No pairs of one kind or both, and pairs that are all beyond ``d̂``, give correctly shaped results."""
    x, pt_pairs, ee_pairs, eps_x = _random_scene(seed=3, pt=pt, ee=ee)
    got, want = _lagged_both(x, pt_pairs, ee_pairs, eps_x)
    _assert_matches(got, want)
    assert got[0].shape[0] == int(_active(x, pt_pairs, ee_pairs).sum())
    got, want = _lagged_both(x, pt_pairs, ee_pairs, eps_x, dhat2=1e-12)  # nothing within 1 µm
    _assert_matches(got, want)
    assert [tuple(t.shape) for t in got] == [(0, 4), (0, 4), (0, 3, 3), (0,)]
    assert got[0].dtype == torch.int64 and got[1].dtype == F64


def _valid_lagged() -> dict:
    d = backend.torch_device()
    return {
        "x": torch.zeros(6, 3, dtype=F64, device=d),
        "pt_pairs": torch.zeros(2, 4, dtype=torch.int32, device=d),
        "ee_pairs": torch.zeros(3, 4, dtype=torch.int32, device=d),
        "ee_eps_x": torch.ones(3, dtype=F64, device=d),
        "dhat2": DHAT2,
        "stiffness": KAPPA,
        "mu": MU,
    }


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("x", lambda a: a.float(), r"positions must be float64 here, got torch.float32.*to\(torch.float64\)"),
        ("x", lambda a: a[:, :2], r"positions must be a float32 or float64 \[V, 3\] tensor"),
        ("x", lambda a: a.T.contiguous().T, r"positions are not contiguous"),
        ("pt_pairs", lambda a: a.long(), r"pt_pairs must be an int32 \[N, 4\] tensor.*to\(torch.int32\)"),
        ("ee_pairs", lambda a: a[:, :3], r"ee_pairs must be an int32 \[N, 4\] tensor"),
        ("ee_pairs", lambda a: a.T.contiguous().T, r"ee_pairs is not contiguous"),
        ("ee_eps_x", lambda a: a[:2], r"ee_eps_x must have shape \[3\], got \[2\]"),
        ("ee_eps_x", lambda a: a.float(), r"ee_eps_x is torch.float32 but positions are torch.float64"),
        ("ee_eps_x", lambda a: a.to("meta"), r"ee_eps_x is on meta but x is on .*move it with"),
        ("dhat2", lambda a: 0.0, r"dhat2 \(0.0\) must be a positive finite squared activation distance"),
        ("dhat2", lambda a: float("inf"), r"dhat2 \(inf\) must be a positive finite"),
        ("stiffness", lambda a: -1.0, r"stiffness \(-1.0\) must be a finite non-negative number"),
        ("mu", lambda a: float("nan"), r"mu \(nan\) must be a finite non-negative number"),
    ],
)
def test_lagged_contacts_bad_inputs(device, name, make, message):
    args = _valid_lagged()
    args[name] = make(args[name])
    with pytest.raises(ValueError, match=message):
        lagged_contacts(**args)
