"""Contact candidates by box overlap: a BVH over one primitive set, queried with the boxes of another.

The garment simulator (PhysAvatar §3.2 with Codim-IPC) finds its contact candidates once per reach of the Newton
sweeps: every point–triangle and edge–edge pair whose primitives' boxes overlap once the query side is grown by the
activation distance ``d̂``. A primitive is a tuple of vertex indices (a point, an edge, a triangle) and its box the
union of its vertices' boxes, each vertex's box given as ``[lo, hi]`` (for a sweep, the box of its segment).

:class:`BoxTree` builds Warp's BVH (``wp.Bvh``: LBVH on CUDA, SAH on the CPU) over the primitive boxes, rounded
outwards to float32, and :meth:`BoxTree.overlaps` walks it once per query primitive, twice: a count, then, at the
prefix-summed offsets, the pairs (:func:`find_overlaps` runs several queries' counts, then their fills). The exact
test is in float64 (the boxes of 1 mm gaps on 1 m coordinates), so the result is exactly the pairs whose float64
boxes overlap, in a deterministic order (by query, then by the tree's traversal order). Pairs that share a vertex,
pairs whose vertices are all excluded (kinematic: nothing can move them) and, within one set, the mirrored half are
dropped in the kernel. Each :func:`find_overlaps` call costs one read from the device (the numbers of pairs, to
allocate them).

Warp, not Taichi: Warp has a BVH that builds on both devices; on the CPU it runs on one thread.

It replaced a hash grid over primitive centres, which needed dozens of launches and host reads and filtered many
more candidates; the BVH search is several times faster on both devices (``docs/benchmarks.md``).
"""

# Warp needs int(0)/bool(False) to declare variables that change inside dynamic loops.
# ruff: noqa: UP018

from __future__ import annotations

from typing import NamedTuple

import torch
import warp as wp

from kernels import backend

wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["BoxTree", "OverlapQuery", "OverlapSearch", "find_overlaps"]

# float64 → float32 rounding is at most half an ulp (2⁻²⁴ relative); the BVH's boxes are grown by more than that
# so that they contain the float64 boxes, and the exact test then runs on those.
_RELATIVE_PAD = 1.0e-6
_ABSOLUTE_PAD = 1.0e-12


@wp.func
def _rounding_pad(f: wp.vec3):
    return wp.vec3(
        wp.abs(f[0]) * _RELATIVE_PAD + _ABSOLUTE_PAD,
        wp.abs(f[1]) * _RELATIVE_PAD + _ABSOLUTE_PAD,
        wp.abs(f[2]) * _RELATIVE_PAD + _ABSOLUTE_PAD,
    )


@wp.func
def _down(v: wp.vec3d):
    """A float32 point at or below ``v`` on every axis."""
    f = wp.vec3(wp.float32(v[0]), wp.float32(v[1]), wp.float32(v[2]))
    return f - _rounding_pad(f)


@wp.func
def _up(v: wp.vec3d):
    """A float32 point at or above ``v`` on every axis."""
    f = wp.vec3(wp.float32(v[0]), wp.float32(v[1]), wp.float32(v[2]))
    return f + _rounding_pad(f)


