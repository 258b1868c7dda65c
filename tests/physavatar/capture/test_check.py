"""check_capture finds every problem of a hand-written capture folder, each with its fix; ``apps.avatar check``."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from apps import avatar
from physavatar.capture import CaptureCheck, Problem, check_capture, load_capture_folder
from tests.physavatar.capture.handmade import (
    CAMERAS,
    FRAMES,
    HEIGHT,
    WIDTH,
    body_mesh,
    edit_json,
    frame_of,
    garment_mesh,
    image_name,
    to_z_up,
    write_capture_folder,
    write_obj,
)


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    folder = tmp_path_factory.mktemp("check") / "good"
    write_capture_folder(folder)
    return folder


@pytest.fixture
def capture(good, tmp_path):
    """A fresh copy of the good folder to damage."""
    return shutil.copytree(good, tmp_path / "cap")


def test_a_sound_capture_passes_with_its_summary(good):
    check = check_capture(good)
    assert isinstance(check, CaptureCheck) and check.ok and check.problems == [] and check.warnings == []
    summary = dict(check.summary)
    assert summary["frames"] == f"{FRAMES} time indices" and summary["cameras"] == str(CAMERAS)
    assert summary["image size"] == f"{WIDTH} x {HEIGHT} px" and summary["fps"] == "30" and summary["up"] == "y"
    vertices, faces = body_mesh()
    assert summary["body"] == f"{FRAMES} meshes, {len(vertices)} vertices, {len(faces)} faces"
    assert summary["garment"] == "36 vertices, 48 faces (garment.obj)"
    assert summary["boundary"].startswith("automatic")
    assert (
        summary["inside the body"] == "0 of 36 vertices" and summary["cameras seeing it"] == f"{CAMERAS} of {CAMERAS}"
    )
    gap = float(
        re.fullmatch(
            r"nearest vertex ([\d.]+) mm outside the body surface at time index 0", summary["garment to body"]
        ).group(1)
    )
    assert 45.0 < gap <= 50.0  # 5 cm from the tube to the capsule's vertices, at most that to its facets
    text = check.format()
    assert text.splitlines()[0] == f"capture {good}: ok"
    for name, value in check.summary:
        assert re.search(rf"^  {re.escape(name)} +{re.escape(value)}$", text, re.MULTILINE)


def _turn_away(meta, cameras):
    """Turn cameras half a turn about their own y axis: they look away from the scene."""
    for frame in meta["frames"]:
        if frame["camera"] in cameras:
            matrix = np.array(frame["transform_matrix"])
            matrix[:3, [0, 2]] *= -1.0
            frame["transform_matrix"] = matrix.tolist()


def _move_camera(meta):
    frame_of(meta, 1, 1)["transform_matrix"][0][3] += 0.2


def _drop_view(meta):
    meta["frames"].remove(frame_of(meta, 1, 2))


def _renumber_camera(meta):
    for frame in meta["frames"]:
        if frame["camera"] == 1:
            frame["camera"] = 2


def _garment(folder, vertices=None, faces=None, extra=""):
    v, f = garment_mesh()
    write_obj(folder / "garment.obj", v if vertices is None else vertices, f if faces is None else faces, extra)


def _scale_meshes(folder, factor):
    for t in range(FRAMES):
        vertices, faces = body_mesh(t)
        write_obj(folder / "body" / f"{t:04d}.obj", vertices * factor, faces)
    _garment(folder, garment_mesh()[0] * factor)


def _black_masks(folder, camera):
    for t in range(FRAMES):
        Image.fromarray(np.zeros((HEIGHT, WIDTH), np.uint8)).save(folder / "masks" / image_name(camera, t))


def _non_manifold(folder):
    v, f = garment_mesh()
    a, b = f[0][1], f[0][2]  # a diagonal: two faces use it already
    _garment(folder, np.concatenate([v, [[0.0, 0.5, 0.5]]]), np.concatenate([f, [[a, b, len(v)]]]))


def _other_body(folder):
    vertices, faces = body_mesh(1)
    write_obj(folder / "body" / "0001.obj", vertices[:-1], faces[(faces < len(vertices) - 1).all(1)])


def _reordered_faces(folder):
    vertices, faces = body_mesh(1)
    write_obj(folder / "body" / "0001.obj", vertices, faces[::-1])


DEFECTS = {
    # name: (damage(folder), "problem" or "warning", pattern of str(Problem): where: what; fix)
    "no transforms.json": (
        lambda f: (f / "transforms.json").unlink(),
        "problem",
        r"^transforms\.json: .*does not exist",
    ),
    "malformed json": (
        lambda f: (f / "transforms.json").write_text('{"fps": 30,'),
        "problem",
        r"^transforms\.json: is not valid json .*; fix the syntax",
    ),
    "no frames key": (lambda f: edit_json(f, lambda m: m.pop("frames")), "problem", r"lacks the key 'frames'"),
    "no fps": (lambda f: edit_json(f, lambda m: m.pop("fps")), "problem", r"lacks the key 'fps'; add \"fps\""),
    "zero fps": (lambda f: edit_json(f, lambda m: m.update(fps=0)), "problem", r"fps is 0, not a positive number"),
    "no focal length": (
        lambda f: edit_json(f, lambda m: [m.pop("fl_x"), m.pop("fl_y")]),
        "problem",
        r"gives no focal length; add 'fl_x'",
    ),
    "frame lacks a key": (
        lambda f: edit_json(f, lambda m: m["frames"][1].pop("mask_path")),
        "problem",
        r"^transforms\.json frames\[1\]: lacks mask_path; give every frame",
    ),
    "missing image": (
        lambda f: (f / "images" / image_name(1, 2)).unlink(),
        "problem",
        r"^images/c1_t2\.png: .*does not exist \(file_path of frames\[5\].*\); add the image",
    ),
    "missing mask": (lambda f: (f / "masks" / image_name(0, 1)).unlink(), "problem", r"^masks/c0_t1\.png: .*not exist"),
    "missing body mesh": (
        lambda f: edit_json(f, lambda m: m.update(body=["body/0000.obj", "body/0001.obj", "body/0007.obj"])),
        "problem",
        r"^body/0007\.obj: .*does not exist",
    ),
    "body listed outside the folder": (
        lambda f: edit_json(f, lambda m: m.update(body=[f"/nowhere/{t}.obj" for t in range(FRAMES)])),
        "problem",
        r"^/nowhere/0\.obj: /nowhere/0\.obj does not exist",
    ),
    "no body folder": (lambda f: shutil.rmtree(f / "body"), "problem", r"^body/: .*does not exist"),
    "missing garment": (lambda f: (f / "garment.obj").unlink(), "problem", r"^garment\.obj: .*does not exist"),
    "body meshes not T": (
        lambda f: (f / "body" / "0002.obj").unlink(),
        "problem",
        r"^body/: 2 body meshes for 3 time indices; give exactly one body mesh per time index",
    ),
    "camera lacks a time index": (
        lambda f: edit_json(f, _drop_view),
        "problem",
        r"camera 1 has 2 frames but camera 0 has 3; every camera needs one image per time index",
    ),
    "cameras not 0..C-1": (
        lambda f: edit_json(f, _renumber_camera),
        "problem",
        r"cameras \[1\] are missing: cameras must be numbered 0\.\.C-1",
    ),
    "moving camera": (lambda f: edit_json(f, _move_camera), "problem", r"camera 1 moves between time indices"),
    "image of the wrong size": (
        lambda f: Image.new("RGB", (16, 12)).save(f / "images" / image_name(0, 2)),
        "problem",
        r"^images/c0_t2\.png: is 16x12 pixels but transforms\.json says 32x24",
    ),
    "unreadable mask": (
        lambda f: (f / "masks" / image_name(1, 0)).write_bytes(b"not a png"),
        "problem",
        r"^masks/c1_t0\.png: is not a readable image",
    ),
    "zero-area garment triangle": (
        lambda f: _garment(f, extra="f 1 2 1\n"),
        "problem",
        r"^garment\.obj: 1 zero-area faces",
    ),
    "non-manifold garment": (_non_manifold, "problem", r"^garment\.obj: 1 non-manifold edges"),
    "body vertex count changes": (
        _other_body,
        "problem",
        r"^body/0001\.obj: has \d+ vertices but body/0000\.obj has \d+: the body's topology changes",
    ),
    "body faces change": (_reordered_faces, "problem", r"^body/0001\.obj: its faces differ from those of body/0000"),
    "a camera misses the garment": (
        lambda f: edit_json(f, lambda m: _turn_away(m, {1})),
        "warning",
        r"^camera 1: does not see the garment at time index 0",
    ),
    "no camera sees the garment": (
        lambda f: edit_json(f, lambda m: _turn_away(m, {0, 1})),
        "problem",
        r"no camera sees the garment at time index 0",
    ),
    "empty masks of a camera": (
        lambda f: _black_masks(f, 0),
        "warning",
        r"^camera 0: its garment masks are empty in every view",
    ),
    "garment far from the body": (
        lambda f: _garment(f, garment_mesh()[0] + [1.0, 0.0, 0.0]),
        "problem",
        r"^garment\.obj: the garment is not on the body: its nearest vertex is \d+ mm from the body",
    ),
    "millimetres": (lambda f: _scale_meshes(f, 1000.0), "problem", r"^body/0000\.obj: .*millimetres; scale by 0\.001"),
    "invalid up": (lambda f: edit_json(f, lambda m: m.update(up="x")), "problem", r"up is 'x', not one of 'y', 'z'"),
    "units not metres": (lambda f: edit_json(f, lambda m: m.update(units="mm")), "problem", r"units is 'mm'"),
    "boundary out of range": (
        lambda f: (f / "boundary.txt").write_text("0 1\n36 -2 # past the end\n"),
        "problem",
        r"^boundary\.txt: 2 indices are outside 0\.\.35 \(e\.g\. 36, -2\)",
    ),
    "boundary not integers": (
        lambda f: (f / "boundary.txt").write_text("0 1.5\n"),
        "problem",
        r"^boundary\.txt: line 1: '1\.5' is not a vertex index",
    ),
}


@pytest.mark.parametrize("name", DEFECTS)
def test_each_defect_is_named_with_its_fix(capture, name):
    damage, kind, pattern = DEFECTS[name]
    damage(capture)
    check = check_capture(capture)
    found = check.problems if kind == "problem" else check.warnings
    assert any(re.search(pattern, str(problem)) for problem in found), (name, [str(p) for p in found])
    assert check.ok == (kind == "warning")
    assert all(isinstance(p, Problem) and p.where and p.what and p.fix for p in check.problems + check.warnings)
    text = check.format()
    first = found[0]
    assert f"{first.where}: {first.what}" in text and f"fix: {first.fix}" in text


def test_every_problem_is_collected_not_just_the_first(capture):
    (capture / "images" / image_name(0, 0)).unlink()
    (capture / "masks" / image_name(1, 2)).write_bytes(b"")
    edit_json(capture, lambda m: m.update(fps=-1, up="down"))
    (capture / "body" / "0001.obj").unlink()
    _garment(capture, extra="f 1 2 1\n")
    check = check_capture(capture)
    wheres = [p.where for p in check.problems]
    assert wheres.count("transforms.json") == 2  # fps and up
    assert {"images/c0_t0.png", "masks/c1_t2.png", "body/", "garment.obj"} <= set(wheres)
    assert check.format().startswith(f"capture {capture}: {len(check.problems)} problems\n")


def test_a_garment_starting_inside_the_body_is_reported_not_refused(capture):
    _garment(capture, garment_mesh()[0] + [0.1, 0.0, 0.0])  # its -x side is 5 cm inside the 15 cm capsule
    check = check_capture(capture)
    assert check.ok
    inside = dict(check.summary)["inside the body"]
    count, depth = re.fullmatch(r"(\d+) of 36 vertices, up to ([\d.]+) mm deep", inside).groups()
    rings_inside = 3 * 3  # per ring, the 3 vertices within 60° of -x lie inside (x = 0.1 + 0.2 cos θ, r < 0.15)
    # the deepest, 10 cm from the axis, is 15 cm · cos 15° − 10 cm to 15 cm − 10 cm deep (the 12-gon's in- and
    # circumradius)
    assert int(count) == rings_inside and 44.9 < float(depth) <= 50.0
    assert any("start inside the body" in w.what for w in check.warnings)


def test_z_up_captures_are_checked_in_their_own_axes(tmp_path):
    write_capture_folder(tmp_path / "cap", up="z")
    check = check_capture(tmp_path / "cap")
    assert check.ok and not check.warnings, check.format()
    assert dict(check.summary)["up"] == "z (turned to y-up on load)"
    edit_json(tmp_path / "cap", lambda m: m.update(up="y"))  # declared wrong: the body lies along y's normal
    warnings = check_capture(tmp_path / "cap").warnings
    assert any(re.search(r'along the declared up axis y .*set "up": "z"', str(w)) for w in warnings)


def test_the_check_command_prints_the_report_and_exits_0_or_2(good, capture, capsys):
    assert avatar.main(["check", str(good)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"capture {good}: ok\n") and "cameras seeing it" in out
    edit_json(capture, lambda m: m.update(fps=0))
    (capture / "garment.obj").unlink()
    assert avatar.main(["check", str(capture)]) == 2
    out = capsys.readouterr().out
    assert out.startswith(f"capture {capture}: 2 problems\n")
    assert "problem 1: transforms.json: fps is 0" in out and "problem 2: garment.obj:" in out and "  fix: " in out
    assert avatar.main(["check", str(capture / "nowhere")]) == 2
    assert "does not exist" in capsys.readouterr().out


def test_the_documented_example_is_a_capture_that_passes(tmp_path):
    """docs/capture.md's transforms.json, with the hand-made scene standing on its floor (z up) and images of its
    size: the check passes and the loader reads what the page says."""
    text = (Path(__file__).parents[3] / "docs" / "capture.md").read_text()
    meta = json.loads(re.search(r"```json\n(.*?)```", text, re.DOTALL).group(1))
    folder = tmp_path / "cap"
    folder.mkdir()
    (folder / "transforms.json").write_text(json.dumps(meta))
    lift = np.array([0.0, 0.0, 0.9])  # m: the capsule's foot on the floor
    for t in range(2):
        vertices, faces = body_mesh(t)
        write_obj(folder / "body" / f"{t:04d}.obj", to_z_up(vertices) + lift, faces)
    vertices, faces = garment_mesh()
    write_obj(folder / "garment.obj", to_z_up(vertices) + lift, faces)
    for frame in meta["frames"]:
        for key in ("file_path", "mask_path"):
            (folder / frame[key]).parent.mkdir(exist_ok=True)
            Image.new("L" if key == "mask_path" else "RGB", (meta["w"], meta["h"]), 255).save(folder / frame[key])
    check = check_capture(folder)
    assert check.ok and not check.warnings, check.format()
    assert dict(check.summary)["cameras seeing it"] == "2 of 2"
    loaded = load_capture_folder(folder)
    assert loaded.film.images.shape == (2, 2, 480, 640, 3) and loaded.boundary is None and loaded.up == "z"
    assert loaded.film.rig.intrinsics[1].tolist() == [612.5, 611.8, 318.2, 243.1]


def test_a_capture_built_elsewhere_passes_with_its_pushed_patch_reported(handmade):
    """The hand-made capture (another builder of the same format): z-up, scattered cameras, one calibrated apart,
    its body's arm in its chest, a garment patch 3-5 mm inside the body. Only the patch is worth a warning."""
    folder, built = handmade
    check = check_capture(folder)
    assert check.ok, check.format()
    summary = dict(check.summary)
    frames, faces = built["body_frames"].shape[:2], len(built["body_faces"])
    assert summary["body"] == f"{frames[0]} meshes, {frames[1]} vertices, {faces} faces"
    assert summary["boundary"] == f"given: {len(np.unique(built['boundary']))} vertices (boundary.txt)"
    assert summary["cameras seeing it"] == f"{built['cameras']} of {built['cameras']}"
    count, depth = re.fullmatch(r"(\d+) of \d+ vertices, up to ([\d.]+) mm deep", summary["inside the body"]).groups()
    assert int(count) == len(built["pushed"])
    # the files hold 6 decimals (±0.5 µm) and the row one decimal of a millimetre (±0.05 mm)
    assert abs(float(depth) - 1e3 * built["push_depth"].max()) <= 0.05 + 1e-3
    assert [w.where for w in check.warnings] == ["garment.obj"] and "start inside the body" in check.warnings[0].what
