"""Ray casting and shading of triangle meshes through Warp's BVH: the renderer of the project's ground truth.

PIE-NeRF trains its NeRF (§3.1) on multi-view RGBA renders of each scene (§5: "BlenderNeRF ... 100 multi-view
images"). This module is the renderer that makes them from the project's own meshes: first hits through a
bounding-volume hierarchy, then Lambert shading under ambient light plus one directional light whose hard
shadows come from a second ray (the moving shadows of Fig. 7 are cast the same way).

Conventions:

* Directions need not be unit vectors: the kernels normalise them, so every ``t`` and depth is a distance in
  metres along the ray, not a multiple of the direction's length.
* Barycentrics are ``(b1, b2)`` of the hit face ``(v0, v1, v2)``: the hit lies at ``(1 − b1 − b2) v0 + b1 v1 +
  b2 v2`` (the Möller–Trumbore convention; Warp's own ``(u, v)`` weigh ``v0`` and ``v1`` and are converted).
* A miss has ``t = depth = inf``, face −1, barycentrics 0 and RGBA 0 (transparent).

Warp is the only framework here with a triangle BVH (``wp.Mesh``, SAH build on the CPU, LBVH on CUDA) that
refits in place when a mesh deforms; Taichi has none, so both devices run Warp. Warp runs CPU kernels on one
thread, which is fast enough for a view per frame (``docs/benchmarks.md``).
"""

import math
from typing import NamedTuple

import torch
import warp as wp

from kernels import backend

# The renderer is not differentiated; Warp's adjoint code would only add compile time.
wp.set_module_options({"enable_backward": False, "block_dim": backend.SMALL_GRID_BLOCK_DIM})

__all__ = ["ClosestPoints", "MeshBVH", "RayHits", "Shading", "cast_rays", "shade"]

# Warp's ray queries take a finite ``max_t``; an infinite limit becomes this many metres.
_FAR = wp.constant(1.0e30)


class RayHits(NamedTuple):
    """First hits of a batch of rays.

    Attributes:
        t: ``[R]`` float32 distance from the origin to the hit along the unit ray, metres; ``inf`` on a miss.
        face: ``[R]`` int32 index of the hit face, −1 on a miss.
        bary: ``[R, 2]`` float32 barycentrics ``(b1, b2)``: hit ``= (1 − b1 − b2) v0 + b1 v1 + b2 v2``; 0 on a miss.
    """

    t: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor


class Shading(NamedTuple):
    """A shaded batch of rays.

    Attributes:
        rgba: ``[R, 4]`` float32 in [0, 1]: straight (not premultiplied) colour and alpha = 1 on a hit, 0 on a miss.
        depth: ``[R]`` float32 distance along the unit ray to the hit, metres; ``inf`` on a miss. The camera-space
            z-depth is ``depth · (d̂ · forward)`` for a unit ray direction ``d̂`` and unit view axis ``forward``.
    """

    rgba: torch.Tensor
    depth: torch.Tensor


class ClosestPoints(NamedTuple):
    """Closest surface points of a batch of query points.

    Attributes:
        distance: ``[P]`` float32 unsigned distance to the mesh, metres; ``inf`` beyond the search radius.
        face: ``[P]`` int32 face holding the closest point, −1 beyond the search radius.
        bary: ``[P, 2]`` float32 barycentrics ``(b1, b2)`` of the closest point in that face (as :class:`RayHits`).
    """

    distance: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor


@wp.kernel
def _closest_points(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_distance: float,
    distance_out: wp.array(dtype=float),
    face_out: wp.array(dtype=wp.int32),
    bary_out: wp.array(dtype=wp.vec2),
):
    i = wp.tid()
    query = wp.mesh_query_point_no_sign(mesh, points[i], max_distance)
    if query.result:
        closest = wp.mesh_eval_position(mesh, query.face, query.u, query.v)
        distance_out[i] = wp.length(closest - points[i])
        face_out[i] = query.face
        bary_out[i] = wp.vec2(query.v, 1.0 - query.u - query.v)
    else:
        distance_out[i] = wp.inf
        face_out[i] = -1
        bary_out[i] = wp.vec2(0.0, 0.0)


