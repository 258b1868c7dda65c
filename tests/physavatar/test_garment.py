"""Garment loading, validation, placement and boundary vertices (PhysAvatar §3.2, Appendix A.3.2)."""

import numpy as np
import pytest
import torch
import trimesh

from physavatar import garment as garment_module
from physavatar.body import Body
from physavatar.garment import boundary_targets, load_garment, place_on_body, procedural_skirt, select_boundary

pytestmark = pytest.mark.data  # the default garment comes from the shared folder when present


@pytest.fixture(scope="module")
def body() -> Body:
    return Body.mannequin(spacing=0.03)


@pytest.fixture
def garments(shared_data):
    return shared_data / "garments"


def _write(path, vertices, faces):
    trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces), process=False).export(path)
    return path


def test_unwelded_tshirt_is_welded_into_a_manifold_mesh(garments):
    raw = trimesh.load(garments / "tshirt1900.obj", process=False, force="mesh")
    garment = load_garment(garments / "tshirt1900.obj")
    assert garment.vertices.shape[0] < len(raw.vertices)
    assert any("welded" in note for note in garment.notes)
    edges = np.sort(garment.faces.numpy()[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 2 and (counts == 2).sum() > 0.9 * counts.size  # a sheet with a boundary
    # the weld keeps the surface: every original corner lies on a welded vertex
    distance, _ = trimesh.proximity.ProximityQuery(
        trimesh.Trimesh(garment.vertices.numpy(), garment.faces.numpy(), process=False)
    ).vertex(np.asarray(raw.vertices) * 0.1)
    assert distance.max() < 1e-5


def test_unwelded_soup_without_weld_is_rejected(garments):
    with pytest.raises(ValueError, match=r"share no edge .*unwelded triangle soup; raise weld_tolerance"):
        load_garment(garments / "tshirt1900.obj", weld_tolerance=0.0)


def test_non_manifold_edge_is_named(tmp_path):
    vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    faces = [[0, 1, 2], [1, 0, 3], [0, 1, 4]]  # three triangles on edge (0, 1)
    with pytest.raises(ValueError, match=r"non-manifold edges .*\(0, 1\)"):
        load_garment(_write(tmp_path / "fan.obj", vertices, faces), scale=None)


def test_zero_area_face_is_named(tmp_path):
    vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]]
    faces = [[0, 1, 2], [1, 3, 2], [2, 3, 4]]  # face 2 is collinear: (0, 1), (1, 1), (2, 1)
    with pytest.raises(ValueError, match=r"1 zero-area faces \(e\.g\. faces 2\)"):
        load_garment(_write(tmp_path / "flat.ply", vertices, faces), scale=None)


def test_centimetre_mesh_is_rescaled_to_metres(garments, tmp_path):
    skirt = load_garment(garments / "skirt1252.obj")
    path = _write(tmp_path / "skirt_cm.obj", skirt.vertices.numpy() * 100.0, skirt.faces.numpy())
    garment = load_garment(path)
    assert any("centimetres" in note for note in garment.notes)
    torch.testing.assert_close(garment.vertices, skirt.vertices, atol=1e-6, rtol=0)
    assert load_garment(path, scale=None).vertices.max() > 100.0


def test_skirt_waist_ring_is_the_boundary(garments, body):
    skirt = place_on_body(load_garment(garments / "skirt1252.obj"), body)
    index = select_boundary(skirt, body, mode="auto")
    y = skirt.vertices[index, 1]
    assert index.numel() >= 10
    assert float(y.min()) > 1.13 and float(y.max()) == pytest.approx(1.16, abs=2e-3)
    assert int(torch.argmax(skirt.vertices[:, 1])) in index.tolist()
    # the ring goes around the body: vertices on both sides of it in x and z
    xz = skirt.vertices[index][:, [0, 2]]
    assert bool((xz.min(0).values < -0.03).all()) and bool((xz.max(0).values > 0.03).all())
    torch.testing.assert_close(select_boundary(skirt, body, mode="waist"), index)


def test_boundary_override_and_bad_modes(garments, body):
    skirt = load_garment(garments / "skirt1252.obj")
    assert select_boundary(skirt, body, override=[5, 3, 5]).tolist() == [3, 5]
    with pytest.raises(ValueError, match="boundary override is empty"):
        select_boundary(skirt, body, override=[])
    with pytest.raises(ValueError, match=r"indices in 0\.\.680"):
        select_boundary(skirt, body, override=[681])
    with pytest.raises(ValueError, match="unknown boundary mode 'hips'"):
        select_boundary(skirt, body, mode="hips")


