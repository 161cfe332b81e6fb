"""Back-pressure: nothing downstream can stall acquisition, and whatever is dropped instead is
counted where health shows it.

* A Zenoh subscriber that stops consuming for a whole run: high-rate keys are published with
  congestion control DROP (docs/telemetry.md §1), so the service acquires every sample while the
  viewer is blocked; what did not fit in the buffers on the way is dropped, and the viewer
  sees it as gaps in `seq` (with BLOCK, Zenoh stalls `put()` for up to 5 s per put).
* A stalled disk: live, the recorder writes through a bounded queue on its own thread, so the
  bus thread goes on assembling samples; frames that do not fit are counted, never waited for.
* A slow estimator: the reader's sample queue drops (counted) instead of blocking the bus
  thread, and the estimator predicts through the samples it never saw (their seq is kept).

No timing is asserted: each test checks an outcome that a stalled path cannot produce (the
samples arrive although the consumer is blocked), with generous waits for the threads.
"""
from __future__ import annotations

import json
import threading
import time

import can
import numpy as np
import zenoh
from helpers_canopen import channel_name, period_frames, wait_until
from helpers_net import free_tcp_port

from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.bus.reader import DropQueue, HealthReport, Listen, Reader
from rsra.daq.bus.replay import read_frames
from rsra.daq.runtime.service import Service, ServiceOptions
from rsra.daq.runtime.telemetry import viewer_config

T0 = 1_700_000_000.0


def test_a_stalled_zenoh_subscriber_never_stalls_acquisition(cfg):
    n = 12000  # 60 s of acquisition, ≈ 10 MB of records: more than every buffer on the way
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    released = threading.Event()
    got: list[int] = []
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=None, duration=n / cfg.sample_rate_hz,
                                      zenoh=True, zenoh_listen=[f"tcp/127.0.0.1:{free_tcp_port()}"],
                                      zenoh_connect=[ep], identification=False, seed=3))
    first = threading.Event()
    svc.add_sink(lambda key, payload: first.set() if key == "hub_loads" else None)

    def stalled(sample: zenoh.Sample) -> None:
        # a viewer that stops consuming (blocked in its callback) for the whole run
        released.wait(300)
        if str(sample.key_expr).endswith("/hub_loads"):
            got.append(json.loads(sample.payload.to_string())["seq"])

    with zenoh.open(viewer_config([], listen=[ep])) as z:
        sub = z.declare_subscriber(f"{cfg.telemetry.prefix}/**", stalled)
        th = threading.Thread(target=svc.run)
        th.start()
        th.join(300)  # a publisher that waited for the viewer would still be here
        alive = th.is_alive()
        released.set()
        th.join(60)
        assert not alive, "acquisition stalled behind the subscriber"
        time.sleep(0.5)  # what is still in the loopback socket
        sub.undeclare()
    s = svc.summary
    assert s["samples"] == n and s["lost"] == 0  # every sample acquired and estimated
    assert svc.reader.health().to_dict()["queues"]["samples"]["dropped"] == 0
    seqs = sorted(set(got))
    assert seqs  # the link is up: what the buffers held arrives once the viewer moves again
    missed = n - len(seqs)
    assert missed > 0  # the rest was dropped downstream (DROP), not waited for ...
    assert all(0 <= k < n for k in seqs)  # ... and a viewer sees it as seq it never got
    print(f"stalled subscriber: {n} samples acquired while the viewer was blocked; "
          f"{len(seqs)} delivered afterwards, {missed} dropped by Zenoh (DROP), seen as seq gaps")


def test_a_high_rate_put_never_waits_for_a_stalled_subscriber(cfg):
    """The publisher's blocking, measured where it would happen: every high-rate put returns
    while the subscriber is stalled. Zenoh closes a link blocked for `wait_before_close`
    (5 s by default), after which a BLOCK put returns too — enough for a BLOCK publisher to pass
    the test above. Here the publisher's session waits 10 min before closing, so a BLOCK put
    stays in `put()` for as long as the subscriber does not move."""
    from rsra.daq.runtime.telemetry import HIGH_RATE_KEYS, TelemetryPublisher, zenoh_config

    n = 600  # × 3 keys × ~16 kB = ~30 MB: more than every buffer on the way
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = cfg.telemetry.prefix
    entered, released = threading.Event(), threading.Event()
    got: list[int] = []

    def stalled(sample: zenoh.Sample) -> None:
        entered.set()
        released.wait(300)
        got.append(json.loads(sample.payload.to_string())["seq"])

    pub_conf = zenoh_config(cfg.telemetry, listen=[], connect=[ep])
    pub_conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                          "600000000")  # µs
    filler = list(np.linspace(0.0, 1.0, 800))
    with zenoh.open(viewer_config([], listen=[ep])) as zs:
        sub = zs.declare_subscriber(f"{prefix}/**", stalled)
        with zenoh.open(pub_conf) as zp:
            tp = TelemetryPublisher(zp, prefix)
            th = None
            try:
                # the route is up once the subscriber's callback is entered: it now stalls
                probes = 0
                while not entered.wait(0.05):
                    tp.publish("hub_loads", {"seq": -1})
                    probes += 1
                    assert probes < 600, "no route to the subscriber"
                done: list[int] = []
                longest = [0.0]

                def publish_all() -> None:
                    for k in range(n):
                        for key in HIGH_RATE_KEYS:
                            t0 = time.perf_counter()
                            tp.publish(key, {"seq": k, "filler": filler})
                            longest[0] = max(longest[0], time.perf_counter() - t0)
                        done.append(k)

                th = threading.Thread(target=publish_all)
                th.start()
                th.join(120)  # a put that waited for the subscriber would still be there
                puts_while_stalled = len(done) * len(HIGH_RATE_KEYS)
                assert not released.is_set()
            finally:
                released.set()
                if th is not None:
                    th.join(60)
                time.sleep(0.5)  # what is still in the loopback socket
                tp.close()
        sub.undeclare()
    assert puts_while_stalled == n * len(HIGH_RATE_KEYS), "a put waited for the subscriber"
    delivered = len({k for k in got if k >= 0})
    assert delivered < n  # the buffers overflowed: a BLOCK put would have had to wait
    print(f"stalled subscriber: {puts_while_stalled} high-rate puts returned while it was "
          f"stalled (longest {longest[0] * 1e3:.1f} ms); {delivered} of {n} seq delivered "
          "afterwards")


