"""A stall witness: a do-nothing process that sleeps 0.5 ms at a time and records every wake-up
that came late, beside a real-time benchmark (docs/performance.md, "The platform's stalls").

On a shared or virtual machine a thread that waits on a timer or an event is sometimes woken
milliseconds late: the hypervisor did not run the virtual CPU, or another process held it.
Nothing the service does can make up for that; a deadline missed while the witness — which
does no work at all — was stalled as well is the platform's. The witness records the wall
clock (``time.time``, the clock the service stamps its samples with, the same on one machine)
at the start and end of each sleep that lasted more than ``SLEEP_S + LATE_S``; the
benchmark asks which of its late samples overlap one.

It costs ≈ 2 000 wake-ups/s of a few µs each (≈ 1 % of a core), runs at default scheduling
(the service's own, unless the benchmark says otherwise) and keeps at most ``MAX_GAPS``
stalls (bounded). It stops at ``--duration`` or on SIGINT/SIGTERM and writes its JSON file
then.

    python -m bench.witness --duration 70 --out stalls.json
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from typing import Any

import numpy as np

SLEEP_S = 0.0005
LATE_S = 0.001  # a wake-up more than 1 ms after its sleep was due is a stall
MAX_GAPS = 100_000


def watch(duration: float, *, stop: list[bool] | None = None,
          on_start: Callable[[], None] | None = None) -> dict:
    """Sleep ``SLEEP_S`` at a time for ``duration`` s; the stalls seen (wall-clock intervals).
    ``on_start`` is called once the watch has begun (a stall from then on is recorded)."""
    stop = stop if stop is not None else [False]
    gaps: list[tuple[float, float]] = []
    t_end = time.monotonic() + duration
    wakeups = 0
    last_w, last_m = time.time(), time.monotonic()
    if on_start is not None:
        on_start()
    while last_m < t_end and not stop[0]:
        time.sleep(SLEEP_S)
        now_w, now_m = time.time(), time.monotonic()
        wakeups += 1
        if now_m - last_m > SLEEP_S + LATE_S and len(gaps) < MAX_GAPS:
            gaps.append((last_w, now_w))
        last_w, last_m = now_w, now_m
    return {"sleep_s": SLEEP_S, "late_s": LATE_S, "wakeups": wakeups, "gaps": gaps}


def start(duration: float, path: str, *, log: Any = None) -> subprocess.Popen:
    """The witness as a child process that dies with the benchmark (bench.rig.spawn);
    ``log``: its stdout and stderr (default discarded)."""
    from bench.rig import spawn

    return spawn(["-m", "bench.witness", "--duration", f"{duration:g}", "--out", path], log=log)


def load(path: str) -> np.ndarray:
    """The stalls written by a witness: an (n, 2) array of wall-clock (start, end)."""
    with open(path, encoding="utf-8") as f:
        gaps = json.load(f)["gaps"]
    return np.asarray(gaps, float).reshape(-1, 2)


def overlaps(gaps: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each window [a_i, b_i]: does any stall overlap it."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if gaps.size == 0 or a.size == 0:
        return np.zeros(a.shape, bool)
    order = np.argsort(gaps[:, 0])
    starts, ends = gaps[order, 0], gaps[order, 1]
    end_max = np.maximum.accumulate(ends)
    # the stalls that start before b; of them, does the latest-ending one end after a
    k = np.searchsorted(starts, b, side="left")
    hit = np.zeros(a.shape, bool)
    ok = k > 0
    hit[ok] = end_max[k[ok] - 1] > a[ok]
    return hit


def summary(gaps: np.ndarray, t0: float, t1: float) -> dict:
    """The stalls that overlap [t0, t1]: count, over 2 and 3 ms, the longest, and the share of
    time they cover."""
    sel = (gaps[:, 1] > t0) & (gaps[:, 0] < t1) if gaps.size else np.zeros(0, bool)
    g = gaps[sel] if gaps.size else gaps
    d = (g[:, 1] - g[:, 0]) * 1e3 if g.size else np.zeros(0)
    return {"stalls": int(d.size), "over_2ms": int((d > 2.0).sum()), "over_3ms": int((d > 3.0).sum()),
            "max_ms": float(d.max()) if d.size else 0.0,
            "time_share": float(d.sum() / 1e3 / max(t1 - t0, 1e-9)),
            "sleep_ms": SLEEP_S * 1e3, "stall_if_over_ms": (SLEEP_S + LATE_S) * 1e3}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, required=True, help="seconds to watch")
    ap.add_argument("--out", required=True, help="JSON file to write the stalls to")
    args = ap.parse_args(argv)
    stop = [False]

    def on_signal(*_: object) -> None:
        stop[0] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    # one line on stdout once watching (a test waits for it; a benchmark discards it)
    res = watch(args.duration, stop=stop, on_start=lambda: print("watching", flush=True))
    tmp = f"{args.out}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(res, f)
    os.replace(tmp, args.out)  # (a file of the benchmark's own scratch folder)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
