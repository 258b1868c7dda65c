"""The mannequin's skeleton: the 22 SMPL body joints, their rest pose, and linear blend skinning (PhysAvatar §3.2).

Conventions: metres, y up, the body faces +z, its left side is at +x (as in SMPL), the soles touch
y = 0. The rest pose is an A-pose (arms 45° below horizontal) with every joint frame aligned with
the world axes, so a zero rotation everywhere (and a zero root translation) is the rest pose and a
local rotation is expressed in world axes at rest: a positive rotation about +x swings a leg or an
arm backwards (-z) and bends a knee; a positive rotation about +z raises the left arm.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "JOINT_NAMES",
    "JOINT_PARENTS",
    "REFERENCE_HEIGHT",
    "Skeleton",
    "axis_angle_to_matrix",
    "linear_blend_skinning",
    "mannequin_joints",
]

JOINT_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
)
"""The SMPL body joints; ``*_collar`` is the clavicle, ``*_foot`` the ball of the foot (toe joint)."""

JOINT_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
"""Parent index of each joint in :data:`JOINT_NAMES`; parents precede their children."""

REFERENCE_HEIGHT = 1.75  # m, the height the mannequin's proportions below are written for
_ARM_DIRECTION = (math.sqrt(0.5), -math.sqrt(0.5), 0.0)  # left arm at rest, 45° below horizontal


def mannequin_joints() -> tuple[np.ndarray, np.ndarray]:
    """Rest joint positions [J, 3] and bone tail positions [J, 3] of a 1.75 m mannequin, metres.

    A bone runs from its joint to its tail: the child joint for limbs and spine, a tip for the
    end effectors (head top, hand tip, toe tip).
    """
    arm = np.array(_ARM_DIRECTION)
    left = {
        "hip": (0.090, 0.920, 0.000),
        "knee": (0.095, 0.500, 0.010),
        "ankle": (0.100, 0.080, -0.020),
        "foot": (0.105, 0.034, 0.110),
        "collar": (0.035, 1.440, -0.010),
        "shoulder": (0.170, 1.430, -0.015),
    }
    left["elbow"] = tuple(np.array(left["shoulder"]) + 0.28 * arm)
    left["wrist"] = tuple(np.array(left["elbow"]) + 0.25 * arm)
    joints = {
        "pelvis": (0.0, 0.980, 0.000),
        "spine1": (0.0, 1.080, -0.010),
        "spine2": (0.0, 1.200, -0.020),
        "spine3": (0.0, 1.330, -0.020),
        "neck": (0.0, 1.500, -0.010),
        "head": (0.0, 1.580, 0.000),
    }
    for part, (x, y, z) in left.items():
        joints[f"left_{part}"] = (x, y, z)
        joints[f"right_{part}"] = (-x, y, z)
    positions = np.array([joints[name] for name in JOINT_NAMES])
    tails = np.zeros_like(positions)
    first_child = {}
    for j, p in enumerate(JOINT_PARENTS):
        first_child.setdefault(p, j)
    tips = {"head": (0.0, 1.750, 0.020), "left_foot": (0.105, 0.030, 0.190), "right_foot": (-0.105, 0.030, 0.190)}
    for j, name in enumerate(JOINT_NAMES):
        if name in tips:
            tails[j] = tips[name]
        elif name.endswith("wrist"):
            tails[j] = positions[j] + 0.17 * arm * np.array([1.0 if name.startswith("left") else -1.0, 1.0, 1.0])
        elif name in ("spine3", "pelvis"):
            tails[j] = positions[JOINT_NAMES.index("neck" if name == "spine3" else "spine1")]
        else:
            tails[j] = positions[first_child[j]]
    return positions, tails


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from axis-angle vectors by Rodrigues' formula.

    Args:
        axis_angle: [..., 3] rotation vectors (unit axis times angle in radians).

    Returns:
        [..., 3, 3] rotation matrices; a zero vector gives the identity exactly.
    """
    angle = torch.linalg.vector_norm(axis_angle, dim=-1, keepdim=True)
    axis = axis_angle / torch.where(angle > 0, angle, torch.ones_like(angle))
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*axis.shape[:-1], 3, 3)
    s = torch.sin(angle)[..., None]
    c = (1.0 - torch.cos(angle))[..., None]
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + s * k + c * (k @ k)


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A kinematic tree of joints with rest positions.

    Attributes:
        names: joint names, parents before children.
        parents: parent index per joint, -1 for the root.
        rest_positions: [J, 3] joint positions in the rest pose, metres, world frame.
        rest_tails: [J, 3] end point of each joint's bone in the rest pose, metres.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    rest_positions: torch.Tensor
    rest_tails: torch.Tensor

    def __post_init__(self):
        if len(self.names) != len(self.parents):
            raise ValueError(f"skeleton has {len(self.names)} names but {len(self.parents)} parents; give one each")
        for j, p in enumerate(self.parents):
            if not -1 <= p < j or (p == -1) != (j == 0):
                raise ValueError(
                    f"joint {j} ({self.names[j]!r}) has parent {p}; the root must be joint 0 with parent -1 and "
                    "every other parent must come before its child"
                )
        for name, t in (("rest_positions", self.rest_positions), ("rest_tails", self.rest_tails)):
            if tuple(t.shape) != (len(self.names), 3):
                raise ValueError(f"{name} must have shape [{len(self.names)}, 3], got {list(t.shape)}")

    @classmethod
    def mannequin(cls, height: float = REFERENCE_HEIGHT, dtype: torch.dtype = torch.float64) -> "Skeleton":
        """The SMPL-named 22-joint skeleton of the procedural mannequin, scaled to ``height`` metres."""
        if not height > 0:
            raise ValueError(f"height must be positive (metres), got {height}")
        positions, tails = mannequin_joints()
        scale = height / REFERENCE_HEIGHT
        return cls(
            JOINT_NAMES,
            JOINT_PARENTS,
            torch.as_tensor(positions * scale, dtype=dtype),
            torch.as_tensor(tails * scale, dtype=dtype),
        )

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def rest_offsets(self) -> torch.Tensor:
        """[J, 3] rest offset of each joint from its parent, metres; the root's is its rest position."""
        parent_positions = self.rest_positions[[max(p, 0) for p in self.parents]]
        offsets = self.rest_positions - parent_positions
        offsets[0] = self.rest_positions[0]
        return offsets

    def index(self, name: str) -> int:
        """Index of the joint called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r} in the skeleton; joints are: {', '.join(self.names)}") from None

    def rest_rotations(self, *batch: int) -> torch.Tensor:
        """Identity local rotations [*batch, J, 3, 3]: the rest pose."""
        eye = torch.eye(3, dtype=self.rest_positions.dtype, device=self.rest_positions.device)
        return eye.expand(*batch, self.num_joints, 3, 3).clone()

    def _local_rotations(self, rotations: torch.Tensor) -> torch.Tensor:
        j = self.num_joints
        if rotations.shape[-2:] == (j, 3):
            return axis_angle_to_matrix(rotations)
        if rotations.shape[-3:] == (j, 3, 3):
            return rotations
        raise ValueError(
            f"rotations must be axis-angle [..., {j}, 3] or matrices [..., {j}, 3, 3] (one per joint), "
            f"got shape {list(rotations.shape)}"
        )

    def _world_frames(
        self, rotations: torch.Tensor, root_translation: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        local = self._local_rotations(rotations).to(self.rest_positions)
        batch = local.shape[:-3]
        offsets = self.rest_offsets.to(local.device)
        root = offsets[0].expand(*batch, 3)
        if root_translation is not None:
            if root_translation.shape[-1:] != (3,):
                raise ValueError(f"root_translation must have shape [..., 3], got {list(root_translation.shape)}")
            root = root + root_translation.to(local)
        world_rot = [local[..., 0, :, :]]
        world_pos = [root]
        for j in range(1, self.num_joints):
            p = self.parents[j]
            world_rot.append(world_rot[p] @ local[..., j, :, :])
            world_pos.append(world_pos[p] + (world_rot[p] @ offsets[j].unsqueeze(-1)).squeeze(-1))
        return torch.stack(world_rot, dim=-3), torch.stack(world_pos, dim=-2)

    def joint_transforms(self, rotations: torch.Tensor, root_translation: torch.Tensor | None = None) -> torch.Tensor:
        """World transforms of every joint by forward kinematics.

        G_j = G_parent(j) · T(o_j) · R_j, with o_j the rest offset from the parent and R_j the local
        rotation; the root is G_0 = T(p_0 + t) · R_0 with p_0 its rest position and t the root
        translation.

        Args:
            rotations: local joint rotations, axis-angle [..., J, 3] (radians) or matrices [..., J, 3, 3].
            root_translation: [..., 3] displacement of the root from its rest position, metres; ``None``
                for zero.

        Returns:
            [..., J, 4, 4] homogeneous world transforms (rotation, joint position in metres).
        """
        rot, pos = self._world_frames(rotations, root_translation)
        out = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
        out[..., :3, :3] = rot
        out[..., :3, 3] = pos
        out[..., 3, 3] = 1.0
        return out

    def joint_positions(self, rotations: torch.Tensor, root_translation: torch.Tensor | None = None) -> torch.Tensor:
        """[..., J, 3] world joint positions, metres (see :meth:`joint_transforms`)."""
        return self._world_frames(rotations, root_translation)[1]

    def skinning_transforms(
        self, rotations: torch.Tensor, root_translation: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Rest-to-posed bone transforms A_j = G_j · G_j(rest)^-1 as [..., J, 3, 4] (rotation | translation).

        The translation is computed as p_j - R_j p_j(rest) from the same forward-kinematics path as the
        rest pose, so the rest pose gives R_j = I and a translation of exactly zero.
        """
        rot, pos = self._world_frames(rotations, root_translation)
        _, rest_pos = self._world_frames(self.rest_rotations(), None)
        trans = pos - (rot @ rest_pos.to(pos).unsqueeze(-1)).squeeze(-1)
        return torch.cat([rot, trans.unsqueeze(-1)], dim=-1)


