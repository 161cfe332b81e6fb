"""The periodic identification in its own process (a Python thread would hold the GIL for
milliseconds and stall the estimator thread past its per-sample deadline;
docs/performance.md).

The worker owns the sequential posterior and the filter-error state, which continue from
window to window; the estimator thread sends windows and receives `angles` records. Queues
are bounded: a window that finds the worker still busy with two others is dropped and
counted (it would be stale by the time it ran).

The worker is supervised (:class:`SupervisedIdentification`, docs/reliability.md): a worker
that dies is seen within a fraction of a second, reported in `health` and the log, and
restarted from the last accepted posterior — at most `MAX_RESTARTS` times in
`RESTART_WINDOW_S` of acquisition time, after which identification is off for the rest of the
run. The worker ignores SIGINT (a Ctrl-C reaches the whole process group; the parent shuts
it down) and exits when its parent dies.
"""
from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import multiprocessing.queues
import os
import queue
import signal
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any
from dataclasses import replace

import numpy as np

from rsra.daq.jsonout import sanitise
from rsra.daq.runtime.records import ABSENT, AnglesRecord, IdentError, IdentJob, IdentResult

log = logging.getLogger("rsra.identification")

JOB_QUEUE = 2
RESULT_QUEUE = 16
MAX_RESTARTS = 3  # restarts of a dead worker allowed within RESTART_WINDOW_S ...
RESTART_WINDOW_S = 60.0  # ... of acquisition time; one more death and identification is off
WORKER_NICE = 19  # a live worker's nice value where SCHED_IDLE is refused (background_scheduling)
CHECK_INTERVAL_S = 0.2  # real time: how often the worker's liveness is checked (wall clock)


class IdentRuns(dict):
    """The periodic identifications by mode (``runs["known_loads"]``, ...) and the service's
    own companions of them, declared here rather than set on the estimator's objects."""

    #: the next load conditions to apply (known-load records: ``next_conditions``); None: none
    next_conditions: Any = None
    #: what would determine the rest (filter-error records: ``advice``); None: none
    advice: Any = None
    #: the structure fit last saved with the posterior (a change is saved at once)
    saved_structure_fit: Any = None

    @classmethod
    def of(cls, runs: Mapping[str, Any]) -> "IdentRuns":
        """``runs`` itself when it is one, else a copy of the mapping without companions."""
        return runs if isinstance(runs, IdentRuns) else cls(runs)


