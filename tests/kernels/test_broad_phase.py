"""Box-overlap pairs through a BVH against every pair tested by brute force."""

import pytest
import torch

from kernels.broad_phase import BoxTree, OverlapQuery, OverlapSearch, find_overlaps

F64 = torch.float64


def _boxes(device, seed: int = 0, n: int = 300):
    """Vertex boxes of random 2 cm sweeps in a 10 cm cube, and random triangles, edges and points over them."""
    g = torch.Generator().manual_seed(seed)
    x = 0.1 * torch.rand(n, 3, generator=g, dtype=F64)
    end = x + 0.02 * torch.randn(n, 3, generator=g, dtype=F64)
    lo, hi = torch.minimum(x, end), torch.maximum(x, end)
    triangles = torch.randint(0, n, (250, 3), generator=g, dtype=torch.int32)
    edges = torch.randint(0, n, (400, 2), generator=g, dtype=torch.int32)
    points = torch.arange(n, dtype=torch.int32)[:, None]
    excluded = torch.rand(n, generator=g) < 0.3
    to = lambda t: t.to(device).contiguous()  # noqa: E731
    return to(lo), to(hi), to(triangles), to(edges), to(points), to(excluded)


def _brute(lo, hi, query, tree, grow, excluded, same=False, tree_first=False):
    """Every overlapping pair by the dense ``[Q, P]`` box test, filtered as :meth:`BoxTree.overlaps` documents."""
    q, t = query.long(), tree.long()
    q_lo, q_hi = lo[q].amin(1) - grow, hi[q].amax(1) + grow
    t_lo, t_hi = lo[t].amin(1), hi[t].amax(1)
    i, j = ((q_lo[:, None] <= t_hi[None]) & (t_lo[None] <= q_hi[:, None])).all(2).nonzero(as_tuple=True)
    qi, tj = q[i], t[j]
    keep = (qi[:, :, None] != tj[:, None, :]).all(2).all(1) & ~(excluded[qi].all(1) & excluded[tj].all(1))
    if same:
        keep &= j > i
    pairs = torch.cat([tj, qi], 1) if tree_first else torch.cat([qi, tj], 1)
    return pairs[keep].to(torch.int32)


def _rows(pairs: torch.Tensor) -> list[tuple[int, ...]]:
    return sorted(map(tuple, pairs.cpu().tolist()))


@pytest.mark.parametrize(
    "query_kind, tree_kind, same, tree_first",
    [
        ("points", "triangles", False, False),  # garment vertices against garment triangles
        ("triangles", "points", False, True),  # body triangles against garment vertices, point first
        ("edges", "edges", True, False),  # garment edges against themselves
        ("edges", "edges", False, True),  # body edges against garment edges, garment edge first
    ],
)
def test_overlaps_match_brute_force(device, query_kind, tree_kind, same, tree_first):
    """The BVH finds exactly the pairs of the dense box test, with shared vertices, all-excluded pairs and mirrored
    pairs left out, and its vertices in the documented column order."""
    lo, hi, triangles, edges, points, excluded = _boxes(device)
    prims = {"points": points, "triangles": triangles, "edges": edges}
    query, tree = prims[query_kind], prims[tree_kind]
    for grow in (0.0, 1e-3, 1e-2):
        got = BoxTree(lo, hi, tree).overlaps(query, grow, excluded, same=same, tree_first=tree_first)
        want = _brute(lo, hi, query, tree, grow, excluded, same, tree_first)
        assert got.dtype == torch.int32 and got.shape[1] == query.shape[1] + tree.shape[1]
        assert len(want) > 100  # the case is not empty
        assert _rows(got) == _rows(want)
        # ordered by query primitive
        column = tree.shape[1] if tree_first else 0
        firsts = got[:, column].long().cpu()
        if query.shape[1] == 1:
            assert bool((firsts[1:] >= firsts[:-1]).all())


def test_find_overlaps_gives_each_request_its_own_pairs(device):
    """Several requests over two trees, one of them empty, answered together: the same rows in the same order as
    one call each."""
    lo, hi, triangles, edges, points, excluded = _boxes(device)
    triangle_tree, edge_tree = BoxTree(lo, hi, triangles), BoxTree(lo, hi, edges)
    requests = [
        OverlapQuery(triangle_tree, points, 1e-3, excluded),
        OverlapQuery(edge_tree, edges, 1e-3, excluded, same=True),
        OverlapQuery(triangle_tree, points[:0], 1e-3, excluded),
        OverlapQuery(edge_tree, edges, 0.0, excluded, tree_first=True),
    ]
    got = find_overlaps(requests)
    assert len(got) == len(requests) and got[2].shape == (0, 4)
    for pairs, request in zip(got, requests, strict=True):
        tree, query, grow, excluded, same, tree_first = request
        assert torch.equal(pairs, tree.overlaps(query, grow, excluded, same=same, tree_first=tree_first))
    assert min(got[0].shape[0], got[1].shape[0], got[3].shape[0]) > 100
    assert find_overlaps([]) == []


