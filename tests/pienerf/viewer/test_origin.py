"""pienerf.viewer.origin and the viser front end's request check: foreign Host and Origin headers are refused with a
real handshake, also on viser's own server port, which is the viewer's one listening port; same-origin pages are
served, bad addresses, ports in use and an untested viser are refused with the fix, and a malformed message logs one
line instead of a traceback."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import sys

import pytest

from pienerf.viewer.origin import bind_socket, check_address, checked_viser_server
from pienerf.viewer.viser_viewer import ViserViewer


@pytest.fixture(scope="module")
def viewer():
    viewer = ViserViewer("127.0.0.1", 0)
    yield viewer
    viewer.close()


def _http(port: int, head: str) -> str:
    """Send one raw HTTP request head to 127.0.0.1:port, return the status line of the answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=20) as connection:
        connection.sendall(head.encode())
        answer = b""
        while b"\r\n" not in answer:
            chunk = connection.recv(4096)
            if not chunk:
                break
            answer += chunk
    return answer.split(b"\r\n", 1)[0].decode()


def _handshake(port: int, origin: str | None) -> bytes:
    """Open viser's websocket on this port with this Origin; the first frame it sends, or the refusal."""
    import viser
    import websockets

    async def connect() -> bytes:
        async with websockets.connect(
            f"ws://127.0.0.1:{port}", origin=origin, subprotocols=[f"viser-v{viser.__version__}"]
        ) as socket_:
            return await asyncio.wait_for(socket_.recv(), 20.0)

    return asyncio.run(connect())


def test_cross_origin_websocket_upgrades_are_refused(viewer):
    import websockets

    with pytest.raises(websockets.InvalidStatus) as refused:
        _handshake(viewer.port, "http://evil.example.com")
    assert refused.value.response.status_code == 403
    assert viewer.request_check.refused >= 1
    assert isinstance(_handshake(viewer.port, f"http://127.0.0.1:{viewer.port}"), bytes), "the page's own origin"
    assert isinstance(_handshake(viewer.port, f"http://localhost:{viewer.port}"), bytes), "loopback by name"
    assert isinstance(_handshake(viewer.port, None), bytes), "a program that is not a browser sends no Origin"


def test_foreign_host_headers_are_refused(viewer):
    port = viewer.port
    assert _http(port, f"GET / HTTP/1.1\r\nHost: evil.example.com:{port}\r\n\r\n").split()[1] == "403"
    assert _http(port, "GET / HTTP/1.1\r\n\r\n").split()[1] == "403", "no Host at all"
    two = f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nHost: evil.example.com\r\n\r\n"
    assert _http(port, two).split()[1] == "403", "a second Host"
    assert _http(port, f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").split()[1] == "200"


def _listening_ports() -> set[int]:
    """TCP ports this process listens on (Linux: its socket inodes matched against /proc/net/tcp and tcp6)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as rows:
            for row in list(rows)[1:]:
                fields = row.split()
                if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                    ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the process's sockets from /proc")
def test_the_viewer_listens_on_its_own_port_only():
    before = _listening_ports()
    viewer = ViserViewer("127.0.0.1", 0)
    try:
        assert _listening_ports() - before == {viewer.port}, "no second (unchecked) port for viser"
        assert viewer.server.get_port() == viewer.port
    finally:
        viewer.close()


def test_viser_own_server_refuses_foreign_hosts_and_origins(viewer):
    import websockets

    port = viewer.server.get_port()  # viser's server itself, not a front of it
    with pytest.raises(websockets.InvalidStatus) as refused:
        _handshake(port, "http://evil.example.com")
    assert refused.value.response.status_code == 403
    assert _http(port, f"GET / HTTP/1.1\r\nHost: evil.example.com:{port}\r\n\r\n").split()[1] == "403"
    upgrade = (
        f"GET / HTTP/1.1\r\nHost: rebound.example.com:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert _http(port, upgrade).split()[1] == "403", "a websocket upgrade with a foreign Host"
    assert isinstance(_handshake(port, f"http://127.0.0.1:{port}"), bytes), "the page's own origin still connects"


def test_websockets_serve_is_left_as_it_was():
    import websockets.asyncio.server

    serve = websockets.asyncio.server.serve
    viewer = ViserViewer("127.0.0.1", 0)
    viewer.close()
    assert websockets.asyncio.server.serve is serve


def test_an_untested_viser_is_refused_with_the_fix(monkeypatch):
    import viser

    monkeypatch.setattr(viser, "__version__", "0.0.1")
    with pytest.raises(RuntimeError, match=r"viser 0\.0\.1 .*pip install viser==1\.1\.1"):
        checked_viser_server("127.0.0.1", 0)


def test_a_malformed_message_logs_one_line(viewer, caplog):
    import viser
    import websockets

    async def send_garbage() -> None:
        uri, protocols = f"ws://127.0.0.1:{viewer.port}", [f"viser-v{viser.__version__}"]
        for _ in range(3):
            async with websockets.connect(uri, subprotocols=protocols) as socket_:
                await socket_.send(b"\xc1 not msgpack")
                try:
                    while True:
                        await asyncio.wait_for(socket_.recv(), 20.0)
                except websockets.ConnectionClosed:
                    pass

    before = viewer.malformed_log.count
    with caplog.at_level(logging.WARNING):
        asyncio.run(send_garbage())
        for _ in range(100):  # the server thread logs after the connection closed
            if viewer.malformed_log.count - before == 3:
                break
            asyncio.run(asyncio.sleep(0.05))
    assert viewer.malformed_log.count - before == 3
    lines = [r for r in caplog.records if r.name.startswith("websockets")]
    assert len(lines) == 1, "rate-limited: one line for three bad clients in a row"
    assert all(r.exc_info is None and "malformed" in r.getMessage() for r in lines)
    assert "Traceback" not in caplog.text


@pytest.mark.parametrize(
    ("host", "port", "fix"),
    [
        ("127.0.0.1", 99999, "--port N"),
        ("127.0.0.1", -1, "--port N"),
        ("127.0.0.1", True, "--port N"),
        ("", 8080, "--host"),
        ("http://127.0.0.1", 8080, "--host"),
        ("no-such-host.invalid", 8080, "--host"),
    ],
)
def test_bad_addresses_are_refused_with_the_fix(host, port, fix):
    with pytest.raises(ValueError, match=fix):
        check_address(host, port)


def test_a_port_in_use_names_the_port_and_the_fix():
    taken = bind_socket("127.0.0.1", 0)
    try:
        port = taken.getsockname()[1]
        with pytest.raises(OSError, match=f"127.0.0.1:{port}.*--port N"):
            bind_socket("127.0.0.1", port)
        with pytest.raises(OSError, match=f"127.0.0.1:{port}.*--port N"):
            ViserViewer("127.0.0.1", port)
    finally:
        taken.close()
