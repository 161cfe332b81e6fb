"""When each identification result applies: the estimator pipeline's schedule of results
(daq/runtime/pipeline.py; docs/architecture.md, the live two steps).

A job is planned to apply from a stated sample (its window's last sample + the apply delay).
Its result is handed over (:meth:`ResultSchedule.deliver`, live from the service thread) into
an inbox that the next first step takes in, so the sample a result applies from is decided
where samples are counted; a recorded record (replay) applies exactly from its
``applies_from_seq``.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import replace

from rsra.daq.runtime.records import ABSENT, AnglesRecord


class ResultSchedule:
    """The identification results on their way into force: the jobs awaited (``outstanding``:
    job id -> planned apply sample), the results handed over and not yet scheduled (the
    inbox), the scheduled ones waiting for their apply sample (``pending``, in order)."""

    def __init__(self) -> None:
        self.pending: list[AnglesRecord] = []  # results waiting for their apply sample
        # results handed over (deliver: the service thread) and not yet scheduled: the
        # first step takes them in at its next sample (live, that step runs in the bus
        # thread; deque's append/popleft are atomic), so the sample a result applies from is
        # decided where samples are counted
        self._inbox: deque[tuple[AnglesRecord, int | None, bool]] = deque()
        self.outstanding: dict[int, int] = {}  # job id -> planned apply seq
        self.next_job_id = 0

    def plan(self, applies_from_seq: int) -> int:
        """A new job's id, awaited from sample ``applies_from_seq``."""
        job_id = self.next_job_id
        self.next_job_id += 1
        self.outstanding[job_id] = applies_from_seq
        return job_id

    def deliver(self, rec: AnglesRecord, arrival_seq: int | None = None,
                job_id: int | None = None) -> None:
        """Hand over an identification result of job ``job_id`` (live: ``arrival_seq`` given)
        or a recorded angles record (replay). Safe to call while another thread runs the first
        step of the pipeline's ``stages``.

        Live: it applies from its planned sample, or — when the first step has passed that
        sample before taking the result in — from the first sample it takes it in at
        (`late`): after sample ``arrival_seq`` at the earliest. A recorded record carries its
        `applies_from_seq` and is applied exactly there; so is a lock-step result (no
        ``arrival_seq``: the loop waits for it).
        """
        planned = None
        if job_id is not None:
            planned = self.outstanding.pop(job_id, rec.get("applies_from_seq"))
        self._inbox.append((rec, planned, job_id is not None and arrival_seq is not None))

    def waiting_for(self, seq: int) -> list[int]:
        """Jobs whose result must be in before sample `seq` is processed (lock-step)."""
        return [j for j, s in self.outstanding.items() if s <= seq]

    def _take_in(self, seq: int) -> None:
        """The results handed over since the last sample, scheduled (before sample ``seq``)."""
        inbox = self._inbox
        while inbox:
            rec, planned, live = inbox.popleft()
            if planned is not None:
                if live and planned < seq:  # its sample has passed: from this one, late
                    rec = replace(rec, applies_from_seq=seq, late=True)
                else:
                    rec = replace(rec, applies_from_seq=planned,
                                  late=False if rec.late is ABSENT else rec.late)
            self.pending.append(rec)
            self.pending.sort(key=lambda r: r.applies_from_seq)

    def due_now(self, seq: int) -> bool:
        """Whether sample ``seq`` has results to take in or apply (:meth:`due` has work)."""
        return bool(self._inbox) or (bool(self.pending)
                                     and self.pending[0].applies_from_seq <= seq)

    def due(self, seq: int) -> Iterator[AnglesRecord]:
        """The results that apply from sample ``seq`` on (taken in first), in order, each
        removed from the schedule as it is taken."""
        if self._inbox:
            self._take_in(seq)
        while self.pending and self.pending[0].applies_from_seq <= seq:
            yield self.pending.pop(0)

    def final_records(self, after_seq: int) -> list[AnglesRecord]:
        """At the end of a run: the results handed over that no sample applied — they apply
        from a sample after the last one (``after_seq``), i.e. to the next run through the
        state file the worker saved them to. Returned in order so that they are published and
        recorded like the others, and the run's summary and its saved posterior agree."""
        if self._inbox:
            self._take_in(after_seq + 1)
        out, self.pending = self.pending, []
        return out
