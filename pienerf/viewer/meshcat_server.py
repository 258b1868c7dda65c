"""The meshcat viewer's web server: the project's page and script, meshcat's own three.js client, and a websocket.

The browser runs meshcat's unmodified bundle (``meshcat/viewer/dist/main.min.js`` of the installed ``meshcat``
package, read at start) under a page and a script of this project (``web/``). Towards the page the server speaks
two kinds of websocket frame:

* binary frames: meshcat's msgpack commands (``set_object``, ``set_transform``, ``set_property``, ``delete``, built
  from :mod:`meshcat.commands` objects' ``lower()``), plus one command of the project's script, ``set_vertices``
  (a new position buffer for an existing geometry, so a frame never rebuilds the scene);
* text frames: JSON messages of the project (controls, status, progress, NeRF images).

From the page it takes JSON text only (pointer rays, camera, control changes), each handed to ``on_message`` on
the server's thread, which must only queue work (the simulation loop runs it between steps).

Every command sent with a ``key`` is remembered (the latest per key), so a tab that opens late or reloads receives
the whole scene. Commands sent as ``volatile`` (per-frame vertex buffers, status) are skipped for a tab whose
previous frame is still being written, and its latest value follows once the socket drains.

Security: binds 127.0.0.1 by default; refuses requests whose ``Host`` is not the bound address and port (DNS
rebinding) and websocket upgrades whose ``Origin`` is not the page's. Malformed, oversized, binary or unknown
messages are dropped and counted, with one log line per client at most every few seconds, never a traceback.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import meshcat
import tornado.httpserver
import tornado.ioloop
import tornado.web
import tornado.websocket
import umsgpack

from pienerf.viewer.origin import allowed_hosts, bind_socket

__all__ = ["MAX_MESSAGE_BYTES", "MeshcatServer"]

MAX_MESSAGE_BYTES = 1 << 20
"""Largest message a page may send (bytes); larger ones are dropped (far larger ones close that connection)."""

_LOG = logging.getLogger(__name__)
_WARNING_INTERVAL = 5.0  # s between two log lines about one client's dropped messages


def _read_web_file(name: str) -> bytes:
    return resources.files("pienerf.viewer").joinpath("web", name).read_bytes()


def _meshcat_bundle() -> bytes:
    """meshcat's three.js client, from the installed package (never copied into this repository)."""
    path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
    if not path.is_file():
        raise FileNotFoundError(f"meshcat's viewer bundle {path} is missing: reinstall meshcat (pip install meshcat)")
    return path.read_bytes()


def _retrieve(future) -> None:
    """Mark a finished write's outcome as seen (the tab's close is handled by ``on_close``)."""
    if not future.cancelled():
        future.exception()


def _log_loop_error(loop, context: dict) -> None:
    """What the server's event loop could not hand to anyone (a closed tab's write), as one log line."""
    error = context.get("exception")
    why = f"{type(error).__name__}: {str(error)[:200]}" if error is not None else context.get("message", "")
    _LOG.warning("meshcat server: %s", why)


class _Client:
    """One open tab: its socket and the state of its per-frame writes."""

    def __init__(self, socket: _Socket, number: int):
        self.socket = socket
        self.number = number
        self.busy = False  # a volatile frame is being written
        self.behind: set[str] = set()  # keys of volatile frames skipped while busy
        self.dropped = 0
        self.last_warning = -float("inf")
        self.unreported = 0


class _Guarded(tornado.web.RequestHandler):
    """Refuses requests whose Host header is not the server's own address (DNS rebinding)."""

    def initialize(self, server: MeshcatServer, body: bytes = b"", content_type: str = ""):
        self.server, self.body, self.content_type = server, body, content_type

    def prepare(self):
        if self.request.host not in self.server.allowed_hosts:
            raise tornado.web.HTTPError(403, reason="unexpected Host")

    def get(self):
        self.set_header("Content-Type", self.content_type)
        self.set_header("Cache-Control", "no-cache")
        self.write(self.body)


