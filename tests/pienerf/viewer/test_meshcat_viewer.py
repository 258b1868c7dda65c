"""Page message -> Simulation command, with no browser: the meshcat viewer only validates and queues."""

from __future__ import annotations

import asyncio
import json
import math
import re
import time

import numpy as np
import pytest
import torch
from tornado.httpclient import HTTPRequest
from tornado.websocket import websocket_connect

from kernels import backend
from pienerf.viewer import build_app
from pienerf.viewer.meshcat_viewer import Y_UP_TO_Z_UP, page_cameras

CLIENT = 1


@pytest.fixture(scope="module")
def app(request):
    backend.init(request.config.getoption("--device") or backend.default_device())
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True)
    yield app
    app.viewer.close()


def _send(app, **message):
    app.viewer.on_message(CLIENT, message)
    app.run_commands()


def _ray_at_centre(app):
    centre = app.simulation.centre.double().numpy()
    return (centre + np.array([0.0, 0.0, 3.0])).tolist(), [0.0, 0.0, -1.0]


def test_press_drag_release(app):
    sim = app.simulation
    origin, direction = _ray_at_centre(app)
    _send(app, type="pick", origin=origin, direction=direction)
    assert sim.dragging
    depth = float(torch.as_tensor(sim.drag_target).double()[2])
    _send(app, type="drag", origin=[origin[0] + 0.2, origin[1], origin[2]], direction=direction)
    target = sim.drag_target.double()
    assert float(target[0]) == pytest.approx(origin[0] + 0.2) and float(target[2]) == pytest.approx(depth, abs=5e-3)
    _send(app, type="release")
    assert not sim.dragging
    assert app.errors == []


def test_a_tab_closing_mid_drag_releases_it(app):
    origin, direction = _ray_at_centre(app)
    port = app.viewer.port

    async def press_then_close() -> None:
        request = HTTPRequest(f"ws://127.0.0.1:{port}/ws", headers={"Origin": f"http://127.0.0.1:{port}"})
        socket = await websocket_connect(request)
        socket.write_message(json.dumps({"type": "pick", "origin": origin, "direction": direction}))
        assert await _after(lambda: not app.commands.empty())
        app.run_commands()
        assert app.simulation.dragging
        socket.close()
        assert await _after(lambda: not app.commands.empty()), "closing the tab queued nothing"

    asyncio.run(press_then_close())
    app.run_commands()
    assert not app.simulation.dragging


