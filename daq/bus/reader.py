"""The reader: bus → decode → samples, on any python-can interface (docs/bus.md, docs/telemetry.md).

::

    python-can bus ─▶ one BatchNotifier ─▶ FrameTap ─▶ canopen Network.subscribe callbacks
                                  │  (clock, counts,  ├─ SampleAssembler (SYNC, TPDOs)
                                  │   unknown IDs)    ├─ Supervisor (heartbeat, EMCY)
                                  │        │          └─ canopen SDO/NMT (master)
                                  │        └─▶ Deadlines: the watchdog, the 1 Hz HealthMonitor
                                  └─▶ Recorder (every frame, own transmissions too)
    SampleAssembler / HealthMonitor ─▶ ItemQueue (bounded) ─▶ consumer (``Reader.get``)

The FrameTap replaces canopen's own MessageListener (one listener, one dispatch per frame):
it keeps the ONE acquisition clock (model.md §8.3: the frame timestamps — simulated time in
lock-step, recorded time in replay, the wall clock live — made monotone and quantised to
1 µs; the frame is re-stamped with it before the recorder sees it), counts frames, error
frames, bus-off and unknown COB-IDs, and dispatches through canopen's
``Network.subscribe`` table. The heartbeat watchdog and the 1 Hz health report are timed
tasks registered with the tap's :class:`Deadlines` at construction; when the clock passes
the earliest one the tap runs the due ones (one downward call; a heartbeat that brings the
watchdog's time forward lowers the deadline, nothing calls back into the reader).

What differs between a live bus, a lock-step run and a replay is chosen by the caller as
classes and small objects, never as flags (python-can's ``BusABC``: variation in subclasses):

* the reader: :class:`Reader` owns a bus and a notifier thread (live);
  :class:`LockstepReader` owns no thread, a lock-step driver calls :meth:`~LockstepReader.pump`;
  :class:`OfflineReader` has no bus at all, it is fed frames (:meth:`~OfflineReader.feed`:
  replay, benchmarks) and so assembles exactly the samples the live reader did;
* the clock (``Reader`` only): :class:`WallClock` (frames mapped onto the wall clock's
  timebase, an idle bus still advances the clock — the only place that reads the wall
  clock) or :class:`FrameClock` (frame time only);
* the nodes: :class:`Listen` (no NMT, SDO or SYNC), :class:`BootNodes` (the CANopen master:
  boot, periodic SYNC, supervision), :class:`BootNodesSyncOnDemand` (the same, one SYNC per
  ``send_sync``), :class:`RestartNodes` (lock-step: someone else booted the nodes; restarts
  a node that reboots once ``supervise()`` is called);
* the item queue: :class:`DropQueue` (never blocks the bus thread; a full queue drops and
  counts) or :class:`BlockQueue` (lock-step: the producer waits, the waits are counted).

A combination that cannot work has no spelling: the lock-step reader takes only the
node policies that need no bus thread, ``send_sync`` exists only on the on-demand policy,
``supervise`` only on the restart one. (These replaced the keywords ``master``,
``restart_nodes``, ``periodic_sync``, ``wall_clock``, ``overflow``, ``queue_size``,
``offline``, ``bus_kwargs`` and ``start(notifier=False)`` by these; no keyword is kept.)

The health snapshot is a typed, frozen :class:`daq.bus.health.Health`, built in one place
(:meth:`HealthMonitor.snapshot`).
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
from typing import Any, Protocol

import can
import canopen

from rsra.daq.bus.assembler import Sample, SampleAssembler
from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.bus.health import (
    OMIT,
    BusCounts,
    EventQueue,
    Health,
    Queues,
    RecordingHealth,
    SampleCounts,
    SampleQueue,
    SyncHealth,
)
from rsra.daq.bus.master import (
    COB_EMCY,
    COB_HEARTBEAT,
    COB_NMT,
    COB_SDO_RX,
    COB_SDO_TX,
    CanopenMaster,
    Supervisor,
    SyncProducer,
)
from rsra.daq.bus.recorder import Recorder
from rsra.daq.bus.reorder import FrameReorder
from rsra.canbus import BatchNotifier, open_bus, recording_channel, shutdown_bus

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x00000040  # SocketCAN error class bit in an error frame's identifier
LSS_COB_IDS = (0x7E4, 0x7E5)  # CiA 305 (canopen's network subscribes to them)
COB_TIME = 0x100
DEFAULT_QUEUE = 1024  # samples (≈ 5 s at 200 samples/s)
TICK_S = 0.1  # live idle tick of the acquisition clock
IDLE_TICK_S = 1.0  # no frame for this long (wall clock): the idle tick runs the timed tasks
NOTIFIER_CYCLE_S = 0.1
RATE_WINDOW = 10  # health periods over which the sample rate is measured
RATE_LOW_FRACTION = 0.99  # below this fraction of sample_rate_hz: sync.rate_low
TIMEBASE_BLOCK = 256  # frames per estimate of a foreign frame timebase's offset
TIMEBASE_FIRST_BLOCK = 16  # the first block (a quick first estimate)
TIMEBASE_QUANTILE = 0.1  # the block's quantile of receipt delays taken as the offset
READ_RETRY_MIN_S = 0.01  # the pause after a second failed bus read in a row (FrameTap.on_error)
READ_RETRY_MAX_S = 1.0  # ... doubling up to this while the reads keep failing
FOREIGN_TIMEBASE_S = 0.05  # a receipt delay floor beyond this: frames carry a foreign clock
LOCAL_LAG_S = 0.5  # frames stamped up to this far in the past: the local clock, read late
_floor = math.floor


@dataclass(frozen=True, slots=True)
class HealthReport:
    """The 1 Hz ``health`` record, emitted in frame order into the sample stream."""

    t: float
    health: Health


def quantise_us(t: float) -> float:
    """Round a timestamp to 1 µs (6× cheaper than ``round(t, 6)``; the two can differ by one
    µs within float error of a half-µs tie — harmless, because the recordings store the
    quantised value itself, which every log format gives back exactly)."""
    return math.floor(t * 1e6 + 0.5) / 1e6


# -- timed tasks on the acquisition clock ---------------------------------------------------------
class TimedTask(Protocol):
    """A task the acquisition clock runs once it passes ``due`` (which ``run`` moves on)."""

    @property
    def due(self) -> float: ...

    def run(self, t: float) -> None: ...

    def rebase(self, t: float) -> None: ...


class Deadlines:
    """The tap's timed tasks, registered at construction. ``next`` is the earliest ``due``;
    the tap calls :meth:`run` when its clock passes it. :meth:`lower` brings ``next``
    forward (a task whose time moved earlier between two runs: the watchdog on a heartbeat)."""

    def __init__(self) -> None:
        self.tasks: tuple[TimedTask, ...] = ()
        self.next = -math.inf  # the first frame runs every task once (their set-up)

    def add(self, task: TimedTask) -> None:
        self.tasks += (task,)

    def run(self, t: float) -> None:
        for task in self.tasks:
            if t >= task.due:
                task.run(t)
        self.next = min(task.due for task in self.tasks)

    def lower(self, t: float) -> None:
        if t < self.next:
            self.next = t

    def rebase(self, t: float) -> None:
        """The acquisition clock went back to ``t`` (a discontinuity): every task's schedule
        starts again from there."""
        for task in self.tasks:
            task.rebase(t)
        self.next = min(task.due for task in self.tasks)


class _Watchdog:
    """The supervisor's heartbeat watchdog as a timed task."""

    def __init__(self, sup: Supervisor):
        self.sup = sup

    @property
    def due(self) -> float:
        return self.sup.next_deadline

    def run(self, t: float) -> None:
        self.sup.check(t)

    def rebase(self, t: float) -> None:
        self.sup.rebase(t)


