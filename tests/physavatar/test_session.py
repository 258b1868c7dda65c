"""The interactive garment session behind the viewer's verbs, at small size: drag, pin, pause and scrub, fabric
sliders and presets, the contact counters; a user's capture played in place of the mannequin."""

import math

import pytest
import torch

from physavatar.body import raise_arms, save_bvh
from physavatar.capture import load_capture_folder
from physavatar.session import CAPTURE_MOTION, CONTACT_RGB, FABRIC_PRESETS, AvatarConfig, AvatarSimulation
from tests.physavatar.handmade_capture import FPS, build_handmade_capture

F64 = torch.float64


_SESSIONS: dict[str, AvatarSimulation] = {}


@pytest.fixture
def session(device):
    """One small session a device (the procedural skirt of 96 vertices), built once and reset by each test."""
    if device not in _SESSIONS:
        _SESSIONS[device] = AvatarSimulation(AvatarConfig(garment="procedural", skirt=(6, 16)))
    return _SESSIONS[device]


def _front_hem(sim: AvatarSimulation) -> int:
    x = sim.state.x.cpu()
    front = x[:, 2] > x[:, 2].mean()
    return int(torch.where(front, x[:, 1], torch.full_like(x[:, 1], math.inf)).argmin())


def test_a_dragged_hem_follows_half_the_drag_within_half_a_second_and_stays_out_of_the_body(session):
    sim = session
    sim.reset()
    sim.pause()
    sim.step(2)
    hem = _front_hem(sim)
    sim.grab(hem)
    start = sim.state.x[hem].cpu().clone()
    target = start + torch.tensor([0.15, 0.0, 0.0], dtype=F64)
    sim.drag_to(target=target)
    assert sim.dragging and torch.equal(sim.drag_target, target)
    for _ in range(13):  # 0.52 s
        sim.step()
        assert sim.contact()["inside"] == 0
    assert float(sim.state.x[hem, 0].cpu() - start[0]) >= 0.5 * 0.15
    sim.release()
    assert not sim.dragging and sim.drag_target is None


def test_a_pinned_vertex_stays_where_it_was_pinned(session):
    """The pin's spring is 1000 garment weights per metre: the whole garment hanging on it would move it by 1 mm;
    within 5 mm leaves room for the swing of the step it was pinned in."""
    sim = session
    sim.reset()
    sim.pause()
    hem = _front_hem(sim)
    sim.grab(hem)
    sim.drag_to(target=sim.state.x[hem].cpu() + torch.tensor([0.0, 0.0, 0.08], dtype=F64))
    sim.step(6)
    held = sim.state.x[hem].cpu().clone()
    assert sim.pin_picked() == hem and not sim.dragging
    sim.step(8)
    assert float((sim.state.x[hem].cpu() - held).norm()) < 5e-3
    sim.reset()
    assert not sim.drag.pins


def test_pause_holds_the_pose_scrub_travels_and_speed_scales_the_motion(session):
    sim = session
    sim.reset()
    sim.play()
    sim.step(2)
    assert sim.frame == 2.0
    sim.pause()
    sim.step(2)
    assert sim.frame == 2.0 and not math.isinf(sim.max_speed())  # still: the loop may rest
    sim.scrub(10)
    sim.step(3)  # two frames a step
    assert sim.frame == 8.0
    sim.step(2)
    assert sim.frame == 10.0
    sim.set_speed(2.0)
    sim.play()
    sim.step()
    assert sim.frame == 12.0
    sim.set_speed(1.0)
    with pytest.raises(ValueError, match="frame must be a number in"):
        sim.scrub(sim.frame_count + 5)
    with pytest.raises(ValueError, match="speed must be a number in"):
        sim.set_speed(-1)
    with pytest.raises(ValueError, match="unknown motion"):
        sim.set_motion("dance")


def test_the_walk_loops_onto_its_own_pose_and_plays_on(session):
    sim = session
    sim.set_motion("walk")
    clip = sim.clip
    assert float((clip.body[clip.last] - clip.body[clip.loop_start]).abs().max()) < 1e-9
    assert clip.advance(clip.last - 0.5, 1.0) == clip.loop_start + 0.5
    sim.set_motion("jump")
    assert sim.motion == "jump" and sim.frame == 0.0
    sim.set_motion("walk")


def test_fabric_sliders_and_presets_reach_the_solver_and_keep_the_garment(session):
    sim = session
    sim.reset()
    sim.step(2)
    x = sim.state.x.clone()
    sim.set_fabric(kappa_b=8.0, friction=0.5)
    assert (sim.solver.config.kappa_b, sim.solver.config.friction) == (8.0, 0.5)
    assert sim.fabric_name == "custom" and torch.equal(sim.state.x, x)
    sim.step()
    for name, preset in FABRIC_PRESETS.items():
        sim.apply_preset(name)
        config = sim.solver.config
        assert (config.density, config.kappa_s, config.kappa_b, config.friction, config.thickness) == (
            preset.density,
            preset.kappa_s,
            preset.kappa_b,
            preset.friction,
            preset.thickness,
        )
    with pytest.raises(ValueError, match=r"kappa b must be a number in \[0.1, 8\]"):
        sim.set_fabric(kappa_b=20.0)
    with pytest.raises(ValueError, match="unknown fabric"):
        sim.apply_preset("tweed")
    sim.apply_preset("cotton")


