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

import logging
import threading
from collections.abc import Callable
from typing import Any

import can


log = logging.getLogger(__name__)

DEFAULT_PORT = 54701  # python-can-remote's own default
LOOPBACK = "127.0.0.1"



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


class ReconnectingBus(can.BusABC):
    """A bus the reader opened itself, opened again when it fails (docs/reliability.md "The
    bus goes away"): the shared bus's server stopped and started again on the same port, an
    interface taken down and up. Every user — the bus thread's reads, the SYNC producer, the
    master's NMT/SDO — holds this one object; a read or send that fails with a bus failure
    (:func:`rsra.canbus.bus_failure`) drops the inner bus, and the next read or send opens a
    new one (paced by the callers' growing pauses: the tap's 10 ms … 1 s, the SYNC
    producer's). Anything else is passed on unchanged."""

    def __init__(self, opener: Callable[[], can.BusABC], **kwargs: Any):
        self._opener = opener
        self._inner: can.BusABC | None = opener()  # the first open fails as before
        self._lock = threading.Lock()
        self.reopened = 0  # times the bus was opened again after a failure
        self.lost = 0  # times it failed
        super().__init__(channel=str(getattr(self._inner, "channel_info", "")), **kwargs)
        self.channel_info = f"reconnecting {getattr(self._inner, 'channel_info', '')}"

    def _current(self) -> can.BusABC:
        with self._lock:
            if self._inner is None:
                try:
                    self._inner = self._opener()
                except Exception as e:  # still gone: the caller's pause, then again
                    raise can.CanOperationError(f"the bus is still gone "
                                                f"({type(e).__name__}: {e})") from None
                self.reopened += 1
                log.warning("the bus is back: opened again (%d time%s)", self.reopened,
                            "s" if self.reopened != 1 else "")
            return self._inner

    def _failed(self, bus: can.BusABC, exc: BaseException) -> None:
        from rsra.canbus import bus_failure, shutdown_bus

        if not bus_failure(exc):
            return
        with self._lock:
            if self._inner is not bus:
                return  # another thread saw it first
            self._inner = None
            self.lost += 1
        log.warning("the bus failed (%s: %s); it is opened again when it is back",
                    type(exc).__name__, exc)
        shutdown_bus(bus)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        bus = self._current()
        try:
            return bus.recv(timeout)
        except Exception as e:
            self._failed(bus, e)
            raise

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False  # (recv is overridden: not called by python-can)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        bus = self._current()
        try:
            bus.send(msg, timeout)
        except Exception as e:
            self._failed(bus, e)
            raise

    def shutdown(self) -> None:
        from rsra.canbus import shutdown_bus

        with self._lock:
            bus, self._inner = self._inner, None
        if bus is not None:
            shutdown_bus(bus)
        super().shutdown()
