"""The service runtime (`rsra run`, `rsra demo`, `rsra replay`): one code path for every source.

    source (live bus │ simulator in lock-step │ recording: rsra.daq.runtime.sources) ─▶ samples
        ─▶ estimator loop (this thread): pipeline.process(sample) ─▶ publishers
        └▶ identification windows ─▶ worker process ─▶ angles records ─▶ applied from a stated sample

* Live (`--interface/--channel`, or `--sim` in real time): the reader's bus thread assembles
  samples into a bounded queue; this thread estimates and publishes; identification results
  apply from their planned sample, or from the first sample after they arrive (`late`).
* Lock-step (`--sim … --speed max`, or a paced `--speed X`): the simulator boots its nodes
  and produces SYNC; each step moves simulated time by one sample, so the samples are those of
  real time and nothing reads the wall clock. A node that reboots is restarted by the reader
  (SDO and NMT start between two steps, answered synchronously: RestartNodes). The loop
  waits for identification results at their planned sample, so a run is deterministic.
* Replay: recorded frames through the same reader; the recorded `angles` schedule reproduces
  the live run bit for bit, or `--recompute` runs the identification deterministically.

The kind of source is chosen once (``make_source``) and the service asks it only what it is
(``deterministic``, ``saves_posterior``, its angle plan); docs/architecture.md "Runtime".
High-rate records are published inline (Zenoh congestion control DROP never blocks); the
low-rate ones (angles, health) go through a small bounded queue to a publisher thread, since a
slow subscriber may block them.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rsra.config.rig import RigConfig
from rsra.daq.jsonout import dumps
from rsra.daq.runtime.ident_worker import background_scheduling, chained
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.runtime.records import AnglesRecord
from rsra.daq.runtime.run_report import HealthReporter, run_summary
from rsra.daq.runtime.sample_loop import SampleLoop
from rsra.daq.runtime.sources import SIM_BLOCK, BusOpenError, Source, make_source  # noqa: F401 (re-exported)
from rsra.daq.runtime.start import StartPlan, initial_angles, plan_start  # noqa: F401 (re-exported)
from rsra.daq.runtime.supervision import Supervision

if TYPE_CHECKING:
    import zenoh

    from rsra.daq.bus.health import Health
    from rsra.daq.runtime.telemetry import TelemetryPublisher

log = logging.getLogger("rsra.service")

LOW_RATE_QUEUE = 64
# real time: the interpreter's thread switch interval (gil_switch_interval)
LIVE_SWITCH_INTERVAL_S = 0.0005


@dataclass
class ServiceOptions:
    interface: str | None = None
    channel: str | None = None
    sim: str | None = None  # scenario name or path
    seed: int | None = None
    faults: str | None = None
    speed: float | None = 1.0  # None = as fast as possible (lock-step)
    record: str | None = None
    duration: float | None = None  # seconds of acquisition time
    angles: str | None = None  # a saved posterior to start from
    accept_rig_mismatch: bool = False  # use (or replace) a posterior of another rig
    zenoh: bool = True
    zenoh_config: str | None = None
    zenoh_listen: list[str] = field(default_factory=list)
    zenoh_connect: list[str] = field(default_factory=list)
    identification: bool = True
    truth: str | None = None  # simulator truth file (default: beside the recording)
    keep_truth: bool = False  # keep the simulator's truth history in memory (demo report)
    scenario_variants: dict = field(default_factory=dict)
    # replay
    replay: list[str] | None = None
    recompute: bool = False
    realtime: bool = False
    streaming: bool = False  # replay every frame one by one (the reference path)
    # Foxglove WebSocket output (daq.foxglove_out): "HOST:PORT", browser origins let in, and
    # where its address is told (default: standard error)
    foxglove: str | None = None
    foxglove_origins: list[str] = field(default_factory=list)
    foxglove_announce: Callable[[str], None] | None = None
    # real-time scheduling (SCHED_FIFO at this priority, 1-99) for the service's threads;
    # None: the default scheduler (docs/deployment.md "Real-time priority")
    realtime_priority: int | None = None


class _LowRatePublisher:
    """A thread that publishes angles and health records (which may block on Zenoh)."""

    def __init__(self, publish: Callable[[str, dict], Any]):
        self._publish = publish
        self.queue: queue.Queue = queue.Queue(LOW_RATE_QUEUE)
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="rsra-low-rate", daemon=True)
        self._thread.start()

    def put(self, key: str, payload: dict) -> None:
        try:
            self.queue.put_nowait((key, payload))
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                return
            try:
                self._publish(*item)
            except Exception as e:  # never let a publishing error kill the thread
                log.debug("low-rate publish failed: %s", e)

    def close(self) -> None:
        try:
            self.queue.put(None, timeout=2.0)
        except queue.Full:
            pass
        self._thread.join(timeout=5.0)


class Outputs:
    """Where the records go: Zenoh, a JSONL file, in-process sinks (tests, the demo view).

    What it opens (Zenoh session, publisher, low-rate thread) is held by an ExitStack and
    closed in reverse order by :meth:`close` (or ``with``)."""

    def __init__(self, cfg: RigConfig, opts: ServiceOptions):
        self.cfg = cfg
        # live, hub_loads is published from the bus thread and the rest from the service
        # thread: one record at a time through the sinks, Foxglove and Zenoh
        self._lock = threading.Lock()
        self._stack = contextlib.ExitStack()
        self.session: zenoh.Session | None = None
        self.telemetry: TelemetryPublisher | None = None
        self.low_rate: _LowRatePublisher | None = None
        self.sinks: list[Callable[[str, dict], None]] = []
        self.counts: dict[str, int] = {}
        self.foxglove = None
        if opts.foxglove:  # first: a taken port is refused before Zenoh opens
            from rsra.daq.runtime.foxglove_out import FoxgloveOutput, parse_address

            host, port = parse_address(opts.foxglove)
            self.foxglove = FoxgloveOutput(cfg.telemetry.prefix, host, port,
                                           opts.foxglove_origins,
                                           announce=opts.foxglove_announce)
        try:
            if opts.zenoh:  # (ServiceOptions.zenoh False: no session at all — export, tests)
                self._open_zenoh(cfg, opts)
        except BaseException:  # what was opened before the failure is closed
            self.close()
            raise

    def _open_zenoh(self, cfg: RigConfig, opts: ServiceOptions) -> None:
        import zenoh

        from rsra.config.rig import ConfigError
        from rsra.config.rigfile import zenoh_endpoint_problem
        from rsra.daq.runtime.telemetry import TelemetryPublisher, zenoh_config

        for opt, eps in (("--zenoh-listen", opts.zenoh_listen),
                         ("--zenoh-connect", opts.zenoh_connect)):
            for ep in eps or ():
                problem = zenoh_endpoint_problem(ep)
                if problem:
                    raise ConfigError(opt, ep, problem, f"e.g. {opt} tcp/127.0.0.1:7447")
        conf = zenoh_config(cfg.telemetry, listen=opts.zenoh_listen or None,
                            connect=opts.zenoh_connect or None,
                            config_file=opts.zenoh_config)
        self.session = session = zenoh.open(conf)
        self._stack.callback(session.close)
        # two processes never publish into one stream: another service's token under this
        # prefix (on the sessions this one reaches) refuses the start (docs/telemetry.md)
        from rsra.daq.runtime.instances import publishing

        prefix = cfg.telemetry.prefix
        others = publishing(session, f"{prefix}/alive/*/*/*/*")
        if others:
            raise ConfigError("telemetry.prefix", prefix,
                              f"another rsra publishes there ({others[0].describe()})",
                              "stop that service, or give this one its own prefix "
                              "(telemetry.prefix in a rig file)")
        # state/config tells the endpoints the session really uses (options, config file)
        effective = cfg.effective()
        tel = effective.setdefault("telemetry", {})
        for k in ("listen", "connect"):
            tel[k] = json.loads(conf.get_json(f"{k}/endpoints"))
        self.telemetry = telemetry = TelemetryPublisher(session, cfg.telemetry.prefix, effective)
        self._stack.callback(telemetry.close)
        self.low_rate = _LowRatePublisher(telemetry.publish)
        self._stack.callback(self.low_rate.close)

    def publish(self, key: str, payload: dict | AnglesRecord | Health) -> None:
        if not isinstance(payload, dict):  # a typed record: its JSON object (daq.records, daq.bus.health)
            payload = payload.to_dict()
        with self._lock:
            self.counts[key] = self.counts.get(key, 0) + 1
            for sink in self.sinks:
                sink(key, payload)
            if self.foxglove is not None:
                self.foxglove.publish(key, payload)
            if self.telemetry is None:
                return
            if key in ("angles", "health") and self.low_rate is not None:  # (opened with it)
                self.low_rate.put(key, payload)
            else:
                self.telemetry.publish(key, payload)

    def close(self) -> None:
        self._stack.close()
        self.telemetry = self.session = None
        if self.foxglove is not None:
            self.foxglove.close()
            self.foxglove = None

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def gil_switch_interval(seconds: float):
    """The interpreter's thread switch interval (``sys.setswitchinterval``) while the service
    runs in real time, the one before restored after.

    A thread that wants the interpreter waits until the one holding it reaches the interval
    (CPython's default: 5 ms) — a period at 200 samples/s. In real time the bus thread and
    the simulator's answer then waited behind the low-rate publisher encoding an angles
    record, or the worker queue's feeder pickling a window: with a busy core the late periods were at the
    samples where a result comes into force and at a window's cut (docs/performance.md "The
    interpreter's switch interval"). At ``LIVE_SWITCH_INTERVAL_S`` such a wait is a tenth of
    a period."""
    import sys

    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def realtime_priority(priority: int) -> Callable[[], None]:
    """SCHED_FIFO at ``priority`` for the calling thread, inherited by every thread it starts
    from then on (Linux); returns the call that restores the thread's previous policy. Not
    permitted (no root, CAP_SYS_NICE or RLIMIT_RTPRIO), or not on this system: a ConfigError
    naming the option, before anything starts."""
    from rsra.config.rig import ConfigError

    fix = ("run as root, grant the interpreter CAP_SYS_NICE (setcap cap_sys_nice+ep) or an "
           f"RLIMIT_RTPRIO of at least {priority} (ulimit -r), or leave --realtime-priority out")
    if not hasattr(os, "sched_setscheduler"):
        raise ConfigError("--realtime-priority", priority,
                          "this system has no SCHED_FIFO (Linux only)", "leave it out")
    lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not lo <= priority <= hi:
        raise ConfigError("--realtime-priority", priority, "not a SCHED_FIFO priority",
                          f"give {lo}..{hi} (10 is plenty: above every normal process)")
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as e:
        raise ConfigError("--realtime-priority", priority,
                          f"this process may not use SCHED_FIFO ({e.strerror or e})", fix) from None

    def restore() -> None:
        os.sched_setscheduler(0, old[0], old[1])
    return restore


def normal_scheduling() -> None:
    """The identification worker's first call under --realtime-priority: back to the default
    scheduler (its runs take a core for up to a second; they are not real-time work)."""
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _say_hub_path(pipeline: EstimatorPipeline) -> None:
    """The compiled hub path (daq/runtime/hubpath.py) or why not (health too): said once
    everything has started (a start that fails stays one line)."""
    if pipeline.hub_kernel is not None:
        log.info("hub path: %s", pipeline.hub_kernel_status)
    else:
        log.warning("hub path: the compiled kernel is %s; the pure-Python path runs "
                    "(the same records, more CPU per sample)", pipeline.hub_kernel_status)


def _close_logged(stack: contextlib.ExitStack, close: Callable[[], None]) -> None:
    """Close ``close`` when ``stack`` unwinds; a failure is logged and the rest still close."""
    def run() -> None:
        try:
            close()
        except Exception as e:  # keep closing the rest
            log.error("shutdown: %s", e)
    stack.callback(run)


def _observed(items: Iterator, observers: list[Callable[[Any], None]]) -> Iterator:
    """``items`` with each assembled sample shown to ``observers`` first."""
    if not observers:
        return items
    from rsra.daq.bus.assembler import Sample

    def tap() -> Iterator:
        for item in items:
            if isinstance(item, Sample):
                for observe in observers:
                    observe(item)
            yield item

    return tap()


def jsonl_sink(path: str | Path):
    """A sink writing `{"key": …, …payload}` lines (strict JSON), and its closer (which makes
    the file: the one writer, daq.runtime.persistence.OutputFile)."""
    from rsra.daq.runtime.persistence import OutputFile

    out = OutputFile(path)
    f = out.open()

    def sink(key: str, payload: dict) -> None:
        f.write(dumps({"key": key, **payload}) + "\n")

    def close() -> None:
        try:
            out.commit()
        finally:
            out.discard()

    return sink, close


class Service:
    """Builds the sources, the pipeline, the worker and the outputs; `run()` until done.

    The wiring only: the start is planned (daq.runtime.start), the items go through the
    sample loop (daq.runtime.sample_loop), the identification worker is supervised
    (daq.runtime.supervision), health and summary are composed by daq.runtime.run_report."""

    def __init__(self, cfg: RigConfig, opts: ServiceOptions):
        # the kind of source (bus, simulator in real time or lock-step, replay): chosen once
        # here from the options, asked what it is afterwards (daq.sources)
        self.source: Source = make_source(cfg, opts)
        if not self.source.saves_posterior and cfg.identification.state_file:
            # a replay (recomputed or not) saves no posterior: identification.state_file is the
            # live service's output, never one the user named for a replay (docs/cli.md §6)
            import dataclasses

            cfg = dataclasses.replace(cfg, identification=dataclasses.replace(
                cfg.identification, state_file=""))
        self.cfg = cfg
        self.opts = opts
        self.stop_event = threading.Event()
        self.fs = cfg.sample_rate_hz
        self.dt = 1.0 / self.fs
        self.summary: dict[str, Any] = {}
        self._extra_sinks: list[Callable[[str, dict], None]] = []
        self._sample_observers: list[Callable[[Any], None]] = []
        self.warnings: list[str] = []  # start-up problems the service went on with
        self.schedule: dict | None = None  # replay: where the angles come from
        self.worker_initializer: Callable[[], None] | None = None  # first in the worker (tests)
        # what run() builds, in this order (None before it has)
        self.pipeline: EstimatorPipeline | None = None
        self.supervision: Supervision | None = None
        self.outputs: Outputs | None = None
        self.loop: SampleLoop | None = None
        self._health: HealthReporter | None = None
        # --duration in samples of acquisition time
        self._n_max = None if opts.duration is None else max(1, round(opts.duration * self.fs))

    @property
    def reader(self):
        """The source's reader (its health, its recorder), once the source is open."""
        return self.source.reader

    @property
    def sim(self):
        """The in-process simulator, if the source has one."""
        return self.source.sim

    @property
    def recorder(self):
        return self.source.recorder

    @property
    def worker(self):
        """The supervised identification worker (daq.runtime.ident_worker), if it runs."""
        return self.supervision.worker if self.supervision is not None else None

    # the loop's counts (0/None/empty before the run has started its loop)
    @property
    def samples(self) -> int:
        return self.loop.samples if self.loop is not None else 0

    @property
    def lost(self) -> int:
        return self.loop.lost if self.loop is not None else 0

    @property
    def last_seq(self) -> int | None:
        return self.loop.last_seq if self.loop is not None else None

    @property
    def angles_log(self) -> deque[AnglesRecord]:
        """The latest angles records applied (bounded)."""
        return self.loop.angles.log if self.loop is not None else deque()

    @property
    def last_health(self) -> Health | None:
        return self._health.last if self._health is not None else None

    def add_sink(self, sink: Callable[[str, dict], None]) -> None:
        self._extra_sinks.append(sink)

    def add_sample_observer(self, observe: Callable[[Any], None]) -> None:
        """``observe(sample)`` for every assembled sample the source gives, in order, before
        the pipeline takes it (a campaign task derives a second product from the same replay
        instead of reading the recording twice)."""
        self._sample_observers.append(observe)

    def stop(self, *_: Any) -> None:
        self.stop_event.set()
        if self.supervision is not None:
            self.supervision.stop()

    def install_signal_handlers(self) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self.stop)
            signal.signal(signal.SIGTERM, self.stop)

    # -- the run -----------------------------------------------------------------------------
    def run(self) -> dict:
        opts, cfg = self.opts, self.cfg
        with contextlib.ExitStack() as stack:
            if opts.realtime_priority is not None:
                self._raise_priority(stack, opts.realtime_priority)
            plan = plan_start(cfg, opts, self.source)
            self.schedule = plan.schedule
            self.warnings.extend(plan.warnings)
            self.pipeline = pipeline = plan.pipeline()
            self.supervision = supervision = Supervision(pipeline)
            self.outputs = outputs = Outputs(cfg, opts)
            _close_logged(stack, outputs.close)
            outputs.sinks.extend(self._extra_sinks)
            loop = SampleLoop(pipeline, outputs, supervision, self.source, self.stop_event,
                              self.dt, self._n_max)
            self._health = loop.on_health = HealthReporter(loop, self.warnings)
            self.loop = loop
            # (after loop.finish, which records the last windows' results there)
            _close_logged(stack, self._close_recorded_angles)
            _close_logged(stack, loop.finish)
            if loop.live:
                stack.enter_context(gil_switch_interval(LIVE_SWITCH_INTERVAL_S))
            if plan.use_ident:
                self._start_worker(supervision, plan, loop.live)
            if loop.live:  # hub_loads from the bus thread (no hand-off on the latency path)
                self.source.first_step = loop.first_step
            stack.enter_context(self.source)
            if self.source.reader is not None and hasattr(self.source.reader,
                                                          "keep_angles_open"):
                self.source.reader.keep_angles_open = True
            if self.recorder is not None:
                self._record_start(plan, outputs, stack)
            log.info("service started: %s", self.source.describe())
            _say_hub_path(pipeline)
            loop.run(_observed(self.source.items(self.stop_event), self._sample_observers))
        self.summary = run_summary(loop, self.reader, self.warnings, self.schedule, cfg)
        return self.summary

    def _raise_priority(self, stack: contextlib.ExitStack, priority: int) -> None:
        """First: every thread started after (Zenoh's, the bus thread, the SYNC producer, the
        simulator's) inherits it; the worker process drops it, and multiprocessing's
        resource tracker (a helper process) starts before it."""
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
        stack.callback(realtime_priority(priority))
        if self.worker_initializer is None:
            self.worker_initializer = normal_scheduling

    def _start_worker(self, supervision: Supervision, plan: StartPlan, live: bool) -> None:
        """The identification worker; live, it yields the cores to the real-time threads."""
        init = self.worker_initializer
        if live:
            init = chained(init, background_scheduling)
        supervision.start(self.cfg, plan.state, initializer=init)

    def _record_start(self, plan: StartPlan, outputs: Outputs,
                      stack: contextlib.ExitStack) -> None:
        """The recording's starting angles, and the operator marks (rsra mark) into its
        marks.jsonl when Zenoh runs."""
        assert self.recorder is not None  # (called with a recording)
        self.recorder.write_angles(plan.initial_record().to_dict())
        if outputs.session is not None:
            from rsra.daq.runtime.marks import MarkRecorder

            marks = MarkRecorder(outputs.session, self.cfg.telemetry.prefix,
                                 self.recorder.folder)
            outputs.sinks.append(marks.observe)
            _close_logged(stack, marks.close)

    def _close_recorded_angles(self) -> None:
        if self.recorder is not None:
            self.recorder.close_angles()
