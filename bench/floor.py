"""The one-process floor of P5, P6b and P8 (docs/performance.md, "The one-process floor").

A do-nothing master and a do-nothing responder in **one process** on the service's own
virtual bus (``rsra.canbus.open_bus(interface='virtual')``), with the service's thread
topology and transport calls, and nothing else:

* the master's SYNC thread is the service's :class:`rsra.daq.bus.master.SyncProducer`
  (its re-phasing rule, its ``late`` and ``periods_not_taken`` counts), SYNC with counter;
* the responder's receive thread answers every SYNC with the sample's TPDOs in one send
  (``rsra.canbus.send_batch``, as the simulator does), constant data;
* the master's receive thread reads in batches (``recv`` then ``recv_batch``, as
  ``BatchNotifier`` does), counts each period's frames and — given a Zenoh endpoint —
  publishes a payload of ``hub_loads``' size with the SYNC's send time when a period's last
  frame arrives (the declared publisher's ``put``, as the service).

No decode, no estimator, no record beyond the stamp: what Python threads, the GIL, the
virtual bus and the scheduler allow one process. A figure of the service that this floor
also misses is stopped by the platform, not by rsra's own work; the difference between the
two is what rsra's per-sample work costs.
"""
from __future__ import annotations

import json
import threading
import time
import uuid

import numpy as np

SYNC_ID = 0x080


def default_frames(required_only: bool) -> list[tuple[int, int]]:
    """(COB-ID, length) of the TPDOs per SYNC: the default nodes only (P6b's aircraft) or the
    ``ground-test`` scenario's (P5, P8)."""
    from bench.rig import response_frames
    from rsra.config.rig import load_config
    from rsra.daq.bus.decoder import DecodeTable

    if not required_only:
        return response_frames("ground-test")
    return [(t.cob_id, t.length) for nl in DecodeTable(load_config()).nodes if nl.required
            for t in nl.tpdos]


