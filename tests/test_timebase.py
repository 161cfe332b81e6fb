"""Frames stamped with a clock of their own (an interface with a device clock, or frames
from another machine) never move the live acquisition clock (docs/reliability.md "Frame
timebase"; issue 17)."""
from __future__ import annotations

import copy
import threading
import time

import can
import pytest
from can.interfaces.virtual import VirtualBus

from rsra.daq.bus.reader import (
    FOREIGN_TIMEBASE_S,
    IDLE_TICK_S,
    LOCAL_LAG_S,
    HealthReport,
    Listen,
    Reader,
    Timebase,
)
from rsra.sim_bus.drivers import RealtimeSim
from tests.helpers_canopen import channel_name


class _Clock:
    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_local_timestamps_are_kept_exactly():
    clock = _Clock()
    tb = Timebase(block=4, clock=clock)
    for k in range(20):
        clock.t = 1000.0 + 0.005 * k + 0.002
        ts = 1000.0 + 0.005 * k + 0.0001 * (k % 3)  # receipt 1.7–2 ms after the stamp
        assert tb.map(ts) == ts


@pytest.mark.parametrize("offset", [-20.0, 3600.0, -1.7e9])
def test_a_foreign_clock_is_mapped_onto_the_wall_clock_keeping_the_spacing(offset):
    clock = _Clock()
    tb = Timebase(block=8, clock=clock)
    out = []
    for k in range(40):
        clock.t = 1000.0 + 0.005 * k + 0.0005 + 0.0003 * (k % 5)  # latency 0.5–1.7 ms
        out.append(tb.map(1000.0 + 0.005 * k + offset))
    for k, t in enumerate(out):
        assert abs(t - (1000.0 + 0.005 * k + 0.0005)) < 0.0004  # near the latency floor
    assert abs(tb.shift - (0.0005 - offset)) < 0.0004 and abs(tb.shift) > FOREIGN_TIMEBASE_S


@pytest.mark.parametrize("offset", [0.0, -20.0])
@pytest.mark.parametrize("bad", [1e6, -1e6])
def test_a_few_frames_stamped_far_away_do_not_move_the_mapping(offset, bad):
    """They stay bad timestamps for the SYNC clock (docs/reliability.md): the mapping of
    every other frame is unchanged."""
    clock = _Clock()
    tb = Timebase(block=32, clock=clock)
    for k in range(200):
        clock.t = 1000.0 + 0.005 * k + 0.001
        ts = 1000.0 + 0.005 * k + offset + (bad if k % 40 == 7 else 0.0)
        t = tb.map(ts)
        if k % 40 != 7:
            assert abs(t - (1000.0 + 0.005 * k + (0.0 if offset == 0.0 else 0.001))) < 1e-6


class _OffsetBus(VirtualBus):
    """A virtual bus whose frames carry a clock ``OFFSET`` s away from the wall clock."""

    OFFSET = -20.0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        m = copy.copy(msg)
        m.timestamp = msg.timestamp + self.OFFSET
        super().send(m, timeout)


def test_frames_from_an_offset_clock_give_every_sample_at_the_wall_clock(cfg):
    """The simulator producing SYNC in real time, its frames 20 s behind the wall clock: the
    live reader assembles every sample, none lost, stamped near the wall clock, no bad
    timestamp (before the mapping: the idle tick ran 20 s ahead of the frames)."""
    chan = channel_name("timebase")
    bus = _OffsetBus(channel=chan, preserve_timestamps=True, receive_own_messages=False)
    sim = RealtimeSim(cfg, "ground-test", seed=2, autostart=True, bus=bus)
    samples, health = [], []
    try:
        with Reader(cfg, interface="virtual", channel=chan, nodes=Listen()) as reader:
            with sim:
                runner = threading.Thread(target=sim.run, args=(2.0,), daemon=True)
                runner.start()
                while runner.is_alive():
                    item = reader.get(timeout=0.1)
                    if isinstance(item, HealthReport):
                        health.append(item.health.to_dict())
                    elif item is not None:
                        samples.append((item, time.time()))
    finally:
        sim.close()
        bus.shutdown()
    assert len(samples) > 100 and health
    first = samples[0][0].seq
    assert [s.seq for s, _ in samples] == list(range(first, first + len(samples)))
    assert all(s.lost_before == 0 for s, _ in samples[1:])
    assert all(abs(s.t - wall) < 1.0 for s, wall in samples)
    assert all(h["sync"]["bad_timestamp"] == 0 for h in health)


class _OnePerIdBus(VirtualBus):
    """An interface with periodic sending of its own that keeps one message per COB-ID
    (python-can-remote's server): a counter SYNC sequence would go out with one counter."""

    def _send_periodic_internal(self, msgs, period, duration=None, autostart=True,
                                modifier_callback=None):
        raise AssertionError("the SYNC counter sequence was given to the interface")


def test_a_counter_sync_sequence_uses_our_producer_on_an_interface_without_sequences(cfg):
    import canopen

    from rsra.daq.bus.decoder import DecodeTable
    from rsra.daq.bus.master import CanopenMaster, SyncProducer, Supervisor

    assert cfg.sync.counter_overflow > 1
    table = DecodeTable(cfg)
    bus = _OnePerIdBus(channel=channel_name("seq"))
    net = canopen.Network(bus)
    sup = Supervisor(cfg, table, set_alive=lambda *a: None, on_event=lambda *a: None,
                     wake=lambda t: None)
    master = CanopenMaster(cfg, table, net, sup, clock=time.time)
    try:
        master.start_sync()
        assert isinstance(master.sync_task, SyncProducer)
    finally:
        master.stop()
        bus.shutdown()


@pytest.mark.parametrize("lag", [0.06, 0.3, 0.45])
def test_a_busy_start_is_not_taken_for_a_foreign_clock(lag):
    """Issue 29: on a loaded machine the bus thread started `lag` s late with frames queued;
    the first frame's delay alone moved every timestamp by it, the next block moved them
    back, and every SYNC after the jump back was a bad timestamp (111 in the first second
    of a real-time run; its replay counted 3). A backlog being caught up is not an offset."""
    clock = _Clock()
    tb = Timebase(block=32, clock=clock)
    n_backlog = int(lag / 0.0005)  # frames queued 0.5 ms apart, read 20 µs apart
    for k in range(n_backlog + 400):
        ts = 1000.0 + 0.0005 * k
        clock.t = 1000.0 + lag + 2e-5 * k if k < n_backlog else ts + 0.0003
        clock.t = max(clock.t, ts + 0.0003)
        assert tb.map(ts) == ts, k
    assert LOCAL_LAG_S < IDLE_TICK_S  # an unmapped lag never lets the idle tick run ahead