def build_identification(cfg, initial_state=None):
    """The two periodic identifications (known loads, filter error) over one posterior:
    (posterior, :class:`IdentRuns`, the filter-error design cache)."""
    from rsra.daq.rigmodel import design_cache
    from rsra.estimator.posterior import PeriodicIdentification, SequentialPosterior, rig_fingerprint

    model = cfg.rig_model()
    idc = cfg.identification
    angle_names = model.geometry.angle_names
    names = angle_names if idc.parameters == "angles" else tuple(idc.parameters)
    # the file names its own rig beside the fingerprint (the name is not compared: a rig
    # that extends another with the same cells reads its posteriors)
    post = SequentialPosterior.from_config(idc, names, angle_names,
                                           rig={**rig_fingerprint(model.geometry),
                                                "name": str(cfg.rig_name)})
    if initial_state is not None:
        post.restore(initial_state)
    if post.structure_fit is None:  # the structure in force from the start (configured)
        post.structure_fit = idc.structure_fit
    fs = cfg.sample_rate_hz
    common = dict(model=model, posterior=post, fs=fs, moment_floor=idc.moment_floor_Nm,
                  max_iterations=idc.max_iterations,
                  apply_delay_samples=int(round(idc.apply_delay_s * fs)),
                  settle_time_constants=idc.settle_time_constants,
                  gap_samples=int(round(idc.gap_s * fs)),
                  correlation_time_s=cfg.filter.time_constant_s,
                  alpha_base=idc.initial_angles_rad)
    f = cfg.filter
    cache = design_cache(cfg, model=model, low_frequency=False)  # the filter-error model's
    from rsra.estimator.content import ContentFilter

    w0, harm = cfg.rotor.omega_nominal_rad_s, tuple(f.harmonics)

    def settle(kind: str) -> int:
        # the content filter starts from its first sample held constant: that sample's noise
        # rings in the output for a while, so those samples are not scored (after the start)
        return ContentFilter(kind, fs, w0, harm, 1).settle_samples

    sens = np.asarray(idc.angle_load_sensitivity_rad_per_unit, float)
    known = PeriodicIdentification(mode="known_loads", content=idc.content_known_loads,
                                   content_settle_samples=settle(idc.content_known_loads),
                                   angle_load_sensitivity=sens,  # the load spread
                                   angle_drift_rate=idc.angle_drift_rate_rad_per_s,
                                   nonlinearity_limit=(idc.nonlinearity_limit if idc.nonlinearity_check
                                                       else math.inf), **common)
    design = cache.design_for(w0)
    from rsra.daq.runtime.next_conditions import NextConditions

    ferr = PeriodicIdentification(mode="filter_error", content=idc.content_filter_error,
                                  design=design,
                                  content_sos=ContentFilter(idc.content_filter_error, fs, w0,
                                                            harm, 1).sos,
                                  content_settle_samples=settle(idc.content_filter_error),
                                  angle_load_sensitivity=sens,
                                  scattered_fraction=idc.filter_error_scattered_fraction,
                                  **common)
    from rsra.daq.runtime.flight_advice import FlightAdvice

    runs = IdentRuns({"known_loads": known, "filter_error": ferr})
    runs.next_conditions = NextConditions(cfg)
    runs.advice = FlightAdvice(cfg)
    runs.saved_structure_fit = post.structure_fit
    return post, runs, cache


