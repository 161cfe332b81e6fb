"""The sample loop: each item a source yields (a sample, a health report, or None when idle)
through the pipeline to the outputs, in acquisition order, until ``--duration`` or a stop.

Live (a bus, the simulator in real time), a sample's first step (its hub loads) runs in the
bus thread that completed it (:meth:`SampleLoop.first_step`) and the rest in the service
thread (:meth:`SampleLoop.on_sample`); lock-step and replay run both in the service thread
and wait for the identification results due at each sample (daq.runtime.supervision).
docs/architecture.md "Runtime".
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, cast

from rsra.daq.runtime.records import AnglesRecord
from rsra.daq.runtime.supervision import Supervision
from rsra.estimator.verdict import held_window

if TYPE_CHECKING:
    from rsra.daq.runtime.pipeline import EstimatorPipeline

log = logging.getLogger("rsra.service")

LATENCY_HISTORY = 2000
ANGLES_HISTORY = 16  # recent angles records kept in memory (~15 kB each with P)
STATUS_PERIOD_S = 60.0  # a calibrated run's one-line calibration status, this often (record t)


class _FirstStepDone:
    """A live sample from the bus thread: its first step done there (hub_loads published;
    ``rest`` the second step to take), or — ``rest`` None — the whole sample for the service
    thread (a slow first step); ``error`` a first step that failed."""

    __slots__ = ("sample", "rest", "records", "error")

    def __init__(self, sample: Any, rest: Any, records: list,
                 error: BaseException | None = None):
        self.sample, self.rest, self.records, self.error = sample, rest, records, error

    @property
    def seq(self) -> int:
        return self.sample.seq


class AnglesTally:
    """The angles records of a run as they are applied: recorded (the source's recorder;
    a replay has none), the latest kept, accepted and rejected runs counted and logged."""

    def __init__(self, source: Any):
        self._source = source
        #: the latest angles records (bounded: a record with its P is ~10 kB, one per period
        #: for as long as the service runs)
        self.log: deque[AnglesRecord] = deque(maxlen=ANGLES_HISTORY)
        #: identification runs, and the rejected ones by reason
        self.runs = 0
        self.rejected: dict[str, int] = {}
        #: the directions the last advised window determined (the advice is logged when it
        #: changes, not every window)
        self._advised: int | None = None
        #: the calibration so far, for the periodic status line: windows accepted and held,
        #: the time of the last accepted run and of the last status line (record t)
        self._accepted = 0
        self._held = 0
        self._last_change: float | None = None
        self._last_status: float | None = None

    def add(self, rec: AnglesRecord) -> None:
        """An angles record applied (or, at the end, one that never applied). (The
        pipeline's records are typed ``dict``; an ``angles`` payload is an AnglesRecord.)"""
        recorder = self._source.recorder
        if recorder is not None:  # (a replay records nothing)
            recorder.write_angles(rec.to_dict())
        self.log.append(rec)
        self.runs += 1
        if not rec.get("accepted"):
            reason = str(rec.get("reason"))
            self.rejected[reason] = self.rejected.get(reason, 0) + 1
        if rec.get("accepted"):
            self._on_accepted(rec)
        elif held_window(rec):
            self._on_held(rec)
        else:
            log.info("identification rejected (%s, %s): %s: %s%s", rec.get("mode"),
                     rec.get("content"), rec.get("reason"), rec.get("explanation") or
                     rec.get("detail"), f"; hint: {rec.get('hint')}" if rec.get("hint") else "")
        self._log_advice(rec)
        self._log_status(rec)

    def _on_accepted(self, rec: AnglesRecord) -> None:
        """An accepted run: counted, its time kept for the status line, logged."""
        t = rec.get("t")
        self._accepted += 1
        self._last_change = t if isinstance(t, (int, float)) else self._last_change
        sig = rec.get("sigma_cr") or []
        worst = max((x for x in sig if x is not None), default=float("nan"))
        log.info("identification accepted (%s, %s): %d of %d directions determined, "
                 "worst sigma_CR %.3f deg, applies from sample %s%s", rec.get("mode"),
                 rec.get("content"), rec.get("determined", 0), len(rec.get("names") or []),
                 math.degrees(worst), rec.get("applies_from_seq"),
                 " (late)" if rec.get("late") else "")

    def _on_held(self, rec: AnglesRecord) -> None:
        """A held window: counted and logged with the information it adds."""
        self._held += 1
        info = rec.get("information")
        adds = (f"adds {info:.2g} of what the posterior knows"
                if isinstance(info, (int, float)) and math.isfinite(info) else
                "is not identifiable on its own")
        # once calibrated a held window is routine: the status line below says enough
        log.log(logging.DEBUG if self._accepted else logging.INFO,
                "identification held (%s, %s): this window %s; its information is used "
                "with the next windows", rec.get("mode"), rec.get("content"), adds)

    def _log_status(self, rec: AnglesRecord) -> None:
        """Once calibrated, every STATUS_PERIOD_S of acquisition time: one line saying where
        the calibration stands."""
        t = rec.get("t")
        if not self._accepted or not isinstance(t, (int, float)):
            return
        if self._last_status is not None and t - self._last_status < STATUS_PERIOD_S:
            return
        self._last_status = t
        log.info("%s", calibration_status(rec, self._accepted, self._held,
                                          None if self._last_change is None
                                          else t - self._last_change))

    def _log_advice(self, rec: AnglesRecord) -> None:
        """A filter-error window's advice, in one sentence, when what it determines changes."""
        from rsra.estimator.flight_advice import advice_summary

        adv = rec.get("advice")
        if not isinstance(adv, dict) or adv.get("determined") == self._advised:
            return
        self._advised = adv.get("determined")
        text = advice_summary(adv, len(rec.get("names") or []) or None)
        if text:
            log.info("advice: %s", text)


def calibration_status(rec: Any, accepted: int, held: int, since_change_s: float | None) -> str:
    """``calibration: 14 of 14 directions determined, largest σ 0.117°, …`` from the latest
    angles record (its ``determined`` and posterior ``P``)."""
    names = rec.get("names") or []
    sig = _largest_sigma_deg(rec.get("P"), len(names))
    parts = [f"calibration: {rec.get('determined')} of {len(names)} directions determined"]
    if sig is not None:
        parts.append(f"largest σ {sig:.3f}°")
    parts.append(f"{accepted} runs accepted, {held} windows held and used")
    if since_change_s is not None:
        parts.append(f"last change {since_change_s:.0f} s ago")
    return ", ".join(parts)


def _largest_sigma_deg(P: Any, n: int) -> float | None:
    """The largest √P_ii (degrees) of the first ``n``, None without a usable P."""
    try:
        diag = [P[i][i] for i in range(n)] if P is not None else []
        return max(math.degrees(math.sqrt(max(float(x), 0.0))) for x in diag) if diag else None
    except (TypeError, ValueError, IndexError):
        return None


class SampleLoop:
    """Items of a source through the pipeline to ``outputs.publish``, counted.

    ``source`` is asked only ``deterministic``, its ``recorder`` and (live) its reader's
    item queue; ``on_health`` takes the reader's health reports (daq.runtime.run_report)."""

    def __init__(self, pipeline: EstimatorPipeline, outputs: Any, supervision: Supervision,
                 source: Any, stop_event: threading.Event, dt: float,
                 n_max: int | None = None,
                 on_health: Callable[[Any], None] | None = None):
        self.pipeline = pipeline
        self.outputs = outputs
        self.supervision = supervision
        self.source = source
        self.stop_event = stop_event
        self.dt = dt
        #: live: the hub loads are published from the bus thread, results applied on arrival
        self.live = not source.deterministic
        self._n_max = n_max  # --duration in samples of acquisition time
        #: the reader's health reports go there (daq.runtime.run_report.HealthReporter)
        self.on_health = on_health
        self.angles = AnglesTally(source)
        #: hub_loads latencies (live) and those over one sample period
        self.latencies: deque[float] = deque(maxlen=LATENCY_HISTORY)
        self.deadline_misses = 0
        self.samples = 0
        self.lost = 0
        self.last_seq: int | None = None
        self.first_t: float | None = None
        self.last_t: float | None = None
        self._first_seq: int | None = None  # the first sample processed
        # live: samples the bus thread passed on whole (a slow first step, or after one):
        # counted by the bus thread when queued, by the service thread when done; the bus
        # thread runs first steps again only once none is left (sample order kept)
        self._whole_queued = 0
        self._whole_done = 0
        self._step_error: BaseException | None = None  # a first step failed (bus thread)

    def run(self, source: Iterator) -> None:
        from rsra.daq.bus.reader import HealthReport

        for item in source:
            if item is None:
                if self.live:
                    self.supervision.poll(self.last_seq)
            elif isinstance(item, HealthReport):
                if self.on_health is not None:
                    self.on_health(item)
            else:
                if self._first_seq is not None and self._past_last(item.seq):
                    break  # (the last wanted sample was dropped from a full queue)
                self.on_sample(item)
                if self._last_wanted(item.seq):
                    break
            if self.stop_event.is_set():
                break
        if self._step_error is not None:
            raise self._step_error

    def finish(self) -> None:
        """The end: the windows still being identified taken in (published, recorded and
        counted before the outputs close — the worker saves accepted ones to the state file,
        so what the run says last is what the state file holds), a replay's recorded records
        that apply after its last sample the same way; then the worker stops."""
        if self.last_seq is not None:
            self.supervision.finish(self.last_seq)
            for rec in self.pipeline.final_records(self.last_seq):
                self.outputs.publish("angles", rec)
                self.angles.add(rec)
        self.supervision.close()

    def _last_wanted(self, seq: int) -> bool:
        """Sample ``seq`` is the last one --duration asks for (it counts samples of
        acquisition time from the first one processed: lost ones included, they keep seq)."""
        if self._first_seq is None:
            self._first_seq = seq
        if self._n_max is None:
            return False
        return seq - self._first_seq + 1 >= self._n_max

    def _past_last(self, seq: int) -> bool:
        if self._first_seq is None:
            self._first_seq = seq
        return self._n_max is not None and seq - self._first_seq + 1 > self._n_max

    def first_step(self, s: Any) -> Any:
        """The bus thread, as a sample completes (live): the pipeline's first step and the
        publication of its records (hub_loads, and angles applied from this sample) at once,
        with no hand-off to another thread (the latency path). The service thread
        finishes the sample (:meth:`on_sample`). Samples after the last one wanted, or
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

    def _publish_first(self, s: Any, records: list) -> None:
        publish = self.outputs.publish
        for key, payload in records:
            publish(key, payload)
            if key == "hub_loads":
                lat = time.time() - s.t
                self.latencies.append(lat)
                if lat > self.dt:
                    self.deadline_misses += 1
            elif key == "angles":  # recorded where applied: never lost with a dropped sample
                self.angles.add(cast(AnglesRecord, payload))

    def on_sample(self, item: Any) -> None:
        p = self.pipeline
        live = self.live
        counted = False  # a whole sample the bus thread counted (first_step)
        if isinstance(item, _FirstStepDone):  # live: hub_loads is out (with its angles)
            if item.error is not None:
                raise item.error
            s, stages = item.sample, item.rest
            counted = stages is None
        else:
            s, stages = item, None
        if not live:
            self.supervision.wait(s.seq)

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
                self.angles.add(cast(AnglesRecord, payload))
        if out.job is not None:
            self.supervision.submit(out.job, s.seq, deterministic=not live)
        self.samples += 1
        self.lost += int(s.lost_before)
        self.last_seq = s.seq
        if self.first_t is None:
            self.first_t = s.t
        self.last_t = s.t
        if live:  # after the sample, off the SYNC → hub_loads path:
            self.supervision.poll(self.last_seq)  # a result in now applies from the next
            if counted:                           # sample at the earliest
                self._whole_done += 1  # the bus thread may take first steps again
