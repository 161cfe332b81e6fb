"""P5 — end-to-end latency: SYNC → hub-load sample at a Zenoh subscriber in another process.

The service runs as its own process exactly as a user starts it, in real time with the
simulated aircraft on the virtual bus (``python -m rsra run --sim ground-test --speed 1``:
the service is the CANopen master and produces SYNC at 200 samples/s; the periodic
identification runs in its own worker process). This benchmark process subscribes to
``<prefix>/hub_loads`` over Zenoh (loopback TCP, scouting off) and takes, per sample,
receive time − ``t`` (the service's acquisition time of the SYNC: the wall clock live, the
same clock on one machine). The first ``WARMUP_S`` are not scored (start-up: boot, designs,
worker); then 60 s are.

Peer: the Zenoh hop itself — a publisher in another process sending a payload of the same
size at the same rate with its send time — the floor of any such pipeline.

Targets: p50 ≤ 1 ms, p99 ≤ 3 ms, zero deadline misses (a sample not received before the
next SYNC, or not at all) in 60 s.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np

from bench.common import BLAS_ENV, arg_parser, ratio, writer_from_args
from bench import witness
from bench.rig import free_tcp_port, stop, wait_listening

BENCH = "p5_latency"
WARMUP_S = 5.0
SCORED_S = 60.0
FLOOR_S = 10.0
CONNECT_TIMEOUT_S = 180.0  # the machine is shared: start-up can take a minute


class Receiver:
    """A Zenoh subscriber that stamps each message on arrival (parsing comes later)."""

    def __init__(self, endpoint: str, key: str, capacity: int) -> None:
        import zenoh

        from rsra.daq.runtime.telemetry import viewer_config

        self.stamps = np.zeros(capacity)
        self.payloads: list[bytes] = []
        self.capacity = capacity
        self.n = 0
        self.overflow = 0
        self._lock = threading.Lock()
        self.session = zenoh.open(viewer_config([endpoint]))
        self.sub = self.session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        t = time.time()
        with self._lock:
            if self.n >= self.capacity:  # bounded: never grows past the expected count
                self.overflow += 1
                return
            self.stamps[self.n] = t
            self.payloads.append(sample.payload.to_bytes())
            self.n += 1

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()

    def series(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(seq, t of the sample, latency s) of every message received."""
        with self._lock:
            recs = [json.loads(p) for p in self.payloads[: self.n]]
            stamps = self.stamps[: self.n].copy()
        seq = np.array([r["seq"] for r in recs], dtype=np.int64)
        t = np.array([r["t"] for r in recs], float)
        return seq, t, stamps - t


