"""Contact of the garment simulator: candidate pairs, their covers, the broad phase, the CCD bound and friction.

A step's contact candidates are the point–triangle and edge–edge pairs (garment–body first, then garment–garment)
whose boxes come within the IPC activation distance ``d̂`` of each other (Li et al. 2020). :class:`ClothContact`
finds them once per step along each vertex's predicted path (a :class:`ContactCover`), filters them for every
Newton sweep that stays inside that cover, bounds each sweep by additive CCD (:mod:`kernels.ccd`) and computes the
lagged friction data at the start of the step (IPC §5, :mod:`kernels.friction`). The barrier energies of the
candidates are the incremental potential's (:mod:`physavatar.cloth.potential`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from kernels import backend, ccd, ipc_barrier
from kernels import contact as kernels_contact
from kernels import friction as kernels_friction
from kernels.broad_phase import BoxTree, OverlapQuery, OverlapSearch
from kernels.raycast import MeshBVH
from physavatar.cloth.config import ClothConfig

__all__ = [
    "PARALLEL_SIN2",
    "REACH",
    "TREE_REBUILD",
    "ClothContact",
    "ContactCover",
    "ContactPairs",
    "GarmentDistances",
    "LaggedFriction",
    "compact_rows",
    "friction_potential",
    "garment_distances",
    "keep_pairs",
]


class ContactPairs(NamedTuple):
    """Contact candidates: ``pt [P, 4]``, ``ee [Q, 4]`` int32, how many of each lead (garment–body first), and the
    edge pairs' mollifier thresholds ``ε_x [Q]`` (:func:`kernels.ipc_barrier.edge_edge_mollifier_threshold`, found with
    the candidates and carried along with them)."""

    pt: torch.Tensor
    ee: torch.Tensor
    pt_body: int
    ee_body: int
    ee_eps: torch.Tensor


class ContactCover(NamedTuple):
    """Contact candidates valid while every vertex sweeps inside its box ``[lo, hi]`` (``[V + B, 3]`` each)."""

    lo: torch.Tensor
    hi: torch.Tensor
    pairs: ContactPairs


class LaggedFriction(NamedTuple):
    """Lagged friction data of the contacts at the start of the step (IPC §5)."""

    index: torch.Tensor  # [K, 4] long
    weight: torch.Tensor  # [K, 4] closest-point weights: Δ = Σ w_i x_i is the gap vector
    projector: torch.Tensor  # [K, 3, 3] I − n nᵀ
    force: torch.Tensor  # [K] μ λ, N


PARALLEL_SIN2 = 1e-8
"""Edge pairs closer to parallel than ``sin²θ < 10⁻⁸`` over a whole sweep leave the edge–edge candidates.

