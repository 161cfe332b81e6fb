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
import math
import os
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.jsonout import dumps
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.runtime.records import AnglesRecord, IdentError, IdentResult, InitialAngles
from rsra.daq.runtime.sources import SIM_BLOCK, BusOpenError, Source, make_source  # noqa: F401 (re-exported)

if TYPE_CHECKING:
    from rsra.daq.bus.health import Health

log = logging.getLogger("rsra.service")

LOW_RATE_QUEUE = 64
LATENCY_HISTORY = 2000
FINAL_RESULTS_WAIT_S = 10.0  # at the end: the wait for windows still being identified
ANGLES_HISTORY = 16  # recent angles records kept in memory (~15 kB each with P)


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
        self.session = None
        self.telemetry = None
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

        from rsra.config.rig import ConfigError, zenoh_endpoint_problem
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
        self.session = zenoh.open(conf)
        self._stack.callback(self.session.close)
        # state/config tells the endpoints the session really uses (options, config file)
        effective = cfg.effective()
        tel = effective.setdefault("telemetry", {})
        for k in ("listen", "connect"):
            tel[k] = json.loads(conf.get_json(f"{k}/endpoints"))
        self.telemetry = TelemetryPublisher(self.session, cfg.telemetry.prefix, effective)
        self._stack.callback(self.telemetry.close)
        self.low_rate = _LowRatePublisher(self.telemetry.publish)
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
            if key in ("angles", "health"):
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


def _close_logged(stack: contextlib.ExitStack, close: Callable[[], None]) -> None:
    """Close ``close`` when ``stack`` unwinds; a failure is logged and the rest still close."""
    def run() -> None:
        try:
            close()
        except Exception as e:  # keep closing the rest
            log.error("shutdown: %s", e)
    stack.callback(run)


def jsonl_sink(path: str | Path):
    """A sink writing `{"key": …, …payload}` lines (strict JSON), and its closer."""
    f = open(path, "w", encoding="utf-8")

    def sink(key: str, payload: dict) -> None:
        f.write(dumps({"key": key, **payload}) + "\n")

    return sink, f.close


def initial_angles(cfg: RigConfig, state_path: str | None, accept_rig_mismatch: bool = False):
    """(alpha0, posterior state or None, warning or None) from the config or a saved
    posterior (of this rig, within the angles' physical range: daq.posterior_file)."""
    alpha0 = np.asarray(cfg.identification.initial_angles_rad, float).copy()
    if not state_path:
        return alpha0, None, None
    from rsra.daq.runtime.posterior_file import load_checked

    names = cfg.rig_model().geometry.angle_names
    idc = cfg.identification
    wanted = names if idc.parameters == "angles" else tuple(idc.parameters)
    # PosteriorFileError on a corrupt file, another rig's, or angles out of range
    state, warning = load_checked(cfg, state_path, wanted,
                                  accept_rig_mismatch=accept_rig_mismatch)
    for n, v in zip(state.names, state.theta):
        if n in names:
            alpha0[names.index(n)] = v
    return alpha0, state, warning


class _FirstStepDone:
    """A live sample from the bus thread: its first step done there (hub_loads published;
    ``rest`` the second step to take), or — ``rest`` None — the whole sample for the service
    thread (a slow first step); ``error`` a first step that failed."""

    __slots__ = ("sample", "rest", "records", "error")

    def __init__(self, sample, rest, records, error=None):
        self.sample, self.rest, self.records, self.error = sample, rest, records, error

    @property
    def seq(self) -> int:
        return self.sample.seq


