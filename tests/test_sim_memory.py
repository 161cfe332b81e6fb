"""The simulator's per-sample bookkeeping is bounded by what is needed: without a truth file
only the last SYNC cycles (before: a tuple per sample, 1.8 MB a minute, capped at an hour);
with one, compact arrays, the truth spilled to an anonymous file chunk by chunk."""
from __future__ import annotations

import numpy as np
import pytest
from test_sim_bus import lockstep, run_steps

from rsra.sim_bus.bus_sim import RECENT_SAMPLES, SyncLog, TruthBuffer


def test_a_sync_log_without_truth_keeps_only_the_recent_cycles():
    log = SyncLog(keep=False)
    for k in range(20_000):
        log.append((k, k % 240 + 1, 0.005 * k, k % 7 == 0))
        if k == 1000:
            size = log.nbytes
    assert log.nbytes == size <= 32 * RECENT_SAMPLES
    assert len(log) == 20_000 and log[-1] == (19_999, 19_999 % 240 + 1, 0.005 * 19_999, True)
    assert log[20_000 - RECENT_SAMPLES][0] == 20_000 - RECENT_SAMPLES
    with pytest.raises(IndexError):
        log[0]
    assert [e[0] for e in log] == list(range(20_000 - RECENT_SAMPLES, 20_000))
    a = log.arrays()
    assert a["k"].tolist() == list(range(20_000 - RECENT_SAMPLES, 20_000))


def test_a_sync_log_for_a_truth_file_keeps_every_cycle_compactly():
    log = SyncLog(keep=True, max_n=10_000)
    for k in range(12_000):
        log.append((k, -1 if k == 3 else k % 240 + 1, 1e9 + 0.005 * k, k == 5))
    a = log.arrays()
    assert len(log) == 12_000 and len(a) == 10_000  # bounded
    assert a["k"].tolist() == list(range(10_000)) and a["counter"][3] == -1 and a["lost"][5]
    assert a["t"][9_999] == 1e9 + 0.005 * 9_999
    assert log.nbytes <= 40 * 4096  # one chunk in memory, the rest spilled
    assert list(log)[7] == log[7] == (7, 8, 1e9 + 0.035, False)


def test_a_spilled_truth_buffer_keeps_memory_flat_and_gives_the_same_arrays():
    from types import SimpleNamespace

    rng = np.random.default_rng(1)
    mem, spilled = TruthBuffer(chunk=64), TruthBuffer(chunk=64, spill=True)
    rows = [SimpleNamespace(index=k, H=rng.normal(size=6), s=np.uint8(k % 3))
            for k in range(64 * 5 + 17)]
    sizes = []
    for r in rows:
        mem.append(r)
        spilled.append(r)
        sizes.append(spilled.nbytes)
    assert max(sizes) == sizes[0]  # at most one chunk in memory
    assert mem.nbytes > 5 * sizes[0]
    a, b = mem.arrays(), spilled.arrays()
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    np.testing.assert_array_equal(spilled[100].H, rows[100].H)
    assert spilled[-1].index == rows[-1].index


@pytest.mark.parametrize("keep", [False, True])
def test_the_simulator_bookkeeping_stops_growing(cfg, keep):
    sim = lockstep(cfg, keep_samples=keep)
    try:
        sim.start()
        run_steps(sim, 4096)  # one chunk
        before = sim.sync_info.nbytes + sim.samples.nbytes
        run_steps(sim, 4096 * 2)
        after = sim.sync_info.nbytes + sim.samples.nbytes
        assert len(sim.sync_info) == 3 * 4096
        assert after == before
        if keep:  # all of it, for the truth file
            assert len(sim.truth_arrays()["index"]) == 3 * 4096
    finally:
        sim.close()


def test_the_fault_log_is_bounded_and_complete_for_a_truth_file():
    from rsra.sim_bus.faults import FaultInjector, FaultLog, parse_faults

    fi = FaultInjector(parse_faults("jitter:0.3ms"), seed=1)
    fi.log = FaultLog(keep=True, chunk=100)
    for k in range(1050):
        fi.record(k, 0.005 * k, "jitter", None, offset_s=1e-4 * (k % 3))
    assert len(fi.log._mem) == 50 and len(fi.log) == 1050  # 10 chunks spilled
    got = list(fi.log)
    assert [e["sample"] for e in got] == list(range(1050)) and got[7]["offset_s"] == 1e-4
    ring = FaultInjector(parse_faults("jitter:0.3ms"), seed=1)
    ring.log = FaultLog(keep=False, recent=64)
    for k in range(1050):
        ring.record(k, 0.005 * k, "jitter", None)
    assert [e["sample"] for e in ring.log] == list(range(1050 - 64, 1050))
    assert ring.counts == {"jitter": 1050} == fi.counts and ring.events == 1050
    assert ring.dropped_log_entries == 1050 - 64 and fi.dropped_log_entries == 0
