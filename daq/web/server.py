"""The `rsra web` gateway: an aiohttp server that is just another Zenoh client.

It subscribes to ``<prefix>/**`` (a bounded ring, like `rsra listen`), keeps a bounded
history, and serves: the Open MCT files (``/openmct/…``), the rsra plugin and page (``/``,
``/rsra/…``), the telemetry dictionary (``/api/dictionary``), history (``/api/history``),
real-time points over a WebSocket (``/ws``) and its counters (``/status``).

Every HTTP and WebSocket request must carry an allowed ``Host`` (the bound address and
port, ``localhost`` on loopback, names given with ``--allow-host``) and, when it carries an
``Origin``, the same origin: a page from anywhere else gets 403 (no DNS rebinding, no
cross-site WebSocket). Each browser has a bounded queue of point batches; when it cannot
keep up, the oldest batch is dropped and its points counted (``/status``, the exit line):
a slow browser never slows the gateway or the service.

Every payload received (subscription and the late joiner's ``state/*`` replies) goes through
a :class:`~rsra.daq.payload_guard.PayloadGuard` first: a bad one is counted (``/status``
``bad_messages``, per key with its reason) and dropped, never fatal. The requests that cost
(history, WebSocket browsers) are bounded in number: beyond it the answer is 503 with
``Retry-After`` at once, counted (``/status`` ``shed``), so the gateway stays responsive
under a flood of requests.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

from aiohttp import WSMsgType, web

from rsra.daq.jsonout import dumps
from rsra.daq.netaddr import is_loopback
from rsra.daq.payload_guard import PayloadGuard, Received
from rsra.daq.web.dictionary import BandEnvelope, Dictionary, envelope, points
from rsra.daq.web.history import (History, HistoryFileError, TelemetryFile, merged_query,
                                  points_of)

log = logging.getLogger("rsra.web")

HERE = Path(__file__).resolve().parent
STATIC_DIR = HERE / "web-static"
OPENMCT_DIR = HERE / "openmct-dist"  # filled by `make web` (git-ignored)
FLUSH_S = 0.1  # batches sent to each browser this often
MAX_BATCHES = 50  # per browser: 5 s of batches
MAX_BATCH_POINTS = 20000  # per batch
MAX_SUBSCRIPTIONS = 2000  # per browser
# keys published at every sample: a gap in `seq` is a message missed (as `rsra listen` counts)
EVERY_SAMPLE = ("hub_loads", "channels")
# history requests answered at once (each parses up to MAX_POINTS messages per source, off
# the event loop); one more gets 503 with Retry-After (2 000 at once used to stall the
# gateway for ~30 s)
MAX_HISTORY_REQUESTS = 4
# history requests that wait for one of those (an Open MCT page asks for every object it shows
# at once: a few dozen); one more than these gets the 503
MAX_HISTORY_WAITING = 128
MAX_BROWSERS = 64  # WebSocket connections at once (each holds a bounded queue)
RETRY_AFTER_S = 1


def openmct_dir() -> Path | None:
    """Where the Open MCT files are, or None (run `make web`)."""
    return OPENMCT_DIR if (OPENMCT_DIR / "openmct.js").is_file() else None



def allowed_hosts(host: str, port: int, extra: Sequence[str] = ()) -> set[str]:
    """The ``Host`` header values accepted (lower case, with the port)."""
    names = {host.lower()}
    if is_loopback(host):
        names |= {"localhost", "127.0.0.1", "[::1]"}
    names |= {h.lower() for h in extra}
    out = set()
    for n in names:
        if ":" in n and not n.startswith("["):
            n = f"[{n}]"  # an IPv6 literal
        out.add(f"{n}:{port}")
        if port == 80:
            out.add(n)
    return out


def request_allowed(headers, hosts: set[str]) -> str | None:
    """None when the request may go on, else why not (Host or Origin)."""
    host = (headers.get("Host") or "").lower()
    if host not in hosts:
        return f"Host {host!r} not allowed"
    origin = headers.get("Origin")
    if origin is not None and origin.lower() != f"http://{host}":
        return f"cross-origin request from {origin!r}"
    return None


class Client:
    """One browser's WebSocket: its subscriptions and a bounded queue of point batches."""

    def __init__(self, ws, max_batches: int = MAX_BATCHES,
                 max_batch_points: int = MAX_BATCH_POINTS):
        self.ws = ws
        self.subs: set[str] = set()
        self.batch: list = []
        self.queue: deque[list] = deque()
        self.max_batches = max_batches
        self.max_batch_points = max_batch_points
        self.wake = asyncio.Event()
        self.dropped = 0  # points dropped (queue or batch full)
        self.sent = 0  # points sent
        self.max_depth = 0
        self.closing = False

    def offer(self, pts: list[tuple[str, dict]]) -> None:
        for pid, d in pts:
            if pid in self.subs:
                if len(self.batch) >= self.max_batch_points:
                    self.dropped += 1
                else:
                    self.batch.append([pid, d])

    def flush(self) -> None:
        if not self.batch:
            return
        if len(self.queue) >= self.max_batches:
            self.dropped += len(self.queue.popleft())
        self.queue.append(self.batch)
        self.max_depth = max(self.max_depth, len(self.queue))
        self.batch = []
        self.wake.set()

    async def writer(self) -> None:
        """Sends the queued batches until :meth:`stop`. Never cancelled mid-send: aiohttp
        sends a compressed frame in a shielded task of its own, and cancelling the send
        leaves that task to fail unobserved when the browser has gone ("Task exception was
        never retrieved")."""
        try:
            while not self.closing:
                await self.wake.wait()
                self.wake.clear()
                while self.queue and not self.closing:
                    b = self.queue.popleft()
                    # strict JSON: a value a peer's record overflows to ±inf is null
                    await self.ws.send_str(dumps({"points": b}))
                    self.sent += len(b)
        except ConnectionResetError:  # aiohttp's ClientConnectionResetError: the browser left
            pass

    async def stop(self, task: asyncio.Task) -> None:
        """Ends the writer after its current send (bounded: cancelled after 5 s)."""
        self.closing = True
        self.wake.set()
        try:
            await asyncio.wait_for(task, timeout=5.0)
        except (asyncio.TimeoutError, asyncio.CancelledError, ConnectionResetError):
            pass


