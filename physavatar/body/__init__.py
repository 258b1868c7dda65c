"""The body that drives and collides with the garment, and the motions that drive it (PhysAvatar §3.2, Appendix A.3).

PhysAvatar uses SMPL-X as the body collider {V^C_t, F^C} and animates it with linear blend skinning (LBS);
SMPL-X is not freely licensed, so this package builds a procedural mannequin in its place:

- :mod:`~physavatar.body.skeleton`: the 22 SMPL joints, their rest pose, and linear blend skinning;
- :mod:`~physavatar.body.mannequin`: the skin's signed distance field, its marching-tetrahedra mesh and its
  skinning weights;
- :mod:`~physavatar.body.body`: :class:`Body`, the skinned, closed collider mesh, and the closest points of a mesh's
  surface;
- :mod:`~physavatar.body.attachment`: points carried by a body mesh's triangles (a captured body has no skeleton);
- :mod:`~physavatar.body.motion`: procedural motions (walk, turn, raise arms, jump);
- :mod:`~physavatar.body.bvh`: BVH motion files, read and written.
"""

from physavatar.body.attachment import SurfaceAttachment, attach_to_surface
from physavatar.body.body import Body, surface_closest_points
from physavatar.body.bvh import BVH_NAME_MAPS, MAX_BVH_FRAMES, REQUIRED_JOINTS, load_bvh, save_bvh
from physavatar.body.mannequin import bone_distances, mannequin_mesh, skinning_weights
from physavatar.body.motion import MOTIONS, Motion, jump, named_motion, raise_arms, turn, walk
from physavatar.body.skeleton import (
    JOINT_NAMES,
    JOINT_PARENTS,
    REFERENCE_HEIGHT,
    Skeleton,
    axis_angle_to_matrix,
    linear_blend_skinning,
    mannequin_joints,
)

__all__ = [
    "BVH_NAME_MAPS",
    "Body",
    "JOINT_NAMES",
    "JOINT_PARENTS",
    "MAX_BVH_FRAMES",
    "MOTIONS",
    "Motion",
    "REFERENCE_HEIGHT",
    "REQUIRED_JOINTS",
    "Skeleton",
    "SurfaceAttachment",
    "attach_to_surface",
    "axis_angle_to_matrix",
    "bone_distances",
    "jump",
    "linear_blend_skinning",
    "load_bvh",
    "mannequin_joints",
    "mannequin_mesh",
    "named_motion",
    "raise_arms",
    "save_bvh",
    "skinning_weights",
    "surface_closest_points",
    "turn",
    "walk",
]
