"""The estimator pipeline's pieces, each alone (issue 27 item 4): the schedule of
identification results (daq/runtime/result_schedule.py), the angles in force
(daq/runtime/angles_in_force.py) and the calibration branch (daq/runtime/calibration_branch.py);
and that the pipeline's face forwards to them."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.daq.runtime.angles_in_force import AnglesInForce
from rsra.daq.runtime.calibration_branch import CalibrationBranch, WindowBuffer
from rsra.daq.runtime.records import ABSENT, AnglesRecord
from rsra.daq.runtime.result_schedule import ResultSchedule
from rsra.estimator.angle_uncertainty import HubAngleVariance
from rsra.estimator.geometry import wrench_matrix


@pytest.fixture(scope="module")
def cfg():
    return load_config()


# --- ResultSchedule -------------------------------------------------------------------------
def _rec(**kw) -> AnglesRecord:
    return AnglesRecord(accepted=True, reason=None, **kw)


def test_the_schedule_plans_jobs_and_applies_a_result_from_its_planned_sample():
    r = ResultSchedule()
    assert (r.plan(10), r.plan(20)) == (0, 1)
    assert r.outstanding == {0: 10, 1: 20} and r.waiting_for(15) == [0]
    r.deliver(_rec(seq=1), arrival_seq=5, job_id=0)  # before its sample: on time
    assert r.outstanding == {1: 20} and r.due_now(6)
    assert list(r.due(9)) == []  # taken in, not yet due
    assert not r.due_now(9) and r.due_now(10)
    (got,) = r.due(10)
    assert got.applies_from_seq == 10 and got.late is False
    assert not r.due_now(11)


def test_a_result_after_its_sample_applies_late_from_the_sample_that_takes_it_in():
    r = ResultSchedule()
    job = r.plan(10)
    r.deliver(_rec(seq=2), arrival_seq=12, job_id=job)
    (got,) = r.due(13)
    assert got.applies_from_seq == 13 and got.late is True


def test_a_recorded_record_applies_exactly_from_its_sample_and_results_come_in_order():
    r = ResultSchedule()
    r.deliver(_rec(seq=3, applies_from_seq=30))
    r.deliver(_rec(seq=2, applies_from_seq=20))
    assert [x.applies_from_seq for x in r.due(30)] == [20, 30]
    r.deliver(_rec(seq=4, applies_from_seq=40))
    assert [x.late for x in r.due(40)] == [ABSENT]  # a replayed record is not changed


def test_the_results_no_sample_applied_are_the_final_records():
    r = ResultSchedule()
    job = r.plan(100)
    r.deliver(_rec(seq=5), arrival_seq=50, job_id=job)
    (got,) = r.final_records(after_seq=60)
    assert got.applies_from_seq == 100 and got.late is False
    assert r.final_records(after_seq=60) == [] and not r.due_now(10 ** 9)


# --- AnglesInForce ---------------------------------------------------------------------------
class _Follower:
    def __init__(self):
        self.calls = []

    def set_alpha(self, alpha):
        self.calls.append(np.array(alpha))


def _angles(cfg, bound2=1.0):  # (σ², the same on every axis)
    model = cfg.rig_model()
    f = _Follower()
    a = AnglesInForce(model, cfg.identification.initial_angles_rad,
                      cfg.identification.prior_sigma_rad, np.full(6, bound2), f)
    return a, f, model.geometry


def test_the_angles_start_at_the_given_ones_with_the_prior_covariance(cfg):
    a, f, g = _angles(cfg)
    a0 = np.asarray(cfg.identification.initial_angles_rad, float)
    assert np.array_equal(a.alpha, a0) and a.structure is None and a.sigma is None
    assert np.array_equal(a.S, wrench_matrix(g, a0))
    assert np.array_equal(a.P, np.eye(len(g.angle_names)) * cfg.identification.prior_sigma_rad ** 2)
    assert f.calls == []


def test_an_accepted_record_moves_the_angles_it_names_and_the_follower_takes_them(cfg):
    a, f, g = _angles(cfg)
    a0 = a.alpha.copy()
    names = list(g.angle_names)
    a.apply(_rec(names=[names[2], "not_an_angle"], alpha=[0.01, 5.0]))
    want = a0.copy()
    want[2] = 0.01
    assert np.array_equal(a.alpha, want)
    assert len(f.calls) == 1 and np.array_equal(f.calls[0], want)
    assert np.array_equal(a.S, wrench_matrix(g, want))


def test_a_rejected_record_changes_only_the_covariance(cfg):
    a, f, g = _angles(cfg)
    a0 = a.alpha.copy()
    n = len(g.angle_names)
    P = np.eye(n) * 1e-8
    a.apply(AnglesRecord(accepted=False, reason="not_identifiable", names=list(g.angle_names),
                         alpha=[0.0] * n, P=P.tolist()))
    assert np.array_equal(a.alpha, a0) and f.calls == []
    assert np.array_equal(a.P, P)
    a.set_covariance(None, None)  # nothing said: nothing changes
    assert np.array_equal(a.P, P)
    T = np.linspace(100.0, 700.0, 7)
    a.measure(T)
    assert np.array_equal(a.sigma, np.sqrt(np.abs(HubAngleVariance(g, a0, P).variance(T))))


def test_the_sigma_is_flagged_uncertain_above_the_bound(cfg):
    T = np.linspace(100.0, 700.0, 7)
    big, _, _ = _angles(cfg, bound2=1e30)
    big.measure(T)
    tiny, _, _ = _angles(cfg, bound2=0.0)
    tiny.measure(T)
    assert not big.uncertain and tiny.uncertain
    assert np.array_equal(big.sigma, tiny.sigma)


def test_a_structure_in_force_uses_its_angles_and_dropping_it_the_identified_ones(cfg):
    from rsra.estimator.structure import parameter_names

    a, f, g = _angles(cfg)
    model = cfg.rig_model()
    n = len(g.angle_names)
    a0 = np.radians(np.linspace(-1.0, 1.0, n))
    fit = {"structure": "balance", "alpha0": a0.tolist(),
           "beta": [0.0] * len(parameter_names("balance", model)),
           "T_ref": [0.0] * g.n_cells, "alpha0_sigma": [np.radians(0.2)] * n}
    a.set_structure(fit)
    assert a.structure is not None and np.array_equal(f.calls[-1], a.structure.alpha)
    a.set_structure(fit)  # the same fit again: nothing to do
    assert len(f.calls) == 1
    a.set_alpha(np.zeros(n))  # identified angles under a structure: kept, not used
    assert len(f.calls) == 1 and np.array_equal(a.alpha, np.zeros(n))
    a.set_structure(None)
    assert a.structure is None and np.array_equal(f.calls[-1], np.zeros(n))
    assert np.array_equal(a.S, wrench_matrix(g, np.zeros(n)))


# --- CalibrationBranch -----------------------------------------------------------------------
def _sample(t, known=True):
    return SimpleNamespace(t=t, known_H=np.arange(6.0) if known else None)


def test_the_branch_cuts_a_job_every_period_and_plans_it_in_the_schedule(cfg):
    sched = ResultSchedule()
    b = CalibrationBranch(cfg, sched)
    assert b.period_n == round(cfg.identification.period_s * cfg.sample_rate_hz)
    T, z, alpha = np.full(7, 100.0), np.ones(6), np.zeros(14)
    jobs = []
    for i in range(2 * b.period_n):
        job = b.step(_sample(i / cfg.sample_rate_hz), 1000 + i, i + 1, T, z, True, None,
                     alpha, None, ())
        if job is not None:
            jobs.append((i, job))
    assert [i for i, _ in jobs] == [b.period_n - 1, 2 * b.period_n - 1]
    _, job = jobs[-1]
    last = 1000 + 2 * b.period_n - 1
    assert job.job_id == 1 and job.mode == "known_loads"
    assert job.applies_from_seq == last + b.apply_delay_n
    assert sched.outstanding == {0: jobs[0][1].applies_from_seq, 1: job.applies_from_seq}
    assert len(job.seq) == b.window_n and int(job.seq[-1]) == last
    assert job.dpsi is None  # (design mode)
    assert job.alpha is not alpha and job.ok.all() and job.known.all()
    assert np.array_equal(job.T_mean, T)


def test_without_known_loads_the_branch_takes_the_filter_error_mode(cfg):
    b = CalibrationBranch(cfg, ResultSchedule())
    T, z = np.full(7, 100.0), np.ones(6)
    job = None
    for i in range(b.period_n):
        job = b.step(_sample(i / cfg.sample_rate_hz, known=False), i, i + 1, T, z, True, 60.0,
                     np.zeros(14), None, ())
    assert job is not None and job.mode == "filter_error"
    assert job.content == cfg.identification.content_filter_error
    assert not job.known.any() and (job.omega == 60.0).all()


def test_what_a_sample_lacked_is_named_by_its_flags(cfg):
    b = CalibrationBranch(cfg, ResultSchedule())
    labels = b.input_labels
    assert b.missing_bits([labels[1], "transient"], measured=False) == 1 << 1
    assert b.missing_bits([], measured=False) == 1 << (len(labels) - 1)  # unusable
    assert b.missing_bits(["transient"], measured=True) == 0


def test_the_window_buffer_keeps_the_last_window_in_time_order():
    w = WindowBuffer(3, 9)
    for i in range(5):
        w.add(i, 0.1 * i, np.full(7, i), np.full(6, i), np.zeros(6), i != 3, True, 1.0,
              raw=(np.full(7, 10.0 * i), np.full(6, i)) if i != 3 else None)
    got = w.window()
    assert got["seq"].tolist() == [2, 3, 4] and got["ok"].tolist() == [True, False, True]
    assert np.array_equal(got["T_mean"], np.full(7, 30.0))  # over the complete samples only


# --- the pipeline's face ---------------------------------------------------------------------
def test_the_pipeline_forwards_to_its_pieces(cfg):
    from rsra.daq.runtime.pipeline import EstimatorPipeline

    p = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, hub_kernel=False)
    assert p.alpha is p.angles.alpha and p.structure is None
    assert p.outstanding is p.results.outstanding
    assert p.calibration.schedule is p.results
    p.outstanding[0] = 5
    assert p.waiting_for(5) == [0]
    p.deliver(_rec(seq=0), job_id=0)
    assert p.outstanding == {} and [r.applies_from_seq for r in p.final_records(3)] == [5]
