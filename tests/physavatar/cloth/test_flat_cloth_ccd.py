"""Edge-edge distance and CCD of flat and coplanar cloth: kernel against the brute-force reference and ipctk.

A flat strip with alternating diagonals holds exactly parallel, coplanar diagonals 14.6 mm apart. A parallel test
on the Gram determinant ``a e − b²``, which cancels to rounding noise for parallel lines, lets such pairs through to
the line-line type, whose distance is 0 for any two coplanar lines: the CCD would then stop every sweep at t = 0.
"""

import numpy as np
import pytest
import torch

from kernels import backend, ccd, ipc_barrier
from kernels.reference import cloth as ref

try:  # the IPC Toolkit is the external oracle where it is installed
    import ipctk
except ImportError:
    ipctk = None

needs_ipctk = pytest.mark.skipif(ipctk is None, reason="ipctk is not installed (pip install ipctk==1.6.1)")

F64 = torch.float64


def _strip(nx: int = 20, ny: int = 50, width: float = 0.2, length: float = 0.5):
    """Vertices ``[nx·ny, 3]`` of a flat ``width × length`` strip and its diagonals ``[D, 2]``, alternating per cell."""
    xs = torch.linspace(0.0, width, nx, dtype=F64)
    ys = torch.linspace(0.0, length, ny, dtype=F64)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    x = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(-1, 3)
    diagonals = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            if (i + j) % 2 == 0:
                diagonals.append((i * ny + j, (i + 1) * ny + j + 1))
            else:
                diagonals.append(((i + 1) * ny + j, i * ny + j + 1))
    return x, torch.tensor(diagonals)


def _parallel_diagonal_pairs(x: torch.Tensor, diagonals: torch.Tensor, reach: float = 0.035) -> torch.Tensor:
    """Pairs ``[P, 4]`` int32 of vertex-disjoint diagonals whose midpoints lie within ``reach`` (m)."""
    mid = 0.5 * (x[diagonals[:, 0]] + x[diagonals[:, 1]])
    close = torch.cdist(mid, mid) < reach
    a, b = torch.nonzero(torch.triu(close, diagonal=1), as_tuple=True)
    pairs = torch.cat([diagonals[a], diagonals[b]], 1)
    disjoint = (pairs[:, :2, None] != pairs[:, None, 2:]).all(2).all(1)
    return pairs[disjoint].to(torch.int32).contiguous()


def _dev(t: torch.Tensor) -> torch.Tensor:
    return t.to(backend.torch_device()).contiguous()


def _exactly_parallel(x: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    q = x[pairs.long()]
    return torch.linalg.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]).norm(dim=1) < 1e-18


def test_strip_has_coplanar_parallel_diagonals_14_6_mm_apart():
    x, diagonals = _strip()
    pairs = _parallel_diagonal_pairs(x, diagonals)
    q = x[pairs.long()]
    parallel = _exactly_parallel(x, pairs)
    da = q[:, 1] - q[:, 0]
    normal = torch.stack([-da[:, 1], da[:, 0], torch.zeros_like(da[:, 0])], 1) / da.norm(dim=1, keepdim=True)
    gap = ((q[:, 2] - q[:, 0]) * normal).sum(1).abs()
    assert bool((parallel & (gap - 0.0146).abs().lt(2e-4)).any()), "the fixture holds the degenerate pair"


def test_flat_strip_sweeps_are_not_blocked(device):
    """In-plane stretch, rigid motion and an out-of-plane lift of a flat strip: no pair may stop the sweep."""
    x, diagonals = _strip()
    pairs = _parallel_diagonal_pairs(x, diagonals)
    stretch = torch.zeros_like(x)
    stretch[:, 1] = -1e-3 * (0.5 - x[:, 1])  # a hanging strip sags more at its free end
    rigid = torch.zeros_like(x)
    rigid[:, 1] = -1e-3
    lift = torch.zeros_like(x)
    lift[:, 2] = 1e-6
    for dx in (stretch, rigid, lift, stretch + lift):
        toi = ccd.edge_edge_ccd(_dev(x), _dev(dx), _dev(pairs)).cpu()
        assert toi.min().item() == 1.0, f"a flat sweep stopped at t = {toi.min().item()}"
    distance = ipc_barrier.edge_edge_distance_value(_dev(x), _dev(pairs)).cpu()
    assert distance.min().item() > (0.0146 - 2e-4) ** 2


