"""The batch reader (issue 26, docs/performance.md "One wake-up per sample"): the bus thread
takes every frame the bus has received when it wakes (rsra.canbus.BatchNotifier), and the
simulator answers a SYNC in one send on the in-process virtual bus. Nothing may be lost or
reordered by it, and a sample is the same however its frames are split over wake-ups."""
from __future__ import annotations

import threading

import can
import pytest
from helpers_canopen import T0, channel_name, period_frames, wait_until

from rsra.canbus import BatchNotifier, EchoFirstVirtualBus, recv_batch, send_batch
from rsra.daq.bus.reader import FrameClock, HealthReport, Listen, OfflineReader, Reader

BURST = 10_000


class _Collect(can.Listener):
    def __init__(self) -> None:
        self.ids: list[int] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.ids.append(int.from_bytes(msg.data[:2], "little"))


def _frame(i: int) -> can.Message:
    return can.Message(arbitration_id=0x181 + i % 7, data=i.to_bytes(2, "little"),
                       is_extended_id=False, timestamp=T0 + i * 1e-6)


@pytest.mark.parametrize("kind", ["echo-first", "python-can"])
def test_a_10000_frame_burst_loses_no_frame_and_keeps_their_order(kind):
    """A sender thread sends 10 000 frames — single sends and batches of up to 13 — while
    the batch notifier reads; every frame arrives once, in the order sent. ``python-can``:
    python-can's own virtual bus (no batch read: recv with a zero timeout)."""
    ch = channel_name("burst")
    bus_cls = EchoFirstVirtualBus if kind == "echo-first" else can.interfaces.virtual.VirtualBus
    rx = bus_cls(channel=ch)
    tx = EchoFirstVirtualBus(channel=ch)
    got = _Collect()
    notifier = BatchNotifier(rx, [got], 0.05)
    try:
        frames = [_frame(i) for i in range(BURST)]

        def send() -> None:
            i = 0
            while i < BURST:
                n = 1 + i % 13
                chunk = frames[i:i + n]
                if n % 2:
                    send_batch(tx, chunk)
                else:
                    for m in chunk:
                        tx.send(m)
                i += n

        th = threading.Thread(target=send)
        th.start()
        th.join(30)
        wait_until(lambda: len(got.ids) >= BURST, 30, "the burst")
    finally:
        notifier.stop(2.0)
        tx.shutdown()
        rx.shutdown()
    assert got.ids == list(range(BURST))
    assert notifier.frames == BURST
    assert 1 <= notifier.wakeups <= BURST


def test_recv_batch_takes_what_is_queued_in_order_and_nothing_more():
    ch = channel_name("batch")
    rx = EchoFirstVirtualBus(channel=ch)
    tx = EchoFirstVirtualBus(channel=ch)
    try:
        assert recv_batch(rx, 10) == []
        send_batch(tx, [_frame(i) for i in range(25)])
        first = recv_batch(rx, 10)
        rest = recv_batch(rx, 100)
        assert [int.from_bytes(m.data, "little") for m in first + rest] == list(range(25))
        assert len(first) == 10 and recv_batch(rx, 10) == []
        assert all(m.is_rx for m in first + rest)
    finally:
        tx.shutdown()
        rx.shutdown()


def test_a_batch_send_reaches_the_sender_first_and_its_own_copy_is_not_rx():
    """send_many keeps send's ordering guarantee (own copy first) and its flags."""
    ch = channel_name("own")
    tx = EchoFirstVirtualBus(channel=ch, receive_own_messages=True)
    rx = EchoFirstVirtualBus(channel=ch)
    try:
        send_batch(tx, [_frame(i) for i in range(3)])
        own, other = recv_batch(tx, 10), recv_batch(rx, 10)
        assert [m.data for m in own] == [m.data for m in other]
        assert not any(m.is_rx for m in own) and all(m.is_rx for m in other)
        assert own[0] is not other[0]
    finally:
        tx.shutdown()
        rx.shutdown()


def _samples(items):
    return [x for x in items if not isinstance(x, HealthReport)]


@pytest.mark.parametrize("split", [1, 3, 8])
def test_a_sample_split_across_two_wake_ups_is_assembled_the_same(cfg, split):
    """SYNC and the first ``split`` frames in one wake-up, the rest in a second: the live
    reader (bus thread, batch reads) gives the samples an offline reader gives for the same
    frames fed one by one, bit for bit."""
    ch = channel_name("split")
    tx = EchoFirstVirtualBus(channel=ch, preserve_timestamps=True)
    periods = [period_frames(cfg, k, T0 + 0.005 * k) for k in range(4)]
    ref = OfflineReader(cfg)
    for p in periods:
        for m in p:
            ref.feed(m)
    expected = _samples(ref.poll())
    rx = EchoFirstVirtualBus(channel=ch)
    r = Reader(cfg, rx, nodes=Listen(), clock=FrameClock())
    try:
        r.start()
        for p in periods:
            w0 = r.wakeups[0]
            send_batch(tx, p[:1 + split])
            wait_until(lambda: r.wakeups[1] >= sum(len(q) for q in periods[:periods.index(p)])
                       + 1 + split, 5, "the first part")
            assert r.wakeups[0] > w0  # the two parts come in two wake-ups
            send_batch(tx, p[1 + split:])
            wait_until(lambda: r.wakeups[1] >= sum(len(q) for q in periods[:periods.index(p) + 1]),
                       5, "the second part")
        wait_until(lambda: r.items.queue.qsize() >= len(expected) - 1, 5, "the samples")
        got = _samples(r.poll())
        r.assembler.finish()
        got += _samples(r.poll())
    finally:
        r.close()
        tx.shutdown()
        rx.shutdown()
    ref.assembler.finish()
    expected += _samples(ref.poll())
    assert len(got) == len(expected) == 4
    assert all(a.same_as(b) for a, b in zip(got, expected))


def test_the_live_reader_counts_wake_ups_and_frames(cfg):
    ch = channel_name("count")
    tx = EchoFirstVirtualBus(channel=ch)
    rx = EchoFirstVirtualBus(channel=ch)
    r = Reader(cfg, rx, nodes=Listen(), clock=FrameClock())
    try:
        assert r.wakeups is None  # not started: no bus thread
        r.start()
        frames = period_frames(cfg, 0, T0)
        send_batch(tx, frames)
        wait_until(lambda: r.wakeups[1] >= len(frames), 5, "the frames")
        assert r.wakeups == (1, len(frames))  # one send, one wake-up, every frame
    finally:
        r.close()
        tx.shutdown()
        rx.shutdown()
