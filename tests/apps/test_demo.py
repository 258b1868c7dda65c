"""apps.demo: the smoke runs exit 0, the viser server survives malformed messages and disconnects, and the NeRF
render mode serves each client a warped-NeRF image of its own view, coarse while moving and refined when still."""

from __future__ import annotations

import asyncio
import math
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from apps import demo

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_smoke_run_exits_zero(device):
    result = subprocess.run(
        [sys.executable, "-m", "apps.demo", "--smoke", "--port", str(free_port()), "--device", device],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "smoke: 3 steps of plant" in result.stdout


@pytest.fixture
def app(device):
    app = demo.build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True)
    yield app
    app.viewer.close()


def test_click_picks_then_drags_and_bad_clicks_are_reported(app):
    sim = app.simulation
    centre = sim.particle_positions()[int(sim.model.position[:, 1].argmax())].double()
    origin = centre + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    app.submit("click", lambda: app.click(origin, torch.tensor([0.0, 0.0, -1.0])))
    app.tick()
    drag = sim.interaction.drag
    assert drag.dragging
    app.submit("click", lambda: app.click(origin + torch.tensor([0.3, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0])))
    app.submit("click", lambda: app.click((math.nan, 0.0, 0.0), (0.0, 0.0, -1.0)))
    app.submit("click", lambda: app.click("not a ray", None))
    start = drag.position(sim.state.q).clone()
    for _ in range(3):
        app.tick()
    assert float(drag.target[0] - origin[0]) == pytest.approx(0.3, abs=1e-6)
    assert float(drag.position(sim.state.q)[0] - start[0]) > 1e-3  # the spring pulls toward +x
    assert len(app.errors) == 2 and all("click failed" in e for e in app.errors)
    assert "must be 3 finite numbers" in app.errors[0]
    # The viewer's own handler drops a malformed event before it reaches the loop.
    app.viewer._on_click(SimpleNamespace(ray_origin=(1.0, 2.0), ray_direction=(0.0, 0.0, -1.0)))
    assert app.commands.empty() and "ignored a malformed click" in app.viewer.message.content


def test_server_survives_malformed_messages_and_disconnects(app):
    import msgspec
    import viser
    import websockets
    from viser._messages import ScenePointerMessage

    uri = f"ws://127.0.0.1:{app.viewer.port}"
    protocols = [f"viser-v{viser.__version__}"]
    click = ScenePointerMessage(
        event_type="click",
        ray_origin=(math.nan, 0.0, 0.0),
        ray_direction=(0.0, 0.0, -1.0),
        screen_pos=((0.5, 0.5),),
        modifier=None,
    )

    async def exercise() -> tuple[bool, bool]:
        async with websockets.connect(uri, subprotocols=protocols) as socket_:
            await socket_.send(b"\xc1 not msgpack")
            try:
                while True:
                    await asyncio.wait_for(socket_.recv(), 20.0)
            except websockets.ConnectionClosed:
                dropped = True
        async with websockets.connect(uri, subprotocols=protocols) as socket_:
            served = isinstance(await asyncio.wait_for(socket_.recv(), 20.0), bytes)
            await socket_.send(msgspec.msgpack.encode(click.as_serializable_dict()))
            await socket_.send(b"\x81\xa4type\xa5Bogus")  # valid msgpack, unknown message type
        return dropped, served  # leaving the block disconnects the client

    dropped, served = asyncio.run(exercise())
    assert dropped and served
    before = app.simulation.time
    app.tick()
    assert app.simulation.time > before  # the loop goes on

    async def reconnect() -> bool:
        async with websockets.connect(uri, subprotocols=protocols) as socket_:
            return isinstance(await asyncio.wait_for(socket_.recv(), 20.0), bytes)

    assert asyncio.run(reconnect())  # still serving new clients


