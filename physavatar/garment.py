"""Garment meshes for the simulator: loading, validation, placement on the body and Dirichlet boundary vertices.

PhysAvatar drives a garment by the body collider and by a few garment vertices "in permanent contact with the
human body" that follow the body's linear blend skinning (§3.2, Eq. 5: ``V^b_{t+1}``; Appendix A.3.2: the
boundary nodes follow "the nearest corresponding SMPL skinning weights"). This module turns a mesh file into
a simulation-ready garment in metres, placed outside the body, and picks and animates those vertices.

Conventions are those of :mod:`physavatar.body`: metres, y up, the body faces +z.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from physavatar.body import Body, linear_blend_skinning, surface_closest_points

__all__ = [
    "BOUNDARY_MODES",
    "DEFAULT_GARMENT",
    "MAX_GAP",
    "SHARED_GARMENTS",
    "Garment",
    "default_garment",
    "boundary_targets",
    "load_garment",
    "place_on_body",
    "procedural_skirt",
    "select_boundary",
]

BOUNDARY_MODES = ("waist", "shoulders", "auto")
SHARED_GARMENTS = (
    Path(os.environ.get("PIE_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data").expanduser()
    / "garments"
)
"""The DiffCloth garments of the project's read-only data folder (``$PIE_SHARED_DATA``, else ``../shared/data`` beside
the checkout, as :data:`pienerf.paths.SHARED_DATA`, which this package may not import); absent in a fresh clone."""
DEFAULT_GARMENT = SHARED_GARMENTS / "skirt1252.obj"
"""The garment simulated when none is given, where the shared data folder is present."""
_PLAUSIBLE_HEIGHT = (0.1, 2.0)  # m, the vertical extent of a garment worn by an adult
_TYPICAL_HEIGHT = 0.6  # m, the extent "auto" scaling aims for among powers of ten
_UNIT_NAMES = {-1: "decimetres", -2: "centimetres", -3: "millimetres", 1: "decametres"}
MAX_GAP = 0.1
"""Largest distance (m) from a garment's nearest vertex to the body surface for it to count as worn."""
_MAX_COORDINATE = 1e9  # any unit: a 2 m garment in nanometres stays below it, corrupt floats (1e308) do not