class Gateway:
    """The state of one `rsra web`: dictionary, history, files, browsers, counters."""

    def __init__(self, dic: Dictionary, history: History, files: list[TelemetryFile],
                 hosts: set[str], *, guard: PayloadGuard, static_dir: Path = STATIC_DIR,
                 openmct: Path | None = None, max_batches: int = MAX_BATCHES,
                 max_history_requests: int = MAX_HISTORY_REQUESTS,
                 max_history_waiting: int = MAX_HISTORY_WAITING,
                 max_browsers: int = MAX_BROWSERS):
        self.dic = dic
        #: every received payload is checked here first (the telemetry keys' schemas)
        self.payload_guard = guard
        self.history = history
        self.files = files
        self.hosts = hosts
        self.static_dir = static_dir
        self.openmct = openmct
        self.max_batches = max_batches
        self.clients: set[Client] = set()
        self.received: dict[str, int] = {}
        self.ignored = 0  # messages on keys without a schema (not telemetry rsra publishes)
        self.refused = 0
        #: requests of each costly kind at most at once, and those now being answered
        self.limits = {"history": max_history_requests, "browsers": max_browsers}
        self.busy = dict.fromkeys(self.limits, 0)
        self.shed = dict.fromkeys(self.limits, 0)  # answered 503 (over the limit)
        #: requests of each kind that may wait for a free place (beyond: 503), those waiting
        self.max_waiting = {"history": max_history_waiting, "browsers": 0}
        self.waiting = dict.fromkeys(self.limits, 0)
        self._free: dict[str, asyncio.Condition] = {}
        self.dropped_closed = 0  # points dropped by browsers that have gone
        self.sent_closed = 0
        self.seq: dict[str, list[int]] = {}  # key -> [first, last, received in order]
        #: the live band lines, reduced to their envelope (dictionary.BandEnvelope)
        self.bands = BandEnvelope()
        self.started = time.monotonic()

    # -- telemetry in --------------------------------------------------------------------
    @property
    def bad_messages(self) -> int:
        return self.payload_guard.bad_total

    def ingest(self, key: str, data: Received | str) -> None:
        """One received message on ``key`` (under the prefix), as received: checked by the
        guard, then counted, kept for history and offered to the browsers."""
        if key not in self.payload_guard.validators:  # not telemetry rsra publishes: not kept
            self.ignored += 1
            return
        got = self.payload_guard.receive(
            key, data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data)
        if got is None:
            return
        payload = got.payload
        text = dumps(payload)  # (what was received, compact; non-finite numbers as null)
        self.received[key] = self.received.get(key, 0) + 1
        seq = payload.get("seq")
        if key in EVERY_SAMPLE and isinstance(seq, int) and not isinstance(seq, bool):
            s = self.seq.get(key)
            if s is None or seq < s[0]:  # the first, or a restarted service
                self.seq[key] = [seq, seq, 1]
            elif seq > s[1]:
                s[1] = seq
                s[2] += 1
        t = payload.get("t")
        if isinstance(t, (int, float)) and not isinstance(t, bool):
            self.history.add(key, float(t), text)
        pts = self.bands.reduce(points(self.dic, key, payload))
        if pts:
            for c in self.clients:
                c.offer(pts)

    def flush(self) -> None:
        for c in self.clients:
            c.flush()

    # -- counters ------------------------------------------------------------------------
    def status(self) -> dict:
        clients = [{"subscriptions": len(c.subs), "sent": c.sent, "dropped": c.dropped,
                    "queue_depth": len(c.queue), "queue_max_depth": c.max_depth,
                    "queue_size": c.max_batches} for c in self.clients]
        span = self.history.span()
        return {
            "rig": self.dic.rig, "prefix": self.dic.prefix,
            "uptime_s": round(time.monotonic() - self.started, 1),
            "received": dict(self.received),
            "missed": {k: s[1] - s[0] + 1 - s[2] for k, s in self.seq.items()},
            "bad_messages": self.bad_messages,
            "guard": self.payload_guard.as_json(), "guard_lines": self.payload_guard.lines(),
            "ignored": self.ignored,
            "history": {"seconds": self.history.history_s, "messages": self.history.count(),
                        "bytes": self.history.bytes, "evicted": self.history.evicted,
                        "caps": self.history.caps,
                        "span": None if span is None else list(span)},
            "files": [{"path": str(f.path), "t0": f.t0, "t1": f.t1, "records": f.counts}
                      for f in self.files],
            "browsers": clients,
            "points_sent": self.sent_closed + sum(c.sent for c in self.clients),
            "points_dropped": self.dropped_closed + sum(c.dropped for c in self.clients),
            "refused": self.refused,
            "shed": dict(self.shed), "waiting": dict(self.waiting),
        }

    # -- HTTP ----------------------------------------------------------------------------
    @web.middleware
    async def guard(self, request: web.Request, handler):
        why = request_allowed(request.headers, self.hosts)
        if why is not None:
            self.refused += 1
            log.warning("refused %s %s: %s", request.method, request.path, why)
            return web.Response(status=403, text=f"forbidden: {why}\n")
        kind = COSTLY.get(request.path)
        if kind is None:
            resp = await handler(request)
        elif (self.busy[kind] >= self.limits[kind]
              and self.waiting[kind] >= self.max_waiting[kind]):
            self.shed[kind] += 1
            resp = web.json_response(
                {"error": "busy", "detail": f"{self.limits[kind]} {kind} requests at once and "
                 f"{self.max_waiting[kind]} waiting; retry later"}, status=503,
                headers={"Retry-After": str(RETRY_AFTER_S)})
        else:
            free = self._free.setdefault(kind, asyncio.Condition())
            if self.busy[kind] >= self.limits[kind]:  # wait for a place (bounded above)
                self.waiting[kind] += 1
                try:
                    async with free:
                        await free.wait_for(lambda: self.busy[kind] < self.limits[kind])
                finally:
                    self.waiting[kind] -= 1
            self.busy[kind] += 1
            try:
                resp = await handler(request)
            finally:
                self.busy[kind] -= 1
                async with free:
                    free.notify()
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("Referrer-Policy", "no-referrer")
        return resp

    async def index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(self.static_dir / "index.html")

    async def dictionary(self, request: web.Request) -> web.Response:
        return web.json_response(self.dic.as_json())

    async def status_view(self, request: web.Request) -> web.Response:
        return web.json_response(self.status(), dumps=dumps)

    async def history_view(self, request: web.Request) -> web.Response:
        q = request.query
        mid = q.get("id", "")
        try:
            start = float(q.get("start", "0")) / 1000.0
            end = float(q.get("end", "inf")) / 1000.0
        except ValueError:
            raise web.HTTPBadRequest(text="start and end: milliseconds\n") from None
        if mid not in self.dic.by_id:
            raise web.HTTPNotFound(text=f"no telemetry {mid!r}\n")
        loop = asyncio.get_running_loop()
        texts = self.history.texts(self.dic, mid, start, end)  # taken here, parsed off the loop
        mem = await loop.run_in_executor(None, points_of, self.dic, mid, texts)
        sources: list[Callable[[], list[dict]]] = [lambda: mem]
        for f in self.files:
            try:
                got = await loop.run_in_executor(None, f.query, self.dic, mid, start, end)
            except HistoryFileError as e:  # the file changed under us
                log.warning("%s", e)
                continue
            def answer(got: list[dict] = got) -> list[dict]:
                return got

            sources.append(answer)
        out = envelope(mid, merged_query(sources))
        if q.get("strategy") == "latest":
            out = out[-1:]
        return web.json_response(out, dumps=dumps)  # strict: overflows are null

    async def websocket(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=1 << 20)
        await ws.prepare(request)
        c = Client(ws, self.max_batches)
        self.clients.add(c)
        writer = asyncio.create_task(c.writer())
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                try:
                    m = json.loads(msg.data)
                except ValueError:
                    continue
                if not isinstance(m, dict):
                    continue
                for pid in _ids(m.get("subscribe")):
                    if pid in self.dic.by_id and len(c.subs) < MAX_SUBSCRIPTIONS:
                        c.subs.add(pid)
                for pid in _ids(m.get("unsubscribe")):
                    c.subs.discard(pid)
        finally:
            self.clients.discard(c)
            await c.stop(writer)
            self.dropped_closed += c.dropped + sum(len(b) for b in c.queue) + len(c.batch)
            self.sent_closed += c.sent
        return ws

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self.guard], client_max_size=1 << 16)
        app.router.add_get("/", self.index)
        app.router.add_get("/api/dictionary", self.dictionary)
        app.router.add_get("/api/history", self.history_view)
        app.router.add_get("/status", self.status_view)
        app.router.add_get("/ws", self.websocket)
        app.router.add_static("/rsra/", self.static_dir, follow_symlinks=False)
        if self.openmct is not None:
            app.router.add_static("/openmct/", self.openmct, follow_symlinks=False)
        return app


