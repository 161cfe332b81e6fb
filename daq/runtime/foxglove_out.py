"""Live telemetry for the Foxglove app (`--foxglove [HOST:PORT]` on run, replay, demo).

* :class:`FoxgloveOutput` — one output of the service (rsra.daq.runtime.service.Outputs holds it: started
  before acquisition, closed on exit, its port released). It runs the Foxglove SDK's WebSocket
  server (PyPI ``foxglove-sdk``, protocol ``foxglove.sdk.v1``) and logs every telemetry key
  (``hub_loads``, ``channels``, ``innovations``, ``angles``, ``health``) on one channel each:
  topic ``<prefix>/<key>`` (as in `rsra export --mcap`), JSON messages with the JSON Schema of
  rsra.daq.analysis.export (derived from docs/telemetry.md), log time = the record's acquisition time ``t``
  (never the wall clock). Publishing never blocks: a record is handed to the SDK, which keeps
  at most ``backlog`` messages per client and drops the oldest beyond (it does not count
  them); a key nobody subscribes to is not even serialised.
* :class:`OriginGate` — the SDK's server has no Origin check, so it listens on an ephemeral
  loopback port and this small TCP relay listens on HOST:PORT in front of it: it reads the
  client's HTTP upgrade request and refuses (HTTP 403, counted) every request that carries a
  browser ``Origin`` header not named with ``--foxglove-allow-origin``, then relays bytes
  unchanged. Bounded: at most ``max_clients`` connections, a 16 KiB request head, blocking
  writes (a slow client stalls only its own relay, and the SDK then drops its oldest
  messages). The SDK's own port is reachable on loopback only and is not checked: a process
  on this machine can use it (as it can the front port), a web page would have to find it.
"""
from __future__ import annotations

import json
import logging
import socket
import sys
import threading
from collections.abc import Callable, Iterable

from rsra.daq.netaddr import is_loopback

log = logging.getLogger("rsra.foxglove")

DEFAULT_ADDRESS = "127.0.0.1:8765"
SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk 0.30 speaks (was foxglove.websocket.v1)
BACKLOG = 1024  # messages per client the SDK buffers (its default); the oldest go beyond
MAX_CLIENTS = 16
MAX_HEAD = 16384
HANDSHAKE_TIMEOUT_S = 5.0
FIX = "fix: give HOST:PORT, e.g. --foxglove 127.0.0.1:8765 (or --foxglove alone for that)"


class FoxgloveAddressError(ValueError):
    """A --foxglove address that cannot be used (one line naming the option and the fix)."""


def address_problem(text: str) -> tuple[str | None, tuple[str, int] | None]:
    """(why ``text`` is not a usable HOST:PORT, None) or (None, (host, port)); ``[v6]:PORT``
    for an IPv6 address, port 0 for any free port."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        return f"{text!r} is not HOST:PORT", None
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        p = int(port)
    except ValueError:
        return f"the port {port!r} of {text!r} is not a whole number", None
    if not 0 <= p <= 65535:
        return f"the port {p} of {text!r} is not 0 … 65535", None
    try:
        socket.getaddrinfo(host, p, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        return f"unknown host {host!r} in {text!r}", None
    return None, (host, p)


def parse_address(text: str) -> tuple[str, int]:
    """(host, port) of a --foxglove address; FoxgloveAddressError naming the fix."""
    why, addr = address_problem(text)
    if why:
        raise FoxgloveAddressError(f"--foxglove: {why}; {FIX}")
    assert addr is not None  # no problem: an address
    return addr


def add_options(p) -> None:
    """--foxglove [HOST:PORT] and --foxglove-allow-origin ORIGIN on an argparse parser."""
    import argparse

    def address(text: str) -> str:
        why, _ = address_problem(text)
        if why:
            raise argparse.ArgumentTypeError(f"{why}; {FIX}")
        return text

    p.add_argument("--foxglove", nargs="?", const=DEFAULT_ADDRESS, default=None,
                   type=address, metavar="HOST:PORT",
                   help=f"also serve the telemetry to the Foxglove app (Foxglove WebSocket, "
                   f"{SUBPROTOCOL}); default {DEFAULT_ADDRESS} (loopback) when given alone; "
                   "port 0 picks a free port")
    p.add_argument("--foxglove-allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="let a web page of this origin connect (e.g. https://app.foxglove.dev); "
                   "by default every connection carrying a browser Origin header is refused "
                   "(repeatable)")


def check_option(args) -> None:
    """A taken --foxglove port refused before anything starts (one line, exit 2)."""
    if getattr(args, "foxglove", None):
        check_address(*parse_address(args.foxglove))



def risk_line(host: str, port: int) -> str | None:
    """The warning for a non-loopback bind (None on loopback)."""
    if is_loopback(host):
        return None
    return (f"warning: --foxglove {host}:{port} is not loopback: anyone who can reach this "
            "port reads the rig's telemetry (no authentication, no encryption; read-only: "
            "nothing can be sent to the rig). Firewall it or use a VPN (docs/deployment.md)")


def bind_front(host: str, port: int) -> socket.socket:
    """The listening socket on HOST:PORT; FoxgloveAddressError naming the fix when taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        family = info[0][0]
        addr = info[0][4]
    except socket.gaierror:
        addr = (host, port)
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(addr)
        s.listen(MAX_CLIENTS)
    except OSError as e:
        s.close()
        why = "the port is in use (another rsra --foxglove, or a Foxglove bridge?)" \
            if e.errno in (98, 48, 10048) else (e.strerror or str(e))
        raise FoxgloveAddressError(
            f"--foxglove {host}:{port}: cannot listen ({why}); fix: stop that process or give "
            "a free port, e.g. --foxglove 127.0.0.1:8766") from None
    return s


