"""Where the service's samples come from: one :class:`Source` protocol, one class per kind.

::

    make_source(cfg, opts) ─▶ BusSource        a CANopen bus; the reader is the master
                           ├▶ RealtimeSimSource the in-process simulator in real time + BusSource
                           ├▶ LockstepSource   the simulator stepped with the reader
                           │                   (sim_bus.drivers.LockstepDriver)
                           └▶ ReplaySource     recorded frames through an offline reader

    with source:                                   # opens bus / simulator / recording
        for item in source.items(stop_event):      # Sample | HealthReport | None (idle)
            ...

Each kind differs by its class, never by a flag the service checks: the service asks a source
what it is (``deterministic``: the samples do not come at the wall clock's pace, so the
identification results are awaited at their planned sample and nothing measures latency;
``saves_posterior``), and for the replay-only angle schedule (:meth:`Source.angles_plan`).
``make_source`` is the one place that reads the run options to choose the kind.
A source's ``__exit__`` closes what it opened in reverse order (an ExitStack), the
simulator's truth file written after the simulator stopped.
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, TypeGuard, cast

from rsra.daq.jsonlines import json_lines
from rsra.daq.runtime.records import AnglesRecord

if TYPE_CHECKING:
    from rsra.daq.bus.assembler import Sample
    from rsra.config.rig import RigConfig
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.daq.bus.reader import HealthReport, ReaderBase
    from rsra.daq.bus.recorder import Recorder
    from rsra.sim_bus.drivers import LockstepDriver

log = logging.getLogger("rsra.service")

# the in-process simulator computes its physics in blocks of samples; a block of 1000 takes
# 7-14 ms, longer than a 5 ms sample period, which in real time made the simulated nodes miss
# a SYNC every 5 s. 100-sample blocks take ~1 ms. Lock-step uses the same size, so a seed gives
# the same samples in both modes.
SIM_BLOCK = 100
LIVE_POLL_S = 0.05  # a live source yields None after this long without an item
PACE_SLACK_S = 0.05  # paced lock-step: a delay longer than this is not caught up


class BusOpenError(RuntimeError):
    """The CAN interface could not be opened (no such interface or channel, no driver)."""


@dataclass
class AnglesPlan:
    """Where the angles of a run come from (replay: the recording's schedule, or recomputed).

    ``recorded_initial``/``recorded``: the recording's starting record and angles records
    (applied from their samples); ``recompute``: the identification runs; ``schedule``: the
    summary's ``angles_schedule`` (None for a live source); ``folder``: the recording."""

    recorded_initial: dict | None = None
    recorded: list[AnglesRecord] = field(default_factory=list)
    recompute: bool = False
    schedule: dict | None = None
    folder: Path | None = None


class Source(Protocol):
    """A stream of samples and 1 Hz health reports, in acquisition order."""

    deterministic: ClassVar[bool]  # not paced by the wall clock: results awaited, no latency
    saves_posterior: ClassVar[bool]  # identification.state_file is written by this kind of run
    reader: ReaderBase | None  # Reader, LockstepReader or OfflineReader
    sim: Any  # the in-process simulator, if any (its truth, recent samples)
    recorder: Recorder | None
    # live: the service's first step of each sample, run in the bus thread (set before open)
    first_step: Callable[[Sample], Any] | None

    def describe(self) -> str: ...

    def angles_plan(self, identification: bool, recompute: bool) -> AnglesPlan: ...

    def __enter__(self) -> Source: ...

    def __exit__(self, *exc: object) -> None: ...

    def items(self, stop: threading.Event) -> Iterator[Sample | HealthReport | None]: ...


class _Base:
    """What every source shares: the reader, the recorder, an ExitStack of what it opened."""

    deterministic: ClassVar[bool] = False
    saves_posterior: ClassVar[bool] = True

    def __init__(self, cfg: RigConfig):
        self.cfg = cfg
        self.table: DecodeTable | None = None  # read on open (the EDS files)
        self.reader: ReaderBase | None = None
        self.sim: Any = None
        self.recorder: Recorder | None = None
        self.truth_error: str | None = None  # the simulator's truth file could not be written
        self._stack = contextlib.ExitStack()
        # a live source runs this on each sample in its bus thread before queueing it (the
        # service's first step: hub loads published with no hand-off between threads, so the
        # service's own share of the latency stays a fraction of the sample period); set
        # before the source is opened; sources that are not live ignore it
        self.first_step: Callable[[Sample], Any] | None = None

    def angles_plan(self, identification: bool, recompute: bool) -> AnglesPlan:
        return AnglesPlan(recompute=recompute)

    def __enter__(self):
        from rsra.daq.bus.decoder import DecodeTable

        try:
            # the EDS files first: one the simulator cannot read either is a ConfigError
            # naming the key (exit 2), not a traceback from inside the simulator's nodes
            self.table = DecodeTable(self.cfg)
            self._open()
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def close(self) -> None:
        self._stack.close()

    def _open(self) -> None:
        raise NotImplementedError

    def _close_quietly(self, close: Any) -> None:
        """Register ``close`` so that a failure is logged and the rest still closes."""
        def run() -> None:
            try:
                close()
            except Exception as e:  # keep closing the rest
                log.error("shutdown: %s", e)
        self._stack.callback(run)


def _write_truth_after(stack: contextlib.ExitStack, sim: Any, truth: str | None,
                       source: _Base) -> None:
    """On exit: the simulator closed first (in real time its threads would still be
    appending), then its truth file written (beside the recording by default)."""
    def close() -> None:
        path = truth
        if path is None and source.recorder is not None:
            path = str(Path(source.recorder.folder) / "truth.npz")
        sim.close()
        if path:
            from rsra.daq.runtime.persistence import write_bytes_atomic

            try:  # written whole or not at all (a full disk leaves no empty file)
                sim.write_truth(path, write=write_bytes_atomic)
            except Exception as e:
                source.truth_error = f"truth not written ({path}): {_why(e)}"
                log.error("%s", source.truth_error)
    source._close_quietly(close)


def _why(e: BaseException) -> str:
    return (e.strerror or str(e)) if isinstance(e, OSError) else f"{type(e).__name__}: {e}"


class BusSource(_Base):
    """A CANopen bus through python-can; the reader boots the nodes, produces SYNC and
    supervises them; samples come from its bus thread through a bounded queue."""

    record_channel: str | None = None  # the recording's channel name (None: the interface's)

    def __init__(self, cfg: RigConfig, *, interface: str | None,
                 channel: str | None, record: str | None = None):
        super().__init__(cfg)
        self.interface, self.channel, self.record = interface, channel, record

    def describe(self) -> str:
        return f"bus {self.interface}:{self.channel}"

    def _open(self) -> None:
        import can

        from rsra.daq.bus.reader import DropQueue, Reader

        # the live master (BootNodes), the wall clock, a queue that never blocks the bus thread
        reader = Reader(self.cfg, interface=self.interface, channel=self.channel,
                        record=self.record, table=self.table,
                        items=DropQueue(first_step=self.first_step),
                        record_channel=self.record_channel)
        self.reader = reader
        self._close_quietly(reader.close)
        try:
            reader.start()  # boots the nodes; BootError names node, object and both values
        except (OSError, ImportError, ValueError, can.CanError) as e:
            raise BusOpenError(
                f"cannot open the bus {self.interface or 'virtual'}:{self.channel} ({e}); check "
                f"--interface/--channel (python-can interfaces: "
                f"{', '.join(sorted(set(can.VALID_INTERFACES) - {'udp_multicast'}))})") from None
        self.recorder = reader.recorder

    def items(self, stop: threading.Event) -> Iterator[Sample | HealthReport | None]:
        reader = self.reader
        assert reader is not None  # _open() made it
        while not stop.is_set():
            yield reader.get(timeout=LIVE_POLL_S)  # None when idle: results are still polled


def _physics(cfg: RigConfig, sim: str, seed: int | None, variants: dict) -> Any:
    from rsra.sim_bus.physics import AircraftPhysics
    from rsra.sim_bus.scenarios import load_scenario

    return AircraftPhysics(cfg, load_scenario(sim, **variants), seed=seed, block_size=SIM_BLOCK)


@dataclass
class SimOptions:
    """The in-process simulator: scenario, seed, faults, truth file."""

    scenario: str
    seed: int | None = None
    faults: str | None = None
    channel: str | None = None
    truth: str | None = None
    keep_truth: bool = False  # keep the truth history even without a truth file
    variants: dict = field(default_factory=dict)


class RealtimeSimSource(BusSource):
    """The simulator in real time on a virtual bus (its own threads), the reader its master."""

    record_channel = "sim"  # the bus is the simulator's, its generated name new every run

    def __init__(self, cfg: RigConfig, sim: SimOptions,
                 record: str | None = None):
        super().__init__(cfg, interface="virtual",
                         channel=sim.channel or f"rsra-{id(self):x}", record=record)
        self.sim_opts = sim

    def describe(self) -> str:
        return f"simulator {self.sim_opts.scenario!r} in process (real time)"

    def _open(self) -> None:
        from rsra.sim_bus.drivers import RealtimeSim

        o = self.sim_opts
        # the truth history (bounded, ~0.5 kB a sample) only when a truth file is wanted
        keep = bool(o.truth or self.record or o.keep_truth)
        self.sim = RealtimeSim(self.cfg, physics=_physics(self.cfg, o.scenario, o.seed, o.variants),
                               seed=o.seed, faults=o.faults, channel=self.channel,
                               autostart=False, keep_samples=keep)
        _write_truth_after(self._stack, self.sim, o.truth, self)
        self.sim.start()
        super()._open()


class LockstepSource(_Base):
    """The simulator boots and starts its nodes and produces SYNC; each step moves simulated
    time one sample (sim_bus.drivers.LockstepDriver). The reader listens, and restarts a node
    that reboots (bus.md: reconfigured and restarted without restarting the service) in its
    master's thread, its SDO answered while the driver holds time. ``speed``: None as fast as
    possible, else simulated time runs at ``speed`` × the wall clock."""

    deterministic = True

    def __init__(self, cfg: RigConfig, sim: SimOptions,
                 speed: float | None, record: str | None = None):
        super().__init__(cfg)
        self.sim_opts, self.speed, self.record = sim, speed, record
        self.driver: LockstepDriver | None = None

    def describe(self) -> str:
        mode = "lock-step, as fast as possible" if self.speed is None else \
            f"lock-step at {self.speed:g}x real time"
        return f"simulator {self.sim_opts.scenario!r} in process ({mode})"

    def _open(self) -> None:
        import can

        from rsra.daq.bus.reader import BlockQueue, LockstepReader, RestartNodes
        from rsra.sim_bus.drivers import HandoffBus, LockstepDriver, LockstepSim

        o, cfg = self.sim_opts, self.cfg
        channel = o.channel or f"rsra-{id(self):x}"
        keep = bool(o.truth or self.record or o.keep_truth)
        t0 = round(time.time(), 3)  # simulated time reads like UNIX time
        self.sim = LockstepSim(cfg, physics=_physics(cfg, o.scenario, o.seed, o.variants),
                               seed=o.seed, faults=o.faults, channel=channel, autostart=True,
                               t0=t0, keep_samples=keep)
        _write_truth_after(self._stack, self.sim, o.truth, self)
        bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=True,
                      preserve_timestamps=True)
        self._close_quietly(bus.shutdown)
        handoff = HandoffBus(bus)
        restart = RestartNodes()  # the simulator boots the nodes; a reboot is restarted
        # (HandoffBus: python-can's bus, its own send; a wrapper, not a can.BusABC subclass)
        reader = LockstepReader(cfg, cast(can.BusABC, handoff), record=self.record,
                                table=self.table, items=BlockQueue(), nodes=restart,
                                record_channel="sim")
        self.reader = reader
        self._close_quietly(reader.close)
        self.driver = driver = LockstepDriver(self.sim, reader, handoff)
        self._close_quietly(driver.close)  # before the reader: its master may wait on it
        reader.start()
        driver.start()  # the simulator's own boot-ups: seen, not acted upon
        restart.supervise()
        self.recorder = reader.recorder

    def items(self, stop: threading.Event) -> Iterator[Sample | HealthReport | None]:
        driver, reader, speed = self.driver, self.reader, self.speed
        assert driver is not None and reader is not None  # _open() made them
        dt = 1.0 / self.cfg.sample_rate_hz
        wall0 = time.monotonic()
        k = 0
        while not stop.is_set():
            driver.step()  # a node that booted: restarted before time moves on
            k += 1
            yield from reader.poll()
            if speed:  # paced lock-step: simulated time runs at `speed` x the wall clock
                ahead = k * dt / speed - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
                elif ahead < -PACE_SLACK_S:
                    # held up (a consumer waited, the machine stalled): go on at the pace
                    # from here, not in a burst that catches up (subscribers under DROP
                    # would lose the burst)
                    wall0 -= ahead  # ahead < 0: the schedule moves later by the delay


