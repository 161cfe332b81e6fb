"""A CAN bus shared between processes over loopback (docs/deployment.md "A shared bus
between processes"): python-can-remote's server, wrapped — never re-implemented.

* :class:`BusServer` hosts one python-can bus (virtual by default) and shares it with
  clients that open ``can.Bus(channel='ws://127.0.0.1:PORT/', interface='remote')``. It binds
  127.0.0.1 unless told otherwise, and refuses every WebSocket upgrade that carries an
  ``Origin`` header: browsers always send one, python-can-remote's client never does, and the
  server has no authentication — a web page could otherwise open ``ws://127.0.0.1:PORT/``
  and send NMT commands to the rig.
* Closing any python-can bus once (python-can-remote's client raises from ``shutdown`` when
  the server already closed the connection, and again from ``__del__``) is
  :func:`rsra.canbus.shutdown_bus`, shared with the simulator.
"""
from __future__ import annotations

import ipaddress
import logging
import threading


log = logging.getLogger(__name__)

DEFAULT_PORT = 54701  # python-can-remote's own default
LOOPBACK = "127.0.0.1"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _handler_class():
    from can_remote.server import ClientRequestHandler

    class NoBrowserHandler(ClientRequestHandler):
        """python-can-remote's handler, refusing WebSocket upgrades from web pages."""

        refused = 0

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            upgrade = self.headers.get("Upgrade", "").lower() == "websocket"
            if upgrade and self.headers.get("Origin") is not None:
                type(self).refused += 1
                log.warning("refused a WebSocket upgrade from origin %r (%s)",
                            self.headers.get("Origin"), self.address_string())
                self.send_error(403, "WebSocket upgrades from a web page (Origin header) "
                                "are refused")
                return
            super().do_GET()

    return NoBrowserHandler


def _server_class():
    from can_remote.server import RemoteServer

    class Server(RemoteServer):
        """python-can-remote's server with the handler above; a client's broken connection
        is one log line, not a traceback on the console (socketserver's default)."""

        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            self.RequestHandlerClass = _handler_class()

        def handle_error(self, request, client_address) -> None:
            import sys

            e = sys.exc_info()[1]
            log.info("connection from %s ended: %s: %s", client_address,
                     type(e).__name__, e)

    return Server


def _quiet_disconnects(args: threading.ExceptHookArgs) -> None:
    """python-can-remote's per-client sender thread raises BrokenPipeError/ConnectionResetError
    when a client goes away mid-frame: a disconnect, logged in one line, not a traceback."""
    if issubclass(args.exc_type, (BrokenPipeError, ConnectionResetError)):
        log.info("a client disconnected while a frame was sent to it (%s)", args.exc_type.__name__)
        return
    _previous_excepthook(args)


_previous_excepthook = threading.excepthook


class BusServer:
    """python-can-remote's RemoteServer on ``host:port`` (port 0: a free one) sharing the
    python-can bus ``interface``/``channel``. ``start()`` serves from a thread; ``close()``
    closes every client connection and releases the port."""

    def __init__(self, host: str = LOOPBACK, port: int = DEFAULT_PORT,
                 interface: str = "virtual", channel: str = "rig"):
        # each client's bus in the server: python-can's virtual bus with the sender's own
        # copy first (rsra.canbus.EchoFirstVirtualBus, registered as "rsra_virtual")
        served = "rsra_virtual" if interface == "virtual" else interface
        self.server = _server_class()(host, port, interface=served, channel=channel)
        self.host, self.port = host, self.server.server_port
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}/"

    @property
    def refused(self) -> int:
        return self.server.RequestHandlerClass.refused

    def start(self) -> BusServer:
        threading.excepthook = _quiet_disconnects
        self._thread = threading.Thread(target=self.server.serve_forever, args=(0.1,),
                                        name="rsra-bus-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self.server.shutdown()  # serve_forever returns
            self._thread.join(timeout=2.0)
            self._thread = None
        for client in list(self.server.clients):  # each connection's own bus closes after
            try:
                client.close()
            except OSError:
                pass
        self.server.server_close()  # the port is released

    def __enter__(self) -> BusServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