@dataclass(frozen=True, eq=False)
class Garment:
    """A triangle mesh ready for :class:`physavatar.cloth.SolverCloth`.

    Attributes:
        vertices: ``[V, 3]`` float64 rest positions, m.
        faces: ``[F, 3]`` int64 vertex indices, manifold, consistently oriented.
        name: the file's stem, or a name the caller gave.
        notes: what loading and placement changed (welds, unit rescaling, translation), one sentence each.
        vertex_map: ``[N]`` int64 for a garment read by :func:`load_garment`: the vertex (index into ``vertices``)
            that each of the file's ``N`` vertices became after welding, in the file's vertex order, ``-1`` for a
            file vertex in no triangle; ``None`` otherwise. Indices given against the file (say, its boundary
            vertices) go through it.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    name: str
    notes: tuple[str, ...] = ()
    vertex_map: torch.Tensor | None = None

    def replace(self, vertices: torch.Tensor, note: str) -> Garment:
        """The same garment with new vertex positions ``[V, 3]`` and one more note."""
        return Garment(vertices, self.faces, self.name, (*self.notes, note), self.vertex_map)


# ---------------------------------------------------------------------------------------------------------------
# Loading and validation
# ---------------------------------------------------------------------------------------------------------------


def load_garment(path: str | Path, scale: float | str | None = "auto", weld_tolerance: float = 1e-6) -> Garment:
    """Read an OBJ/PLY garment, weld duplicate vertices, validate it and bring it to metres.

    Args:
        path: mesh file (anything trimesh reads as one triangle mesh; OBJ and PLY are tested).
        scale: ``None`` keeps the file's coordinates; a number multiplies them; ``"auto"`` keeps a garment whose
            height lies in 0.1–2 m and otherwise rescales by the power of ten (cm, mm, ...) that brings the height
            closest to 0.6 m, noting the unit it assumed.
        weld_tolerance: vertices closer than this fraction of the bounding-box diagonal are merged (unwelded
            triangle soups store each corner separately).

    Returns:
        The :class:`Garment`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a triangle mesh; zero-area faces; non-manifold edges (listed); an unwelded soup that no
            weld within the tolerance makes manifold; inconsistent orientation.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"garment file {path} does not exist; pass the path of an OBJ or PLY mesh")
    file_vertices = _check_obj_lines(path) if path.suffix.lower() == ".obj" else None
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
    except Exception as error:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path.name}: cannot read a triangle mesh ({error}); export it as OBJ or PLY") from None
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3 or vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{path.name}: no triangles found; a garment must be a triangle mesh")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{path.name}: vertex coordinates hold NaN or inf")
    outside = np.flatnonzero(((faces < 0) | (faces >= vertices.shape[0])).any(1))
    if outside.size:
        raise ValueError(
            f"{path.name}: {outside.size} faces (e.g. faces {_few(outside)}) name vertices beyond its "
            f"{vertices.shape[0]}; the file is truncated or its face list is corrupt: export it again"
        )
    if np.abs(vertices).max() > _MAX_COORDINATE:
        raise ValueError(
            f"{path.name}: coordinates reach {np.abs(vertices).max():.3g}, beyond {_MAX_COORDINATE:g} in any unit "
            "a garment is modelled in; the file is corrupt or not a garment"
        )
    notes = []
    diagonal = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    count = vertices.shape[0]
    loaded = _file_order(file_vertices, vertices, diagonal)
    parent = _weld(vertices, weld_tolerance * diagonal)
    used = np.unique(parent[faces])
    renumber = np.full(count, -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    vertices, faces = vertices[used], renumber[parent[faces]]
    vertex_map = np.where(loaded >= 0, renumber[parent[loaded]], -1)
    if vertices.shape[0] < count:
        notes.append(f"welded {count} vertices into {vertices.shape[0]} (tolerance {weld_tolerance:g} × size)")
    _validate(vertices, faces, path.name, welded=bool(notes))
    vertices, note = _rescale(vertices, scale, path.name)
    if note:
        notes.append(note)
    return Garment(
        torch.from_numpy(vertices), torch.from_numpy(faces), path.stem, tuple(notes), torch.from_numpy(vertex_map)
    )


def _check_obj_lines(path: Path) -> np.ndarray:
    """Refuse an OBJ whose text, vertex or face lines are malformed, naming the line (trimesh skips or guesses).

    ``v`` lines need three finite numbers; ``f`` lines at least three references whose vertex index is a
    non-zero integer within the vertices the file defines (negative: counted back from the latest one).

    Returns:
        ``[N, 3]`` float64 the ``v`` lines' positions in file order (trimesh drops vertices in no face and splits
        them along texture seams, so its order is not the file's).
    """
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        line = raw.count(b"\n", 0, error.start) + 1
        raise ValueError(f"{path.name}:{line}: not a text OBJ file (byte {error.start} is not UTF-8)") from None
    total = sum(1 for line in text.splitlines() if line.split()[:1] == ["v"])
    positions = []
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        if "\x00" in line:
            raise ValueError(f"{path.name}:{number}: not a text OBJ file (it holds NUL bytes)")
        if tokens[0] == "v":
            try:
                values = [float(t) for t in tokens[1:4]]
            except ValueError:
                values = []
            if len(values) != 3 or not all(math.isfinite(v) for v in values):
                raise ValueError(f"{path.name}:{number}: a vertex needs three finite numbers, got {line.strip()!r}")
            positions.append(values)
        elif tokens[0] == "f":
            if len(tokens) < 4:
                raise ValueError(f"{path.name}:{number}: a face needs at least three vertices, got {line.strip()!r}")
            for ref in tokens[1:]:
                head = ref.split("/", 1)[0]
                index = int(head) if head.lstrip("-").isascii() and head.lstrip("-").isdigit() else 0
                if index == 0 or index > total or index < -len(positions):
                    raise ValueError(
                        f"{path.name}:{number}: face vertex {ref!r} is not an index of the file's {total} vertices "
                        "(1-based, or negative counting back)"
                    )
    return np.asarray(positions, dtype=np.float64).reshape(-1, 3)


def _weld(vertices: np.ndarray, tolerance: float) -> np.ndarray:
    """``[V]`` the vertex each vertex merges into: vertices within ``tolerance`` of each other are merged (union-find
    over close pairs); the lowest index survives."""
    pairs = cKDTree(vertices).query_pairs(tolerance, output_type="ndarray") if tolerance > 0 else np.zeros((0, 2))
    parent = np.arange(vertices.shape[0])
    if len(pairs):
        for a, b in pairs:
            ra, rb = a, b
            while parent[ra] != ra:
                ra = parent[ra]
            while parent[rb] != rb:
                rb = parent[rb]
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
        for i in range(len(parent)):  # flatten: parents precede children after the min-rule above
            parent[i] = parent[parent[i]]
    return parent


def _file_order(file_vertices: np.ndarray | None, vertices: np.ndarray, diagonal: float) -> np.ndarray:
    """``[N]`` the loaded vertex at each file vertex's position (``-1``: none, a vertex in no face), for the
    ``file_vertices [N, 3]`` of an OBJ's text; a format trimesh reads in file order (``None``) maps to itself."""
    if file_vertices is None:
        return np.arange(vertices.shape[0])
    if not len(file_vertices) or not len(vertices):
        return np.full(len(file_vertices), -1, dtype=np.int64)
    distance, nearest = cKDTree(vertices).query(file_vertices)
    return np.where(distance <= 1e-12 * max(diagonal, 1.0), nearest, -1).astype(np.int64)


def _edge_uses(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges ``[E, 2]``, how many faces use each, and how many use it in its sorted direction."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    edges, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    forward = np.bincount(inverse.reshape(-1), weights=(directed[:, 0] < directed[:, 1]), minlength=len(edges))
    return edges, counts, forward.astype(np.int64)


def _validate(vertices: np.ndarray, faces: np.ndarray, name: str, welded: bool) -> None:
    """Refuse degenerate, non-manifold and inconsistently oriented meshes, naming faces and edges."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    diagonal = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    degenerate = np.flatnonzero(area <= 1e-12 * diagonal * diagonal)
    if degenerate.size:
        raise ValueError(
            f"{name}: {degenerate.size} zero-area faces (e.g. faces {_few(degenerate)}); remove or re-triangulate "
            "them (a collapsed triangle has no membrane rest shape)"
        )
    edges, counts, forward = _edge_uses(faces)
    isolated = np.flatnonzero(_isolated_faces(faces))
    if isolated.size:
        raise ValueError(
            f"{name}: {isolated.size} of {len(faces)} triangles share no edge with any other (e.g. faces "
            f"{_few(isolated)}): an unwelded triangle soup; raise weld_tolerance or weld the mesh in a modeller"
        )
    over = np.flatnonzero(counts > 2)
    if over.size:
        hint = (
            "welding merged them from an unwelded soup; lower weld_tolerance or repair the mesh"
            if welded
            else "split the mesh there or remove the extra faces"
        )
        raise ValueError(
            f"{name}: {over.size} non-manifold edges shared by more than two faces (e.g. vertex pairs "
            f"{_few_pairs(edges[over])}); {hint}"
        )
    flipped = np.flatnonzero((counts == 2) & (forward != 1))
    if flipped.size:
        raise ValueError(
            f"{name}: {flipped.size} edges whose two faces wind the same way (e.g. vertex pairs "
            f"{_few_pairs(edges[flipped])}); orient the faces consistently"
        )


def _isolated_faces(faces: np.ndarray) -> np.ndarray:
    """``[F]`` bool: faces none of whose edges is used by another face."""
    directed = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, inverse, counts = np.unique(directed, axis=0, return_inverse=True, return_counts=True)
    return (counts[inverse.reshape(3, -1)] == 1).all(0)


def _few(index: np.ndarray, count: int = 5) -> str:
    return ", ".join(str(int(i)) for i in index[:count]) + (", ..." if len(index) > count else "")


def _few_pairs(edges: np.ndarray, count: int = 3) -> str:
    return ", ".join(f"({int(a)}, {int(b)})" for a, b in edges[:count]) + (", ..." if len(edges) > count else "")


def _rescale(vertices: np.ndarray, scale, name: str) -> tuple[np.ndarray, str]:
    if scale is None:
        return vertices, ""
    if isinstance(scale, str):
        if scale != "auto":
            raise ValueError(f"scale must be None, a positive number or 'auto', got {scale!r}")
        height = float(np.ptp(vertices[:, 1]))
        lo, hi = _PLAUSIBLE_HEIGHT
        if lo <= height <= hi:
            return vertices, ""
        if height <= 0.0:
            raise ValueError(f"{name}: the mesh is flat in y; cannot infer its units (pass scale=...)")
        exponent = round(math.log10(_TYPICAL_HEIGHT / height))
        factor = 10.0**exponent
        unit = _UNIT_NAMES.get(exponent, f"units of 10^{exponent} m")
        note = (
            f"its height {height:g} is not a garment's in metres: read it in {unit} and scaled by {factor:g} "
            f"about the origin to {height * factor:.3f} m"
        )
        return vertices * factor, note
    if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be None, a positive number or 'auto', got {scale!r}")
    return vertices * float(scale), f"scaled by {scale:g}" if scale != 1 else ""


# ---------------------------------------------------------------------------------------------------------------
# Placement
# ---------------------------------------------------------------------------------------------------------------


def place_on_body(
    garment: Garment,
    body: Body,
    margin: float = 2e-3,
    max_widening: float = 1.3,
    max_gap: float = MAX_GAP,
) -> Garment:
    """Move a garment minimally so that every vertex starts at least ``margin`` outside the rest body, and refuse
    one that is not worn by the body at all.

    A garment is worn when its bounding box overlaps the body's and its nearest vertex lies within ``max_gap`` of
    the body surface (a garment elsewhere would fall freely, touching nothing). Tries, in order: the garment as it
    is; centred horizontally on the body's cross-section at the garment's heights; then that, widened horizontally
    about the body's axis in 2 % steps up to ``max_widening``.

    Args:
        garment: garment in metres.
        body: the body in its rest pose (the first frame of the motion).
        margin: smallest signed distance a vertex may have to the body surface, m (keep it above ``d̂``).
        max_widening: largest horizontal scale factor allowed.
        max_gap: largest distance of the garment's nearest vertex to the body surface, m (:data:`MAX_GAP`).

    Returns:
        The garment, with a note of what was done (nothing if it already fits).

    Raises:
        ValueError: the garment is not on the body (its box misses the body's, or its nearest vertex is farther
            than ``max_gap``), naming the distance; or no candidate clears the body, naming the deepest vertex and
            how far inside it lies.
    """
    if not (math.isfinite(max_gap) and max_gap > margin):
        raise ValueError(f"max_gap must be a finite distance above margin ({margin:g} m), got {max_gap!r}")
    x = garment.vertices.to(torch.float64)
    body = body.to("cpu", torch.float64)
    _check_worn(garment, x, body, max_gap)
    depth = _clearance(x, body)
    if depth >= margin:
        return garment
    band = (body.vertices[:, 1] >= x[:, 1].min()) & (body.vertices[:, 1] <= x[:, 1].max())
    axis_xz = (body.vertices[band] if bool(band.any()) else body.vertices)[:, [0, 2]].mean(0)
    centre_xz = 0.5 * (x[:, [0, 2]].amin(0) + x[:, [0, 2]].amax(0))
    shift = torch.zeros(3, dtype=x.dtype)
    shift[[0, 2]] = axis_xz - centre_xz
    centred = x + shift
    best = (depth, x, "")
    for widen in np.arange(1.0, max_widening + 1e-9, 0.02):
        candidate = centred.clone()
        candidate[:, [0, 2]] = axis_xz + float(widen) * (centred[:, [0, 2]] - axis_xz)
        d = _clearance(candidate, body)
        if d >= margin:
            note = f"moved by ({shift[0]:.3f}, 0, {shift[2]:.3f}) m onto the body's axis"
            if widen > 1.0:
                note += f" and widened horizontally by {widen:.2f}"
            return garment.replace(candidate, note + f" to clear the body by {margin * 1e3:g} mm")
        if d > best[0]:
            best = (d, candidate, "")
    sd = _signed_distance(best[1], body)
    worst = int(torch.argmin(sd))
    raise ValueError(
        f"{garment.name}: cannot place the garment outside the body: even centred and widened by {max_widening} "
        f"its vertex {worst} lies {-float(sd[worst]) * 1e3:.1f} mm inside the body (needs {margin * 1e3:g} mm "
        "outside); fit the garment to this body first or pass a larger garment"
    )


def _check_worn(garment: Garment, x: torch.Tensor, body: Body, max_gap: float) -> None:
    """Refuse a garment ``x [V, 3]`` (m) whose bounding box misses the body's or whose nearest vertex lies farther
    than ``max_gap`` (m) from the body surface, naming the distance, what loading changed, and the fixes."""
    lo, hi = x.amin(0), x.amax(0)
    body_lo, body_hi = body.vertices.amin(0), body.vertices.amax(0)
    _, distance, _, _ = body.closest_points(x)
    nearest = float(distance.min())
    separated = bool(((lo > body_hi) | (hi < body_lo)).any())
    if not separated and nearest <= max_gap:
        return
    where = (
        f"its bounding box [{_point(lo)}]–[{_point(hi)}] m does not overlap the body's [{_point(body_lo)}]–"
        f"[{_point(body_hi)}] m"
        if separated
        else f"its nearest vertex is {nearest * 1e3:.0f} mm from the body surface, farther than {max_gap * 1e3:g} mm"
    )
    notes = f" (notes: {'; '.join(garment.notes)})" if garment.notes else ""
    option = "" if separated else ", or pass a larger max_gap"
    raise ValueError(
        f"{garment.name}: the garment is not on the body: {where}{notes}, so it would fall freely, touching "
        f"nothing; move or scale it onto the body (load it with the scale its file is in, e.g. scale=1 for "
        f"metres){option}"
    )


def _point(p: torch.Tensor) -> str:
    return ", ".join(f"{float(c):.2f}" for c in p)


def _clearance(x: torch.Tensor, body: Body) -> float:
    """Smallest signed distance of the points ``x [V, 3]`` to the rest body, m (negative: inside)."""
    return float(_signed_distance(x, body).min())


def _signed_distance(x: torch.Tensor, body: Body) -> torch.Tensor:
    """Signed distance ``[V]`` to the body, m: the closest-point distance, negative where ``x`` lies behind the
    smooth (barycentric vertex-normal) surface normal there; exact in sign for points near a smooth closed body
    and far cheaper than the winding number."""
    closest, distance, face, bary = body.closest_points(x)
    normals = torch.from_numpy(np.array(body.trimesh().vertex_normals)).to(x)
    n = (bary[:, :, None] * normals[body.faces[face]]).sum(1)
    side = ((x - closest) * n).sum(1)
    return torch.where(side < 0, -distance, distance)


# ---------------------------------------------------------------------------------------------------------------
# Boundary (Dirichlet) vertices
# ---------------------------------------------------------------------------------------------------------------


def select_boundary(
    garment: Garment,
    body: Body | tuple[torch.Tensor, torch.Tensor],
    mode: str = "auto",
    override=None,
    band: float = 5e-3,
    shoulder_band: float = 0.06,
) -> torch.Tensor:
    """Garment vertices that follow the body exactly (Dirichlet; PhysAvatar Appendix A.3.2).

    Modes:

    * ``"waist"``: the topmost boundary loop (a skirt's or trousers' waistband), down to 2 cm below its top,
      and every vertex within ``band`` of it;
    * ``"shoulders"``: among the vertices within ``shoulder_band`` of the garment's top, those no farther from
      the body than the closest of them plus 1 cm (where a draped garment rests on the shoulders);
    * ``"auto"``: ``"waist"`` when the topmost boundary loop is a nearly level ring around the body (its height
      varies by under 2 cm and the body's axis lies inside it), else ``"shoulders"``.

    Args:
        garment: the placed garment.
        body: the body in the garment's (rest) pose: a :class:`Body`, or the ``(vertices [B, 3], faces [G, 3])`` of
            a captured body's mesh at that frame.
        mode: one of :data:`BOUNDARY_MODES`.
        override: explicit vertex indices (anything ``torch.as_tensor`` takes); replaces the selection.
        band: distance from the waist loop within which vertices join it, m.
        shoulder_band: depth below the garment's top searched in ``"shoulders"`` mode, m.

    Returns:
        ``[D]`` int64 sorted vertex indices.

    Raises:
        ValueError: an unknown mode, an empty or out-of-range override, or a selection that finds nothing.
    """
    v = garment.vertices.shape[0]
    body_vertices, body_faces = (body.vertices, body.faces) if isinstance(body, Body) else body
    body_vertices = body_vertices.detach().cpu().to(torch.float64)
    if override is not None:
        index = torch.as_tensor(override).reshape(-1)
        if index.numel() == 0:
            raise ValueError(
                "the boundary override is empty: pass at least one garment vertex index, or no override to "
                "select the boundary automatically"
            )
        if index.dtype.is_floating_point or int(index.min()) < 0 or int(index.max()) >= v:
            raise ValueError(f"boundary override must hold integer vertex indices in 0..{v - 1}")
        return torch.unique(index.long())
    if mode not in BOUNDARY_MODES:
        raise ValueError(f"unknown boundary mode {mode!r}; choose one of {', '.join(BOUNDARY_MODES)}")
    x = garment.vertices.detach().cpu().numpy()
    loop = _top_loop(x, garment.faces.cpu().numpy())
    if loop is not None:
        loop = loop[x[loop, 1] >= x[loop, 1].max() - 0.02]  # the level band at the top of that loop
    if mode == "auto":
        mode = "waist" if loop is not None and _is_waist(x[loop], body_vertices) else "shoulders"
    if mode == "waist":
        if loop is None:
            raise ValueError(f"{garment.name}: the mesh has no boundary loop, so no waistband; use mode='shoulders'")
        near = cKDTree(x[loop]).query(x, distance_upper_bound=band)[0] <= band
        index = np.flatnonzero(near)
    else:
        top = np.flatnonzero(x[:, 1] >= x[:, 1].max() - shoulder_band)
        _, distance, _, _ = surface_closest_points(body_vertices, body_faces, torch.from_numpy(x[top]))
        d = distance.numpy()
        index = top[d <= d.min() + 0.01]
    if index.size == 0:
        raise ValueError(f"{garment.name}: the {mode} selection found no vertices; pass override=[indices]")
    return torch.from_numpy(np.sort(index)).long()


def _top_loop(x: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """Vertices of the boundary loop with the highest mean height, or ``None`` for a closed mesh."""
    edges, counts, _ = _edge_uses(faces)
    open_edges = edges[counts == 1]
    if open_edges.size == 0:
        return None
    graph = trimesh.graph.connected_components(open_edges, min_len=3)
    loops = [np.asarray(c) for c in graph]
    if not loops:
        return None
    return max(loops, key=lambda c: float(x[c, 1].mean()))


def _is_waist(ring: np.ndarray, body_vertices: torch.Tensor) -> bool:
    """A nearly level loop (height varies by < 2 cm) that surrounds the body's vertical axis at its height."""
    if np.ptp(ring[:, 1]) >= 0.02:
        return False
    y = float(ring[:, 1].mean())
    near = body_vertices[(body_vertices[:, 1] - y).abs() < 0.02]
    if near.shape[0] == 0:
        return False
    axis = near[:, [0, 2]].mean(0).numpy()
    return bool((ring[:, [0, 2]].min(0) < axis).all() and (axis < ring[:, [0, 2]].max(0)).all())


def boundary_targets(
    body: Body,
    rest_positions: torch.Tensor,
    rotations: torch.Tensor,
    root_translation: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Posed boundary vertices: LBS with the skinning weights of their nearest body points (Appendix A.3.2).

    ``x = Σ_j w_j A_j x̄`` (PhysAvatar's LBS, §3.2) with ``w`` from :meth:`Body.surface_weights` at the rest
    positions ``x̄``; these are the ``V^b_{t+1}`` of Eq. 5.

    Args:
        body: the skinned body.
        rest_positions: ``[D, 3]`` boundary vertices on the rest garment, m.
        rotations: local joint rotations ``[..., J, 3, 3]`` or axis-angle ``[..., J, 3]`` (frames batched).
        root_translation: ``[..., 3]`` root displacement, m, or ``None``.
        weights: ``[D, J]`` precomputed surface weights (computed here when ``None``).

    Returns:
        ``[..., D, 3]`` posed positions, m.
    """
    if rest_positions.dim() != 2 or rest_positions.shape[1] != 3 or rest_positions.shape[0] == 0:
        raise ValueError(f"rest_positions must be a non-empty [D, 3] tensor, got {tuple(rest_positions.shape)}")
    if weights is None:
        weights = body.surface_weights(rest_positions.to(body.vertices))
    transforms = body.skeleton.skinning_transforms(rotations, root_translation)
    return linear_blend_skinning(rest_positions.to(transforms), weights, transforms)


def default_garment(body: Body) -> Garment:
    """The garment worn when none is given, placed on ``body`` (:func:`place_on_body`): :data:`DEFAULT_GARMENT` where
    the shared data folder holds it, else the embedded :func:`procedural_skirt`, so a fresh clone runs too.

    Its ``notes`` say which one it is.
    """
    if DEFAULT_GARMENT.is_file():
        garment = load_garment(DEFAULT_GARMENT)
        garment = Garment(
            garment.vertices,
            garment.faces,
            garment.name,
            (f"the default garment {DEFAULT_GARMENT.name}", *garment.notes),
        )
    else:
        skirt = procedural_skirt(body)
        note = f"the embedded procedural skirt ({skirt.vertices.shape[0]} vertices): {DEFAULT_GARMENT} is absent"
        garment = Garment(skirt.vertices, skirt.faces, skirt.name, (note,))
    return place_on_body(garment, body)


# ---------------------------------------------------------------------------------------------------------------
# A procedural skirt (the embedded garment of the synthetic capture)
# ---------------------------------------------------------------------------------------------------------------


def procedural_skirt(
    body: Body,
    rings: int = 10,
    segments: int = 28,
    top: float = 1.06,
    length: float = 0.40,
    clearance: float = 0.012,
    flare: float = 0.12,
) -> Garment:
    """A flared tube skirt fitted around the rest body: a small garment needing no data files.

    Each ring is an ellipse about the body's axis whose half-axes clear the body's cross-section at that height by
    ``clearance``; the half-axes never shrink downwards (the skirt hangs from the hips, it does not hug the
    thighs) and grow linearly by up to ``flare`` at the hem. The mesh is an open tube (waist and hem are its two
    boundary loops), triangulated with alternating diagonals, outward-oriented.

    Args:
        body: the body in its rest pose.
        rings: vertex rings from waist to hem (≥ 2).
        segments: vertices per ring (≥ 6).
        top: height of the waist ring, m.
        length: waist-to-hem height, m.
        clearance: gap to the body at every ring, m (above the contact distance).
        flare: extra radius at the hem, m.

    Returns:
        :class:`Garment` named ``"skirt"`` with ``rings · segments`` vertices.

    Raises:
        ValueError: too few rings or segments, non-positive sizes, or a ring height where the body has no
            cross-section.
    """
    if rings < 2 or segments < 6:
        raise ValueError(f"a skirt needs rings >= 2 and segments >= 6, got {rings} and {segments}")
    if not (length > 0.0 and clearance > 0.0 and flare >= 0.0):
        raise ValueError(f"length ({length}) and clearance ({clearance}) must be positive and flare ({flare}) >= 0")
    v = body.vertices.detach().to("cpu", torch.float64).numpy()
    heights = top - length * np.arange(rings) / (rings - 1)
    angle = 2.0 * math.pi * np.arange(segments) / segments
    torso = np.abs(v[:, 0]) < 0.3  # keeps the hanging hands out of the hip's cross-section
    centre = np.zeros((rings, 2))
    half = np.zeros((rings, 2))
    for r, y in enumerate(heights):
        slab = v[torso & (np.abs(v[:, 1] - y) < 0.02)]
        if slab.shape[0] == 0:
            raise ValueError(f"the body has no cross-section at height {y:.3f} m; lower top or shorten the skirt")
        lo, hi = slab[:, [0, 2]].min(0), slab[:, [0, 2]].max(0)
        centre[r] = 0.5 * (lo + hi)
        half[r] = 0.5 * (hi - lo)
    half = np.maximum.accumulate(half, axis=0) + flare * np.linspace(0.0, 1.0, rings)[:, None]
    centre[:] = centre[0]  # a straight axis: the skirt hangs, it does not follow the legs' cross-section
    y = np.broadcast_to(heights[:, None], (rings, segments))

    def tube(pad: float) -> np.ndarray:
        x = centre[:, None, 0] + (half[:, None, 0] + pad) * np.sin(angle)[None]
        z = centre[:, None, 1] + (half[:, None, 1] + pad) * np.cos(angle)[None]
        return np.stack([x, y, z], -1).reshape(-1, 3)

    # The body's cross-section is not an ellipse: pad the half-axes until every vertex clears it.
    pad = clearance
    while _clearance(torch.from_numpy(tube(pad)), body.to("cpu", torch.float64)) < clearance:
        pad += 0.25 * clearance
        if pad > 0.5:
            raise ValueError("the skirt cannot clear the body; check the body's rest pose")
    vertices = tube(pad)
    r, s = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = r * segments + s, r * segments + (s + 1) % segments
    c, d = a + segments, b + segments
    flip = ((r + s) % 2).astype(bool)  # alternating diagonals: no preferred fold direction
    faces = np.concatenate(
        [
            np.where(flip[..., None], np.stack([a, c, d], -1), np.stack([a, c, b], -1)).reshape(-1, 3),
            np.where(flip[..., None], np.stack([a, d, b], -1), np.stack([b, c, d], -1)).reshape(-1, 3),
        ]
    )
    garment = Garment(torch.tensor(vertices), torch.tensor(faces, dtype=torch.int64), "skirt")
    _validate(vertices, faces, "skirt", welded=True)
    return garment
