"""The dressed avatar behind the viewers, with no browser: page messages become the garment session's verbs."""

from __future__ import annotations

import numpy as np
import pytest

from kernels import backend
from physavatar.session import AvatarConfig, AvatarSimulation
from pienerf.viewer import build_app

CLIENT = 1


def _avatar(progress):
    return AvatarSimulation(AvatarConfig(garment="procedural", skirt=(6, 16)), progress)


@pytest.fixture(scope="module")
def app(request):
    backend.init(request.config.getoption("--device") or backend.default_device())
    app = build_app("avatar", "meshcat", "127.0.0.1", 0, smoke=True, simulation=_avatar)
    yield app
    app.viewer.close()


def _send(app, **message):
    app.viewer.on_message(CLIENT, message)
    app.run_commands()


def _hem_ray(sim):
    """A ray from in front of the skirt onto its lowest front vertex."""
    x = sim.state.x.cpu().numpy()
    front = x[:, 2] > x[:, 2].mean()
    hem = x[np.where(front, x[:, 1], np.inf).argmin()]
    return (hem + np.array([0.0, 0.0, 1.0])).tolist(), [0.0, 0.0, -1.0]


def test_press_on_the_skirt_drags_its_vertex_and_release_lets_go(app):
    sim = app.simulation
    origin, direction = _hem_ray(sim)
    _send(app, type="pick", origin=origin, direction=direction)
    assert sim.dragging, f"errors {app.errors}"
    _send(app, type="drag", origin=[origin[0] + 0.1, origin[1], origin[2]], direction=direction)
    assert float(sim.drag_target[0]) == pytest.approx(origin[0] + 0.1, abs=1e-6)
    app.tick()
    assert "garment vertex" in app.viewer.message
    _send(app, type="release")
    assert not sim.dragging and app.errors == []


def test_panel_messages_reach_the_fabric_playback_and_motion(app):
    sim = app.simulation
    _send(app, type="set", name="kappa_b", value=4.0)
    _send(app, type="set", name="fabric_density", value=300.0)
    assert (sim.solver.config.kappa_b, sim.solver.config.density) == (4.0, 300.0)
    _send(app, type="set", name="preset", value="denim")
    assert sim.fabric_name == "denim" and sim.solver.config.kappa_s == 4.0
    _send(app, type="pause")
    assert not sim.playing and "paused" in app.viewer.message
    frame = sim.frame
    app.tick()
    assert sim.frame == frame
    _send(app, type="set", name="frame", value=6)
    app.tick()
    assert sim.frame == frame + max(-2.0, min(2.0, 6.0 - frame))  # on its way, two frames a step
    _send(app, type="set", name="speed", value=2.0)
    _send(app, type="play")
    assert sim.playing and sim.speed == 2.0
    _send(app, type="set", name="motion", value="turn")
    assert sim.motion == "turn" and sim.frame == 0.0
    _send(app, type="reset")
    assert app.errors == []
    _send(app, type="set", name="motion", value="walk")


@pytest.mark.parametrize(
    ("message", "why"),
    [
        ({"type": "push"}, "a garment has no push"),
        ({"type": "cut"}, "a garment has no cut"),
        ({"type": "resample", "kernel_count": 8}, "a garment has no resample"),
        ({"type": "set", "name": "kappa_b", "value": 80.0}, r"kappa b must be a number in \[0.1, 8\]"),
        ({"type": "set", "name": "preset", "value": "tweed"}, "unknown fabric"),
        ({"type": "set", "name": "motion", "value": "dance"}, "unknown motion"),
        ({"type": "set", "name": "young_modulus", "value": 1e5}, "unknown garment control"),
        ({"type": "set", "name": "render_mode", "value": "nerf"}, "mesh only"),
    ],
)
def test_what_a_garment_has_not_is_refused_naming_what_it_has(app, message, why):
    with pytest.raises(ValueError, match=why):
        app.viewer.on_message(CLIENT, message)
    assert app.commands.empty()


def test_the_status_shows_the_contact_and_the_breakdown_and_the_controls_the_garment(app, monkeypatch):
    sent = []
    monkeypatch.setattr(app.viewer.server, "send_json", lambda message, **_: sent.append(message))
    app.tick()
    app.viewer._send_controls()
    status = next(m for m in sent if m["type"] == "status")
    assert "0 vertices inside the body" in status["contact"] and "min distance to body" in status["contact"]
    for phase in ("candidate search", "Newton iterations", "linear solves"):
        assert f"{phase} " in status["breakdown"]
    controls = next(m for m in sent if m["type"] == "controls")
    assert controls["kind"] == "garment" and controls["presets"] == ["silk", "cotton", "denim", "leather"]
    assert controls["motions"] == ["walk", "turn", "raise", "jump"] and controls["render_modes"] == ["mesh"]


