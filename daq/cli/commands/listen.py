"""`rsra listen`: the reference telemetry subscriber — a live table of any rig, or JSON lines.

Uses a ring-buffer handler (a slow terminal never backs up the publisher) and shows the
latest values, rates, missed samples (gaps in `seq`), staleness and node health.

Every message is untrusted: it goes through the payload guard (daq/payload_guard.py: size,
depth, UTF-8, strict JSON, the key's schema) before anything reads it; a bad one is counted
and shown ("N bad messages from <key> (last: why)"), never fatal, and every string shown in
the table is stripped of control characters and markup.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from rsra.config.units import axis_units, to_units
from rsra.daq.jsonout import dumps
from rsra.daq.cli.whose import Whose
from rsra.daq.payload_guard import printable
from rsra.estimator.verdict import held_window

if TYPE_CHECKING:
    from rich.console import RenderableType

    from rsra.daq.payload_guard import PayloadGuard, Received

AXES = ("X", "Y", "Z", "L", "M", "N")
MAX_KEYS = 256  # rows of the table; messages on further keys are counted together
MAX_TEXT = 200  # characters of one string from a payload shown


def _text(v: Any) -> str:
    """A value from a payload as table text: no control characters, no rich markup, bounded."""
    from rich.markup import escape

    s = v if isinstance(v, str) else str(v)
    if len(s) > MAX_TEXT:
        s = s[:MAX_TEXT - 1] + "…"
    return escape(printable(s))


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _vec6(v: Any) -> list[float | None]:
    """A six-component load from a payload: six numbers or None (missing, short, wrong)."""
    items = v if isinstance(v, list) else []
    return [_num(x) for x in items[:6]] + [None] * (6 - min(6, len(items)))


def _ms(v) -> str:
    """A latency for the view: 3 significant digits (0.827, 12.4), '—' when absent."""
    return "—" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.3g}"


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(name, help="live view of a rig's telemetry (or JSON lines)",
                       description="Subscribe to <prefix>/** and show the latest values, rates, "
                       "missed samples, staleness and node health.")
    common_options(p)
    p.add_argument("--prefix", default=None,
                   help="key prefix (default: the rig publishing, else the config's rsra/bench)")
    p.add_argument("--rig", default=None, metavar="NAME",
                   help="show the rig of this name (rig.name) among those publishing")
    p.add_argument("--key", action="append", default=[], metavar="K",
                   help="only this key under the prefix (repeatable), e.g. hub_loads")
    p.add_argument("--json", action="store_true", help="print one JSON object per message")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="endpoint to connect to (default: the config's listen endpoints)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh config file (TLS, user/password) instead of --zenoh-connect")
    from rsra.daq.cli.options import positive_float, positive_int

    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop after S seconds (exit 0)")
    p.add_argument("--count", type=positive_int, default=None, metavar="N",
                   help="stop after N messages")
    return p


# Missed messages are counted where the publication is regular (docs/telemetry.md): every
# sample for these keys (each missing seq), every n-th sample for `innovations` (n found as
# the greatest common divisor of the seq steps); `angles` and `health` are published on
# events and are never dropped by Zenoh (congestion control BLOCK): not counted.
EVERY_SAMPLE = ("hub_loads", "channels")
EVERY_NTH_SAMPLE = ("innovations",)
STALE_INTERVALS = 5  # a key's rate falls to 0 after this many of its intervals without one


class KeyStats:
    """Rate, missed messages (by seq, where the key is published regularly) and staleness of
    one key; bounded history."""

    def __init__(self, key: str = "") -> None:
        self.key = key.rsplit("/", 1)[-1]
        self.counted = self.key in EVERY_SAMPLE or self.key in EVERY_NTH_SAMPLE
        self.count = 0
        self.first_seq: int | None = None
        self.last_seq: int | None = None
        self.n_seq = 0  # messages with a seq, in order
        self.stride = 1 if self.key in EVERY_SAMPLE else 0  # 0: not known yet
        self.last_arrival = 0.0
        self.arrivals: deque[float] = deque(maxlen=256)
        self.latest: dict = {}

    @property
    def missed(self) -> int | None:
        """Messages never received between the first and the latest; None: not counted."""
        if not self.counted:
            return None
        if self.first_seq is None or self.last_seq is None or not self.stride:
            return 0
        return max(0, (self.last_seq - self.first_seq) // self.stride + 1 - self.n_seq)

    def add(self, payload: dict, now: float) -> None:
        self.count += 1
        seq = payload.get("seq") if isinstance(payload, dict) else None
        if self.counted and isinstance(seq, int) and not isinstance(seq, bool):
            self._seq(seq)
        self.last_arrival = now
        self.arrivals.append(now)
        self.latest = payload if isinstance(payload, dict) else {"value": payload}

    def _seq(self, seq: int) -> None:
        """A message's seq: the first, or a later one (a gap counts as missed; the stride of
        every n-th sample is the greatest common divisor of the steps)."""
        if self.first_seq is None or self.last_seq is None:  # (the two are set together)
            self.first_seq = self.last_seq = seq
            self.n_seq = 1
        elif seq > self.last_seq:
            if self.key not in EVERY_SAMPLE:
                self.stride = math.gcd(self.stride, seq - self.last_seq)
            self.last_seq = seq
            self.n_seq += 1

    def rate(self, now: float | None = None) -> float:
        """Messages per second over the recent arrivals; 0 once none has come for
        STALE_INTERVALS of their own interval (at least a second): a stopped service's keys
        fall to 0 instead of showing their last rate."""
        if len(self.arrivals) < 2:
            return 0.0
        span = self.arrivals[-1] - self.arrivals[0]
        if span <= 0:
            return 0.0
        interval = span / (len(self.arrivals) - 1)
        if now is not None and now - self.arrivals[-1] > max(1.0, STALE_INTERVALS * interval):
            return 0.0
        return 1.0 / interval


def _fmt(v, width: int = 9) -> str:
    if v is None or not math.isfinite(v):
        return "—".rjust(width)
    return f"{v:{width}.1f}"


def _keys_table(stats: dict[str, KeyStats], title: str, now: float):
    from rich.table import Table

    t = Table(title=f"rsra telemetry — {_text(title)}", expand=False)
    for col in ("key", "messages", "rate /s", "missed", "age s"):
        t.add_column(col, justify="right" if col != "key" else "left")
    for key in sorted(stats):
        s = stats[key]
        missed = s.missed
        t.add_row(_text(key), str(s.count), f"{s.rate(now):.1f}",
                  "—" if missed is None else str(missed), f"{now - s.last_arrival:.2f}")
    return t


def _hub_loads(h: dict, units: str) -> list[RenderableType]:
    """The latest hub_loads record: H, the static H and σ of the angles' part per axis, and
    its flags."""
    from rich.table import Table

    ht = Table(title="hub loads (" + _text(h.get("frame") or "body") + " axes)")
    ht.add_column("")
    u = axis_units(units)
    for i, ax in enumerate(AXES):
        ht.add_column(f"{ax} [{u[i]}]", justify="right")
    for label, field in (("filter H", "H"), ("static", "H_static"),
                         ("σ angles", "sigma_angles")):
        v = _vec6(h.get(field))
        vals = to_units(np.array([np.nan if x is None else x for x in v]), units).tolist()
        ht.add_row(label, *[_fmt(x) for x in vals])
    flags = [f for f in h.get("flags") or [] if f is not None]
    return [ht, *([f"flags: {_text(', '.join(flags))}"] if flags else [])]


def _degrees(x: Any, fmt: str) -> str:
    return "—" if x is None else f"{np.degrees(x):{fmt}}"


def _angles_table(a: dict):
    from rich.table import Table

    names = a.get("names") or []
    verdict = ("accepted" if a.get("accepted") else "held" if held_window(a)
               else f"rejected ({_text(a.get('reason'))})")
    at = Table(title=f"angles — {_text(a.get('mode'))} / {_text(a.get('content'))}: "
               f"{verdict}, {_text(a.get('determined'))} of {len(names)} determined")
    at.add_column("angle")
    at.add_column("deg", justify="right")
    at.add_column("σ_CR deg", justify="right")
    for n, x, s in zip(names, a.get("alpha") or [], a.get("sigma_cr") or []):
        at.add_row(_text(n), _degrees(x, "7.3f"), _degrees(s, "6.3f"))
    return at


def _why(a: dict) -> list[RenderableType]:
    """A rejected run's reason in one line each (records of older recordings carry
    neither)."""
    if a.get("accepted") or not (a.get("explanation") or a.get("hint")):
        return []
    lines: list[RenderableType] = [f"why: {_text(a.get('explanation') or a.get('detail'))}"]
    if a.get("hint"):
        lines.append(f"hint: {_text(a.get('hint'))}")
    return lines


def _angles(a: dict, units: str) -> list[RenderableType]:
    """The latest angles record: the angles, the advice (filter error: what would determine
    the rest) and why a run was rejected."""
    from rsra.estimator.flight_advice import advice_summary

    adv = advice_summary(a.get("advice"))
    return [_angles_table(a), *([f"advice: {_text(adv)}"] if adv else []), *_why(a)]


def _health(h: dict, units: str) -> list[RenderableType]:
    """The latest health record: the nodes, the bus and samples in one line, SYNC in one."""
    from rich.table import Table

    from rsra.daq.cli.demo_view import sync_text

    nt = Table(title="nodes")
    for col in ("node", "state", "heartbeat age s", "emcy"):
        nt.add_column(col)
    for name, nd in (h.get("nodes") or {}).items():
        age = nd.get("heartbeat_age")
        nt.add_row(_text(name), _text(nd.get("state")), "—" if age is None else f"{age:.2f}",
                   str(len(nd.get("emcy") or [])))
    bus = h.get("bus") or {}
    smp = h.get("samples") or {}
    lat = h.get("latency_ms") or {}
    return [nt, _text(
        f"bus: frames {bus.get('frames')} errors {bus.get('errors')} bus-off {bus.get('bus_off')} "
        f"unknown {bus.get('unknown')} malformed {bus.get('malformed')} | samples: complete "
        f"{smp.get('complete')} incomplete {smp.get('incomplete')} lost {smp.get('lost')} | "
        f"latency p50 {_ms(lat.get('p50'))} ms p99 {_ms(lat.get('p99'))} ms"),
        "sync: " + _text(sync_text(h))]


# the keys shown below the table, in order, each by its latest record
_SECTIONS = (("hub_loads", _hub_loads), ("angles", _angles), ("health", _health))


def render(stats: dict[str, KeyStats], prefix: str, units: str, now: float,
           notes: list[str] | None = None, source: str | None = None):
    """The live view; ``source``: whose telemetry it is (daq.runtime.instances), or why
    nothing is shown."""
    from rich.console import Group

    parts: list[RenderableType] = [_keys_table(stats, source or prefix, now)]
    for key, section in _SECTIONS:
        st = stats.get(key)
        if st and st.latest:
            parts += section(st.latest, units)
    parts.extend(_text(n) for n in notes or ())
    return Group(*parts)


class Listener:
    """What `rsra listen` does with each message received, apart from Zenoh (so tests feed it
    bytes in-process): the guard, then a JSON line (``out``) or the table's statistics."""

    def __init__(self, guard: PayloadGuard, out: TextIO | None = None) -> None:
        #: every payload goes through it first; it counts the bad ones
        self.guard = guard
        #: --json: where the lines go (None: the table)
        self.out = out
        #: the table's statistics per key (at most MAX_KEYS keys)
        self.stats: dict[str, KeyStats] = {}
        #: messages received (bad ones included)
        self.received = 0
        #: messages on keys beyond MAX_KEYS (not in the table)
        self.other_keys = 0

    def feed(self, key: str, data: Received, now: float) -> None:
        self.received += 1
        got = self.guard.receive(key, data)
        if got is None:
            return
        if self.out is not None:
            rec = {"key": key, **{k: v for k, v in got.payload.items() if k != "key"}}
            if got.non_finite:
                rec["non_finite"] = True
            self.out.write(dumps(rec) + "\n")
            return
        st = self.stats.get(key)
        if st is None:
            if len(self.stats) >= MAX_KEYS:
                self.other_keys += 1
                return
            st = self.stats[key] = KeyStats(key)
        st.add(got.payload, now)

    def notes(self) -> list[str]:
        """The lines under the table: bad messages, messages on keys not shown."""
        out = self.guard.lines()
        if self.other_keys:
            out.append(f"{self.other_keys} messages on more than {MAX_KEYS} keys (not shown)")
        return out