def test_flat_strip_distances_match_the_reference(device):
    x, diagonals = _strip()
    pairs = _parallel_diagonal_pairs(x, diagonals)
    kinds, terms = ipc_barrier.edge_edge_distance(_dev(x), _dev(pairs))
    brute = torch.func.vmap(ref.edge_edge_sq_distance)(x[pairs.long()])
    torch.testing.assert_close(terms.energy.cpu(), brute, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(
        ipc_barrier.edge_edge_distance_value(_dev(x), _dev(pairs)).cpu(), brute, rtol=1e-12, atol=0.0
    )
    parallel = _exactly_parallel(x, pairs)
    assert not bool((kinds.cpu()[parallel] == 8).any()), "parallel edges never take the line-line type"


def _coplanar_segments(count: int, seed: int) -> torch.Tensor:
    """``[count, 4, 3]`` random segment pairs lying in one random plane; every third pair exactly parallel."""
    g = torch.Generator().manual_seed(seed)
    flat = torch.rand(count, 4, 2, dtype=F64, generator=g) * 0.05
    parallel = torch.arange(count) % 3 == 0
    flat[parallel, 3] = flat[parallel, 2] + (flat[parallel, 1] - flat[parallel, 0])
    q = torch.cat([flat, torch.zeros(count, 4, 1, dtype=F64)], 2)
    rotation, _ = torch.linalg.qr(torch.randn(3, 3, dtype=F64, generator=g))
    return q @ rotation.T + torch.randn(3, dtype=F64, generator=g)


@needs_ipctk
def test_coplanar_and_parallel_distances_match_reference_and_ipctk(device):
    q = _coplanar_segments(300, 3)
    x, pairs = q.reshape(-1, 3).contiguous(), torch.arange(4 * len(q), dtype=torch.int32).reshape(-1, 4)
    _, terms = ipc_barrier.edge_edge_distance(_dev(x), _dev(pairs))
    got = terms.energy.cpu()
    brute = torch.func.vmap(ref.edge_edge_sq_distance)(q)
    expect = torch.tensor([ipctk.edge_edge_distance(*qk) for qk in q.numpy()], dtype=F64)
    crossing = brute < 1e-14  # coplanar segments that intersect: distance 0 up to rounding
    torch.testing.assert_close(got[~crossing], brute[~crossing], rtol=1e-8, atol=0.0)
    torch.testing.assert_close(got[~crossing], expect[~crossing], rtol=1e-8, atol=0.0)
    assert got[crossing].abs().max().item() < 1e-14 if bool(crossing.any()) else True
    assert int((~crossing).sum()) > 150


@needs_ipctk
def test_flat_strip_ccd_agrees_with_ipctk_on_no_contact(device):
    x, diagonals = _strip(8, 12, 0.2 * 7 / 19, 0.5 * 11 / 49)
    pairs = _parallel_diagonal_pairs(x, diagonals)
    dx = torch.zeros_like(x)
    dx[:, 1] = -1e-3 * (x[:, 1].max() - x[:, 1])
    toi = ccd.edge_edge_ccd(_dev(x), _dev(dx), _dev(pairs)).cpu()
    narrow = ipctk.AdditiveCCD()
    for k, p in enumerate(pairs.long()):
        q0, q1 = x[p].numpy(), (x[p] + dx[p]).numpy()
        hit, t = narrow.edge_edge_ccd(*q0, *q1)
        assert not hit or np.isclose(t, 1.0), f"ipctk sees contact on pair {k}"
        assert toi[k].item() == 1.0
