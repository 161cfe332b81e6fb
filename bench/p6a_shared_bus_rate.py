"""P6a — the highest sample rate the service sustains in its own process, the simulator in
another, on the shared bus (docs/performance.md).

``rsra bus`` (python-can-remote on loopback) once; per trial a fresh ``rsra sim --scenario
ground-test`` and ``rsra run --config <the rig at that rate>`` on it, a Zenoh subscriber
here. After a warm-up, a rate passes when over the trial: every SYNC gave a published sample
(no gap in ``seq``), none flagged ``lost_before`` or ``missing:<node>``, and at most 0.1 % of
the SYNCs went out more than half a period behind schedule (health ``sync.late`` over
``sync.sent``, differenced over the trial).

Ceiling, the same run, the same server: a do-nothing master (SYNC from a thread, the same
re-phasing rule) and a do-nothing responder answering every SYNC with the simulator's frames;
a rate passes when every period got all its frames before the next SYNC and ≤ 0.1 % of the
SYNCs were late.

Search (each side): double from 200 samples/s while it passes (or halve while it fails),
then bisect ``BISECT_STEPS`` times, ``TRIAL_S`` per trial; the best rate is then confirmed for
``CONFIRM_S`` (60 s; a failed confirmation steps down 10 %, ``CONFIRM_TRIES`` times, then
halves down to ``MIN_RATE``: 0 only when nothing from there passes a minute).
Target: the service's rate ≥ 90 % of the ceiling.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from bench.common import arg_parser, ratio, writer_from_args
from bench.p5c_shared_bus import floor_run
from bench.rig import start_sim_and_service, Receiver, rate_config, start_bus, stop

BENCH = "p6a_shared_bus_rate"
TRIAL_S = 12.0
CONFIRM_S = 60.0
CONFIRM_TRIES = 2
WARMUP_S = 6.0
START_RATE = 200.0
MIN_RATE = 50.0  # the default rig refuses rates below 31.5 samples/s (its 5th harmonic)
MAX_RATE = 3200.0
BISECT_STEPS = 2
LATE_MAX = 0.001
TINY_TRIAL_S, TINY_WARMUP_S = 1.0, 0.5  # --tiny: the smoke run (every path once, no figure)


def service_trial(channel: str, rate: float, seconds: float, warmup: float, tmp: Path) -> dict:
    from rsra.config.rig import load_config

    cfg_path = rate_config(rate, tmp)
    prefix = load_config().telemetry.prefix
    sim = svc = rx = None
    try:
        sim, svc, ep = start_sim_and_service(channel, cfg_path)
        rx = Receiver(ep, prefix, int(rate * (seconds + warmup + 180)))
        deadline = time.monotonic() + 120
        while rx.count() == 0 and time.monotonic() < deadline:  # the nodes booted
            time.sleep(0.2)
        time.sleep(warmup)
        h0, s0 = rx.health, rx.last_seq()
        time.sleep(seconds)
        s1 = rx.last_seq()
        time.sleep(1.5)  # the health after the window
        h1 = rx.health
    finally:
        if rx is not None:
            rx.close()
        for p in (svc, sim):
            stop(p)
    sy0, sy1 = (h0 or {}).get("sync") or {}, (h1 or {}).get("sync") or {}
    win = rx.window(s0, s1) if s0 >= 0 else {"expected": 0, "received": 0, "missing": 0,
                                            "flagged": 0}
    sent = (sy1.get("sent") or 0) - (sy0.get("sent") or 0)
    late = (sy1.get("late") or 0) - (sy0.get("late") or 0)
    if not sent:  # health does not carry sent: the samples expected are the SYNCs sent
        sent = win["expected"]
    ok = (win["expected"] > 0 and win["missing"] == 0 and win["flagged"] == 0
          and late <= LATE_MAX * max(sent, 1))
    return {"rate": rate, "ok": ok, **win, "sync_sent": sent, "sync_late": late,
            "achieved_rate": round(win["received"] / seconds, 1), "side": "service"}


def floor_trial(channel: str, rate: float, seconds: float, warmup: float, tmp: Path) -> dict:
    tally, _ = floor_run(channel, rate, seconds + warmup, 0, tmp, with_zenoh=False)
    sent, late = tally.get("sent", 0), tally.get("late", 0)
    ok = sent > 0 and tally.get("incomplete", 1) == 0 and late <= LATE_MAX * sent
    return {"rate": rate, "ok": ok, **tally, "side": "ceiling"}


def search(trial, tiny: bool, log: list) -> float:
    def attempt(rate: float, seconds: float) -> bool:
        r = trial(rate, seconds)
        log.append(r)
        print(f"bench.{BENCH}: {r['side']} {rate:g}/s {'ok' if r['ok'] else 'FAIL'} {r}", flush=True)
        return r["ok"]

    seconds = TINY_TRIAL_S if tiny else TRIAL_S
    good = bad = None
    rate = START_RATE
    while True:
        if attempt(rate, seconds):
            good = rate
            if tiny or rate >= MAX_RATE:
                break
            rate *= 2
        else:
            bad = rate
            break
    while good is None and not tiny and rate / 2 >= MIN_RATE:
        rate /= 2
        if attempt(rate, seconds):
            good = rate
        else:
            bad = rate
    if good is not None and bad is not None and not tiny:
        for _ in range(BISECT_STEPS):
            rate = round((good + bad) / 2.0)
            if attempt(rate, seconds):
                good = rate
            else:
                bad = rate
    if good is None or tiny:
        return float(good or 0.0)
    for _ in range(CONFIRM_TRIES):  # the figure: sustained for the full CONFIRM_S
        if attempt(good, CONFIRM_S):
            return float(good)
        good = round(good * 0.9)
    while good >= MIN_RATE:  # a machine whose stalls fail a minute at any rate: halve
        if attempt(good, CONFIRM_S):
            return float(good)
        good = round(good / 2)
    return 0.0


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    warmup = TINY_WARMUP_S if args.tiny else WARMUP_S
    log: list[dict] = []
    bus, channel = start_bus()
    try:
        with tempfile.TemporaryDirectory(prefix="rsra-p6a-") as d:
            tmp = Path(d)
            ceiling = search(lambda r, s: floor_trial(channel, r, s, warmup, tmp), args.tiny, log)
            best = search(lambda r, s: service_trial(channel, r, s, warmup, tmp), args.tiny, log)
    finally:
        stop(bus)
    r = ratio(best, ceiling)
    w.add("max_sustained_rate", best, "samples/s",
          peer="do-nothing master + responder, same shared bus, same run (samples/s)",
          peer_figure=ceiling, ratio_value=r, ratio_is="figure/peer",
          target="≥ 90 % of the ceiling (60 s, zero lost, ≤ 0.1 % of periods late)",
          met=r is not None and r >= 0.9, trials=log, trial_s=TINY_TRIAL_S if args.tiny else TRIAL_S,
          confirm_s=None if args.tiny else CONFIRM_S, warmup_s=warmup,
          load_average=os.getloadavg()[0],
          note="a tiny run tries 200 samples/s only" if args.tiny else None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