def _zenoh_conf(args: argparse.Namespace, cfg) -> Any:
    from rsra.daq.runtime.telemetry import viewer_config, zenoh_config

    if args.zenoh_config:
        return zenoh_config(cfg.telemetry, config_file=args.zenoh_config)
    return viewer_config(args.zenoh_connect or list(cfg.telemetry.listen))


def _view(lis: Listener, whose: Whose, args: argparse.Namespace, now: float,
          notes: bool = True):
    return render(lis.stats, whose.prefix or "", args.units, now,
                  lis.notes() if notes else None, source=whose.title())


def _start(lis: Listener, whose: Whose, args: argparse.Namespace):
    """The live table (None with --json: the source goes to stderr instead)."""
    if args.json:
        print(f"rsra listen: {whose.title()}", file=sys.stderr)
        return None
    from rich.live import Live

    from rsra.daq.cli.console import make_console

    live = Live(_view(lis, whose, args, time.monotonic(), notes=False),
                console=make_console(), refresh_per_second=4, transient=False)
    live.start()
    return live


def _subscribe(session: Any, prefix: str, keys: list[str]) -> list[Any]:
    import zenoh

    return [session.declare_subscriber(f"{prefix}/{k}", zenoh.handlers.RingChannel(4096))
            for k in keys]