class ReplaySource(_Base):
    """Recorded frames through an offline reader (daq.replay), as fast as possible or at
    recorded timing (``paced``); the angles follow the recorded schedule or are recomputed.
    As fast as possible the recording is read by the columnar path (daq.bus.columnar)
    unless ``streaming`` (every frame one by one: the reference); the items are the same."""

    deterministic = True
    saves_posterior = False  # identification.state_file is the live service's output (cli.md)

    def __init__(self, cfg: RigConfig, paths: list[str],
                 paced: bool = False, streaming: bool = False):
        super().__init__(cfg)
        self.paths, self.paced, self.streaming = list(paths), paced, streaming
        self._items: Iterator | None = None

    def describe(self) -> str:
        return f"replay of {', '.join(self.paths)}"

    def angles_plan(self, identification: bool, recompute: bool) -> AnglesPlan:
        folder = next((Path(p) for p in self.paths if Path(p).is_dir()), None)
        plan = AnglesPlan(recompute=recompute, folder=folder)
        schedule = None if folder is None else folder / "angles.jsonl"
        if not identification:
            # the starting angles (the recording's, or --angles) for the whole replay
            if folder is not None:
                plan.recorded_initial, _ = read_angles_schedule(folder)
            plan.schedule = {"source": "off"}
        elif recompute:
            plan.schedule = {"source": "recomputed", "why": "--recompute"}
        elif schedule is None or not schedule.is_file():
            # a recording from elsewhere (bus.md): the identification is recomputed
            plan.recompute = True
            plan.schedule = {"source": "recomputed", "why": "no angle schedule"}
        else:
            assert folder is not None  # the schedule is in it
            _follow_recorded(plan, folder, schedule)
        return plan

    def _open(self) -> None:
        from rsra.daq.bus.reader import OfflineReader
        from rsra.daq.bus.replay import replay

        self.reader = OfflineReader(self.cfg, table=self.table)
        self._items = replay(self.cfg, self.paths, realtime=self.paced, reader=self.reader,
                             finish=True, streaming=self.streaming)

    def items(self, stop: threading.Event) -> Iterator[Sample | HealthReport | None]:
        assert self._items is not None  # _open() made it
        return self._items


