"""apps.demo: the smoke run exits 0, and the viser server survives malformed messages and disconnects."""

from __future__ import annotations

import asyncio
import math
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

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
        cwd=ROOT, capture_output=True, text=True, timeout=300,
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
    click = ScenePointerMessage(event_type="click", ray_origin=(math.nan, 0.0, 0.0), ray_direction=(0.0, 0.0, -1.0),
                                screen_pos=((0.5, 0.5),), modifier=None)

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
