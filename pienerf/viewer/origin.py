"""Who may talk to a viewer: the address checks shared by both front ends, and a guard in front of viser.

A page on any web site can open a websocket to ``127.0.0.1`` (browsers send its ``Origin`` but do not block it),
and a site whose name an attacker re-points at ``127.0.0.1`` (DNS rebinding) sends a foreign ``Host``. A viewer
must therefore refuse requests whose ``Host`` is not its own address and websocket upgrades whose ``Origin`` is
not its own page.

viser (1.1.1) runs its own ``websockets`` server and offers no option or public hook to check either header, so
:class:`OriginGuard` listens on the viewer's address instead, reads the head of each HTTP request, refuses a
foreign ``Host`` or ``Origin`` with ``403``, and otherwise relays the connection byte for byte to the viser
server, which binds an ephemeral loopback port. viser answers each plain HTTP request and closes the connection,
so every request passes the check.

Limitation: the ephemeral port itself is unguarded. Nothing of the viewer's tells a page that port, but a page
that scans the loopback ports can find it and reach viser directly (as can any local program); closing that gap
needs a header check inside viser's server, which viser does not offer.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import socket
import threading
import time

__all__ = ["LOOPBACK", "OriginGuard", "allowed_hosts", "bind_socket", "check_address"]

LOOPBACK = ("127.0.0.1", "localhost", "::1")
"""Names of the loopback address; a viewer bound to one of them answers to all of them."""

_LOG = logging.getLogger(__name__)
_WARNING_INTERVAL = 5.0  # s between two log lines about refused requests
_HEAD_LIMIT = 64 * 1024  # bytes of an HTTP request head
_HEAD_SECONDS = 10.0  # s a client may take to send its request head


def check_address(host, port) -> tuple[str, int]:
    """``(host, port)`` of a viewer, or a ValueError saying what is wrong and how to fix it.

    Args:
        host: an IP address or a name this machine resolves (``127.0.0.1`` keeps the viewer local).
        port: TCP port in ``0..65535`` (0 picks a free one).
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"port {port!r} is not a TCP port: pass --port N with N in 0..65535 (0 picks a free one)")
    if not isinstance(host, str) or not host or any(c.isspace() or c in "/[]@" for c in host):
        raise ValueError(f"host {host!r} is not an address: pass --host 127.0.0.1 (or another IP or host name)")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        try:
            socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError):
            raise ValueError(f"host {host!r} does not resolve: pass --host 127.0.0.1 (or another IP)") from None
    return host, port


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``(host, port)``, or an OSError naming the port and the fix."""
    check_address(host, port)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        return socket.create_server((host, port), family=family, backlog=64)
    except OSError as error:
        raise OSError(
            error.errno,
            f"cannot listen on {host}:{port} ({error.strerror or error}): another program may use that port; "
            "pass --port N for another one (or --port 0 for any free one)",
        ) from None


def allowed_hosts(host: str, port: int) -> frozenset[str]:
    """``Host`` header values a viewer bound to ``host:port`` answers (all loopback names for a loopback host)."""
    names = {host, *LOOPBACK} if host in LOOPBACK else {host}
    return frozenset(f"[{name}]:{port}" if ":" in name else f"{name}:{port}" for name in names)


class OriginGuard:
    """Listens on a viewer's address, refuses foreign ``Host`` and ``Origin`` headers, relays the rest to a server.

    Args:
        host, port: where to listen (port 0 picks a free one, see :attr:`port`); checked by :func:`check_address`.
        backend_port: the guarded server's port on ``127.0.0.1``.

    Attributes:
        port: the port listened on.
        allowed_hosts, allowed_origins: the header values accepted.
        refused: requests refused so far.
    """

    def __init__(self, host: str, port: int, backend_port: int):
        self._socket = bind_socket(host, port)
        self.host, self.port = host, self._socket.getsockname()[1]
        self.backend_port = int(backend_port)
        self.allowed_hosts = allowed_hosts(host, self.port)
        self.allowed_origins = frozenset(f"http://{name}" for name in self.allowed_hosts)
        self.refused = 0
        self._last_warning = -float("inf")
        self._unreported = 0
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="viewer-origin-guard", daemon=True)
        self._thread.start()
        self._ready.wait()

    def _serve(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        self._stopped = asyncio.Event()

        async def serve() -> None:
            server = await asyncio.start_server(self._relay, sock=self._socket, limit=_HEAD_LIMIT)
            self._ready.set()
            async with server:
                await self._stopped.wait()

        try:
            loop.run_until_complete(serve())
        finally:
            self._ready.set()
            loop.close()

    def check(self, head: bytes) -> str | None:
        """Why the request with this head (request line and headers) is refused, or ``None`` to let it through."""
        lines = head.decode("latin-1").split("\r\n")
        headers: dict[str, list[str]] = {}
        for line in lines[1:]:
            name, colon, value = line.partition(":")
            if colon:
                headers.setdefault(name.strip().lower(), []).append(value.strip())
        hosts, origins = headers.get("host", []), headers.get("origin", [])
        if len(hosts) != 1 or hosts[0] not in self.allowed_hosts:
            return f"unexpected Host {', '.join(hosts)[:80]!r}"
        if len(origins) > 1 or (origins and origins[0] not in self.allowed_origins):
            return f"cross-origin request from {', '.join(origins)[:80]!r}"
        return None

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), _HEAD_SECONDS)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ConnectionError):
            writer.close()
            return
        why = self.check(head)
        if why is not None:
            self._refuse(why)
            body = f"403 Forbidden: {why}\n".encode()
            writer.write(
                b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                + f"Content-Length: {len(body)}\r\n\r\n".encode()
                + body
            )
            try:
                await writer.drain()
            except ConnectionError:
                pass
            writer.close()
            return
        try:
            backend_reader, backend_writer = await asyncio.open_connection("127.0.0.1", self.backend_port)
        except OSError:
            writer.close()
            return
        backend_writer.write(head)
        await asyncio.gather(_pipe(reader, backend_writer), _pipe(backend_reader, writer))

    def _refuse(self, why: str) -> None:
        self.refused += 1
        self._unreported += 1
        now = time.monotonic()
        if now - self._last_warning >= _WARNING_INTERVAL:
            _LOG.warning("viewer on port %d refused %d request(s) (last: %s)", self.port, self._unreported, why)
            self._last_warning, self._unreported = now, 0

    def close(self) -> None:
        """Stop listening (relayed connections end with the guarded server)."""
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stopped.set)
            self._thread.join(10.0)


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Copy ``reader`` to ``writer`` until either side closes, then close ``writer``."""
    try:
        while data := await reader.read(1 << 16):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, asyncio.CancelledError):
        pass
    finally:
        writer.close()