class _KnownLoadJob:
    """A known-load window's job: the balance must be present in every sample used, and the
    record adds the next load conditions to apply."""

    @staticmethod
    def inputs(job: Mapping[str, Any], ident: Any, cache: Any
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(valid samples, known hub loads H, the rotor's turn per sample: none here)."""
        return job["ok"] & job["known"], job["known_H"], None

    @staticmethod
    def extras(out: dict, rec: Any, runs: IdentRuns, ident: Any, job: Mapping[str, Any],
               valid: np.ndarray, cfg: Any) -> None:
        nc = runs.next_conditions
        if nc is not None:
            if rec.reason == "reset":
                nc.tracker = type(nc.tracker)(nc.model, cfg.identification.prior_sigma_rad,
                                              moment_floor=cfg.identification.moment_floor_Nm)
            elif rec.reason in (None, "not_identifiable"):  # the data the posterior holds
                nc.add_window(ident.alpha(), job["T"][valid], int(np.count_nonzero(valid)))
            out["next_conditions"] = nc.recommend(rec.names, ident.alpha(), rec.P)
        out["advice"] = None


class _FilterErrorJob:
    """A filter-error window's job: the calibration filter redesigned for the window's Ω (or,
    in azimuth mode, its gain held while the harmonics turn with the measured azimuth), and
    the record adds what would determine the rest (``advice``)."""

    @staticmethod
    def inputs(job: Mapping[str, Any], ident: Any, cache: Any
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        dpsi = job.get("dpsi")
        omega = float(np.median(job["omega"]))
        from rsra.estimator.filters import AZIMUTH_GAIN_BAND

        held = (dpsi is not None and ident.design is not None and not ident.design.rotor_stopped
                and not cache.is_stopped(omega)
                and abs(omega / ident.design.omega - 1.0) <= AZIMUTH_GAIN_BAND)
        # azimuth mode: the harmonics turn with the measured azimuth, the gain is held
        design = ident.design if held else cache.design_for(omega)
        if design is not ident.design:
            ident.design = design  # an Ω redesign is not a discontinuity (the state carries over)
        return job["ok"] & True, None, dpsi

    @staticmethod
    def extras(out: dict, rec: Any, runs: IdentRuns, ident: Any, job: Mapping[str, Any],
               valid: np.ndarray, cfg: Any) -> None:
        adv = runs.advice
        out["advice"] = adv.for_window(ident) if adv is not None else None


# what each identification mode's job takes and adds (the job's mode picks it)
JOBS: dict[str, Any] = {"known_loads": _KnownLoadJob, "filter_error": _FilterErrorJob}


def run_job(cfg, runs: dict, cache, job: dict) -> dict:
    """One window (``IdentJob.as_mapping()``) → the `angles` record's JSON object
    (docs/telemetry.md §2.4) with the job id attached (the numerics; :func:`handle_job` types it)."""
    runs = IdentRuns.of(runs)
    mode = job["mode"]
    ident, kind = runs[mode], JOBS[mode]
    seq = job["seq"]
    valid, H, dpsi = kind.inputs(job, ident, cache)
    # a window that skips samples (lost, or the start) is a discontinuity for the filter
    gaps = np.diff(seq) > 1
    if gaps.any() and (np.diff(seq).max() - 1) > ident.gap_samples:
        ident.mark_discontinuity()
    # the pipeline buffers z = I − D q: the measured external loads are already taken off
    # (and W carries their noise), so their columns of the stacked data are zero here
    n_ext = ident.par.model.external.wrenches.shape[1]
    q = np.zeros((len(job["T"]), n_ext)) if n_ext else None
    static_load = None
    if job.get("T_mean") is not None:
        from rsra.estimator.balance import static_estimate

        static_load = static_estimate(ident.par.model, np.asarray(job["alpha"], float),
                                      np.asarray(job["T_mean"], float)[None, :],
                                      np.asarray(job["z_mean"], float)[None, :])[0]
    rec = ident.run_window(job["z"], job["T"], H, q, seq0=int(seq[0]), valid=valid,
                           t=float(job["t"][-1]), dpsi=dpsi, static_load=static_load)
    # when the other mode runs next, its state must restart after new angles
    if rec.accepted:
        for other in runs.values():
            if other is not ident:
                other.mark_discontinuity()
    out = sanitise(rec.to_dict())  # strict JSON values, as they cross the process boundary
    from rsra.daq.runtime.reasons import explain, input_labels, missing_inputs

    # the figures behind the decision and the likely cause, in words (never the decision)
    labels = input_labels(cfg)
    out["explanation"], out["hint"] = explain(rec, {**job, "mode": mode}, cfg.identification,
                                              labels)
    # the samples the likelihood used and the inputs the others lacked
    out["missing_inputs"] = [{"input": lab, "fraction": f}
                             for lab, f in missing_inputs({**job, "mode": mode}, labels)]
    out["applies_from_seq"] = int(job["applies_from_seq"])
    out["late"] = False
    out["restarted"] = False
    out["job_id"] = job["job_id"]
    out["condition"] = rec.condition
    kind.extras(out, rec, runs, ident, job, valid, cfg)
    ident.last_window = None  # its problem (azimuth mode: Φ per sample, ~18 MB) is not kept
    return out


def save_state(post, rec: AnglesRecord, state_file: str) -> str | None:
    """Save the posterior after an accepted run; the error text if that failed (the result
    stands: it is applied and published, and the next accepted run saves again)."""
    try:
        from rsra.daq.runtime.persistence import save_posterior

        st = post.state()
        st.applies_from_seq = rec.applies_from_seq
        save_posterior(state_file, st)
        return None
    except Exception as e:  # a full disk, a read-only directory, ...
        what = e.strerror if isinstance(e, OSError) and e.strerror else f"{type(e).__name__}: {e}"
        return f"{state_file}: {what}"


def handle_job(cfg, post, runs: dict, cache, job: IdentJob,
               state_file: str | None) -> IdentResult | IdentError:
    """One job → its `angles` record (or an error); a failed save is attached as
    ``save_error`` (None when the save worked), never in place of the result."""
    try:
        out = run_job(cfg, runs, cache, job.as_mapping())
    except Exception as e:
        return IdentError(f"{type(e).__name__}: {e}", job.job_id,
                          traceback.format_exc(limit=5))
    job_id = out.pop("job_id", job.job_id)
    res = IdentResult(job_id, AnglesRecord.from_dict(out))
    # saved after an accepted run, and when the structure the hub loads use changes
    fit = res.record.structure_fit
    runs = IdentRuns.of(runs)
    changed = fit is not ABSENT and fit != runs.saved_structure_fit
    if (res.record.accepted or changed) and state_file:
        res = replace(res, save_error=save_state(post, res.record, state_file))
        runs.saved_structure_fit = None if fit is ABSENT else fit
    return res


def _exit_with_parent() -> None:
    """A worker never outlives its parent (kill -9 of the service included): a thread waits on
    the parent's sentinel (a pipe the parent holds open; readable when it is gone) and exits
    the process."""
    parent = mp.parent_process()
    if parent is None:
        return

    def watch() -> None:
        from multiprocessing.connection import wait

        wait([parent.sentinel])
        os._exit(0)

    threading.Thread(target=watch, name="rsra-parent-watch", daemon=True).start()


def background_scheduling() -> None:
    """A live service's worker runs only on CPU time its real-time threads leave
    (``SCHED_IDLE``: any other thread that wakes takes the core from it at once).

    Its runs take a core for up to a second every window. At the default policy, on a 2-core
    machine, the bus thread, the SYNC producer, the simulator, Zenoh's threads and a
    subscriber waited for it up to a time slice at every window's start: nearly every missed
    per-sample deadline was in the first 10 samples of a window (docs/performance.md "The worker
    yields the cores"). A worker that cannot keep up drops windows (``dropped``, logged),
    never a sample. Where SCHED_IDLE is refused, nice ``WORKER_NICE``; where that is refused
    too, nothing changes. Lock-step and replay runs keep the default: they wait for it."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, WORKER_NICE)


def chained(*initializers: Callable[[], None] | None) -> Callable[[], None]:
    """One worker initializer calling each given one in order (picklable for spawn)."""
    import functools

    return functools.partial(_call_each, tuple(f for f in initializers if f is not None))


def _call_each(fns: tuple[Callable[[], None], ...]) -> None:
    for f in fns:
        f()


def _worker_main(cfg, initial_state, jobs: mp.Queue, results: mp.Queue,
                 restarted: bool = False, initializer=None) -> None:
    # Ctrl-C goes to the whole process group: the parent stops the run and then this worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked by the parent
    _exit_with_parent()
    if initializer is not None:
        initializer()
    try:
        post, runs, cache = build_identification(cfg, initial_state)
    except Exception as e:  # report and stop: the service goes on without identification
        results.put(IdentError(f"identification worker failed to start: {e}", fatal=True))
        return
    state_file = cfg.identification.state_file
    while True:
        job = jobs.get()
        if job is None:
            break
        rec = handle_job(cfg, post, runs, cache, job, state_file)
        if restarted and isinstance(rec, IdentResult):  # the first record after a restart
            rec = replace(rec, record=replace(rec.record, restarted=True))  # says so
            restarted = False
        results.put(rec)


class _JobQueue(multiprocessing.queues.Queue):
    """The job queue; when a dead worker's pipe is closed under the feeder thread, the broken
    pipe is logged, not printed as a traceback."""

    @staticmethod
    def _on_queue_feeder_error(e, obj):
        log.debug("identification job not delivered (worker gone): %s", e)


class IdentificationWorker:
    """Owns the worker process and its two bounded queues."""

    def __init__(self, cfg, initial_state=None, *, restarted: bool = False, initializer=None):
        ctx = mp.get_context("spawn")
        self.jobs = _JobQueue(maxsize=JOB_QUEUE, ctx=ctx)
        self.results = ctx.Queue(maxsize=RESULT_QUEUE)
        self.proc = ctx.Process(target=_worker_main, args=(cfg, initial_state, self.jobs,
                                                           self.results, restarted, initializer),
                                name="rsra-identification", daemon=True)
        # SIGINT blocked while the worker is spawned: it inherits the mask, so a Ctrl-C during
        # its start-up (imports) raises nothing there; the worker then ignores SIGINT. Here
        # a Ctrl-C meanwhile stays pending and is delivered when unblocked, not lost.
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self.proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        self.submitted = 0
        self.dropped = 0

    def submit(self, job: IdentJob) -> bool:
        try:
            self.jobs.put_nowait(job)
            self.submitted += 1
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def poll(self) -> list[IdentResult | IdentError]:
        out = []
        while True:
            try:
                out.append(self.results.get_nowait())
            except queue.Empty:
                return out

    def wait(self, timeout: float = 60.0) -> IdentResult | IdentError | None:
        """Block for the next result (lock-step). None when the worker has died."""
        while True:
            try:
                return self.results.get(timeout=min(timeout, 1.0))
            except queue.Empty:
                timeout -= 1.0
                if not self.proc.is_alive() or timeout <= 0:
                    return None

    def alive(self) -> bool:
        return self.proc.is_alive()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the worker: finish the job in hand, then exit; terminate if it hangs. The
        queues never block interpreter exit (a job still in a pipe is abandoned)."""
        for q in (self.jobs, self.results):
            q.cancel_join_thread()
        if self.proc.is_alive():
            try:
                self.jobs.put(None, timeout=1.0)
            except Exception:
                pass
            self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2.0)
        for q in (self.jobs, self.results):
            q.close()

    def abandon(self) -> None:
        """After the worker died: let go of its queues without reading them (a message cut by
        the kill could block a read) and reap the process. Our own copy of the job pipe's
        reading end is closed, so a feeder thread blocked writing to the dead worker gets a
        broken pipe and ends instead of blocking for ever."""
        for q in (self.jobs, self.results):
            q.cancel_join_thread()
        try:
            self.jobs._reader.close()  # type: ignore[attr-defined]  # multiprocessing's own pipe end (private: not in typeshed)
        except (AttributeError, OSError):
            pass
        for q in (self.jobs, self.results):
            q.close()
        self.proc.join(1.0)


class SupervisedIdentification:
    """The identification worker under supervision (docs/reliability.md).

    * A dead worker (killed, crashed) is seen at the next :meth:`check` — every sample in
      lock-step and replay, every ``CHECK_INTERVAL_S`` of wall clock live — reported in the log
      and in :meth:`health` as dead, and restarted from the last accepted posterior (the
      starting one before any): held windows and filter-error state start afresh, the jobs
      in its hands are lost (``on_restart`` is told, to forget them; it is told too when
      identification goes off), and the new worker's
      first record carries ``restarted: true``.
    * At most ``MAX_RESTARTS`` restarts within ``RESTART_WINDOW_S`` of acquisition time; one
      death more, or a worker that cannot start, and identification is off (``off``).
    * A save of the posterior that failed is reported (``save_error``, logged) and the result
      stands; the next accepted run saves again.
    """

    def __init__(self, cfg, initial_state=None, *, on_restart=None, initializer=None,
                 check_interval_s: float = CHECK_INTERVAL_S):
        self.cfg = cfg
        self.fs = cfg.sample_rate_hz
        self.state = initial_state  # the last accepted posterior: where a restart starts
        self.on_restart = on_restart
        self.initializer = initializer
        self.check_interval_s = float(check_interval_s)
        self.submitted = 0
        self.dropped = 0
        self.deaths = 0
        self.restarts = 0
        self.last_death: str | None = None
        self.off_reason: str | None = None
        self.save_error: str | None = None
        self.save_failures = 0
        self._restart_seqs: deque[int] = deque(maxlen=MAX_RESTARTS)
        self._next_check = 0.0
        self.generation = 0  # workers started after the first
        # the service is stopping (Ctrl-C, SIGTERM — which a service manager sends to the
        # whole group, the worker included): a worker found dead now is not restarted
        self.stopping = False
        self.worker: IdentificationWorker | None = IdentificationWorker(
            cfg, initial_state, initializer=initializer)

    @property
    def off(self) -> bool:
        return self.worker is None

    @property
    def proc(self):
        """The current worker process (None when identification is off)."""
        return None if self.worker is None else self.worker.proc

    # -- supervision ------------------------------------------------------------------------
    def check(self, seq: int | None, *, every_call: bool = False) -> bool:
        """Is the worker alive (after a restart if it had died)? False when identification is
        off. Live it looks at most every ``check_interval_s``; ``every_call`` (lock-step) at
        every call, so that a run is deterministic."""
        if self.worker is None:
            return False
        if not every_call:
            now = time.monotonic()
            if now < self._next_check:
                return True
            self._next_check = now + self.check_interval_s
        if self.worker.alive():
            return True
        if self.stopping:
            return False
        self._died(seq)
        return self.worker is not None

    def _died(self, seq: int | None) -> None:
        worker = self.worker
        assert worker is not None  # check() found it dead
        code = worker.proc.exitcode
        how = (f"killed by {signal.Signals(-code).name}" if code is not None and code < 0
               and -code in signal.valid_signals() else f"exit code {code}")
        seq = 0 if seq is None else int(seq)
        if code == 0:  # exited by itself: it could not start (its last words say why)
            msgs = [r.error for r in worker.poll()
                    if isinstance(r, IdentError) and r.fatal]
            worker.abandon()
            self.worker = None
            self._turn_off(msgs[0] if msgs else "the identification worker exited")
            return
        self.deaths += 1
        self.last_death = f"died at sample {seq} ({how})"
        worker.abandon()
        self.worker = None
        window = int(round(RESTART_WINDOW_S * self.fs))
        if len(self._restart_seqs) == MAX_RESTARTS and seq - self._restart_seqs[0] < window:
            self._turn_off(f"the identification worker died {MAX_RESTARTS + 1} times within "
                           f"{RESTART_WINDOW_S:g} s (last: {how})")
            return
        self._restart_seqs.append(seq)
        self.restarts += 1
        log.error("identification worker %s; restarted from the last accepted posterior "
                  "(restart %d; at most %d in %g s)", self.last_death, self.restarts,
                  MAX_RESTARTS, RESTART_WINDOW_S)
        self.generation += 1
        self.worker = IdentificationWorker(self.cfg, self.state, restarted=True,
                                           initializer=self.initializer)
        if self.on_restart is not None:
            self.on_restart()  # the jobs the dead one held are lost

    def _turn_off(self, reason: str) -> None:
        self.off_reason = reason
        if self.worker is not None:
            self.worker.close()
            self.worker = None
        log.error("%s: identification is off for the rest of the run (the estimate goes on "
                  "with the angles in force)", reason)
        if self.on_restart is not None:
            self.on_restart()  # told too: no job will come back

    # -- jobs and results -------------------------------------------------------------------
    def submit(self, job: IdentJob, seq: int | None = None) -> bool:
        """Live: hand over a window, never waiting; False if not taken (busy, dead or off; a
        window cut before a death was seen is not given to the new worker)."""
        generation = self.generation
        if not self.check(seq, every_call=True) or self.generation != generation:
            return False
        assert self.worker is not None  # check() is True: a worker is running
        if self.worker.submit(job):
            self.submitted += 1
            return True
        self.dropped += 1  # alive, and still busy with two windows
        log.warning("identification busy: window ending at sample %d dropped",
                    int(job.seq[-1]))
        return False

    def put(self, job: IdentJob, seq: int | None = None) -> bool:
        """Lock-step: hand over a window, waiting for room; False if the worker died."""
        generation = self.generation
        while self.check(seq, every_call=True) and self.generation == generation:
            assert self.worker is not None  # check() is True: a worker is running
            try:
                self.worker.jobs.put(job, timeout=0.5)
                self.submitted += 1
                return True
            except queue.Full:
                continue
        return False

    def poll(self, seq: int | None = None) -> list[IdentResult | IdentError]:
        """Live: the results in (after a liveness check)."""
        self.check(seq)
        if self.worker is None:
            return []
        return [r for r in map(self._received, self.worker.poll()) if r is not None]

    def wait(self, seq: int | None = None,
             timeout: float = 120.0) -> IdentResult | IdentError | None:
        """Lock-step: the next result. None when the worker died (restarted or off: the jobs
        it held are lost) or gave none within ``timeout`` (then it is treated as hung: ended
        and restarted)."""
        generation = self.generation
        while self.check(seq, every_call=True) and self.generation == generation:
            assert self.worker is not None  # check() is True: a worker is running
            r = self.worker.wait(timeout=min(timeout, 1.0))
            if r is not None:
                r = self._received(r)
                if r is not None:
                    return r
                continue
            timeout -= 1.0
            if timeout <= 0:
                log.error("identification worker gave no result for %g s: ended", 120.0)
                self.worker.proc.kill()
                self.worker.proc.join(5.0)
        return None

    def _received(self, r: IdentResult | IdentError) -> IdentResult | IdentError | None:
        """Book-keeping on a result: a fatal start error turns identification off; an
        accepted run becomes the restart point; a failed save is reported."""
        if isinstance(r, IdentError):
            if r.fatal:
                self._turn_off(str(r.error))
                return None
            return r
        if r.save_error is not ABSENT:
            err = r.save_error
            if err is not None:
                self.save_failures += 1
                log.error("posterior not saved: %s; the result is applied and the next accepted "
                          "run saves again", err)
            elif self.save_error is not None:
                log.warning("posterior saved again (%s)", self.cfg.identification.state_file)
            self.save_error = err
        rec = r.record
        if rec.accepted:
            from rsra.estimator.posterior import PosteriorState

            self.state = PosteriorState(tuple(rec.names), np.asarray(rec.alpha, float),
                                        np.asarray(rec.P, float), rec.get("applies_from_seq"),
                                        rec.get("t"))
        return r

    def health(self) -> dict:
        """The `health` record's ``identification`` object (docs/telemetry.md §2.5)."""
        return {"worker": "off" if self.worker is None else "running",
                "pid": None if self.worker is None else self.worker.proc.pid,
                "deaths": self.deaths, "restarts": self.restarts, "last_death": self.last_death,
                "off_reason": self.off_reason, "save_error": self.save_error,
                "save_failures": self.save_failures}

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()

    def finish(self, pending: Callable[[], int], timeout: float) -> list[IdentResult | IdentError]:
        """At the end of a run: the results of the jobs still in hand, as they arrive, while
        ``pending()`` says some are outstanding, for at most ``timeout`` s. A job not done by
        then is abandoned with the worker (terminated, so it saves nothing the run did not
        publish); the caller says so."""
        out: list[IdentResult | IdentError] = []
        deadline = time.monotonic() + timeout
        while self.worker is not None and pending() > len(out):
            left = deadline - time.monotonic()
            if left <= 0 or not self.worker.alive():
                break
            r = self.worker.wait(timeout=min(left, 0.5))
            if r is not None and (r := self._received(r)) is not None:
                out.append(r)
        if self.worker is not None and pending() > len(out) and self.worker.alive():
            self.worker.proc.terminate()  # mid-job: nothing saved after what was published
            self.worker.proc.join(5.0)
        return out


