"""The reader: bus → decode → samples, on any python-can interface (docs/bus.md, docs/telemetry.md).

::

    python-can bus ─▶ one Notifier ─▶ FrameTap ─▶ canopen Network.subscribe callbacks
                                  │  (clock, counts,  ├─ SampleAssembler (SYNC, TPDOs)
                                  │   unknown IDs)    ├─ Supervisor (heartbeat, EMCY)
                                  │                   └─ canopen SDO/NMT (master)
                                  └─▶ Recorder (every frame, own transmissions too)
    SampleAssembler / 1 Hz health ─▶ bounded queue ─▶ consumer (``Reader.get``)

The FrameTap replaces canopen's own MessageListener (one listener, one dispatch per frame):
it keeps the ONE acquisition clock (model.md §8.3: the frame timestamps — simulated time in
lock-step, recorded time in replay, the wall clock live — made monotone and quantised to
1 µs; the frame is re-stamped with it before the recorder sees it), counts frames, error
frames, bus-off and unknown COB-IDs, and dispatches through canopen's
``Network.subscribe`` table. Heartbeat watchdog and the 1 Hz health report run when that
clock passes their deadline. Live, an idle bus still advances
the clock from the wall clock (the only place that reads it).

Replay feeds recorded frames to the same FrameTap (:meth:`Reader.feed`), so it assembles
exactly the samples the live reader did.
"""
from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen

from rsra.daq.bus.assembler import Sample, SampleAssembler
from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.bus.master import (
    COB_EMCY,
    COB_HEARTBEAT,
    COB_NMT,
    COB_SDO_RX,
    COB_SDO_TX,
    CanopenMaster,
    Supervisor,
)
from rsra.daq.bus.recorder import Recorder
from rsra.canbus import open_bus, shutdown_bus

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x00000040  # SocketCAN error class bit in an error frame's identifier
LSS_COB_IDS = (0x7E4, 0x7E5)  # CiA 305 (canopen's network subscribes to them)
COB_TIME = 0x100
DEFAULT_QUEUE = 1024  # samples (≈ 5 s at 200 samples/s)
TICK_S = 0.1  # live idle tick of the acquisition clock
NOTIFIER_CYCLE_S = 0.1
RATE_WINDOW = 10  # health periods over which the sample rate is measured
RATE_LOW_FRACTION = 0.99  # below this fraction of sample_rate_hz: sync.rate_low
TIMEBASE_BLOCK = 256  # frames per estimate of a foreign frame timebase's offset
TIMEBASE_FIRST_BLOCK = 16  # the first block (a quick first estimate)
TIMEBASE_QUANTILE = 0.1  # the block's quantile of receipt delays taken as the offset
FOREIGN_TIMEBASE_S = 0.05  # a receipt delay floor beyond this: frames carry a foreign clock
_floor = math.floor


@dataclass(frozen=True, slots=True)
class HealthReport:
    """The 1 Hz ``health`` payload, emitted in frame order into the sample stream."""

    t: float
    payload: dict


def quantise_us(t: float) -> float:
    """Round a timestamp to 1 µs (6× cheaper than ``round(t, 6)``; the two can differ by one
    µs within float error of a half-µs tie — harmless, because the recordings store the
    quantised value itself, which every log format gives back exactly)."""
    return math.floor(t * 1e6 + 0.5) / 1e6


