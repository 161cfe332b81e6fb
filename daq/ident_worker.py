"""The periodic identification in its own process (a Python thread would hold the GIL for
milliseconds and stall the estimator thread; performance.md P5).

The worker owns the sequential posterior and the filter-error state, which continue from
window to window; the estimator thread sends windows and receives `angles` records. Queues
are bounded: a window that finds the worker still busy with two others is dropped and
counted (it would be stale by the time it ran).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import queue
import traceback
from typing import Any

import numpy as np

log = logging.getLogger("rsra.identification")

JOB_QUEUE = 2
RESULT_QUEUE = 16


def build_identification(cfg, initial_state=None):
    """The two periodic identifications (known loads, filter error) over one posterior."""
    from estimator.filters import DesignCache
    from estimator.posterior import PeriodicIdentification, SequentialPosterior

    model = cfg.rig_model()
    idc = cfg.identification
    angle_names = model.geometry.angle_names
    names = angle_names if idc.parameters == "angles" else tuple(idc.parameters)
    post = SequentialPosterior.from_config(idc, names, angle_names)
    if initial_state is not None:
        post.restore(initial_state)
    fs = cfg.sample_rate_hz
    common = dict(model=model, posterior=post, fs=fs, moment_floor=idc.moment_floor_Nm,
                  max_iterations=idc.max_iterations,
                  apply_delay_samples=int(round(idc.apply_delay_s * fs)),
                  settle_time_constants=idc.settle_time_constants,
                  gap_samples=int(round(idc.gap_s * fs)),
                  correlation_time_s=cfg.filter.time_constant_s,
                  alpha_base=idc.initial_angles_rad)
    f = cfg.filter
    cache = DesignCache(
        model, harmonics=tuple(f.harmonics), dt=1.0 / fs, tuning=f.tuning,
        time_constant_s=f.time_constant_s, low_frequency=False, psd=f.process_noise_psd,
        alpha=idc.initial_angles_rad, moment_floor=idc.moment_floor_Nm, frame=None,
        redesign_band=cfg.rotor.redesign_band, cache_resolution=cfg.rotor.cache_resolution,
        omega_min=cfg.rotor.omega_min_fraction * cfg.rotor.omega_nominal_rad_s,
        omega_default=None if cfg.rotor.stopped else cfg.rotor.omega_nominal_rad_s)
    from estimator.content import ContentFilter

    w0, harm = cfg.rotor.omega_nominal_rad_s, tuple(f.harmonics)

    def settle(kind: str) -> int:
        # the content filter starts from its first sample held constant: that sample's noise
        # rings in the output for a while, so those samples are not scored (after the start)
        return ContentFilter(kind, fs, w0, harm, 1).settle_samples

    known = PeriodicIdentification(mode="known_loads", content=idc.content_known_loads,
                                   content_settle_samples=settle(idc.content_known_loads),
                                   **common)
    design = cache.design_for(w0)
    ferr = PeriodicIdentification(mode="filter_error", content=idc.content_filter_error,
                                  design=design,
                                  content_sos=ContentFilter(idc.content_filter_error, fs, w0,
                                                            harm, 1).sos,
                                  content_settle_samples=settle(idc.content_filter_error),
                                  **common)
    return post, {"known_loads": known, "filter_error": ferr}, cache


def run_job(cfg, runs: dict, cache, job: dict) -> dict:
    """One window → one `angles` record (telemetry.md) with the job id attached."""
    mode = job["mode"]
    ident = runs[mode]
    seq = job["seq"]
    valid = job["ok"] & (job["known"] if mode == "known_loads" else True)
    if mode == "filter_error":
        omega = float(np.median(job["omega"]))
        design = cache.design_for(omega)
        if design is not ident.design:
            ident.design = design  # an Ω redesign is not a discontinuity (the state carries over)
    # a window that skips samples (lost, or the start) is a discontinuity for the filter
    gaps = np.diff(seq) > 1
    if gaps.any() and (np.diff(seq).max() - 1) > ident.gap_samples:
        ident.mark_discontinuity()
    # the pipeline buffers z = I − D q: the measured external loads are already taken off
    # (and W carries their noise), so their columns of the stacked data are zero here
    n_ext = ident.par.model.external.wrenches.shape[1]
    q = np.zeros((len(job["T"]), n_ext)) if n_ext else None
    rec = ident.run_window(job["z"], job["T"], job["known_H"] if mode == "known_loads" else None,
                           q, seq0=int(seq[0]), valid=valid, t=float(job["t"][-1]))
    # when the other mode runs next, its state must restart after new angles
    if rec.accepted:
        for other in runs.values():
            if other is not ident:
                other.mark_discontinuity()
    out = rec.to_dict()
    out["applies_from_seq"] = int(job["applies_from_seq"])
    out["late"] = False
    out["job_id"] = job["job_id"]
    out["condition"] = rec.condition
    return out


def _worker_main(cfg, initial_state, jobs: mp.Queue, results: mp.Queue) -> None:
    try:
        post, runs, cache = build_identification(cfg, initial_state)
    except Exception as e:  # report and stop: the service goes on without identification
        results.put({"error": f"identification worker failed to start: {e}"})
        return
    state_file = cfg.identification.state_file
    while True:
        job = jobs.get()
        if job is None:
            break
        try:
            rec = run_job(cfg, runs, cache, job)
            if rec["accepted"] and state_file:
                from estimator.posterior import save_posterior

                st = post.state()
                st.applies_from_seq = rec["applies_from_seq"]
                save_posterior(state_file, st)
        except Exception as e:
            rec = {"job_id": job["job_id"], "error": f"{type(e).__name__}: {e}",
                   "traceback": traceback.format_exc(limit=5)}
        results.put(rec)


class IdentificationWorker:
    """Owns the worker process and its two bounded queues."""

    def __init__(self, cfg, initial_state=None):
        ctx = mp.get_context("spawn")
        self.jobs = ctx.Queue(maxsize=JOB_QUEUE)
        self.results = ctx.Queue(maxsize=RESULT_QUEUE)
        self.proc = ctx.Process(target=_worker_main, args=(cfg, initial_state, self.jobs,
                                                           self.results),
                                name="rsra-identification", daemon=True)
        self.proc.start()
        self.submitted = 0
        self.dropped = 0
        self.errors = 0

    def submit(self, job: dict) -> bool:
        try:
            self.jobs.put_nowait(job)
            self.submitted += 1
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def poll(self) -> list[dict]:
        out = []
        while True:
            try:
                out.append(self.results.get_nowait())
            except queue.Empty:
                return out

    def wait(self, timeout: float = 60.0) -> dict | None:
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


def queue_stats(worker: IdentificationWorker | None) -> dict[str, Any]:
    if worker is None:
        return {}
    return {"identification": {"submitted": worker.submitted, "dropped": worker.dropped,
                               "errors": worker.errors}}
