"""The meshcat server keeps serving whatever a page (or anything else on 127.0.0.1) sends it."""

from __future__ import annotations

import asyncio
import gc
import json
import os
import time
import urllib.error
import urllib.request

import pytest
import umsgpack
from tornado.httpclient import HTTPClientError, HTTPRequest
from tornado.websocket import websocket_connect

from pienerf.viewer.meshcat_server import MeshcatServer


def _until(condition, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


@pytest.fixture
def server():
    received: list[tuple[int, dict]] = []

    def on_message(client: int, message: dict) -> None:
        if message["type"] != "known":
            raise ValueError(f"unknown message type {message['type']!r}")
        received.append((client, message))

    server = MeshcatServer("127.0.0.1", 0, on_message=on_message)
    server.received = received
    yield server
    server.close()


def _get(server: MeshcatServer, path: str = "", host: str | None = None) -> int:
    request = urllib.request.Request(server.url + path, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            response.read()
            return response.status
    except urllib.error.HTTPError as error:
        return error.code


def _socket(server: MeshcatServer, origin: str | None = None, host: str | None = None):
    headers = {"Origin": origin or f"http://127.0.0.1:{server.port}"}
    if host:
        headers["Host"] = host
    return websocket_connect(HTTPRequest(f"ws://127.0.0.1:{server.port}/ws", headers=headers))


def test_serves_the_page_the_script_and_meshcats_bundle(server):
    assert [_get(server, path) for path in ("", "pienerf.js", "meshcat/main.min.js")] == [200, 200, 200]
    assert _get(server, "../../etc/passwd") == 404


def test_survives_malformed_oversized_and_unknown_messages(server):
    async def attack() -> None:
        socket = await _socket(server)
        socket.write_message(os.urandom(4096), binary=True)
        socket.write_message(b"\xc1\xff\x00not msgpack", binary=True)
        socket.write_message("{not json")
        socket.write_message(json.dumps([1, 2, 3]))
        socket.write_message(json.dumps({"type": 7}))
        socket.write_message(json.dumps({"type": "no such type", "payload": 1}))
        socket.write_message(json.dumps({"type": "known", "value": "x" * 1_500_000}))  # over 1 MiB: dropped
        socket.write_message(json.dumps({"type": "known", "value": 1}))
        assert await _after(lambda: len(server.received) == 1)
        socket.write_message("x" * 10_000_000)  # far over the limit: tornado closes this connection
        assert await socket.read_message() is None
        again = await _socket(server)
        again.write_message(json.dumps({"type": "known", "value": 2}))
        assert await _after(lambda: len(server.received) == 2)
        again.close()

    asyncio.run(attack())
    assert [message["value"] for _, message in server.received] == [1, 2]
    assert server.dropped == 7
    assert _get(server) == 200


async def _after(condition, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not condition():
        await asyncio.sleep(0.01)
    return condition()


def test_refuses_cross_origin_sockets_and_spoofed_hosts(server):
    async def connect(**headers) -> int:
        try:
            socket = await _socket(server, **headers)
        except HTTPClientError as error:
            return error.code
        socket.close()
        return 101

    assert asyncio.run(connect()) == 101
    assert asyncio.run(connect(origin=f"http://localhost:{server.port}")) == 101
    assert asyncio.run(connect(origin="http://evil.example")) == 403
    assert asyncio.run(connect(origin=f"http://127.0.0.1:{server.port + 1}")) == 403
    assert asyncio.run(connect(host=f"evil.example:{server.port}", origin=f"http://evil.example:{server.port}")) == 403
    assert _get(server, host=f"evil.example:{server.port}") == 403
    assert _get(server, host=f"127.0.0.1:{server.port}") == 200
    assert _get(server) == 200


def test_fifty_connections_opened_and_closed(server):
    async def churn() -> None:
        for _ in range(50):
            socket = await _socket(server)
            socket.close()

    asyncio.run(churn())
    assert _until(lambda: server.clients == [])
    assert _get(server) == 200


def test_a_late_tab_receives_the_remembered_scene(server):
    server.send({"type": "set_property", "path": "/a", "property": "visible", "value": False}, key="a")
    server.send({"type": "delete", "path": "/gone"})  # not remembered
    server.send_json({"type": "status", "text": "first"}, key="status")
    server.send_json({"type": "status", "text": "second"}, key="status")  # replaces the first

    async def late_tab() -> list:
        socket = await _socket(server)
        frames = [await socket.read_message(), await socket.read_message()]
        socket.close()
        return frames

    frames = asyncio.run(late_tab())
    assert umsgpack.unpackb(frames[0])["path"] == "/a"
    assert json.loads(frames[1]) == {"type": "status", "text": "second"}


def test_deeply_nested_json_is_dropped_and_the_connection_kept(server, caplog):
    async def nested() -> None:
        socket = await _socket(server)
        socket.write_message("[" * 100_000 + "]" * 100_000)  # 200 kB, under the size limit
        socket.write_message('{"type": "known", "value": ' + "[" * 50_000 + "]" * 50_000 + "}")
        socket.write_message(json.dumps({"type": "known", "value": 3}))
        assert await _after(lambda: len(server.received) == 1)
        socket.close()

    asyncio.run(nested())
    assert server.dropped == 2
    assert [message["value"] for _, message in server.received] == [3]
    assert not [record for record in caplog.records if record.exc_info], "a traceback was logged"


def test_idle_tabs_that_go_mid_write_leave_no_traceback(server, caplog):
    frame = {"type": "set_property", "path": "/a", "property": "value", "value": "x" * 200_000}

    async def idle_tabs() -> None:
        sockets = [await _socket(server) for _ in range(20)]  # they never read
        assert await _after(lambda: len(server.clients) == 20)
        for _ in range(20):
            server.send(frame, key="big")
        for socket in sockets:
            socket.close()

    asyncio.run(idle_tabs())
    assert _until(lambda: server.clients == [])
    for _ in range(5):
        server.send(frame)  # to no one
    gc.collect()
    assert _get(server) == 200
    assert not [record for record in caplog.records if record.exc_info], "a traceback was logged"
    assert not [record for record in caplog.records if "never retrieved" in record.getMessage()]
