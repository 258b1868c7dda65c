"""The mannequin's skin: a signed distance field around the skeleton, its mesh, and its skinning weights.

The skin is the zero level set of a smooth union of ellipsoids and tapered capsules, one or more
per bone, extracted by marching tetrahedra on a Kuhn (6-tetrahedra-per-cube) grid. The level set of
a piecewise-linear field on a simplicial grid with no zero values is a closed 2-manifold, so the
mesh is watertight by construction; its vertices are then relaxed tangentially and projected back
onto the level set to even out the triangles. Conventions are those of :mod:`physavatar.body.skeleton`.
"""

from dataclasses import dataclass

import numpy as np

from physavatar.body.skeleton import JOINT_NAMES, mannequin_joints

__all__ = [
    "bone_distances",
    "mannequin_mesh",
    "skinning_weights",
]

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
    positions, tails = mannequin_joints()
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


def bone_distances(points: np.ndarray, scale: float) -> np.ndarray:
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


def mannequin_mesh(scale: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
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


def skinning_weights(bone_distance: np.ndarray, falloff: float, influences: int = 4) -> np.ndarray:
    """Softmax weights [N, J] over the ``influences`` nearest bones: w_j ∝ exp(-(d_j - d_min) / falloff)."""
    d = bone_distance - bone_distance.min(axis=1, keepdims=True)
    w = np.exp(-d / falloff)
    cut = np.partition(w, -influences, axis=1)[:, -influences][:, None]
    w[w < cut] = 0.0
    return w / w.sum(axis=1, keepdims=True)