def test_garment_inside_the_body_is_refused_with_its_depth(garments, body):
    skirt = load_garment(garments / "skirt1252.obj")
    assert place_on_body(skirt, body) is skirt  # already outside: untouched
    axis = torch.tensor([0.0, 0.0])
    tight = skirt.vertices.clone()
    tight[:, [0, 2]] = axis + 0.4 * (tight[:, [0, 2]] - axis)
    with pytest.raises(ValueError, match=r"cannot place the garment outside the body.* mm inside the body"):
        place_on_body(skirt.replace(tight, "shrunk"), body)


def test_off_centre_garment_is_moved_onto_the_body(garments, body):
    skirt = load_garment(garments / "skirt1252.obj")
    shifted = skirt.replace(skirt.vertices + torch.tensor([0.15, 0.0, 0.0], dtype=torch.float64), "shifted")
    placed = place_on_body(shifted, body)
    assert "moved by" in placed.notes[-1]
    assert float(body.signed_distance(placed.vertices).min()) > 1e-3


def test_boundary_targets_follow_the_skinning(garments, body):
    skirt = load_garment(garments / "skirt1252.obj")
    index = select_boundary(skirt, body, mode="waist")
    rest = skirt.vertices[index]
    skeleton = body.skeleton
    rotations = skeleton.rest_rotations(2)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.02, 0.3]], dtype=torch.float64)
    targets = boundary_targets(body, rest, rotations, shift)
    assert targets.shape == (2, index.numel(), 3)
    torch.testing.assert_close(targets[0], rest, atol=1e-12, rtol=0)
    torch.testing.assert_close(targets[1], rest + shift[1], atol=1e-12, rtol=0)
    # a pelvis turn about y turns the waist ring with it (the waist's weights sit on pelvis and spine)
    turn = torch.zeros(skeleton.num_joints, 3, dtype=torch.float64)
    turn[0, 1] = 0.3
    turned = boundary_targets(body, rest, turn)
    assert float((turned - rest).norm(dim=1).max()) > 0.02
    with pytest.raises(ValueError, match=r"non-empty \[D, 3\]"):
        boundary_targets(body, rest[:0], rotations)


def test_procedural_skirt_is_a_manifold_tube_clear_of_the_body(body):
    skirt = procedural_skirt(body, rings=6, segments=16, clearance=0.01)
    mesh = trimesh.Trimesh(skirt.vertices.numpy(), skirt.faces.numpy(), process=False)
    assert skirt.vertices.shape == (96, 3) and skirt.faces.shape == (2 * 5 * 16, 3)
    assert mesh.is_winding_consistent
    # Outward orientation: face normals point away from the skirt's axis.
    axis = skirt.vertices[:, [0, 2]].mean(0)
    radial = torch.as_tensor(mesh.triangles_center[:, [0, 2]]) - axis
    assert bool(((radial * torch.as_tensor(mesh.face_normals[:, [0, 2]])).sum(1) > 0).all())
    assert float(body.signed_distance(skirt.vertices.to(body.vertices)).min()) >= 0.01 - 1e-9
    # Waist and hem are its only boundary loops; the waist is the Dirichlet ring.
    assert place_on_body(skirt, body) is skirt
    ring = select_boundary(skirt, body, mode="auto")
    assert torch.equal(ring, torch.arange(16))
    with pytest.raises(ValueError, match="rings >= 2"):
        procedural_skirt(body, rings=1)


def test_default_garment_is_the_procedural_skirt_without_the_shared_data(body, tmp_path, monkeypatch):
    """A fresh clone has no shared data folder: the default garment is then the embedded skirt, and says so."""
    monkeypatch.setattr(garment_module, "DEFAULT_GARMENT", tmp_path / "absent" / "skirt1252.obj")
    garment = garment_module.default_garment(body)
    skirt = procedural_skirt(body)
    assert garment.name == "skirt" and torch.equal(garment.faces, skirt.faces)
    assert "procedural skirt" in garment.notes[0] and "is absent" in garment.notes[0]
    assert float(body.signed_distance(garment.vertices).min()) > 0.0  # placed outside the body
