"""Sample assembly by frame order (daq.assembler) through the reader's frame tap (daq.reader):
completeness, missing/lost/malformed/unknown accounting, flags, the acquisition clock."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers_canopen import ACCEL, CELL, T0, accel, cell, heartbeat, msg, period_frames, rotor, sync

from rsra.config.rig import G0, load_config
from rsra.daq.bus.master import EMCY_HISTORY
from rsra.daq.bus.reader import DropQueue, HealthReport, OfflineReader

DT = 0.005


def feed(r: OfflineReader, frames) -> list:
    for m in frames:
        r.feed(m)
    return r.poll()


def samples(items) -> list:
    return [x for x in items if not isinstance(x, HealthReport)]


def test_a_complete_sample_is_passed_on_at_its_last_tpdo(cfg):
    r = OfflineReader(cfg)
    first = period_frames(cfg, 0, T0 - DT)  # (the first sample waits for every node)
    feed(r, first)
    frames = period_frames(cfg, 1, T0 + 0.00000025, status=[0, 0, 1, 0, 2, 0, 3],
                           forces=[1000.0 * (i + 1) for i in range(7)],
                           acc=(10, -20, -1000))
    out = feed(r, frames[:1])  # the SYNC passes seq 0 on
    out = feed(r, frames[1:-1])
    assert out == []  # the accelerometer is still missing: nothing yet
    (s,) = feed(r, frames[-1:])  # no next SYNC needed
    assert (s.seq, s.sync, s.lost_before, s.missing, s.complete) == (1, 2, 0, (), True)
    assert s.t == T0  # SYNC receive time rounded to 1 µs
    np.testing.assert_array_equal(s.T, [1000.0 * (i + 1) for i in range(7)])
    np.testing.assert_allclose(s.accel, [[0.010 * G0, -0.020 * G0, -G0]], rtol=1e-15)
    assert s.cell_status == {"A": 0, "B": 0, "C": 1, "D": 0, "E": 2, "F": 0, "G": 3}
    assert s.flags == ("overrange:C", "fault:E", "overrange:G", "fault:G")
    assert s.omega is None and s.azimuth is None and s.known_H is None and s.drive is None
    h = r.health().to_dict()
    assert h["samples"] == {"complete": 2, "incomplete": 0, "lost": 0}
    assert h["bus"]["frames"] == len(first) + len(frames)


def test_an_incomplete_sample_is_passed_on_at_the_next_sync_with_missing_flagged(cfg):
    r = OfflineReader(cfg)
    assert feed(r, period_frames(cfg, 0, T0, skip=("cell_D",))) == []
    out = feed(r, period_frames(cfg, 1, T0 + DT))
    s0, s1 = samples(out)
    assert s0.missing == ("cell_D",) and "missing:cell_D" in s0.flags and not s0.complete
    assert math.isnan(s0.T[3]) and np.isfinite(np.delete(s0.T, 3)).all()
    assert "D" not in s0.cell_status
    assert s1.complete and s1.seq == 1
    assert r.health().to_dict()["samples"] == {"complete": 1, "incomplete": 1, "lost": 0}


def test_skipped_sync_counters_count_as_lost_samples_and_keep_their_numbers(cfg):
    r = OfflineReader(cfg)
    ks = [0, 1, 4, 5, 236, 237, 238, 239, 240, 243]  # counter = k % 240 + 1: wraps 240 -> 1
    out = []
    for k in ks:
        out += feed(r, period_frames(cfg, k, T0 + k * DT))
    got = [(s.seq, s.sync, s.lost_before) for s in samples(out)]
    assert got == [(0, 1, 0), (1, 2, 0), (4, 5, 2), (5, 6, 0), (236, 237, 230), (237, 238, 0),
                   (238, 239, 0), (239, 240, 0), (240, 1, 0), (243, 4, 2)]
    assert [("lost_before" in s.flags) for s in samples(out)] == [g[2] > 0 for g in got]
    assert r.health().to_dict()["samples"]["lost"] == 2 + 230 + 2
    sy = r.health().to_dict()["sync"]
    assert (sy["duplicate"], sy["bad_timestamp"]) == (0, 0)


def test_without_a_counter_byte_nothing_is_counted_lost():
    cfg0 = load_config(overrides={"sync": {"counter_overflow": 0}})
    r = OfflineReader(cfg0)
    out = []
    for k in range(3):
        out += feed(r, period_frames(cfg0, k, T0 + k * DT))
    out += feed(r, [sync(7, T0 + 3 * DT)])  # a counter where none is configured: tolerated
    r.feed(msg(0x80, b"\x01\x02", T0 + 4 * DT))  # two bytes: malformed, ignored
    assert [(s.seq, s.sync, s.lost_before) for s in samples(out)] == [(0, 0, 0), (1, 0, 0),
                                                                      (2, 0, 0)]
    assert r.health().to_dict()["bus"]["malformed"] == 1


def test_malformed_duplicate_and_orphan_frames_are_counted_never_used(cfg):
    r = OfflineReader(cfg)
    r.feed(cell(0x11, 5.0, 0, T0 - 0.001))  # before any SYNC: orphan
    frames = period_frames(cfg, 0, T0)
    bad = msg(0x193, frames[3].data[:-1], T0 + 1e-6)  # cell_C one byte short
    dup = cell(0x11, -1.0, 0, T0 + 2e-6)  # cell_A twice in one period
    frames = [frames[0], frames[1], dup, bad] + [f for f in frames[2:] if f.arbitration_id != 0x193]
    out = feed(r, frames + period_frames(cfg, 1, T0 + DT))
    s0 = samples(out)[0]
    assert s0.missing == ("cell_C",) and math.isnan(s0.T[2])
    assert s0.T[0] == 1000.0  # the first cell_A value is kept
    b = r.health().to_dict()["bus"]
    assert (b["malformed"], b["duplicate"], b["orphan"]) == (1, 1, 1)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_mark_the_channel_missing(cfg, bad):
    r = OfflineReader(cfg)
    forces = [1.0, 2.0, bad, 4.0, 5.0, 6.0, 7.0]
    out = feed(r, period_frames(cfg, 0, T0, forces=forces) + period_frames(cfg, 1, T0 + DT))
    s0 = samples(out)[0]
    assert math.isnan(s0.T[2]) and s0.missing == ("cell_C",) and "missing:cell_C" in s0.flags
    assert s0.cell_status["C"] == 0  # the status byte arrived and is kept
    assert not s0.complete
    json.dumps(s0.channels_payload(), allow_nan=False)  # strict JSON: null, never NaN


def test_optional_nodes_are_waited_for_once_seen_alive(cfg):
    r = OfflineReader(cfg)
    H = (1.0, 2.0, 80000.0, 4.0, 5.0, 6.0)
    # period 0: rotor and balance report, not known to be alive; the first sample waits for
    # every node (no period before it says which report), so it holds them
    out = feed(r, period_frames(cfg, 0, T0, omega=19.4, az=49152, H=H))
    assert samples(out)[0].omega == pytest.approx(19.4, rel=1e-7)
    # period 1: seen in the last period, so now expected; complete only with them
    frames = period_frames(cfg, 1, T0 + DT, omega=19.4, az=49152, H=H)
    assert samples(feed(r, frames[:-3])) == []
    (s1,) = samples(feed(r, frames[-3:]))
    assert s1.omega == pytest.approx(19.4, rel=1e-7)
    assert s1.azimuth == pytest.approx(1.5 * math.pi, rel=1e-15)
    np.testing.assert_array_equal(s1.known_H, H)
    # period 2: the balance stops: passed on at the next SYNC, flagged once
    feed(r, period_frames(cfg, 2, T0 + 2 * DT, omega=19.4, az=0))
    s2, s3 = samples(feed(r, period_frames(cfg, 3, T0 + 3 * DT, omega=19.4)))
    assert s2.missing == ("balance",) and s2.known_H is None and s2.omega is not None
    # period 3 no longer waits for it (not seen, no operational heartbeat): passed on at
    # its last expected frame
    assert s3.complete and s3.known_H is None
    assert r.health().to_dict()["samples"]["incomplete"] == 1
    # an operational heartbeat makes it expected again
    r.feed(heartbeat(0x41, 0x05, T0 + 4 * DT - 1e-4))
    feed(r, period_frames(cfg, 4, T0 + 4 * DT, omega=19.4))
    s4, s5 = samples(feed(r, period_frames(cfg, 5, T0 + 5 * DT, omega=19.4, H=H)))
    assert s4.missing == ("balance",)
    assert s5.complete and s5.known_H is not None


def test_assembly_is_by_frame_order_not_timestamps(cfg):
    """TPDOs stamped before their SYNC (jittery stamps) still belong to the sample after it;
    the same frames with other timestamps give the same samples (but for t)."""
    frames = period_frames(cfg, 0, T0) + period_frames(cfg, 1, T0 + DT, skip=("cell_G",)) + \
        period_frames(cfg, 2, T0 + 2 * DT)
    a = samples(feed(OfflineReader(cfg), frames))
    rng = np.random.default_rng(1)
    jittered = []
    for m in frames:
        m2 = msg(m.arbitration_id, m.data, m.timestamp + rng.uniform(-0.004, 0.004))
        jittered.append(m2)
    b = samples(feed(OfflineReader(cfg), jittered))
    assert len(a) == len(b) == 3
    for x, y in zip(a, b):
        y.t = x.t
        assert x.same_as(y)
    # monotone clock: a sample is never stamped before the previous one
    assert all(p.t <= q.t for p, q in zip(b, b[1:]))


def test_unknown_error_and_remote_frames_are_counted_and_not_passed_on(cfg):
    r = OfflineReader(cfg)
    frames = period_frames(cfg, 0, T0)
    extra = [
        msg(0x1FF, b"\x00" * 5, T0 + 1e-6),  # TPDO1 of a node nobody configured
        msg(0x191, b"\x00" * 5, T0 + 1e-6, is_extended_id=False, is_remote_frame=True),
        msg(0x80, b"", T0 + 1e-6, is_error_frame=True),  # error class 0x80 == SYNC id
        msg(0x40, b"", T0 + 1e-6, is_error_frame=True),  # bus-off
    ]
    ext = msg(0x191, b"\x00" * 5, T0 + 1e-6)
    ext.is_extended_id = True  # 29-bit frame with a known 11-bit value
    out = feed(r, frames[:2] + extra + [ext] + frames[2:] + [sync(2, T0 + DT)])
    (s,) = samples(out)
    assert s.complete and s.sync == 1 and s.T[0] == 1000.0
    b = r.health().to_dict()["bus"]
    assert (b["unknown"], b["remote"], b["errors"], b["bus_off"]) == (2, 1, 2, 1)
    assert b["malformed"] == b["duplicate"] == 0


def test_heartbeat_watchdog_runs_on_the_acquisition_clock(cfg):
    r = OfflineReader(cfg)
    events = []
    sup = r.supervisor
    base = sup.on_event
    sup.on_event = lambda kind, node: (events.append((kind, node, r.now)), base(kind, node))
    period = cfg.heartbeat.producer_ms / 1000
    t = T0
    last_hb = None
    for k in range(200):  # 1 s of samples; accel_1 beats until 0.5 s, then stops
        t = T0 + k * DT
        if k % 20 == 0 and t - T0 <= 0.5:
            for nc in cfg.nodes:
                r.feed(heartbeat(nc.node_id, 0x05, t))
            last_hb = t
        elif k % 20 == 0:
            for nc in cfg.nodes:
                if nc.name != "accel_1":
                    r.feed(heartbeat(nc.node_id, 0x05, t))
        feed(r, period_frames(cfg, k, t + 1e-6))
    lost = [e for e in events if e[0] == "lost"]
    assert [(k, n) for k, n, _ in lost] == [("lost", "accel_1")]
    t_lost = lost[0][2]
    timeout = cfg.heartbeat.timeout_factor * period
    assert last_hb + timeout < t_lost <= last_hb + timeout + DT  # the first frame past it
    h = r.health().to_dict()["nodes"]["accel_1"]
    assert h["state"] == "lost" and h["losses"] == 1
    assert h["heartbeat_age"] == pytest.approx(r.now - last_hb, abs=1e-6)
    assert r.health().to_dict()["nodes"]["cell_A"]["state"] == "operational"


def test_boot_up_and_emcy_are_decoded_with_a_bounded_history(cfg):
    r = OfflineReader(cfg)
    r.feed(heartbeat(0x12, 0x00, T0))  # boot-up
    assert r.health().to_dict()["nodes"]["cell_B"]["state"] == "booting"
    assert r.health().to_dict()["nodes"]["cell_B"]["boots"] == 1
    r.feed(msg(0x92, bytes.fromhex("01ff8103000000aa"), T0 + 0.001))  # 8 bytes
    r.feed(msg(0x92, bytes.fromhex("0050"), T0 + 0.002))  # 2 bytes: tolerated
    e = r.health().to_dict()["nodes"]["cell_B"]["emcy"]
    assert e[0] == {"t": T0 + 0.001, "code": 0xFF01, "register": 0x81, "info": "03000000aa",
                    "length": 8}
    assert (e[1]["code"], e[1]["register"], e[1]["length"]) == (0x5000, 0, 2)
    for i in range(3 * EMCY_HISTORY):
        r.feed(msg(0x92, bytes([i, 0, 1]), T0 + 0.01 + i * 1e-3))
    h = r.health().to_dict()["nodes"]["cell_B"]
    assert len(h["emcy"]) == EMCY_HISTORY and h["emcy_count"] == 2 + 3 * EMCY_HISTORY
    assert h["emcy"][-1]["code"] == 3 * EMCY_HISTORY - 1


def test_health_is_reported_once_a_second_of_acquisition_time(cfg):
    r = OfflineReader(cfg)
    out = []
    for k in range(700):  # 3.5 s
        out += feed(r, period_frames(cfg, k, T0 + k * DT))
    reports = [x for x in out if isinstance(x, HealthReport)]
    assert [rep.t for rep in reports] == [T0 + 1.0, T0 + 2.0, T0 + 3.0]
    # in the stream at their place: the sample after a report is the first of that second
    i = out.index(reports[0])
    assert out[i - 1].t < T0 + 1.0 <= out[i + 1].t
    p = reports[-1].health.to_dict()
    assert set(p) >= {"t", "nodes", "bus", "samples", "queues", "recording"}
    assert set(p["bus"]) >= {"frames", "errors", "bus_off", "unknown", "malformed"}
    assert set(p["samples"]) == {"complete", "incomplete", "lost"}
    assert p["samples"]["complete"] == 600  # samples of t < T0 + 3 s, counted in frame order
    json.dumps(p, allow_nan=False)


def test_the_health_record_is_frozen_typed_and_serialised_in_the_payloads_order(cfg):
    import dataclasses

    from rsra.daq.bus.health import OMIT, Health, Latency
    from rsra.daq.jsonout import dumps

    r = OfflineReader(cfg)
    for k in range(220):  # past the first report
        feed(r, period_frames(cfg, k, T0 + k * DT))
    h = r.health()
    assert isinstance(h, Health) and h.samples.complete == 220 and h.bus.frames > 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        h.t = 0.0
    with pytest.raises(TypeError):
        h.nodes["cell_A"] = None  # a read-only mapping
    d = h.to_dict()
    # the reader's part, in the order the payload always had; optional keys left out
    assert list(d) == ["t", "nodes", "bus", "samples", "queues", "recording", "sync"]
    assert "last_callback_error" not in d["bus"] and "master_events" not in d["queues"]
    assert list(d["sync"]) == ["duplicate", "bad_timestamp", "late_received", "rate_hz",
                              "rate_low", "discontinuities", "gaps", "gap_longest_s"]
    assert d["recording"] == {"active": False}
    assert list(d["nodes"]["cell_A"]) == ["state", "heartbeat_age", "emcy", "required", "boots",
                                          "losses", "emcy_count"]
    # the service's parts: replaced in, after the reader's, the original unchanged
    h2 = dataclasses.replace(h, latency_ms=Latency(p50=None, p99=None), warnings=("w",))
    assert list(h2.to_dict())[-2:] == ["latency_ms", "warnings"]
    assert h2.to_dict()["warnings"] == ["w"] and h.latency_ms is OMIT
    assert dumps(h2.to_dict()) == json.dumps(h2.to_dict(), separators=(",", ":"),
                                             allow_nan=False)


def test_the_tap_runs_its_timed_tasks_and_a_lowered_deadline_in_frame_order():
    from rsra.daq.bus.reader import Deadlines

    ran: list = []

    class Task:
        def __init__(self, name, due):
            self.name, self.due = name, due

        def run(self, t):
            ran.append((self.name, t))
            self.due = t + 10.0

    d = Deadlines()
    a, b = Task("a", 5.0), Task("b", 7.0)
    d.add(a)
    d.add(b)
    d.run(1.0)  # the first frame: nothing due yet, the schedule set up
    assert ran == [] and d.next == 5.0
    d.run(7.0)  # both due: in registration order
    assert ran == [("a", 7.0), ("b", 7.0)] and d.next == 17.0
    a.due = 9.0  # a task's time moved earlier between two runs (the watchdog on a heartbeat)
    d.lower(9.0)
    d.lower(12.0)  # later than next: no change
    assert d.next == 9.0
    d.run(9.0)
    assert ran[-1] == ("a", 9.0) and d.next == 17.0


def test_the_queue_is_bounded_and_back_pressure_is_counted(cfg):
    r = OfflineReader(cfg, items=DropQueue(4))
    for k in range(10):
        for m in period_frames(cfg, k, T0 + k * DT):
            r.feed(m)
    got = samples(r.poll())
    assert [s.seq for s in got] == [0, 1, 2, 3]
    q = r.health().to_dict()["queues"]["samples"]
    assert (q["dropped"], q["size"], q["max_depth"]) == (6, 4, 4)
    out = samples(feed(r, period_frames(cfg, 10, T0 + 10 * DT)))
    assert [s.seq for s in out] == [10]  # the gap is visible through seq


def test_channels_payload_is_strict_json(cfg):
    r = OfflineReader(cfg)
    out = feed(r, period_frames(cfg, 0, T0, skip=("accel_1",)) + period_frames(cfg, 1, T0 + DT))
    p = samples(out)[0].channels_payload()
    text = json.dumps(p, allow_nan=False)
    back = json.loads(text)
    assert back["accel"] == [[None, None, None]] and back["T"][0] == 1000.0
    assert set(back) == {"seq", "t", "T", "accel", "omega", "azimuth", "known_H", "drive",
                         "status"}


def test_rotor_without_balance_and_the_azimuth_wraps(cfg):
    r = OfflineReader(cfg)
    feed(r, period_frames(cfg, 0, T0, omega=10.0, az=65535))
    s = samples(feed(r, period_frames(cfg, 1, T0 + DT, omega=10.0, az=65535)))[-1]
    assert 0.0 <= s.azimuth < 2 * math.pi
    assert s.azimuth == pytest.approx(2 * math.pi * 65535 / 65536, rel=1e-15)
    r2 = OfflineReader(load_config(overrides={"calibration": {
        "rotor_speed.azimuth": {"offset": 0.5}}}))
    feed(r2, period_frames(cfg, 0, T0, omega=10.0, az=65535))
    s = samples(feed(r2, period_frames(cfg, 1, T0 + DT, omega=10.0, az=65535)))[-1]
    assert s.azimuth == pytest.approx(2 * math.pi * 65535 / 65536 + 0.5 - 2 * math.pi)


def test_frames_of_one_tpdo_from_a_node_reader_does_not_know_are_unknown(cfg):
    r = OfflineReader(cfg)
    r.feed(rotor(0x32, 1.0, 0, T0))  # rotor TPDO layout, but node 0x32 is not configured
    r.feed(accel(0x22, (0, 0, 0), T0))  # accelerometer 2 is not in the default rig
    assert r.health().to_dict()["bus"]["unknown"] == 2


def test_live_the_idle_bus_still_advances_the_clock(cfg):
    """The live wall-clock tick (driven here with explicit times): health and the watchdog
    go on when no frame arrives."""
    r = OfflineReader(cfg)
    r.feed(heartbeat(0x21, 0x05, T0))
    r.tap.tick(T0 + 0.1)
    assert r.poll() == []
    r.tap.tick(T0 + 1.3)  # bus silent for 1.3 s
    (rep,) = r.poll()
    assert isinstance(rep, HealthReport) and rep.t == T0 + 1.3
    assert rep.health.to_dict()["nodes"]["accel_1"]["state"] == "lost"
    assert rep.health.to_dict()["nodes"]["accel_1"]["heartbeat_age"] == pytest.approx(1.3)
    r.tap.tick(T0 + 1.2)  # the clock never goes back
    assert r.now == T0 + 1.3
    # a frame stamped before the tick keeps its own (frame-monotone) time, as in a recording
    r.feed(heartbeat(0x21, 0x05, T0 + 1.25))
    assert r.health().to_dict()["nodes"]["accel_1"]["state"] == "operational"
    assert r.tap.frame_time == T0 + 1.25 and r.now == T0 + 1.3


def test_live_the_tick_runs_no_timed_task_while_frames_flow(cfg):
    """The bus thread may be behind the wall clock (a loaded machine): a tick ahead of frames
    still queued must not judge their node lost, nor put a health report where a replay of
    the recording cannot. The timed tasks run at frame times alone until the bus has been
    quiet for IDLE_TICK_S (issue 29: a live run flagged a sample its replay did not)."""
    from rsra.daq.bus.reader import IDLE_TICK_S

    r = OfflineReader(cfg)
    timeout = cfg.heartbeat.timeout_factor * cfg.heartbeat.producer_ms / 1000
    assert timeout < 0.9 * IDLE_TICK_S
    for k in range(10):  # up to T0 + 0.9
        r.feed(heartbeat(0x21, 0x05, T0 + 0.1 * k))
    # the wall clock past the watchdog's deadline and the health report's, frames queued
    r.tap.tick(T0 + 0.9 + 0.9 * IDLE_TICK_S)
    assert r.poll() == []
    for k in range(10, 20):  # ... processed now
        r.feed(heartbeat(0x21, 0x05, T0 + 0.1 * k))
    (rep,) = r.poll()
    assert rep.t == T0 + 1.0  # at the frame that passed the due time, as in a replay
    assert r.health().to_dict()["nodes"]["accel_1"]["state"] == "operational"
    assert r.supervisor.nodes["accel_1"].losses == 0


CALIBRATED = {"calibration": {"cell_B.force": {"gain": 1.01, "offset": -50.0},
                              "cell_G.force": {"offset": 3.25},
                              "accel_1.z": {"gain": 0.98, "offset": 0.05}}}


@pytest.mark.parametrize("seed,calibrated", [(1, False), (2, True), (3, True)])
def test_samples_match_a_per_frame_reference_on_messy_traffic(cfg, seed, calibrated):
    """The hot path keeps each TPDO's frame and decodes the whole sample at once; a reference
    built frame by frame with DecodeTable.decode (first frame of the right length per TPDO,
    a node counts when all its TPDOs came and every value is finite) must give the same
    samples bit for bit, under drops, duplicates, wrong lengths, NaN/inf, status bits, SYNC
    counters skipped and TPDOs in any order."""
    from rsra.daq.bus.decoder import DecodeTable

    if calibrated:
        cfg = load_config(overrides=CALIBRATED)
    table = DecodeTable(cfg)
    rng = np.random.default_rng(seed)
    required = [nl for nl in table.nodes if nl.required]
    specials = [math.nan, math.inf, -math.inf]
    ov = cfg.sync.counter_overflow
    frames, expected = [], []
    seq = -1
    for k in range(150):
        skip = int(rng.random() < 0.05)  # a lost SYNC before this one
        seq += 1 + skip
        t = T0 + seq * DT
        frames.append(sync(seq % ov + 1, t))
        period = []
        for nl in required:
            for lay in nl.tpdos:
                if rng.random() < 0.08:
                    continue  # dropped
                for _ in range(1 + int(rng.random() < 0.1)):  # sometimes a duplicate
                    if lay.codes == "fB":
                        f = float(np.float32(rng.normal(0.0, 5e4)))
                        if rng.random() < 0.05:
                            f = specials[rng.integers(3)]
                        st_byte = int(rng.integers(4)) if rng.random() < 0.2 else 0
                        data = CELL.pack(f, st_byte)
                    else:
                        data = ACCEL.pack(*(int(x) for x in rng.integers(-32768, 32768, 3)))
                    if rng.random() < 0.05:
                        data = data[:-1]  # malformed
                    period.append(msg(lay.cob_id, data, t + 1e-5 * (len(period) + 1)))
        order = rng.permutation(len(period))
        period = [period[i] for i in order]
        frames.extend(period)
        # the reference, frame by frame
        first: dict[int, bytes] = {}
        for m in period:
            lay = table.tpdos[m.arbitration_id]
            if len(m.data) == lay.length and lay.cob_id not in first:
                first[lay.cob_id] = bytes(m.data)
        values: dict[str, float] = {}
        reported, missing = set(), []
        for nl in required:
            if all(lay.cob_id in first for lay in nl.tpdos):
                reported.add(nl.name)
                for lay in nl.tpdos:
                    values.update(table.decode(lay.cob_id, first[lay.cob_id]))
                if all(math.isfinite(values[c.key]) for c in table.channels[nl.start:nl.stop]):
                    continue
            missing.append(nl.name)
        flags = [f"missing:{m}" for m in missing] + (["lost_before"] if skip else [])
        status = {}
        for c in cfg.cells:
            if c.node in reported:
                status[c.name] = int(values[f"{c.node}.status"])
                if status[c.name] & 1:
                    flags.append(f"overrange:{c.name}")
                if status[c.name] & 2:
                    flags.append(f"fault:{c.name}")
        good = reported - set(missing)  # NaN for every other node's channels
        T = [values[f"{c.node}.force"] if c.node in good else math.nan for c in cfg.cells]
        acc = [[values[f"{a.node}.{x}"] if a.node in good else math.nan for x in "xyz"]
               for a in cfg.accelerometers]
        expected.append((seq, seq % ov + 1, tuple(missing), tuple(flags), status, T, acc, skip))
    r = OfflineReader(cfg, items=DropQueue(1000))
    out = feed(r, frames)
    r.assembler.finish()
    got = samples(out + r.poll())
    assert len(got) == len(expected)
    n_incomplete = 0
    for s, (seq, counter, missing, flags, status, T, acc, skip) in zip(got, expected):
        assert (s.seq, s.sync, s.missing, s.flags, s.lost_before) == (seq, counter, missing,
                                                                         flags, skip)
        assert s.cell_status == status and s.complete == (not missing)
        np.testing.assert_array_equal(s.T, T)  # exact, NaN where missing
        np.testing.assert_array_equal(s.accel, acc)
        n_incomplete += not s.complete
    assert 10 < n_incomplete < len(expected) - 10  # both kinds were exercised


@pytest.mark.parametrize("alive", [False, True])
def test_the_first_sample_holds_everything_its_frames_hold(cfg, alive):
    """Issue 29: at seq 0 a replay published omega, azimuth and known_H as null although their
    frames were in the log — no period before it said the optional nodes report, so it was
    passed on as soon as the required ones had. The first sample now waits for every node
    (or the next SYNC); `missing` is still judged against what was expected."""
    r = OfflineReader(cfg)
    if alive:  # the optional nodes' heartbeats seen first (a recording with the boot)
        for n in ("rotor_speed", "balance"):
            r.feed(heartbeat(cfg.node(n).node_id, 0x05, T0 - 0.01))
    H = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    got = []
    for k in range(3):
        got += samples(feed(r, period_frames(cfg, k, T0 + k * DT, omega=20.0, az=100, H=H)))
    s0 = got[0]
    assert s0.seq == 0 and s0.complete and s0.missing == ()
    assert s0.omega is not None and s0.azimuth is not None and s0.known_H is not None
    assert s0.omega == got[1].omega and np.array_equal(s0.known_H, got[1].known_H)
    # without the optional nodes' frames, seq 0 is passed on at the next SYNC, not flagged
    r2 = OfflineReader(cfg)
    feed(r2, period_frames(cfg, 0, T0, skip=("rotor_speed", "balance")))
    assert samples(r2.poll()) == []
    s = samples(feed(r2, period_frames(cfg, 1, T0 + DT)))[0]
    assert s.seq == 0 and s.omega is None and s.known_H is None and s.missing == ()


def test_the_layout_decodes_one_period_alone(cfg):
    """SampleLayout without the assembler: a period's frames (one per TPDO, bit order), the
    bits reported and expected in, the Sample out — calibrated, the unreported node missing
    and NaN, the lost samples flagged, the SYNC's numbers as given."""
    from rsra.daq.bus.assembler import SampleLayout
    from rsra.daq.bus.decoder import DecodeTable

    table = DecodeTable(cfg)
    layout = SampleLayout(cfg, table)
    forces = [100.0 * (i + 1) for i in range(7)]
    frames, have = list(table.zero_frames), 0
    for m in period_frames(cfg, 3, T0, forces=forces, status=[0, 1, 0, 0, 0, 0, 0],
                           skip=("cell_D",))[1:]:  # (without its SYNC)
        slot = next(k for k, lay in enumerate(table.layouts) if lay.cob_id == m.arbitration_id)
        frames[slot] = bytes(m.data)
        have |= table.layouts[slot].bit
    required = sum(nl.mask for nl in table.nodes if nl.required)
    s = layout.sample(frames, have, required, seq=7, counter=4, t=T0, lost=2)
    assert (s.seq, s.sync, s.t, s.lost_before, s.missing, s.complete) == (
        7, 4, T0, 2, ("cell_D",), False)
    assert s.flags == ("missing:cell_D", "lost_before", "overrange:B")
    assert math.isnan(s.T[3])
    np.testing.assert_array_equal(np.delete(s.T, 3), np.delete(forces, 3))
    assert "D" not in s.cell_status and s.cell_status["B"] == 1
    again = layout.sample(frames, have | table.node("cell_D").mask, required, 8, 5, T0, 0)
    assert again.complete and again.missing == () and again.flags == ("overrange:B",)
