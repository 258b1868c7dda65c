"""Density fields σ(x) and their gradients ∇σ(x): the one interface the sampler and simulator read.

PIE-NeRF samples particles from a trained NeRF's volume density σ(x) and sizes them by ‖∇σ(x)‖
(§4.1, Eq. 3). The simulator never asks where σ comes from: a trained NeRF, a triangle mesh or an
analytic shape all implement :class:`DensityField`.

Shapes and meshes give a smooth density from a signed distance ``d(x)`` (metres, negative inside):

    σ(x) = σ_max · sigmoid(−d(x) / τ)                                   (:func:`sigmoid_density`)

so σ = σ_max / 2 on the surface, → σ_max inside, → 0 outside, and ‖∇σ‖ peaks on the surface at
σ_max / (4τ), the sharp density step a NeRF shows at an object's boundary. ``τ`` (``softness``,
metres) defaults to 1 % of the shape's smallest feature (a sphere's or capsule's radius, a box's
smallest half-extent), ``σ_max`` (``max_density``) to 50 per metre, a typical NeRF opacity. With those
defaults the sampler's threshold σ = ε = 10⁻² sits at ``d = τ · ln(σ_max/ε − 1) ≈ 8.5 τ`` outside the
surface (:meth:`SDFDensity.level_distance`).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "Box",
    "Capsule",
    "DensityField",
    "MeshDensity",
    "SDFDensity",
    "Sphere",
    "Union",
    "load_mesh_file",
    "mesh_signed_distance_grid",
    "sigmoid_density",
]

DEFAULT_MAX_DENSITY = 50.0
# Default softness τ as a fraction of a shape's smallest feature.
DEFAULT_SOFTNESS_FRACTION = 0.01
# Bounds pad the shape by this many τ: outside them σ < σ_max · e^-20 ≈ 2e-9 σ_max.
BOUNDS_PADDING_IN_SOFTNESS = 20.0
# Points per chunk in the default autograd gradient, so a million points stay in bounded memory.
GRADIENT_CHUNK = 1 << 18

Bounds = tuple[torch.Tensor, torch.Tensor]


def sigmoid_density(signed_distance: torch.Tensor, max_density: float, softness: float) -> torch.Tensor:
    """Smooth volume density of a solid from its signed distance, ``σ = σ_max · sigmoid(−d / τ)``.

    Args:
        signed_distance: ``[N]`` signed distance ``d``, metres, negative inside.
        max_density: ``σ_max``, the density deep inside, per metre.
        softness: ``τ``, metres: σ falls from 73 % to 27 % of ``σ_max`` across ``2τ`` of the surface.

    Returns:
        ``[N]`` density σ, per metre, same dtype as ``signed_distance``.
    """
    return max_density * torch.sigmoid(-signed_distance / softness)


class DensityField(ABC):
    """A volume density σ(x) ≥ 0 over space with its gradient: what PIE-NeRF samples particles from.

    Subclasses implement :meth:`density` and :attr:`bounds`; :meth:`density_grad` defaults to
    autograd through :meth:`density`. Inputs may be float32 or float64 on any torch device; outputs
    match them.
    """

    @abstractmethod
    def density(self, x: torch.Tensor) -> torch.Tensor:
        """Volume density σ at points ``x [N, 3]`` (metres); returns ``[N]``, per metre."""

    @property
    @abstractmethod
    def bounds(self) -> Bounds:
        """Axis-aligned box ``(lo [3], hi [3])``, metres, float64 on the CPU, outside which σ is ~0."""

    def density_grad(self, x: torch.Tensor) -> torch.Tensor:
        """Spatial gradient ∇σ at points ``x [N, 3]``; returns ``[N, 3]``, per square metre.

        Differentiates :meth:`density` with autograd, :data:`GRADIENT_CHUNK` points at a time.
        """
        _check_points(x)
        grad = torch.empty_like(x)
        for start in range(0, x.shape[0], GRADIENT_CHUNK):
            chunk = x[start : start + GRADIENT_CHUNK].detach().requires_grad_(True)
            with torch.enable_grad():
                sigma = self.density(chunk)
                (grad[start : start + GRADIENT_CHUNK],) = torch.autograd.grad(sigma.sum(), chunk)
        return grad


class SDFDensity(DensityField):
    """Density of a solid given by a signed distance, ``σ = σ_max · sigmoid(−d / τ)``.

    Subclasses implement :meth:`signed_distance`, :meth:`_tight_bounds` and :meth:`_feature_size`.

    Args:
        max_density: ``σ_max``, per metre (default 50).
        softness: ``τ``, metres (default: 1 % of the shape's smallest feature).
    """

    def __init__(self, max_density: float = DEFAULT_MAX_DENSITY, softness: float | None = None):
        if not (max_density > 0.0 and math.isfinite(max_density)):
            raise ValueError(f"max_density must be a positive density (per metre), got {max_density}")
        if softness is None:
            softness = DEFAULT_SOFTNESS_FRACTION * self._feature_size()
        if not (softness > 0.0 and math.isfinite(softness)):
            raise ValueError(f"softness must be a positive length in metres, got {softness}")
        self.max_density = float(max_density)
        self.softness = float(softness)

    @abstractmethod
    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance ``[N]`` (metres, negative inside) at points ``x [N, 3]``."""

    @abstractmethod
    def _tight_bounds(self) -> Bounds:
        """Axis-aligned box of the solid itself (σ ≥ σ_max / 2), float64 CPU tensors."""

    @abstractmethod
    def _feature_size(self) -> float:
        """The solid's smallest feature, metres; the default softness is a fraction of it."""

    def density(self, x: torch.Tensor) -> torch.Tensor:
        _check_points(x)
        return sigmoid_density(self.signed_distance(x), self.max_density, self.softness)

    @property
    def bounds(self) -> Bounds:
        lo, hi = self._tight_bounds()
        pad = BOUNDS_PADDING_IN_SOFTNESS * self.softness
        return lo - pad, hi + pad

    def level_distance(self, level: float) -> float:
        """Signed distance, metres, at which σ equals ``level`` (``0 < level < σ_max``).

        E.g. the sampler's threshold ε = 10⁻² lies ``τ · ln(σ_max/ε − 1)`` outside the surface.
        """
        if not 0.0 < level < self.max_density:
            raise ValueError(f"level must lie strictly between 0 and max_density={self.max_density}, got {level}")
        return self.softness * math.log(self.max_density / level - 1.0)


class Sphere(SDFDensity):
    """Solid ball, ``d(x) = ‖x − c‖ − R``.

    Args:
        centre: ``[3]``, metres.
        radius: ``R``, metres.
        max_density, softness: as :class:`SDFDensity` (default τ = R / 100).
    """

    def __init__(self, centre: Sequence[float] | torch.Tensor, radius: float, **kwargs):
        self.centre = _vector(centre, "centre")
        if not radius > 0.0:
            raise ValueError(f"Sphere radius must be positive (metres), got {radius}")
        self.radius = float(radius)
        super().__init__(**kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        _check_points(x)
        return torch.linalg.vector_norm(x - self.centre.to(x), dim=-1) - self.radius

    def _tight_bounds(self) -> Bounds:
        return self.centre - self.radius, self.centre + self.radius

    def _feature_size(self) -> float:
        return self.radius


class Box(SDFDensity):
    """Solid oriented box, exact signed distance.

    Args:
        centre: ``[3]``, metres.
        half_extents: ``[3]``, metres, half the edge lengths along the box's own axes.
        rotation: ``[3, 3]`` rotation whose columns are the box's axes in world coordinates
            (``None``: axis-aligned).
        max_density, softness: as :class:`SDFDensity` (default τ = smallest half-extent / 100).
    """

    def __init__(
        self,
        centre: Sequence[float] | torch.Tensor,
        half_extents: Sequence[float] | torch.Tensor,
        rotation: torch.Tensor | None = None,
        **kwargs,
    ):
        self.centre = _vector(centre, "centre")
        self.half_extents = _vector(half_extents, "half_extents")
        if not bool((self.half_extents > 0.0).all()):
            raise ValueError(f"Box half_extents must all be positive (metres), got {self.half_extents.tolist()}")
        if rotation is None:
            rotation = torch.eye(3, dtype=torch.float64)
        rotation = torch.as_tensor(rotation, dtype=torch.float64).cpu()
        if rotation.shape != (3, 3):
            raise ValueError(f"Box rotation must be a [3, 3] matrix, got shape {tuple(rotation.shape)}")
        if not torch.allclose(rotation.T @ rotation, torch.eye(3, dtype=torch.float64), atol=1e-6) or (
            torch.linalg.det(rotation) < 0.0
        ):
            raise ValueError("Box rotation must be a proper rotation (orthonormal, det +1); orthonormalise it first")
        self.rotation = rotation
        super().__init__(**kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        _check_points(x)
        local = (x - self.centre.to(x)) @ self.rotation.to(x)
        q = local.abs() - self.half_extents.to(x)
        outside = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1)
        inside = q.amax(dim=-1).clamp_max(0.0)
        return outside + inside

    def _tight_bounds(self) -> Bounds:
        world_half = self.rotation.abs() @ self.half_extents
        return self.centre - world_half, self.centre + world_half

    def _feature_size(self) -> float:
        return float(self.half_extents.min())


class Capsule(SDFDensity):
    """Solid capsule: points within ``radius`` of the segment ``a``–``b``.

    Args:
        a, b: segment end points ``[3]``, metres (equal end points give a sphere).
        radius: metres.
        max_density, softness: as :class:`SDFDensity` (default τ = radius / 100).
    """

    def __init__(self, a: Sequence[float] | torch.Tensor, b: Sequence[float] | torch.Tensor, radius: float, **kwargs):
        self.a = _vector(a, "a")
        self.b = _vector(b, "b")
        if not radius > 0.0:
            raise ValueError(f"Capsule radius must be positive (metres), got {radius}")
        self.radius = float(radius)
        super().__init__(**kwargs)

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        _check_points(x)
        a, axis = self.a.to(x), (self.b - self.a).to(x)
        t = (((x - a) @ axis) / (axis @ axis).clamp_min(1e-30)).clamp(0.0, 1.0)
        return torch.linalg.vector_norm(x - a - t[:, None] * axis, dim=-1) - self.radius

    def _tight_bounds(self) -> Bounds:
        return torch.minimum(self.a, self.b) - self.radius, torch.maximum(self.a, self.b) + self.radius

    def _feature_size(self) -> float:
        return self.radius


class Union(SDFDensity):
    """Union of solids: the signed distance is the minimum of the members' signed distances.

    Its density is ``σ_max · sigmoid(−min_i d_i / τ)``; with one ``σ_max`` and ``τ`` for all members
    this equals the maximum of the members' densities (the sigmoid is monotone), so overlapping
    members do not add up to more than a solid's density.

    Args:
        *fields: the member :class:`SDFDensity` solids, at least one.
        max_density: ``σ_max`` (default: the largest of the members').
        softness: ``τ`` (default: the smallest of the members', so no edge gets softer).
    """

    def __init__(self, *fields: SDFDensity, max_density: float | None = None, softness: float | None = None):
        if not fields:
            raise ValueError("Union needs at least one member field")
        for field in fields:
            if not isinstance(field, SDFDensity):
                raise TypeError(f"Union members must be SDFDensity shapes, got {type(field).__name__}")
        self.fields = tuple(fields)
        super().__init__(
            max_density=max(f.max_density for f in fields) if max_density is None else max_density,
            softness=min(f.softness for f in fields) if softness is None else softness,
        )

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([f.signed_distance(x) for f in self.fields]).amin(dim=0)

    def _tight_bounds(self) -> Bounds:
        boxes = [f._tight_bounds() for f in self.fields]
        return torch.stack([lo for lo, _ in boxes]).amin(0), torch.stack([hi for _, hi in boxes]).amax(0)

    def _feature_size(self) -> float:
        return min(f._feature_size() for f in self.fields)


def load_mesh_file(path: str | Path):
    """The triangle mesh in ``path`` (any format ``trimesh.load`` reads; metres) as a ``trimesh.Trimesh``.

    A file that holds no triangles (empty, not a mesh, unreadable) or whose vertices are not all finite is refused
    by name before trimesh's processing would drop the bad vertices and leave a mesh that merely is not watertight.

    Raises:
        ValueError: the file is empty, cannot be read as a mesh, holds no triangles, or has NaN/inf vertices.
    """
    import trimesh  # deferred: only mesh-file scenes need trimesh

    path = Path(path)
    if path.is_file() and path.stat().st_size == 0:
        raise ValueError(
            f"mesh file {path} is empty (0 bytes); give a mesh file with triangles (.obj, .ply, .stl, ...)"
        )
    try:
        raw = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds for a file it cannot parse
        raise ValueError(
            f"mesh file {path} cannot be read as a mesh ({error}); check its format and contents"
        ) from None
    if not isinstance(raw, trimesh.Trimesh) or len(raw.faces) == 0 or len(raw.vertices) == 0:
        raise ValueError(
            f"mesh file {path} holds no triangles (is it a mesh of this suffix's format?); give a closed triangle mesh"
        )
    finite = np.isfinite(np.asarray(raw.vertices)).all(axis=1)
    if not finite.all():
        raise ValueError(
            f"mesh file {path} has {int((~finite).sum())} of {len(finite)} vertices with NaN or infinite "
            "coordinates; fix or remove them"
        )
    return trimesh.load(path, force="mesh")


class MeshDensity(SDFDensity):
    """Density of the solid bounded by a watertight triangle mesh.

    The exact signed distance (closest point on the triangles, sign by generalised winding number)
    is computed once on a regular ``resolution³`` grid over the padded bounds; :meth:`signed_distance`
    interpolates that grid trilinearly, so density and gradient are fast and differentiable. Beyond
    the grid, the distance to the grid's box is added to the value at the nearest grid point.
    Interpolation error is about ``h² κ / 8`` for grid spacing ``h`` and surface curvature ``κ``.

    Args:
        mesh: a watertight ``trimesh.Trimesh`` or a path ``trimesh.load`` reads; metres.
        softness: ``τ``, metres (default: 1 % of the smallest half-extent of the mesh's bounding box).
        max_density: ``σ_max``, per metre (default 50).
        resolution: grid points per axis (default 64); the grid is computed once on the CPU
            (:func:`mesh_signed_distance_grid`).

    Raises:
        ValueError: the mesh is not watertight or has no volume.
    """

    def __init__(
        self,
        mesh,
        softness: float | None = None,
        max_density: float = DEFAULT_MAX_DENSITY,
        resolution: int = 64,
    ):
        import trimesh

        if isinstance(mesh, (str, Path)):
            mesh = load_mesh_file(mesh)
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"mesh must be a trimesh.Trimesh or a path to a mesh file, got {type(mesh).__name__}")
        if not mesh.is_watertight:
            raise ValueError(
                "MeshDensity needs a watertight mesh (every edge shared by exactly two faces) to tell inside "
                "from outside; repair it first (e.g. mesh.merge_vertices(); trimesh.repair.fill_holes(mesh)) "
                "or supply a closed mesh"
            )
        if abs(mesh.volume) <= 0.0:
            raise ValueError("MeshDensity needs a mesh that encloses a volume; this one has zero volume")
        if resolution < 2:
            raise ValueError(f"resolution must be at least 2 grid points per axis, got {resolution}")
        self.vertices = torch.as_tensor(mesh.vertices, dtype=torch.float64)
        self.faces = torch.as_tensor(mesh.faces, dtype=torch.int64)
        self._mesh_lo, self._mesh_hi = self.vertices.amin(0), self.vertices.amax(0)
        super().__init__(max_density=max_density, softness=softness)

        lo, hi = super().bounds
        self.resolution = int(resolution)
        # One spare grid spacing each side, so the sigmoid's tail inside the bounds is interpolated.
        spacing = (hi - lo) / (self.resolution - 3)
        self.grid_lo, self.grid_hi = lo - spacing, hi + spacing
        self.grid_spacing = (self.grid_hi - self.grid_lo) / (self.resolution - 1)
        self.grid = mesh_signed_distance_grid(self.vertices, self.faces, self.grid_lo, self.grid_hi, self.resolution)
        self._grid_cache: dict[tuple[torch.device, torch.dtype], torch.Tensor] = {}

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        _check_points(x)
        key = (x.device, x.dtype)
        if key not in self._grid_cache:
            self._grid_cache[key] = self.grid.to(x)
        grid = self._grid_cache[key]
        lo, hi = self.grid_lo.to(x), self.grid_hi.to(x)
        inside_box = torch.minimum(torch.maximum(x, lo), hi)
        beyond = torch.linalg.vector_norm(x - inside_box, dim=-1)
        return _trilinear(grid, (inside_box - lo) / self.grid_spacing.to(x)) + beyond

    def _tight_bounds(self) -> Bounds:
        return self._mesh_lo, self._mesh_hi

    def _feature_size(self) -> float:
        return 0.5 * float((self._mesh_hi - self._mesh_lo).min())


def mesh_signed_distance_grid(
    vertices: torch.Tensor, faces: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, resolution: int
) -> torch.Tensor:
    """Exact signed distance to a closed triangle mesh at the nodes of a regular grid.

    Unsigned distance: the smallest point-triangle distance over candidate faces, those whose
    bounding ball (centroid, circumradius ``ρ_f``) can hold a point nearer than the nearest
    centroid, found with a k-d tree. Sign: a grid edge whose two nodes both lie farther than
    half its length from the surface cannot cross it, so the sign is constant on each connected
    component of such nodes; the generalised winding number ``w = Σ_f Ω_f / 4π`` (van
    Oosterom–Strackee solid angles) decides it for one node per component and for every node
    nearer the surface; ``|w| > 1/2`` is inside, whatever the orientation of the faces.

    Args:
        vertices: ``[V, 3]``, metres.
        faces: ``[F, 3]`` int64 vertex indices of a watertight mesh.
        lo, hi: ``[3]`` corners of the grid, metres.
        resolution: nodes per axis.

    Returns:
        ``[R, R, R]`` float64 signed distance, metres, negative inside; node ``(i, j, k)`` sits at
        ``lo + (i, j, k) * (hi - lo) / (R - 1)``.
    """
    from scipy import ndimage

    axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution, dtype=torch.float64) for i in range(3)]
    nodes = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    tri = vertices.to(torch.float64)[faces]  # [F, 3 corners, 3]
    distance = _unsigned_distance(nodes, tri)

    spacing = float(((hi - lo) / (resolution - 1)).max())
    near = distance <= 0.5 * spacing
    components, count = ndimage.label((~near).reshape((resolution,) * 3).numpy())
    components = torch.from_numpy(components.reshape(-1)).long()
    order = torch.argsort(components, stable=True)
    first_of_label = torch.searchsorted(components[order], torch.arange(1, count + 1))
    representative = order[first_of_label]
    decide = torch.cat([torch.nonzero(near).flatten(), representative])
    inside = _winding_number(nodes[decide], tri).abs() > 0.5
    node_inside = torch.zeros(nodes.shape[0], dtype=torch.bool)
    node_inside[decide] = inside
    label_inside = torch.zeros(count + 1, dtype=torch.bool)
    label_inside[1:] = inside[near.sum() :]
    node_inside = torch.where(near, node_inside, label_inside[components])
    return torch.where(node_inside, -distance, distance).reshape(resolution, resolution, resolution)