@wp.kernel
def _bounds_kernel(
    lo: wp.array(dtype=wp.vec3d),
    hi: wp.array(dtype=wp.vec3d),
    prims: wp.array2d(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    j = wp.tid()
    b_lo = lo[prims[j, 0]]
    b_hi = hi[prims[j, 0]]
    for a in range(1, prims.shape[1]):
        b_lo = wp.min(b_lo, lo[prims[j, a]])
        b_hi = wp.max(b_hi, hi[prims[j, a]])
    lowers[j] = _down(b_lo)
    uppers[j] = _up(b_hi)


@wp.kernel
def _overlaps_kernel(
    bvh: wp.uint64,
    lo: wp.array(dtype=wp.vec3d),
    hi: wp.array(dtype=wp.vec3d),
    tree: wp.array2d(dtype=wp.int32),
    query: wp.array2d(dtype=wp.int32),
    grow: wp.float64,
    excluded: wp.array(dtype=wp.uint8),
    same: int,
    tree_first: int,
    fill: int,
    slots: int,
    offset: wp.array(dtype=wp.int64),
    count: wp.array(dtype=wp.int32),
    pairs: wp.array2d(dtype=wp.int32),
):
    i = wp.tid()
    if fill == 3 and count[i] <= slots:  # this query's pairs are in its slots already
        return
    kq = query.shape[1]
    kt = tree.shape[1]
    q_lo = lo[query[i, 0]]
    q_hi = hi[query[i, 0]]
    q_free = excluded[query[i, 0]] == wp.uint8(0)
    for a in range(1, kq):
        q_lo = wp.min(q_lo, lo[query[i, a]])
        q_hi = wp.max(q_hi, hi[query[i, a]])
        q_free = q_free or excluded[query[i, a]] == wp.uint8(0)
    g = wp.vec3d(grow, grow, grow)
    q_lo = q_lo - g
    q_hi = q_hi + g
    found = int(0)
    j = int(0)
    walk = wp.bvh_query_aabb(bvh, _down(q_lo), _up(q_hi))
    while wp.bvh_query_next(walk, j):
        if same != 0 and j <= i:
            continue
        t_lo = lo[tree[j, 0]]
        t_hi = hi[tree[j, 0]]
        free = q_free
        shared = bool(False)
        for b in range(kt):
            v = tree[j, b]
            if b > 0:
                t_lo = wp.min(t_lo, lo[v])
                t_hi = wp.max(t_hi, hi[v])
            free = free or excluded[v] == wp.uint8(0)
            for a in range(kq):
                if query[i, a] == v:
                    shared = True
        if shared or not free:
            continue
        if q_lo[0] > t_hi[0] or q_lo[1] > t_hi[1] or q_lo[2] > t_hi[2]:
            continue
        if t_lo[0] > q_hi[0] or t_lo[1] > q_hi[1] or t_lo[2] > q_hi[2]:
            continue
        row = int(-1)
        if fill == 1 or fill == 3:
            row = int(offset[i]) + found
        elif fill == 2 and found < slots:
            row = i * slots + found
        if row >= 0:
            for a in range(kq):
                pairs[row, a + tree_first * kt] = query[i, a]
            for b in range(kt):
                pairs[row, b + (1 - tree_first) * kq] = tree[j, b]
        found += 1
    if fill == 0 or fill == 2:
        count[i] = found


@wp.kernel
def _gather_slots_kernel(
    slotted: wp.array2d(dtype=wp.int32),
    slots: int,
    count: wp.array(dtype=wp.int32),
    offset: wp.array(dtype=wp.int64),
    pairs: wp.array2d(dtype=wp.int32),
):
    i, k = wp.tid()
    if k < count[i] and count[i] <= slots:  # the others are walked again (_overlaps_kernel's fill 3)
        for c in range(pairs.shape[1]):
            pairs[int(offset[i]) + k, c] = slotted[i * slots + k, c]


class BoxTree:
    """A BVH over the boxes of a primitive set, for the pairs whose boxes overlap those of another set.

    Args:
        lo, hi: ``[V, 3]`` float64 corners of each vertex's box, m, on the backend device; kept by reference, shared
            by the tree's primitives and the queries' (do not modify them while the tree lives).
        prims: ``[P, k]`` int32 vertex indices of the tree's primitives (``k`` = 1 point, 2 edge, 3 triangle).

    Raises:
        ValueError: malformed boxes or indices.
    """

    def __init__(self, lo: torch.Tensor, hi: torch.Tensor, prims: torch.Tensor):
        _check_boxes(lo, hi)
        _check_prims(prims, "prims")
        self.lo, self.hi, self.prims = lo, hi, prims
        self._bvh = None
        if prims.shape[0]:
            device = backend.warp_device()
            self._lowers = wp.empty(prims.shape[0], dtype=wp.vec3, device=device)
            self._uppers = wp.empty(prims.shape[0], dtype=wp.vec3, device=device)
            backend.warp_launch(
                _bounds_kernel,
                dim=prims.shape[0],
                inputs=[backend.warp_arg(lo, wp.vec3d), backend.warp_arg(hi, wp.vec3d), backend.warp_arg(prims)],
                outputs=[self._lowers, self._uppers],
                device=device,
            )
            self._bvh = wp.Bvh(self._lowers, self._uppers)

    def refit(self, lo: torch.Tensor, hi: torch.Tensor) -> None:
        """Take new vertex boxes (as the constructor takes them, same shapes) and refit the BVH to them: its
        hierarchy stays, its node boxes are recomputed bottom-up, a fraction of a build's cost
        (``docs/benchmarks.md``, ``kernels.broad_phase``). Every pair is still found (the boxes are
        exact); a hierarchy refitted far from the shape it was built for only makes the walks longer, so callers
        build anew from time to time."""
        _check_boxes(lo, hi)
        if lo.shape != self.lo.shape:
            raise ValueError(f"refit needs boxes of the tree's {self.lo.shape[0]} vertices, got {lo.shape[0]}")
        self.lo, self.hi = lo, hi
        if self._bvh is None:
            return
        backend.warp_launch(
            _bounds_kernel,
            dim=self.prims.shape[0],
            inputs=[backend.warp_arg(lo, wp.vec3d), backend.warp_arg(hi, wp.vec3d), backend.warp_arg(self.prims)],
            outputs=[self._lowers, self._uppers],
            device=self._lowers.device,
        )
        self._bvh.refit()

    def overlaps(
        self,
        query: torch.Tensor,
        grow: float,
        excluded: torch.Tensor,
        same: bool = False,
        tree_first: bool = False,
    ) -> torch.Tensor:
        """Pairs of a query primitive and a tree primitive whose boxes overlap, the query's grown by ``grow``.

        Pairs that share a vertex and pairs whose vertices are all ``excluded`` are left out.

        Args:
            query: ``[Q, kq]`` int32 vertex indices of the query primitives (into the tree's ``lo``/``hi``).
            grow: distance, m, by which each query box is grown on every side (``d̂``).
            excluded: ``[V]`` bool, vertices whose pairs are dropped when all four are excluded.
            same: the queries are the tree's own primitives: each unordered pair once (the query index smaller).
            tree_first: write the tree primitive's vertices first.

        Returns:
            ``[N, kq + k]`` int32 vertex indices, query's then tree's (or the reverse), ordered by query.
        """
        return find_overlaps([OverlapQuery(self, query, grow, excluded, same, tree_first)])[0]

    def _count(self, request: OverlapQuery, slots: int = 0) -> _Counted:
        """Checks ``request`` and launches its counting walk; with ``slots``, one that also writes each query's first
        ``slots`` pairs to its rows of :attr:`_Counted.slotted` (:class:`OverlapSearch`)."""
        query, grow, excluded, same = request.query, request.grow, request.excluded, request.same
        _check_prims(query, "query")
        if excluded.dtype != torch.bool or tuple(excluded.shape) != (self.lo.shape[0],):
            raise ValueError(
                f"excluded must be a bool [{self.lo.shape[0]}] tensor, got {excluded.dtype} {tuple(excluded.shape)}"
            )
        if not grow >= 0.0:
            raise ValueError(f"grow ({grow}) must be non-negative, m")
        if same and query is not self.prims and not torch.equal(query, self.prims):
            raise ValueError("same=True needs the tree's own primitives as the queries")
        width = query.shape[1] + self.prims.shape[1]
        device = self.lo.device
        empty = torch.zeros(0, width, dtype=torch.int32, device=device)
        if self._bvh is None or query.shape[0] == 0:
            return _Counted([], empty, None, None, empty)
        n = query.shape[0]
        count = torch.empty(n, dtype=torch.int32, device=device)
        offset = torch.zeros(n, dtype=torch.int64, device=device)
        flags = excluded.contiguous().view(torch.uint8)
        args = [self._bvh.id, (self.lo, wp.vec3d), (self.hi, wp.vec3d), self.prims, query, wp.float64(grow), flags]
        args += [int(same), int(request.tree_first)]
        if slots:
            slotted = torch.empty(n * slots, width, dtype=torch.int32, device=device)
            backend.launch(_overlaps_kernel, n, [*args, 2, slots, offset, count, slotted])
            return _Counted(args, empty, count, offset, slotted)  # offsets not summed yet
        backend.launch(_overlaps_kernel, n, [*args, 0, 0, offset, count, empty])
        torch.cumsum(count[:-1], 0, out=offset[1:])
        return _Counted(args, empty, count, offset, empty)


class OverlapQuery(NamedTuple):
    """The arguments of one :meth:`BoxTree.overlaps` call, for :func:`find_overlaps`."""

    tree: BoxTree
    query: torch.Tensor
    grow: float
    excluded: torch.Tensor
    same: bool = False
    tree_first: bool = False


class _Counted(NamedTuple):
    args: list  # the walk's arguments up to the pass flag; empty where nothing can overlap
    empty: torch.Tensor  # [0, width] int32
    count: torch.Tensor | None  # [Q] pairs per query primitive
    offset: torch.Tensor | None  # [Q] int64 exclusive prefix sum of count
    slotted: torch.Tensor  # [Q · slots, width] int32: each query's first pairs in its rows (OverlapSearch)


def find_overlaps(requests: list[OverlapQuery]) -> list[torch.Tensor]:
    """The pairs of each request, as :meth:`BoxTree.overlaps` finds them, with one read from the device for all.

    The counting walks of every request run first, then the totals are read back together (a read waits for the
    device to finish its queue, so one per request cost a search of five requests four extra stalls), then the
    filling walks run.
    """
    counted = [request.tree._count(request) for request in requests]
    sizes = [c.offset[-1] + c.count[-1] for c in counted if c.count is not None]
    totals = iter(torch.stack(sizes).tolist() if sizes else [])
    found = []
    for c in counted:
        total = next(totals) if c.count is not None else 0
        if total == 0:
            found.append(c.empty)
            continue
        pairs = torch.empty(total, c.empty.shape[1], dtype=torch.int32, device=c.empty.device)
        backend.launch(_overlaps_kernel, c.count.shape[0], [*c.args, 1, 0, c.offset, c.count, pairs])
        found.append(pairs)
    return found


class OverlapSearch:
    """:func:`find_overlaps` in one walk per request instead of two, for a caller that repeats the same requests.

    Each query primitive writes the pairs it finds into its own ``slots`` rows of a scratch array while it counts
    them; one read from the device for all requests then gives each request's total and its largest count, and a
    copy to the prefix-summed offsets finishes the request. Only the query primitives that found more pairs than
    their slots walk again, writing all theirs at their offsets, and the request's slots grow to the next power of
    two that would have held them (at most :attr:`max_slots`), for the next search. The pairs and their
    order are :func:`find_overlaps`'. The walks dominate a garment's candidate search (``docs/benchmarks.md``,
    ``kernels.broad_phase``).

    Args:
        slots: pairs each query primitive can hold at first.
        max_slots: the most slots a query primitive is given (bounds the scratch memory).
    """

    def __init__(self, slots: int = 16, max_slots: int = 256):
        if not 1 <= slots <= max_slots:
            raise ValueError(f"need 1 <= slots <= max_slots, got {slots} and {max_slots}")
        self.slots, self.max_slots = slots, max_slots
        self.request_slots: list[int] = []  # per request position, learnt from the searches so far
        self.overflows = 0  # requests in which some query primitive walked again (more pairs than its slots)

    def __call__(self, requests: list[OverlapQuery]) -> list[torch.Tensor]:
        """The pairs of each request, as :func:`find_overlaps` gives them."""
        while len(self.request_slots) < len(requests):
            self.request_slots.append(self.slots)
        walked = []
        for request, slots in zip(requests, self.request_slots, strict=False):
            counted = request.tree._count(request, slots)
            walked.append((counted, slots))
        stats = [torch.stack([c.count.sum(), c.count.max().to(torch.int64)]) for c, _ in walked if c.count is not None]
        read = iter(torch.stack(stats).tolist() if stats else [])
        found = []
        for position, (c, slots) in enumerate(walked):
            total, most = next(read) if c.count is not None else (0, 0)
            if total == 0:
                found.append(c.empty)
                continue
            torch.cumsum(c.count[:-1], 0, out=c.offset[1:])
            pairs = torch.empty(total, c.empty.shape[1], dtype=torch.int32, device=c.empty.device)
            gather = [c.slotted, slots, c.count, c.offset, pairs]
            backend.launch(_gather_slots_kernel, (c.count.shape[0], slots), gather)
            if most > slots:  # the query primitives that found more walk again
                backend.launch(_overlaps_kernel, c.count.shape[0], [*c.args, 3, slots, c.offset, c.count, pairs])
                self.request_slots[position] = min(1 << (most - 1).bit_length(), self.max_slots)
                self.overflows += 1
            found.append(pairs)
        return found


def _check_boxes(lo: torch.Tensor, hi: torch.Tensor) -> None:
    for name, t in (("lo", lo), ("hi", hi)):
        if t.dtype != torch.float64 or t.dim() != 2 or t.shape[1] != 3:
            raise ValueError(f"{name} must be a float64 [V, 3] tensor, got {t.dtype} {tuple(t.shape)}")
        if not t.is_contiguous():
            raise ValueError(f"{name} is not contiguous; call .contiguous() first")
    if lo.shape != hi.shape:
        raise ValueError(f"lo {tuple(lo.shape)} and hi {tuple(hi.shape)} must have the same shape")


def _check_prims(prims: torch.Tensor, what: str) -> None:
    if prims.dtype != torch.int32 or prims.dim() != 2 or not 1 <= prims.shape[1] <= 3:
        raise ValueError(
            f"{what} must be an int32 [N, k] tensor with k = 1, 2 or 3 vertices per primitive, got {prims.dtype} "
            f"{tuple(prims.shape)}; convert with .to(torch.int32)"
        )
    if not prims.is_contiguous():
        raise ValueError(f"{what} is not contiguous; call .contiguous() first")