def _redraw(live, lis: Listener, whose: Whose, args: argparse.Namespace, now: float,
            last_draw: float) -> float:
    """The table drawn again at most four times a second; when it was last drawn."""
    if live is None or now - last_draw <= 0.25:
        return last_draw
    live.update(_view(lis, whose, args, now))
    return now


def _drain(subs: list[Any], prefix: str, lis: Listener, count: int | None) -> tuple[bool, bool]:
    """Every message waiting on the subscribers fed to the listener: (any came, --count
    reached)."""
    got = False
    for sub in subs:
        while (s := sub.handler.try_recv()) is not None:
            got = True
            lis.feed(str(s.key_expr)[len(prefix) + 1:], s.payload, time.monotonic())
            if count is not None and lis.received >= count:
                return got, True
    return got, False


def _stop(live, lis: Listener, whose: Whose, args: argparse.Namespace) -> None:
    """The table drawn a last time, or (--json, stdout stays JSON lines) the bad messages
    said on stderr."""
    if live is not None:
        live.update(_view(lis, whose, args, time.monotonic()))
        live.stop()
    elif lis.guard.bad or lis.guard.non_finite:
        sys.stdout.flush()
        for line in lis.guard.lines():
            print(f"rsra listen: {line}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    import zenoh

    from rsra.daq.rigmodel import load_rig
    from rsra.daq.runtime.telemetry import payload_guard

    cfg = load_rig(args.config)
    conf = _zenoh_conf(args, cfg)
    keys = args.key or ["**"]
    lis = Listener(payload_guard(), sys.stdout if args.json else None)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    with zenoh.open(conf) as session:
        whose = Whose(session, cfg.telemetry.prefix, args.prefix, args.rig)
        subs: list[Any] = []
        live = None
        try:
            whose.discover(time.monotonic())
            live = _start(lis, whose, args)
            last_draw = 0.0
            prefix = ""
            while True:
                if not subs and whose.prefix is not None:
                    prefix = whose.prefix
                    subs = _subscribe(session, prefix, keys)
                got, done = _drain(subs, prefix, lis, args.count)
                if done:
                    return 0
                now = time.monotonic()
                whose.poll(now)
                last_draw = _redraw(live, lis, whose, args, now, last_draw)
                if args.json:
                    sys.stdout.flush()
                if t_end is not None and now >= t_end:
                    return 0
                if not got:
                    time.sleep(0.02)
        except KeyboardInterrupt:
            return 0
        finally:
            _stop(live, lis, whose, args)
            for sub in subs:
                sub.undeclare()
            whose.close()