def test_overlap_search_in_one_walk_gives_find_overlaps_pairs(device):
    """OverlapSearch gives find_overlaps' rows in its order: from its slots where every query's pairs fit, by the
    filling walk where some query found more, after which that request's slots have grown to hold them."""
    lo, hi, triangles, edges, points, excluded = _boxes(device)
    triangle_tree, edge_tree = BoxTree(lo, hi, triangles), BoxTree(lo, hi, edges)
    requests = [
        OverlapQuery(triangle_tree, points, 1e-3, excluded),
        OverlapQuery(triangle_tree, points[:0], 1e-3, excluded),
        OverlapQuery(edge_tree, edges, 1e-3, excluded, same=True),
        OverlapQuery(edge_tree, edges, 0.0, excluded, tree_first=True),
    ]
    want = find_overlaps(requests)
    most = []
    for request in requests:
        pairs = find_overlaps([request])[0]
        column = request.tree.prims.shape[1] if request.tree_first else 0
        first = pairs[:, column : column + request.query.shape[1]].cpu()
        counts = torch.unique_consecutive(first, dim=0, return_counts=True)[1] if len(pairs) else torch.zeros(1)
        most.append(int(counts.max()))
    assert max(most) > 2, "the case must overflow two slots"
    search = OverlapSearch(slots=2, max_slots=512)
    for attempt in range(2):
        got = search(requests)
        assert len(got) == len(requests)
        for a, b in zip(got, want, strict=True):
            assert torch.equal(a, b)
        if attempt == 0:
            assert search.overflows == sum(m > 2 for m in most)
            assert all(s >= m for s, m in zip(search.request_slots, most, strict=True))
    assert search.overflows == sum(m > 2 for m in most), "the grown slots hold every pair the second time"
    assert search([]) == []
    with pytest.raises(ValueError, match="slots"):
        OverlapSearch(slots=0)


def test_overlaps_are_deterministic_and_exact_at_touching_boxes(device):
    """Boxes that touch exactly (float64 coordinates whose float32 rounding differs) overlap; boxes a hair apart do
    not; the same call twice gives the same rows in the same order."""
    xs = [0.1, 0.3, 0.1 + 1e-3, 0.1 + 1e-3 + 1e-15]
    lo = torch.tensor([[v, 0.0, 0.0] for v in xs], dtype=F64)
    hi = lo.clone()
    hi[:, 1:] = 1.0
    lo, hi = lo.to(device).contiguous(), hi.to(device).contiguous()
    tree = BoxTree(lo, hi, torch.tensor([[2], [3]], dtype=torch.int32, device=device))
    query = torch.tensor([[0]], dtype=torch.int32, device=device)
    none = torch.zeros(4, dtype=torch.bool, device=device)
    got = tree.overlaps(query, 1e-3, none)
    assert _rows(got) == _rows(_brute(lo, hi, query, tree.prims, 1e-3, none)) == [(0, 2)]
    lo, hi, triangles, edges, points, excluded = _boxes(device, seed=3)
    tree = BoxTree(lo, hi, triangles)
    assert torch.equal(tree.overlaps(points, 1e-3, excluded), tree.overlaps(points, 1e-3, excluded))


def test_empty_sets_and_bad_input(device):
    lo, hi, triangles, edges, points, excluded = _boxes(device)
    assert BoxTree(lo, hi, triangles[:0]).overlaps(points, 1e-3, excluded).shape == (0, 4)
    assert BoxTree(lo, hi, triangles).overlaps(points[:0], 1e-3, excluded).shape == (0, 4)
    far = lo + 10.0, hi + 10.0
    assert BoxTree(*far, triangles).overlaps(points, 1e-3, excluded).shape[0] > 0  # all moved together
    with pytest.raises(ValueError, match="float64"):
        BoxTree(lo.float(), hi, triangles)
    with pytest.raises(ValueError, match="int32"):
        BoxTree(lo, hi, triangles.long())
    with pytest.raises(ValueError, match="k = 1, 2 or 3"):
        BoxTree(lo, hi, torch.zeros(3, 4, dtype=torch.int32, device=device))
    tree = BoxTree(lo, hi, triangles)
    with pytest.raises(ValueError, match="excluded"):
        tree.overlaps(points, 1e-3, excluded[:5])
    with pytest.raises(ValueError, match="grow"):
        tree.overlaps(points, -1.0, excluded)
    with pytest.raises(ValueError, match="same=True"):
        tree.overlaps(points, 1e-3, excluded, same=True)


def test_refitted_tree_finds_the_pairs_of_a_fresh_one(device):
    """A tree refitted to moved boxes finds every pair a tree built on them finds (its order may differ)."""
    lo, hi, triangles, edges, points, excluded = _boxes(device, seed=3)
    moved_lo, moved_hi, *_ = _boxes(device, seed=4)
    for prims, query in ((triangles, points), (edges, edges)):
        tree = BoxTree(lo, hi, prims)
        tree.refit(moved_lo, moved_hi)
        fresh = BoxTree(moved_lo, moved_hi, prims)
        got = tree.overlaps(query, 1e-3, excluded)
        assert len(got) > 100 and _rows(got) == _rows(fresh.overlaps(query, 1e-3, excluded))
    with pytest.raises(ValueError, match="refit needs"):
        tree.refit(moved_lo[:10].contiguous(), moved_hi[:10].contiguous())