def run_floor(rate: float, duration: float, frames: list[tuple[int, int]], *,
              warmup: float = 1.0, endpoint: str | None = None, key: str = "floor/hub_loads",
              size: int = 0, counter_overflow: int = 240) -> dict:
    """Run the pair for ``duration`` s at ``rate`` SYNCs/s. Scored after ``warmup`` s: periods,
    complete (exactly the sample's frames before the next SYNC), all-missing (none), late
    SYNCs and periods not taken (the producer's counts over the scored window), the SYNC rate
    achieved, and ``ok`` — P6b's criterion: every scored period complete and ≥ 99 % of the
    rate kept."""
    import can

    from rsra.canbus import open_bus, recv_batch, send_batch, shutdown_bus
    from rsra.daq.bus.master import SyncProducer

    channel = f"floor-{uuid.uuid4().hex[:8]}"
    master = open_bus(interface="virtual", channel=channel, receive_own_messages=True)
    responder = open_bus(interface="virtual", channel=channel)
    ids = {c for c, _ in frames}
    n_frames = len(frames)
    answer = [can.Message(arbitration_id=c, data=bytes(n), is_extended_id=False)
              for c, n in frames]
    syncs = [can.Message(arbitration_id=SYNC_ID, data=bytes([k + 1]) if counter_overflow else b"",
                         is_extended_id=False) for k in range(max(1, counter_overflow))]
    cap = int(rate * (duration + 5)) + 100
    counts = np.zeros(cap, dtype=np.int32)  # frames per period (bounded)
    t_sync = np.zeros(cap)
    put_s = np.full(cap, np.nan)  # last frame counted -> put returned (P5b's floor)
    cur = [-1]
    stop = threading.Event()
    pub = session = None
    if endpoint:
        from bench.rig import floor_publisher

        session, pub = floor_publisher(endpoint, key)
    pad = "x" * max(0, size - 40)

    def answer_loop() -> None:
        while not stop.is_set():
            m = responder.recv(0.1)
            if m is not None and m.arbitration_id == SYNC_ID:
                send_batch(responder, answer)

    def read_loop() -> None:
        while not stop.is_set():
            m = master.recv(0.1)
            if m is None:
                continue
            for f in [m, *recv_batch(master, 1024)]:
                if f.arbitration_id == SYNC_ID:
                    k = cur[0] + 1
                    if k < cap:
                        cur[0] = k
                        t_sync[k] = f.timestamp
                    continue
                k = cur[0]
                if f.arbitration_id in ids and 0 <= k < cap:
                    counts[k] += 1
                    if counts[k] == n_frames and pub is not None:
                        t_last = time.perf_counter()
                        pub.put(json.dumps({"seq": k, "t": float(t_sync[k]), "pad": pad}))
                        put_s[k] = time.perf_counter() - t_last

    threads = [threading.Thread(target=answer_loop, name="floor-responder", daemon=True),
               threading.Thread(target=read_loop, name="floor-reader", daemon=True)]
    for th in threads:
        th.start()
    producer = None
    try:
        if pub is not None:  # the subscriber connects (at most 2 s)
            deadline = time.monotonic() + 2.0
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.02)
        producer = SyncProducer(master, syncs, 1.0 / rate, threading.Lock())
        time.sleep(warmup)
        k0, late0, skip0 = cur[0], producer.late, producer.periods_not_taken
        t0 = time.perf_counter()
        time.sleep(max(0.0, duration - warmup))
        k1, late1, skip1 = cur[0], producer.late, producer.periods_not_taken
        wall = time.perf_counter() - t0
    finally:
        if producer is not None:
            producer.stop()
        time.sleep(0.05)  # the last answer arrives
        stop.set()
        for th in threads:
            th.join(2.0)
        for b in (master, responder):
            shutdown_bus(b)
        if pub is not None:
            pub.undeclare()
            session.close()
    sel = counts[k0 + 1: k1] if k1 > k0 + 1 else counts[:0]  # scored, the last still open
    periods = int(len(sel))
    late, skipped = late1 - late0, skip1 - skip0
    out = {"rate": rate, "periods": periods, "complete": int((sel == n_frames).sum()),
           "all_missing": int((sel == 0).sum()), "late": int(late),
           "periods_not_taken": int(skipped), "frames_per_sample": n_frames,
           "achieved_rate": (k1 - k0) / wall if wall > 0 else None}
    out["incomplete"] = periods - out["complete"]
    slots = periods + out["periods_not_taken"]
    out["on_time"] = 1.0 - (late + skipped) / slots if slots else None
    shares = put_s[k0 + 1: k1]
    shares = shares[np.isfinite(shares)] * 1e3
    if shares.size:
        out["last_frame_to_put_p50_ms"] = float(np.percentile(shares, 50))
        out["last_frame_to_put_p99_ms"] = float(np.percentile(shares, 99))
    out["scored_seq"] = [int(k0 + 1), int(k1)]
    out["ok"] = (periods > 0 and out["incomplete"] == 0
                 and (out["achieved_rate"] or 0.0) >= 0.99 * rate)
    return out


def ceiling(frames: list[tuple[int, int]], trial_s: float, *, start: float = 200.0,
            cap: float = 3200.0, bisect: int = 3, attempts: int = 2, log=print) -> dict:
    """The highest rate the pair sustains (``ok``), searched as P6b searches the service:
    double from ``start`` while it passes, then bisect (``attempts`` tries per rate)."""
    trials = []

    def passes(rate: float) -> bool:
        for _ in range(attempts):
            r = run_floor(rate, trial_s, frames)
            trials.append(r)
            log(f"bench.floor: {rate:g} samples/s: {'ok' if r['ok'] else 'LOST'} {r}")
            if r["ok"]:
                return True
        return False

    good = bad = None
    rate = start
    while rate <= cap:
        if passes(rate):
            good = rate
            rate *= 2
        else:
            bad = rate
            break
    if good is not None and bad is not None:
        for _ in range(bisect):
            mid = round((good + bad) / 2.0)
            if passes(mid):
                good = mid
            else:
                bad = mid
    return {"samples_per_s": float(good or 0.0), "first_failing_rate": bad,
            "search_capped_at": cap, "trials": trials}


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.floor --rate R --duration S [--endpoint EP --key K --size N]
    [--all-nodes] --out PATH``: one run of the pair in this process, its figures as JSON."""
    import argparse
    from pathlib import Path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--endpoint")
    ap.add_argument("--key", default="floor/hub_loads")
    ap.add_argument("--size", type=int, default=0)
    ap.add_argument("--all-nodes", action="store_true",
                    help="the ground-test scenario's nodes (default: the default nodes only)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    r = run_floor(a.rate, a.duration, default_frames(not a.all_nodes), warmup=a.warmup,
                  endpoint=a.endpoint, key=a.key, size=a.size)
    Path(a.out).write_text(json.dumps(r), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
