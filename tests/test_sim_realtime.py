"""The simulator's real-time fast paths (sim_bus.bus_sim) change nothing the bus carries:
the physics block computed ahead of its SYNC (half a period after the SYNC that ended the
previous block), the whole answer to each SYNC built ahead of it (undone by NMT, SDO or an
unexpected SYNC counter) and the immutable frame payloads give the frames and the fault log of
lock-step bit for bit."""
from __future__ import annotations

import time

import can
import pytest
from helpers_canopen import wait_until
from test_sim_nodes import channel_name

from rsra.config.rig import load_config
from rsra.sim_bus.bus_sim import SimulatedTime, Simulator, WallClock
from rsra.sim_bus.drivers import LockstepSim, RealtimeSim
from rsra.sim_bus.physics import AircraftPhysics
from rsra.sim_bus.scenarios import load_scenario

BLOCK = 5  # samples per physics block
RATE = 50.0  # samples/s: the block is computed 10 ms after a SYNC, 10 ms before the next one


def _physics(cfg, seed: int) -> AircraftPhysics:
    return AircraftPhysics(cfg, load_scenario("ground-test"), seed=seed, block_size=BLOCK)


def _sync_and_tpdos(frames) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in frames
            if m.arbitration_id == 0x80 or 0x180 <= m.arbitration_id < 0x580]


@pytest.mark.timeout(60)
def test_physics_computed_ahead_in_real_time_gives_the_lockstep_frames():
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    n = 40  # 0.8 s of real time, 8 block boundaries
    chan = channel_name("ls-ahead")
    with LockstepSim(cfg, physics=_physics(cfg, 11), seed=11, autostart=True,
                     channel=chan) as sim:
        ref = []
        for _ in range(n):
            ref.extend(sim.step())
    assert sim.prefetched == 0  # lock-step never computes ahead
    ref = _sync_and_tpdos(ref)

    chan = channel_name("rt-ahead")
    rx = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        sim = RealtimeSim(cfg, physics=_physics(cfg, 11), seed=11, autostart=True, channel=chan)
        with sim:
            assert sim.run(duration=n * cfg.sample_period_s) == n
        got = []
        while (m := rx.recv(0)) is not None:
            assert isinstance(m.data, bytearray)  # receivers get python-can's usual type
            got.append(m)
    finally:
        rx.shutdown()
    assert _sync_and_tpdos(got) == ref
    # the blocks after the first were computed ahead (a late ticker may miss one: then the
    # SYNC computes it, as before — the frames above are the same either way)
    assert 1 <= sim.prefetched <= n // BLOCK


# ------------------------------------------------------------------------------------------
# the whole answer to a SYNC built ahead of it (real time): same frames, same fault log

FAULTS = ("drop:cell_A:0.3;malformed:cell_B:0.2;stuck:accel_1@0.2-0.4;overrange:cell_C@0.3-0.5;"
          "sensor:cell_F@0.1-0.3;silent:cell_D@0.1-0.2;reboot:cell_E@0.5;unknown:0.2;"
          "errorframe:0.1;lostsync:0.1;jitter:0.5ms")


def _not_heartbeats(frames) -> list[tuple[int, bytes, bool]]:
    """Every frame but heartbeats/boot-ups (0x700+id: live they follow the wall clock)."""
    return [(m.arbitration_id, bytes(m.data), m.is_error_frame) for m in frames
            if not 0x700 <= m.arbitration_id < 0x780]


@pytest.mark.timeout(60)
def test_answers_built_ahead_in_real_time_give_the_lockstep_frames_and_faults():
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    n = 40  # 0.8 s of real time; every fault kind fires or opens/closes a window in it
    chan = channel_name("ls-plan")
    with LockstepSim(cfg, physics=_physics(cfg, 5), seed=5, autostart=True,
                     channel=chan, faults=FAULTS) as sim:
        ref = []
        for _ in range(n):
            ref.extend(sim.step())
    assert sim.prepared == 0  # lock-step never builds ahead
    ref_log = sim.fault_log
    kinds = {e["kind"] for e in ref_log}
    assert {"drop", "malformed", "unknown", "errorframe", "lostsync", "jitter", "stuck",
            "overrange", "sensor", "silent", "reboot"} <= kinds  # the check below covers them

    chan = channel_name("rt-plan")
    rx = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        sim = RealtimeSim(cfg, physics=_physics(cfg, 5), seed=5, autostart=True, channel=chan,
                          faults=FAULTS)
        with sim:
            assert sim.run(duration=n * cfg.sample_period_s) == n
        got = []
        while (m := rx.recv(0)) is not None:
            assert type(m) is can.Message and isinstance(m.data, bytearray)
            got.append(m)
    finally:
        rx.shutdown()
    assert _not_heartbeats(got) == _not_heartbeats(ref)
    assert sim.fault_log == ref_log
    # most answers went out as built ahead (a late ticker leaves one to its SYNC, as before);
    # the samples with a window change, a reboot, an EMCY or a lost SYNC are never built ahead
    assert sim.prepared >= 1
    assert sim.plans_discarded == 0


