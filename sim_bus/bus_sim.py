"""The simulated aircraft on a CAN bus: every configured CANopen node fed by the physics, one
sample per SYNC (docs/bus.md §2; model.md §8.3 "Time").

The aircraft and how its time moves are separate::

    Simulator  (this module)          the aircraft: bus, nodes, physics, faults, SDO server,
       │                              truth; answers a SYNC at time t, sends the heartbeats
       │ clock: SimulatedTime         due by t; no thread, no mode
       │        | WallClock           how frames are stamped (and the bus serialised)
       ▼
    sim_bus.drivers                   who moves time, and in which thread:
       LockstepSim   simulated time, no thread: step() / on_sync() / pump() in the caller's
       FollowSim     simulated time the master's SYNC frames carry; a Notifier thread serves
                     NMT, SDO and SYNC (a blocking SDO client gets its answers)
       RealtimeSim   the wall clock; Notifier + heartbeat ticker threads; each SYNC's answer
                     built ahead of it; run()

Construct the driver (``LockstepSim(cfg, …)``, ``RealtimeSim(cfg, …)``: it builds its
Simulator with the right clock and reads like one); the Simulator alone is driven by hand
(``pump``, ``answer_sync``, ``produce_sync``, ``advance``, ``prepare_next``).

Masters
-------
* **follow** (default): the nodes boot, send their boot-up frames and wait for an external
  master's NMT start; every SYNC seen on the bus produces one physics sample and the TPDOs.
* **autostart**: the nodes start themselves and the simulator is its own master, producing
  SYNC (with the CiA 301 counter) at the sample rate (``produce_sync``: ``RealtimeSim.run()``
  in real time, ``LockstepSim.step()`` in lock-step).

Clocks
------
* :class:`SimulatedTime` (lock-step): simulated time is the one acquisition clock. It moves
  only with the SYNCs (their time, or SYNC frames' timestamps) and ``advance(t)``, and drives
  the heartbeats and the fault timeline; nothing reads the wall clock. Frame timestamps are
  simulated time, spaced by each frame's transmission time at the EDS bit rate, rounded to
  1 µs. The same seed gives the same frames bit for bit, and the same sample values as real
  time (one physics sample per SYNC in both).
* :class:`WallClock` (real time): frames are stamped when sent.

Frames from the other bus users: ``pump()`` handles the frames queued on the bus in the
caller's thread, in order, so a master that sends NMT start then SYNC and calls ``pump()``
gets a deterministic answer without any sleep; or a driver's Notifier thread hands them over
as they arrive (SDO needs that when the client blocks).

Answers built ahead (``prepare_next``; only ``RealtimeSim`` asks, docs/performance.md P5):
half a period after each SYNC the driver's ticker computes the next physics sample
(``prefetch``) and has the whole answer to the next SYNC built (process image, TPDOs due, the
drop/malformed/unknown/errorframe draws, the frames as python-can messages, the fault-log
entries in order), so the SYNC only sends pre-built frames. A sample where a fault window
opens or closes, a node reboots, an EMCY goes out or the SYNC is lost is built at its SYNC,
as in lock-step; an NMT command or SDO request in between, or a SYNC counter other than the
one predicted, undoes the plan (node snapshots) and the SYNC builds its answer itself.
"""
from __future__ import annotations

import dataclasses
from collections import deque
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, ClassVar, Protocol

import can
import canopen
import numpy as np
from canopen.objectdictionary import datatypes as od_types

from rsra.config.rig import RigConfig
from rsra.canbus import recording_channel, send_batch, shutdown_bus
from rsra.sim_bus.faults import (
    EMCY_OVER_RANGE,
    EMCY_SENSOR_FAULT,
    STATUS_OVER_RANGE,
    STATUS_SENSOR_FAULT,
    WINDOW_KINDS,
    Fault,
    FaultInjector,
    FaultLog,
    parse_faults,
    validate_faults,
)
from rsra.sim_bus.nodes import (
    COB_EMCY_BASE,
    COB_HEARTBEAT,
    COB_NMT,
    COB_SDO_RX,
    COB_SDO_TX,
    NMT_START,
    OPERATIONAL,
    PRE_OPERATIONAL,
    ROLE_CHANNELS,
    Frame,
    SimNode,
)
from rsra.sim_bus.offline import ChannelCodec

log = logging.getLogger(__name__)

RECENT_SAMPLES = 512  # the last samples' truth, whatever keep_samples says (live views)
MAX_TRUTH_SAMPLES = 720_000  # one hour at 200 samples/s: the truth history is bounded
FRAME_OVERHEAD_BITS = 47  # 11-bit identifier frame without data, before stuffing (docs/bus.md §4)
DEFAULT_BITRATE = 1_000_000  # docs/bus.md: 1 Mbit/s on the aircraft, when no EDS says otherwise
COB_TIME, COB_LSS_MASTER, COB_LSS_SLAVE = 0x100, 0x7E5, 0x7E4
_ENCODED = ("force", "status", "accel_counts", "omega", "azimuth_counts", "balance", "drive")
# (status bit, EMCY code) pairs the load-cell status drives
_STATUS_EMCY = ((STATUS_OVER_RANGE, EMCY_OVER_RANGE), (STATUS_SENSOR_FAULT, EMCY_SENSOR_FAULT))


class SampleSource(Protocol):
    """What the simulator needs from the physics (sim_bus.physics.AircraftPhysics)."""

    dt: float

    def next_sample(self) -> Any: ...


