"""Reference of :mod:`kernels.raycast`: every ray against every triangle (Möller–Trumbore), in float64 torch.

No hierarchy, so it is only for small meshes: the work is ``R × F`` ray-triangle tests. Conventions are those of
:mod:`kernels.raycast`: unit-normalised directions, ``t`` in metres, barycentrics ``(b1, b2)`` with the hit at
``(1 − b1 − b2) v0 + b1 v1 + b2 v2``, misses as ``t = inf``, face −1.
"""

from __future__ import annotations

import math

import torch

__all__ = ["cast_rays", "closest_points", "shade"]

# Ray-triangle pairs per chunk, so the [rows, F] intermediates stay in bounded memory.
_PAIRS_PER_CHUNK = 1 << 22
# Rays (nearly) parallel to a triangle's plane do not hit it.
_PARALLEL = 1e-12


def cast_rays(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    max_distance: float = math.inf,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """First hit of each ray with a triangle mesh, by testing every triangle.

    Möller–Trumbore: with edges ``e1 = v1 − v0``, ``e2 = v2 − v0``, ``p = d × e2``, ``det = e1 · p``,
    ``s = o − v0``, ``q = s × e1``: ``b1 = s · p / det``, ``b2 = d · q / det``, ``t = e2 · q / det``; a hit needs
    ``b1, b2 ≥ 0``, ``b1 + b2 ≤ 1`` and ``0 ≤ t < max_distance``. Either side of a face counts.

    Args:
        vertices: ``[V, 3]``, metres.
        faces: ``[F, 3]`` vertex indices.
        origins, directions: ``[R, 3]`` rays (directions normalised here).
        max_distance: metres.

    Returns:
        ``t [R]`` (float64, inf on a miss), ``face [R]`` (int64, −1), ``bary [R, 2]`` (float64, 0).
    """
    tri = vertices.detach().to(torch.float64)[faces.long()]  # [F, 3 corners, 3]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    origins = origins.detach().to(torch.float64)
    directions = torch.nn.functional.normalize(directions.detach().to(torch.float64), dim=-1)
    count = origins.shape[0]
    best_t = torch.full((count,), math.inf, dtype=torch.float64)
    best_face = torch.full((count,), -1, dtype=torch.int64)
    best_bary = torch.zeros(count, 2, dtype=torch.float64)
    rows = max(1, _PAIRS_PER_CHUNK // max(tri.shape[0], 1))
    for start in range(0, count, rows):
        o, d = origins[start : start + rows, None], directions[start : start + rows, None]  # [C, 1, 3]
        p = torch.linalg.cross(d.expand(-1, e2.shape[0], -1), e2[None].expand(d.shape[0], -1, -1))
        det = (e1[None] * p).sum(-1)
        parallel = det.abs() < _PARALLEL
        inv = 1.0 / torch.where(parallel, torch.ones_like(det), det)
        s = o - v0[None]
        b1 = (s * p).sum(-1) * inv
        q = torch.linalg.cross(s, e1[None].expand_as(s))
        b2 = (d * q).sum(-1) * inv
        t = (e2[None] * q).sum(-1) * inv
        hit = ~parallel & (b1 >= 0.0) & (b2 >= 0.0) & (b1 + b2 <= 1.0) & (t >= 0.0) & (t < max_distance)
        t = torch.where(hit, t, torch.full_like(t, math.inf))
        t_min, face = t.min(dim=1)
        any_hit = torch.isfinite(t_min)
        rows_index = torch.arange(t.shape[0])
        best_t[start : start + rows] = t_min
        best_face[start : start + rows] = torch.where(any_hit, face, torch.full_like(face, -1))
        bary = torch.stack([b1[rows_index, face], b2[rows_index, face]], dim=-1)
        best_bary[start : start + rows] = torch.where(any_hit[:, None], bary, torch.zeros_like(bary))
    return best_t, best_face, best_bary


def closest_points(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Unsigned distance ``[P]`` (float64, m) from each point to the mesh, by testing every triangle.

    A point whose projection onto a triangle's plane falls inside the triangle is at its plane distance; otherwise
    the closest point lies on one of the three edges, each a clamped segment projection.
    """
    tri = vertices.detach().to(torch.float64)[faces.long()]
    points = points.detach().to(torch.float64)
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = torch.nn.functional.normalize(torch.linalg.cross(v1 - v0, v2 - v0), dim=-1)
    best = torch.full((points.shape[0],), math.inf, dtype=torch.float64)
    rows = max(1, _PAIRS_PER_CHUNK // max(tri.shape[0], 1))
    for start in range(0, points.shape[0], rows):
        p = points[start : start + rows, None]  # [C, 1, 3]
        height = ((p - v0) * normal).sum(-1)
        foot = p - height[..., None] * normal
        inside = torch.ones_like(height, dtype=torch.bool)
        for a, b in ((v0, v1), (v1, v2), (v2, v0)):
            inside &= (torch.linalg.cross((b - a).expand_as(foot), foot - a) * normal).sum(-1) >= 0.0
        distance = torch.where(inside, height.abs(), torch.full_like(height, math.inf))
        for a, b in ((v0, v1), (v1, v2), (v2, v0)):
            edge = b - a
            u = (((p - a) * edge).sum(-1) / (edge * edge).sum(-1).clamp_min(1e-300)).clamp(0.0, 1.0)
            distance = torch.minimum(distance, torch.linalg.norm(p - (a + u[..., None] * edge), dim=-1))
        best[start : start + rows] = distance.min(dim=1).values
    return best


def winding_number(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Generalised winding number ``[P]`` (float64) of the mesh at each point: the sum of the signed solid angles
    of all triangles over 4π (Van Oosterom and Strackee 1983); 1 inside a closed outward-oriented mesh, 0 outside.
    """
    tri = vertices.detach().to(torch.float64)[faces.long()]
    points = points.detach().to(torch.float64)
    out = torch.empty(points.shape[0], dtype=torch.float64)
    rows = max(1, _PAIRS_PER_CHUNK // max(tri.shape[0], 1))
    for start in range(0, points.shape[0], rows):
        rel = tri[None] - points[start : start + rows, None, None, :]
        a, b, c = rel[..., 0, :], rel[..., 1, :], rel[..., 2, :]
        la, lb, lc = (torch.linalg.norm(t, dim=-1) for t in (a, b, c))
        num = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[start : start + rows] = torch.atan2(num, den).sum(1) / (2.0 * math.pi)
    return out


def shade(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    colors: torch.Tensor,
    *,
    face_colors: bool = False,
    light_direction=(0.35, 1.0, 0.55),
    ambient: float = 0.3,
    diffuse: float = 0.7,
    shadows: bool = True,
    shadow_bias: float = 1.0e-4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lambert shading with ambient light and a shadowed directional light, as :func:`kernels.raycast.shade`.

    Flat shading only (geometric face normals). Returns ``rgba [R, 4]`` and ``depth [R]``, float64.
    """
    vertices64 = vertices.detach().to(torch.float64)
    faces64 = faces.long()
    directions = torch.nn.functional.normalize(directions.detach().to(torch.float64), dim=-1)
    origins = origins.detach().to(torch.float64)
    t, face, bary = cast_rays(vertices64, faces64, origins, directions)
    hit = face >= 0
    rgba = torch.zeros(origins.shape[0], 4, dtype=torch.float64)
    if not bool(hit.any()):
        return rgba, t
    f = faces64[face[hit]]
    b1, b2 = bary[hit, 0:1], bary[hit, 1:2]
    colors64 = colors.detach().to(torch.float64)
    if face_colors:
        albedo = colors64[face[hit]]
    else:
        albedo = (1.0 - b1 - b2) * colors64[f[:, 0]] + b1 * colors64[f[:, 1]] + b2 * colors64[f[:, 2]]
    v0, v1, v2 = vertices64[f[:, 0]], vertices64[f[:, 1]], vertices64[f[:, 2]]
    normal = torch.nn.functional.normalize(torch.linalg.cross(v1 - v0, v2 - v0), dim=-1)
    d = directions[hit]
    normal = torch.where(((normal * d).sum(-1) > 0.0)[:, None], -normal, normal)
    light = torch.nn.functional.normalize(torch.as_tensor(light_direction, dtype=torch.float64), dim=0)
    cosine = (normal @ light).clamp_min(0.0)
    if shadows:
        point = origins[hit] + t[hit, None] * d + shadow_bias * normal
        shadow_t, _, _ = cast_rays(vertices64, faces64, point, light.expand_as(point))
        cosine = torch.where(torch.isfinite(shadow_t), torch.zeros_like(cosine), cosine)
    rgba[hit, :3] = (albedo * (ambient + diffuse * cosine[:, None])).clamp(0.0, 1.0)
    rgba[hit, 3] = 1.0
    return rgba, t