def test_smoke_run_with_the_nerf_render(device, tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "apps.demo",
            "--smoke",
            "--render",
            "nerf",
            "--port",
            str(free_port()),
            "--device",
            device,
            "--cache-dir",
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "smoke: 3 steps of plant" in result.stdout and "smoke: nerf frame 64x48" in result.stdout
    assert list(tmp_path.glob("scenes/plant-*/ngp-*.pt")), "the fitted NeRF is cached under the scene's folder"


def test_viser_cameras_follow_the_client_camera():
    # A viser (OpenCV) camera at z = 3 looking down −z: x right, y down in the image; quaternion of diag(1, −1, −1).
    cameras = demo.viser_cameras((0.2, 0.5, 3.0), (0.0, 1.0, 0.0, 0.0), math.radians(40.0), 1.5, 60)
    assert (cameras.width, cameras.height) == (90, 60)
    origin, centre = cameras.pixel_rays(0, torch.tensor([45.0]), torch.tensor([30.0]))
    torch.testing.assert_close(origin.reshape(3), torch.tensor([0.2, 0.5, 3.0]))
    torch.testing.assert_close(centre[0], torch.tensor([0.0, 0.0, -1.0]))
    _, top = cameras.pixel_rays(0, torch.tensor([45.0]), torch.tensor([0.0]))
    assert math.degrees(math.atan2(float(top[0, 1]), -float(top[0, 2]))) == pytest.approx(20.0, abs=1e-4)
    _, left = cameras.pixel_rays(0, torch.tensor([0.0]), torch.tensor([30.0]))
    assert float(left[0, 0]) < 0.0, "the image's left edge looks toward −x"


def test_refinement_schedule_is_coarse_while_moving_and_refines_once_when_still():
    schedule = demo.RefinementSchedule(moving=4, still=1, tolerance=1e-4)
    q = torch.zeros(5, 3, dtype=torch.float64)
    assert schedule.next(q, "view a") == 4
    assert schedule.next(q + 1e-5, "view a") == 1, "still: refine"
    assert schedule.next(q, "view a") is None, "already refined"
    assert schedule.next(q + 1e-3, "view a") == 4, "the body moved"
    assert schedule.next(q + 1e-3, "view b") == 4, "the camera moved"
    assert [schedule.next(q + 1e-3, "view b") for _ in range(3)] == [1, None, None]


def test_render_menu_switches_to_the_nerf_and_serves_each_client_its_view(device, tmp_path):
    import msgspec
    import viser
    import websockets
    from viser._messages import ViewerCameraMessage

    app = demo.build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True, cache_dir=str(tmp_path))
    try:
        sim = app.simulation
        assert app.render_mode == "mesh" and "nerf" not in sim.render_backends
        app.submit("render mode", lambda: app.viewer._set_render_mode("nerf"))
        app.paused = True
        app.tick()
        assert app.render_mode == "nerf" and "nerf" in sim.render_backends and not app.errors
        assert not app.viewer.mesh.visible and not app.viewer.ground.visible
        assert app.viewer.nerf_renders == [], "no client, nothing rendered"

        centre = sim.centre.double().tolist()
        camera = ViewerCameraMessage(
            wxyz=(0.0, 1.0, 0.0, 0.0),
            position=(centre[0], centre[1], centre[2] + 2.6),
            fov=math.radians(40.0),
            near=0.01,
            far=100.0,
            image_height=600,
            image_width=800,
            look_at=tuple(centre),
            up_direction=(0.0, 1.0, 0.0),
        )
        uri, protocols = f"ws://127.0.0.1:{app.viewer.port}", [f"viser-v{viser.__version__}"]

        async def look_and_render() -> None:
            async with websockets.connect(uri, subprotocols=protocols) as socket_:
                await asyncio.wait_for(socket_.recv(), 20.0)
                await socket_.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
                for _ in range(100):
                    clients = app.viewer.server.get_clients().values()
                    if any(c.camera.update_timestamp > 0 for c in clients):
                        break
                    await asyncio.sleep(0.05)
                # The server's connect handler also moves the camera, at a moment of its own: tick until two ticks
                # in a row render nothing.
                idle = 0
                for _ in range(10):
                    count = len(app.viewer.nerf_renders)
                    app.tick()
                    idle = idle + 1 if len(app.viewer.nerf_renders) == count else 0
                    if idle == 2:
                        break
                    await asyncio.sleep(0.1)

        asyncio.run(look_and_render())
        renders = app.viewer.nerf_renders
        assert renders[-1] == 1 and set(renders[:-1]) == {4}, f"coarse, then refined once, then nothing: {renders}"
        image = app.viewer.last_nerf_image
        assert image.shape == (app.viewer.nerf_height, round(app.viewer.nerf_height * 800 / 600), 3)
        middle = image[image.shape[0] // 3 : 2 * image.shape[0] // 3, image.shape[1] // 3 : 2 * image.shape[1] // 3]
        assert (np.abs(middle.astype(int) - 255).sum(-1) > 60).mean() > 0.05, "the plant is in the middle"

        app.submit("render mode", lambda: app.viewer._set_render_mode("mesh"))
        app.tick()
        assert app.render_mode == "mesh" and app.viewer.mesh.visible and app.viewer.ground.visible
    finally:
        app.viewer.close()