class TruthBuffer:
    """The samples the bus carried, stored compactly: one growing array per sample field (in
    chunks, so appending is cheap and memory is ~8 bytes per number, not a Python object per
    sample). Bounded: past ``max_samples`` further samples are counted, not kept.

    ``spill=True``: every full chunk goes to an anonymous temporary file (``TMPDIR``; it has
    no name on disk and disappears with the process, even after ``kill -9``), so resident
    memory stays flat over a long run; :meth:`arrays` reads them back (at the end, to write
    the truth file)."""

    def __init__(self, max_samples: int = MAX_TRUTH_SAMPLES, chunk: int = 4096,
                 spill: bool = False):
        self.max_samples, self.chunk = int(max_samples), int(chunk)
        self.spill = spill
        self._fields: list[str] | None = None
        self._chunks: dict[str, list[np.ndarray | tuple[int, np.dtype, tuple]]] = {}
        self._n = 0
        self._file: Any = None
        self.dropped = 0

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes held in memory (chunks not spilled)."""
        return sum(c.nbytes for v in self._chunks.values() for c in v if isinstance(c, np.ndarray))

    def append(self, sample: Any) -> None:
        if self._n >= self.max_samples:
            self.dropped += 1
            return
        if self._fields is None:
            if dataclasses.is_dataclass(sample):
                self._fields = [f.name for f in dataclasses.fields(sample)]
            else:
                self._fields = list(vars(sample))
        row = self._n % self.chunk
        for name in self._fields:
            v = getattr(sample, name)
            if row == 0:
                a = np.asarray(v)
                self._chunks.setdefault(name, []).append(np.zeros((self.chunk,) + a.shape, a.dtype))
            self._chunks[name][-1][row] = v
        self._n += 1
        if self.spill and row == self.chunk - 1:
            self._spill_last()

    def _spill_last(self) -> None:
        import tempfile

        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="rsra-truth-")  # noqa: SIM115 (lives with the buffer)
        f = self._file
        f.seek(0, 2)
        for chunks in self._chunks.values():
            a = chunks[-1]
            chunks[-1] = (f.tell(), a.dtype, a.shape)
            f.write(a.tobytes())

    def _load(self, c) -> np.ndarray:
        if isinstance(c, np.ndarray):
            return c
        off, dtype, shape = c
        self._file.seek(off)
        return np.fromfile(self._file, dtype=dtype, count=int(np.prod(shape))).reshape(shape)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every field stacked over the kept samples (first axis = sample)."""
        return {k: np.concatenate([self._load(c) for c in v])[: self._n]
                for k, v in self._chunks.items()}

    def __getitem__(self, k: int) -> SimpleNamespace:
        """Sample k's fields (a view into the buffer)."""
        if not -self._n <= k < self._n:
            raise IndexError(k)
        k %= self._n
        c, r = divmod(k, self.chunk)
        return SimpleNamespace(**{f: self._load(self._chunks[f][c])[r]
                                  for f in (self._fields or [])})


class SyncLog:
    """Per SYNC cycle: (sample index, counter (-1: none), time, lost), compactly. With
    ``keep`` every cycle up to ``max_n`` (the truth file's sync arrays), in a spilled
    :class:`TruthBuffer` (resident memory flat); without, only the last ``recent`` (live
    views, tests that look back a little) in a ring — what a run without a truth file needs.
    ``len()`` is the number of cycles ever appended."""

    _DTYPE = np.dtype([("k", np.int64), ("counter", np.int16), ("t", np.float64),
                       ("lost", np.bool_)])

    def __init__(self, keep: bool, max_n: int = MAX_TRUTH_SAMPLES, recent: int = RECENT_SAMPLES,
                 chunk: int = 4096):
        self.keep = keep
        self.capacity = int(max_n) if keep else int(recent)
        self._buf = TruthBuffer(self.capacity, chunk, spill=True) if keep else None
        self._ring = None if keep else np.zeros(self.capacity, self._DTYPE)
        self._n = 0  # appended in all

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        return self._buf.nbytes if self.keep else self._ring.nbytes

    def append(self, entry: tuple[int, int, float, bool]) -> None:
        n = self._n
        self._n += 1
        if self.keep:
            k, c, t, lost = entry
            self._buf.append(SimpleNamespace(k=int(k), counter=int(c), t=float(t),
                                             lost=bool(lost)))
        else:
            self._ring[n % self.capacity] = entry

    def _span(self) -> tuple[int, int]:
        """(first, number) of the entries held."""
        if self.keep:
            return 0, len(self._buf)
        held = min(self._n, self.capacity)
        return self._n - held, held

    def __getitem__(self, i: int) -> tuple[int, int, float, bool]:
        """Entry ``i`` (0 = the first SYNC cycle; negative from the latest), if held."""
        if i < 0:
            i += self._n
        first, held = self._span()
        if not first <= i < first + held:
            raise IndexError(f"SYNC cycle {i} is not kept (keep_samples=False keeps the last "
                             f"{self.capacity})")
        e = self._buf[i] if self.keep else None
        if e is not None:
            return int(e.k), int(e.counter), float(e.t), bool(e.lost)
        r = self._ring[i % self.capacity]
        return int(r["k"]), int(r["counter"]), float(r["t"]), bool(r["lost"])

    def __iter__(self):
        a = self.arrays()
        for r in a:
            yield int(r["k"]), int(r["counter"]), float(r["t"]), bool(r["lost"])

    def arrays(self) -> np.ndarray:
        """The entries held, in order (a structured array: k, counter, t, lost)."""
        first, held = self._span()
        out = np.zeros(held, self._DTYPE)
        if not held:
            return out
        if self.keep:
            for name, v in self._buf.arrays().items():
                out[name] = v
        else:
            idx = np.arange(first, first + held) % self.capacity
            out[:] = self._ring[idx]
        return out


class _TxMessage(can.Message):
    """A frame the simulator sends. python-can's virtual bus deep-copies every sent frame for
    every receiver (can/interfaces/virtual.py); copying this one builds the receiver's plain
    ``can.Message`` directly — the payload is immutable bytes and the channel a str, there is
    nothing deeper to copy — instead of ``copy.deepcopy`` recursing into both (a third of the
    send time). Receivers get what they got before: a ``can.Message`` with a bytearray."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> can.Message:
        data = self.data
        return can.Message(timestamp=self.timestamp, arbitration_id=self.arbitration_id,
                           is_extended_id=self.is_extended_id,
                           is_remote_frame=self.is_remote_frame,
                           is_error_frame=self.is_error_frame, channel=self.channel,
                           dlc=self.dlc, data=data if type(data) is bytes else bytes(data),
                           is_fd=self.is_fd, is_rx=self.is_rx,
                           bitrate_switch=self.bitrate_switch,
                           error_state_indicator=self.error_state_indicator)


@dataclass
class _Plan:
    """The answer to the next SYNC, built ahead of it (real time): the node state is already
    advanced (``snap`` undoes that), the frames are built; the SYNC only sends them."""

    sample: Any
    k: int
    st: float
    counter: int | None
    n_sync: int
    snap: list[tuple[SimNode, tuple]]
    carried: list[tuple[SimNode, list]]
    # in order: ("rec", args, kwargs) a fault-log entry, ("send", message) a frame
    actions: list[tuple]


def _round_us(t: float) -> float:
    return round(t * 1e6) / 1e6


class Clock(Protocol):
    """The simulator's time base: what time it is, and how a frame sent now is stamped."""

    simulated: ClassVar[bool]  # frames carry simulated time (the truth file's ``lockstep``)

    def now(self) -> float: ...

    def advance_to(self, t: float) -> None: ...

    def stamp(self, t: float | None, duration: float) -> float: ...

    def occupy(self, t: float, duration: float) -> None: ...

    def sync_time(self, timestamp: float) -> float: ...


