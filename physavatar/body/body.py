"""The body that drives and collides with the garment (PhysAvatar §3.2, Appendix A.3).

PhysAvatar uses SMPL-X as the body collider {V^C_t, F^C} and animates it with linear blend skinning
(LBS); garment boundary vertices follow the LBS of the nearest body points (Appendix A.3.2). SMPL-X
is not freely licensed, so this module builds a procedural mannequin in its place: an articulated
skeleton with the 22 body joints of SMPL (same names, same order, same parent tree), a smooth,
closed, genus-0 skin mesh, and per-vertex skinning weights.

Conventions: metres, y up, the body faces +z, its left side is at +x (as in SMPL), the soles touch
y = 0. The rest pose is an A-pose (arms 45° below horizontal) with every joint frame aligned with
the world axes, so a zero rotation everywhere (and a zero root translation) is the rest pose and a
local rotation is expressed in world axes at rest: a positive rotation about +x swings a leg or an
arm backwards (-z) and bends a knee; a positive rotation about +z raises the left arm.

The skin is the zero level set of a smooth union of ellipsoids and tapered capsules, one or more
per bone, extracted by marching tetrahedra on a Kuhn (6-tetrahedra-per-cube) grid. The level set of
a piecewise-linear field on a simplicial grid with no zero values is a closed 2-manifold, so the
mesh is watertight by construction; its vertices are then relaxed tangentially and projected back
onto the level set to even out the triangles.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from physavatar.body.mannequin import bone_distances, mannequin_mesh, skinning_weights
from physavatar.body.skeleton import REFERENCE_HEIGHT, Skeleton, linear_blend_skinning

__all__ = [
    "Body",
    "surface_closest_points",
]

# --- the body -------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Body:
    """A skinned body: skeleton, closed rest mesh and LBS weights (the collider {V^C, F^C} of Eq. 5).

    Attributes:
        skeleton: the kinematic tree driving the mesh.
        vertices: [V, 3] rest-pose vertex positions, metres.
        faces: [F, 3] vertex indices, counter-clockwise seen from outside (normals point out).
        weights: [V, J] skinning weights, non-negative, at most four non-zero per row, rows sum to one.
    """

    skeleton: Skeleton
    vertices: torch.Tensor
    faces: torch.Tensor
    weights: torch.Tensor

    @classmethod
    def mannequin(cls, height: float = REFERENCE_HEIGHT, spacing: float = 0.028, falloff: float = 0.012) -> "Body":
        """Build the procedural mannequin.

        Args:
            height: standing height, metres (soles at y = 0, top of the head at y = height).
            spacing: grid spacing of the surface extraction at 1.75 m height, metres; 0.028 gives about
                17k triangles.
            falloff: distance over which skinning weights fade from one bone to the next, metres.

        Returns:
            The body in float64 on the CPU; use :meth:`to` to move it.
        """
        if not height > 0:
            raise ValueError(f"height must be positive (metres), got {height}")
        if not 0.004 <= spacing <= 0.03:
            raise ValueError(
                f"spacing must lie in [0.004, 0.03] m (finer is slow, coarser loses the wrists), got {spacing}"
            )
        if not falloff > 0:
            raise ValueError(f"falloff must be positive (metres), got {falloff}")
        scale = height / REFERENCE_HEIGHT
        vertices, faces = mannequin_mesh(scale, spacing * scale)
        weights = skinning_weights(bone_distances(vertices, scale), falloff * scale)
        return cls(
            Skeleton.mannequin(height),
            torch.as_tensor(vertices, dtype=torch.float64),
            torch.as_tensor(faces, dtype=torch.int64),
            torch.as_tensor(weights, dtype=torch.float64),
        )

    def to(self, device: str | torch.device | None = None, dtype: torch.dtype | None = None) -> "Body":
        """A copy with every tensor on ``device`` and floating tensors in ``dtype``."""

        def move(t):
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        skel = self.skeleton
        return Body(
            Skeleton(skel.names, skel.parents, move(skel.rest_positions), move(skel.rest_tails)),
            move(self.vertices),
            move(self.faces),
            move(self.weights),
        )

    def trimesh(self, vertices: torch.Tensor | None = None) -> trimesh.Trimesh:
        """The rest mesh (or the same connectivity with ``vertices`` [V, 3]) as a ``trimesh.Trimesh``."""
        v = self.vertices if vertices is None else vertices
        return trimesh.Trimesh(v.detach().cpu().numpy(), self.faces.cpu().numpy(), process=False)

    def skin(self, rotations: torch.Tensor, root_translation: torch.Tensor | None = None) -> torch.Tensor:
        """Posed vertex positions by LBS.

        Args:
            rotations: local joint rotations, axis-angle [..., J, 3] (radians) or matrices [..., J, 3, 3];
                leading dimensions (e.g. frames) are batched.
            root_translation: [..., 3] root displacement from rest, metres, or ``None``.

        Returns:
            [..., V, 3] vertex positions, metres.
        """
        transforms = self.skeleton.skinning_transforms(rotations, root_translation)
        return linear_blend_skinning(self.vertices, self.weights, transforms)

    def closest_points(self, points: torch.Tensor, vertices: torch.Tensor | None = None):
        """Closest points on the body surface (:func:`surface_closest_points` of this mesh).

        Args:
            points: [P, 3] query points, metres.
            vertices: [V, 3] posed vertices to query instead of the rest mesh.

        Returns:
            ``(closest [P, 3], distance [P], face [P], barycentric [P, 3])``, metres for lengths.
        """
        return surface_closest_points(self.vertices if vertices is None else vertices, self.faces, points)

    def winding_number(self, points: torch.Tensor, vertices: torch.Tensor | None = None) -> torch.Tensor:
        """Generalised winding number [P] of the closed surface at ``points`` [P, 3]: 1 inside, 0 outside.

        Sums the signed solid angles of all triangles (Van Oosterom-Strackee formula) divided by 4π.
        """
        v = (self.vertices if vertices is None else vertices).to(points)
        tri = v[self.faces.to(points.device)]
        out = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
        for start in range(0, points.shape[0], 128):
            q = points[start : start + 128]
            r = tri.unsqueeze(0) - q[:, None, None, :]  # [P, F, 3, 3]
            length = torch.linalg.vector_norm(r, dim=-1)
            a, b, c = r.unbind(-2)
            la, lb, lc = length.unbind(-1)
            det = (a * torch.cross(b, c, dim=-1)).sum(-1)
            den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
            out[start : start + 128] = 2.0 * torch.atan2(det, den).sum(-1) / (4.0 * math.pi)
        return out

    def signed_distance(self, points: torch.Tensor, vertices: torch.Tensor | None = None) -> torch.Tensor:
        """Signed distance [P] from ``points`` [P, 3] to the body surface, metres, negative inside."""
        _, distance, _, _ = self.closest_points(points, vertices)
        inside = self.winding_number(points, vertices) > 0.5
        return torch.where(inside, -distance, distance)

    def surface_weights(self, points: torch.Tensor) -> torch.Tensor:
        """Skinning weights [P, J] for points near the rest body, from the closest surface point.

        The weights of the closest triangle's vertices, blended barycentrically; this is how garment
        boundary vertices follow the body's LBS (Appendix A.3.2).
        """
        _, _, face, bary = self.closest_points(points)
        corner_weights = self.weights[self.faces[face.to(self.faces.device)]]  # [P, 3, J]
        w = (bary.to(corner_weights).unsqueeze(-1) * corner_weights).sum(1).clamp_min(0.0)
        return w / w.sum(1, keepdim=True)


# --- surface queries of any triangle mesh --------------------------------------------------------------------


def surface_closest_points(vertices: torch.Tensor, faces: torch.Tensor, points: torch.Tensor):
    """Closest points of a triangle mesh's surface to query points, exact in float64.

    The distance to a point's nearest mesh vertex bounds its distance to the surface from above, and every point of
    a triangle lies within the triangle's largest centroid–corner distance of its centroid; so the triangles whose
    centroids lie within the sum of the two hold the closest point, and only those are measured (a k-d tree finds
    them). Vertices that no face uses are left out of the bound.

    Args:
        vertices: [V, 3] mesh vertices, metres.
        faces: [F, 3] vertex indices, F ≥ 1.
        points: [P, 3] query points, metres.

    Returns:
        ``(closest [P, 3], distance [P], face [P], barycentric [P, 3])``, metres for lengths, in the dtype and on the
        device of ``points`` (``face`` int64 indexes ``faces``).
    """
    v = vertices.detach().cpu().numpy()
    f = faces.cpu().numpy()
    q = points.detach().cpu().numpy().astype(np.float64)
    tri = v[f]
    centroid = tri.mean(axis=1)
    reach = np.linalg.norm(tri - centroid[:, None], axis=2).max()
    upper, _ = cKDTree(v[np.unique(f)]).query(q)
    candidates = cKDTree(centroid).query_ball_point(q, upper + reach)
    point_index = np.repeat(np.arange(len(q)), [len(c) for c in candidates])
    face_index = np.concatenate([np.asarray(c, dtype=np.int64) for c in candidates])
    on_face = trimesh.triangles.closest_point(tri[face_index], q[point_index])
    squared = ((on_face - q[point_index]) ** 2).sum(1)
    order = np.lexsort((squared, point_index))  # per point, its nearest candidate first
    first = order[np.searchsorted(point_index[order], np.arange(len(q)))]
    closest, face = on_face[first], face_index[first]
    bary = trimesh.triangles.points_to_barycentric(tri[face], closest)
    out = torch.as_tensor(closest, dtype=points.dtype, device=points.device)
    return (
        out,
        torch.linalg.vector_norm(out - points, dim=1),
        torch.as_tensor(face, device=points.device),
        torch.as_tensor(bary, dtype=points.dtype, device=points.device),
    )