def make_source(cfg: RigConfig, opts: Any) -> Source:
    """The source the run options name (``daq.service.ServiceOptions``): a replay, the
    simulator in lock-step (``--speed`` other than 1) or real time, or a bus. Opens nothing
    (the source does, entered)."""
    if opts.replay is not None:
        return ReplaySource(cfg, opts.replay, paced=opts.realtime, streaming=opts.streaming)
    if opts.sim is not None:
        sim = SimOptions(scenario=opts.sim, seed=opts.seed, faults=opts.faults,
                         channel=opts.channel, truth=opts.truth, keep_truth=opts.keep_truth,
                         variants=opts.scenario_variants)
        if opts.speed != 1.0:
            return LockstepSource(cfg, sim, opts.speed, record=opts.record)
        return RealtimeSimSource(cfg, sim, record=opts.record)
    return BusSource(cfg, interface=opts.interface, channel=opts.channel,
                     record=opts.record)


# -- the recorded angle schedule (replay) -------------------------------------------------------
def read_angles_schedule(folder: Path, file: Path | None = None
                         ) -> tuple[dict | None, list[dict]]:
    """The starting posterior and the recorded angles records of a recording folder (or of
    ``file``, an ``angles.jsonl`` by another name)."""
    p = folder / "angles.jsonl" if file is None else file
    if not p.is_file():
        return None, []
    initial, records = None, []

    def skip(n: int, why: str) -> None:
        log.warning("%s:%d: unreadable angles record skipped (%s; a crash mid-write?)", p, n, why)

    for n, rec in json_lines(p, skip):
        problem = _schedule_problem(rec)
        if problem:
            from rsra.daq.bus.replay import ReplayError

            raise ReplayError(f"{p}:{n}: {problem}; fix: replay with --recompute (runs the "
                              "identification again) or repair that line")
        if rec.get("initial"):
            initial = rec
        else:
            records.append(rec)
    return initial, records


