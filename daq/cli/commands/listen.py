"""`rsra listen`: the reference telemetry subscriber — a live table of any rig, or JSON lines.

Uses a ring-buffer handler (a slow terminal never backs up the publisher) and shows the
latest values, rates, missed samples (gaps in `seq`), staleness and node health.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from rsra.config.units import axis_units, to_units

if TYPE_CHECKING:
    from rich.console import RenderableType

AXES = ("X", "Y", "Z", "L", "M", "N")


def _ms(v) -> str:
    """A latency for the view: 3 significant digits (0.827, 12.4), '—' when absent."""
    return "—" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.3g}"


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(name, help="live view of a rig's telemetry (or JSON lines)",
                       description="Subscribe to <prefix>/** and show the latest values, rates, "
                       "missed samples, staleness and node health.")
    common_options(p)
    p.add_argument("--prefix", default=None, help="key prefix (default: the config's, rsra/bench)")
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
            if self.first_seq is None or self.last_seq is None:  # (the two are set together)
                self.first_seq = seq
                self.last_seq = seq
                self.n_seq = 1
            elif seq > self.last_seq:
                if self.key not in EVERY_SAMPLE:
                    self.stride = math.gcd(self.stride, seq - self.last_seq)
                self.last_seq = seq
                self.n_seq += 1
        self.last_arrival = now
        self.arrivals.append(now)
        self.latest = payload if isinstance(payload, dict) else {"value": payload}

    def rate(self) -> float:
        if len(self.arrivals) < 2:
            return 0.0
        span = self.arrivals[-1] - self.arrivals[0]
        return (len(self.arrivals) - 1) / span if span > 0 else 0.0


def _fmt(v, width: int = 9) -> str:
    if v is None:
        return "—".rjust(width)
    return f"{v:{width}.1f}"


def render(stats: dict[str, KeyStats], prefix: str, units: str, now: float):
    from rich.console import Group
    from rich.table import Table

    parts: list[RenderableType] = []
    t = Table(title=f"rsra telemetry — {prefix}", expand=False)
    for col in ("key", "messages", "rate /s", "missed", "age s"):
        t.add_column(col, justify="right" if col != "key" else "left")
    for key in sorted(stats):
        s = stats[key]
        missed = s.missed
        t.add_row(key, str(s.count), f"{s.rate():.1f}", "—" if missed is None else str(missed),
                  f"{now - s.last_arrival:.2f}")
    parts.append(t)
    hl = stats.get("hub_loads")
    if hl and hl.latest:
        ht = Table(title="hub loads (" + str(hl.latest.get("frame", "body")) + " axes)")
        ht.add_column("")
        u = axis_units(units)
        for i, ax in enumerate(AXES):
            ht.add_column(f"{ax} [{u[i]}]", justify="right")
        for label, field in (("filter H", "H"), ("static", "H_static"),
                             ("σ angles", "sigma_angles")):
            v = hl.latest.get(field)
            vals = ([None] * 6 if v is None else
                    to_units(np.array([np.nan if x is None else x for x in v]), units).tolist())
            ht.add_row(label, *[_fmt(None if x != x else x) for x in vals])
        flags = hl.latest.get("flags") or []
        parts.append(ht)
        if flags:
            parts.append(f"flags: {', '.join(flags)}")
    an = stats.get("angles")
    if an and an.latest:
        a = an.latest
        names = a.get("names") or []
        alpha = a.get("alpha") or []
        sig = a.get("sigma_cr") or []
        at = Table(title=f"angles — {a.get('mode')} / {a.get('content')}: "
                   f"{'accepted' if a.get('accepted') else 'rejected'}"
                   f"{'' if a.get('accepted') else ' (' + str(a.get('reason')) + ')'}, "
                   f"{a.get('determined')} of {len(names)} determined")
        at.add_column("angle")
        at.add_column("deg", justify="right")
        at.add_column("σ_CR deg", justify="right")
        for n, x, s in zip(names, alpha, sig):
            at.add_row(n, "—" if x is None else f"{np.degrees(x):7.3f}",
                       "—" if s is None else f"{np.degrees(s):6.3f}")
        parts.append(at)
        from rsra.estimator.flight_advice import advice_summary

        adv = advice_summary(a.get("advice"))  # filter error: what would determine the rest
        if adv:
            parts.append(f"advice: {adv}")
        if not a.get("accepted") and (a.get("explanation") or a.get("hint")):
            # why, in one line each (issue 28; records of older recordings carry neither)
            parts.append(f"why: {a.get('explanation') or a.get('detail')}")
            if a.get("hint"):
                parts.append(f"hint: {a.get('hint')}")
    he = stats.get("health")
    if he and he.latest:
        h = he.latest
        nt = Table(title="nodes")
        for col in ("node", "state", "heartbeat age s", "emcy"):
            nt.add_column(col)
        for name, nd in (h.get("nodes") or {}).items():
            age = nd.get("heartbeat_age")
            nt.add_row(name, str(nd.get("state")), "—" if age is None else f"{age:.2f}",
                       str(len(nd.get("emcy") or [])))
        parts.append(nt)
        bus = h.get("bus") or {}
        smp = h.get("samples") or {}
        lat = h.get("latency_ms") or {}
        parts.append(
            f"bus: frames {bus.get('frames')} errors {bus.get('errors')} bus-off {bus.get('bus_off')} "
            f"unknown {bus.get('unknown')} malformed {bus.get('malformed')} | samples: complete "
            f"{smp.get('complete')} incomplete {smp.get('incomplete')} lost {smp.get('lost')} | "
            f"latency p50 {_ms(lat.get('p50'))} ms p99 {_ms(lat.get('p99'))} ms")
        from rsra.daq.cli.demo_view import sync_text

        parts.append("sync: " + sync_text(h))
    return Group(*parts)


def run(args: argparse.Namespace) -> int:
    import zenoh

    from rsra.daq.rigmodel import load_rig
    from rsra.daq.runtime.telemetry import viewer_config, zenoh_config

    cfg = load_rig(args.config)
    prefix = args.prefix or cfg.telemetry.prefix
    if args.zenoh_config:
        conf = zenoh_config(cfg.telemetry, config_file=args.zenoh_config)
    else:
        connect = args.zenoh_connect or list(cfg.telemetry.listen)
        conf = viewer_config(connect)
    keys = args.key or ["**"]
    stats: dict[str, KeyStats] = {}
    t_end = None if args.duration is None else time.monotonic() + args.duration
    received = 0
    with zenoh.open(conf) as session:
        subs = [session.declare_subscriber(f"{prefix}/{k}", zenoh.handlers.RingChannel(4096))
                for k in keys]
        live = None
        if not args.json:
            from rich.live import Live

            from rsra.daq.cli.console import make_console

            live = Live(render(stats, prefix, args.units, time.monotonic()),
                        console=make_console(), refresh_per_second=4, transient=False)
            live.start()
        try:
            last_draw = 0.0
            while True:
                got = False
                for sub in subs:
                    while (s := sub.handler.try_recv()) is not None:
                        got = True
                        received += 1
                        key = str(s.key_expr)[len(prefix) + 1:]
                        text = s.payload.to_string()
                        try:
                            payload = json.loads(text)
                        except ValueError:
                            payload = {"raw": text}
                        if args.json:
                            rec = {"key": key, **payload} if isinstance(payload, dict) else {
                                "key": key, "value": payload}
                            sys.stdout.write(json.dumps(rec) + "\n")
                        else:
                            stats.setdefault(key, KeyStats(key)).add(payload, time.monotonic())
                        if args.count is not None and received >= args.count:
                            return 0
                now = time.monotonic()
                if live is not None and now - last_draw > 0.25:
                    live.update(render(stats, prefix, args.units, now))
                    last_draw = now
                if args.json:
                    sys.stdout.flush()
                if t_end is not None and now >= t_end:
                    return 0
                if not got:
                    time.sleep(0.02)
        except KeyboardInterrupt:
            return 0
        finally:
            if live is not None:
                live.stop()
            for sub in subs:
                sub.undeclare()