def check_address(host: str, port: int) -> None:
    """Refuse a taken HOST:PORT before anything starts (the service binds it again)."""
    bind_front(host, port).close()


def _origin(head: bytes) -> str | None:
    """The Origin of an HTTP request head (Sec-WebSocket-Origin of old drafts too)."""
    for line in head.split(b"\r\n")[1:]:
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() in (b"origin", b"sec-websocket-origin"):
            return value.strip().decode("latin-1")
    return None


class OriginGate:
    """A TCP relay on a listening socket to ``target`` that refuses browser Origins."""

    def __init__(self, sock: socket.socket, target: tuple[str, int],
                 allowed_origins: Iterable[str] = (), max_clients: int = MAX_CLIENTS):
        self.sock = sock
        self.target = target
        self.allowed = frozenset(o.rstrip("/") for o in allowed_origins)
        self.max_clients = max_clients
        self.refused = 0  # requests refused for their Origin
        self.turned_away = 0  # connections refused beyond max_clients or with a bad head
        self.connections = 0  # relayed connections so far
        self._lock = threading.Lock()
        self._open: dict[int, tuple[socket.socket, ...]] = {}
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._warned: set[str] = set()  # origins refused and logged (once each, bounded)
        self._accept = threading.Thread(target=self._accept_loop, name="rsra-foxglove-gate",
                                        daemon=True)
        self._accept.start()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._open)

    def _accept_loop(self) -> None:
        n = 0
        while not self._stop.is_set():
            try:
                c, _ = self.sock.accept()
            except OSError:
                if self._stop.is_set():
                    return
                continue
            with self._lock:
                full = len(self._open) >= self.max_clients
                if not full:
                    n += 1
                    self._open[n] = (c,)
                    self._threads = [t for t in self._threads if t.is_alive()]
            if full:
                self.turned_away += 1
                c.close()
                continue
            t = threading.Thread(target=self._serve, args=(n, c), name="rsra-foxglove-relay",
                                 daemon=True)
            with self._lock:
                self._threads.append(t)
            t.start()

    def _serve(self, n: int, c: socket.socket) -> None:
        up = None
        try:
            c.settimeout(HANDSHAKE_TIMEOUT_S)
            data = b""
            while b"\r\n\r\n" not in data:
                chunk = c.recv(4096)
                if not chunk or len(data) + len(chunk) > MAX_HEAD:
                    self.turned_away += 1
                    return
                data += chunk
            origin = _origin(data.split(b"\r\n\r\n", 1)[0])
            if origin is not None and origin.rstrip("/") not in self.allowed:
                self.refused += 1
                first = origin not in self._warned and len(self._warned) < 32
                if first:
                    self._warned.add(origin)
                log.log(logging.WARNING if first else logging.DEBUG,
                        "refused a Foxglove WebSocket connection from a web page of origin %r; "
                        "fix: if that is your Foxglove app, give --foxglove-allow-origin %s",
                        origin, origin)
                body = b"Connections from a web page (Origin header) are refused; see rsra " \
                       b"--foxglove-allow-origin.\n"
                c.sendall(b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\n"
                          b"Content-Length: " + str(len(body)).encode() +
                          b"\r\nConnection: close\r\n\r\n" + body)
                return
            up = socket.create_connection(self.target, timeout=HANDSHAKE_TIMEOUT_S)
            with self._lock:
                if self._stop.is_set():
                    return
                self._open[n] = (c, up)
                self.connections += 1
            c.settimeout(None)
            up.settimeout(None)
            up.sendall(data)
            back = threading.Thread(target=self._pump, args=(up, c), daemon=True,
                                    name="rsra-foxglove-relay")
            back.start()
            self._pump(c, up)
            back.join()
        except OSError as e:
            log.debug("foxglove relay: %s", e)
        finally:
            with self._lock:
                self._open.pop(n, None)
            for s in (c, up):
                if s is not None:
                    s.close()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                b = src.recv(65536)
                if not b:
                    break
                dst.sendall(b)  # blocks on a slow reader: nothing is buffered here
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        with self._lock:
            socks = [s for pair in self._open.values() for s in pair]
            threads = list(self._threads)
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._accept.join(timeout=2.0)
        for t in threads:
            t.join(timeout=2.0)


