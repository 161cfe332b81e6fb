"""P5c — SYNC → ``hub_loads`` at a subscriber, across processes on the shared bus
(docs/performance.md).

The bench rig's topology: ``rsra bus`` (python-can-remote on loopback), ``rsra sim
--scenario ground-test`` and ``rsra run`` each in its own process on it, 200 samples/s,
identification running (its worker process); this process subscribes to ``hub_loads`` over
Zenoh and takes receive time − ``t`` per sample (``t``: the service's acquisition time of the
SYNC). The first ``WARMUP_S`` are not scored, then ``SCORED_S`` are.

Floor, measured in the same run on the same shared-bus server: a do-nothing master (SYNC
from a thread with the service's re-phasing rule; when a period's last frame arrives, a
payload of the same size published over Zenoh with the SYNC's send time) and a do-nothing
responder answering every SYNC with the same TPDOs the simulator sends — the same frames
through the same transport, plus the Zenoh hop. Target: p50 ≤ floor p50 + 0.3 ms.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import arg_parser, ratio, writer_from_args
from bench.rig import (
    start_sim_and_service,
    Receiver,
    floor_master_main,
    free_tcp_port,
    responder_main,
    response_frames,
    scored,
    start_bus,
    stop,
    wait_listening,
)

BENCH = "p5c_shared_bus"
WARMUP_S = 8.0
SCORED_S = 60.0
RATE = 200.0


def floor_run(channel: str, rate: float, seconds: float, size: int, tmp: Path,
              with_zenoh: bool = True) -> tuple[dict, np.ndarray | None]:
    """The do-nothing pair on ``channel`` for ``seconds``: (master's tally, latencies s)."""
    ctx = mp.get_context("spawn")
    frames = response_frames("ground-test")
    res = tmp / f"floor-{rate:g}-{time.monotonic_ns()}.json"
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}" if with_zenoh else None
    key = f"rsra-bench/floor/{os.getpid()}"
    ready = ctx.Event()
    resp = ctx.Process(target=responder_main, args=(channel, frames, seconds + 30.0, ready),
                       daemon=True)
    resp.start()
    if not ready.wait(120):  # the responder is connected
        resp.terminate()
        resp.join(10)
        raise RuntimeError("the do-nothing responder did not connect to the shared bus")
    master = ctx.Process(target=floor_master_main,
                         args=(channel, frames, rate, seconds, ep, key, size, str(res)), daemon=True)
    master.start()
    rx = None
    try:
        if with_zenoh:
            wait_listening(port, None)
            rx = _FloorReceiver(ep, key, int(rate * (seconds + 30)))
        master.join(seconds + 120)
    finally:
        for p in (master, resp):
            if p.is_alive():
                p.terminate()
            p.join(10)
        if rx is not None:
            rx.close()
    tally = json.loads(res.read_text()) if res.exists() else {}
    lat = None
    if rx is not None and rx.n:
        lat = rx.stamps[: rx.n] - rx.t[: rx.n]
    return tally, lat


class _FloorReceiver:
    def __init__(self, endpoint: str, key: str, capacity: int) -> None:
        import zenoh

        from rsra.daq.runtime.telemetry import viewer_config

        self.stamps, self.t = np.zeros(capacity), np.zeros(capacity)
        self.n = 0
        self.session = zenoh.open(viewer_config([endpoint]))
        self.sub = self.session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        t = time.time()
        if self.n < len(self.stamps):
            self.stamps[self.n] = t
            self.t[self.n] = json.loads(sample.payload.to_bytes())["t"]
            self.n += 1

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def service_run(channel: str, seconds: float, warmup: float, tmp: Path) -> dict:
    from rsra.config.rig import load_config

    cfg = load_config()
    sim = svc = rx = None
    try:
        sim, svc, ep = start_sim_and_service(channel)
        rx = Receiver(ep, cfg.telemetry.prefix, int(RATE * (seconds + warmup + 120)))
        deadline = time.monotonic() + 120
        while rx.count() == 0 and time.monotonic() < deadline:  # the nodes booted
            time.sleep(0.2)
        time.sleep(warmup + seconds + 1.0)
        seq, t, lat = rx.series()
        lat_s, got, missing = scored(seq, t, lat, warmup, round(seconds * RATE))
        return {"lat_ms": lat_s * 1e3, "got": got, "missing": missing, "size": rx.size,
                "health": rx.health}
    finally:
        if rx is not None:
            rx.close()
        for p in (svc, sim):
            stop(p)


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    warmup, seconds = (0.5, 1.0) if args.tiny else (WARMUP_S, SCORED_S)
    bus, channel = start_bus()
    try:
        with tempfile.TemporaryDirectory(prefix="rsra-p5c-") as d:
            r = service_run(channel, seconds, warmup, Path(d))
            tally, floor = floor_run(channel, RATE, seconds + warmup, r["size"] or 400, Path(d))
    finally:
        stop(bus)
    lat = r["lat_ms"]
    p50, p99 = float(np.percentile(lat, 50)), float(np.percentile(lat, 99))
    fl = (floor[int(warmup * RATE):] if floor is not None and len(floor) > warmup * RATE * 2
          else floor)
    f50 = float(np.percentile(fl, 50)) * 1e3 if fl is not None and len(fl) else None
    f99 = float(np.percentile(fl, 99)) * 1e3 if fl is not None and len(fl) else None
    sync = (r["health"] or {}).get("sync") or {}
    details = {"rate": RATE, "warmup_s": warmup, "scored_s": seconds, "received": r["got"],
               "missing": r["missing"], "late_over_period": int((lat > 1e3 / RATE).sum()),
               "p90_ms": float(np.percentile(lat, 90)), "max_ms": float(lat.max()),
               "p99_ms": p99, "floor_p99_ms": f99, "floor_tally": tally, "floor_samples": 0 if fl is None else len(fl),
               "service_sync": sync, "payload_bytes": r["size"],
               "load_average": os.getloadavg()[0],
               "topology": "rsra bus + rsra sim --scenario ground-test + rsra run, each its own "
                           "process, --interface remote"}
    w.add("p50", p50, "ms", peer="do-nothing master + responder through the same shared bus, "
          "+ the Zenoh hop (p50, same run)", peer_figure=f50,
          ratio_value=ratio(f50, p50), ratio_is="peer/figure", target="p50 ≤ floor + 0.3 ms",
          met=f50 is not None and p50 <= f50 + 0.3, excess_over_floor_ms=None if f50 is None
          else p50 - f50, **details)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