class FrameTap(can.Listener):
    """The one per-frame entry point (bus thread, lock-step driver, or the replay loop)."""

    def __init__(self, network: canopen.Network, known: set[int], asm: SampleAssembler,
                 deadlines: Deadlines):
        self.subscribers = network.subscribers  # canopen's subscribe table (live dict)
        self.known = frozenset(known)
        self.deadlines = deadlines
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
        self._read_failed_at = -1  # self.frames at the last failed read
        self._backoff = 0.0  # the pause after a failed read (on_error)
        self._failing = False  # a read failed and no frame has been read since
        self.pause: Callable[[float], Any] = time.sleep  # a bus reader's: its stop event's wait
        self.recovered: Callable[[], None] | None = None  # a frame read after a failure
        self.frame_time = -math.inf  # monotone, quantised frame time (but at a discontinuity)
        self.discontinuities = 0
        self.tick_time = -math.inf  # live idle tick (wall clock)
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        self.frames += 1
        if self._failing:  # the bus reads again after a failure
            self._failing = False
            if self.recovered is not None:
                self.recovered()
        t = _floor(msg.timestamp * 1e6 + 0.5) / 1e6  # 1 µs, the recordings' resolution
        # a time far from where the SYNC counter / schedule puts the frame is re-stamped
        # (counted as a bad timestamp; docs/reliability.md)
        cid = msg.arbitration_id
        if cid == self.sync_cob and not (msg.is_extended_id or msg.is_error_frame
                                         or msg.is_remote_frame):
            ts = self.stamp_sync(msg.data, t, self.frame_time)
            if self._clock.jumped:
                self._discontinuity(t)
        elif (self._clock._suspect is None and t <= self.frame_time + self._ahead_s
              and self._clock._back is None):
            ts = t  # stamp_frame's common case, inline (nothing pending, not far ahead)
        else:
            ts = self.stamp_frame(t, self.frame_time)
            if self._clock.jumped:  # a SYNC stamped far back, confirmed by this frame
                self._clock.jumped = False
                self._discontinuity(self._clock.base_t or t)
        own = t
        if ts != t:
            t = _floor(ts * 1e6 + 0.5) / 1e6
        if t > self.frame_time:
            self.frame_time = t
            deadlines = self.deadlines
            if t >= deadlines.next:
                deadlines.run(t)
        else:
            t = self.frame_time  # never backwards (own transmissions stamped at send time)
        # what the recorder (next listener) writes: the frame's own time, or the clock when
        # it was behind it — never a frame held back (a suspect time, a late SYNC): the
        # replay then sees the times this tap saw and takes the same decisions, so its
        # samples and clock are the live ones bit for bit
        msg.timestamp = own if own > t else t
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

    def _discontinuity(self, t: float) -> None:
        """The SYNC clock found time going back at this SYNC (``SyncClock.jumped``: two
        recordings joined, a clock stepped back). Counted and reported, never turned into
        lost samples or rewritten times: the clock, the watchdog and the health schedule
        start afresh from it, its sample takes its own time (docs/reliability.md)."""
        self.discontinuities += 1
        if self.discontinuities == 1:
            log.warning("time goes back %.3f s at frame %d (SYNC at %.6f after %.6f): a "
                        "discontinuity (recordings joined? a clock stepped back?); counted in "
                        "health sync.discontinuities, no sample invented", self.frame_time - t,
                        self.frames, t, self.frame_time)
        self.frame_time = t
        self.deadlines.rebase(t)

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
        """Live idle tick: advance the clock from the wall clock when no frame does.

        The timed tasks (watchdog, health) run from the tick only once no frame has come for
        ``IDLE_TICK_S``: while frames flow they run at the frames' times alone, as in a
        replay of the recording (the bus thread may be some way behind the wall clock, and
        a watchdog run at the wall clock would judge frames still queued lost)."""
        with self.lock:
            t = quantise_us(wall)
            if t > self.tick_time:
                self.tick_time = t
                if t > self.frame_time + IDLE_TICK_S and t >= self.deadlines.next:
                    self.deadlines.run(t)

    def on_error(self, exc: Exception) -> None:
        """A bus read failed (interface down, the shared bus's server gone, …): counted
        (health ``bus.errors``, the text in ``bus.last_callback_error``), logged when it changes, and the notifier keeps
        reading — after a pause that doubles while the reads keep failing (10 ms … 1 s), so
        a bus that is gone for good does not spin the bus thread; a frame read again resets
        it."""
        self.errors += 1
        text = f"bus: {type(exc).__name__}: {exc}"
        if text != self.last_callback_error:
            log.error("bus read failed (%s); retrying, the samples report what is missing",
                      text[5:])
        self.last_callback_error = text
        self._failing = True
        if self._read_failed_at == self.frames:  # no frame since the last failure
            self._backoff = min(READ_RETRY_MAX_S, max(READ_RETRY_MIN_S, 2 * self._backoff))
            self.pause(self._backoff)
        else:
            self._backoff = 0.0
        self._read_failed_at = self.frames

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
        # frames stamped in the future are another clock beyond FOREIGN_TIMEBASE_S; frames
        # stamped in the past may be the bus thread running behind (a busy start reads a
        # backlog): another clock only beyond LOCAL_LAG_S (below it the idle tick, which
        # waits IDLE_TICK_S for a quiet bus, never runs ahead of frames still coming)
        self.offset = offset
        foreign = offset < -FOREIGN_TIMEBASE_S or offset > LOCAL_LAG_S
        self.shift = offset if foreign else 0.0


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


