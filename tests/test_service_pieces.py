"""The service's pieces alone (daq.runtime.supervision, daq.runtime.run_report): the worker's
results to the pipeline, a lost worker, the summary's figures — with stand-ins, no process,
no bus (the whole service: test_service.py, test_first_step.py)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from rsra.daq.runtime.records import IdentError, IdentResult
from rsra.daq.runtime.run_report import latency_percentiles, schedule_summary
from rsra.daq.runtime.supervision import Supervision


class _Pipeline:
    def __init__(self):
        self.outstanding: dict[int, int] = {}
        self.delivered: list = []
        self.identification, self.identification_off = True, False

    def deliver(self, record, arrival_seq=None, job_id=None):
        self.outstanding.pop(job_id, None)
        self.delivered.append((record, arrival_seq, job_id))

    def waiting_for(self, seq):
        return any(due <= seq for due in self.outstanding.values())


class _Worker:
    def __init__(self, results=(), take=True):
        self.results, self.take, self.off, self.stopping = list(results), take, False, False
        self.jobs: list = []

    def submit(self, job, seq):
        self.jobs.append(("submit", job.job_id, seq))
        return self.take

    def put(self, job, seq):
        self.jobs.append(("put", job.job_id, seq))
        return self.take

    def poll(self, seq):
        out, self.results = self.results, []
        return out

    def check(self, seq, every_call=False):
        return True

    def wait(self, seq, timeout):
        return self.results.pop(0) if self.results else None


def _supervised(worker):
    p = _Pipeline()
    sup = Supervision(p)
    sup.worker = worker
    return p, sup


def test_without_a_worker_every_call_is_a_no_op():
    p = _Pipeline()
    sup = Supervision(p)
    p.outstanding[1] = 10
    sup.submit(SimpleNamespace(job_id=1), 5, deterministic=False)
    sup.poll(5)
    sup.wait(10)
    sup.finish(10)
    sup.stop()
    sup.close()
    assert p.outstanding == {1: 10} and p.delivered == [] and sup.errors == 0


def test_results_go_to_the_pipeline_and_errors_are_counted_and_forgotten():
    rec = SimpleNamespace(name="angles")
    worker = _Worker([IdentResult(job_id=1, record=rec), IdentError("boom", job_id=2)])
    p, sup = _supervised(worker)
    p.outstanding.update({1: 40, 2: 80})
    sup.poll(33)  # live: delivered as arriving after sample 33
    assert p.delivered == [(rec, 33, 1)]
    assert sup.errors == 1 and p.outstanding == {}  # the failed window is not waited for


@pytest.mark.parametrize("deterministic", [True, False])
def test_a_window_the_worker_does_not_take_is_forgotten(deterministic):
    worker = _Worker(take=False)
    p, sup = _supervised(worker)
    p.outstanding[7] = 100
    sup.submit(SimpleNamespace(job_id=7), 50, deterministic=deterministic)
    assert worker.jobs == [("put" if deterministic else "submit", 7, 50)]
    assert p.outstanding == {}


def test_lock_step_waits_for_the_result_due_and_a_dead_worker_drops_its_windows():
    rec = SimpleNamespace(name="angles")
    p, sup = _supervised(_Worker([IdentResult(job_id=3, record=rec)]))
    p.outstanding[3] = 20
    sup.wait(19)
    assert p.delivered == []  # not due yet
    sup.wait(20)
    assert p.delivered == [(rec, None, 3)]
    p.outstanding[4] = 30
    sup.wait(30)  # the worker died (wait gives None): nothing is waited for any more
    assert p.outstanding == {}


def test_a_worker_off_for_good_turns_the_pipelines_identification_off():
    worker = _Worker()
    p, sup = _supervised(worker)
    p.outstanding[1] = 5
    sup.worker_lost()  # restarted: only its windows are lost
    assert p.outstanding == {} and p.identification and not p.identification_off
    worker.off = True
    sup.worker_lost()
    assert not p.identification and p.identification_off
    sup.stop()
    assert worker.stopping


def test_latency_percentiles_and_the_schedule_summary():
    assert latency_percentiles([]) is None
    lat = latency_percentiles([0.001] * 99 + [0.010])
    assert lat == pytest.approx({"p50": 1.0, "p99": 1.09, "max": 10.0})
    cfg = SimpleNamespace(sample_rate_hz=100.0,
                          identification=SimpleNamespace(period_s=10.0, apply_delay_s=1.0))
    sch = {"source": "recorded", "last_applies_from_seq": 1000}
    assert schedule_summary(sch, None, cfg) == sch
    short = schedule_summary(sch, 2000, cfg)  # 10 s past the last record: a period, not more
    assert short["uncovered_s"] == 10.0 and short["partial"] is False
    assert schedule_summary(sch, 2300, cfg)["partial"] is True  # 13 s > 10 + 1 + 1 s
    assert schedule_summary({"source": "recomputed"}, 2300, cfg) == {"source": "recomputed"}


def _finished_loop(stuck_episodes: int = 0):
    """A stand-in of a finished SampleLoop: what run_summary reads of it."""
    import numpy as np

    stuck = SimpleNamespace(health=lambda: {"stuck_episodes": stuck_episodes,
                                            "stuck_samples": 7 * stuck_episodes})
    return SimpleNamespace(
        samples=100, lost=2, first_t=1.0, last_t=1.5, deadline_misses=0, latencies=[],
        last_seq=99, outputs=SimpleNamespace(counts={"hub_loads": 100}),
        angles=SimpleNamespace(rejected={"stale_input": 1}, runs=3, log=[]),
        pipeline=SimpleNamespace(implausible_omega=0, design_errors=0, stuck=stuck,
                                 alpha=np.zeros(2)))


def _reader(gaps: int):
    health = SimpleNamespace(samples=SimpleNamespace(complete=98, incomplete=2),
                             sync=SimpleNamespace(gaps=gaps, gap_longest_s=0.25))
    return SimpleNamespace(health=lambda: health)


def test_the_summary_names_sync_gaps_and_stuck_episodes_only_when_there_were_some(cfg):
    from rsra.daq.runtime.run_report import run_summary

    quiet = run_summary(_finished_loop(), _reader(0), [], None, cfg)
    assert (quiet["samples_complete"], quiet["samples_incomplete"]) == (98, 2)
    assert quiet["accepted"] == 2 and quiet["duration_s"] == 0.5
    assert "sync_gaps" not in quiet and "stuck" not in quiet and "implausible_omega" not in quiet
    eventful = run_summary(_finished_loop(stuck_episodes=1), _reader(3), ["w"], None, cfg)
    assert eventful["sync_gaps"] == {"count": 3, "longest_s": 0.25}
    assert eventful["stuck"] == {"episodes": 1, "samples": 7}
    assert eventful["warnings"] == ["w"]
    assert "samples_complete" not in run_summary(_finished_loop(), None, [], None, cfg)