class Service:
    """Builds the sources, the pipeline, the worker and the outputs; `run()` until done."""

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
        self.latencies: deque[float] = deque(maxlen=LATENCY_HISTORY)
        self.deadline_misses = 0
        self.worker = None
        self.ident_errors = 0
        self.outputs: Outputs | None = None
        self.summary: dict[str, Any] = {}
        self.last_seq: int | None = None
        self.first_t: float | None = None
        self.last_t: float | None = None
        # the latest angles records (bounded: a record with its P is ~10 kB, one per period
        # for as long as the service runs) and running counts for the summary
        self.angles_log: deque[AnglesRecord] = deque(maxlen=ANGLES_HISTORY)
        self.ident_runs = 0
        self.ident_rejected: dict[str, int] = {}
        self.lost = 0
        self.samples = 0
        self.last_health: Health | None = None  # (daq.bus.health)
        self._extra_sinks: list[Callable[[str, dict], None]] = []
        self.pipeline: EstimatorPipeline | None = None
        self.warnings: list[str] = []  # start-up problems the service went on with
        self.schedule: dict | None = None  # replay: where the angles come from
        self.worker_initializer = None  # called first in the worker process (tests)
        # --duration in samples of acquisition time
        self._n_max = None if opts.duration is None else max(1, round(opts.duration * self.fs))
        self._first_seq: int | None = None  # the first sample processed
        # live: samples the bus thread passed on whole (a slow first step, or after one):
        # counted by the bus thread when queued, by the service thread when done; the bus
        # thread runs first steps again only once none is left (sample order kept)
        self._whole_queued = 0
        self._whole_done = 0
        self._step_error: BaseException | None = None  # a first step failed (bus thread)

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

    def add_sink(self, sink: Callable[[str, dict], None]) -> None:
        self._extra_sinks.append(sink)

    # -- set-up ----------------------------------------------------------------------------
    def _setup_identification(self, alpha0, state) -> None:
        from rsra.daq.runtime.ident_worker import SupervisedIdentification

        self.worker = SupervisedIdentification(self.cfg, state, on_restart=self._worker_lost,
                                               initializer=self.worker_initializer)

    def _worker_lost(self) -> None:
        """The identification worker died: the windows it held are lost (a restart is a
        discontinuity; its first record says so), and when it is off for good the pipeline
        stops cutting windows and flags every sample."""
        p = self.pipeline
        p.outstanding.clear()
        if self.worker is not None and self.worker.off:
            p.identification = False
            p.identification_off = True

    def _initial_record(self, alpha0, state) -> InitialAngles:
        names = self.cfg.rig_model().geometry.angle_names
        if state is not None:
            P = state.P.tolist()
            rec_names = list(state.names)
            theta = state.theta.tolist()
        else:
            s = self.cfg.identification.prior_sigma_rad
            rec_names = list(names)
            theta = alpha0.tolist()
            P = (np.eye(len(names)) * s * s).tolist()
        return InitialAngles(names=rec_names, alpha=theta, P=P, alpha_all=alpha0.tolist(),
                             structure_fit=getattr(self, "start_fit", None))

    def stop(self, *_: Any) -> None:
        self.stop_event.set()
        if self.worker is not None:
            self.worker.stopping = True

    def install_signal_handlers(self) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self.stop)
            signal.signal(signal.SIGTERM, self.stop)

    # -- the run -----------------------------------------------------------------------------
    def run(self) -> dict:
        opts, cfg = self.opts, self.cfg
        with contextlib.ExitStack() as stack:
            if opts.realtime_priority is not None:
                # first: every thread started below (Zenoh's, the bus thread, the SYNC
                # producer, the simulator's) inherits it; the worker process drops it, and
                # multiprocessing's resource tracker (a helper process) starts before it
                from multiprocessing import resource_tracker

                resource_tracker.ensure_running()
                stack.callback(realtime_priority(opts.realtime_priority))
                if self.worker_initializer is None:
                    self.worker_initializer = normal_scheduling
            plan = self.source.angles_plan(opts.identification, opts.recompute)
            self.schedule = plan.schedule
            recorded_initial, recorded, folder = plan.recorded_initial, plan.recorded, plan.folder
            if recorded_initial is not None and not opts.angles:
                alpha0 = np.asarray(recorded_initial.get("alpha_all", recorded_initial["alpha"]),
                                    float)
                n_angles = len(cfg.rig_model().geometry.angle_names)
                if alpha0.shape != (n_angles,):
                    from rsra.daq.bus.replay import ReplayError

                    raise ReplayError(f"{folder / 'angles.jsonl'}: the starting record holds "
                                      f"{alpha0.size} angles, the rig has {n_angles}; fix: "
                                      "replay with --recompute or give the recording's --config")
                state = None
            else:
                alpha0, state, warning = initial_angles(cfg, opts.angles,
                                                        opts.accept_rig_mismatch)
                if warning:
                    log.warning("%s", warning)
                    self.warnings.append(warning)
            use_ident = opts.identification and (self.source.saves_posterior or plan.recompute)
            if use_ident:
                # the worker saves accepted runs there: only over a posterior of ours
                # (ConfigError naming the key otherwise, before acquisition starts)
                from rsra.daq.runtime.posterior_file import prepare_state_file

                for warning in prepare_state_file(
                        cfg, accept_rig_mismatch=opts.accept_rig_mismatch):
                    log.warning("%s", warning)
                    self.warnings.append(warning)
            self.pipeline = EstimatorPipeline(cfg, alpha0, identification=use_ident)
            # the covariance of the starting angles (hub_loads sigma_angles): the recording's
            # starting posterior in a replay, else the saved posterior's or the prior
            start = (recorded_initial if recorded_initial is not None and not opts.angles
                     else self._initial_record(alpha0, state).to_dict())
            self.pipeline.set_angles_covariance(start.get("names"), start.get("P"))
            # the structure the hub loads use from the start (issue 19): the recording's
            # first line in a replay; else the saved posterior's, else the config's
            if recorded_initial is not None and not opts.angles:
                self.start_fit = recorded_initial.get("structure_fit")
            elif state is not None and state.structure is not None:
                self.start_fit = state.structure
            else:
                self.start_fit = cfg.identification.structure_fit
            if self.start_fit is not None:
                self.pipeline.set_structure(self.start_fit)
            for rec in recorded:
                self.pipeline.deliver(rec)
            self.outputs = Outputs(cfg, opts)
            _close_logged(stack, self.outputs.close)
            self.outputs.sinks.extend(self._extra_sinks)
            # (after _close_worker, which records the last windows' results there)
            _close_logged(stack, self._close_recorded_angles)
            _close_logged(stack, self._close_worker)
            if use_ident:
                self._setup_identification(alpha0, state)
            if not self.source.deterministic:  # hub_loads from the bus thread (P5b)
                self.source.first_step = self._first_step
            stack.enter_context(self.source)
            if self.source.reader is not None and hasattr(self.source.reader,
                                                          "keep_angles_open"):
                self.source.reader.keep_angles_open = True
            if self.recorder is not None:
                self.recorder.write_angles(self._initial_record(alpha0, state).to_dict())
            log.info("service started: %s", self.source.describe())
            # the compiled hub path (daq/runtime/hubpath.py) or why not (health too): said once
            # everything has started (a start that fails stays one line)
            if self.pipeline.hub_kernel is not None:
                log.info("hub path: %s", self.pipeline.hub_kernel_status)
            else:
                log.warning("hub path: the compiled kernel is %s; the pure-Python path runs "
                            "(the same records, more CPU per sample)",
                            self.pipeline.hub_kernel_status)
            self._loop(self.source.items(self.stop_event))
        self.summary = self._summary()
        return self.summary

    def _close_recorded_angles(self) -> None:
        if self.recorder is not None:
            self.recorder.close_angles()

    def _close_worker(self) -> None:
        """The windows still being identified when acquisition ended: their results are
        taken in (for at most FINAL_RESULTS_WAIT_S) and published, recorded and counted
        before the outputs close — the worker saves accepted ones to the state file, so
        what the run says last is what the state file holds (issue 29); one not done by then
        is abandoned unsaved, and the log says so. Then the worker stops."""
        p = self.pipeline
        if p is not None and self.last_seq is not None and self.outputs is not None:
            if self.worker is not None:
                for r in self.worker.finish(lambda: len(p.outstanding), FINAL_RESULTS_WAIT_S):
                    self._deliver(r, self.last_seq)
                if p.outstanding:
                    log.warning("%d identification window(s) still running at the end: "
                                "abandoned (not applied, not saved)", len(p.outstanding))
                    p.outstanding.clear()
            # (a replay's recorded records that apply after its last sample, the same way)
            for rec in p.final_records(self.last_seq):
                self.outputs.publish("angles", rec)
                self._on_angles(rec)
        if self.worker is not None:
            self.worker.close()

    # -- per item ------------------------------------------------------------------------------
    def _loop(self, source: Iterator) -> None:
        from rsra.daq.bus.reader import HealthReport

        for item in source:
            if item is None:
                self._poll_results()
            elif isinstance(item, HealthReport):
                self._on_health(item)
            else:
                if self._first_seq is not None and self._past_last(item.seq):
                    break  # (the last wanted sample was dropped from a full queue)
                self._on_sample(item)
                if self._last_wanted(item.seq):
                    break
            if self.stop_event.is_set():
                break
        if self._step_error is not None:
            raise self._step_error

    def _last_wanted(self, seq: int) -> bool:
        """Sample ``seq`` is the last one --duration asks for (it counts samples of
        acquisition time from the first one processed: lost ones included, they keep seq)."""
        if self._first_seq is None:
            self._first_seq = seq
        if self._n_max is None:
            return False
        return seq - self._first_seq + 1 >= self._n_max

    def _poll_results(self) -> None:
        if self.worker is None or self.source.deterministic:
            return
        arrival = self.last_seq if self.last_seq is not None else 0
        for r in self.worker.poll(self.last_seq):  # (and restarts a dead worker)
            self._deliver(r, arrival)

    def _deliver(self, r: IdentResult | IdentError, arrival: int | None) -> None:
        if isinstance(r, IdentError):
            self.ident_errors += 1
            log.error("identification: %s", r.error)
            if r.job_id is not None:
                self.pipeline.outstanding.pop(r.job_id, None)
            return
        self.pipeline.deliver(r.record, arrival_seq=arrival, job_id=r.job_id)

    def _wait_results(self, seq: int) -> None:
        """Lock-step and replay: the result of every window due at this sample first; a dead
        worker is seen at every sample (restarted, or identification off: deterministic)."""
        if self.worker is None:
            return
        self.worker.check(seq, every_call=True)
        while self.pipeline.waiting_for(seq):
            r = self.worker.wait(seq, timeout=120.0)
            if r is None:  # it died: restarted or off, its jobs forgotten (_worker_lost)
                self.pipeline.outstanding.clear()
                return
            self._deliver(r, None)

    def _first_step(self, s):
        """The bus thread, as a sample completes (live): the pipeline's first step and the
        publication of its records (hub_loads, and angles applied from this sample) at once,
        with no hand-off to another thread (docs/performance.md P5b). The service thread
        finishes the sample (:meth:`_on_sample`). Samples after the last one wanted, or
        once stopping, are passed on untouched (the loop ends before them)."""
        if self.stop_event.is_set() or self._past_last(s.seq):
            return s
        p = self.pipeline
        if self._whole_queued != self._whole_done or not p.first_step_is_quick(s):
            # slow work (new angles, a filter design), or such a sample still in the service
            # thread: the whole sample goes there, in order (a full queue drops it: uncounted)
            if not self.source.reader.items.queue.full():
                self._whole_queued += 1
            return _FirstStepDone(s, None, [])  # rest None: the whole sample
        try:
            rest = p.stages(s)
            records = next(rest).records
            self._publish_first(s, records)
        except BaseException as e:  # the run stops; raised again in the service thread
            self._step_error = e
            self.stop_event.set()
            return _FirstStepDone(s, None, [], e)
        return _FirstStepDone(s, rest, records)

    def _past_last(self, seq: int) -> bool:
        if self._first_seq is None:
            self._first_seq = seq
        return self._n_max is not None and seq - self._first_seq + 1 > self._n_max

    def _publish_first(self, s, records: list) -> None:
        publish = self.outputs.publish
        for key, payload in records:
            publish(key, payload)
            if key == "hub_loads":
                lat = time.time() - s.t
                self.latencies.append(lat)
                if lat > self.dt:
                    self.deadline_misses += 1
            elif key == "angles":  # recorded where applied: never lost with a dropped sample
                self._on_angles(payload)

    def _on_sample(self, item) -> None:
        p = self.pipeline
        live = not self.source.deterministic
        counted = False  # a whole sample the bus thread counted (_first_step)
        if isinstance(item, _FirstStepDone):  # live: hub_loads is out (with its angles)
            if item.error is not None:
                raise item.error
            s, stages = item.sample, item.rest
            counted = stages is None
        else:
            s, stages = item, None
        if not live:
            self._wait_results(s.seq)

        if stages is None:
            if live:  # the hub loads are published before the rest of the sample
                stages = p.stages(s)
                self._publish_first(s, next(stages).records)
                out = next(stages)
            else:
                out = p.process(s)
        else:
            out = next(stages)
        publish = self.outputs.publish
        for key, payload in out.records:
            publish(key, payload)
            if key == "angles":
                self._on_angles(payload)
        if out.job is not None and self.worker is not None:
            if self.source.deterministic:
                # deterministic: every window runs (unless the worker died meanwhile)
                if not self.worker.put(out.job, s.seq):
                    p.outstanding.pop(out.job.job_id, None)
            elif not self.worker.submit(out.job, s.seq):  # busy, dead or off: logged
                p.outstanding.pop(out.job.job_id, None)
        self.samples += 1
        self.lost += int(s.lost_before)
        self.last_seq = s.seq
        if self.first_t is None:
            self.first_t = s.t
        self.last_t = s.t
        if live:  # after the sample, off the SYNC → hub_loads path (docs/performance.md P5b):
            self._poll_results()  # a result in now applies from the next sample at the earliest
            if counted:
                self._whole_done += 1  # the bus thread may take first steps again

    def _on_angles(self, rec: AnglesRecord) -> None:
        if self.recorder is not None:  # (a replay records nothing)
            self.recorder.write_angles(rec.to_dict())
        self.angles_log.append(rec)
        self.ident_runs += 1
        if not rec.get("accepted"):
            reason = str(rec.get("reason"))
            self.ident_rejected[reason] = self.ident_rejected.get(reason, 0) + 1
        if rec.get("accepted"):
            sig = rec.get("sigma_cr") or []
            worst = max((x for x in sig if x is not None), default=float("nan"))
            log.info("identification accepted (%s, %s): %d of %d directions determined, "
                     "worst sigma_CR %.3f deg, applies from sample %s%s", rec.get("mode"),
                     rec.get("content"), rec.get("determined", 0), len(rec.get("names") or []),
                     math.degrees(worst), rec.get("applies_from_seq"),
                     " (late)" if rec.get("late") else "")
        else:
            log.info("identification rejected (%s, %s): %s: %s%s", rec.get("mode"),
                     rec.get("content"), rec.get("reason"), rec.get("explanation") or
                     rec.get("detail"), f"; hint: {rec.get('hint')}" if rec.get("hint") else "")

    def _on_health(self, item) -> None:
        """The reader's health record (daq.bus.health) with the service's parts, replaced
        into it; published as it is (serialised once, ``Health.to_dict``)."""
        import dataclasses

        from rsra.daq.bus.health import IdentQueue, Latency, PublisherQueue, frozen_map

        h = item.health
        if self.latencies:
            a = np.fromiter(self.latencies, float) * 1e3
            latency = Latency(p50=float(np.percentile(a, 50)), p99=float(np.percentile(a, 99)),
                              max=float(a.max()), deadline_misses=self.deadline_misses)
        else:
            latency = Latency(p50=None, p99=None)
        queues, more = h.queues, {}
        if self.worker is not None:
            queues = dataclasses.replace(queues, identification=IdentQueue(
                submitted=self.worker.submitted, dropped=self.worker.dropped,
                errors=self.ident_errors))
            more["identification"] = frozen_map(self.worker.health())
        if self.outputs is not None and self.outputs.low_rate is not None:
            queues = dataclasses.replace(queues, publisher=PublisherQueue(
                depth=self.outputs.low_rate.queue.qsize(), dropped=self.outputs.low_rate.dropped))
        if self.outputs is not None and self.outputs.foxglove is not None:
            more["foxglove"] = frozen_map(self.outputs.foxglove.health())
        if self.pipeline is not None:  # readings the estimator refused (bad input, counted)
            p = self.pipeline
            est = {"implausible_omega": p.implausible_omega,
                   "design_errors": p.design_errors,
                   "inertial": p.cfg.angular,
                   "harmonic_phase": p.cfg.rotor.harmonic_phase,
                   "hub_kernel": p.hub_kernel_status,
                   "hub_kernel_samples": 0 if p.hub_kernel is None else p.hub_kernel.samples}
            if p.azimuth_mode:
                est["azimuth_missing"] = p.azimuth_missing
                est["azimuth_refused"] = p.azimuth.refused
            if self.pipeline.stuck is not None:
                est.update(self.pipeline.stuck.health())
            more["estimator"] = frozen_map(est)
        if self.warnings:
            more["warnings"] = tuple(self.warnings)
        h = dataclasses.replace(h, latency_ms=latency, queues=queues, **more)
        prev = self.last_health.recording.error if self.last_health is not None else None
        err = h.recording.error
        if err and err != prev:
            log.error("recording stopped: %s", err)
        self.last_health = h
        self.outputs.publish("health", h)

    def _summary(self) -> dict:
        rej = dict(self.ident_rejected)
        out = {"samples": self.samples, "lost": self.lost,
               "duration_s": None if self.first_t is None else self.last_t - self.first_t,
               "identification_runs": self.ident_runs,
               "accepted": self.ident_runs - sum(rej.values()),
               "rejected": rej, "published": dict(self.outputs.counts) if self.outputs else {},
               "deadline_misses": self.deadline_misses}
        if self.reader is not None:  # the reader's counts, as a replay of the run reports them
            h = self.reader.health()
            out["samples_complete"] = h.samples.complete
            out["samples_incomplete"] = h.samples.incomplete
            if h.sync.gaps:
                out["sync_gaps"] = {"count": h.sync.gaps, "longest_s": h.sync.gap_longest_s}
        if self.warnings:
            out["warnings"] = list(self.warnings)
        if self.pipeline is not None and (self.pipeline.implausible_omega
                                          or self.pipeline.design_errors):
            out["implausible_omega"] = self.pipeline.implausible_omega
            out["design_errors"] = self.pipeline.design_errors
        if self.pipeline is not None and self.pipeline.stuck is not None:
            st = self.pipeline.stuck.health()
            if st["stuck_episodes"]:
                out["stuck"] = {"episodes": st["stuck_episodes"], "samples": st["stuck_samples"]}
        if self.latencies:
            a = np.fromiter(self.latencies, float) * 1e3
            out["latency_ms"] = {"p50": float(np.percentile(a, 50)),
                                 "p99": float(np.percentile(a, 99)), "max": float(a.max())}
        if self.angles_log:
            last = self.angles_log[-1]
            out["angles"] = {"names": last.get("names"), "alpha": last.get("alpha"),
                             "sigma": [math.sqrt(max(last.P[i][i], 0.0))
                                       for i in range(len(last.get("names") or []))]
                             if last.get("P") else None}
        if self.pipeline is not None:
            out["alpha_applied"] = self.pipeline.alpha.tolist()
        if self.schedule is not None:
            out["angles_schedule"] = self._schedule_summary()
        return out

    def _schedule_summary(self) -> dict:
        """Replay: where the angles came from. A recorded schedule is partial when the
        recording runs on for more than a period, the apply delay and a second past its last
        record (a live run publishes one record per period)."""
        sch = dict(self.schedule)
        if sch["source"] != "recorded" or self.last_seq is None:
            return sch
        idc = self.cfg.identification
        last = sch["last_applies_from_seq"]
        sch["last_seq"] = self.last_seq
        if last is not None:
            sch["uncovered_s"] = max(0, self.last_seq - last) / self.fs
            sch["partial"] = self.last_seq - last > (idc.period_s + idc.apply_delay_s
                                                     + 1.0) * self.fs
        return sch