class FoxgloveOutput:
    """The Foxglove WebSocket server of one service run (see the module doc)."""

    def __init__(self, prefix: str, host: str, port: int, allowed_origins: Iterable[str] = (),
                 backlog: int | None = None,
                 announce: Callable[[str], None] | None = None):
        import foxglove

        from rsra.daq.runtime.schema import FIELDS, json_schema

        if not log.isEnabledFor(logging.DEBUG):  # the SDK's own start/stop lines
            logging.getLogger("foxglove").setLevel(logging.WARNING)
        front = bind_front(host, port)  # first: a taken port is refused before anything runs
        self.server = None
        self.gate: OriginGate | None = None
        try:
            self._ctx = foxglove.Context()  # our own: nothing global, nothing left behind
            self.server = foxglove.start_server(
                name=f"rsra {prefix}", host="127.0.0.1", port=0, context=self._ctx,
                message_backlog_size=backlog or BACKLOG)
            self.channels = {
                key: foxglove.Channel(
                    f"{prefix}/{key}", message_encoding="json", context=self._ctx,
                    schema=foxglove.Schema(name=f"rsra.{key}", encoding="jsonschema",
                                           data=json.dumps(json_schema(key)).encode()))
                for key in FIELDS}  # every key the service publishes (docs/telemetry.md)
            self.gate = OriginGate(front, ("127.0.0.1", self.server.port), allowed_origins)
        except BaseException:
            front.close()
            if self.server is not None:
                self.server.stop()
            raise
        bound = front.getsockname()
        self.host, self.port = host, bound[1]
        self.published = 0
        self.errors = 0
        self._last_ns = 0
        shown = f"[{host}]" if ":" in host else host
        self.url = f"ws://{shown}:{self.port}"
        (announce or _stderr)(f"Foxglove WebSocket on {self.url} (open it in Foxglove: "
                              f"Open connection → Foxglove WebSocket)")
        risk = risk_line(host, self.port)
        if risk:
            (announce or _stderr)(risk)

    def publish(self, key: str, payload: dict) -> None:
        """Hand one record to the SDK (never blocks; skipped when nobody subscribes)."""
        ch = self.channels.get(key)
        if ch is None:
            return
        self._last_ns = _log_time_ns(payload, self._last_ns)
        try:
            if not ch.has_sinks():
                return
            ch.log(_dumps(payload).encode(), log_time=self._last_ns)
            self.published += 1
        except Exception as e:  # never let a viewer's output stop the service
            self.errors += 1
            log.debug("foxglove publish %s failed: %s", key, e)

    def health(self) -> dict:
        g = self.gate
        return {"clients": g.clients if g else 0, "connections": g.connections if g else 0,
                "refused": g.refused if g else 0, "published": self.published,
                "errors": self.errors}

    def close(self) -> None:
        if self.gate is not None:
            self.gate.close()
            self.gate = None
        if self.server is not None:
            for ch in self.channels.values():
                ch.close()
            self.server.stop()
            self.server = None


def _log_time_ns(payload: dict, last: int) -> int:
    from rsra.daq.runtime.schema import log_time_ns

    return log_time_ns(payload, last)


def _dumps(payload: dict) -> str:
    from rsra.daq.jsonout import dumps

    return dumps(payload)


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