# -- the clock: what advances the acquisition clock besides the frames (Reader) -----------------
class FrameClock:
    """The acquisition clock is the frames' time only (a bus whose frames carry simulated
    time; benchmarks). The recorder writes inline: nothing runs in real time."""

    def listener(self, tap: FrameTap) -> can.Listener:
        return tap

    def recorder(self, folder: Path, cfg: RigConfig, fmt: str | None,
                 channel: str = "can") -> Recorder:
        return Recorder(folder, cfg, fmt=fmt, threaded=False, channel=channel)

    def start(self, tap: FrameTap, recorder: Recorder | None) -> None:
        pass

    def stop(self) -> None:
        pass


class WallClock(FrameClock):
    """Live: frames mapped onto the wall clock's timebase (:class:`Timebase`), and an idle
    bus still advances the clock from the wall clock (a thread ticks it every ``TICK_S``).
    The recorder writes from a thread of its own behind a bounded queue (a slow disk never
    stalls the bus thread)."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def listener(self, tap: FrameTap) -> can.Listener:
        return _LockedTap(tap)

    def recorder(self, folder: Path, cfg: RigConfig, fmt: str | None,
                 channel: str = "can") -> Recorder:
        return Recorder(folder, cfg, fmt=fmt, threaded=True, channel=channel)

    def start(self, tap: FrameTap, recorder: Recorder | None) -> None:
        def tick() -> None:
            while not self._stop.wait(TICK_S):
                tap.tick(time.time())  # the live acquisition clock when the bus is idle
                if recorder is not None:
                    recorder.tick(tap.now)
        self._thread = threading.Thread(target=tick, name="rsra-clock-tick", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None


# -- the nodes: who boots, starts, supervises them and produces SYNC --------------------------------
class NodePolicy:
    """Who drives the nodes (a subclass each): the reader calls :meth:`attach` before its
    bus thread starts, :meth:`begin` after, :meth:`stop` on close; the supervisor's events
    go to :meth:`on_event`."""

    master: CanopenMaster | None = None

    def attach(self, cfg: RigConfig, table: DecodeTable, network: canopen.Network,
               supervisor: Supervisor, clock: Callable[[], float]) -> None:
        """Set up before the bus thread starts (the reader's start)."""

    def begin(self) -> None:
        """After the bus thread (if any) and the clock started."""

    def on_event(self, kind: str, node: str) -> None:
        """A supervisor event (bus thread: never blocks)."""
        master = self.master
        if master is not None:
            master.on_event(kind, node)

    def idle(self) -> bool:
        """No node reconfiguration pending or running."""
        master = self.master
        return master is None or master.idle()

    def check_bus(self, cfg: RigConfig, bus: Any) -> None:
        """Refuse a caller's bus this policy cannot work with (ValueError)."""

    def stop(self) -> None:
        if self.master is not None:
            self.master.stop()


class Listen(NodePolicy):
    """Only listen: no NMT, no SDO, no SYNC (a recording of another master, nodes that start
    by themselves, lock-step runs where the simulator owns the nodes)."""


class RestartNodes(NodePolicy):
    """Lock-step: the nodes were booted by someone else (the simulator); once
    :meth:`supervise` is called a node that reboots is reconfigured over SDO and started by
    the master's thread, as the live master does (docs/bus.md §3 "Boot and supervision"),
    its answers served by the lock-step driver while the reader is busy."""

    def attach(self, cfg: RigConfig, table: DecodeTable, network: canopen.Network,
               supervisor: Supervisor, clock: Callable[[], float]) -> None:
        self.master = CanopenMaster(cfg, table, network, supervisor, clock=clock)

    def supervise(self) -> None:
        """From now on restart a node that reboots (the boot-ups already processed — the
        other master's start — are not acted upon). The reader must be started."""
        if self.master is None:
            raise RuntimeError("supervise() needs a started reader")
        self.master.supervise()


class _Master(NodePolicy):
    """The CANopen master: boots, verifies and starts the nodes on :meth:`Reader.start`
    (master.BootError when it cannot), SYNC as the subclass says, then keeps the nodes
    running (docs/bus.md §3)."""

    def attach(self, cfg: RigConfig, table: DecodeTable, network: canopen.Network,
               supervisor: Supervisor, clock: Callable[[], float]) -> None:
        self.master = CanopenMaster(cfg, table, network, supervisor, clock=clock)

    def begin(self) -> None:
        assert self.master is not None  # attach() made it
        self.master.boot()
        self._sync()
        self.master.supervise()

    def _sync(self) -> None:
        pass

    def check_bus(self, cfg: RigConfig, bus: Any) -> None:
        if cfg.sync.producer == "service" and \
                getattr(bus, "receive_own_messages", True) is False:
            raise ValueError("the service produces SYNC but this bus does not deliver its "
                             "own transmissions: open it with receive_own_messages=True")


class BootNodes(_Master):
    """The live CANopen master: boot, SYNC at the sample rate (``sync.producer: service``;
    the interface's periodic sending or a thread of ours), supervision."""

    def _sync(self) -> None:
        assert self.master is not None  # attach() made it
        self.master.start_sync()


class BootNodesSyncOnDemand(_Master):
    """The CANopen master without a SYNC clock of its own: one SYNC per :meth:`send_sync`
    (a test or driver owns the sample clock)."""

    def send_sync(self, timestamp: float | None = None) -> None:
        """Put one SYNC on the bus (``timestamp`` kept on buses that preserve it)."""
        if self.master is None:
            raise RuntimeError("send_sync() needs a started reader")
        self.master.send_sync(timestamp)


LockstepNodes = Listen | RestartNodes  # what needs no bus thread (SDO answered by a driver)


# -- the items: what a full queue does -----------------------------------------------------------------
class ItemQueue:
    """The bounded queue of samples and health reports between the bus side and the
    consumer; a subclass says what a full queue does.

    ``first_step``, when given, is called with each Sample in the producer's thread (the bus
    thread, under the tap's lock: one sample at a time, in order) before it is queued, and
    what it returns is queued instead: the service publishes a sample's hub loads there,
    with no hand-off to another thread: the SYNC → hub_loads latency is what it saves."""

    def __init__(self, size: int = DEFAULT_QUEUE,
                 first_step: Callable[[Sample], Any] | None = None):
        self.first_step = first_step
        self.queue: queue.Queue[Sample | HealthReport] = queue.Queue(size)
        self.size = size
        self.dropped = 0
        self.blocked = 0
        self.max_depth = 0

    def put(self, item: Sample | HealthReport) -> None:
        raise NotImplementedError

    def get(self, timeout: float | None = None) -> Sample | HealthReport | None:
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def poll(self) -> list[Sample | HealthReport]:
        out = []
        q = self.queue
        while True:
            try:
                out.append(q.get_nowait())
            except queue.Empty:
                return out

    def status(self) -> SampleQueue:
        return SampleQueue(depth=self.queue.qsize(), size=self.size, max_depth=self.max_depth,
                           dropped=self.dropped, blocked=self.blocked)


class DropQueue(ItemQueue):
    """Never blocks the producer (the bus thread): a full queue drops the item and counts
    it (visible through seq gaps)."""

    def put(self, item: Sample | HealthReport) -> None:
        q = self.queue
        if self.first_step is not None and not isinstance(item, HealthReport):
            item = self.first_step(item)
        try:
            q.put_nowait(item)
        except queue.Full:
            self.dropped += 1
            return
        depth = len(q.queue)  # a statistic: no need for qsize()'s lock (per sample)
        if depth > self.max_depth:
            self.max_depth = depth


class BlockQueue(ItemQueue):
    """Lock-step: a full queue makes the producer wait; the waits are counted."""

    def put(self, item: Sample | HealthReport) -> None:
        q = self.queue
        if self.first_step is not None and not isinstance(item, HealthReport):
            item = self.first_step(item)
        if q.full():
            self.blocked += 1
        q.put(item)
        depth = len(q.queue)
        if depth > self.max_depth:
            self.max_depth = depth


# -- health --------------------------------------------------------------------------------------------
class HealthMonitor:
    """The 1 Hz health report on acquisition time (a timed task of the tap) and the health
    snapshot, built here only. It reads the parts; nothing reads it back but the consumer."""

    period_s = 1.0

    def __init__(self, cfg: RigConfig, tap: FrameTap, asm: SampleAssembler,
                 supervisor: Supervisor, items: ItemQueue, nodes: NodePolicy):
        self.cfg, self.tap, self.asm, self.supervisor = cfg, tap, asm, supervisor
        self.items, self.nodes = items, nodes
        self.recorder: Recorder | None = None  # set when a bus reader starts recording
        self.reorder: FrameReorder | None = None  # set by a replay (its late frames: bus.late)
        self.due = -math.inf  # the first run only sets the schedule up
        self.last: Health | None = None
        self._rate_hist: deque[tuple[float, int]] = deque(maxlen=RATE_WINDOW + 1)
        self._rate_hz: float | None = None

    def rebase(self, t: float) -> None:
        """A discontinuity: the next report one period after ``t``, the rate measured afresh."""
        self.due = math.floor(t) + self.period_s
        self._rate_hist.clear()

    def run(self, t: float) -> None:
        """The acquisition clock passed ``due`` (bus thread / replay loop, frame order)."""
        if self.due == -math.inf:
            self.due = math.floor(t) + self.period_s
            return
        # 1 Hz on acquisition time; a long gap gives one report, not a burst
        self.due = max(self.due + self.period_s, math.floor(t) + self.period_s)
        self._measure_rate(t)
        h = self.snapshot(t)
        self.last = h
        self.items.put(HealthReport(t, h))

    def snapshot(self, t: float | None = None) -> Health:
        """The ``health`` record of docs/telemetry.md §2.5 (the reader's part of it)."""
        tap, asm = self.tap, self.asm
        t = tap.now if t is None else t
        bus = BusCounts(frames=tap.frames, errors=tap.errors, bus_off=tap.bus_off,
                        unknown=tap.unknown, malformed=asm.malformed + self.supervisor.malformed,
                        duplicate=asm.duplicate, orphan=asm.orphan, remote=tap.remote,
                        callback_errors=tap.callback_errors,
                        last_callback_error=tap.last_callback_error or OMIT,
                        late=self.reorder.late if self.reorder and self.reorder.late else OMIT)
        master = self.nodes.master
        queues = Queues(samples=self.items.status(), master_events=OMIT if master is None
                        else EventQueue(depth=master.events_pending,
                                        dropped=master.events_dropped))
        rec = RecordingHealth(active=False) if self.recorder is None else \
            RecordingHealth.from_status(self.recorder.status())
        return Health(t=t if math.isfinite(t) else None, nodes=self.supervisor.snapshot(t),
                      bus=bus, samples=self._samples(), queues=queues,
                      recording=rec, sync=self._sync())

    def _samples(self) -> SampleCounts:
        """What the assembler emitted; a SYNC the replay's reorder stage dropped as late is
        counted there (bus.late), not as a lost sample."""
        c = self.asm.counters()
        if self.reorder is not None:
            c["lost"] = max(0, c["lost"] - self.reorder.late_syncs)
        return SampleCounts(**c)

    def _sync(self) -> SyncHealth:
        """Duplicated SYNCs, bad timestamps (docs/reliability.md), late SYNCs of our own
        producer and the sample rate over the last ``RATE_WINDOW`` health periods."""
        asm = self.asm
        master = self.nodes.master
        task = master.sync_task if master is not None else None
        late = periods = OMIT
        if isinstance(task, SyncProducer):  # (the interface's own periodic sending: no counts)
            late, periods = task.late, task.periods_not_taken
        rate = self._rate_hz
        return SyncHealth(duplicate=asm.duplicate_sync, bad_timestamp=asm.clock.bad_timestamp,
                          late_received=asm.clock.late,
                          discontinuities=self.tap.discontinuities,
                          gaps=asm.clock.gaps, gap_longest_s=round(asm.clock.gap_longest_s, 6),
                          late=late, periods_not_taken=periods, rate_hz=rate,
                          rate_low=rate is not None
                          and rate < RATE_LOW_FRACTION * self.cfg.sample_rate_hz)

    def _measure_rate(self, t: float) -> None:
        """Samples assembled per second of acquisition time, over the last health periods
        (called once per health period, before the report)."""
        hist = self._rate_hist
        hist.append((t, self.asm.emitted))
        (t0, n0), (t1, n1) = hist[0], hist[-1]
        self._rate_hz = (n1 - n0) / (t1 - t0) if t1 - t0 >= 0.999 * self.period_s else None


def known_cob_ids(cfg: RigConfig, table: DecodeTable) -> set[int]:
    """Every COB-ID the rig's nodes, SYNC, NMT, TIME and LSS use (any other is ``unknown``)."""
    known = {COB_NMT, COB_TIME, cfg.sync.cob_id, *LSS_COB_IDS, *table.tpdos}
    for nl in table.nodes:
        known |= {COB_HEARTBEAT + nl.node_id, COB_EMCY + nl.node_id,
                  COB_SDO_TX + nl.node_id, COB_SDO_RX + nl.node_id}
    return known


# -- the readers ------------------------------------------------------------------------------------------
class ReaderBase:
    """What every reader is: the decode table, the assembler, the supervisor, the tap with
    its deadlines, the health monitor, the item queue; frames in by :meth:`feed` (the bus
    thread, a lock-step pump or the replay loop: one code path), items out by :meth:`get`
    and :meth:`poll`."""

    def __init__(self, cfg: RigConfig, table: DecodeTable | None, items: ItemQueue,
                 nodes: NodePolicy):
        self.cfg = cfg
        self.table = table or DecodeTable(cfg)
        self.items = items
        self.nodes = nodes
        self.recorder: Recorder | None = None
        self.network = canopen.Network(None)
        # the bus thread wakes this often to see a stop (canopen's default: 1 s per close)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.assembler = SampleAssembler(cfg, self.table, self.items.put)
        deadlines = Deadlines()
        self.supervisor = Supervisor(cfg, self.table, set_alive=self.assembler.set_alive,
                                     on_event=self.nodes.on_event, wake=deadlines.lower)
        self.tap = FrameTap(self.network, self._known_cob_ids(), self.assembler, deadlines)
        self.monitor = HealthMonitor(cfg, self.tap, self.assembler, self.supervisor,
                                     self.items, self.nodes)
        deadlines.add(_Watchdog(self.supervisor))
        deadlines.add(self.monitor)
        # our callbacks first: canopen's own (added by the master) must not shadow them
        for cob, cb in self.supervisor.callbacks().items():
            self.network.subscribe(cob, cb)
        for cob, cb in self.assembler.callbacks().items():
            self.network.subscribe(cob, cb)

    def _known_cob_ids(self) -> set[int]:
        return known_cob_ids(self.cfg, self.table)

    @property
    def master(self) -> CanopenMaster | None:
        """The CANopen master of the node policy (None: only listening)."""
        return self.nodes.master

    # -- frames in ---------------------------------------------------------------------------
    def feed(self, msg: can.Message) -> None:
        """Process one frame on the caller's thread (the same code path as the bus thread)."""
        self.tap.on_message_received(msg)
        if self.recorder is not None:
            self.recorder.on_message_received(msg)

    # -- items out -----------------------------------------------------------------------------
    def get(self, timeout: float | None = None) -> Sample | HealthReport | None:
        """The next item (Sample or HealthReport), None after ``timeout`` seconds."""
        return self.items.get(timeout)

    def poll(self) -> list[Sample | HealthReport]:
        """Every item available now, without waiting."""
        return self.items.poll()

    @property
    def now(self) -> float:
        """The acquisition clock (seconds)."""
        return self.tap.now

    def health(self, t: float | None = None) -> Health:
        """A snapshot of the ``health`` record (docs/telemetry.md §2.5)."""
        return self.monitor.snapshot(t)

    def close(self) -> None:
        """Nothing to close (a bus reader closes its bus, threads and recording)."""


class OfflineReader(ReaderBase):
    """Calibrated, time-stamped samples from frames the caller feeds (replay, benchmarks):
    ``feed(msg)`` each frame, ``poll()`` the items. No bus, no thread, no master
    (:class:`Listen`); the clock is the frames' time; a full queue drops (DropQueue)."""

    def __init__(self, cfg: RigConfig, *, table: DecodeTable | None = None,
                 items: ItemQueue | None = None):
        super().__init__(cfg, table, items if items is not None else DropQueue(), Listen())


class _BusReader(ReaderBase):
    """What a reader with a bus adds: opening (or taking) the bus, the recording, the node
    policy's start and stop, closing in order."""

    def __init__(self, cfg: RigConfig, bus: can.BusABC | None, *, interface: str | None,
                 channel: Any, record: str | Path | None, record_format: str | None,
                 table: DecodeTable | None, items: ItemQueue, nodes: NodePolicy,
                 clock: FrameClock, record_channel: str | None = None):
        super().__init__(cfg, table, items, nodes)
        self.clock = clock
        #: the channel name of the recording's frames (``sim``: the in-process simulator's bus)
        self.record_channel = record_channel or recording_channel(
            interface, channel if channel is not None or bus is None
            else getattr(bus, "channel_id", getattr(bus, "channel", None)))
        self._bus = bus
        self._own_bus = False
        # the service writes the last windows' results after the bus stops (Service._close_worker)
        self.keep_angles_open = False
        self._bus_args: dict[str, Any] = {}
        if interface is not None:
            self._bus_args["interface"] = interface
        if channel is not None:
            self._bus_args["channel"] = channel
        self.network.bus = bus
        # --record DIR is taken as given (and must be new); recording.dir in the config is a
        # parent folder: every run records into its own time-stamped subfolder
        self.record_dir = Path(record) if record else (
            Path(cfg.recording.dir) / time.strftime("%Y%m%d-%H%M%S")
            if cfg.recording.dir else None)
        self.record_format = record_format
        self._stop = threading.Event()
        self._started = False

    def _start(self, thread: bool) -> None:
        if self._started:
            return
        self._started = True
        try:
            if self._bus is None:
                args = dict(self._bus_args)
                # the service's own SYNC/NMT/SDO must come back to the tap and the recorder
                args.setdefault("receive_own_messages", True)
                if args.get("interface") != "remote":
                    self._bus = open_bus(**args)  # virtual: own copy first (rsra.canbus)
                else:  # the shared bus (`rsra bus`) can go away and come back: opened again
                    # when it fails (not SocketCAN: its kernel-timed SYNC (BCM) stays native)
                    from rsra.daq.bus.sharedbus import ReconnectingBus

                    self._bus = ReconnectingBus(lambda: open_bus(**args))
                self._own_bus = True
                self.network.bus = self._bus
            else:
                self.nodes.check_bus(self.cfg, self._bus)
            listeners: list[can.Listener] = [self.clock.listener(self.tap)]
            if self.record_dir is not None:
                self.recorder = self.clock.recorder(self.record_dir, self.cfg,
                                                    self.record_format, self.record_channel)
                self.monitor.recorder = self.recorder
                listeners.append(self.recorder)
            self.network.listeners = listeners  # type: ignore[assignment]  # canopen's is inferred list[MessageListener]
            self.nodes.attach(self.cfg, self.table, self.network, self.supervisor,
                              clock=lambda: self.tap.now)
            if thread:
                # canopen's Network.connect, with python-can's Notifier reading in batches:
                # one wake-up takes every frame received meanwhile (rsra.canbus.BatchNotifier)
                self.network.notifier = BatchNotifier(self._bus, self.network.listeners,
                                                      self.network.NOTIFIER_CYCLE)
                # a failed read pauses on the stop event (close() ends it at once), and once
                # frames come again the failure python-can keeps in notifier.exception is
                # cleared: canopen's send_message raises it otherwise (NMT, SDO) for ever
                self.tap.pause = self._stop.wait
                self.tap.recovered = self._bus_recovered
            self.clock.start(self.tap, self.recorder)
            self.nodes.begin()
        except BaseException:
            self.close()
            raise

    @property
    def wakeups(self) -> tuple[int, int] | None:
        """(wake-ups, frames) of the bus thread so far: how often it woke for a frame and
        how many frames it took (the bus thread's backlog); None without a bus thread."""
        notifier = self.network.notifier
        if not isinstance(notifier, BatchNotifier):
            return None
        return notifier.wakeups, notifier.frames

    def _bus_recovered(self) -> None:
        notifier = self.network.notifier
        if notifier is not None:
            notifier.exception = None
        log.warning("the bus reads again (%d failed reads so far)", self.tap.errors)

    def close(self) -> None:
        """Stop SYNC, the master, the notifier, the recording; shut down a bus we opened."""
        self._stop.set()
        self.nodes.stop()
        self.clock.stop()
        if self.recorder is not None:  # (the notifier stops it as a listener too)
            self.recorder.keep_angles_open = self.keep_angles_open
        if self.network.notifier is not None:
            self.network.notifier.stop(2.0)  # also stops the recorder (a listener)
            self.network.notifier = None
        if self.recorder is not None:  # angles.jsonl stays open when the service asks
            self.recorder.stop(angles=not self.keep_angles_open)
        if self._own_bus and self._bus is not None:
            shutdown_bus(self._bus)
            self._bus = None
            self.network.bus = None

    def __exit__(self, *exc: object) -> None:
        self.close()


class Reader(_BusReader):
    """Calibrated, time-stamped samples from a CANopen bus, read by a notifier thread.

    Live::

        with Reader(cfg, interface="virtual", channel="rig") as r:   # boots the nodes
            while (item := r.get(timeout=1.0)) is not None:
                ...  # Sample, or HealthReport once a second of acquisition time

    Defaults: the live master (:class:`BootNodes`), the wall clock (:class:`WallClock`), a
    queue that never blocks the bus thread (:class:`DropQueue`)."""

    def __init__(self, cfg: RigConfig, bus: can.BusABC | None = None, *,
                 interface: str | None = None, channel: Any = None,
                 record: str | Path | None = None, record_format: str | None = None,
                 table: DecodeTable | None = None, items: ItemQueue | None = None,
                 nodes: NodePolicy | None = None, clock: FrameClock | None = None,
                 record_channel: str | None = None):
        super().__init__(cfg, bus, interface=interface, channel=channel, record=record,
                         record_format=record_format, table=table,
                         items=items if items is not None else DropQueue(),
                         nodes=nodes if nodes is not None else BootNodes(),
                         clock=clock if clock is not None else WallClock(),
                         record_channel=record_channel)

    def start(self) -> Reader:
        """Connect, start recording, the bus thread, the clock; the node policy's start
        (BootNodes: boot the nodes, start SYNC). Raises master.BootError (after closing
        everything) when the nodes cannot be started."""
        self._start(thread=True)
        return self

    def __enter__(self) -> Reader:
        return self.start()

    def samples(self, timeout: float = 1.0) -> Iterator[Sample | HealthReport]:
        """Items until the reader is closed (``timeout`` between checks)."""
        while not self._stop.is_set():
            item = self.get(timeout)
            if item is not None:
                yield item


class LockstepReader(_BusReader):
    """A reader without a bus thread: a lock-step driver (sim_bus.drivers.LockstepDriver)
    calls :meth:`pump` to process the frames queued on the bus, in its thread, and holds
    time while :meth:`busy` (a :class:`RestartNodes` master restarting a node, its
    transmissions handed over by a HandoffBus). The clock is the frames' time; the recorder
    writes inline; by default a full queue makes the driver wait (:class:`BlockQueue`)."""

    def __init__(self, cfg: RigConfig, bus: can.BusABC | None = None, *,
                 interface: str | None = None, channel: Any = None,
                 record: str | Path | None = None, record_format: str | None = None,
                 table: DecodeTable | None = None, items: ItemQueue | None = None,
                 nodes: LockstepNodes | None = None, record_channel: str | None = None):
        super().__init__(cfg, bus, interface=interface, channel=channel, record=record,
                         record_format=record_format, table=table,
                         items=items if items is not None else BlockQueue(),
                         nodes=nodes if nodes is not None else Listen(), clock=FrameClock(),
                         record_channel=record_channel)

    def start(self) -> LockstepReader:
        """Connect the bus (no thread) and start recording."""
        self._start(thread=False)
        return self

    def __enter__(self) -> LockstepReader:
        return self.start()

    def pump(self) -> int:
        """Process every frame queued on the bus now, in order, in this thread. Returns the
        number of frames."""
        bus = self._bus
        assert bus is not None  # start() opened it
        n = 0
        while (msg := bus.recv(0.0)) is not None:
            self.feed(msg)
            n += 1
        return n

    def busy(self) -> bool:
        """A node reconfiguration is pending or running (lock-step drivers hold time)."""
        return not self.nodes.idle()