Their distance is the smallest end point–segment distance, which the point–triangle pairs of the edges' triangles
already bound; the edge-edge kernels classify such pairs by a machine-epsilon test and can report a line-line
distance of 0 for parallel, separated edges."""

REACH = 2.0
"""Contact pairs within ``REACH · d̂`` of each other join the Newton matrix's sparsity pattern when it grows (active
or not yet), so that pairs that close in later seldom change it (each change costs cuDSS a new analysis)."""

TREE_REBUILD = 32
"""On CUDA the candidate search's BVHs are refitted to the garment's new boxes and built anew every this many
searches (:meth:`ClothContact.box_pairs`)."""


def friction_potential(
    displacement: torch.Tensor, friction: LaggedFriction, eps: float, hessian: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """IPC's smoothed lagged friction potential ``D = Σ_k μλ_k f₀(‖u_k‖)`` (Li et al. 2020, Eq. 14–16) of the lagged
    contacts, by the Warp kernel :func:`kernels.friction.friction_potential`.

    Args:
        displacement: ``[N, 3]`` displacement of every vertex since the start of the step, m.
        friction: lagged contacts.
        eps: ``ε_v Δt``, m.
        hessian: also return the ``[K, 12, 12]`` Hessians (PSD).

    Returns:
        ``(energy [K] (J), grad [K, 4, 3] (N), hess [K, 12, 12] or None)``.
    """
    f = friction
    return kernels_friction.friction_potential(displacement, f.index, f.weight, f.projector, f.force, eps, hessian)


def keep_pairs(pairs: ContactPairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor) -> ContactPairs:
    """The pairs selected by the masks (one read from the device: the counts size the selections)."""
    return _select(pairs, pt_keep, ee_keep, _counts(pairs, pt_keep, ee_keep).tolist())


def _counts(pairs: ContactPairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor) -> torch.Tensor:
    """``[4]`` on the device: the garment–body and all point–triangle pairs the masks select, then the same for the
    edge–edge pairs."""
    return torch.stack([pt_keep[: pairs.pt_body].sum(), pt_keep.sum(), ee_keep[: pairs.ee_body].sum(), ee_keep.sum()])


def _select(pairs: ContactPairs, pt_keep: torch.Tensor, ee_keep: torch.Tensor, counts: list[int]) -> ContactPairs:
    """The pairs selected by the masks, given their :func:`_counts` as read from the device."""
    pt_body, pt, ee_body, ee = counts
    pt_rows = torch.nonzero_static(pt_keep, size=pt).squeeze(1)
    ee_rows = torch.nonzero_static(ee_keep, size=ee).squeeze(1)
    return ContactPairs(
        pairs.pt.index_select(0, pt_rows),
        pairs.ee.index_select(0, ee_rows),
        pt_body,
        ee_body,
        pairs.ee_eps.index_select(0, ee_rows),
    )


def _unique_edges(faces: torch.Tensor) -> torch.Tensor:
    f = faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    return torch.unique(e, dim=0)


def compact_rows(mask: torch.Tensor, size: int | None = None) -> torch.Tensor:
    """Rows where ``mask`` holds, in order: all of them (their number is read from the device), or exactly ``size``
    rows with the last row of the masked array filling the rest (no read: the caller checks the count)."""
    if size is None:
        return mask.nonzero().squeeze(1)
    return torch.nonzero_static(mask, size=size, fill_value=mask.shape[0] - 1).squeeze(1)


class ClothContact:
    """Contact candidates, sweeps, CCD bounds and lagged friction of a garment against itself and a body collider.

    Vertices ``0 … V − 1`` are the garment's, ``V … V + B − 1`` the body's, in every position array ``X [V + B, 3]``
    it is given (m, float64).

    Args:
        faces: ``[F, 3]`` int32 garment triangles on the backend device.
        body_faces: ``[Fb, 3]`` integer body triangles indexing the body's ``B`` vertices; may be empty.
        vertex_count: the garment's ``V``.
        body_vertex_count: the body's ``B``.
        config: the contact distance ``d̂``, CCD's ``η`` and the friction coefficient are read from it.
    """

    def __init__(
        self,
        faces: torch.Tensor,
        body_faces: torch.Tensor,
        vertex_count: int,
        body_vertex_count: int,
        config: ClothConfig,
    ):
        device = backend.torch_device()
        self.config = config
        self.faces = faces
        self.edges = _unique_edges(self.faces)
        v = vertex_count
        self.body_faces = (body_faces.to(device).long() + v).contiguous()
        self.body_edges = _unique_edges(body_faces.to(device)) + v if body_faces.numel() else self.edges[:0]
        # the primitives of the broad phase, as int32 vertex tuples
        self._points = torch.arange(v, dtype=torch.int32, device=device)[:, None].contiguous()
        self._edges = self.edges.to(torch.int32).contiguous()
        body_points = torch.arange(v, v + body_vertex_count, dtype=torch.int32, device=device)
        self._body_points = body_points[:, None].contiguous()
        self._body_faces = self.body_faces.to(torch.int32).contiguous()
        self._body_edges = self.body_edges.to(torch.int32).contiguous()
        self._search = OverlapSearch()  # box_pairs' five requests, each in one walk
        # box_pairs' BVHs (garment points, triangles, edges; body points, edges), refitted on CUDA
        self._trees: tuple[BoxTree, ...] | None = None
        self._tree_age = 0  # searches since they were built

    def broad_phase(
        self, X: torch.Tensor, p: torch.Tensor, kinematic: torch.Tensor, x_rest: torch.Tensor
    ) -> ContactPairs:
        """Contact candidates whose boxes, swept over ``X → X + p`` and grown by ``d̂``, overlap (IPC); ``kinematic``
        and ``x_rest`` as :meth:`box_pairs` takes them."""
        return self.swept(X, p, self.cover(X, X + p, kinematic, x_rest, 0.0))

    def cover(
        self, X: torch.Tensor, end: torch.Tensor, kinematic: torch.Tensor, x_rest: torch.Tensor, margin: float
    ) -> ContactCover:
        """Candidates of every sweep that keeps each vertex inside the box of its segment ``X → end`` grown by
        ``margin``: pairs whose primitives' boxes (unions of their vertices' boxes, the query side grown by ``d̂``)
        overlap. Pairs of kinematic vertices only are left out (``kinematic`` and ``x_rest`` as :meth:`box_pairs`
        takes them).

        Growing each box by its segment's own extent as well (so that Newton may overshoot the prediction) halved
        the searches of the 1252-face skirt walking but tripled the candidates; filtering them then cost more on
        the CPU than the searches saved."""
        lo, hi = torch.minimum(X, end) - margin, torch.maximum(X, end) + margin
        return ContactCover(lo, hi, self.box_pairs(lo, hi, kinematic, x_rest))

    @staticmethod
    def covers(cover: ContactCover, X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Whether the sweep ``X → X + p`` keeps every vertex inside its box of ``cover`` (0-d bool, on the device:
        the caller reads it with the step's other flags)."""
        end = X + p
        inside = (torch.minimum(X, end) >= cover.lo) & (torch.maximum(X, end) <= cover.hi)
        return inside.all()

    def swept(self, X: torch.Tensor, p: torch.Tensor, cover: ContactCover) -> ContactPairs:
        """The candidates of ``cover`` whose boxes, swept over ``X → X + p`` and grown by ``d̂``, overlap, less
        edge pairs parallel at both ends of the sweep (:data:`PARALLEL_SIN2`). Equal to a fresh search of the sweep
        when ``cover`` covers it (:meth:`covers`)."""
        return keep_pairs(cover.pairs, *self.sweep_masks(X, p, cover))

    def sweep_masks(self, X: torch.Tensor, p: torch.Tensor, cover: ContactCover) -> tuple[torch.Tensor, torch.Tensor]:
        """The masks of :meth:`swept` over ``cover``'s point–triangle and edge–edge candidates (no read)."""
        dhat = self.config.contact_distance
        pairs = cover.pairs
        pt_keep = kernels_contact.pair_boxes_overlap(X, p, pairs.pt, 1, dhat)
        return pt_keep, kernels_contact.pair_boxes_overlap(X, p, pairs.ee, 2, dhat, parallel=PARALLEL_SIN2)

    def box_pairs(
        self, lo: torch.Tensor, hi: torch.Tensor, kinematic: torch.Tensor, x_rest: torch.Tensor
    ) -> ContactPairs:
        """Pairs whose primitives' boxes overlap, given each vertex's box ``[lo, hi]`` (the query side grown by
        ``d̂``): garment vertices and edges against body triangles and edges, then the garment against itself.
        Pairs that share a vertex or whose vertices are all kinematic (``kinematic [V + B]`` bool) are left out;
        the edge pairs' mollifier thresholds come from the rest positions ``x_rest [V + B, 3]`` (m).

        Which side of a garment–body request is the tree was measured (skirt7271 on the walking mannequin; figures
        in ``docs/benchmarks.md``): body triangles walk the garment's points (as fast as the other way round), while
        the garment's triangles walk the body's points and its edges the body's edges, several times faster than the
        reverse: the body primitives inside the skirt's box but far from the cloth made the long walks."""
        dhat = self.config.contact_distance
        lo, hi = lo.contiguous(), hi.contiguous()
        points, triangles, edges, body_points, body_edges = self._boxes_trees(lo, hi)
        pt_vb, pt_bv, ee_b, pt_self, ee_self = self._search(
            [  # garment vertices against body triangles, body vertices against garment triangles, body edges
                OverlapQuery(points, self._body_faces, dhat, kinematic, tree_first=True),
                OverlapQuery(body_points, self.faces, dhat, kinematic, tree_first=True),
                OverlapQuery(body_edges, self._edges, dhat, kinematic),
                # then the garment against itself
                OverlapQuery(triangles, self._points, dhat, kinematic),
                OverlapQuery(edges, self._edges, dhat, kinematic, same=True),
            ]
        )
        pt_body, ee_body = pt_vb.shape[0] + pt_bv.shape[0], ee_b.shape[0]
        ee = torch.cat([ee_b, ee_self])
        eps = ipc_barrier.edge_edge_mollifier_threshold(x_rest, ee)
        return ContactPairs(torch.cat([pt_vb, pt_bv, pt_self]), ee, pt_body, ee_body, eps)

    def _boxes_trees(self, lo: torch.Tensor, hi: torch.Tensor) -> tuple[BoxTree, ...]:
        """The BVHs of the garment's points, triangles and edges and of the body's points and edges over the vertex
        boxes ``lo``, ``hi``.

        On CUDA the trees outlive the search and are refitted (:meth:`kernels.broad_phase.BoxTree.refit`), built
        anew every :data:`TREE_REBUILD` searches: garment and body keep their neighbourhoods, so a hierarchy stays
        good for many frames (the walks of a six-searches-old refitted tree took as long as a fresh one's), and
        builds cost a search of skirt7271 many times what refits do (``docs/benchmarks.md``). On the
        CPU (Warp's SAH build on one thread) they are built every time: the pairs come in the tree's order, which a
        refit would change, and the CPU's results stay those of a fresh build."""
        if lo.device.type != "cuda" or self._trees is None or self._tree_age >= TREE_REBUILD:
            prims = (self._points, self.faces, self._edges, self._body_points, self._body_edges)
            self._trees = tuple(BoxTree(lo, hi, p) for p in prims)
            self._tree_age = 0
        else:
            for tree in self._trees:
                tree.refit(lo, hi)
        self._tree_age += 1
        return self._trees

    def near(self, X: torch.Tensor, pairs: ContactPairs) -> ContactPairs:
        """The candidates whose boxes at ``X`` lie within ``d̂`` (a superset of the active barrier pairs)."""
        dhat = self.config.contact_distance
        pt_keep = kernels_contact.pair_boxes_overlap(X, None, pairs.pt, 1, dhat)
        return keep_pairs(pairs, pt_keep, kernels_contact.pair_boxes_overlap(X, None, pairs.ee, 2, dhat))

    def ccd_bound(self, X: torch.Tensor, p: torch.Tensor, pairs: ContactPairs) -> torch.Tensor:
        """Largest step fraction in ``[0, 1]`` that additive CCD certifies intersection-free (Li et al. 2021), 0-d on
        the device."""
        eta = self.config.ccd_eta
        times = [X.new_ones(1)]
        if pairs.pt.shape[0]:
            times.append(ccd.point_triangle_ccd(X, p, pairs.pt, eta=eta))
        if pairs.ee.shape[0]:
            times.append(ccd.edge_edge_ccd(X, p, pairs.ee, eta=eta))
        return torch.cat(times).min()

    def lagged_friction(self, X: torch.Tensor, pairs: ContactPairs, kappa: float) -> LaggedFriction:
        """Normal forces ``μλ_k``, closest-point weights and tangent projectors of the contacts at ``x^t`` (IPC §5),
        by the Warp kernel :func:`kernels.friction.lagged_contacts`; ``kappa`` is the barrier stiffness ``κ``, J/m⁴."""
        dhat2, mu = self.config.contact_distance**2, self.config.friction
        return LaggedFriction(*kernels_friction.lagged_contacts(X, pairs.pt, pairs.ee, pairs.ee_eps, dhat2, kappa, mu))

    def min_distances(
        self, X: torch.Tensor, pairs: ContactPairs, masks: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[float, float, int]:
        """Smallest garment–body and garment–garment distances among the pairs (those ``masks`` select, when given),
        m (inf where there are none), and the number of pairs within ``d̂``; one read from the device."""
        dhat2 = self.config.contact_distance**2
        d_pt = ipc_barrier.point_triangle_distance_value(X, pairs.pt)
        d_ee = ipc_barrier.edge_edge_distance_value(X, pairs.ee)
        if masks is not None:
            d_pt, d_ee = (torch.where(mask, d, math.inf) for mask, d in zip(masks, (d_pt, d_ee), strict=True))
        inf = X.new_full((1,), math.inf)
        body = torch.cat([d_pt[: pairs.pt_body], d_ee[: pairs.ee_body], inf])
        own = torch.cat([d_pt[pairs.pt_body :], d_ee[pairs.ee_body :], inf])
        contacts = (body < dhat2).sum() + (own < dhat2).sum()
        body, own, contacts = torch.stack([body.min(), own.min(), contacts.to(X.dtype)]).tolist()
        return math.sqrt(max(body, 0.0)), math.sqrt(max(own, 0.0)), int(contacts)


class GarmentDistances(NamedTuple):
    """How close a garment comes to a body and to itself (:func:`garment_distances`).

    Attributes:
        body: smallest garment–body distance, m; ``inf`` where nothing lies within the reach.
        garment: smallest distance between garment primitives that share no vertex, m; ``inf`` likewise.
        inside: garment vertices inside the closed body mesh (by its winding number).
    """

    body: float
    garment: float
    inside: int


def garment_distances(
    x: torch.Tensor, faces: torch.Tensor, body_x: torch.Tensor, body_faces: torch.Tensor, reach: float = 1e-2
) -> GarmentDistances:
    """Garment–body and garment–garment distances and the vertices inside the body, measured as the garment
    simulator measures its own steps: the point–triangle and edge–edge pairs of :meth:`ClothContact.box_pairs`
    (pairs that share a vertex left out), their distances by :mod:`kernels.ipc_barrier`
    (:meth:`ClothContact.min_distances`), and the body's winding number (:meth:`kernels.raycast.MeshBVH.inside`).

    The distances are unsigned: a vertex through the body counts by ``inside``, not by a negative distance. Any
    positions will do (another simulator's output, say); they are float64 copies on the backend device.

    Args:
        x: ``[V, 3]`` garment vertices, m.
        faces: ``[F, 3]`` integer garment triangles.
        body_x: ``[B, 3]`` body vertices, m.
        body_faces: ``[Fb, 3]`` integer body triangles, closed and outward-oriented for ``inside``.
        reach: distances up to this are exact, m; beyond it they are reported as ``inf``.

    Returns:
        :class:`GarmentDistances`.
    """
    if not (math.isfinite(reach) and reach > 0.0):
        raise ValueError(f"reach ({reach}) must be a positive distance, m")
    for name, points in (("x", x), ("body_x", body_x)):
        if points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"{name} must be a [N, 3] tensor of positions, got {tuple(points.shape)}")
    device = backend.torch_device()
    v, b = x.shape[0], body_x.shape[0]
    X = torch.cat([x.detach().to(device, torch.float64), body_x.detach().to(device, torch.float64)]).contiguous()
    contact = ClothContact(
        faces.to(device, torch.int32).contiguous(), body_faces, v, b, ClothConfig(contact_distance=reach)
    )
    kinematic = torch.zeros(v + b, dtype=torch.bool, device=device)
    kinematic[v:] = True  # leaves out the body's pairs with itself
    d_body, d_garment, _ = contact.min_distances(X, contact.box_pairs(X, X, kinematic, X))
    inside = MeshBVH(X[v:], body_faces.to(device).long(), winding_numbers=True).inside(X[:v]) if b else X[:0, 0]
    # a pair's boxes within the reach need not hold the closest pair beyond it: report only distances within it
    return GarmentDistances(
        d_body if d_body <= reach else math.inf,
        d_garment if d_garment <= reach else math.inf,
        int(inside.sum()),
    )