def _point_triangle_distance_sq(p: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """Squared distance ``[M]`` from points ``[M, 3]`` to triangles ``[M, 3 corners, 3]``.

    The distance to the plane where the point projects inside the triangle, else to the nearest edge.
    """
    a, b, c = tri.unbind(1)
    normal = torch.linalg.cross(b - a, c - a)
    area2 = torch.linalg.vector_norm(normal, dim=-1)
    inner = area2 > 0.0
    edge_sq = torch.full_like(area2, math.inf)
    for corner, edge in ((a, b - a), (b, c - b), (c, a - c)):
        offset = p - corner
        inner = inner & (_dot(torch.linalg.cross(edge, offset), normal) >= 0.0)
        t = (_dot(offset, edge) / _dot(edge, edge).clamp_min(1e-300)).clamp(0.0, 1.0)
        edge_sq = torch.minimum(edge_sq, _dot(offset - t[:, None] * edge, offset - t[:, None] * edge))
    plane_sq = _dot(p - a, normal).square() / area2.square().clamp_min(1e-300)
    return torch.where(inner, plane_sq, edge_sq)


def _unsigned_distance(points: torch.Tensor, tri: torch.Tensor, points_per_chunk: int = 1 << 14) -> torch.Tensor:
    """Exact distance ``[N]`` from points ``[N, 3]`` to the nearest of triangles ``[F, 3, 3]``."""
    import numpy as np
    from scipy.spatial import cKDTree

    centroid = tri.mean(dim=1)
    circumradius = torch.linalg.vector_norm(tri - centroid[:, None], dim=-1).amax(dim=1)
    tree = cKDTree(centroid.numpy())
    out = torch.empty(points.shape[0], dtype=torch.float64)
    for start in range(0, points.shape[0], points_per_chunk):
        p = points[start : start + points_per_chunk]
        # A face's centroid lies on it, so the nearest centroid bounds the distance from above.
        nearest, _ = tree.query(p.numpy())
        lists = tree.query_ball_point(p.numpy(), nearest + float(circumradius.max()))
        lengths = torch.from_numpy(np.fromiter(map(len, lists), dtype=np.int64, count=len(lists)))
        face = torch.from_numpy(np.concatenate(lists).astype(np.int64))
        point = torch.repeat_interleave(torch.arange(p.shape[0]), lengths)
        keep = (
            torch.linalg.vector_norm(p[point] - centroid[face], dim=-1) - circumradius[face]
            <= torch.from_numpy(nearest)[point]
        )
        point, face = point[keep], face[keep]
        d_sq = _point_triangle_distance_sq(p[point], tri[face])
        best = torch.full((p.shape[0],), math.inf, dtype=torch.float64)
        out[start : start + p.shape[0]] = best.scatter_reduce(0, point, d_sq, reduce="amin").sqrt()
    return out


def _winding_number(points: torch.Tensor, tri: torch.Tensor, pairs_per_chunk: int = 1 << 20) -> torch.Tensor:
    """Generalised winding number ``[N]`` of triangles ``[F, 3, 3]`` at points ``[N, 3]``: ±1 inside, 0 outside."""
    out = torch.empty(points.shape[0], dtype=torch.float64)
    rows = max(1, pairs_per_chunk // tri.shape[0])
    for start in range(0, points.shape[0], rows):
        ra, rb, rc = (tri[None, :, i] - points[start : start + rows, None] for i in range(3))  # [C, F, 3]
        la, lb, lc = (torch.linalg.vector_norm(r, dim=-1) for r in (ra, rb, rc))
        det = _dot(ra, torch.linalg.cross(rb, rc))
        denominator = la * lb * lc + _dot(ra, rb) * lc + _dot(rb, rc) * la + _dot(rc, ra) * lb
        out[start : start + rows] = torch.atan2(det, denominator).sum(dim=1) / (2.0 * math.pi)
    return out


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.einsum("...i,...i->...", u, v)


def _trilinear(grid: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of ``grid [R, R, R]`` at continuous grid coordinates ``u [N, 3]``."""
    upper = torch.tensor(grid.shape, device=u.device) - 2
    cell = torch.minimum(u.detach().floor().long().clamp_min(0), upper)
    f = u - cell.to(u)
    i, j, k = cell.unbind(-1)
    fx, fy, fz = f.unbind(-1)
    c00 = grid[i, j, k] * (1 - fx) + grid[i + 1, j, k] * fx
    c10 = grid[i, j + 1, k] * (1 - fx) + grid[i + 1, j + 1, k] * fx
    c01 = grid[i, j, k + 1] * (1 - fx) + grid[i + 1, j, k + 1] * fx
    c11 = grid[i, j + 1, k + 1] * (1 - fx) + grid[i + 1, j + 1, k + 1] * fx
    return (c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz


def _vector(value, what: str) -> torch.Tensor:
    vector = torch.as_tensor(value, dtype=torch.float64).cpu()
    if vector.shape != (3,) or not bool(torch.isfinite(vector).all()):
        raise ValueError(f"{what} must be 3 finite numbers (metres), got {value!r}")
    return vector


def _check_points(x: torch.Tensor) -> None:
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise TypeError(f"points must be a floating-point torch.Tensor, got {getattr(x, 'dtype', type(x).__name__)}")
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {tuple(x.shape)}")
