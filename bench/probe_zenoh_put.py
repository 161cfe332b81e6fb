"""What one Zenoh ``put`` costs the thread that calls it (docs/performance.md, "Issue 26,
session 22"): the service's share P5b ends with the ``put`` of ``hub_loads`` in the bus thread.

A publisher declared as the service declares its high-rate keys (``express``, ``DROP``,
``REAL_TIME``) puts a ``hub_loads``-sized payload (400 bytes) 200 times a second to a
subscriber in another process, over loopback TCP, scouting off. Per ``put``: the wall time of
the call and the calling thread's CPU time; at the subscriber, the hop (the payload carries
its send time). Three conditions of the publishing process, in turn:

* ``idle`` — nothing else runs (the one-process floor's situation);
* ``busy`` — another Python thread runs a CPU loop: ``put`` lets the GIL go and, to return,
  waits for the other thread's switch interval (``sys.getswitchinterval()``, 5 ms by default;
  the live service runs at 0.5 ms);
* ``cold`` — 16 MB of memory is written between two ``put`` calls, as the rest of a
  sample's work does to the caches in the service.

A probe, not a benchmark of a target: one JSON line per condition, nothing written to
``bench/results``. ``--quick`` (2 s, ``idle`` only) is the smoke test.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import threading
import time

import numpy as np

KEY = "bench/probe_zenoh_put"
PAYLOAD_BYTES = 400
RATE_HZ = 200.0


def _config(listen: str | None = None, connect: str | None = None):
    """The project's peer config (daq.runtime.telemetry.viewer_config): loopback endpoints
    only, listening nowhere unless told (Zenoh's own default is every interface), multicast
    scouting off."""
    from rsra.daq.runtime.telemetry import viewer_config

    return viewer_config([connect] if connect else [], [listen] if listen else [])


def _subscriber(endpoint: str, q, seconds: float) -> None:
    import zenoh

    hops: list[float] = []

    def on_sample(sample) -> None:
        now = time.time()
        hops.append(now - float(bytes(sample.payload)[:20].decode()))

    with zenoh.open(_config(connect=endpoint)) as s:
        sub = s.declare_subscriber(KEY, on_sample)
        q.put("ready")
        time.sleep(seconds)
        sub.undeclare()
    q.put(hops)


def measure(mode: str, port: int, seconds: float) -> dict:
    """One condition (module doc): the put call's wall and CPU time, and the hop."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{port}"
    ctx = mp.get_context("spawn")  # never fork a process that runs Zenoh's threads
    q = ctx.Queue()
    calls, cpus = [], []
    stop = threading.Event()
    junk = np.ones(2 << 20) if mode == "cold" else None  # 16 MB
    with zenoh.open(_config(listen=endpoint)) as session:
        child = ctx.Process(target=_subscriber, args=(endpoint, q, seconds + 4.0), daemon=True)
        child.start()
        try:
            q.get(timeout=30)
            pub = session.declare_publisher(
                KEY, encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.REAL_TIME, express=True)
            time.sleep(1.0)  # the subscriber's declaration reaches the publisher
            if mode == "busy":
                def burn() -> None:
                    while not stop.is_set():
                        pass
                threading.Thread(target=burn, name="probe-burner", daemon=True).start()
            t_next = time.monotonic()
            end = t_next + seconds
            while t_next < end:
                t_next += 1.0 / RATE_HZ
                time.sleep(max(0.0, t_next - time.monotonic()))
                if junk is not None:
                    junk += 1.0
                payload = (f"{time.time():20.6f}" + "x" * (PAYLOAD_BYTES - 20)).encode()
                c0, t0 = time.thread_time(), time.perf_counter()
                pub.put(payload)
                calls.append(time.perf_counter() - t0)
                cpus.append(time.thread_time() - c0)
            stop.set()
            hops = q.get(timeout=30)
            pub.undeclare()
        finally:
            stop.set()
            child.join(timeout=10)
            if child.is_alive():
                child.kill()
    a, c, h = (np.array(x) * 1e3 for x in (calls, cpus, hops or [np.nan]))
    return {"mode": mode, "puts": len(a), "received": len(hops),
            "put_call_ms": {"p50": float(np.median(a)), "p99": float(np.percentile(a, 99))},
            "put_cpu_ms": {"p50": float(np.median(c)), "p99": float(np.percentile(c, 99))},
            "hop_ms": {"p50": float(np.median(h)), "p99": float(np.percentile(h, 99))}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--modes", nargs="+", choices=("idle", "busy", "cold"),
                   default=["idle", "busy", "cold", "idle", "busy", "cold"],
                   help="conditions, in this order (default: each twice, alternated)")
    p.add_argument("--seconds", type=float, default=18.0, help="puts per condition, seconds")
    p.add_argument("--port", type=int, default=0, help="first TCP port (default: free ones)")
    p.add_argument("--quick", action="store_true", help="2 s of idle (the smoke test)")
    args = p.parse_args(argv)
    modes, seconds = (["idle"], 2.0) if args.quick else (args.modes, args.seconds)
    for i, mode in enumerate(modes):
        port = args.port + i if args.port else _free_port()
        print(json.dumps(measure(mode, port, seconds)), flush=True)
    return 0


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


if __name__ == "__main__":
    raise SystemExit(main())
