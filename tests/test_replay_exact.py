"""A real-time run and its replay agree record for record (issue 29): what a Zenoh subscriber
took from `rsra run --sim ground-test` in real time (the wall clock, the service's own SYNC
thread, late SYNCs on a loaded machine) equals what `rsra replay` of its recording writes —
`t`, flags and every value of `hub_loads`, `channels` and `innovations`, and the times and
SYNC/sample counts of `health`. Before: 21 of 3 670 samples differed in `t` by 21–162 ms, one
in its flags, and the replay counted 9 bad timestamps the live run had not."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest
import zenoh
from helpers_net import free_tcp_port

from rsra.daq.runtime.telemetry import viewer_config

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
DURATION_S = 6.0  # acquisition time: bounded, and long enough for a few late SYNCs under load
KEYS = ("hub_loads", "channels", "innovations", "health")


def _health_part(d: dict) -> dict:
    """What of a health record the frames decide (the rest is the live process's: queues,
    latency, the identification worker, the recording's own state)."""
    return {"t": d["t"], "samples": d["samples"],
            "sync": {k: d["sync"].get(k) for k in ("duplicate", "bad_timestamp",
                                                   "late_received", "rate_hz")}}


@pytest.mark.slow  # 6 s of real time, then its replay: ~25 s
def test_a_real_time_run_and_its_replay_agree_record_for_record(cfg, tmp_path):
    rec = tmp_path / "rec"
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    got: dict[str, list[dict]] = {k: [] for k in KEYS}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr).rsplit("/", 1)[-1]
        d = json.loads(sample.payload.to_string())
        with lock:
            got[key].append(d)

    with zenoh.open(viewer_config([], listen=[ep])) as z:
        subs = [z.declare_subscriber(f"{cfg.telemetry.prefix}/{k}", on_sample) for k in KEYS]
        # real time (--speed 1, the default): the service's SYNC thread, the wall clock
        proc = subprocess.run(
            [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--seed", "5",
             "--duration", str(DURATION_S), "--record", str(rec),
             "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--zenoh-connect", ep,
             "--log-level", "warning"],
            capture_output=True, text=True, timeout=120, env=ENV, check=False)
        time.sleep(0.3)  # the last records still in the loopback socket
        for s in subs:
            s.undeclare()
    assert proc.returncode == 0, proc.stderr[-2000:]

    out = tmp_path / "replay.jsonl"
    r = subprocess.run([sys.executable, "-m", "rsra", "replay", str(rec), "--out", str(out)],
                       capture_output=True, text=True, timeout=300, env=ENV, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    replayed: dict[str, list[dict]] = {k: [] for k in KEYS}
    for line in out.read_text().splitlines():
        d = json.loads(line)
        key = d.pop("key")
        if key in replayed:
            replayed[key].append(d)

    with lock:
        live = {k: list(v) for k, v in got.items()}
    for key in ("hub_loads", "channels", "innovations"):
        rep = {d["seq"]: d for d in replayed[key]}
        pub = {d["seq"]: d for d in live[key]}
        # the subscriber may miss a few (Zenoh drops under congestion); the replay has all
        assert len(pub) > 0.9 * len(rep) > 0, (key, len(pub), len(rep))
        assert set(pub) <= set(rep), key
        diff = [s for s in sorted(pub) if pub[s] != rep[s]]
        assert not diff, (key, len(diff), [(pub[s], rep[s]) for s in diff[:2]])
    # health: at the same acquisition times, with the same counts the frames decide
    rep_h = {d["t"]: _health_part(d) for d in replayed["health"]}
    pub_h = [_health_part(d) for d in live["health"]]
    pub_h = [h for h in pub_h if h["t"] in rep_h or h["t"] > max(rep_h)]
    assert len(pub_h) >= DURATION_S - 2
    for h in pub_h:
        if h["t"] <= max(rep_h):
            assert h == rep_h[h["t"]], (h, rep_h[h["t"]])
    late = live["health"][-1]["sync"]["late_received"]
    print(f"real time {DURATION_S:g} s: {len(live['hub_loads'])} hub_loads received, "
          f"{len(replayed['hub_loads'])} replayed, 0 differ; late SYNCs received {late}")