@wp.kernel
def _inside(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), inside_out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    query = wp.mesh_query_point_sign_winding_number(mesh, points[i], _FAR)
    inside_out[i] = wp.where(query.result and query.sign < 0.0, 1, 0)


# Solid angles a thread of :func:`_solid_angle_sums` adds up: one chunk of faces for one point.
_FACES_PER_THREAD = 256
# Up to this many point–face pairs a CUDA device sums every face's solid angle (:meth:`MeshBVH.inside`): about
# 0.3 ms on an H100-class GPU, where the tree's traversal, one thread a point, waits on memory for milliseconds.
_DIRECT_PAIRS = 1 << 28


@wp.kernel
def _solid_angle_sums(
    points: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    chunk: int,
    sums_out: wp.array(dtype=float, ndim=2),
):
    # consecutive threads take consecutive points and the same faces, which a warp then reads once
    c, i = wp.tid()
    p = points[i]
    start = c * chunk
    end = wp.min(start + chunk, faces.shape[0])
    total = wp.float32(0.0)  # a dynamic variable: the loop adds to it
    for f in range(start, end):
        a = vertices[faces[f, 0]] - p
        b = vertices[faces[f, 1]] - p
        d = vertices[faces[f, 2]] - p
        la = wp.length(a)
        lb = wp.length(b)
        ld = wp.length(d)
        # tan(Ω/2) of the triangle seen from p (Van Oosterom and Strackee 1983)
        num = wp.dot(a, wp.cross(b, d))
        den = la * lb * ld + wp.dot(a, b) * ld + wp.dot(b, d) * la + wp.dot(d, a) * lb
        total += wp.atan2(num, den)
    sums_out[c, i] = total


@wp.kernel
def _cast_rays(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    max_distance: float,
    t_out: wp.array(dtype=float),
    face_out: wp.array(dtype=wp.int32),
    bary_out: wp.array(dtype=wp.vec2),
):
    i = wp.tid()
    query = wp.mesh_query_ray(mesh, origins[i], wp.normalize(directions[i]), max_distance)
    if query.result:
        t_out[i] = query.t
        face_out[i] = query.face
        bary_out[i] = wp.vec2(query.v, 1.0 - query.u - query.v)
    else:
        t_out[i] = wp.inf
        face_out[i] = -1
        bary_out[i] = wp.vec2(0.0, 0.0)