def _sdo_write_u8(node_id: int, index: int, sub: int, value: int) -> can.Message:
    """A raw CiA 301 expedited SDO download of one byte (no blocking client needed)."""
    return can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                       data=bytes([0x2F, index & 0xFF, index >> 8, sub, value, 0, 0, 0]))


def _follow_run(cfg, chan: str, clock, build_ahead: bool):
    """Follow mode, the master's frames by hand and the simulator driven by hand (no thread):
    NMT start, SYNCs, and between two SYNCs the events that change an answer already built
    (NMT stop/start of a node, an SDO write of a transmission type, a skipped SYNC counter);
    ``build_ahead``: each answer built before those events, as RealtimeSim's ticker does.
    Returns (the simulator's frames, simulator)."""
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    node_id = next(n.node_id for n in cfg.nodes if n.name == "cell_B")
    out = []
    try:
        sim = Simulator(cfg, physics=_physics(cfg, 3), seed=3, channel=chan, clock=clock)
        with sim:
            def sync(counter: int, k: int, before=()):
                if build_ahead:
                    sim.prepare_next()
                for msg in before:
                    master.send(msg)
                sim.pump()
                out.extend(sim.answer_sync(counter, k * sim.dt))

            master.send(can.Message(arbitration_id=0, is_extended_id=False, data=[1, 0]))
            sim.pump()
            sync(1, 1)
            sync(2, 2)
            sync(3, 3, [can.Message(arbitration_id=0, is_extended_id=False, data=[2, node_id])])
            sync(4, 4, [can.Message(arbitration_id=0, is_extended_id=False, data=[1, node_id])])
            sync(5, 5, [_sdo_write_u8(node_id, 0x1800, 2, 2)])  # TPDO1 every 2nd SYNC
            for k in range(6, 10):
                sync(k, k)
            sync(12, 10)  # the master skipped two counters
            sync(13, 11)
        sim.check()
    finally:
        master.shutdown()
    return [(m.arbitration_id, bytes(m.data)) for m in out
            if not 0x700 <= m.arbitration_id < 0x780], sim


@pytest.mark.timeout(60)
def test_nmt_sdo_and_counter_changes_undo_an_answer_built_ahead():
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    ref, _ = _follow_run(cfg, channel_name("follow-ls"), SimulatedTime(), build_ahead=False)
    got, rt = _follow_run(cfg, channel_name("follow-rt"), WallClock(), build_ahead=True)
    assert got == ref
    node_id = next(n.node_id for n in cfg.nodes if n.name == "cell_B")
    tpdo1 = [d for c, d in ref if c == 0x180 + node_id]
    assert len(tpdo1) == 2 + 1 + 3  # SYNC 1-2, stopped at 3, started at 4, every 2nd from 5
    # the plans met by NMT (2), SDO (1) and a skipped counter (1) were undone, the rest sent
    assert rt.plans_discarded >= 4 and rt.prepared >= 6


def _tpdos(frames) -> list[tuple[int, bytes]]:
    return [(m.arbitration_id, bytes(m.data)) for m in frames if 0x180 <= m.arbitration_id < 0x580]


@pytest.mark.timeout(60)
def test_real_time_behind_a_master_sends_answers_built_ahead_and_the_lockstep_frames():
    """RealtimeSim in follow mode (the service's real-time source): a master's SYNC frames
    come through the Notifier; the driver listens for SYNC after the simulator has answered
    and has the next answer built ahead (``prepared``), which gives lock-step's frames."""
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    n = 20  # 0.4 s of real time
    start = can.Message(arbitration_id=0, is_extended_id=False, data=[1, 0])
    chan = channel_name("follow-ref")
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        with LockstepSim(cfg, physics=_physics(cfg, 3), seed=3, channel=chan) as sim:
            master.send(start)
            ref = _tpdos(f for k in range(1, n + 1) for f in sim.on_sync(k, k * sim.dt))
    finally:
        master.shutdown()
    chan = channel_name("follow-live")
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        with RealtimeSim(cfg, physics=_physics(cfg, 3), seed=3, channel=chan) as sim:
            master.send(start)
            for k in range(1, n + 1):
                time.sleep(sim.dt)  # pace only: nothing below depends on how long it took
                master.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=[k]))
            wait_until(lambda: len(sim.sync_info) == n, timeout=20.0, what="every SYNC answered")
            sim.check()
        got = list(iter(lambda: master.recv(0), None))
    finally:
        master.shutdown()
    assert _tpdos(got) == ref
    # the answers built ahead went out as built (a late ticker leaves one to its SYNC)
    assert sim.prepared >= 1 and sim.plans_discarded == 0