def linear_blend_skinning(rest_points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning x = Σ_j w_j A_j x̄ (the LBS of PhysAvatar §3.2 "Animation", after SMPL).

    Evaluated as x = x̄ + (Σ_j w_j (R_j - I)) x̄ + Σ_j w_j t_j, which equals the usual form for weights
    that sum to one and returns the rest points bit for bit in the rest pose.

    Args:
        rest_points: [V, 3] rest positions, metres.
        weights: [V, J] skinning weights, non-negative, rows summing to one.
        transforms: [..., J, 3, 4] rest-to-posed bone transforms from :meth:`Skeleton.skinning_transforms`.

    Returns:
        [..., V, 3] posed positions, metres.
    """
    if weights.shape[0] != rest_points.shape[0] or weights.shape[1] != transforms.shape[-3]:
        raise ValueError(
            f"weights must have shape [V={rest_points.shape[0]}, J={transforms.shape[-3]}], got {list(weights.shape)}"
        )
    delta = transforms.clone()
    delta[..., :, :, :3] -= torch.eye(3, dtype=transforms.dtype, device=transforms.device)
    blended = torch.einsum("vj,...jab->...vab", weights.to(transforms), delta)
    x = rest_points.to(transforms)
    return x + (blended[..., :3] @ x.unsqueeze(-1)).squeeze(-1) + blended[..., 3]