async def _after(condition, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not condition():
        await asyncio.sleep(0.01)
    return condition()


def test_controls_change_the_material(app):
    sim = app.simulation
    _send(app, type="set", name="young_modulus", value=5.0e4)
    _send(app, type="set", name="poisson_ratio", value=0.25)
    _send(app, type="set", name="density", value=800)
    _send(app, type="set", name="model", value="stvk")
    _send(app, type="set", name="gravity", value=3.0)
    _send(app, type="set", name="damping", value=2.0)
    assert (sim.material.young_modulus, sim.material.poisson_ratio, sim.material.density) == (5.0e4, 0.25, 800.0)
    solver = sim.config.solver
    assert sim.material.model == "stvk" and solver.gravity == (0.0, -3.0, 0.0) and solver.rayleigh_alpha == 2.0
    assert app.errors == []


def test_buttons_pin_push_reset(app):
    sim = app.simulation
    pins = len(sim.interaction.pins)
    origin, direction = _ray_at_centre(app)
    _send(app, type="pick", origin=origin, direction=direction)
    _send(app, type="pin")
    assert len(sim.interaction.pins) == pins + 1 and not sim.dragging
    _send(app, type="pick", origin=origin, direction=direction)
    _send(app, type="push")
    assert len(sim.interaction.forces) == 1
    assert float(sim.interaction.forces[0].force[0, 2]) < 0  # half the weight along -z
    sim.step()
    _send(app, type="reset")
    assert len(sim.interaction.forces) == 0 and len(sim.interaction.pins) == pins and sim.time == 0.0
    _send(app, type="pin")  # nothing picked: reported, the loop goes on
    assert "nothing is picked" in app.errors.pop()


@pytest.mark.parametrize(
    "message",
    [
        {"type": "teleport"},
        {"type": "pick", "origin": [0, 0], "direction": [0, 0, -1]},
        {"type": "pick", "origin": [0, 0, math.nan], "direction": [0, 0, -1]},
        {"type": "drag", "origin": "up", "direction": [0, 0, -1]},
        {"type": "set", "name": "young_modulus", "value": -1.0},
        {"type": "set", "name": "young_modulus", "value": "20 kPa"},
        {"type": "set", "name": "density", "value": True},
        {"type": "set", "name": "model", "value": "rubber"},
        {"type": "set", "name": "render_mode", "value": "wireframe"},
        {"type": "set", "name": "__class__", "value": 1},
        {"type": "resample", "kernel_count": 10**9},
        {"type": "camera", "matrix": [1] * 16, "fov": 50, "aspect": 1.5},
        {"type": "camera", "matrix": np.eye(4).ravel().tolist(), "fov": 0, "aspect": 1.5},
    ],
)
def test_malformed_messages_are_refused_before_anything_is_queued(app, message):
    with pytest.raises(ValueError):
        app.viewer.on_message(CLIENT, message)
    assert app.commands.empty()


@pytest.mark.parametrize(
    ("name", "value", "why"),
    [
        ("render_mode", "bogus", "unknown render mode 'bogus'"),
        ("damping", 1e300, "damping must be a number in [0, 100]"),
        ("young_modulus", math.inf, "young modulus must be a number in [100, 1e+09]"),
        ("gravity", -9.81, "gravity must be a number in [0, 100]"),
    ],
)
def test_refused_values_are_shown_in_the_page_and_change_nothing(app, name, value, why):
    sim, mode, damping = app.simulation, app.render_mode, app.simulation.config.solver.rayleigh_alpha
    with pytest.raises(ValueError, match=re.escape(why)):
        app.viewer.on_message(CLIENT, {"type": "set", "name": name, "value": value})
    assert app.viewer.message.startswith("refused: ") and why in app.viewer.message
    assert app.commands.empty() and app.render_mode == mode and sim.config.solver.rayleigh_alpha == damping


def test_page_cameras_follow_threejs_conventions():
    c2w = np.eye(4)
    c2w[:3, 3] = (0.1, 0.5, 2.0)
    cameras = page_cameras(c2w.T.ravel().tolist(), 90.0, 2.0, 100)  # column-major, as three.js sends it
    assert (cameras.width, cameras.height) == (200, 100)
    assert float(cameras.fx[0]) == pytest.approx(50.0)
    assert torch.allclose(cameras.c2w[0], torch.tensor(c2w, dtype=torch.float32))
    # the root node turns the scene's up (+y) into meshcat's up (+z)
    assert np.allclose(Y_UP_TO_Z_UP[:3, :3] @ (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def test_resample_rebuilds_with_the_new_kernel_count(app):
    _send(app, type="resample", kernel_count=8)
    assert app.simulation.model.basis.kernel_count == 8
    assert app.errors == []


def test_the_nerf_view_holds_the_frame_budget_by_its_resolution(device, tmp_path):
    app = build_app("plant", "meshcat", "127.0.0.1", 0, smoke=True, render="nerf", cache_dir=str(tmp_path))
    try:
        viewer = app.viewer
        app.paused = True  # only the camera moves
        eye = np.eye(4)
        eye[:3, 3] = app.simulation.centre.double().numpy() + np.array([0.0, 0.0, 3.0])

        def look(shift: float) -> None:
            matrix = eye.copy()
            matrix[0, 3] += shift
            camera = {"type": "camera", "matrix": matrix.T.reshape(-1).tolist(), "fov": 50.0, "aspect": 4 / 3}
            viewer.on_message(CLIENT, camera)

        with pytest.raises(ValueError, match="frame_budget must be a positive number of seconds"):
            viewer.nerf_schedules.frame_budget = 0.0
        # A budget every render holds: full resolution from the first measured render on.
        viewer.nerf_schedules.frame_budget = 600.0
        viewer.nerf_renders.clear()
        for frame in range(4):
            look(0.01 * (frame + 1))  # the camera moves every frame
            app.tick()
        assert viewer.nerf_renders[:2] == [4, 4] and set(viewer.nerf_renders[2:]) == {1}, viewer.nerf_renders
        # A budget no render can hold: the finest level not much slower than the coarsest, as the schedule's fit of
        # the measured renders predicts (on this CPU the smoke NeRF's renders cost about the same at every size).
        viewer.nerf_schedules.frame_budget = 1e-9
        viewer.nerf_renders.clear()
        for frame in range(6):
            look(0.5 + 0.01 * (frame + 1))
            app.tick()
        assert viewer.nerf_renders[:3] == [4, 4, 8], viewer.nerf_renders
        schedule = viewer.nerf_schedules.of(CLIENT)
        floor = 1.15 * schedule.predicted_seconds(8)
        expected = next(level for level in range(1, 9) if schedule.predicted_seconds(level) <= floor)
        look(0.6)
        app.tick()  # the next moving frame renders at the level the renders measured so far predict
        assert viewer.nerf_renders[-1] == expected, (viewer.nerf_renders, expected)
        viewer.nerf_schedules.frame_budget = 1e-9  # a new budget starts the schedules again
        viewer.nerf_renders.clear()
        for _ in range(3):  # the camera stays
            app.tick()
        assert viewer.nerf_renders == [4, 1], "the start level, then refined once when still, then nothing"
        assert not app.errors, app.errors
    finally:
        app.viewer.close()