def test_sent_frames_reach_receivers_as_independent_plain_messages():
    chan = channel_name("txmsg")
    cfg = load_config()
    rxs = [can.Bus(interface="virtual", channel=chan, receive_own_messages=False) for _ in range(2)]
    try:
        with LockstepSim(cfg, "ground-test", seed=1, autostart=True,
                         channel=chan) as sim:
            sent = sim.step()
        got = [list(iter(lambda r=rx: r.recv(0), None)) for rx in rxs]
    finally:
        for rx in rxs:
            rx.shutdown()
    boot = len(got[0]) - len(sent)  # the boot-up frames came before the step
    for g in got:
        assert [(m.arbitration_id, bytes(m.data), m.timestamp, m.dlc) for m in g[boot:]] == \
            [(m.arbitration_id, bytes(m.data), m.timestamp, m.dlc) for m in sent]
        assert all(type(m) is can.Message and isinstance(m.data, bytearray) and m.is_rx
                   for m in g)
    got[0][-1].data[0] ^= 0xFF  # one receiver's copy is its own
    assert got[1][-1].data[0] != got[0][-1].data[0]


@pytest.mark.timeout(60)
def test_at_short_periods_each_sync_builds_the_next_answer_in_its_own_wake_up(monkeypatch):
    """At periods of ``RealtimeSim.INLINE_PLAN_PERIOD_S`` or less the SYNC's own callback
    builds the next answer (the ticker half a period later is often late there): with the
    ticker's work-ahead switched off, every SYNC after the first still finds its answer built,
    and the frames are lock-step's."""
    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    monkeypatch.setattr(RealtimeSim, "INLINE_PLAN_PERIOD_S", 2.0 / RATE)  # RATE counts as short
    monkeypatch.setattr(RealtimeSim, "_schedule_ahead", lambda self: None)  # no ticker plans
    n = 20
    start = can.Message(arbitration_id=0, is_extended_id=False, data=[1, 0])
    chan = channel_name("inline-ref")
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        with LockstepSim(cfg, physics=_physics(cfg, 3), seed=3, channel=chan) as sim:
            master.send(start)
            ref = _tpdos(f for k in range(1, n + 1) for f in sim.on_sync(k, k * sim.dt))
    finally:
        master.shutdown()
    chan = channel_name("inline-live")
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        with RealtimeSim(cfg, physics=_physics(cfg, 3), seed=3, channel=chan) as sim:
            master.send(start)
            for k in range(1, n + 1):
                time.sleep(sim.dt)  # pace only: the SYNCs are handled in order, one thread
                master.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=[k]))
            wait_until(lambda: len(sim.sync_info) == n, timeout=20.0, what="every SYNC answered")
            sim.check()
        got = list(iter(lambda: master.recv(0), None))
    finally:
        master.shutdown()
    assert _tpdos(got) == ref
    assert sim.prepared == n - 1 and sim.plans_discarded == 0  # all but the first built ahead


def test_a_sync_wakes_the_ticker_only_when_it_would_sleep_past_the_work_ahead():
    """A SYNC sets the work-ahead half a period later; the ticker, which already plans to wake
    by then when the SYNCs keep their rhythm, is not woken at the SYNC — the moment the
    service receives the answer and computes the hub loads (docs/performance.md P5b) — and is
    woken when it is planning (None) or would sleep past it. (No thread runs: the decision
    alone, on stated times.)"""
    import threading

    cfg = load_config(overrides={"rig": {"sample_rate_hz": RATE}})
    sim = RealtimeSim(cfg, physics=_physics(cfg, 3), seed=3, channel=channel_name("wake"))
    try:
        sim._ticker = threading.Thread(target=lambda: None)  # present, never started
        for planned, woken in ((lambda now: now, False), (lambda now: now + 0.7 * sim.dt, False),
                               (lambda now: None, True), (lambda now: now + 2.0 * sim.dt, True)):
            sim._wake.clear()
            sim._ticker_wake_at = planned(time.time())
            sim._schedule_ahead()
            assert sim._wake.is_set() is woken, planned
            assert sim._prefetch_at is not None
    finally:
        sim._ticker = None
        sim.close()
