"""pienerf.viewer: the loop picks and drags on clicks, the viser server survives malformed messages and
disconnects, and the NeRF render mode serves each client a warped-NeRF image of its own view, coarse while moving and
refined when still."""

from __future__ import annotations

import asyncio
import logging
import math
import socket
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pienerf.viewer import build_app


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _camera(sim):
    """A viser client's camera message: 40° vertical field of view, 2.6 m in front of the body, 800x600."""
    from viser._messages import ViewerCameraMessage

    centre = sim.centre.double().tolist()
    return ViewerCameraMessage(
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


@pytest.fixture
def app(device):
    app = build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True)
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
    app.viewer.on_click(SimpleNamespace(ray_origin=(1.0, 2.0), ray_direction=(0.0, 0.0, -1.0)))
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


def test_render_menu_switches_to_the_nerf_and_serves_each_client_its_view(device, tmp_path):
    import msgspec
    import viser
    import websockets

    app = build_app("plant", "viser", "127.0.0.1", free_port(), smoke=True, cache_dir=str(tmp_path))
    try:
        sim = app.simulation
        assert app.render_mode == "mesh" and "nerf" not in sim.render_backends
        app.submit("render mode", lambda: app.viewer.set_render_mode("nerf"))
        app.tick()
        assert app.nerf_job is not None and app.render_mode == "mesh", "the NeRF is fitted in the background"
        assert app.viewer.progress.visible
        start, ticks = sim.time, 0
        while app.nerf_job is not None and ticks < 20000:  # the loop steps on while another process fits
            app.tick()
            ticks += 1
        assert not app.errors, app.errors
        assert app.render_mode == "nerf" and "nerf" in sim.render_backends and not app.viewer.progress.visible
        assert ticks > 1 and sim.time > start, "the simulation stepped while the NeRF was fitted"
        assert app.viewer.render_mode.value == "nerf"
        app.paused = True
        assert not app.viewer.mesh.visible and not app.viewer.ground.visible
        assert app.viewer.nerf_renders == [], "no client, nothing rendered"

        camera = _camera(sim)
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

        app.submit("render mode", lambda: app.viewer.set_render_mode("mesh"))
        app.tick()
        assert app.render_mode == "mesh" and app.viewer.mesh.visible and app.viewer.ground.visible
    finally:
        app.viewer.close()


def test_out_of_range_panel_values_are_refused_in_the_panel(app, caplog):
    import msgspec
    import viser
    import websockets
    from viser._messages import GuiUpdateMessage

    viewer, sim = app.viewer, app.simulation
    young, damping = sim.material.young_modulus, sim.config.solver.rayleigh_alpha
    assert viewer.young.label == "Young's modulus (Pa)" and viewer.young.value == young, "E in Pa, as people read it"
    sent = [
        (viewer.render_mode, "bogus"),
        (viewer.young, 1e400),  # log10 400 on the old slider: an OverflowError the panel never showed
        (viewer.damping, 1e300),
        (viewer.young, "20 kPa"),
    ]

    async def send() -> list[str]:
        uri, protocols = f"ws://127.0.0.1:{viewer.port}", [f"viser-v{viser.__version__}"]
        shown = []
        async with websockets.connect(uri, subprotocols=protocols) as socket_:
            await asyncio.wait_for(socket_.recv(), 20.0)
            await socket_.send(msgspec.msgpack.encode(_camera(sim).as_serializable_dict()))
            for _ in range(200):  # viser knows a client once it sent its camera
                if viewer.server.get_clients():
                    break
                await asyncio.sleep(0.02)
            for handle, value in sent:
                viewer.message.content = ""
                message = GuiUpdateMessage(handle._impl.uuid, {"value": value})
                await socket_.send(msgspec.msgpack.encode(message.as_serializable_dict()))
                for _ in range(200):  # the server's thread handles it
                    if viewer.message.content:
                        break
                    await asyncio.sleep(0.02)
                shown.append(viewer.message.content)
        return shown

    before = viewer.malformed_log.count
    with caplog.at_level(logging.WARNING):
        shown = asyncio.run(send())
    assert viewer.malformed_log.count == before + 1, "text for a number fails in viser's own cast: one line"
    assert "Traceback" not in caplog.text and "a viser client: dropped a malformed message" in caplog.text
    assert "refused: unknown render mode 'bogus'" in shown[0]
    assert "refused: young modulus must be a number in [100, 1e+09]" in shown[1], shown
    assert "refused: damping must be a number in [0, 100]" in shown[2], shown
    assert shown[3] == "", "viser drops it before the viewer sees it"
    assert app.commands.empty(), "a refusal and its revert queue nothing (the refusal stays shown)"
    assert viewer.render_mode.value == app.render_mode == "mesh" and viewer.mesh.visible, "the body stays shown"
    assert viewer.young.value == young and viewer.damping.value == damping, "the controls show the values in use"
    app.tick()
    assert not app.errors and sim.material.young_modulus == young

    viewer.young.value = 5e4  # a good value still goes through after the refusals
    app.tick()
    assert sim.material.young_modulus == 5e4 and "E = 50 kPa" in viewer.message.content


def test_status_message_and_time_breakdown_head_the_panel(app):
    viewer = app.viewer
    app.tick()
    top = [viewer.stats, viewer.message, viewer.breakdown]
    assert "fps" in viewer.stats.content and " ms" in viewer.breakdown.content
    root = {h._impl.parent_container_id for h in top}
    assert len(root) == 1, "all three at the panel's top level"
    others = [viewer.young, viewer.kernels, viewer.release, viewer.render_mode]
    assert [h.order for h in top] == sorted(h.order for h in top), "status first, then message, breakdown"
    assert max(h.order for h in top) < min(h.order for h in others), "above every folder's controls"
