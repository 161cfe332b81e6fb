"""Late SYNCs: the sample slots our SYNC producer never took are counted and reported
(health `sync`, the demo view, `rsra listen`); a sample rate below 99 % is flagged."""
from __future__ import annotations

import threading
from types import SimpleNamespace

import can
import pytest
from helpers_canopen import T0, period_frames

from rsra.daq.bus.master import SyncProducer
from rsra.daq.bus.reader import HealthReport, OfflineReader

P = 0.005


class FakeTime:
    """The producer's clock and wait, and a bus whose send takes ``stalls[k]`` seconds."""

    def __init__(self, stalls: dict[int, float], n: int):
        self.now = 100.0
        self.stalls, self.n = stalls, n
        self.sent = 0

    def clock(self) -> float:
        return self.now

    def make(self) -> SyncProducer:
        t = self

        class Bus:
            def send(self, msg):
                t.now += t.stalls.get(t.sent, 0.0)
                t.sent += 1
                if t.sent >= t.n:
                    p._stop.set()

        msgs = [can.Message(arbitration_id=0x80, data=[c], is_extended_id=False)
                for c in range(1, 241)]
        p = SyncProducer(Bus(), msgs, P, threading.Lock(), clock=self.clock, start=False)

        def wait(s):
            self.now += max(0.0, s)
            return p._stop.is_set()

        p._wait = wait
        return p


@pytest.mark.parametrize("stalls", [
    {}, {100: 0.023}, {k: 0.6 * P for k in range(200, 400)}, {50: 0.2, 51: 0.004, 900: 0.0126},
], ids=["on-time", "one-stall", "each-slightly-late", "mixed"])
def test_every_period_not_taken_is_counted(stalls):
    """Slots the schedule offered (elapsed time / period) = SYNCs sent + periods not taken
    (to within the one slot in progress)."""
    ft = FakeTime(stalls, 1000)
    start = ft.now
    p = ft.make()
    p._run()
    slots = (ft.now - start) / P
    assert p.sent == 1000
    assert abs(slots - (p.sent + p.periods_not_taken)) <= 1.0, (slots, p.periods_not_taken)
    if not stalls:
        assert p.late == 0 and p.periods_not_taken == 0
    else:
        assert p.late >= 1 and p.periods_not_taken >= 1


def test_a_real_stall_of_the_sync_thread_is_counted():
    """The threaded producer (real time; bounded): a send that blocks 60 ms skips at least
    the 11 slots it covers (lower bound only: a slower machine skips more)."""
    sends = []

    class Bus:
        def send(self, msg):
            sends.append(msg)
            if len(sends) == 5:
                threading.Event().wait(0.06)

    msgs = [can.Message(arbitration_id=0x80, data=[1], is_extended_id=False)]
    p = SyncProducer(Bus(), msgs, P, threading.Lock())
    try:
        deadline = threading.Event()
        while len(sends) < 20 and not deadline.wait(0.01):
            pass
    finally:
        p.stop()
    assert p.late >= 1 and p.periods_not_taken >= 11


def _reader_with_producer(cfg, producer):
    r = OfflineReader(cfg)
    r.nodes.master = SimpleNamespace(sync_task=producer, events_pending=0, events_dropped=0)
    return r


def test_health_reports_periods_not_taken_and_the_views_show_them(cfg):
    from rich.console import Console

    from rsra.daq.cli.commands.listen import KeyStats
    from rsra.daq.cli.commands.listen import render as listen_render
    from rsra.daq.cli.demo_view import DemoState
    from rsra.daq.cli.demo_view import render as demo_render

    ft = FakeTime({10: 0.05}, 100)
    p = ft.make()
    p._run()
    r = _reader_with_producer(cfg, p)
    h = r.health().to_dict()
    assert h["sync"]["periods_not_taken"] == p.periods_not_taken >= 9
    assert h["sync"]["late"] == p.late
    con = Console(width=250, record=True)
    hs = KeyStats("health")
    hs.add(h, 0.0)
    con.print(listen_render({"health": hs}, "rsra/bench", "si", 1.0))
    assert f"not taken {p.periods_not_taken}" in con.export_text()
    st = DemoState(cfg, [0.0] * 6, ("a",))
    st.on_record("health", h)
    con = Console(width=250, record=True)
    con.print(demo_render(st, "demo", "si"))
    assert f"not taken {p.periods_not_taken}" in con.export_text()


def _run_frames(cfg, times):
    r = OfflineReader(cfg)
    reports = []
    for k, t in enumerate(times):
        for m in period_frames(cfg, k, t):
            r.feed(m)
        reports += [x.health.to_dict() for x in r.poll() if isinstance(x, HealthReport)]
    return reports


def test_a_sample_rate_below_99_percent_is_flagged(cfg):
    n = 12 * 200
    ok = _run_frames(cfg, [T0 + k * P for k in range(n)])
    assert ok[-1]["sync"]["rate_low"] is False
    assert ok[-1]["sync"]["rate_hz"] == pytest.approx(200.0, abs=0.5)
    # every 50th SYNC re-phased half a period late (as our producer does when it is late):
    # 1 % of the slots never taken, nothing lost by the counter
    times, t = [], T0
    for k in range(n):
        t += P * (1.5 if k % 50 == 49 else 1.0)
        times.append(t)
    slow = _run_frames(cfg, times)
    assert slow[-1]["samples"]["lost"] == 0
    assert slow[-1]["sync"]["rate_hz"] < 198.5 and slow[-1]["sync"]["rate_low"] is True
