"""Who may talk to a viewer: the address checks shared by both front ends, and the same checks inside viser.

A page on any web site can open a websocket to ``127.0.0.1`` (browsers send its ``Origin`` but do not block it),
and a site whose name an attacker re-points at ``127.0.0.1`` (DNS rebinding) sends a foreign ``Host``. A viewer
must therefore refuse requests whose ``Host`` is not its own address and websocket upgrades whose ``Origin`` is
not its own page: :class:`RequestCheck` holds those rules.

viser (1.1.1) runs its own ``websockets`` server and offers no option or public hook to check either header.
:func:`checked_viser_server` puts the check inside that server, at its one seam: viser's server thread opens it
with ``websockets.asyncio.server.serve(..., process_request=...)``, and ``process_request`` runs on every request
(plain HTTP and websocket upgrade alike) before viser answers it. While viser starts, that function is replaced, for
viser's call alone, by one that serves viser on a socket bound to the viewer's own address (so a port in use is
refused with the fix instead of viser moving to the next port) and runs :meth:`RequestCheck.check` ahead of viser's
``process_request``. The viewer thus listens on one port, the one it shows, and every request to it is checked;
there is no second, unguarded port.
"""

from __future__ import annotations

import http
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Sequence

__all__ = [
    "LOOPBACK",
    "VISER_VERSIONS",
    "RequestCheck",
    "allowed_hosts",
    "bind_socket",
    "check_address",
    "checked_viser_server",
]

LOOPBACK = ("127.0.0.1", "localhost", "::1")
"""Names of the loopback address; a viewer bound to one of them answers to all of them."""

VISER_VERSIONS = ("1.1.1",)
"""viser releases whose server :func:`checked_viser_server` was read against and tested with."""

_LOG = logging.getLogger(__name__)
_WARNING_INTERVAL = 5.0  # s between two log lines about refused requests
_VISER_HOOK_LOCK = threading.Lock()  # one viser server starts at a time while websockets' serve is replaced


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


class RequestCheck:
    """The rules of who may talk to a viewer at ``host:port``, and a count of the requests refused.

    A request passes with exactly one ``Host`` header among :attr:`allowed_hosts` and, if it has an ``Origin``
    (browsers send one with every websocket upgrade and cross-origin request), exactly one among
    :attr:`allowed_origins`. Refusals are counted and logged, one line at most every few seconds.

    Attributes:
        allowed_hosts, allowed_origins: the header values accepted.
        refused: requests refused so far.
    """

    def __init__(self, host: str, port: int):
        self.host, self.port = host, int(port)
        self.allowed_hosts = allowed_hosts(host, self.port)
        self.allowed_origins = frozenset(f"http://{name}" for name in self.allowed_hosts)
        self.refused = 0
        self._last_warning = -float("inf")
        self._unreported = 0
        self._lock = threading.Lock()

    def check(self, hosts: Sequence[str], origins: Sequence[str]) -> str | None:
        """Why a request with these ``Host`` and ``Origin`` header values is refused, or ``None`` to let it through."""
        if len(hosts) != 1 or hosts[0] not in self.allowed_hosts:
            why = f"unexpected Host {', '.join(hosts)[:80]!r}"
        elif len(origins) > 1 or (origins and origins[0] not in self.allowed_origins):
            why = f"cross-origin request from {', '.join(origins)[:80]!r}"
        else:
            return None
        with self._lock:
            self.refused += 1
            self._unreported += 1
            now = time.monotonic()
            if now - self._last_warning >= _WARNING_INTERVAL:
                _LOG.warning("viewer on port %d refused %d request(s) (last: %s)", self.port, self._unreported, why)
                self._last_warning, self._unreported = now, 0
        return why


def checked_viser_server(host: str, port: int, label: str | None = None):
    """A started ``viser.ViserServer`` listening on ``host:port`` whose every request passes a :class:`RequestCheck`.

    The check runs inside viser's own ``websockets`` server (see the module docstring for the seam), ahead of
    viser's handling; a refused request gets ``403 Forbidden`` with the reason. viser's server thread opens its
    server during ``ViserServer()``, so the replacement of ``websockets.asyncio.server.serve`` lasts exactly that
    long, under a lock, and acts on viser's call only (any other caller gets websockets' own ``serve``).

    Args:
        host, port: where to listen (port 0 picks a free one: ``server.get_port()``); checked by
            :func:`check_address`, and a port in use raises OSError naming the fix.
        label: viser's panel title.

    Returns:
        ``(server, check)``: the viser server and the :class:`RequestCheck` guarding it.

    Raises:
        RuntimeError: the installed viser is not one of :data:`VISER_VERSIONS`, or its server no longer opens
            through ``websockets.asyncio.server.serve``; the message names the fix.
    """
    import viser  # deferred: the optional browser viewer
    import websockets.asyncio.server as websockets_server  # deferred: viser's server library, needed with it only

    if viser.__version__ not in VISER_VERSIONS:
        raise RuntimeError(
            f"viser {viser.__version__} is installed, but the viewer checks requests inside viser's server as of "
            f"viser {', '.join(VISER_VERSIONS)} only: pip install viser=={VISER_VERSIONS[-1]} (or use --viewer meshcat)"
        )
    listening = bind_socket(host, port)
    check = RequestCheck(host, listening.getsockname()[1])
    websockets_serve = websockets_server.serve
    hooked = []

    def checked_process_request(viser_process_request):
        def process_request(connection, request):
            why = check.check(request.headers.get_all("Host"), request.headers.get_all("Origin"))
            if why is not None:
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"403 Forbidden: {why}\n")
            return None if viser_process_request is None else viser_process_request(connection, request)

        return process_request

    def serve(handler, *args, process_request=None, **options):
        if hooked or getattr(handler, "__module__", None) != "viser.infra._infra":
            return websockets_serve(handler, *args, process_request=process_request, **options)
        hooked.append(handler)
        return websockets_serve(
            handler, sock=listening, process_request=checked_process_request(process_request), **options
        )

    try:
        with _VISER_HOOK_LOCK:
            websockets_server.serve = serve
            try:
                server = viser.ViserServer(host=host, port=check.port, label=label, verbose=False)
            finally:
                websockets_server.serve = websockets_serve
    except BaseException:
        listening.close()
        raise
    if not hooked or server.get_port() != check.port:
        server.stop()
        listening.close()
        raise RuntimeError(
            f"viser {viser.__version__}'s server did not open through websockets.asyncio.server.serve, so the "
            f"viewer cannot check its requests: pip install viser=={VISER_VERSIONS[-1]} (or use --viewer meshcat)"
        )
    return server, check
