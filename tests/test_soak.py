"""Soak: the whole service as a user runs it (`rsra run --sim ground-test --speed max
--record DIR --faults …`: recording on, so the simulator also keeps the truth for
`truth.npz`), for `RSRA_SOAK_S` seconds of acquisition at 200 samples/s (default 600, the
10 minutes of docs/performance.md P7), identification running in its process, a fault every few
seconds — in lock-step (the samples of real time, deterministic, counted against the
simulator). Nothing is patched out. Deselected by default (`-m soak`); bounded: about 1 s of
wall time per 5 s of acquisition.

Checks: no crash; every sample published or counted lost (seq kept), lost samples equal to
the SYNCs the simulator dropped; every incomplete sample counted in health; resident memory
flat (growth < 5 MB after the warm-up — the first minute, or the first third of a shorter
run — in the service process, simulator included, and in the identification worker).
"""
from __future__ import annotations

import os
from collections import Counter

import pytest

from rsra.daq.runtime.service import Service, ServiceOptions

SOAK_S = float(os.environ.get("RSRA_SOAK_S", "600"))
PAGE = os.sysconf("SC_PAGE_SIZE")
# one fault every FAULT_EVERY_S seconds, cycling through every kind that recovers by itself
# (a reboot needs the service's SDO restart: covered by tests/test_faults_e2e.py)
FAULT_EVERY_S = 4.0
TEMPLATES = [
    "silent:cell_B@{a}-{a3}", "overrange:cell_C@{a}-{a3}", "sensor:cell_D@{a}-{a3}",
    "stuck:cell_E@{a}-{a2}", "drop:cell_F:0.05@{a}-{a2}", "malformed:cell_A:0.05@{a}-{a2}",
    "lostsync:0.03@{a}-{a2}", "unknown:0.1@{a}-{a2}", "errorframe:0.05@{a}-{a2}",
    "jitter:0.3ms@{a}-{a2}", "silent:accel_1@{a}-{a6}",
]


def fault_spec(duration_s: float) -> str:
    items = []
    k = 0
    t = 2.0
    while t + 2.0 < duration_s:
        items.append(TEMPLATES[k % len(TEMPLATES)].format(a=f"{t:g}", a2=f"{t + 2:g}",
                                                         a3=f"{t + 0.3:g}", a6=f"{t + 0.6:g}"))
        k += 1
        t += FAULT_EVERY_S
    return ";".join(items)


def rss_bytes(pid: int | str = "self") -> int:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * PAGE


@pytest.mark.soak
def test_soak_ten_minutes_with_faults(cfg, tmp_path):
    fs = cfg.sample_rate_hz
    n = round(SOAK_S * fs)
    from tests.helpers_net import free_tcp_port

    # telemetry on (loopback), as `rsra run` has it
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=None, duration=SOAK_S, seed=11,
                                      zenoh_listen=[f"tcp/127.0.0.1:{free_tcp_port()}"],
                                      record=str(tmp_path / "rec"), faults=fault_spec(SOAK_S)))
    state = {"next": 0, "gaps": 0, "hub": 0, "incomplete": 0, "invalid": 0, "angles": 0}
    rss: list[tuple[float, int, int]] = []  # (acquisition s, service RSS, worker RSS)
    t0: list[float] = []

    def sink(key, payload):
        if key == "hub_loads":
            seq = payload["seq"]
            state["gaps"] += seq - state["next"]
            state["next"] = seq + 1
            state["hub"] += 1
            flags = payload["flags"]
            state["incomplete"] += any(f.startswith("missing:") for f in flags)
            state["invalid"] += "invalid" in flags
        elif key == "angles":
            state["angles"] += 1
        elif key == "health":
            t0[:] = t0 or [payload["t"]]
            w = svc.worker.proc.pid if svc.worker is not None and svc.worker.alive() else None
            rss.append((payload["t"] - t0[0], rss_bytes(), rss_bytes(w) if w else 0))

    svc.add_sink(sink)
    summary = svc.run()
    injected = Counter(svc.sim.faults.counts)  # every fault the simulator injected, by kind

    # nothing lost that is not counted
    assert summary["samples"] + summary["lost"] == n
    assert state["hub"] == summary["samples"] and state["gaps"] == summary["lost"]
    assert summary["lost"] == injected["lostsync"]
    assert h_sync_ok(svc.reader.health().to_dict())
    h = svc.reader.health().to_dict()
    assert h["samples"]["incomplete"] == state["incomplete"]
    assert h["samples"]["lost"] == summary["lost"]
    assert h["queues"]["samples"]["dropped"] == 0 and h["bus"]["callback_errors"] == 0
    assert h["bus"]["unknown"] == injected["unknown"]
    assert h["bus"]["errors"] == injected["errorframe"]
    assert h["bus"]["malformed"] == injected["malformed"]
    rec = h["recording"]
    assert rec["error"] is None and rec["dropped"] == 0, rec
    assert state["angles"] >= SOAK_S / cfg.identification.period_s - 2
    assert summary.get("identification_runs", 0) == state["angles"]

    assert (tmp_path / "rec" / "truth.npz").is_file()  # the truth was kept, as for a user

    # memory flat after the warm-up (docs/performance.md P7: growth < 5 MB after the first minute)
    warm = min(60.0, SOAK_S / 3)
    after = [r for r in rss if r[0] >= warm]
    assert len(after) >= (SOAK_S - warm) * 0.9
    growth = max(r[1] for r in after) - after[0][1]
    worker = [r[2] for r in after if r[2]]
    wgrowth = max(worker) - worker[0] if worker else 0
    print(f"soak {SOAK_S:g} s (memory after {warm:g} s): {summary['samples']} samples, {summary['lost']} lost (all "
          f"counted), {state['incomplete']} incomplete, {state['invalid']} invalid, "
          f"{state['angles']} identification runs; faults {dict(injected)}; service RSS "
          f"{after[0][1] / 1e6:.1f} -> max {max(r[1] for r in after) / 1e6:.1f} MB "
          f"(+{growth / 1e6:.2f}), worker +{wgrowth / 1e6:.2f} MB")
    curve = [f"{r[0]:.0f}s {r[1] / 1e6:.1f}" for r in rss[:: max(1, len(rss) // 10)]]
    print("service RSS (acquisition time, MB): " + ", ".join(curve))
    assert growth < 5e6, growth
    assert wgrowth < 5e6, wgrowth


def h_sync_ok(h: dict) -> bool:
    """A lock-step run: no duplicated SYNC, no bad timestamp (the simulated clock is exact;
    jittered SYNCs stay within a period)."""
    return h["sync"]["duplicate"] == 0 and h["sync"]["bad_timestamp"] == 0
