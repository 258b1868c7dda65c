"""Refine a triangle mesh by splitting its long edges at their midpoints, leaving its rest surface unchanged.

A mesh carried by the Q-GMLS displacement field, x(X) = X + Σ_s N_s(X) q_s (Eq. 9), moves only its vertices; each
triangle stays flat between them. Where an edge is long against the distance over which the field bends, the
deformed mesh shows the chord instead of the bend: the teapot's rod is one 0.6 m cylinder between two rings of
vertices, so bent by the drag it stays a straight segment (Fig. 8). :func:`split_long_edges` adds vertices until every
edge is shorter than a given length. Midpoints of straight edges and barycentric colours lie on the same flat
triangles, so the refined mesh renders the rest state exactly as the original does; only the deformed shape gains
detail.

Each pass marks every edge longer than the limit (an edge shared by two triangles is split for both, so the mesh
stays conforming, with no T-junctions) and replaces each triangle by the template of its marked edges: two triangles
for one, three for two (the remaining quad cut along its shorter diagonal), four for three. Triangles keep their
winding. Edges halve each pass, so a mesh whose longest edge is L needs about log2(L / limit) passes.
"""

from __future__ import annotations

import math

import torch

__all__ = ["MAX_REFINED_VERTICES", "split_long_edges"]

MAX_REFINED_VERTICES = 2_000_000
"""Default limit on the refined mesh's vertices: past it :func:`split_long_edges` stops with an error."""


def split_long_edges(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    attributes: torch.Tensor | None = None,
    max_edge: float = math.inf,
    max_vertices: int = MAX_REFINED_VERTICES,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Split edges longer than ``max_edge`` at their midpoints until none is left (module docstring).

    Args:
        vertices: ``[V, 3]`` positions (m).
        faces: ``[F, 3]`` vertex indices, any winding (kept).
        attributes: ``[V, C]`` per-vertex values interpolated linearly along the edges (e.g. albedo), or ``None``.
        max_edge: longest edge allowed in the result (m), > 0.
        max_vertices: stop with an error rather than produce more vertices than this.

    Returns:
        ``(vertices [V', 3], faces [F', 3], attributes [V', C] or None)`` in the input's dtypes and device. The
        first ``V`` vertices are the input's, in order, so indices into the original mesh stay valid.

    Raises:
        ValueError: malformed input, ``max_edge`` not > 0, or a result past ``max_vertices`` (raise ``max_edge``).
    """
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be [V, 3], got {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F, 3] vertex indices, got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]):
        raise ValueError(f"faces index vertices outside [0, {vertices.shape[0]})")
    if attributes is not None and (attributes.dim() != 2 or attributes.shape[0] != vertices.shape[0]):
        raise ValueError(f"attributes must be [V, C] with V = {vertices.shape[0]}, got {tuple(attributes.shape)}")
    if not (isinstance(max_edge, (int, float)) and max_edge > 0 and not math.isnan(max_edge)):
        raise ValueError(f"max_edge must be a positive length in metres, got {max_edge!r}")
    face_dtype = faces.dtype
    x = vertices.double()
    values = attributes.double() if attributes is not None else None
    tri = faces.long()
    while tri.numel():
        edges = torch.stack([tri, tri.roll(-1, dims=1)], dim=-1)  # [F, 3, 2]: edge k runs from corner k to k + 1
        unique, edge_of = torch.unique(edges.sort(dim=-1).values.reshape(-1, 2), dim=0, return_inverse=True)
        long = (x[unique[:, 0]] - x[unique[:, 1]]).norm(dim=1) > max_edge
        if not bool(long.any()):
            break
        split = unique[long]
        if x.shape[0] + split.shape[0] > max_vertices:
            raise ValueError(
                f"splitting edges down to {max_edge:.4g} m would make more than {max_vertices} vertices; "
                "raise max_edge (or max_vertices)"
            )
        midpoint = torch.full((unique.shape[0],), -1, dtype=torch.long, device=tri.device)
        midpoint[long] = torch.arange(split.shape[0], device=tri.device) + x.shape[0]
        x = torch.cat([x, 0.5 * (x[split[:, 0]] + x[split[:, 1]])])
        if values is not None:
            values = torch.cat([values, 0.5 * (values[split[:, 0]] + values[split[:, 1]])])
        tri = _split_faces(tri, midpoint[edge_of.reshape(-1, 3)], x)
    refined = (x.to(vertices.dtype), tri.to(face_dtype))
    return (*refined, values.to(attributes.dtype) if attributes is not None else None)


def _split_faces(tri: torch.Tensor, middle: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Replace each triangle ``tri [F, 3]`` by the template of its split edges; ``middle [F, 3]`` holds the new
    vertex on edge k (corner k to k + 1), −1 where that edge stays whole."""
    marked = middle >= 0
    count = marked.sum(1)
    # Turn each triangle so that its split edges come first (one: edge 0; two: edges 0 and 1), keeping the winding.
    first = torch.where(count == 1, marked.int().argmax(1), (~marked).int().argmax(1) + 1) % 3
    turn = (torch.arange(3, device=tri.device)[None, :] + first[:, None]) % 3
    v, m = tri.gather(1, turn), middle.gather(1, turn)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
    out = [tri[count == 0]]
    one = count == 1
    out += [torch.stack(t, 1)[one] for t in ((a, ab, c), (ab, b, c))]
    two = count == 2
    # The quad a, ab, bc, c: cut along the shorter of its diagonals a–bc and ab–c.
    short = (x[a] - x[bc.clamp_min(0)]).norm(dim=1) <= (x[ab.clamp_min(0)] - x[c]).norm(dim=1)
    out += [torch.stack(t, 1)[two] for t in ((ab, b, bc),)]
    out += [torch.stack(t, 1)[two & short] for t in ((a, ab, bc), (a, bc, c))]
    out += [torch.stack(t, 1)[two & ~short] for t in ((a, ab, c), (ab, bc, c))]
    three = count == 3
    out += [torch.stack(t, 1)[three] for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    return torch.cat(out)
