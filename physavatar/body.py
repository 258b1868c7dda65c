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

__all__ = [
    "JOINT_NAMES",
    "JOINT_PARENTS",
    "Body",
    "Skeleton",
    "axis_angle_to_matrix",
    "linear_blend_skinning",
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

_REFERENCE_HEIGHT = 1.75  # m, the height the mannequin's proportions below are written for
_ARM_DIRECTION = (math.sqrt(0.5), -math.sqrt(0.5), 0.0)  # left arm at rest, 45° below horizontal


def _mannequin_joints() -> tuple[np.ndarray, np.ndarray]:
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
    def mannequin(cls, height: float = _REFERENCE_HEIGHT, dtype: torch.dtype = torch.float64) -> "Skeleton":
        """The SMPL-named 22-joint skeleton of the procedural mannequin, scaled to ``height`` metres."""
        if not height > 0:
            raise ValueError(f"height must be positive (metres), got {height}")
        positions, tails = _mannequin_joints()
        scale = height / _REFERENCE_HEIGHT
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


# --- the mannequin's shape: a smooth union of per-bone primitives -------------------------------------


@dataclass(frozen=True)
class _Primitive:
    """One solid attached to a joint: a tapered capsule (a→b, radii ra→rb) or an ellipsoid (centre a, radii r)."""

    joint: str
    kind: str
    a: tuple[float, float, float]
    b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radii: tuple[float, ...] = ()


def _mannequin_primitives() -> list[list[_Primitive]]:
    """Groups of primitives for the 1.75 m mannequin, metres; each group is one smooth-union blend."""
    positions, tails = _mannequin_joints()
    at = {name: tuple(positions[j]) for j, name in enumerate(JOINT_NAMES)}
    tail = {name: tuple(tails[j]) for j, name in enumerate(JOINT_NAMES)}
    trunk = [
        _Primitive("pelvis", "ellipsoid", (0.0, 0.955, 0.015), radii=(0.150, 0.100, 0.100)),
        _Primitive("spine1", "ellipsoid", (0.0, 1.060, 0.025), radii=(0.118, 0.080, 0.082)),
        _Primitive("spine2", "ellipsoid", (0.0, 1.170, 0.030), radii=(0.092, 0.100, 0.068)),
        _Primitive("spine3", "ellipsoid", (0.0, 1.320, 0.020), radii=(0.140, 0.140, 0.100)),
        _Primitive("neck", "capsule", (0.0, 1.430, -0.005), (0.0, 1.570, 0.005), (0.052, 0.048)),
        _Primitive("head", "ellipsoid", (0.0, 1.655, 0.020), radii=(0.075, 0.095, 0.090)),
    ]
    groups = [trunk]
    for side in ("left", "right"):
        s = 1.0 if side == "left" else -1.0
        arm = [
            _Primitive(f"{side}_collar", "capsule", at[f"{side}_collar"], at[f"{side}_shoulder"], (0.050, 0.050)),
            _Primitive(f"{side}_shoulder", "capsule", at[f"{side}_shoulder"], at[f"{side}_elbow"], (0.048, 0.038)),
            _Primitive(f"{side}_elbow", "capsule", at[f"{side}_elbow"], at[f"{side}_wrist"], (0.037, 0.028)),
            _Primitive(f"{side}_wrist", "capsule", at[f"{side}_wrist"], tail[f"{side}_wrist"], (0.030, 0.025)),
        ]
        leg = [
            _Primitive(f"{side}_hip", "capsule", at[f"{side}_hip"], at[f"{side}_knee"], (0.072, 0.050)),
            _Primitive(f"{side}_knee", "capsule", at[f"{side}_knee"], at[f"{side}_ankle"], (0.048, 0.034)),
            _Primitive(
                f"{side}_ankle", "capsule", (0.100 * s, 0.043, -0.050), (0.105 * s, 0.041, 0.100), (0.036, 0.034)
            ),
            _Primitive(f"{side}_foot", "capsule", at[f"{side}_foot"], tail[f"{side}_foot"], (0.030, 0.025)),
        ]
        groups += [arm, leg]
    return groups


_BLEND_RADIUS = {"trunk": 0.05, "limb": 0.02, "attach": 0.035}  # m, smooth-union widths


def _primitive_distance(p: _Primitive, points: np.ndarray, scale: float) -> np.ndarray:
    """Approximate signed distance [N] from ``points`` [N, 3] to one primitive scaled by ``scale``, metres."""
    a = np.array(p.a) * scale
    if p.kind == "ellipsoid":
        r = np.array(p.radii) * scale
        q = points - a
        k0 = np.linalg.norm(q / r, axis=1)
        k1 = np.linalg.norm(q / (r * r), axis=1)
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)
    b = np.array(p.b) * scale
    ra, rb = (r * scale for r in p.radii)
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1) - (ra + t * (rb - ra))


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two distances with blend width ``k`` metres (C1, equals min beyond k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _mannequin_distance(points: np.ndarray, scale: float) -> np.ndarray:
    """Signed distance [N] of the mannequin's smooth-union solid at ``points`` [N, 3], negative inside."""
    groups = _mannequin_primitives()
    total = None
    for g, group in enumerate(groups):
        k = (_BLEND_RADIUS["trunk"] if g == 0 else _BLEND_RADIUS["limb"]) * scale
        d = _primitive_distance(group[0], points, scale)
        for prim in group[1:]:
            d = _smooth_min(d, _primitive_distance(prim, points, scale), k)
        total = d if total is None else _smooth_min(total, d, _BLEND_RADIUS["attach"] * scale)
    return total


def _bone_distances(points: np.ndarray, scale: float) -> np.ndarray:
    """[N, J] distance from each point to each bone's flesh (its primitives' surfaces), metres."""
    out = np.full((points.shape[0], len(JOINT_NAMES)), np.inf)
    for group in _mannequin_primitives():
        for prim in group:
            j = JOINT_NAMES.index(prim.joint)
            out[:, j] = np.minimum(out[:, j], _primitive_distance(prim, points, scale))
    return out


# --- iso-surface extraction ---------------------------------------------------------------------------

# The six tetrahedra of the Kuhn triangulation of a cube (corner index = dx + 2 dy + 4 dz): each walks
# from corner 0 to corner 7 along one permutation of the axes, so neighbouring cubes split their
# shared face along the same diagonal.
_KUHN_TETS = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def _marching_tetrahedra(values: np.ndarray, origin: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate the zero level set of grid samples ``values`` [nx, ny, nz] (negative inside).

    Returns vertices [V, 3] (metres) and faces [F, 3] wound counter-clockwise seen from outside. No
    sample may be exactly zero (the caller nudges them), which makes the surface a closed 2-manifold.
    """
    nx, ny, nz = values.shape
    flat = values.ravel()
    ii, jj, kk = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    base = (ii * ny + jj) * nz + kk
    corner_step = np.array([dx * ny * nz + dy * nz + dz for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])
    corners = base.reshape(-1, 1) + corner_step  # [C, 8]
    inside = flat[corners] < 0
    crossing = inside.any(axis=1) & ~inside.all(axis=1)
    tets = corners[crossing][:, _KUHN_TETS].reshape(-1, 4)
    tet_inside = flat[tets] < 0
    n_in = tet_inside.sum(axis=1)
    keep = (n_in > 0) & (n_in < 4)
    tets, tet_inside, n_in = tets[keep], tet_inside[keep], n_in[keep]
    order = np.argsort(~tet_inside, axis=1, kind="stable")  # inside corners first
    tets = np.take_along_axis(tets, order, axis=1)

    edges, outward = [], []
    for count in (1, 2, 3):
        t = tets[n_in == count]
        if count == 1:
            polys = [[(0, 1), (0, 2), (0, 3)]]
        elif count == 3:
            polys = [[(0, 3), (1, 3), (2, 3)]]
        else:
            polys = [[(0, 2), (0, 3), (1, 3)], [(0, 2), (1, 3), (1, 2)]]
        for poly in polys:
            edges.append(np.stack([np.stack([t[:, a], t[:, b]], axis=1) for a, b in poly], axis=1))  # [M, 3, 2]
            outward.append(t)
    edges = np.concatenate(edges)
    tet_of_face = np.concatenate(outward)

    lo, hi = np.minimum(edges[..., 0], edges[..., 1]), np.maximum(edges[..., 0], edges[..., 1])
    keys, faces = np.unique((lo * flat.size + hi).ravel(), return_inverse=True)
    faces = faces.reshape(-1, 3)
    a, b = keys // flat.size, keys % flat.size
    fa, fb = flat[a], flat[b]

    def position(index):
        i, rem = np.divmod(index, ny * nz)
        j, k = np.divmod(rem, nz)
        return origin + spacing * np.stack([i, j, k], axis=1)

    t = (fa / (fa - fb))[:, None]
    vertices = position(a) + t * (position(b) - position(a))

    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tet_pos = position(tet_of_face.ravel()).reshape(-1, 4, 3)
    tet_out = flat[tet_of_face] > 0
    out_centre = (tet_pos * tet_out[..., None]).sum(1) / tet_out.sum(1, keepdims=True)
    in_centre = (tet_pos * ~tet_out[..., None]).sum(1) / (~tet_out).sum(1, keepdims=True)
    flip = np.einsum("ij,ij->i", normal, out_centre - in_centre) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return vertices, faces


def _relax_onto_level_set(
    vertices: np.ndarray, faces: np.ndarray, distance, spacing: float, iterations: int = 8
) -> np.ndarray:
    """Even out triangles: tangential umbrella smoothing alternating with Newton projection onto f = 0."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    valence = np.bincount(edges[:, 0], minlength=len(vertices))[:, None]
    eps = 1e-4 * spacing

    def gradient(x):
        g = np.stack(
            [distance(x + eps * e) - distance(x - eps * e) for e in np.eye(3)],
            axis=1,
        )
        return g / (2 * eps)

    def project(x):
        for _ in range(3):
            g = gradient(x)
            x = x - (distance(x) / np.maximum((g * g).sum(1), 1e-12))[:, None] * g
        return x

    x = project(vertices)
    for _ in range(iterations):
        mean = np.zeros_like(x)
        np.add.at(mean, edges[:, 0], x[edges[:, 1]])
        step = mean / valence - x
        n = gradient(x)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        step -= (step * n).sum(1, keepdims=True) * n
        x = project(x + 0.5 * step)
    return x


def _mannequin_mesh(scale: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Watertight skin mesh of the mannequin scaled by ``scale``, from a grid of ``spacing`` metres."""
    lo = np.array([-0.80, -0.02, -0.15]) * scale
    hi = np.array([0.80, 1.77, 0.25]) * scale
    counts = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[i] + spacing * np.arange(counts[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = _mannequin_distance(grid, scale)
    values[values == 0.0] = 1e-12  # no sample on the surface itself: keeps the level set a manifold
    vertices, faces = _marching_tetrahedra(values.reshape(*counts), lo, spacing)
    vertices = _relax_onto_level_set(vertices, faces, lambda x: _mannequin_distance(x, scale), spacing)
    return vertices, faces


def _skinning_weights(bone_distance: np.ndarray, falloff: float, influences: int = 4) -> np.ndarray:
    """Softmax weights [N, J] over the ``influences`` nearest bones: w_j ∝ exp(-(d_j - d_min) / falloff)."""
    d = bone_distance - bone_distance.min(axis=1, keepdims=True)
    w = np.exp(-d / falloff)
    cut = np.partition(w, -influences, axis=1)[:, -influences][:, None]
    w[w < cut] = 0.0
    return w / w.sum(axis=1, keepdims=True)


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
    def mannequin(cls, height: float = _REFERENCE_HEIGHT, spacing: float = 0.028, falloff: float = 0.012) -> "Body":
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
        scale = height / _REFERENCE_HEIGHT
        vertices, faces = _mannequin_mesh(scale, spacing * scale)
        weights = _skinning_weights(_bone_distances(vertices, scale), falloff * scale)
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
        """Closest points on the body surface.

        Args:
            points: [P, 3] query points, metres.
            vertices: [V, 3] posed vertices to query instead of the rest mesh.

        Returns:
            ``(closest [P, 3], distance [P], face [P], barycentric [P, 3])``, metres for lengths.
        """
        v = (self.vertices if vertices is None else vertices).detach().cpu().numpy()
        f = self.faces.cpu().numpy()
        q = points.detach().cpu().numpy().astype(np.float64)
        tri = v[f]
        centroid = tri.mean(axis=1)
        reach = np.linalg.norm(tri - centroid[:, None], axis=2).max()
        upper, _ = cKDTree(v).query(q)
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