class SimulatedTime:
    """Simulated time (lock-step; model §8.3 "Time"): it moves only when the driver says (a
    SYNC's time, ``advance_to``). The bus is serialised: a frame starts when the previous one
    has finished (``duration``: its transmission time at the bit rate); timestamps are rounded
    to 1 µs. Nothing reads the wall clock."""

    simulated: ClassVar[bool] = True

    def __init__(self, t0: float = 0.0):
        self.t0 = float(t0)
        self.t = self.t0
        self._bus_free = self.t0  # when the frame on the bus has finished

    def now(self) -> float:
        return self.t

    def advance_to(self, t: float) -> None:
        self.t = max(self.t, t)

    def stamp(self, t: float | None, duration: float) -> float:
        """A frame sent at ``t`` (None: now) starts when the bus is free."""
        ts = _round_us(max(self.t if t is None else t, self._bus_free))
        self._bus_free = ts + duration
        return ts

    def occupy(self, t: float, duration: float) -> None:
        """Another user's frame (the master's SYNC) held the bus from ``t``."""
        self._bus_free = max(self._bus_free, t + duration)

    def sync_time(self, timestamp: float) -> float:
        """The time of a SYNC frame received: the time it carries."""
        return timestamp


class WallClock:
    """Real time: the wall clock; frames are stamped when sent, the bus is the interface's."""

    simulated: ClassVar[bool] = False

    def now(self) -> float:
        return time.time()

    def advance_to(self, t: float) -> None:
        pass

    def stamp(self, t: float | None, duration: float) -> float:
        return time.time()

    def occupy(self, t: float, duration: float) -> None:
        pass

    def sync_time(self, timestamp: float) -> float:
        return time.time()


class _SimNetwork(canopen.Network):
    """canopen's Network whose sends (LocalNode's SDO server, among others) go through the
    simulator, so they are stamped, recorded and captured like every other frame."""

    def __init__(self, bus: can.BusABC, sim: "Simulator"):
        super().__init__(bus)
        self._sim = sim

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._sim._transmit("sdo" if COB_SDO_TX < can_id <= COB_SDO_TX + 0x7F else "other",
                            can_id, bytes(data), None, remote=remote)


class _Logged:
    """A sent frame as the simulator's log writes it: the frame's fields with the
    recording's channel name (the frame itself, sent and perhaps captured, is unchanged)."""

    __slots__ = ("_msg", "channel")

    def __init__(self, msg: can.Message, channel: str):
        self._msg, self.channel = msg, channel

    def __getattr__(self, name: str) -> Any:
        return getattr(self._msg, name)


class _Recorder(can.Listener):
    """Frames received from the other bus users go to the simulator's log."""

    def __init__(self, sim: "Simulator"):
        self._sim = sim

    def on_message_received(self, msg: can.Message) -> None:
        self._sim._on_received(msg)

    def stop(self) -> None:  # the logger itself is closed by the simulator
        pass


@dataclass
class _NodeFeed:
    node: SimNode
    raws: Callable[[dict], Any]  # encoded sample (lists) -> raw values, ROLE_CHANNELS order
    full_scale: float | None  # load cell: the force an over-range reads (config)


# The data types sim_bus.offline.ChannelCodec encodes to (docs/bus.md §1 "Nodes"): the EDS must agree.
_CODEC_TYPES = {
    ("load_cell", "force"): od_types.REAL32, ("load_cell", "status"): od_types.UNSIGNED8,
    ("accelerometer", "x"): od_types.INTEGER16, ("accelerometer", "y"): od_types.INTEGER16,
    ("accelerometer", "z"): od_types.INTEGER16, ("rotor_speed", "omega"): od_types.REAL32,
    ("rotor_speed", "azimuth"): od_types.UNSIGNED16, ("drive_load", "torque"): od_types.REAL32,
    **{("balance", c): od_types.REAL32 for c in "XYZLMN"},
}


def _validate(parsed: tuple[Fault, ...], nodes: list[tuple[str, str]], autostart: bool) -> None:
    validate_faults(parsed, dict(nodes), {name: ROLE_CHANNELS[role] for name, role in nodes},
                    autostart)


def check_faults(cfg: RigConfig, spec: str, nodes_present: tuple[str, ...] | None,
                 autostart: bool) -> tuple[Fault, ...]:
    """Parse and check a fault SPEC against the nodes a simulator of ``cfg`` would put on the
    bus (the same selection and check as :class:`Simulator`), before building one: raises
    FaultSpecError."""
    parsed = parse_faults(spec)
    _validate(parsed, [(n.name, n.role) for n in cfg.nodes
                       if n.required or nodes_present is None or n.role in nodes_present],
              autostart)
    return parsed