class MeshBVH:
    """A triangle mesh with its bounding-volume hierarchy, built once and refitted as the mesh deforms.

    Args:
        vertices: ``[V, 3]`` float tensor on the backend device, metres (copied into the BVH's own buffer).
        faces: ``[F, 3]`` integer tensor of vertex indices on the backend device.
        winding_numbers: also keep the per-node data of the fast winding number (Barill et al. 2018) that
            :meth:`inside` needs; it costs a little more to build and refit.

    Raises:
        ValueError: shapes are wrong, the mesh is empty or a face indexes a missing vertex.
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, winding_numbers: bool = False):
        _check_vertices(vertices, "vertices")
        if not isinstance(faces, torch.Tensor) or faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point():
            raise ValueError(f"faces must be an integer [F, 3] tensor, got {getattr(faces, 'shape', type(faces))}")
        if faces.shape[0] == 0 or vertices.shape[0] == 0:
            raise ValueError("MeshBVH needs at least one face and its vertices; the mesh is empty")
        if int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[0]:
            raise ValueError(
                f"faces index vertices 0..{vertices.shape[0] - 1} but hold indices "
                f"{int(faces.min())}..{int(faces.max())}"
            )
        self._points = vertices.detach().to(torch.float32).contiguous().clone()
        self._faces = faces.detach().to(torch.int32).contiguous()
        self._indices = self._faces.reshape(-1)
        self.winding_numbers = winding_numbers
        self.mesh = wp.Mesh(
            points=backend.to_warp(self._points, dtype=wp.vec3),
            indices=backend.to_warp(self._indices),
            support_winding_number=winding_numbers,
        )

    @property
    def vertices(self) -> torch.Tensor:
        """``[V, 3]`` float32 vertex positions the BVH currently bounds, metres."""
        return self._points

    @property
    def faces(self) -> torch.Tensor:
        """``[F, 3]`` int32 vertex indices."""
        return self._faces

    def refit(self, vertices: torch.Tensor) -> None:
        """Move the vertices to ``vertices [V, 3]`` (same connectivity) and refit the hierarchy's boxes in place.

        Refitting keeps the tree's topology, so it stays fast for smooth deformations; rebuild a new
        :class:`MeshBVH` after the mesh has been torn apart or moved by far more than its size.
        """
        _check_vertices(vertices, "vertices")
        if vertices.shape != self._points.shape:
            raise ValueError(
                f"refit needs {tuple(self._points.shape)} vertices (same mesh), got {tuple(vertices.shape)}; "
                "build a new MeshBVH for a different mesh"
            )
        self._points.copy_(vertices)
        self.mesh.refit()

    def cast(self, origins: torch.Tensor, directions: torch.Tensor, max_distance: float = math.inf) -> RayHits:
        """First hit of each ray ``origins + t · d̂`` with ``0 ≤ t < max_distance`` (see :func:`cast_rays`)."""
        origins, directions = _check_rays(origins, directions)
        count = origins.shape[0]
        device = origins.device
        t = torch.empty(count, dtype=torch.float32, device=device)
        face = torch.empty(count, dtype=torch.int32, device=device)
        bary = torch.empty(count, 2, dtype=torch.float32, device=device)
        if count:
            backend.warp_launch(
                _cast_rays,
                dim=count,
                inputs=[
                    self.mesh.id,
                    backend.to_warp(origins, dtype=wp.vec3),
                    backend.to_warp(directions, dtype=wp.vec3),
                    _finite_limit(max_distance),
                    backend.to_warp(t),
                    backend.to_warp(face),
                    backend.to_warp(bary, dtype=wp.vec2),
                ],
                device=backend.warp_device(),
            )
        return RayHits(t, face, bary)

    def closest(self, points: torch.Tensor, max_distance: float = math.inf) -> ClosestPoints:
        """Closest point of the mesh's surface to each of ``points [P, 3]`` (metres) within ``max_distance``.

        The BVH prunes every box farther than the best distance found so far, so a query costs about
        ``O(log F)``; distances are exact point–triangle distances (float32).
        """
        _check_vertices(points, "points")
        count = points.shape[0]
        device = points.device
        distance = torch.empty(count, dtype=torch.float32, device=device)
        face = torch.empty(count, dtype=torch.int32, device=device)
        bary = torch.empty(count, 2, dtype=torch.float32, device=device)
        if count:
            backend.warp_launch(
                _closest_points,
                dim=count,
                inputs=[
                    self.mesh.id,
                    backend.to_warp(points.detach().to(torch.float32).contiguous(), dtype=wp.vec3),
                    _finite_limit(max_distance),
                    backend.to_warp(distance),
                    backend.to_warp(face),
                    backend.to_warp(bary, dtype=wp.vec2),
                ],
                device=backend.warp_device(),
            )
        return ClosestPoints(distance, face, bary)

    def inside(self, points: torch.Tensor, method: str = "auto") -> torch.Tensor:
        """``[P]`` bool: which of ``points [P, 3]`` (metres) lie inside the closed, outward-oriented mesh.

        A point is inside where the mesh's generalised winding number exceeds ½ (Jacobson et al. 2013), which holds
        for self-intersecting and slightly open meshes too. ``method`` says how it is evaluated:

        * ``"tree"``: Warp's fast winding number through the BVH (Barill et al. 2018; far clusters of triangles
          summed as dipoles), about ``O(log F)`` a point;
        * ``"direct"``: the exact sum of every face's solid angle, ``O(F)`` a point spread over threads that each
          take :data:`_FACES_PER_THREAD` faces;
        * ``"auto"``: direct on CUDA up to :data:`_DIRECT_PAIRS` point–face pairs (there a point's traversal of
          the tree, one thread each, is latency-bound: 3 ms for a garment's 3.7k vertices against a 15k-face body
          on an H200, where the direct sum takes a tenth of that), the tree otherwise.

        Raises:
            ValueError: the BVH was built without ``winding_numbers=True``, or ``method`` is unknown.
        """
        if not self.winding_numbers:
            raise ValueError("inside() needs the winding-number data: build the MeshBVH with winding_numbers=True")
        if method not in ("auto", "tree", "direct"):
            raise ValueError(f"method must be 'auto', 'tree' or 'direct', got {method!r}")
        _check_vertices(points, "points")
        count = points.shape[0]
        if count == 0:
            return torch.zeros(0, dtype=torch.bool, device=points.device)
        points = points.detach().to(torch.float32).contiguous()
        faces = self._faces.shape[0]
        if method == "auto":
            method = "direct" if points.device.type == "cuda" and count * faces <= _DIRECT_PAIRS else "tree"
        if method == "direct":
            chunks = -(-faces // _FACES_PER_THREAD)
            sums = torch.empty(chunks, count, dtype=torch.float32, device=points.device)
            backend.warp_launch(
                _solid_angle_sums,
                dim=(chunks, count),
                inputs=[
                    backend.to_warp(points, dtype=wp.vec3),
                    backend.to_warp(self._points, dtype=wp.vec3),
                    backend.to_warp(self._faces),
                    _FACES_PER_THREAD,
                    backend.to_warp(sums),
                ],
                device=backend.warp_device(),
            )
            # Σ atan2 = Σ Ω/2, so the winding number Σ Ω / 4π exceeds ½ where the sum exceeds π
            return sums.sum(0) > math.pi
        flags = torch.zeros(count, dtype=torch.int32, device=points.device)
        backend.warp_launch(
            _inside,
            dim=count,
            inputs=[self.mesh.id, backend.to_warp(points, dtype=wp.vec3), backend.to_warp(flags)],
            device=backend.warp_device(),
        )
        return flags.bool()


def cast_rays(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    max_distance: float = math.inf,
) -> RayHits:
    """First hit of each ray with a triangle mesh: distance, face and barycentrics.

    Builds a :class:`MeshBVH` for this one call; keep a :class:`MeshBVH` and call :meth:`MeshBVH.cast` to cast
    many batches against one mesh, and :meth:`MeshBVH.refit` when it deforms.

    Args:
        vertices: ``[V, 3]`` float tensor, metres.
        faces: ``[F, 3]`` integer tensor of vertex indices.
        origins: ``[R, 3]`` ray origins, metres.
        directions: ``[R, 3]`` ray directions (normalised here; need not be unit).
        max_distance: hits at or beyond this distance (metres) count as misses.

    Returns:
        :class:`RayHits` with ``t [R]``, ``face [R]`` and ``bary [R, 2]``.
    """
    return MeshBVH(vertices, faces).cast(origins, directions, max_distance)


@wp.kernel
def _shade(
    mesh: wp.uint64,
    faces: wp.array(dtype=wp.int32, ndim=2),
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    face_colors: int,
    normals: wp.array(dtype=wp.vec3),
    smooth: int,
    light: wp.vec3,
    ambient: float,
    diffuse: float,
    shadows: int,
    shadow_bias: float,
    max_distance: float,
    rgba_out: wp.array(dtype=wp.vec4),
    depth_out: wp.array(dtype=float),
):
    i = wp.tid()
    direction = wp.normalize(directions[i])
    query = wp.mesh_query_ray(mesh, origins[i], direction, max_distance)
    if not query.result:
        rgba_out[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        depth_out[i] = wp.inf
        return
    f = query.face
    # Warp's (u, v) weigh corners 0 and 1; corner 2 takes the rest.
    w0 = query.u
    w1 = query.v
    w2 = 1.0 - query.u - query.v
    a = faces[f, 0]
    b = faces[f, 1]
    c = faces[f, 2]
    albedo = wp.vec3(0.0, 0.0, 0.0)
    if face_colors != 0:
        albedo = colors[f]
    else:
        albedo = w0 * colors[a] + w1 * colors[b] + w2 * colors[c]
    normal = query.normal
    if smooth != 0:
        normal = wp.normalize(w0 * normals[a] + w1 * normals[b] + w2 * normals[c])
    # Two-sided: shade the side the ray arrives on.
    if wp.dot(query.normal, direction) > 0.0:
        normal = -normal
    geometric = query.normal
    if wp.dot(geometric, direction) > 0.0:
        geometric = -geometric
    cosine = wp.max(wp.dot(normal, light), 0.0)
    if shadows != 0 and cosine > 0.0:
        # Leave the surface along its geometric normal so the shadow ray cannot re-hit the face it starts on.
        start = origins[i] + query.t * direction + shadow_bias * geometric
        if wp.mesh_query_ray_anyhit(mesh, start, light, _FAR):
            cosine = 0.0
    radiance = albedo * (ambient + diffuse * cosine)
    rgba_out[i] = wp.vec4(
        wp.clamp(radiance[0], 0.0, 1.0), wp.clamp(radiance[1], 0.0, 1.0), wp.clamp(radiance[2], 0.0, 1.0), 1.0
    )
    depth_out[i] = query.t


def shade(
    bvh: MeshBVH,
    origins: torch.Tensor,
    directions: torch.Tensor,
    colors: torch.Tensor,
    *,
    face_colors: bool = False,
    normals: torch.Tensor | None = None,
    light_direction=(0.35, 1.0, 0.55),
    ambient: float = 0.3,
    diffuse: float = 0.7,
    shadows: bool = True,
    shadow_bias: float = 1.0e-4,
    max_distance: float = math.inf,
) -> Shading:
    """Shade the first hit of each ray: Lambert reflection of ambient light and one directional light.

    The colour of a hit with albedo ρ and unit normal n (turned to face the ray) is

        c = clamp(ρ · (k_a + k_d · max(0, n · l̂) · V), 0, 1)

    with ``k_a = ambient``, ``k_d = diffuse``, ``l̂`` the unit direction toward the light and visibility ``V`` = 0
    when a shadow ray from the hit toward the light meets the mesh, else 1. The shadow ray starts
    ``shadow_bias`` metres off the surface along the geometric normal, which removes self-shadowing "acne".
    The light is at infinity (directional), so the colour does not depend on the view: a Lambertian scene.

    Args:
        bvh: the mesh and its hierarchy.
        origins: ``[R, 3]`` ray origins, metres.
        directions: ``[R, 3]`` ray directions (normalised here).
        colors: albedo in [0, 1], ``[V, 3]`` per vertex (interpolated by barycentrics) or, with
            ``face_colors=True``, ``[F, 3]`` per face.
        face_colors: ``colors`` holds one colour per face.
        normals: ``[V, 3]`` unit vertex normals for smooth shading; ``None`` shades each face flat with its
            geometric normal.
        light_direction: ``[3]`` direction from the scene toward the light (normalised here).
        ambient: ``k_a``, fraction of the albedo reflected everywhere.
        diffuse: ``k_d``, fraction reflected under a light facing the surface.
        shadows: cast shadow rays (``False``: every surface facing the light is lit).
        shadow_bias: offset of the shadow ray's origin, metres; about 1e-4 of the scene's size.
        max_distance: primary hits at or beyond this distance (metres) count as misses.

    Returns:
        :class:`Shading` with ``rgba [R, 4]`` and ``depth [R]`` (distance along the ray, metres).
    """
    origins, directions = _check_rays(origins, directions)
    vertex_count, face_count = bvh.vertices.shape[0], bvh.faces.shape[0]
    expected = face_count if face_colors else vertex_count
    if colors.dim() != 2 or colors.shape != (expected, 3):
        per = "face" if face_colors else "vertex"
        raise ValueError(
            f"colors must be [{expected}, 3] (one RGB per {per}), got {tuple(colors.shape)}; "
            f"pass face_colors={not face_colors} if the colours are per {'vertex' if face_colors else 'face'}"
        )
    colors = colors.to(device=origins.device, dtype=torch.float32).contiguous()
    if normals is None:
        normals_arg = torch.zeros(1, 3, dtype=torch.float32, device=origins.device)
    else:
        if normals.shape != (vertex_count, 3):
            raise ValueError(f"normals must be [{vertex_count}, 3] vertex normals, got {tuple(normals.shape)}")
        normals_arg = normals.to(device=origins.device, dtype=torch.float32).contiguous()
    light = torch.as_tensor(light_direction, dtype=torch.float64).flatten()
    if light.shape != (3,) or not bool(torch.isfinite(light).all()) or float(light.norm()) == 0.0:
        raise ValueError(f"light_direction must be 3 finite numbers, not all zero, got {light_direction!r}")
    light = light / light.norm()
    if not (ambient >= 0.0 and diffuse >= 0.0):
        raise ValueError(f"ambient and diffuse must be non-negative, got {ambient} and {diffuse}")
    if not shadow_bias >= 0.0:
        raise ValueError(f"shadow_bias must be a non-negative length in metres, got {shadow_bias}")

    count = origins.shape[0]
    rgba = torch.empty(count, 4, dtype=torch.float32, device=origins.device)
    depth = torch.empty(count, dtype=torch.float32, device=origins.device)
    if count:
        backend.warp_launch(
            _shade,
            dim=count,
            inputs=[
                bvh.mesh.id,
                backend.to_warp(bvh.faces),
                backend.to_warp(origins, dtype=wp.vec3),
                backend.to_warp(directions, dtype=wp.vec3),
                backend.to_warp(colors, dtype=wp.vec3),
                int(face_colors),
                backend.to_warp(normals_arg, dtype=wp.vec3),
                int(normals is not None),
                wp.vec3(*light.tolist()),
                float(ambient),
                float(diffuse),
                int(shadows),
                float(shadow_bias),
                _finite_limit(max_distance),
                backend.to_warp(rgba, dtype=wp.vec4),
                backend.to_warp(depth),
            ],
            device=backend.warp_device(),
        )
    return Shading(rgba, depth)


def _finite_limit(max_distance: float) -> float:
    if not max_distance > 0.0:
        raise ValueError(f"max_distance must be a positive length in metres (or inf), got {max_distance}")
    return min(float(max_distance), _FAR)


def _check_vertices(vertices: torch.Tensor, what: str) -> None:
    if not isinstance(vertices, torch.Tensor) or not vertices.is_floating_point():
        raise TypeError(
            f"{what} must be a floating-point torch.Tensor, got {getattr(vertices, 'dtype', type(vertices))}"
        )
    if vertices.dim() != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{what} must have shape [V, 3], got {tuple(vertices.shape)}")


def _check_rays(origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    for name, value in (("origins", origins), ("directions", directions)):
        if not isinstance(value, torch.Tensor) or value.dim() != 2 or value.shape[1] != 3:
            raise ValueError(f"{name} must be an [R, 3] tensor, got {tuple(getattr(value, 'shape', ()))}")
    if origins.shape != directions.shape:
        raise ValueError(
            f"origins and directions must have one row per ray, "
            f"got {tuple(origins.shape)} and {tuple(directions.shape)}"
        )
    return origins.to(torch.float32).contiguous(), directions.to(torch.float32).contiguous()