def _live_reader(cfg, tmp_path, **kw):
    ch = channel_name("backpressure")
    r = Reader(cfg, interface="virtual", channel=ch, nodes=Listen(), record=tmp_path / "rec",
               **kw)
    r.start()
    tx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False)
    return r, tx


def test_a_stalled_disk_never_stalls_the_bus_thread_and_every_lost_frame_is_counted(
        cfg, tmp_path):
    r, tx = _live_reader(cfg, tmp_path, items=DropQueue(8192))
    rec = r.recorder
    disk = threading.Event()
    real = rec._logger.on_message_received

    def stalled(msg):  # the disk stops answering (NFS hang, dying medium, …)
        disk.wait(300)
        real(msg)

    rec._logger.on_message_received = stalled
    periods = 2000  # 18 000 frames: more than the writer queue holds
    try:
        sent = 0
        for k in range(periods):
            for m in period_frames(cfg, k, T0 + k * cfg.sample_period_s):
                tx.send(m)
                sent += 1
        # the bus thread keeps assembling samples while the disk is stalled
        wait_until(lambda: r.tap.frames >= sent, timeout=300, what="the bus thread")
        items = r.poll()
        samples = [s for s in items if not isinstance(s, HealthReport)]
        assert [s.seq for s in samples] == list(range(periods))
        st = rec.status()
        q = st["queue"]
        assert q["overflow"] > 0 and st["dropped"] == q["overflow"] and st["frames"] == 0
        # every frame is either handed to the writer or counted as dropped
        assert q["queued"] + q["overflow"] == sent
        assert q["queued"] <= q["size"] + 2  # the queue, the frame in hand, a tick marker
        h = r.health().to_dict()["recording"]
        assert h["queue"]["overflow"] == q["overflow"] and h["active"]
    finally:
        disk.set()  # the disk comes back: the queued frames are written at close
        r.close()
        tx.shutdown()
    frames = list(read_frames([tmp_path / "rec"]))
    assert len(frames) == rec.frames == rec.queued == sent - rec.dropped  # nothing else lost
    assert [m.timestamp for m in frames] == sorted(m.timestamp for m in frames)
    print(f"stalled disk: {sent} frames on the bus, {len(frames)} recorded, "
          f"{rec.dropped} counted as dropped; {periods} samples assembled meanwhile")


def test_a_slow_estimator_costs_counted_samples_and_the_filter_predicts_through_them(cfg,
                                                                                   tmp_path):
    qsize = 64
    r, tx = _live_reader(cfg, tmp_path, items=DropQueue(qsize))
    first, second = 400, 40
    try:
        sent = 0
        for k in range(first):  # the estimator is busy: nobody takes samples meanwhile
            for m in period_frames(cfg, k, T0 + k * cfg.sample_period_s):
                tx.send(m)
                sent += 1
        wait_until(lambda: r.tap.frames >= sent, timeout=300, what="the bus thread")
        batch1 = r.poll()  # what the queue kept
        for k in range(first, first + second):  # the estimator keeps up again
            for m in period_frames(cfg, k, T0 + k * cfg.sample_period_s):
                tx.send(m)
                sent += 1
        wait_until(lambda: r.tap.frames >= sent, timeout=300, what="the bus thread")
        batch2 = r.poll()
        h = r.health().to_dict()["queues"]["samples"]
    finally:
        r.close()
        tx.shutdown()
    s1 = [s for s in batch1 if not isinstance(s, HealthReport)]
    s2 = [s for s in batch2 if not isinstance(s, HealthReport)]
    assert len(batch1) == qsize and s1[0].seq == 0
    gap = s2[0].seq - s1[-1].seq - 1  # samples the estimator never saw: they keep their seq
    assert gap > 0 and s2[0].lost_before == 0  # nothing was lost on the bus
    # counted in health: the samples, plus any 1 Hz health report that did not fit either
    n_health = sum(isinstance(x, HealthReport) for x in batch1 + batch2)
    assert gap <= h["dropped"] <= gap + n_health + 2
    # the estimator predicts through the gap (Φ^gap) and flags it like a SYNC loss
    pipe = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    twin = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    for s in s1:
        pipe.process(s)
        twin.process(s)
    from dataclasses import replace

    out = pipe.process(s2[0]).records[0][1]
    told = twin.process(replace(s2[0], lost_before=gap,
                                flags=s2[0].flags + ("lost_before",))).records[0][1]
    assert "lost_before" in out["flags"]
    np.testing.assert_array_equal(pipe.load_filter.state, twin.load_filter.state)
    np.testing.assert_array_equal(out["H"], told["H"])
