"""The identification worker as the sample loop sees it: windows handed over, results taken
in and given to the pipeline, a worker that dies restarted or turned off (its windows lost),
the windows still running at the end awaited for a bounded time.

The worker process itself and its restarts are daq.runtime.ident_worker's
(``SupervisedIdentification``); this is the service's side of it. With the identification
off there is no worker and every call is a no-op (``worker`` None).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rsra.daq.runtime.records import IdentError, IdentResult

if TYPE_CHECKING:
    from rsra.config.rig import RigConfig
    from rsra.daq.runtime.ident_worker import SupervisedIdentification
    from rsra.daq.runtime.pipeline import EstimatorPipeline

log = logging.getLogger("rsra.service")

FINAL_RESULTS_WAIT_S = 10.0  # at the end: the wait for windows still being identified
RESULT_WAIT_S = 120.0  # lock-step: the longest wait for the result due at a sample


class Supervision:
    """Between the pipeline (its ``outstanding`` windows, ``deliver``) and the worker."""

    def __init__(self, pipeline: EstimatorPipeline):
        #: the pipeline the results go to (and whose windows a dead worker loses)
        self.pipeline = pipeline
        #: the supervised worker process; None while the identification is off
        self.worker: SupervisedIdentification | None = None
        #: results that came back as errors (logged; the health record counts them)
        self.errors = 0

    def start(self, cfg: RigConfig, state: Any,
              initializer: Callable[[], None] | None = None) -> None:
        """Start the worker (from the posterior ``state``, or the prior)."""
        from rsra.daq.runtime.ident_worker import SupervisedIdentification

        self.worker = SupervisedIdentification(cfg, state, on_restart=self.worker_lost,
                                               initializer=initializer)

    def worker_lost(self) -> None:
        """The identification worker died: the windows it held are lost (a restart is a
        discontinuity; its first record says so), and when it is off for good the pipeline
        stops cutting windows and flags every sample."""
        p = self.pipeline
        p.outstanding.clear()
        if self.worker is not None and self.worker.off:
            p.identification = False
            p.identification_off = True

    def stop(self) -> None:
        """The service is stopping: a worker that dies now is not restarted."""
        if self.worker is not None:
            self.worker.stopping = True

    def submit(self, job: Any, seq: int, deterministic: bool) -> None:
        """Hand the window ``job`` (cut at sample ``seq``) to the worker. Deterministic
        (lock-step, replay): every window runs, unless the worker died meanwhile; live: a
        busy, dead or turned-off worker drops it (logged). A window not taken is forgotten
        by the pipeline."""
        if self.worker is None:
            return
        taken = (self.worker.put(job, seq) if deterministic else self.worker.submit(job, seq))
        if not taken:
            self.pipeline.outstanding.pop(job.job_id, None)

    def poll(self, last_seq: int | None) -> None:
        """Live: the results in now (and a dead worker restarted), delivered as arriving
        after sample ``last_seq``."""
        if self.worker is None:
            return
        arrival = last_seq if last_seq is not None else 0
        for r in self.worker.poll(last_seq):
            self.deliver(r, arrival)

    def deliver(self, r: IdentResult | IdentError, arrival: int | None) -> None:
        if isinstance(r, IdentError):
            self.errors += 1
            log.error("identification: %s", r.error)
            if r.job_id is not None:
                self.pipeline.outstanding.pop(r.job_id, None)
            return
        self.pipeline.deliver(r.record, arrival_seq=arrival, job_id=r.job_id)

    def wait(self, seq: int) -> None:
        """Lock-step and replay: the result of every window due at this sample first; a dead
        worker is seen at every sample (restarted, or identification off: deterministic)."""
        if self.worker is None:
            return
        self.worker.check(seq, every_call=True)
        while self.pipeline.waiting_for(seq):
            r = self.worker.wait(seq, timeout=RESULT_WAIT_S)
            if r is None:  # it died: restarted or off, its jobs forgotten (worker_lost)
                self.pipeline.outstanding.clear()
                return
            self.deliver(r, None)

    def finish(self, last_seq: int) -> None:
        """The windows still being identified when acquisition ended (at ``last_seq``):
        their results taken in for at most FINAL_RESULTS_WAIT_S; one not done by then is
        abandoned unsaved, and the log says so."""
        if self.worker is None:
            return
        p = self.pipeline
        for r in self.worker.finish(lambda: len(p.outstanding), FINAL_RESULTS_WAIT_S):
            self.deliver(r, last_seq)
        if p.outstanding:
            log.warning("%d identification window(s) still running at the end: "
                        "abandoned (not applied, not saved)", len(p.outstanding))
            p.outstanding.clear()

    def close(self) -> None:
        if self.worker is not None:
            resource_tracker_gone()  # before the worker's queues release their semaphores
            self.worker.close()


def _nothing(name: str, rtype: str) -> None:
    """A resource tracker call with no tracker to tell (see :func:`resource_tracker_gone`)."""


def resource_tracker_gone() -> bool:
    """multiprocessing's resource tracker (the helper process that removes a crashed
    process's semaphores) killed under the run: one line, once. Without it, the first
    semaphore released afterwards starts a new tracker, which prints a ``KeyError: '/mp-…'``
    traceback for every semaphore it never saw (6 at the end of a run). This process removes
    its own semaphores as it releases them (``SemLock._cleanup``: ``sem_unlink`` first), so
    nothing leaks when the tracker is not told: its register/unregister become no-ops for
    the rest of the run. True if it was gone."""
    from multiprocessing import resource_tracker as rt

    t: Any = rt._resource_tracker  # (its private state: not in typeshed)
    if rt.unregister is _nothing or t._fd is None or t._check_alive():
        return False
    log.warning("multiprocessing's resource tracker (pid %s) has gone (killed?); not "
                "restarted: this process removes its own semaphores as it releases them",
                t._pid)
    rt.register = _nothing  # type: ignore[assignment]  # (typeshed: name is Sized)
    rt.unregister = _nothing  # type: ignore[assignment]
    return True