class FrameTap(can.Listener):
    """The one per-frame entry point (bus thread, or the replay loop)."""

    def __init__(self, reader: Reader, network: canopen.Network, known: set[int]):
        self.reader = reader
        self.subscribers = network.subscribers  # canopen's subscribe table (live dict)
        self.known = frozenset(known)
        asm = reader.assembler
        self.sync_cob = asm.sync_cob_id
        self.stamp_sync = asm.stamp_sync
        self.stamp_frame = asm.clock.stamp_frame
        self._clock = asm.clock
        self._ahead_s = asm.clock.tol * asm.clock.period
        self.frames = 0
        self.errors = 0
        self.bus_off = 0
        self.unknown = 0
        self.remote = 0
        self.callback_errors = 0
        self.last_callback_error: str | None = None
        self.frame_time = -math.inf  # monotone, quantised frame time
        self.tick_time = -math.inf  # live idle tick (wall clock)
        self.deadline = -math.inf  # next watchdog / health time (first frame: set up)
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        self.frames += 1
        t = _floor(msg.timestamp * 1e6 + 0.5) / 1e6  # 1 µs, the recordings' resolution
        # a time far from where the SYNC counter / schedule puts the frame is re-stamped
        # (counted as a bad timestamp; docs/reliability.md)
        cid = msg.arbitration_id
        if cid == self.sync_cob and not (msg.is_extended_id or msg.is_error_frame
                                         or msg.is_remote_frame):
            ts = self.stamp_sync(msg.data, t, self.frame_time)
        elif self._clock._suspect is None and t <= self.frame_time + self._ahead_s:
            ts = t  # stamp_frame's common case, inline (nothing pending, not far ahead)
        else:
            ts = self.stamp_frame(t, self.frame_time)
        if ts != t:
            t = _floor(ts * 1e6 + 0.5) / 1e6
        if t > self.frame_time:
            self.frame_time = t
            if t >= self.deadline:
                self.reader._on_time(t)
        else:
            t = self.frame_time  # never backwards (own transmissions stamped at send time)
        # the frame carries the acquisition time from here on: the recorder (next listener)
        # writes exactly this value, so a replay sees the same clock bit for bit
        msg.timestamp = t
        cbs = self.subscribers.get(cid)
        if cbs is None or msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            self._classify(msg, cid, cbs)
            return
        data = msg.data
        for cb in cbs:
            try:
                cb(cid, data, t)
            except Exception as e:  # canopen only logs these; count them visibly
                self.callback_errors += 1
                self.last_callback_error = f"0x{cid:03X}: {type(e).__name__}: {e}"

    __call__ = on_message_received  # the Notifier calls listeners directly: one frame less

    def _classify(self, msg: can.Message, cid: int, cbs: list | None) -> None:
        if msg.is_error_frame:
            self.errors += 1
            if cid & CAN_ERR_BUSOFF:
                self.bus_off += 1
        elif msg.is_extended_id or cid not in self.known:
            self.unknown += 1  # counted, never passed on
        elif msg.is_remote_frame:
            self.remote += 1
        # else: a known COB-ID nobody listens to (our own SDO requests, NMT): nothing to do

    @property
    def now(self) -> float:
        """The acquisition clock: frame time, or the live idle tick when it is later."""
        return max(self.frame_time, self.tick_time)

    def tick(self, wall: float) -> None:
        """Live idle tick: advance the clock from the wall clock when no frame does."""
        with self.lock:
            t = quantise_us(wall)
            if t > self.tick_time:
                self.tick_time = t
                if t > self.frame_time and t >= self.deadline:
                    self.reader._on_time(t)

    def on_error(self, exc: Exception) -> None:
        # a bus read failed (interface down, …): count it, keep the notifier running
        self.errors += 1
        self.last_callback_error = f"bus: {type(exc).__name__}: {exc}"

    def stop(self) -> None:
        pass


class Timebase:
    """Live: frame timestamps in the local wall clock's timebase (docs/reliability.md
    "Frame timebase").

    The acquisition clock's idle tick reads the wall clock, so frame times must be on it
    too. SocketCAN and python-can's virtual bus stamp frames with it; an interface with a
    clock of its own (a device clock counting from power-up, another machine's clock) does
    not. Each frame's receipt delay ``wall − timestamp`` is the transport latency plus the
    offset between the two clocks; a low quantile of it over a block of frames (robust to a
    few frames stamped far away: those stay bad timestamps, SyncClock) estimates the offset
    with the latency's floor. An estimate within ``FOREIGN_TIMEBASE_S`` of zero is the local
    clock and the timestamps are kept exactly; otherwise every timestamp is moved by the
    estimate (the frames keep their own spacing, only the origin moves). The first frame
    gives the first estimate; a short first block, then one block after another, follow
    drift."""

    def __init__(self, block: int = TIMEBASE_BLOCK, clock: Callable[[], float] = time.time):
        self.block = block
        self.clock = clock
        self.offset: float | None = None  # estimated wall − frame time (s)
        self.shift = 0.0  # what is added to every timestamp (0.0: the local timebase)
        self._d: list[float] = []
        self._n = min(block, TIMEBASE_FIRST_BLOCK)

    def map(self, ts: float) -> float:
        d = self.clock() - ts
        if self.offset is None:
            self._set(d)
        self._d.append(d)
        if len(self._d) >= self._n:
            ds = sorted(self._d)
            self._set(ds[int(TIMEBASE_QUANTILE * (len(ds) - 1))])
            self._d.clear()
            self._n = self.block
        return ts + self.shift

    def _set(self, offset: float) -> None:
        self.offset = offset
        self.shift = offset if abs(offset) > FOREIGN_TIMEBASE_S else 0.0