class _Socket(tornado.websocket.WebSocketHandler):
    def initialize(self, server: MeshcatServer):
        self.server = server
        self.client: _Client | None = None

    def prepare(self):
        if self.request.host not in self.server.allowed_hosts:
            raise tornado.web.HTTPError(403, reason="unexpected Host")

    def check_origin(self, origin: str) -> bool:
        return origin in self.server.allowed_origins

    def get_compression_options(self):
        return None

    def open(self):
        self.client = self.server._opened(self)

    def on_message(self, message):
        if self.client is not None:
            self.server._received(self.client, message)

    def on_close(self):
        if self.client is not None:
            self.server._closed(self.client)


class MeshcatServer:
    """Serves the meshcat page and relays commands and messages between the simulation thread and every tab.

    Args:
        host: address to bind (default loopback only).
        port: TCP port; 0 picks a free one (see :attr:`port`). A bad address raises ValueError, a port in use
            OSError, both naming the fix.
        on_message: ``on_message(client, message)`` with a page's JSON object (a dict with a ``"type"``), called
            on the server's thread; raise ``ValueError`` to have the message dropped and counted.
        on_open: ``on_open(client)`` when a tab connects (after it received the remembered scene).
        on_close: ``on_close(client)`` when a tab goes.
        max_message_bytes: largest message accepted from a page.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        on_message: Callable[[int, dict], None] | None = None,
        on_open: Callable[[int], None] | None = None,
        on_close: Callable[[int], None] | None = None,
        max_message_bytes: int = MAX_MESSAGE_BYTES,
    ):
        self.on_message, self.on_open, self.on_close = on_message, on_open, on_close
        self.max_message_bytes = int(max_message_bytes)
        self.dropped = 0  # messages dropped, all clients together
        self._clients: dict[int, _Client] = {}
        self._count = 0
        self._scene: dict[str, tuple[bool, bytes | str]] = {}  # key -> (binary, frame), latest per key
        listening = bind_socket(host, port)  # checks the address; a port in use says so
        listening.setblocking(False)
        sockets = [listening]
        self.host, self.port = host, listening.getsockname()[1]
        self.allowed_hosts = allowed_hosts(host, self.port)
        self.allowed_origins = frozenset(f"http://{name}" for name in self.allowed_hosts)
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        files = {
            "/": (_read_web_file("index.html"), "text/html; charset=utf-8"),
            "/pienerf.js": (_read_web_file("pienerf.js"), "text/javascript; charset=utf-8"),
            "/meshcat/main.min.js": (_meshcat_bundle(), "text/javascript; charset=utf-8"),
            "/favicon.ico": (b"", "image/x-icon"),
        }
        routes = [
            (path, _Guarded, {"server": self, "body": body, "content_type": kind})
            for path, (body, kind) in files.items()
        ]
        routes.append(("/ws", _Socket, {"server": self}))
        # Tornado closes a connection whose message exceeds its limit; up to twice ours they are dropped here.
        self._application = tornado.web.Application(routes, websocket_max_message_size=2 * self.max_message_bytes)
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(sockets,), name="meshcat-server", daemon=True)
        self._thread.start()
        self._ready.wait()

    # -- the server's thread ---------------------------------------------------------------------

    def _serve(self, sockets) -> None:
        loop = asyncio.new_event_loop()
        loop.set_exception_handler(_log_loop_error)  # one line, never a traceback
        asyncio.set_event_loop(loop)
        self._loop = tornado.ioloop.IOLoop.current()
        self._http = tornado.httpserver.HTTPServer(self._application)
        self._http.add_sockets(sockets)
        self._ready.set()
        self._loop.start()
        self._loop.close(all_fds=True)

    def _opened(self, socket: _Socket) -> _Client:
        self._count += 1
        client = _Client(socket, self._count)
        self._clients[client.number] = client
        for binary, frame in list(self._scene.values()):
            self._write(client, frame, binary)
        if self.on_open is not None:
            self._call(client, self.on_open, client.number)
        return client

    def _closed(self, client: _Client) -> None:
        self._clients.pop(client.number, None)
        if self.on_close is not None:
            self._call(client, self.on_close, client.number)

    def _received(self, client: _Client, message: str | bytes) -> None:
        if isinstance(message, bytes):
            self._drop(client, f"a binary message of {len(message)} bytes (the page sends JSON text)")
            return
        if len(message) > self.max_message_bytes:
            self._drop(client, f"a message of {len(message)} bytes (limit {self.max_message_bytes})")
            return
        try:
            decoded = json.loads(message)
        except ValueError:
            self._drop(client, "a message that is not JSON")
            return
        except RecursionError:  # nesting deeper than the interpreter's stack, well under the size limit
            self._drop(client, "a JSON message nested too deeply")
            return
        if not isinstance(decoded, dict) or not isinstance(decoded.get("type"), str):
            self._drop(client, "a JSON message that is not an object with a string 'type'")
            return
        if self.on_message is not None:
            self._call(client, self.on_message, client.number, decoded)

    def _call(self, client: _Client, function, *args) -> None:
        try:
            function(*args)
        except ValueError as error:
            self._drop(client, str(error))
        except Exception as error:  # a handler's bug (or a RecursionError) must not take the server down
            self._drop(client, f"{type(error).__name__}: {str(error)[:200]}")

    def _drop(self, client: _Client, why: str) -> None:
        """Count a dropped message; log one line per client at most every few seconds."""
        self.dropped += 1
        client.dropped += 1
        client.unreported += 1
        now = time.monotonic()
        if now - client.last_warning >= _WARNING_INTERVAL:
            _LOG.warning(
                "meshcat client %d: dropped %d message(s), %d in all (last: %s)",
                client.number,
                client.unreported,
                client.dropped,
                why[:200],
            )
            client.last_warning, client.unreported = now, 0

    def _write(self, client: _Client, frame: bytes | str, binary: bool):
        try:
            future = client.socket.write_message(frame, binary=binary)
        except tornado.websocket.WebSocketClosedError:
            return None
        # A tab that goes while the frame is written fails the write's task with WebSocketClosedError; retrieving it
        # here keeps asyncio from logging "Task exception was never retrieved" for every frame sent to it.
        future.add_done_callback(_retrieve)
        return future

    def _broadcast(self, frame: bytes | str, binary: bool, key: str | None, volatile: bool, to: int | None) -> None:
        if key is not None and to is None:
            self._scene[key] = (binary, frame)
        targets = [self._clients[to]] if to in self._clients else [] if to is not None else self._clients.values()
        for client in list(targets):
            if volatile and client.busy:
                if key is not None:
                    client.behind.add(key)
                continue
            future = self._write(client, frame, binary)
            if volatile and future is not None:
                client.busy = True
                future.add_done_callback(lambda _f, c=client: self._drained(c))

    def _drained(self, client: _Client) -> None:
        client.busy = False
        behind, client.behind = client.behind, set()
        for key in behind:
            if key in self._scene and client.number in self._clients:
                self._write(client, self._scene[key][1], self._scene[key][0])

    # -- any thread ------------------------------------------------------------------------------

    def send(self, command: dict, key: str | None = None, volatile: bool = False, to: int | None = None) -> None:
        """Send a meshcat command (a ``lower()``-ed dict) to every tab, or to the tab ``to``.

        Args:
            command: the command; numpy buffers inside must already be ``umsgpack.Ext`` (meshcat's packing).
            key: remember it under this key (replacing the last one) for tabs that open later.
            volatile: skip tabs still writing an earlier volatile frame (they get the latest one afterwards).
            to: one client's number instead of all.
        """
        self._loop.add_callback(self._broadcast, umsgpack.packb(command), True, key, volatile, to)

    def send_json(self, message: dict, key: str | None = None, volatile: bool = False, to: int | None = None) -> None:
        """Send a JSON message of the project's script; arguments as :meth:`send`."""
        self._loop.add_callback(self._broadcast, json.dumps(message), False, key, volatile, to)

    def forget(self, key: str) -> None:
        """Stop replaying ``key`` to tabs that open later."""
        self._loop.add_callback(self._scene.pop, key, None)

    def forget_all(self) -> None:
        """Stop replaying anything sent so far to tabs that open later (a new scene is sent whole after it)."""
        self._loop.add_callback(self._scene.clear)

    @property
    def clients(self) -> list[int]:
        """Numbers of the open tabs."""
        return list(self._clients)

    def close(self) -> None:
        """Close every tab and stop serving."""
        if not self._thread.is_alive():
            return

        def stop() -> None:
            self._http.stop()
            for client in list(self._clients.values()):
                client.socket.close()
            self._loop.stop()

        self._loop.add_callback(stop)
        self._thread.join(10.0)