def _floor_publisher(endpoint: str, key: str, n: int, period: float, size: int) -> None:
    """Another process: publish n payloads of about ``size`` bytes, stamped at send time."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as s:
        pub = s.declare_publisher(key)
        time.sleep(1.0)  # the subscriber connects
        pad = "x" * max(0, size - 60)
        t_next = time.monotonic()
        for k in range(n):
            t_next += period
            pub.put(json.dumps({"seq": k, "t": time.time(), "pad": pad}))
            dt = t_next - time.monotonic()
            if dt > 0:
                time.sleep(dt)
        time.sleep(0.5)
        pub.undeclare()


def measure_floor(n: int, period: float, size: int) -> np.ndarray:
    import multiprocessing as mp

    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    key = f"rsra-bench/floor/{os.getpid()}"
    p = mp.get_context("spawn").Process(target=_floor_publisher, args=(ep, key, n, period, size))
    p.start()
    try:
        wait_listening(port, None, CONNECT_TIMEOUT_S)
        rx = Receiver(ep, key, n + 10)
        try:
            p.join(timeout=n * period + 60)
        finally:
            rx.close()
    finally:
        if p.is_alive():
            p.terminate()
            p.join(5)
    _, _, lat = rx.series()
    return lat


def measure_one_process_floor(rate: float, seconds: float, size: int) -> dict:
    """The one-process floor (bench/floor.py): a do-nothing master and responder in one
    process on the service's virtual bus, publishing a payload of ``size`` bytes when a
    period's last frame arrives; this process subscribes. SYNC → subscriber over the scored
    periods (p50, p99, misses: late or never received), and the pair's own last frame →
    ``put`` returned (P5b's floor)."""
    import tempfile

    from bench.rig import spawn

    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    key = f"rsra-bench/floor1/{os.getpid()}"
    warm = 1.0
    with tempfile.TemporaryDirectory(prefix="rsra-p5-floor-") as tmp:
        out = os.path.join(tmp, "floor.json")
        stalls_path = os.path.join(tmp, "stalls.json")
        wit = witness.start(warm + seconds + CONNECT_TIMEOUT_S, stalls_path)
        proc = spawn(["-m", "bench.floor", "--all-nodes", "--rate", f"{rate:g}", "--duration",
                      f"{warm + seconds:g}", "--warmup", f"{warm:g}", "--endpoint", ep,
                      "--key", key, "--size", str(size), "--out", out])
        rx = None
        try:
            wait_listening(port, proc, CONNECT_TIMEOUT_S)
            rx = Receiver(ep, key, int((warm + seconds + 10) * rate))
            proc.wait(warm + seconds + 120)
        finally:
            if rx is not None:
                rx.close()
            stop(proc)
            stop(wit)
        with open(out, encoding="utf-8") as f:
            res = json.load(f)
        gaps = witness.load(stalls_path)
    seq, t, lat = rx.series()
    a, b = res["scored_seq"]
    sel = (seq >= a) & (seq < b)
    lat_ms = lat[sel] * 1e3
    n = b - a
    late_sel = lat_ms > 1e3 / rate
    if sel.any():
        ts = t[sel]
        stalled = witness.overlaps(gaps, ts[late_sel], ts[late_sel] + lat[sel][late_sel])
        res["platform_stalls"] = {**witness.summary(gaps, float(ts.min()), float(ts.max())),
                                  "late_during_a_stall": int(stalled.sum()),
                                  "late_not_during_a_stall": int(late_sel.sum() - stalled.sum())}
    res.update({
        "latency_p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else None,
        "latency_p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else None,
        "deadline_misses": int(n - len(np.unique(seq[sel])) + (lat_ms > 1e3 / rate).sum()),
        "scored_s": seconds})
    return res


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    from rsra.config.rig import load_config
    cfg = load_config()
    warmup, scored = (1.0, 1.0) if args.tiny else (WARMUP_S, SCORED_S)
    fs, dt = cfg.sample_rate_hz, cfg.sample_period_s
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    duration = warmup + scored + 1.0
    cmd = [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--speed", "1",
           "--seed", "1", "--duration", f"{duration:g}", "--zenoh-listen", ep,
           "--log-level", "warning"]
    import tempfile

    from rsra.daq.stagetiming import ENV as STAGE_ENV
    tmpdir = tempfile.TemporaryDirectory(prefix="rsra-p5-")
    stages_path = os.path.join(tmpdir.name, "stages.npz")
    # P5b: the service's own share, timed inside it (the hook is off unless asked for)
    # the platform's stalls meanwhile, seen by a process that does nothing (bench/witness.py)
    stalls_path = os.path.join(tmpdir.name, "stalls.json")
    wit = witness.start(duration + CONNECT_TIMEOUT_S, stalls_path)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **BLAS_ENV, STAGE_ENV: stages_path})
    rx = None
    try:
        wait_listening(port, proc, CONNECT_TIMEOUT_S)
        rx = Receiver(ep, f"{cfg.telemetry.prefix}/hub_loads", int((duration + 30) * fs))
        out, err = proc.communicate(timeout=duration + 120)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.communicate(timeout=30)
        if rx is not None:
            rx.close()
        stop(wit)
    if proc.returncode != 0:
        raise RuntimeError(f"the service failed ({proc.returncode}): {err[-2000:]}")
    summary = {}
    for line in out.splitlines():
        if line.startswith('{"summary"'):
            summary = json.loads(line)["summary"]
    seq, t, lat = rx.series()
    if len(seq) == 0:
        raise RuntimeError("the subscriber received nothing")
    # scored: from warm-up on, every sample of `scored` seconds of acquisition time
    t0 = t.min()
    order = np.argsort(seq)
    seq, t, lat = seq[order], t[order], lat[order]
    k0 = int(np.searchsorted(t, t0 + warmup))
    if k0 >= len(seq):
        raise RuntimeError(f"only {len(seq)} samples received, none after the warm-up")
    s0 = int(seq[k0])
    n_expected = round(scored * fs)
    sel = (seq >= s0) & (seq < s0 + n_expected)
    lat_s, got = lat[sel] * 1e3, int(sel.sum())
    missing = n_expected - got
    late = int((lat_s > dt * 1e3).sum())
    # which late samples the witness saw the platform stall during (SYNC -> received)
    gaps = witness.load(stalls_path)
    t_sel = t[sel]
    late_sel = lat_s > dt * 1e3
    stalled = witness.overlaps(gaps, t_sel[late_sel], t_sel[late_sel] + lat_s[late_sel] / 1e3)
    base = witness.overlaps(gaps, t_sel, t_sel + lat_s / 1e3)
    stall_info = {**witness.summary(gaps, float(t_sel.min()), float(t_sel.max())),
                  "late_during_a_stall": int(stalled.sum()),
                  "late_not_during_a_stall": int(late - stalled.sum()),
                  "late_seq": [int(x) for x in seq[sel][late_sel][:50]],
                  "any_sample_during_a_stall": float(base.mean())}
    p50, p99 = float(np.percentile(lat_s, 50)), float(np.percentile(lat_s, 99))
    payload_bytes = int(np.median([len(p) for p in rx.payloads[:200]]))
    floor = measure_floor(int((0.5 if args.tiny else FLOOR_S) * fs), dt, payload_bytes) * 1e3
    one = measure_one_process_floor(fs, 2.0 if args.tiny else SCORED_S, payload_bytes)
    f50 = float(np.percentile(floor, 50)) if len(floor) else None
    f99 = float(np.percentile(floor, 99)) if len(floor) else None
    common = {"scenario": "ground-test", "sample_rate_hz": fs, "warmup_s": warmup, "scored_s": scored,
                  "scored_samples": got, "expected_samples": n_expected, "missing": missing,
                  "late": late, "max_ms": float(lat_s.max()), "p90_ms": float(np.percentile(lat_s, 90)),
                  "p999_ms": float(np.percentile(lat_s, 99.9)), "payload_bytes": payload_bytes,
                  "floor_p50_ms": f50, "floor_p99_ms": f99, "floor_samples": len(floor),
                  "one_process_floor": one, "platform_stalls": stall_info,
                  "service_summary": {k: summary.get(k) for k in (
                      "samples", "lost", "deadline_misses", "latency_ms",
                      "identification_runs", "accepted", "rejected")},
                  "identification": "own worker process (the service's default)",
                  "command": " ".join(cmd[1:])}
    w.add("p50", p50, "ms", peer="Zenoh hop, another process, same payload size and rate (p50)",
          peer_figure=f50, ratio_value=ratio(f50, p50), ratio_is="peer/figure",
          target="p50 ≤ 1 ms", met=p50 <= 1.0, **common)
    w.add("p99", p99, "ms", peer="Zenoh hop (p99)", peer_figure=f99,
          ratio_value=ratio(f99, p99), ratio_is="peer/figure", target="p99 ≤ 3 ms",
          met=p99 <= 3.0, **common)
    # P5b: last frame of a sample received -> hub_loads handed to Zenoh (put returned), the
    # same scored samples, timed inside the service; the Zenoh hop beside it
    st = np.load(stages_path)
    tmpdir.cleanup()
    keep = (st["seq"] >= s0) & (st["seq"] < s0 + n_expected)
    share = (st["put"][keep] - st["frame"][keep]) * 1e3
    share = share[np.isfinite(share)]
    put_ms = (st["put"][keep] - st["handed"][keep]) * 1e3
    put_ms = put_ms[np.isfinite(put_ms)]
    b50, b99 = float(np.percentile(share, 50)), float(np.percentile(share, 99))
    # the CPU the hub path took in the thread that stamped both ends (live: the bus thread)
    cpu_ms = (st["put_cpu"][keep] - st["frame_cpu"][keep]) * 1e3
    cpu_ms = cpu_ms[np.isfinite(cpu_ms)]
    # before it: SYNC -> the sample's last frame processed (the simulator's answer and
    # python-can's delivery of its frames, in the service's process)
    answer_ms = (st["frame"][keep] - st["sync"][keep]) * 1e3
    answer_ms = answer_ms[np.isfinite(answer_ms)]
    p5b = {"samples_timed": int(share.size), "max_ms": float(share.max()),
           "p90_ms": float(np.percentile(share, 90)),
           "zenoh_put_call_p50_ms": float(np.percentile(put_ms, 50)),
           "zenoh_put_call_p99_ms": float(np.percentile(put_ms, 99)),
           "zenoh_hop_p50_ms": f50, "zenoh_hop_p99_ms": f99,
           # the do-nothing pair's last frame -> put returned (its json.dumps and the put)
           "one_process_floor_p50_ms": one.get("last_frame_to_put_p50_ms"),
           "one_process_floor_p99_ms": one.get("last_frame_to_put_p99_ms"),
           "sync_to_last_frame_p50_ms": float(np.percentile(answer_ms, 50)) if answer_ms.size else None,
           "sync_to_last_frame_p99_ms": float(np.percentile(answer_ms, 99)) if answer_ms.size else None,
           "hub_path_cpu_p50_ms": float(np.percentile(cpu_ms, 50)) if cpu_ms.size else None,
           "hub_path_cpu_p90_ms": float(np.percentile(cpu_ms, 90)) if cpu_ms.size else None,
           "timed": "RSRA_STAGE_TIMING hook (daq/stagetiming.py): assembler's sample "
                    "completion by its last TPDO -> Zenoh put returned"}
    w.add("p5b_service_share_p50", b50, "ms", peer="Zenoh hop (p50), same run", peer_figure=f50,
          ratio_value=ratio(f50, b50), ratio_is="peer/figure", target="p50 ≤ 0.1 ms",
          met=b50 <= 0.1, **p5b)
    w.add("p5b_service_share_p99", b99, "ms", peer="Zenoh hop (p99), same run", peer_figure=f99,
          ratio_value=ratio(f99, b99), ratio_is="peer/figure", target="p99 ≤ 1 ms",
          met=b99 <= 1.0, **p5b)
    w.add("one_process_floor_p50", one["latency_p50_ms"], "ms",
          peer="the service, same run (P5 p50)", peer_figure=p50,
          ratio_value=ratio(one["latency_p50_ms"], p50), ratio_is="figure/peer",
          target="reported: a do-nothing master and responder in one process on the same "
                 "virtual bus, the same payload over the same Zenoh hop (bench/floor.py): what "
                 "P5 cannot go below", met=True, **one)
    misses = missing + late
    w.add("deadline_misses", float(misses), f"samples in {scored:g} s (late or missing)",
          target="0 deadline misses (received before the next SYNC) in 60 s",
          met=misses == 0, **common)
    # the misses the platform does not explain: late with no stall of the do-nothing witness
    # during the sample's SYNC -> received, or never received (docs/performance.md)
    own = missing + stall_info["late_not_during_a_stall"]
    w.add("deadline_misses_outside_stalls", float(own),
          f"samples in {scored:g} s (late with the witness not stalled, or missing)",
          peer="the same run's stalls of a do-nothing process (bench/witness.py)",
          peer_figure=float(stall_info["over_3ms"]),
          target="reported: 0 means every miss fell in a platform stall", met=own == 0, **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