class _LockedTap(can.Listener):
    """The tap behind the lock shared with the live idle tick, frames mapped onto the
    wall clock's timebase first (Timebase)."""

    def __init__(self, tap: FrameTap):
        self.tap = tap
        self.timebase = Timebase()

    def on_message_received(self, msg: can.Message) -> None:
        with self.tap.lock:
            msg.timestamp = self.timebase.map(msg.timestamp)
            self.tap.on_message_received(msg)

    __call__ = on_message_received

    def on_error(self, exc: Exception) -> None:
        self.tap.on_error(exc)

    def stop(self) -> None:
        pass


class Reader:
    """Calibrated, time-stamped samples from a CANopen bus.

    Live::

        with Reader(cfg, interface="virtual", channel="rig") as r:   # boots the nodes
            while (item := r.get(timeout=1.0)) is not None:
                ...  # Sample, or HealthReport once a second of acquisition time

    Offline (replay, benchmarks): ``Reader.offline(cfg)``, then ``feed(msg)`` and ``poll()``.

    ``master=False`` only listens (no NMT, no SDO, no SYNC): a recording of another master, a
    bus whose nodes start by themselves, lock-step runs where the simulator owns the nodes.
    ``restart_nodes=True`` with ``master=False`` (lock-step): the nodes were booted by someone
    else, but once :meth:`supervise` is called a node that reboots is reconfigured over SDO
    and started by this reader's master thread, as the live master does (docs/bus.md §3 "Boot and
    supervision"); a lock-step driver (sim_bus.drivers) holds time while :meth:`busy`.
    ``overflow="drop"`` (live) never blocks the bus thread: a full queue drops the item and
    counts it; ``"block"`` (lock-step) makes the bus thread wait and counts the waits.
    """

    def __init__(self, cfg: RigConfig, *, bus: can.BusABC | None = None,
                 interface: str | None = None, channel: Any = None,
                 bus_kwargs: dict | None = None, master: bool = True,
                 record: str | Path | None = None, record_format: str | None = None,
                 queue_size: int = DEFAULT_QUEUE, overflow: str = "drop",
                 wall_clock: bool | None = None, table: DecodeTable | None = None,
                 offline: bool = False, periodic_sync: bool = True,
                 restart_nodes: bool = False):
        if overflow not in ("drop", "block"):
            raise ValueError(f"overflow must be 'drop' or 'block', not {overflow!r}")
        self.cfg = cfg
        self.table = table or DecodeTable(cfg)
        self.offline = offline
        self._bus = bus
        self._own_bus = False
        self._bus_args = dict(bus_kwargs or {})
        if interface is not None:
            self._bus_args["interface"] = interface
        if channel is not None:
            self._bus_args["channel"] = channel
        self.use_master = master and not offline
        self.restart_nodes = restart_nodes and not master and not offline
        self.periodic_sync = periodic_sync
        self.wall_clock = (not offline) if wall_clock is None else wall_clock
        self.overflow = overflow
        self.queue: queue.Queue[Sample | HealthReport] = queue.Queue(queue_size)
        self.queue_size = queue_size
        self.dropped = 0
        self.blocked = 0
        self.max_depth = 0
        self.health_period_s = 1.0
        self._next_health = math.inf
        self.last_health: dict | None = None
        self._rate_hist: deque[tuple[float, int]] = deque(maxlen=RATE_WINDOW + 1)
        self._rate_hz: float | None = None
        # --record DIR is taken as given (and must be new); recording.dir in the config is a
        # parent folder: every run records into its own time-stamped subfolder
        self.record_dir = Path(record) if record else (
            Path(cfg.recording.dir) / time.strftime("%Y%m%d-%H%M%S")
            if cfg.recording.dir and not offline else None)
        self.record_format = record_format
        self.recorder: Recorder | None = None
        self.master: CanopenMaster | None = None
        self._tick_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._started = False

        self.network = canopen.Network(bus)
        # the bus thread wakes this often to see a stop (canopen's default: 1 s per close)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.assembler = SampleAssembler(cfg, self.table, self._put)
        self.supervisor = Supervisor(cfg, self.table, set_alive=self.assembler.set_alive,
                                     on_event=self._on_node_event, wake=self._wake)
        known = self._known_cob_ids()
        self.tap = FrameTap(self, self.network, known)
        # our callbacks first: canopen's own (added by the master) must not shadow them
        for cob, cb in self.supervisor.callbacks().items():
            self.network.subscribe(cob, cb)
        for cob, cb in self.assembler.callbacks().items():
            self.network.subscribe(cob, cb)

    @classmethod
    def offline(cls, cfg: RigConfig, **kw: Any) -> Reader:
        """A reader without a bus: feed it frames (replay, benchmarks)."""
        kw.setdefault("master", False)
        return cls(cfg, offline=True, **kw)

    def _known_cob_ids(self) -> set[int]:
        known = {COB_NMT, COB_TIME, self.cfg.sync.cob_id, *LSS_COB_IDS, *self.table.tpdos}
        for nl in self.table.nodes:
            known |= {COB_HEARTBEAT + nl.node_id, COB_EMCY + nl.node_id,
                      COB_SDO_TX + nl.node_id, COB_SDO_RX + nl.node_id}
        return known

    # -- lifecycle --------------------------------------------------------------------------
    def start(self, notifier: bool = True) -> Reader:
        """Connect, start recording, boot the nodes (master) and start SYNC. Raises
        master.BootError (after closing everything) when the nodes cannot be started.

        ``notifier=False`` (lock-step, no master): no bus thread; call :meth:`pump`."""
        if self.offline:
            raise RuntimeError("an offline reader has no bus: use feed()")
        if self._started:
            return self
        self._started = True
        try:
            if self._bus is None:
                args = dict(self._bus_args)
                # the service's own SYNC/NMT/SDO must come back to the tap and the recorder
                args.setdefault("receive_own_messages", True)
                self._bus = open_bus(**args)  # virtual: own copy first (rsra.canbus)
                self._own_bus = True
                self.network.bus = self._bus
            elif (self.use_master and self.cfg.sync.producer == "service"
                  and getattr(self._bus, "receive_own_messages", True) is False):
                raise ValueError("the service produces SYNC but this bus does not deliver its "
                                 "own transmissions: open it with receive_own_messages=True")
            listeners: list[can.Listener] = [
                _LockedTap(self.tap) if self.wall_clock else self.tap]
            if self.record_dir is not None:
                # live: a writer thread behind a bounded queue (a slow disk never stalls
                # the bus thread); lock-step: inline (nothing runs in real time)
                self.recorder = Recorder(self.record_dir, self.cfg, fmt=self.record_format,
                                         threaded=self.wall_clock)
                listeners.append(self.recorder)
            self.network.listeners = listeners
            if self.use_master:
                if not notifier:
                    raise ValueError("the master needs the bus thread (SDO): notifier=True")
                self.master = CanopenMaster(self.cfg, self.table, self.network, self.supervisor,
                                            clock=lambda: self.tap.now,
                                            periodic_sync=self.periodic_sync)
            elif self.restart_nodes:  # restarts only, armed by supervise()
                self.master = CanopenMaster(self.cfg, self.table, self.network, self.supervisor,
                                            clock=lambda: self.tap.now, periodic_sync=False)
            if notifier:
                self.network.connect()
            if self.wall_clock:
                self._tick_thread = threading.Thread(target=self._tick, name="rsra-clock-tick",
                                                     daemon=True)
                self._tick_thread.start()
            if self.master is not None and self.use_master:
                self.master.boot()
        except BaseException:
            self.close()
            raise
        return self

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            self.tap.tick(time.time())  # the live acquisition clock when the bus is idle
            if self.recorder is not None:
                self.recorder.tick(self.tap.now)

    def close(self) -> None:
        """Stop SYNC, the master, the notifier, the recording; shut down a bus we opened."""
        self._stop.set()
        if self.master is not None:
            self.master.stop()
        if self._tick_thread is not None:
            self._tick_thread.join(timeout=2.0)
            self._tick_thread = None
        if self.network.notifier is not None:
            self.network.notifier.stop(2.0)  # also stops the recorder (a listener)
            self.network.notifier = None
        if self.recorder is not None:
            self.recorder.stop()
        if self._own_bus and self._bus is not None:
            shutdown_bus(self._bus)
            self._bus = None
            self.network.bus = None

    def __enter__(self) -> Reader:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- frames in (replay / lock-step) -------------------------------------------------------
    def feed(self, msg: can.Message) -> None:
        """Process one frame on the caller's thread (the same code path as the bus thread)."""
        self.tap.on_message_received(msg)
        if self.recorder is not None:
            self.recorder.on_message_received(msg)

    def pump(self) -> int:
        """Lock-step without a bus thread: process every frame queued on the bus now, in
        order, in this thread. Returns the number of frames."""
        if self.network.notifier is not None:
            raise RuntimeError("the bus thread is running: pump() is for start(notifier=False)")
        bus = self._bus
        n = 0
        while (msg := bus.recv(0.0)) is not None:
            self.feed(msg)
            n += 1
        return n

    def supervise(self) -> None:
        """``restart_nodes``: from now on restart a node that reboots (the boot-ups already
        processed — the other master's start — are not acted upon), in the master's thread.
        Without a bus thread the SDO answers come in through :meth:`pump`: a lock-step
        driver (sim_bus.drivers.LockstepDriver) pumps this reader and the peer while
        :meth:`busy`, with the reader's transmissions handed over (HandoffBus)."""
        if self.master is None or self.use_master:
            raise RuntimeError("supervise() needs restart_nodes=True and a started reader")
        self.master.supervise()

    def busy(self) -> bool:
        """A node reconfiguration is pending or running (lock-step drivers hold time)."""
        return not self.master_idle()

    def send_sync(self, timestamp: float | None = None) -> None:
        """Lock-step with the master: put one SYNC on the bus (``periodic_sync=False``)."""
        if self.master is None:
            raise RuntimeError("send_sync() needs the master (master=True, started)")
        self.master.send_sync(timestamp)

    def master_idle(self) -> bool:
        """True when the master has no node reconfiguration pending or running."""
        return self.master is None or self.master.idle()

    # -- items out -------------------------------------------------------------------------------
    def _put(self, item: Sample | HealthReport) -> None:
        q = self.queue
        if self.overflow == "drop" or self.offline:
            try:
                q.put_nowait(item)
            except queue.Full:
                self.dropped += 1  # back-pressure: counted, visible through seq gaps
                return
        else:
            if q.full():
                self.blocked += 1
            q.put(item)
        depth = len(q.queue)  # a statistic: no need for qsize()'s lock (bus thread, per sample)
        if depth > self.max_depth:
            self.max_depth = depth

    def get(self, timeout: float | None = None) -> Sample | HealthReport | None:
        """The next item (Sample or HealthReport), None after ``timeout`` seconds."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def poll(self) -> list[Sample | HealthReport]:
        """Every item available now, without waiting."""
        out = []
        q = self.queue
        while True:
            try:
                out.append(q.get_nowait())
            except queue.Empty:
                return out

    def samples(self, timeout: float = 1.0) -> Iterator[Sample | HealthReport]:
        """Items until the reader is closed (``timeout`` between checks)."""
        while not self._stop.is_set():
            item = self.get(timeout)
            if item is not None:
                yield item

    # -- time -------------------------------------------------------------------------------------
    def _on_time(self, t: float) -> None:
        """The acquisition clock passed a deadline (bus thread / replay loop, frame order)."""
        sup = self.supervisor
        if t >= sup.next_deadline:
            sup.check(t)
        if self._next_health == math.inf:
            self._next_health = math.floor(t) + self.health_period_s
        elif t >= self._next_health:
            # 1 Hz on acquisition time; a long gap gives one report, not a burst
            self._next_health = max(self._next_health + self.health_period_s,
                                    math.floor(t) + self.health_period_s)
            self._measure_rate(t)
            payload = self.health(t)
            self.last_health = payload
            self._put(HealthReport(t, payload))
        self.tap.deadline = min(self._next_health, sup.next_deadline)

    def _wake(self, t: float) -> None:
        """The watchdog needs the clock's attention at ``t`` (earlier than planned)."""
        self.tap.deadline = min(self.tap.deadline, t)

    def _on_node_event(self, kind: str, node: str) -> None:
        if self.master is not None:
            self.master.on_event(kind, node)

    @property
    def now(self) -> float:
        """The acquisition clock (seconds)."""
        return self.tap.now

    # -- health ---------------------------------------------------------------------------
    def health(self, t: float | None = None) -> dict:
        """A snapshot shaped like the ``health`` payload of docs/telemetry.md §2.5."""
        t = self.tap.now if t is None else t
        tap, asm = self.tap, self.assembler
        bus = {"frames": tap.frames, "errors": tap.errors, "bus_off": tap.bus_off,
               "unknown": tap.unknown,
               "malformed": asm.malformed + self.supervisor.malformed,
               "duplicate": asm.duplicate, "orphan": asm.orphan, "remote": tap.remote,
               "callback_errors": tap.callback_errors}
        if tap.last_callback_error:
            bus["last_callback_error"] = tap.last_callback_error
        queues = {"samples": {"depth": self.queue.qsize(), "size": self.queue_size,
                              "max_depth": self.max_depth, "dropped": self.dropped,
                              "blocked": self.blocked}}
        if self.master is not None:
            queues["master_events"] = {"depth": self.master._events.qsize(),
                                       "dropped": self.master.events_dropped}
        rec = self.recorder.status() if self.recorder is not None else {"active": False}
        payload = {"t": t if math.isfinite(t) else None, "nodes": self.supervisor.snapshot(t),
                   "bus": bus, "samples": asm.counters(), "queues": queues, "recording": rec}
        payload["sync"] = self.sync_health(t)
        return payload

    # -- health: SYNC counts and times (one section: docs/telemetry.md §2.5, ``sync.*``) -----------
    def sync_health(self, t: float) -> dict:
        """Duplicated SYNCs, bad timestamps (docs/reliability.md), late SYNCs of our own
        producer and the sample rate over the last ``RATE_WINDOW`` health periods."""
        asm = self.assembler
        out: dict = {"duplicate": asm.duplicate_sync, "bad_timestamp": asm.clock.bad_timestamp}
        task = self.master.sync_task if self.master is not None else None
        if task is not None and hasattr(task, "periods_not_taken"):
            out["late"] = task.late
            out["periods_not_taken"] = task.periods_not_taken
        out["rate_hz"] = self._rate_hz
        out["rate_low"] = self._rate_hz is not None and \
            self._rate_hz < RATE_LOW_FRACTION * self.cfg.sample_rate_hz
        return out

    def _measure_rate(self, t: float) -> None:
        """Samples assembled per second of acquisition time, over the last health periods
        (called once per health period, before the report)."""
        hist = self._rate_hist
        hist.append((t, self.assembler.emitted))
        (t0, n0), (t1, n1) = hist[0], hist[-1]
        self._rate_hz = (n1 - n0) / (t1 - t0) if t1 - t0 >= 0.999 * self.health_period_s \
            else None