def test_the_viser_panel_shows_the_garment_and_a_click_picks_it(device):
    app = build_app("avatar", "viser", "127.0.0.1", 0, smoke=True, simulation=_avatar)
    try:
        viewer, sim = app.viewer, app.simulation
        app.tick()
        assert "fps" in viewer.stats.content and "inside the body" in viewer.contact.content
        assert " ms" in viewer.breakdown.content and viewer.motion.value == "walk"
        origin, direction = _hem_ray(sim)
        app.click(origin, direction)
        assert sim.dragging
        app.tick()
        assert viewer._gizmo is not None  # the target's 3-D handle
        sim.release()
        app.tick()
        assert viewer._gizmo is None and app.errors == []
    finally:
        app.close()


def _broken(progress):
    progress("placing the garment", 0.3)
    raise ValueError("no garment fits")


def test_the_scene_menu_switches_to_and_from_the_avatar_and_keeps_the_scene_a_build_fails(device):
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True, scenes={"avatar": _avatar, "broken": _broken})
    try:
        viewer, sent = app.viewer, []
        viewer.server.send_json = lambda message, **_: sent.append(message)
        viewer._send_controls()
        assert sent[-1]["scenes"] == ["plant", "teapot", "jelly", "cloth", "sculpture", "avatar", "broken"]
        for message, why in (
            ({"type": "scene", "name": "mars"}, "unknown scene 'mars'"),
            ({"type": "scene", "name": 5}, "unknown scene '5'"),
            ({"type": "scene"}, "unknown scene 'None'"),
        ):
            with pytest.raises(ValueError, match=why):
                viewer.on_message(CLIENT, message)
        assert app.commands.empty()
        _send(app, type="scene", name="avatar")
        assert app.scene == "avatar" and app.simulation.kind == "garment" and app.errors == []
        app.tick()
        controls = [m for m in sent if m["type"] == "controls"][-1]
        assert controls["kind"] == "garment" and controls["scene"] == "avatar"
        assert any(m["type"] == "progress" and m["stage"].startswith("avatar: ") for m in sent)
        shown = app.simulation
        _send(app, type="scene", name="broken")
        assert app.simulation is shown and app.scene == "avatar"
        assert "the broken scene could not be built (no garment fits); still showing avatar" in app.errors[-1]
        assert [m for m in sent if m["type"] == "progress"][-1]["fraction"] is None  # the progress bar went
        app.tick()
        _send(app, type="scene", name="teapot")
        assert app.scene == "teapot" and getattr(app.simulation, "kind", "body") == "body"
        app.tick()
        assert [m for m in sent if m["type"] == "controls"][-1]["scene"] == "teapot" and len(app.errors) == 1
    finally:
        app.close()


def test_the_viser_panel_switches_scene_and_tints_the_garment_near_the_body(device):
    app = build_app("plant", "viser", "127.0.0.1", 0, smoke=True, scenes={"avatar": _avatar})
    try:
        viewer = app.viewer
        assert viewer.scene_menu.options == ("plant", "teapot", "jelly", "cloth", "sculpture", "avatar")
        app.tick()
        app.choose_scene("avatar")
        app.run_commands()
        assert app.scene == "avatar" and viewer.scene_menu.value == "avatar" and viewer.motion.value == "walk"
        sim, faces = app.simulation, app.simulation.mesh_faces.numpy()
        for _ in range(40):  # the walking legs reach the skirt within the first steps
            app.tick()
            near = sim.near_body().numpy()
            if near.any():
                break
        assert near.any(), "no garment vertex came within d̂ of the body"
        touching = near[faces].any(1)
        assert viewer.tinted.visible and np.array_equal(viewer.tinted.faces, faces[touching])
        assert np.array_equal(viewer.mesh.faces, faces[~touching])
        assert viewer.tinted.color == (255, 217, 26)  # physavatar.session.CONTACT_RGB
        assert f"contact: {int(near.sum())} vertices within d̂" in viewer.contact.content
        app.choose_scene("plant")
        app.run_commands()
        app.tick()
        assert app.scene == "plant" and viewer.scene_menu.value == "plant" and not viewer._garment
        assert app.errors == []
    finally:
        app.close()
