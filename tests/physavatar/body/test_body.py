"""The procedural mannequin: closed skin mesh, forward kinematics, LBS weights and skinning, skirt fit."""

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from kernels import backend
from physavatar.body import JOINT_NAMES, Body, Skeleton, axis_angle_to_matrix
from physavatar.body.mannequin import bone_distances

TRUNK = ("pelvis", "spine1", "spine2", "spine3", "neck", "head")


@pytest.fixture(scope="module")
def mannequin() -> Body:
    return Body.mannequin()


@pytest.fixture
def body(mannequin, device) -> Body:
    return mannequin.to(backend.torch_device())


def _segments_cross_triangles(p0, p1, tri) -> np.ndarray:
    """Whether each segment p0→p1 [N, 3] passes through the interior of its triangle tri [N, 3, 3]."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = p1 - p0
    h = np.cross(d, e2)
    det = (e1 * h).sum(1)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - tri[:, 0]
    u = (s * h).sum(1) * inv
    q = np.cross(s, e1)
    v = (d * q).sum(1) * inv
    t = (e2 * q).sum(1) * inv
    return ok & (u > 0) & (v > 0) & (u + v < 1) & (t > 0) & (t < 1)


def test_skin_mesh_is_one_closed_outward_manifold(mannequin):
    mesh = mannequin.trimesh()
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2  # one closed genus-0 surface
    assert len(mesh.split(only_watertight=False)) == 1
    assert 5_000 <= len(mesh.faces) <= 20_000
    assert mesh.volume > 0.03  # positive signed volume: faces wound outward; about a slim adult's volume in m³
    assert mesh.bounds[1, 1] == pytest.approx(1.75, abs=0.005)  # height
    assert abs(mesh.bounds[0, 1]) < 0.003  # soles on y = 0
    assert mesh.bounds[0, 0] == pytest.approx(-mesh.bounds[1, 0], abs=0.005)  # left-right symmetric
    toes = mesh.vertices[mesh.vertices[:, 1] < 0.05]
    assert toes[:, 2].max() > 0.18 > 0.1 > -toes[:, 2].min()  # feet point to +z: the body faces +z
    angles = np.degrees(trimesh.triangles.angles(mesh.triangles))
    assert angles.min() > 5.0  # no slivers


def test_face_normals_point_out_of_the_solid(mannequin):
    rng = np.random.default_rng(0)
    mesh = mannequin.trimesh()
    faces = rng.choice(len(mesh.faces), 200, replace=False)
    centre = torch.as_tensor(mesh.triangles_center[faces])
    normal = torch.as_tensor(mesh.face_normals[faces])
    outside = mannequin.winding_number(centre + 0.002 * normal)
    inside = mannequin.winding_number(centre - 0.002 * normal)
    assert torch.allclose(outside, torch.zeros_like(outside), atol=1e-6)
    assert torch.allclose(inside, torch.ones_like(inside), atol=1e-6)


def test_rest_mesh_has_no_self_intersection(mannequin):
    mesh = mannequin.trimesh()
    tri = mesh.triangles
    centre = tri.mean(1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max()
    pairs = cKDTree(centre).query_pairs(2.0 * reach, output_type="ndarray")  # every pair that could touch
    f = mesh.faces
    shares_vertex = (f[pairs[:, 0], :, None] == f[pairs[:, 1], None, :]).any(axis=(1, 2))
    a, b = pairs[~shares_vertex].T
    assert len(a) > 100_000
    hits = 0
    for first, second in ((a, b), (b, a)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hits += _segments_cross_triangles(tri[first, i], tri[first, j], tri[second]).sum()
    assert hits == 0


def test_forward_kinematics_rest_and_bone_lengths(device):
    skel = Skeleton.mannequin()
    rest = skel.joint_positions(skel.rest_rotations())
    assert torch.allclose(rest, skel.rest_positions, atol=1e-12)
    assert len(skel.names) == 22 and skel.names == JOINT_NAMES
    rng = np.random.default_rng(1)
    aa = torch.as_tensor(rng.normal(scale=0.6, size=(5, 22, 3)))
    shift = torch.as_tensor(rng.normal(size=(5, 3)))
    g = skel.joint_transforms(aa, shift)
    assert torch.allclose(g, skel.joint_transforms(axis_angle_to_matrix(aa), shift))
    rot = g[..., :3, :3]
    assert torch.allclose(rot.transpose(-1, -2) @ rot, torch.eye(3, dtype=rot.dtype).expand_as(rot), atol=1e-12)
    pos = g[..., :3, 3]
    parents = list(skel.parents[1:])
    bone = torch.linalg.vector_norm(pos[:, 1:] - pos[:, parents], dim=-1)
    rest_bone = torch.linalg.vector_norm(skel.rest_offsets[1:], dim=-1)
    assert torch.allclose(bone, rest_bone.expand_as(bone), atol=1e-12)
    assert torch.allclose(pos[:, 0], skel.rest_positions[0] + shift)


def test_left_arm_rises_for_positive_z_rotation():
    skel = Skeleton.mannequin()
    aa = torch.zeros(22, 3, dtype=torch.float64)
    aa[skel.index("left_shoulder"), 2] = math.pi / 4
    pos = skel.joint_positions(aa)
    shoulder, elbow = pos[skel.index("left_shoulder")], pos[skel.index("left_elbow")]
    assert elbow[1] == pytest.approx(shoulder[1].item(), abs=1e-12)  # A-pose arm raised 45° is horizontal
    assert elbow[0] > shoulder[0]


def test_weights_are_a_partition_of_unity_led_by_the_nearest_bone(mannequin):
    w = mannequin.weights
    assert (w >= 0).all()
    assert torch.allclose(w.sum(1), torch.ones(len(w), dtype=w.dtype), atol=1e-12)
    assert ((w > 0).sum(1) <= 4).all()
    nearest = bone_distances(mannequin.vertices.numpy(), 1.0).argmin(1)
    assert np.array_equal(w.argmax(1).numpy(), nearest)
    assert (w.max(1).values >= 0.25).all()
    hand = mannequin.vertices[:, 0] > 0.6
    assert (w[hand].argmax(1) == JOINT_NAMES.index("left_wrist")).all()


def test_rest_pose_skins_to_the_rest_mesh_exactly(body):
    skel = body.skeleton
    assert torch.equal(body.skin(skel.rest_rotations()), body.vertices)
    assert torch.equal(body.skin(torch.zeros(22, 3, dtype=torch.float64, device=body.vertices.device)), body.vertices)


def test_root_transform_moves_the_body_rigidly(body):
    skel = body.skeleton
    dev = body.vertices.device
    rot = skel.rest_rotations()
    r0 = axis_angle_to_matrix(torch.tensor([0.3, -1.1, 0.5], dtype=torch.float64, device=dev))
    rot[0] = r0
    shift = torch.tensor([0.2, -0.1, 0.7], dtype=torch.float64, device=dev)
    posed = body.skin(rot, shift)
    pelvis = skel.rest_positions[0]
    expected = (body.vertices - pelvis) @ r0.T + pelvis + shift
    assert torch.allclose(posed, expected, atol=1e-12)


def test_elbow_moves_forearm_and_hand_but_not_torso(body):
    skel = body.skeleton
    aa = torch.zeros(22, 3, dtype=torch.float64, device=body.vertices.device)
    aa[skel.index("left_elbow")] = torch.tensor([-0.5, -0.5, 0.0]) * math.sqrt(2) * (math.pi / 2)
    moved = torch.linalg.vector_norm(body.skin(aa) - body.vertices, dim=1)
    lead = body.weights.argmax(1).cpu()
    trunk = torch.isin(lead, torch.tensor([JOINT_NAMES.index(n) for n in TRUNK]))
    forearm = torch.isin(lead, torch.tensor([JOINT_NAMES.index(n) for n in ("left_elbow", "left_wrist")]))
    right = body.vertices[:, 0].cpu() < 0
    assert moved[trunk.to(moved.device)].max() == 0.0
    assert moved[right.to(moved.device)].max() == 0.0
    assert moved[forearm.to(moved.device)].min() > 0.005
    hand_tip = body.vertices[:, 0].argmax()
    assert moved[hand_tip] > 0.4  # a 90° bend swings the 0.42 m forearm+hand tip by ≈ 0.42·√2


def test_skin_batches_over_frames(body):
    rng = np.random.default_rng(2)
    aa = torch.as_tensor(rng.normal(scale=0.3, size=(3, 22, 3)), device=body.vertices.device)
    shift = torch.as_tensor(rng.normal(scale=0.1, size=(3, 3)), device=body.vertices.device)
    batched = body.skin(aa, shift)
    assert batched.shape == (3, len(body.vertices), 3)
    for f in range(3):
        assert torch.allclose(batched[f], body.skin(aa[f], shift[f]), atol=1e-12)


def test_bad_input_raises_clear_errors(mannequin):
    with pytest.raises(ValueError, match=r"rotations must be axis-angle \[\.\.\., 22, 3\]"):
        mannequin.skin(torch.zeros(21, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="root_translation must have shape"):
        mannequin.skin(torch.zeros(22, 3, dtype=torch.float64), torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="height must be positive"):
        Body.mannequin(height=-1.0)
    with pytest.raises(ValueError, match="spacing must lie in"):
        Body.mannequin(spacing=0.1)
    with pytest.raises(ValueError, match="parent must come before its child"):
        Skeleton(("a", "b"), (-1, 1), torch.zeros(2, 3), torch.zeros(2, 3))
    with pytest.raises(KeyError, match="no joint 'tail'"):
        mannequin.skeleton.index("tail")


def test_surface_weights_of_body_vertices_are_their_own(mannequin):
    idx = torch.arange(0, len(mannequin.vertices), 97)
    w = mannequin.surface_weights(mannequin.vertices[idx])
    assert torch.allclose(w, mannequin.weights[idx], atol=1e-9)


def test_skirt_starts_outside_the_body_with_its_waist_on_it(mannequin, shared_data):
    skirt = trimesh.load(shared_data / "garments" / "skirt1252.obj", process=False)
    edges, counts = np.unique(skirt.edges_sorted, axis=0, return_counts=True)
    boundary = np.unique(edges[counts == 1])
    waist = boundary[skirt.vertices[boundary, 1] > 0.5 * (skirt.bounds[0, 1] + skirt.bounds[1, 1])]
    assert len(waist) > 10
    distance = mannequin.signed_distance(torch.as_tensor(skirt.vertices))
    assert distance.min() > 0.002  # every vertex outside the body, with a margin
    midpoints = torch.as_tensor(skirt.vertices[skirt.edges_unique].mean(1))
    assert mannequin.closest_points(midpoints)[1].min() > 0.002  # and no edge dips to the skin
    waist_distance = distance[torch.as_tensor(waist)]
    assert waist_distance.max() < 0.03  # the waistband sits on the body