def _follow_recorded(plan: AnglesPlan, folder: Path, schedule: Path) -> None:
    """``plan`` follows the recording's angle schedule: its starting record, its records and
    where the last one applies from."""
    plan.recorded_initial, recorded = read_angles_schedule(folder)
    plan.recorded = [AnglesRecord.from_dict(r) for r in recorded]
    applies = [a for a in (r.get("applies_from_seq") for r in recorded) if isinstance(a, int)]
    plan.schedule = {"source": "recorded", "file": str(schedule), "records": len(plan.recorded),
                     "initial": plan.recorded_initial is not None,
                     "last_applies_from_seq": max(applies, default=None)}


def _finite_numbers(x: Any) -> TypeGuard[list[int | float]]:
    return isinstance(x, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in x)


def _schedule_problem(rec: Any) -> str | None:
    """What makes a recorded angles record unusable (None: usable)."""
    if not isinstance(rec, dict):
        return "an angles record must be a JSON object"
    if rec.get("initial"):
        alpha = rec.get("alpha_all", rec.get("alpha"))
        if not _finite_numbers(alpha) or not alpha:
            return "the starting record has no finite 'alpha_all' angles"
        return None
    seq = rec.get("applies_from_seq")
    if "applies_from_seq" not in rec:
        return "angles record without 'applies_from_seq' (the sample it applies from)"
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
        return f"'applies_from_seq' = {seq!r} is not a sample number"
    if rec.get("accepted") and not _named_angles(rec.get("names"), rec.get("alpha")):
        return "an accepted angles record needs 'names' and as many finite 'alpha' values"
    return None


def _named_angles(names: Any, alpha: Any) -> bool:
    """A list of names and as many finite angles."""
    return (isinstance(names, list) and all(isinstance(x, str) for x in names)
            and _finite_numbers(alpha) and len(names) == len(alpha))