class Simulator:
    """The aircraft: every configured node on one python-can bus, fed by the physics one
    sample per SYNC. It runs no thread and has no mode: ``clock`` stamps its frames, and a
    driver (sim_bus.drivers: LockstepSim, FollowSim, RealtimeSim) moves time (module
    docstring).

    Parameters: ``cfg`` the rig; ``scenario`` a scenario name/object for AircraftPhysics, or
    ``physics`` any object with ``dt`` and ``next_sample()``; ``nodes_present`` the optional
    node roles on the bus (default: the scenario's, else all); ``bus`` an open python-can bus
    to use (not closed here), else one is opened with ``interface``/``channel`` (virtual:
    ``preserve_timestamps=True``); ``faults`` a SPEC string or parsed faults; ``record`` a log
    file (python-can Logger by suffix; candump ``.log`` when the suffix is not a log format);
    ``clock`` a :class:`SimulatedTime` (default: from 0 s) or a :class:`WallClock`.
    """

    def __init__(self, cfg: RigConfig, scenario: Any = None, *, physics: SampleSource | None = None,
                 seed: int | None = None, faults: str | tuple[Fault, ...] | None = None,
                 bus: can.BusABC | None = None, interface: str = "virtual",
                 channel: str = "rsra", autostart: bool = False,
                 clock: Clock | None = None, record: str | Path | None = None,
                 keep_samples: bool = True, nodes_present: tuple[str, ...] | None = None):
        self.cfg = cfg
        self.autostart = autostart
        self.clock: Clock = SimulatedTime() if clock is None else clock
        self.keep_samples = keep_samples
        if physics is None:
            from rsra.sim_bus.physics import AircraftPhysics
            if scenario is None or isinstance(scenario, str):
                from rsra.sim_bus.scenarios import load_scenario
                scenario = load_scenario(scenario or "ground-test")
            physics = AircraftPhysics(cfg, scenario, seed=seed)
        self.physics = physics
        self.dt = float(getattr(physics, "dt", cfg.sample_period_s))
        self.seed = seed if seed is not None else int(getattr(physics, "seed", 0) or 0)
        self.lock = threading.RLock()  # the drivers' threads and the caller's take turns
        # ---- nodes from the config; the EDS gives every object and COB-ID ------------------
        # required nodes always; optional ones when the scenario's aircraft has them
        # (Scenario.nodes_present: optional roles), all of them without a scenario
        if nodes_present is None:
            nodes_present = getattr(getattr(physics, "scenario", None), "nodes_present", None)
        self.nodes: list[SimNode] = [
            SimNode(n.name, n.role, n.node_id, n.eds, clock=self.now, lock=self.lock)
            for n in cfg.nodes if n.required or nodes_present is None or n.role in nodes_present]
        self.by_name = {n.name: n for n in self.nodes}
        self._codec = ChannelCodec(cfg)
        self._feeds = self._build_feeds()
        rates = [max(n.od.device_information.allowed_baudrates or {0}) for n in self.nodes]
        self.bitrate = max(rates) if rates and max(rates) > 0 else DEFAULT_BITRATE
        self._counter_overflow = cfg.sync.counter_overflow
        self._sync_cob = cfg.sync.cob_id
        # ---- faults --------------------------------------------------------------------------
        parsed = parse_faults(faults) if isinstance(faults, (str, type(None))) else tuple(faults)
        _validate(parsed, [(n.name, n.role) for n in self.nodes], autostart)
        self.faults = FaultInjector(parsed, seed=self.seed)
        self.faults.log = FaultLog(keep=keep_samples)  # all of it only for a truth file
        self._frozen: dict[tuple[int, str, str], int | float] = {}
        self._unknown_cob = self._pick_unknown_cob()
        self._logger: can.Listener | None = None
        if record is not None:  # before the bus: a bad path must not leak an open bus
            self._logger = _open_logger(Path(record))
        # ---- bus ---------------------------------------------------------------------------------
        self._own_bus = bus is None
        if bus is None:
            kw: dict[str, Any] = {"interface": interface, "channel": channel}
            if interface == "virtual":
                kw.update(preserve_timestamps=True, receive_own_messages=False)
            try:
                bus = can.Bus(**kw)
            except BaseException:
                if self._logger is not None:
                    self._logger.stop()
                raise
        self.bus = bus
        self.channel = str(getattr(bus, "channel_id", None) or getattr(bus, "channel", None) or channel)
        # the name its recording writes on every frame: the interface's channel when it is a
        # real interface's name (vcan0), else "sim" (a virtual bus's generated name, a URL)
        self.log_channel = recording_channel(
            interface, self.channel, sim=interface in ("virtual", "remote")
            or recording_channel(interface, self.channel) != self.channel)
        self.network = _SimNetwork(bus, self)
        self.network.listeners.append(_Recorder(self))
        for n in self.nodes:
            n.attach(self.network)
            n.before_change = self._discard_plan
        self.network.subscribe(COB_NMT, self._guard(self._on_nmt_frame))
        self.network.subscribe(self._sync_cob, self._guard(self._on_sync_frame))
        self._last_flush = self.clock.now()
        # ---- state ---------------------------------------------------------------------------------
        self._capture: list[can.Message] | None = None
        self._n_sync = 0  # SYNC cycles produced (autostart)
        self._counter = 0
        self.frames_sent = 0
        self.frames_received = 0
        self.error_frames_received = 0
        # what every SYNC carried (keep_samples), bounded, spilled to an anonymous temporary
        # file chunk by chunk (resident memory flat); per SYNC cycle the compact SyncLog
        self.samples = TruthBuffer(spill=keep_samples)
        self.last_sample: Any = None
        self.recent_samples: deque = deque(maxlen=RECENT_SAMPLES)  # bounded, for live views
        self.sync_info = SyncLog(keep_samples)  # (sample, counter, t, lost) per SYNC cycle
        self.truth_truncated = False
        self._error: BaseException | None = None
        # real time: the physics block that the next SYNC would compute (~1 ms for 100 samples)
        # is computed half a period after the current SYNC instead (prefetch), off the
        # SYNC → TPDO path
        self._ahead: Any = None  # the next physics sample, computed ahead of its SYNC
        self.prefetched = 0  # physics samples computed ahead (real time)
        # real time: the whole answer to the next SYNC (TPDO frames, fault decisions) is built
        # half a period ahead (prepare_next); the SYNC only sends it (docs/performance.md P5)
        self._plan: _Plan | None = None
        self.prepared = 0  # SYNC answers built ahead and sent as built
        self.plans_discarded = 0  # built ahead but undone (NMT/SDO in between, other counter)
        self._last_counter: int | None = None  # the counter of the last SYNC answered
        self._started = False
        self._closed = False

    # ------------------------------------------------------------------------------------------
    # set-up
    def _build_feeds(self) -> list[_NodeFeed]:
        cfg = self.cfg
        feeds: dict[str, _NodeFeed] = {}

        def add(name: str, fn: Callable[[Any], Any], fs: float | None = None) -> None:
            if name and name in self.by_name:
                feeds[name] = _NodeFeed(self.by_name[name], fn, fs)

        for i, c in enumerate(cfg.cells):
            add(c.node, lambda e, i=i: (e["force"][i], e["status"][i]), c.full_scale_N)
        for k, a in enumerate(cfg.accelerometers):
            add(a.node, lambda e, k=k: e["accel_counts"][k])
        add(cfg.rotor.node, lambda e: (e["omega"], e["azimuth_counts"]))
        add(cfg.balance.node, lambda e: e["balance"])
        for q, x in enumerate(cfg.external_loads):
            add(x.node, lambda e, q=q: (e["drive"][q],))
        for f in feeds.values():
            for ch, var in f.node.channels:
                want = _CODEC_TYPES[(f.node.role, ch)]
                if var.data_type != want:
                    raise ValueError(
                        f"node {f.node.name!r} ({f.node.eds.name}): channel {ch!r} is mapped to "
                        f"0x{var.index:04X}:{var.subindex} of data type 0x{var.data_type:04X}, "
                        f"the bus contract (docs/bus.md §1) says 0x{want:04X}; fix the EDS")
        # bus order: feed in the config's node order
        return [feeds[n.name] for n in self.nodes if n.name in feeds]

    def _pick_unknown_cob(self) -> int:
        """A TPDO1 COB-ID of a node id nobody configured (highest first)."""
        ids = {n.node_id for n in self.cfg.nodes}
        for nid in range(0x7F, 0, -1):
            if nid not in ids:
                return 0x180 + nid
        return 0x7FF

    def known_cob_ids(self) -> set[int]:
        """Every COB-ID the configured nodes and the master use (CiA 301 pre-defined set)."""
        known = {COB_NMT, self._sync_cob, COB_TIME, COB_LSS_MASTER, COB_LSS_SLAVE}
        for nid in {n.node_id for n in self.cfg.nodes}:
            for base in (COB_EMCY_BASE, 0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480,
                         0x500, COB_SDO_TX, COB_SDO_RX, COB_HEARTBEAT):
                known.add(base + nid)
        for n in self.nodes:
            known.update(c.cob_id for c in n.tpdo_configs())
            known.add(n.emcy_cob_id)
        return known

    def start(self) -> "Simulator":
        """Boot every node (boot-up frames); with autostart, start them."""
        with self.lock:
            if self._started:
                return self
            self._started = True
            t = self.now()
            frames = []
            for n in self.nodes:
                frames.extend(n.boot(t))
            for fr in sorted(frames, key=lambda f: f.cob_id):
                self._send_frame(fr, t, None)
            if self.autostart:  # CiA 301 self-starting nodes
                for n in self.nodes:
                    n.nmt(NMT_START, n.node_id, t)
        return self

    def close(self) -> None:
        """Close the recording and (if we opened it) the bus; a driver stops its threads
        first. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self.lock:
            for n in self.nodes:
                n.detach()
            if self._logger is not None:
                self._logger.stop()
                self._logger = None
            if self._own_bus:
                shutdown_bus(self.bus)

    def __enter__(self) -> "Simulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------
    # the acquisition clock
    def now(self) -> float:
        """The clock's time: simulated in lock-step, the wall clock live (model §8.3 "Time")."""
        return self.clock.now()

    def _guard(self, fn: Callable) -> Callable:
        """canopen only logs exceptions in callbacks (docs/bus.md §6 "Library pitfalls"): keep the first one and
        re-raise it in the caller's thread at the next check()."""
        def wrapped(*a, **kw):
            try:
                return fn(*a, **kw)
            except Exception as e:  # noqa: BLE001 - re-raised by check()
                log.exception("simulator callback failed")
                if self._error is None:
                    self._error = e
        return wrapped

    def check(self) -> None:
        """Raise the first exception a bus callback hit."""
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    # ------------------------------------------------------------------------------------------
    # transmission
    def _frame_time(self, nbytes: int) -> float:
        return (FRAME_OVERHEAD_BITS + 8 * nbytes) / self.bitrate

    def _transmit(self, kind: str, cob_id: int, data: bytes, t: float | None, *,
                  remote: bool = False, error: bool = False) -> can.Message:
        with self.lock:
            ts = self.clock.stamp(t, self._frame_time(len(data)))
            msg = self._build(cob_id, data, error, remote=remote)
            msg.timestamp = ts
            self._emit(msg)
            return msg

    def _build(self, cob_id: int, data: bytes, error: bool = False, *,
               remote: bool = False) -> _TxMessage:
        """The message to send (built at the SYNC by ``_transmit``, or ahead of it)."""
        msg = _TxMessage(timestamp=0.0, arbitration_id=cob_id, data=data, is_extended_id=False,
                         is_remote_frame=remote, is_error_frame=error, channel=self.channel,
                         is_rx=False, check=False)
        if not remote:
            # an immutable payload: python-can's virtual bus deep-copies every frame for
            # every receiver, and bytes copy as themselves where a bytearray goes through
            # copyreg (half the send time); receivers still get a bytearray
            msg.data = bytes(msg.data)
        return msg

    def _send_built(self, msg: _TxMessage) -> None:
        """Send a message built ahead, stamped now (as _transmit)."""
        msg.timestamp = self.clock.stamp(None, self._frame_time(len(msg.data)))
        self._emit(msg)

    def _send_built_many(self, msgs: list[_TxMessage]) -> None:
        """Send messages built ahead, in order, each stamped as :meth:`_send_built` does, in
        one call where the bus allows (rsra.canbus.send_batch: a receiver waiting on the
        in-process virtual bus wakes once for all of them)."""
        stamp, frame_time = self.clock.stamp, self._frame_time
        for msg in msgs:
            msg.timestamp = stamp(None, frame_time(len(msg.data)))
        send_batch(self.bus, msgs)
        self.frames_sent += len(msgs)
        if self._logger is not None:
            for msg in msgs:
                self._logger.on_message_received(msg)
        if self._capture is not None:
            self._capture.extend(msgs)

    def _emit(self, msg: _TxMessage) -> None:
        self.bus.send(msg)
        self.frames_sent += 1
        if self._logger is not None:
            self._logger.on_message_received(_Logged(msg, self.log_channel))
        if self._capture is not None:
            self._capture.append(msg)

    def _send_frame(self, fr: Frame, t: float | None, node: SimNode | None) -> can.Message | None:
        if node is not None and node.silent:
            return None
        return self._transmit(fr.kind, fr.cob_id, fr.data, t)

    def _on_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames_received += 1
            if msg.is_error_frame:
                self.error_frames_received += 1
            if self._logger is not None:
                msg.channel = self.log_channel  # one name for the whole recording
                self._logger.on_message_received(msg)

    def pump(self) -> int:
        """Handle every frame already queued on the bus, in order, in this thread (a driver
        without a Notifier reading the bus). Returns the number handled."""
        n = 0
        while True:
            msg = self.bus.recv(0.0)
            if msg is None:
                return n
            n += 1
            for listener in self.network.listeners:
                listener.on_message_received(msg)
            self.check()

    # ------------------------------------------------------------------------------------------
    # NMT and SYNC from the bus
    def _on_nmt_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2:
            return  # malformed NMT: ignored, as a node would
        with self.lock:
            t = self.now()
            frames = []
            for n in self.nodes:
                frames.extend((n, f) for f in n.nmt(data[0], data[1], t))
            for n, f in sorted(frames, key=lambda p: p[1].cob_id):
                self._send_frame(f, t, n)

    def _on_sync_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        counter = data[0] if len(data) >= 1 else None
        with self.lock:
            self._cycle(counter, self.clock.sync_time(timestamp), send_sync=False,
                        received_sync=len(data))

    # ------------------------------------------------------------------------------------------
    # what a driver calls to move time (each returns the frames it sent; none pumps the bus)
    def _captured(self, fn: Callable[..., None], *args: Any, **kw: Any) -> list[can.Message]:
        with self.lock:
            self._capture = out = []
            try:
                fn(*args, **kw)
            finally:
                self._capture = None
        return out

    def advance(self, t: float) -> list[can.Message]:
        """Time passes to ``t`` without a SYNC: due heartbeats go out (each stamped with its due
        time). With simulated time this is how time moves between SYNCs."""
        return self._captured(self._advance, t)

    def _advance(self, t: float) -> None:
        self.clock.advance_to(t)
        due = []
        for n in self.nodes:
            due.extend((d, f.cob_id, n, f) for d, f in n.heartbeats(t))
        for d, _, n, f in sorted(due, key=lambda x: (x[0], x[1])):
            self._send_frame(f, d, n)
        if self._logger is not None and t - self._last_flush >= 1.0:
            self._flush(t)

    def answer_sync(self, counter: int | None, t: float) -> list[can.Message]:
        """A SYNC (counter byte or None) was put on the bus at time ``t`` by someone else: draw
        one physics sample and answer it. Use this *or* SYNC frames on the bus, not both, for
        the same SYNC."""
        out = self._captured(self._cycle, counter, t, send_sync=False)
        self.check()
        return out

    @property
    def syncs_produced(self) -> int:
        """SYNC cycles this simulator produced as its own master (autostart), lost ones too."""
        return self._n_sync

    def sync_jitter(self) -> float:
        """The jitter of the next SYNC :meth:`produce_sync` sends (the faults'; 0 without)."""
        return self._sync_plan(self._n_sync)[0]

    def produce_sync(self, t: float | None = None, jitter: float = 0.0) -> list[can.Message]:
        """As our own master (autostart): the next SYNC (counter; loss per the faults) at time
        ``t`` (None: the clock's now), which includes its ``jitter`` (:meth:`sync_jitter`), and
        every answer."""
        with self.lock:
            out = self._captured(self._cycle, self._next_counter(),
                                 self.clock.now() if t is None else t, send_sync=True,
                                 jitter=jitter)
        self.check()
        return out

    def next_heartbeat(self) -> float | None:
        """When the next heartbeat is due (None: no node produces one)."""
        with self.lock:
            due = [n.next_heartbeat for n in self.nodes if n.next_heartbeat is not None]
        return min(due) if due else None

    def _next_counter(self) -> int | None:
        if self._counter_overflow == 0:
            return None
        self._counter = self._counter % self._counter_overflow + 1  # CiA 301: 1…overflow
        return self._counter

    def _sync_plan(self, k: int) -> tuple[float, bool]:
        """The SYNC jitter and loss of cycle k: a function of (seed, k) only, so real time and
        lock-step agree."""
        t = k * self.dt
        jitter = self.faults.jitter(k, t, 0.45 * self.dt) if self.faults.of("jitter") else 0.0
        lost = self.faults.chance("lostsync", k, t) is not None
        return jitter, lost

    # ------------------------------------------------------------------------------------------
    # one SYNC cycle
    def _next_sample(self) -> Any:
        s, self._ahead = self._ahead, None
        if s is None:
            s = self.physics.next_sample()
        self.last_sample = s  # the latest truth, for live views (kept even without history)
        self.recent_samples.append(s)
        if self.keep_samples:
            self.samples.append(s)
            if self.samples.dropped == 1 and not self.truth_truncated:
                self.truth_truncated = True
                log.warning("truth history full (%d samples): later samples are not kept",
                            self.samples.max_samples)
        return s

    def _cycle(self, counter: int | None, t: float, send_sync: bool, jitter: float = 0.0,
               received_sync: int | None = None) -> None:
        """Everything one SYNC does: heartbeats due, the fault timeline at this sample, the
        physics sample into the nodes, EMCY on status changes, TPDOs in COB-ID order (bus
        arbitration), bus-level faults, the truth bookkeeping."""
        plan, self._plan = self._plan, None
        if plan is not None:  # real time: the answer was built ahead of this SYNC
            if plan.counter == counter and plan.n_sync == self._n_sync and self._ahead is plan.sample:
                self._commit(plan, counter, t, send_sync, jitter)
                return
            self._undo(plan)  # not the SYNC it was built for: build it now, as below
        self._last_counter = counter
        self._advance(t)
        if received_sync is not None:  # the master's SYNC occupied the bus
            self.clock.occupy(t, self._frame_time(received_sync))
        sample = self._next_sample()
        k = int(getattr(sample, "index", len(self.sync_info)))
        st = float(getattr(sample, "t", k * self.dt))
        fi = self.faults
        names = [n.name for n in self.nodes]
        lost = False
        if send_sync:
            _, lost = self._sync_plan(self._n_sync)
            self._n_sync += 1
            if jitter:
                fi.record(k, st, "jitter", None, offset_s=jitter)
            if lost:
                fi.record(k, st, "lostsync", None, counter=counter)
            else:
                self._transmit("sync", self._sync_cob,
                               bytes([counter]) if counter is not None else b"", t)
        self.sync_info.append((k, -1 if counter is None else counter, t, lost))
        if fi:
            started = []
            for f, name, on in fi.window_changes(k, st, names):
                node = self.by_name[name]
                if f.kind in ("overrange", "sensor") and "status" not in ROLE_CHANNELS[node.role]:
                    continue
                fi.record(k, st, f.kind, name, event="start" if on else "end",
                          channel=f.channel, spec=f.token)
                if f.kind == "silent":
                    node.silent = on
                if on:
                    started.append((f, node))
            pre = []
            for f, name in fi.reboots(st, names):
                node = self.by_name[name]
                fi.record(k, st, "reboot", name, event="inject", spec=f.token)
                pre.extend((node, fr) for fr in node.reset(False, t))
            for node, fr in pre:
                self._send_frame(fr, t, node)
        else:
            started = []
        # process image: the sample encoded as the bus carries it (the one codec shared with
        # the off-line API), then the node-level faults on top
        enc = self._codec.encode(T=sample.T, cell_status=sample.cell_status, accel=sample.accel,
                                 omega=sample.omega, azimuth=sample.azimuth,
                                 H_balance=sample.H_balance, drive=sample.drive)
        raw = {k: getattr(enc, k).tolist() for k in _ENCODED}  # exact python ints/floats
        frames: list[tuple[SimNode, Frame]] = []
        for feed in self._feeds:
            node = feed.node
            node.set_raws(feed.raws(raw))
            if fi:
                self._apply_node_faults(feed, started)
            frames.extend((node, fr) for fr in self._status_emcy(feed))
        if lost:
            fi.end_sample(st)
            return
        for n in self.nodes:
            frames.extend((n, fr) for fr in n.sync(counter))
        frames.sort(key=lambda p: p[1].cob_id)  # arbitration: lowest identifier first
        for node, fr in frames:
            if node.silent:
                continue
            if fr.kind == "tpdo" and fi:
                f = fi.chance("drop", k, st, node.name, slot=fr.cob_id)
                if f is not None:
                    fi.record(k, st, "drop", node.name, cob_id=fr.cob_id, tpdo=fr.tpdo)
                    continue
                f = fi.chance("malformed", k, st, node.name, slot=0x1000 | fr.cob_id)
                if f is not None:
                    bad = fr.data[:-1] if len(fr.data) > 1 else fr.data + b"\x00"
                    fi.record(k, st, "malformed", node.name, cob_id=fr.cob_id, tpdo=fr.tpdo,
                              length=len(bad), expected=len(fr.data))
                    fr = fr._replace(data=bad)
            self._send_frame(fr, t, node)
        if fi:
            f = fi.chance("unknown", k, st, slot=0x2000)
            if f is not None:
                cob = f.cob_id if f.cob_id is not None else self._unknown_cob
                fi.record(k, st, "unknown", None, cob_id=cob)
                self._transmit("unknown", cob, fi.payload(k, 0x2000), t)
            f = fi.chance("errorframe", k, st, slot=0x3000)
            if f is not None:
                fi.record(k, st, "errorframe", None)
                self._transmit("error", 0, b"", t, error=True)
            fi.end_sample(st)

    # ------------------------------------------------------------------------------------------
    # the next SYNC's answer built ahead of it (a real-time driver asks, between two SYNCs)
    def prefetch(self) -> None:
        """Compute the next physics sample now when the physics computes a whole block at it
        (AircraftPhysics: every ``block_size`` samples) and it is not computed yet: off the
        next SYNC's path to its TPDOs."""
        with self.lock:
            if self._block_boundary():
                self._ahead = self.physics.next_sample()
                self.prefetched += 1

    def _block_boundary(self) -> bool:
        """The physics computes a whole block at its next sample (AircraftPhysics: every
        ``block_size`` samples) and that sample is not computed ahead yet."""
        bs = getattr(self.physics, "block_size", None)
        k = getattr(self.physics, "index", None)
        return bool(bs) and k is not None and self._ahead is None and k % bs == 0

    def _windows_change(self, st: float) -> bool:
        """A window fault begins or ends at sample time ``st`` (FaultInjector.window_changes
        would report a change), without changing the injector."""
        fi = self.faults
        for kind in WINDOW_KINDS:
            for f in fi.of(kind):
                now = f.active(st)
                for n in self.nodes:
                    if f.applies_to(n.name) and now != ((f.index, n.name) in fi._active):
                        return True
        return False

    def prepare_next(self) -> None:
        """Build the answer to the next SYNC now (a real-time driver, between SYNCs): the same
        steps as ``_cycle`` in the same order — process image, node faults, TPDOs due, the
        drop/malformed/unknown/errorframe draws (pure functions of seed, sample and slot) — with
        the fault-log entries and the frames kept in order for the SYNC to emit and send.
        Not built ahead (left to the SYNC, as before): a sample where a fault window opens or
        closes, a node reboots, an EMCY goes out or the SYNC is lost; anything that then
        changes a node (NMT, SDO) undoes the plan first (SimNode.before_change)."""
        with self.lock:
            if not self._closed and self._plan is None and self._feeds:
                self._prepare_next()

    def _prepare_next(self) -> None:
        ovf = self._counter_overflow
        if self.autostart:
            counter = self._counter % ovf + 1 if ovf else None
            if self._sync_plan(self._n_sync)[1]:
                return  # this SYNC is lost
        elif not self.sync_info:
            return  # follow mode: the master's counter is predicted from its last SYNC
        else:
            last = self._last_counter
            counter = None if last is None or not ovf else last % ovf + 1
        if self._ahead is None:
            self._ahead = self.physics.next_sample()
        sample = self._ahead
        k = int(getattr(sample, "index", len(self.sync_info)))
        st = float(getattr(sample, "t", k * self.dt))
        fi = self.faults
        if fi and (self._windows_change(st) or fi.reboots(st, [n.name for n in self.nodes])):
            return
        plan = _Plan(sample, k, st, counter, self._n_sync,
                     [(n, n.snapshot()) for n in self.nodes], [], [])
        enc = self._codec.encode(T=sample.T, cell_status=sample.cell_status, accel=sample.accel,
                                 omega=sample.omega, azimuth=sample.azimuth,
                                 H_balance=sample.H_balance, drive=sample.drive)
        raw = {name: getattr(enc, name).tolist() for name in _ENCODED}
        for feed in self._feeds:
            feed.node.set_raws(feed.raws(raw))
            if fi:
                self._apply_node_faults(feed, [])
            if self._status_emcy(feed):  # a status bit changes: left to the SYNC
                for node, snap in plan.snap:
                    node.restore(snap)
                return
        frames: list[tuple[SimNode, Frame]] = []
        for n in self.nodes:
            carried: list = []
            frames.extend((n, fr) for fr in n.sync(counter, carried))
            if carried:
                plan.carried.append((n, carried))
        frames.sort(key=lambda p: p[1].cob_id)  # arbitration: lowest identifier first
        acts = plan.actions
        for node, fr in frames:
            if node.silent:
                continue
            if fr.kind == "tpdo" and fi:
                f = fi.chance("drop", k, st, node.name, slot=fr.cob_id)
                if f is not None:
                    acts.append(("rec", (k, st, "drop", node.name),
                                 {"cob_id": fr.cob_id, "tpdo": fr.tpdo}))
                    continue
                f = fi.chance("malformed", k, st, node.name, slot=0x1000 | fr.cob_id)
                if f is not None:
                    bad = fr.data[:-1] if len(fr.data) > 1 else fr.data + b"\x00"
                    acts.append(("rec", (k, st, "malformed", node.name),
                                 {"cob_id": fr.cob_id, "tpdo": fr.tpdo, "length": len(bad),
                                  "expected": len(fr.data)}))
                    fr = fr._replace(data=bad)
            acts.append(("send", self._build(fr.cob_id, fr.data)))
        if fi:
            f = fi.chance("unknown", k, st, slot=0x2000)
            if f is not None:
                cob = f.cob_id if f.cob_id is not None else self._unknown_cob
                acts.append(("rec", (k, st, "unknown", None), {"cob_id": cob}))
                acts.append(("send", self._build(cob, fi.payload(k, 0x2000))))
            f = fi.chance("errorframe", k, st, slot=0x3000)
            if f is not None:
                acts.append(("rec", (k, st, "errorframe", None), {}))
                acts.append(("send", self._build(0, b"", error=True)))
        self._plan = plan

    def _undo(self, plan: _Plan) -> None:
        """The nodes back to before ``plan`` was built (its sample stays the next one)."""
        for node, snap in plan.snap:
            node.restore(snap)
        self.plans_discarded += 1

    def _discard_plan(self) -> None:
        """Something outside a SYNC cycle is about to change a node: undo the plan first."""
        with self.lock:
            plan, self._plan = self._plan, None
            if plan is not None:
                self._undo(plan)

    def _commit(self, plan: _Plan, counter: int | None, t: float, send_sync: bool,
                jitter: float) -> None:
        """The SYNC a plan was built for: what ``_cycle`` does at the SYNC, in its order, with
        the frames sent as built."""
        self._last_counter = counter
        self._advance(t)
        self._next_sample()  # plan.sample: the truth bookkeeping
        k, st, fi = plan.k, plan.st, self.faults
        if send_sync:  # not lost: prepare_next does not build a lost SYNC's answer
            self._n_sync += 1
            if jitter:
                fi.record(k, st, "jitter", None, offset_s=jitter)
            self._transmit("sync", self._sync_cob,
                           bytes([counter]) if counter is not None else b"", t)
        self.sync_info.append((k, -1 if counter is None else counter, t, False))
        for node, carried in plan.carried:
            node.carry(carried)
        sends = []
        for a in plan.actions:
            if a[0] == "send":
                sends.append(a[1])
            else:
                fi.record(*a[1], **a[2])
        if sends:  # the whole answer in one send where the bus allows (one wake-up)
            self._send_built_many(sends)
        self.prepared += 1
        if fi:
            fi.end_sample(st)

    def _apply_node_faults(self, feed: _NodeFeed, started: list[tuple[Fault, SimNode]]) -> None:
        fi, node = self.faults, feed.node
        chans = [c for c in ROLE_CHANNELS[node.role] if c != "status"]
        for f, n in started:  # a stuck channel holds the value it had when the fault began
            if n is node and f.kind == "stuck":
                for ch in ([f.channel] if f.channel else chans):
                    self._frozen[(f.index, node.name, ch)] = node.raw(ch)
        for f in fi.of("stuck"):
            if (f.index, node.name) not in fi._active:
                continue
            for ch in ([f.channel] if f.channel else chans):
                v = self._frozen.get((f.index, node.name, ch))
                if v is not None:
                    node.set_raw(ch, v)
        if "status" in ROLE_CHANNELS[node.role]:
            status = int(node.raw("status") or 0)
            if fi.active("overrange", node.name) is not None:
                status |= STATUS_OVER_RANGE
                force = node.raw("force") or 0.0
                node.set_raw("force", math.copysign(feed.full_scale or abs(force), force))
            if fi.active("sensor", node.name) is not None:
                status |= STATUS_SENSOR_FAULT
            node.set_raw("status", status)

    def _status_emcy(self, feed: _NodeFeed) -> list[Frame]:
        """EMCY when a status bit appears or clears (CiA 301: only in pre-op or operational)."""
        node = feed.node
        if "status" not in ROLE_CHANNELS[node.role] or node.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return []
        status = int(node.raw("status") or 0)
        out = []
        for bit, code in _STATUS_EMCY:
            if status & bit and code not in node._active_errors:
                out.append(node.raise_error(code, info=bytes([status])))
            elif not status & bit and code in node._active_errors:
                fr = node.clear_error(code)
                if fr is not None:
                    out.append(fr)
        return out

    def _flush(self, t: float) -> None:
        self._last_flush = t
        f = getattr(self._logger, "file", None)
        if f is not None and hasattr(f, "flush"):
            f.flush()

    # ------------------------------------------------------------------------------------------
    # truth
    @property
    def fault_log(self) -> list[dict]:
        return list(self.faults.log)

    def sync_arrays(self) -> dict[str, np.ndarray]:
        """Per sample: index, SYNC counter (0: the SYNC carried none), SYNC time, lost flag."""
        a = self.sync_info.arrays()
        return {"sample_index": a["k"].astype(np.int64),
                "sync_counter": np.maximum(a["counter"], 0).astype(np.uint8),
                "sync_time": a["t"].astype(float), "sync_lost": a["lost"].astype(bool)}

    def truth_arrays(self) -> dict[str, np.ndarray]:
        """The kept samples as sim_bus.truth arrays: the physics truth, the channels as the bus
        carried them before faults (quantised by the shared codec, with the raw counts), and per
        sample the SYNC counter, time and loss. Needs keep_samples=True."""
        arrs = self.samples.arrays()
        if not arrs:
            raise ValueError("no samples kept: run with keep_samples=True and at least one SYNC")
        enc = self._codec.encode(**{k: arrs[k] for k in
                                    ("T", "cell_status", "accel", "omega", "azimuth",
                                     "H_balance", "drive")})
        arrs.update(self._codec.decode(enc))
        arrs["accel_counts"], arrs["azimuth_counts"] = enc.accel_counts, enc.azimuth_counts
        n = len(arrs["index"])
        sync = self.sync_arrays()
        arrs["sync_counter"] = sync["sync_counter"][:n]
        arrs["sync_time"] = sync["sync_time"][:n]
        arrs["sync_lost"] = sync["sync_lost"][:n]
        return arrs

    def write_truth(self, path: str | Path, meta: dict | None = None,
                    write: Callable[[Path, bytes], None] | None = None) -> Path:
        """Write the truth file (sim_bus.truth format) with the injected faults; ``write``
        as in :func:`sim_bus.truth.write_truth` (an atomic write)."""
        from rsra.sim_bus.offline import run_meta
        from rsra.sim_bus.truth import write_truth

        full = {}
        if hasattr(self.physics, "scenario"):
            full.update(run_meta(self.cfg, self.physics))
        full.update(faults_spec=[f.token for f in self.faults.faults],
                    fault_entries_not_kept=self.faults.dropped_log_entries,
                    samples_not_kept=self.samples.dropped,
                    nodes=[n.name for n in self.nodes], lockstep=self.clock.simulated,
                    autostart=self.autostart, **(meta or {}))
        arrs = self.truth_arrays()
        return write_truth(path, arrs, faults=self.fault_log, meta=full,
                           sync_counter=arrs["sync_counter"], write=write)


class RecordError(OSError):
    """The recording file cannot be written."""


def _open_logger(path: Path) -> can.Listener:
    """python-can's writer for the file's suffix; candump .log when the suffix names none."""
    from can.io.logger import MESSAGE_WRITERS

    suffixes = [s.lower() for s in path.suffixes]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffixes and (suffixes[-1] in MESSAGE_WRITERS or (
                suffixes[-1] == ".gz" and len(suffixes) > 1 and suffixes[-2] in MESSAGE_WRITERS)):
            return can.Logger(str(path))
        return can.CanutilsLogWriter(str(path))
    except (OSError, ValueError, ImportError) as e:
        raise RecordError(f"cannot record to {path}: {e}") from e