def test_contact_counters_agree_with_the_tint_and_find_nothing_inside_over_a_walk(session):
    sim = session
    sim.reset()
    sim.play()
    for _ in range(15):
        sim.step()
        contact = sim.contact()
        assert contact["inside"] == 0
        assert contact["reach_m"] == sim.solver.config.contact_distance
        tinted = int((sim.vertex_colors() == torch.tensor(CONTACT_RGB)).all(1).sum())
        assert tinted == contact["near"]
        assert contact["min_body_m"] > 0.0
    breakdown = sim.time_breakdown()["seconds_per_step"]
    assert set(breakdown) == {"candidate search", "Newton iterations", "linear solves", "contact view"}
    assert all(value > 0.0 for value in breakdown.values())


def test_a_bvh_file_plays_eased_in_from_rest_and_loops_onto_its_first_pose(session, tmp_path):
    sim = session
    path = tmp_path / "raise.bvh"
    save_bvh(raise_arms(sim.body.skeleton, duration=0.6, fps=30.0), path, sim.body.skeleton)
    sim.set_motion(str(path))
    try:
        clip = sim.clip
        assert str(path) in sim.motions and clip.loop_start == 25
        rest = sim.body.vertices.to(clip.body)
        assert float((clip.body[0] - rest).abs().max()) == 0.0  # the pose the garment was placed in
        assert float((clip.body[clip.last] - clip.body[clip.loop_start]).abs().max()) < 1e-9
        for _ in range(4):
            sim.step()
            assert sim.contact()["inside"] == 0
        with pytest.raises(ValueError, match="or a .bvh file"):
            sim.set_motion(str(tmp_path / "missing.bvh"))
    finally:
        sim.set_motion("walk")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The hand-made user capture (4 frames at 30 fps, z-up, a garment patch pushed into the body)."""
    folder = tmp_path_factory.mktemp("capture")
    build_handmade_capture(folder)
    return folder


def test_a_captures_body_sequence_plays_with_its_garment_resolved_and_loops(device, capture):
    sim = AvatarSimulation(AvatarConfig(capture=str(capture)))
    folder = load_capture_folder(capture, views=False)
    assert folder.film is None and folder.fps == FPS
    assert sim.motions == (CAPTURE_MOTION,) and sim.motion == CAPTURE_MOTION
    assert sim.mesh_faces.shape == folder.garment_faces.shape and "the capture's garment" in sim.notes[0]
    # 4 frames at 30 fps are 0.1 s: at 25 fps frames 0, 1.2, 2.4 and 3 (the last, clamped), then back to 0
    assert sim.frame_count == 7
    body = folder.body_frames.to(sim.clip.body)
    torch.testing.assert_close(sim.clip.body[0], body[0], rtol=0.0, atol=0.0)
    torch.testing.assert_close(sim.clip.body[1], torch.lerp(body[1], body[2], 0.2), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(sim.clip.body[3], body[3], rtol=0.0, atol=0.0)
    torch.testing.assert_close(sim.clip.body[6], body[0], rtol=0.0, atol=0.0)
    # the pushed patch starts outside the body, and nothing goes inside over two loops
    assert sim.contact()["inside"] == 0
    frames = []
    for _ in range(12):
        sim.step()
        frames.append(sim.frame)
        assert sim.contact()["inside"] == 0
    assert frames == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # loops from the last onto 0's pose
    with pytest.raises(ValueError, match="a capture plays its own: capture"):
        sim.set_motion("walk")


def test_a_capture_wears_another_garment_file_with_its_boundary_chosen(device, capture):
    sim = AvatarSimulation(AvatarConfig(capture=str(capture), garment=str(capture / "garment.obj")))
    assert "garment.obj" in sim.notes[0] and "(automatic)" in sim.notes[1]
    assert sim.contact()["inside"] == 0


def test_a_folder_that_is_not_a_capture_is_refused_with_the_fix(tmp_path):
    with pytest.raises(ValueError, match="is not a folder; pass a capture folder"):
        AvatarConfig(capture=str(tmp_path / "missing"))
    with pytest.raises(ValueError, match="must be an OBJ/PLY file"):
        AvatarConfig(capture=str(tmp_path), garment="skirt7271")
    (tmp_path / "body").mkdir()
    with pytest.raises(ValueError, match=r"transforms\.json.*docs/capture\.md.*apps\.avatar check"):
        AvatarSimulation(AvatarConfig(capture=str(tmp_path)))
