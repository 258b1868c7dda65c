"""Points carried along by a moving body mesh: the boundary vertices of a garment worn by a captured body.

PhysAvatar's boundary vertices follow the LBS of their nearest body points (Appendix A.3.2). A captured body is a
mesh per frame (a SMPL-X fit exported frame by frame) with no skeleton to skin, so a point is attached to its
nearest body triangle instead: its barycentric coordinates there and its offset in the triangle's own frame
(first edge, in-plane perpendicular, normal) at the first frame, carried to every frame by the same triangle. For
a rigid motion of the triangle this is the rigid motion of the point; it is LBS with the triangle's three vertices
as the bones.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from physavatar.body.body import surface_closest_points

__all__ = ["SurfaceAttachment", "attach_to_surface"]


@dataclass(frozen=True, eq=False)
class SurfaceAttachment:
    """Points attached to a body mesh's triangles.

    Attributes:
        face: ``[P]`` int64 body triangle of each point.
        barycentric: ``[P, 3]`` float64 coordinates of the point's foot on that triangle.
        offset: ``[P, 3]`` float64 from the foot to the point in the triangle's frame (edge, in-plane, normal), m.
    """

    face: torch.Tensor
    barycentric: torch.Tensor
    offset: torch.Tensor

    def positions(self, body_frames: torch.Tensor, body_faces: torch.Tensor) -> torch.Tensor:
        """The attached points carried by the body through its frames.

        Args:
            body_frames: ``[T, B, 3]`` (or ``[B, 3]``) body vertices per frame, m.
            body_faces: ``[G, 3]`` the body's triangles (those the attachment was made on).

        Returns:
            ``[T, P, 3]`` (or ``[P, 3]``) float64 positions, m.
        """
        single = body_frames.dim() == 2
        frames = body_frames[None] if single else body_frames
        corners = frames.to(torch.float64)[:, body_faces[self.face].cpu()]  # [T, P, 3, 3]
        foot = (self.barycentric[None, :, :, None] * corners).sum(2)
        axes = _triangle_frames(corners)  # [T, P, 3, 3], rows are the axes
        out = foot + (self.offset[None, :, :, None] * axes).sum(2)
        return out[0] if single else out


def attach_to_surface(points: torch.Tensor, body_vertices: torch.Tensor, body_faces: torch.Tensor) -> SurfaceAttachment:
    """Attach points to their nearest triangles of a body mesh (:class:`SurfaceAttachment`).

    Args:
        points: ``[P, 3]`` points, m (e.g. a garment's boundary vertices at the first frame).
        body_vertices: ``[B, 3]`` the body at that frame, m.
        body_faces: ``[G, 3]`` its triangles.

    Raises:
        ValueError: a shape that is not ``[·, 3]``, non-finite coordinates, or a degenerate nearest triangle.
    """
    for name, value in (("points", points), ("body_vertices", body_vertices), ("body_faces", body_faces)):
        if value.dim() != 2 or value.shape[1] != 3 or value.shape[0] == 0:
            raise ValueError(f"{name} must be a non-empty [N, 3] tensor, got {tuple(value.shape)}")
    if not bool(torch.isfinite(points).all()) or not bool(torch.isfinite(body_vertices).all()):
        raise ValueError("points and body_vertices must be finite; the meshes hold NaN or inf coordinates")
    points = points.detach().cpu().to(torch.float64)
    vertices = body_vertices.detach().cpu().to(torch.float64)
    faces = body_faces.detach().cpu().long()
    foot, _, face, barycentric = surface_closest_points(vertices, faces, points)
    axes = _triangle_frames(vertices[faces[face]][None])[0]
    offset = torch.einsum("pij,pj->pi", axes, points - foot)
    if not bool(torch.isfinite(offset).all()):
        raise ValueError("a point's nearest body triangle has no area; remove the body mesh's degenerate triangles")
    return SurfaceAttachment(face.long(), barycentric.to(torch.float64), offset)


def _triangle_frames(corners: torch.Tensor) -> torch.Tensor:
    """``[..., 3, 3]`` orthonormal frames (rows: first edge, in-plane perpendicular, normal) of triangles
    ``corners [..., 3, 3]``."""
    edge = corners[..., 1, :] - corners[..., 0, :]
    normal = torch.linalg.cross(edge, corners[..., 2, :] - corners[..., 0, :], dim=-1)
    first = edge / torch.linalg.vector_norm(edge, dim=-1, keepdim=True)
    normal = normal / torch.linalg.vector_norm(normal, dim=-1, keepdim=True)
    return torch.stack([first, torch.linalg.cross(normal, first, dim=-1), normal], -2)