# the paths whose requests are bounded in number (Gateway.limits)
COSTLY = {"/api/history": "history", "/ws": "browsers"}


def _ids(v) -> list[str]:
    if isinstance(v, str):
        return [v]
    if isinstance(v, list):
        return [x for x in v if isinstance(x, str)]
    return []


async def serve(gw: Gateway, host: str, port: int, zenoh_conf, prefix: str,
                on_ready=None, stop: asyncio.Event | None = None) -> None:
    """Run until ``stop`` is set: the HTTP server and the Zenoh subscription."""
    import zenoh

    stop = stop or asyncio.Event()
    runner = web.AppRunner(gw.app(), access_log=None, handle_signals=False)
    await runner.setup()
    try:
        site = web.TCPSite(runner, host, port, reuse_address=True)
        await site.start()
        bound = runner.addresses[0][1] if runner.addresses else port
        loop = asyncio.get_running_loop()
        session = await loop.run_in_executor(None, zenoh.open, zenoh_conf)
        try:
            sub = session.declare_subscriber(f"{prefix}/**", zenoh.handlers.RingChannel(8192))
            plen = len(prefix) + 1

            def late_joiner():  # the latest angles and health, at once
                out = []
                for reply in session.get(f"{prefix}/state/*", timeout=2.0):
                    if reply.ok is not None:
                        out.append((str(reply.ok.key_expr)[plen:].replace("state/", "", 1),
                                    reply.ok.payload))
                return out

            for key, data in await loop.run_in_executor(None, late_joiner):
                if key in ("angles", "health"):
                    gw.ingest(key, data)
            if on_ready is not None:
                on_ready(bound)
            next_flush = time.monotonic()
            while not stop.is_set():
                n = 0
                while n < 20000 and (s := sub.handler.try_recv()) is not None:
                    n += 1
                    key = str(s.key_expr)[plen:]
                    if key.startswith("state/") or key == "alive":
                        continue
                    gw.ingest(key, s.payload)
                now = time.monotonic()
                if now >= next_flush:
                    gw.flush()
                    next_flush = now + FLUSH_S
                try:
                    await asyncio.wait_for(stop.wait(), 0.02)
                except asyncio.TimeoutError:
                    pass
            sub.undeclare()
        finally:
            await loop.run_in_executor(None, session.close)
    finally:
        await runner.cleanup()
