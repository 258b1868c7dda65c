"""A captured garment's intersections with the body and with itself, removed so that the simulation can start.

The garment simulator (:mod:`physavatar.cloth`, IPC) needs an intersection-free start with every garment vertex a
positive distance from the body: a vertex inside the body stays trapped there, one at distance 0 makes the barrier
infinite. A garment reconstructed from a capture (PhysAvatar §3.1) starts touching or slightly inside the fitted
body, often through itself, and the fitted body (SMPL-X) often intersects itself: an arm into the torso, the thighs
into each other. :func:`resolve_intersections` moves the offending garment vertices the least it can to a clearance
``gap`` from the body, separates the garment's crossing triangles, and spreads the moves a little into their
neighbours.

Inside or outside: the body's generalised winding number (Jacobson et al. 2013) above ½, robust for a
self-intersecting body (a point inside two overlapping parts has winding number 2) and for a slightly open one,
evaluated through the bounding-volume hierarchy of :class:`kernels.raycast.MeshBVH` (the fast winding number of
Barill et al. 2018). Its exact sum over the triangles (``Body.winding_number``) costs ``O(P·F)``: 500 points against
the 23k triangles of the mannequin took 3.6 s on one CPU core, where the hierarchy answers 8000 in 0.05 s.

The body's own intersections. Where the body intersects itself, part of its surface lies inside another part. A
vertex outside the body is nearest to the outer surface anyway (the segment to a point inside another part would
cross that part's surface first), but a vertex inside may be nearest to such a buried triangle, whose outward
normal leads further in. So a vertex inside the body moves to the closest point of the triangles that are not
buried, a triangle being buried when a point just off it along its outward normal lies inside the body; where that
point lies on the buried part of a triangle crossing into another part (its move would end inside), to the closest
point of the triangles with no corner on a buried one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from kernels import backend
from kernels.raycast import MeshBVH
from physavatar.body import surface_closest_points

__all__ = ["RELAX_PASSES", "RELAX_RINGS", "IntersectionReport", "resolve_intersections"]

RELAX_RINGS = 2
"""Edge rings around the moved vertices whose vertices follow the moves (:func:`resolve_intersections`)."""
RELAX_PASSES = 4
"""Jacobi passes of displacement averaging over those rings."""
_PROBE_OFFSET = 1e-5  # the buried-triangle probe's distance off a triangle, as a fraction of the body's size
_STALLED_ROUNDS = 2  # rounds of separation without fewer crossing vertices before it gives up
_RADIUS_BIN = 1.5  # garment triangles are searched for crossings in bins of radii within this factor
_PLANE_TOLERANCE = 1e-9  # a point this fraction of the garment's size from a triangle's plane lies in it
_ALONG_NORMAL = 1e-3  # a vertex nearer the body than this fraction of the gap moves along the triangle's normal


@dataclass(frozen=True)
class IntersectionReport:
    """What :func:`resolve_intersections` found and did.

    Attributes:
        moved: garment vertices moved to resolve an intersection: out of the body to the gap, or apart from garment
            triangles they crossed.
        inside_body: vertices inside the body or closer to it than the gap, before.
        self_intersecting: vertices of garment triangles that crossed another garment triangle (one sharing no
            vertex with them), before.
        max_move_m: largest displacement of any vertex, m.
        mean_move_m: mean displacement of the moved vertices, m (0 when none moved).
        remaining_inside: vertices still inside the body or closer to it than the gap, after (0 on success).
        self_remaining: vertices of garment triangles still crossing another, after (0 on success).
        relaxed: vertices not moved for an intersection but displaced with their moved neighbours (never more than
            the largest move).
        vertices: the garment's vertices.
        edges_through_body: garment edges that meet the body surface, after: an edge whose two ends are clear can
            still pass through a body part thinner than the edge is long; the simulator refuses those as well (a
            finer garment mesh clears them).
    """

    moved: int
    inside_body: int
    self_intersecting: int
    max_move_m: float
    mean_move_m: float
    remaining_inside: int
    self_remaining: int
    relaxed: int
    vertices: int
    edges_through_body: int

    @property
    def clear(self) -> bool:
        """Every vertex ended outside the body with the gap, no garment edge passes through the body and no garment
        triangle crosses another."""
        return self.remaining_inside == 0 and self.self_remaining == 0 and self.edges_through_body == 0

    def summary(self) -> str:
        """One line for a person: what was found, what moved and by how much, and what is left."""
        if self.moved == 0 and self.clear:
            return f"the garment's {self.vertices} vertices are clear of the body and of each other: nothing moved"
        line = (
            f"moved {self.moved} of {self.vertices} garment vertices (max {self.max_move_m * 1e3:.1f} mm, mean "
            f"{self.mean_move_m * 1e3:.1f} mm): {self.inside_body} were inside the body or within the gap, "
            f"{self.self_intersecting} on triangles crossing the garment itself; {self.relaxed} neighbours followed"
        )
        if self.clear:
            return line + "; none is left inside the body, through it or crossing"
        return (
            line + f"; LEFT: {self.remaining_inside} inside the body or within the gap, {self.edges_through_body} "
            f"edges through the body, {self.self_remaining} on crossing triangles"
        )


def resolve_intersections(
    garment_vertices: torch.Tensor,
    garment_faces: torch.Tensor,
    body_vertices: torch.Tensor,
    body_faces: torch.Tensor,
    gap: float,
    iterations: int = 8,
) -> tuple[torch.Tensor, IntersectionReport]:
    """Move a garment out of the body, to a clearance ``gap``, and apart where it crosses itself.

    1. Body. Each garment vertex inside the body (winding number above ½) or closer to its surface than ``gap``
       moves to its closest point of the surface plus ``gap`` along the outward direction there: the outward normal
       of the closest triangle for a vertex inside or on the surface, the direction from that point to the vertex
       for one outside (the least move to the gap). On a self-intersecting body the new point may land inside
       another part, or in a crease too near the surface: the moved vertices are tested again and moved again, up
       to ``iterations`` times.
    2. Garment. Garment triangles that cross a triangle sharing no vertex with them are pushed apart, each pair's
       two triangles along the mean of their normals by half the overlap of their projections on it plus
       ``gap / 2``, a vertex in several pairs by the mean of its pairs' pushes; the body test of step 1 follows each
       round, up to ``iterations`` rounds. Local pushes undo a garment poking through itself over a few triangles;
       sheets that cross over a large region need more than they can give (each round frees about one more ring of
       triangles, and tangles others), so the rounds stop after two without progress and the least tangled state is
       kept: the report counts what is left.
    3. Neighbours. The moves spread into the :data:`RELAX_RINGS` edge rings around the moved vertices by
       :data:`RELAX_PASSES` Jacobi passes of displacement averaging (moved vertices keep theirs), so their neighbours
       are not left crumpled; a neighbour that would come closer to the body than ``gap`` or onto a crossing
       triangle keeps its place.

    Vertices beyond those rings are returned bit for bit as given. A vertex counts as clear of the body from a
    distance of ``gap − 64 ε L`` (``ε`` the float64 machine epsilon, ``L`` the scene's bounding-box diagonal): the
    rounding of a closest-point distance. The inside and edge tests run Warp kernels on the backend's device
    (``kernels.backend.init`` first); the rest runs on the CPU.

    Args:
        garment_vertices: ``[V, 3]`` garment vertices, m (float64; other float dtypes are converted).
        garment_faces: ``[F, 3]`` integer garment triangles.
        body_vertices: ``[B, 3]`` body vertices of the garment's frame (frame 0), m.
        body_faces: ``[G, 3]`` integer body triangles, outward-oriented, the surface closed or nearly closed; it may
            intersect itself.
        gap: clearance every garment vertex ends up with outside the body, m. Pass more than the simulator's contact
            distance ``d̂`` (``ClothConfig.contact_distance``), e.g. ``1.5 d̂ + 0.1 mm``: a garment starting within
            ``d̂`` starts with active barriers, and at 0 with an infinite one.
        iterations: rounds of re-testing and moving again in steps 1 and 2 (at least 1).

    Returns:
        ``(vertices [V, 3] float64 m on the garment's device, report)``; ``report.clear`` tells whether every
        intersection was removed, and :meth:`IntersectionReport.summary` says what was done in a line.

    Raises:
        ValueError: malformed meshes (shapes, NaN or inf, face indices), ``gap`` not positive or ``iterations`` < 1;
            the message names the fix.
    """
    x0, faces, body_x, body_f, gap = _checked(
        garment_vertices, garment_faces, body_vertices, body_faces, gap, iterations
    )
    out_device = garment_vertices.device if isinstance(garment_vertices, torch.Tensor) else torch.device("cpu")
    body = _BodySurface(body_x, body_f)
    everything = np.concatenate([x0, body_x])
    tol = 64.0 * np.finfo(np.float64).eps * float(np.linalg.norm(everything.max(0) - everything.min(0)))
    v = x0.shape[0]
    x = x0.copy()

    # 1. out of the body
    pushed, offending, _ = _push_out(x, np.arange(v), body, gap, tol, iterations)
    # 2. apart from itself
    pairs = _crossing_pairs(x0, faces)
    crossing_before = _crossing_vertices(x0, faces, pairs)
    separated = np.zeros(v, dtype=bool)
    pairs = _crossing_pairs(x, faces) if pushed.any() else pairs
    best = (int(_crossing_vertices(x, faces, pairs).sum()), x.copy(), pushed.copy(), separated.copy())
    stalled = 0
    for _ in range(iterations):
        if not pairs.shape[0] or stalled == _STALLED_ROUNDS:
            break
        apart = _separate(x, faces, pairs, gap)
        separated |= apart
        pushed |= _push_out(x, np.flatnonzero(apart), body, gap, tol, iterations)[0]
        pairs = _crossing_pairs(x, faces)
        count = int(_crossing_vertices(x, faces, pairs).sum())
        stalled = 0 if count < best[0] else stalled + 1
        if count < best[0]:
            best = (count, x.copy(), pushed.copy(), separated.copy())
    _, x, pushed, separated = best  # pushing triangles apart can tangle crossing sheets further: the least tangled
    moved = pushed | separated
    # 3. neighbours follow
    if moved.any():
        relaxed, crossing_after = _relax(x, x0, faces, moved, body, gap, tol)
    else:
        relaxed, crossing_after = moved, crossing_before
    changed = np.flatnonzero(moved | relaxed)
    remaining = body.offending(x[changed], gap, tol)[0].size if changed.size else 0
    edges = _edges(faces)
    through = body.meets(x[edges[:, 0]], x[edges[:, 1]])

    move = np.linalg.norm(x - x0, axis=1)
    report = IntersectionReport(
        moved=int(moved.sum()),
        inside_body=int(offending.size),
        self_intersecting=int(crossing_before.sum()),
        max_move_m=float(move.max()) if v else 0.0,
        mean_move_m=float(move[moved].mean()) if moved.any() else 0.0,
        remaining_inside=int(remaining),
        self_remaining=int(crossing_after.sum()),
        relaxed=int(relaxed.sum()),
        vertices=v,
        edges_through_body=int(through.sum()),
    )
    return torch.from_numpy(x).to(out_device), report


# --- input ----------------------------------------------------------------------------------------------------


def _checked(garment_vertices, garment_faces, body_vertices, body_faces, gap, iterations):
    """The meshes as float64 and int64 NumPy arrays and ``gap`` as a float, or a ValueError that names the problem
    and the fix."""
    try:
        clearance = float(gap)
    except (TypeError, ValueError):
        clearance = math.nan
    if not (math.isfinite(clearance) and clearance > 0):
        raise ValueError(
            f"gap must be a positive clearance in metres, got {gap!r}; pass more than the simulator's contact "
            "distance d̂, e.g. 1.5 · ClothConfig.contact_distance + 1e-4"
        )
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
        raise ValueError(f"iterations must be an integer of at least 1, got {iterations!r}; the default is 8")
    arrays = []
    for name, points, faces in (
        ("garment", garment_vertices, garment_faces),
        ("body", body_vertices, body_faces),
    ):
        p = torch.as_tensor(points).detach().cpu()
        f = torch.as_tensor(faces).detach().cpu()
        if p.dim() != 2 or p.shape[1] != 3 or p.shape[0] < 3 or not p.is_floating_point():
            raise ValueError(
                f"{name}_vertices must be a float [N, 3] array of at least 3 positions in metres, got "
                f"{p.dtype} {list(p.shape)}; pass one row (x, y, z) per vertex"
            )
        if f.dim() != 2 or f.shape[1] != 3 or f.shape[0] < 1 or f.is_floating_point():
            raise ValueError(
                f"{name}_faces must be an integer [F, 3] array of at least one triangle, got {f.dtype} "
                f"{list(f.shape)}; pass one row of three vertex indices per triangle"
            )
        p = p.to(torch.float64).numpy()
        f = f.to(torch.int64).numpy()
        bad = ~np.isfinite(p).all(1)
        if bad.any():
            raise ValueError(
                f"{name}_vertices hold {int(bad.sum())} rows with NaN or inf (e.g. vertex {int(np.argmax(bad))}); "
                "repair or drop those vertices first"
            )
        if f.min() < 0 or f.max() >= p.shape[0]:
            raise ValueError(
                f"{name}_faces index vertices {int(f.min())}..{int(f.max())} but there are {p.shape[0]}; pass faces "
                f"that index {name}_vertices from 0"
            )
        arrays += [p, f]
    return (*arrays, clearance)


# --- the body -------------------------------------------------------------------------------------------------


class _BodySurface:
    """The body mesh's inside test, closest points and outer triangles (float64 NumPy in, out)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces
        tri = vertices[faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        twice_area = np.linalg.norm(normal, axis=1)
        self.size = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        solid = twice_area > 1e-14 * self.size**2  # slivers of zero area hold no closest point of their own
        self.normals = np.where(solid[:, None], normal / np.where(solid, twice_area, 1.0)[:, None], 0.0)
        self.centroids = tri.mean(1)
        self.reach = float(np.linalg.norm(tri - self.centroids[:, None], axis=2).max())
        self.solid = np.flatnonzero(solid)
        self._outer: tuple[np.ndarray, np.ndarray] | None = None
        device = backend.torch_device()
        self._bvh = MeshBVH(
            torch.from_numpy(vertices).to(device), torch.from_numpy(faces).to(device), winding_numbers=True
        )
        self._tree = cKDTree(vertices[np.unique(faces)])

    def inside(self, points: np.ndarray) -> np.ndarray:
        """``[P]`` bool: generalised winding number above ½."""
        return self._bvh.inside(torch.from_numpy(points).to(backend.torch_device())).cpu().numpy()

    def meets(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """``[E]`` bool: the segments ``start → end`` (``[E, 3]`` each) meet the surface."""
        device = backend.torch_device()
        p, q = (torch.from_numpy(a).to(device) for a in (start, end))
        length = torch.linalg.vector_norm(q - p, dim=1)
        hits = self._bvh.cast(p, q - p).t.to(length) < length  # a zero-length segment casts no ray: inf
        return hits.cpu().numpy()

    def outer(self) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the triangles of the outer surface: the solid ones not buried, and those of them with no
        corner on a buried triangle (wholly outer; the others may cross into another part)."""
        if self._outer is None:
            probe = self.centroids + _PROBE_OFFSET * self.size * self.normals
            buried = np.zeros(self.faces.shape[0], dtype=bool)
            buried[self.solid] = self.inside(probe[self.solid])
            exposed = self.solid[~buried[self.solid]]
            corner = np.zeros(self.vertices.shape[0], dtype=bool)
            corner[self.faces[buried]] = True
            clear = exposed[~corner[self.faces[exposed]].any(1)]
            self._outer = (exposed if exposed.size else self.solid, clear if clear.size else exposed)
        return self._outer

    def closest(self, points: np.ndarray, among: np.ndarray):
        """Closest points ``[P, 3]``, distances ``[P]`` and triangles ``[P]`` (indices into ``faces``) among the
        triangles ``among``."""
        c, d, f, _ = surface_closest_points(
            torch.from_numpy(self.vertices), torch.from_numpy(self.faces[among]), torch.from_numpy(points)
        )
        return c.numpy(), d.numpy(), among[f.numpy()]

    def offending(self, points: np.ndarray, gap: float, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which of ``points [P, 3]`` lie inside or within ``gap − tol`` of the surface (``[K]`` indices), and the
        half-space each must move into, ``(y − c) · n ≥ gap``: ``c [K, 3]`` its closest surface point (of the outer
        surface for one inside), ``n [K, 3]`` the outward unit direction there."""
        inside = self.inside(points)
        # a triangle's points lie within 2·reach of its nearest corner: farther from every vertex, farther than gap
        near = self._tree.query(points, distance_upper_bound=gap + 2.0 * self.reach)[0] < gap + 2.0 * self.reach
        index_in, index_out = np.flatnonzero(inside), np.flatnonzero(near & ~inside)
        found = [(index_out[:0], np.zeros((0, 3)), np.zeros((0, 3)))]
        if index_out.size:
            q = points[index_out]
            c, d, f = self.closest(q, self.solid)
            keep = d < gap - tol
            index_out, q, c, d, f = index_out[keep], q[keep], c[keep], d[keep], f[keep]
            off = d > _ALONG_NORMAL * gap
            found.append(
                (index_out, c, np.where(off[:, None], (q - c) / np.where(off, d, 1.0)[:, None], self.normals[f]))
            )
        if index_in.size:
            q = points[index_in]
            exposed, clear = self.outer()
            c, _, f = self.closest(q, exposed)
            n = self.normals[f]
            if clear.size < exposed.size:
                # the closest point may lie on the buried part of a triangle that crosses into another part:
                # where that leads inside, take the closest point of the triangles wholly outside instead
                again = np.flatnonzero(self.inside(c + gap * n))
                if again.size:
                    c[again], _, f = self.closest(q[again], clear)
                    n[again] = self.normals[f]
            found.append((index_in, c, n))
        return tuple(np.concatenate(part) for part in zip(*found, strict=True))


def _push_out(x: np.ndarray, active: np.ndarray, body: _BodySurface, gap: float, tol: float, iterations: int):
    """Move the offending ones of the vertices ``active`` into their half-spaces (:meth:`_BodySurface.offending`),
    in place, testing the moved ones again up to ``iterations`` times. Returns ``(moved [V] bool, offending at first
    [K], offending at last [L])``.

    A vertex offending again after a move sits where the surface folds back on itself (a crease between two body
    parts): moving it into the new half-space alone can leave the last one, and alternating between the two closes
    in on their common corner only geometrically (by 15× a round in the crease of the tests' two spheres, and the
    slower the narrower the crease). So it moves to the nearest point of both half-spaces where the new one alone
    would leave the last."""
    pushed = np.zeros(x.shape[0], dtype=bool)
    last_c, last_n = np.zeros_like(x), np.zeros_like(x)
    index, c, n = body.offending(x[active], gap, tol) if active.size else (active, None, None)
    first = index = active[index]
    for _ in range(iterations):
        if not index.size:
            break
        p = x[index]
        target = c + gap * n
        again = np.flatnonzero(pushed[index])
        if again.size:
            target[again] = _into_both(p[again], c[again], n[again], last_c[index[again]], last_n[index[again]], gap)
        x[index] = target
        pushed[index] = True
        last_c[index], last_n[index] = c, n
        active = index
        index, c, n = body.offending(x[active], gap, tol)
        index = active[index]
    return pushed, first, index


def _into_both(p: np.ndarray, c: np.ndarray, n: np.ndarray, c0: np.ndarray, n0: np.ndarray, gap: float) -> np.ndarray:
    """``[K, 3]``: the points ``p`` moved into the half-space ``(y − c) · n ≥ gap``, and where that alone leaves
    ``(y − c0) · n0 ≥ gap``, to the nearest point of both (both bounds active: ``y = p + a n + b n0``, ``a, b ≥ 0``);
    where no such point exists (parallel planes, or one bound inactive) into the first alone."""
    alone = p + (gap - ((p - c) * n).sum(1))[:, None] * n
    short = ((alone - c0) * n0).sum(1) < gap
    cos = (n * n0).sum(1)
    det = 1.0 - cos**2
    r, r0 = gap - ((p - c) * n).sum(1), gap - ((p - c0) * n0).sum(1)
    a = (r - cos * r0) / np.where(det > 0.0, det, 1.0)
    b = (r0 - cos * r) / np.where(det > 0.0, det, 1.0)
    both = short & (det > 1e-6) & (a >= 0.0) & (b >= 0.0)
    return np.where(both[:, None], p + a[:, None] * n + b[:, None] * n0, alone)


# --- the garment against itself -------------------------------------------------------------------------------


def _crossing_pairs(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``[K, 2]`` pairs of triangles sharing no vertex that cross or touch each other (coplanar overlaps left out;
    a vertex within :data:`_PLANE_TOLERANCE` of the garment's size from a triangle's plane counts as in it)."""
    tri = x[faces]
    centroid = tri.mean(1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max(1)
    # triangles binned by their radius, each bin's pairs with itself and with every larger bin searched within the
    # two bins' largest radii: a few large triangles do not widen the search of all the others
    size = np.floor(np.log(np.maximum(radius, 1e-12) / max(float(radius.max()), 1e-12)) / np.log(_RADIUS_BIN))
    bins = [np.flatnonzero(size == k) for k in np.unique(size)]
    trees = [cKDTree(centroid[b]) for b in bins]
    widest = [float(radius[b].max()) for b in bins]
    found = []
    for k, (bin_k, tree_k) in enumerate(zip(bins, trees, strict=True)):
        found.append(bin_k[tree_k.query_pairs(2.0 * widest[k], output_type="ndarray")].reshape(-1, 2))
        for m in range(k + 1, len(bins)):
            near = tree_k.sparse_distance_matrix(trees[m], widest[k] + widest[m], output_type="ndarray")
            found.append(np.stack([bin_k[near["i"]], bins[m][near["j"]]], 1))
    pairs = np.concatenate(found)
    a, b = pairs[:, 0], pairs[:, 1]
    reach = np.linalg.norm(centroid[a] - centroid[b], axis=1) <= radius[a] + radius[b]
    shared = (faces[a][:, :, None] == faces[b][:, None, :]).any((1, 2))
    pairs = pairs[reach & ~shared]
    t, u = tri[pairs[:, 0]], tri[pairs[:, 1]]
    tol = _PLANE_TOLERANCE * float(np.linalg.norm(x.max(0) - x.min(0)))
    cross = np.zeros(pairs.shape[0], dtype=bool)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        cross |= _segment_crosses(t[:, i], t[:, j], u, tol) | _segment_crosses(u[:, i], u[:, j], t, tol)
    return pairs[cross]


def _segment_crosses(p: np.ndarray, q: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """``[K]`` bool: segment ``p → q`` meets triangle ``tri [K, 3, 3]``; an end within ``tol`` (m) of the triangle's
    plane counts as in it: touching counts, a segment in the plane does not (coplanar triangles are left out).

    Two non-coplanar triangles intersect exactly when an edge of one meets the other: the ends of their common
    segment lie on their edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1)
    n = n / np.where(length > 0.0, length, np.inf)[:, None]  # a degenerate triangle crosses nothing
    hp, hq = ((p - a) * n).sum(1), ((q - a) * n).sum(1)
    on_p, on_q = np.abs(hp) <= tol, np.abs(hq) <= tol
    straddle = ((hp < -tol) & (hq > tol)) | ((hp > tol) & (hq < -tol)) | (on_p ^ on_q)
    d = q - p
    s = [(np.cross(e - p, f - p) * d).sum(1) for e, f in ((a, b), (b, c), (c, a))]
    through = ((s[0] >= 0) & (s[1] >= 0) & (s[2] >= 0)) | ((s[0] <= 0) & (s[1] <= 0) & (s[2] <= 0))
    return straddle & through


def _crossing_vertices(x: np.ndarray, faces: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``[V]`` bool: vertices of the triangles in ``pairs``."""
    on = np.zeros(x.shape[0], dtype=bool)
    on[faces[pairs.reshape(-1)]] = True
    return on


def _separate(x: np.ndarray, faces: np.ndarray, pairs: np.ndarray, gap: float) -> np.ndarray:
    """Push each crossing pair's triangles apart, in place, along the mean of their unit normals (the second turned
    to agree with the first: the normal of the two layers), each by half the overlap of their projections on it plus
    ``gap / 2``, toward the side that needs less; a vertex in several pairs moves by the mean of their pushes.
    Returns ``[V]`` bool, the moved vertices.

    The mean normal moved layered cloth apart more often than either triangle's own normal: on a folded strip whose
    upper layer dips through the lower one, 4 of 5 dips against 2 of 5 with the normal that needs less."""
    f, g = faces[pairs[:, 0]], faces[pairs[:, 1]]
    t, u = x[f], x[g]
    n_t, n_u = (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) for tri in (t, u))
    n_t, n_u = (n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None] for n in (n_t, n_u))
    axis = n_t + np.where((n_t * n_u).sum(1) < 0.0, -1.0, 1.0)[:, None] * n_u
    length = np.linalg.norm(axis, axis=1)
    ok = length > 0.5  # both triangles have a normal (a degenerate one has none and is left to its neighbours)
    axis = axis[ok] / length[ok, None]
    f, g, t, u = f[ok], g[ok], t[ok], u[ok]
    pt, pu = (t * axis[:, None]).sum(2), (u * axis[:, None]).sum(2)
    above, below = pt.max(1) - pu.min(1), pu.max(1) - pt.min(1)  # u moved up past t, or down
    side = np.where(above <= below, 1.0, -1.0)
    push = (0.5 * (np.minimum(above, below) + gap) * side)[:, None] * axis  # u moves by +push, t by −push
    total = np.zeros_like(x)
    count = np.zeros(x.shape[0])
    for index, sign in ((g, 1.0), (f, -1.0)):
        for k in range(3):
            total += np.stack([np.bincount(index[:, k], sign * push[:, c], x.shape[0]) for c in range(3)], 1)
            count += np.bincount(index[:, k], minlength=x.shape[0])
    moved = count > 0
    x[moved] += total[moved] / count[moved, None]
    return moved


def _edges(faces: np.ndarray) -> np.ndarray:
    """``[E, 2]`` the triangles' edges, each once, lower index first."""
    return np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)


# --- neighbours -----------------------------------------------------------------------------------------------


def _relax(
    x: np.ndarray, x0: np.ndarray, faces: np.ndarray, moved: np.ndarray, body: _BodySurface, gap: float, tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Spread the moves ``x − x0`` into the rings around ``moved``, in place (see :func:`resolve_intersections`).
    Returns ``[V]`` bool, the vertices displaced this way, and ``[V]`` bool, the vertices on crossing triangles
    after."""
    v = x.shape[0]
    edges = _edges(faces)
    i, j = edges[:, 0], edges[:, 1]
    region, ring = np.zeros(v, dtype=bool), moved.copy()
    for _ in range(RELAX_RINGS):
        nearby = np.zeros(v, dtype=bool)
        nearby[j[ring[i]]] = True
        nearby[i[ring[j]]] = True
        ring = nearby & ~moved & ~region
        region |= ring
    free = np.flatnonzero(region)
    if not free.size:
        return region, _crossing_vertices(x, faces, _crossing_pairs(x, faces))
    degree = np.bincount(i, minlength=v) + np.bincount(j, minlength=v)
    shift = x - x0
    for _ in range(RELAX_PASSES):
        total = np.stack([np.bincount(i, shift[j, c], v) + np.bincount(j, shift[i, c], v) for c in range(3)], 1)
        shift[free] = total[free] / degree[free, None]
    # keep in place whatever would come too near the body, then whatever ends on a crossing triangle
    stay = free[body.offending(x0[free] + shift[free], gap, tol)[0]]
    shift[stay] = 0.0
    x[free] = x0[free] + shift[free]
    crossing = _crossing_vertices(x, faces, _crossing_pairs(x, faces))
    back = free[crossing[free]]
    if back.size:
        x[back] = x0[back]
        crossing = _crossing_vertices(x, faces, _crossing_pairs(x, faces))
    relaxed = np.zeros(v, dtype=bool)
    relaxed[free] = (x[free] != x0[free]).any(1)
    return relaxed, crossing
