"""Angles that drift in time: the drift candidate of the structure test and the posterior that
tracks with it (issue 27; estimator/structure.py ``DriftTest``, docs/identification.md
"Angles that drift")."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from rsra.config.rig import load_config
from rsra.estimator.balance import inertial_loads
from rsra.estimator.content import ContentFilter
from rsra.estimator.structure import DRIFTING, StructureTest
from rsra.sim_bus import load_scenario, simulate

RUN_S = 120.0
DRIFT = {"angles": "drift", "angles.drift_deg": 1.0, "angles.drift_over_s": RUN_S}


@pytest.fixture(scope="module")
def cfg():
    return load_config()


@pytest.fixture(scope="module")
def runs(cfg):
    """Two sweeps of the ground test, the same aircraft: three angles drifting 1° over the
    120 s, and constant angles."""
    fs = cfg.sample_rate_hz
    return {arm: simulate(cfg, load_scenario("ground-test", **var), seed=4,
                          n_samples=round(RUN_S * fs))
            for arm, var in (("drift", DRIFT), ("constant", {}))}


def _verdicts(cfg, run):
    model, fs = cfg.rig_model(), cfg.sample_rate_hz
    cf = ContentFilter("static", fs, cfg.rotor.omega_nominal_rad_s, tuple(cfg.filter.harmonics),
                       19)
    Y = cf.process(np.hstack([inertial_loads(model, run.accel), run.T, run.H_balance]))
    st = StructureTest(model, cfg.identification.moment_floor_Nm)
    st.joint_fits = False  # the drift verdict does not use them
    P = round(cfg.identification.window_s * fs)
    alpha0 = np.asarray(cfg.identification.initial_angles_rad, float)
    out = []
    for k, end in enumerate(range(P, len(Y) + 1, P)):
        x = Y[end - P:end][cf.settle_samples if k == 0 else 0:]
        out.append(st.add_window(x, alpha0, t=(end - P / 2) / fs))
    return out


def test_drift_is_selected_on_a_drifting_run_and_not_on_a_constant_one(cfg, runs):
    """The simulator's drifting angles are called `drifting` (rates within 4σ of the truth:
    1°/120 s on angles 0, 6, 11, zero elsewhere); the same aircraft with constant angles
    never is. Break check: with the drift candidate off (``drift=False``, the structures of
    issue 19 only) the drifting run is never `drifting` — measured, this test fails."""
    v = _verdicts(cfg, runs["drift"])
    names = [x.structure for x in v]
    assert DRIFTING in names, names
    last = v[-1].drift
    assert last.selected and last.dof == 14
    truth = np.zeros(14)
    truth[[0, 6, 11]] = np.radians(1.0) / RUN_S
    z = (last.rate - truth) / last.rate_sigma
    assert np.all(np.abs(z) < 4.0), z
    # significant on the drifting angles (psi_F, 11, is the least determined: σ 4× theirs)
    assert np.sum(np.abs(last.rate[[0, 6, 11]] / last.rate_sigma[[0, 6, 11]]) > 3.0) >= 2
    c = _verdicts(cfg, runs["constant"])
    assert DRIFTING not in [x.structure for x in c]
    assert not any(x.drift is not None and x.drift.rejects_constant for x in c)


@pytest.mark.slow
def test_the_posterior_tracks_a_drift_consistently_once_selected(cfg, runs):
    """The service's identification over the drifting run: once `drifting`, no reset, every
    accepted run within χ²₁₄(1 − 10⁻³) of the mean true angles of its own window, and the
    `angles` record carries the rates."""
    from bench.a3_known_load import chi2_of, run_calibration

    run = runs["drift"]
    W = round(cfg.identification.window_s * cfg.sample_rate_hz)
    limit = stats.chi2.isf(1e-3, 14)
    seen = False
    for end, rec, theta, P in run_calibration(cfg, run, known_loads=True):
        seen = seen or rec["structure"] == DRIFTING
        if not seen:
            continue
        assert rec["reason"] != "reset"
        assert rec["drift"] is not None and len(rec["drift"]["rate"]) == 14
        if rec["accepted"]:
            truth = run.alpha_true[end + 1 - W:end + 1].mean(axis=0)
            assert chi2_of(theta - truth, P) <= limit
    assert seen



def test_accepted_runs_before_the_drifting_verdict_are_consistent(cfg):
    """Before the drift is called `drifting`, every accepted run of the service's
    identification is within χ²₁₄(1 − 10⁻³) of the mean true angles of its own window: once
    the windows determine the 14 rates, each run's prior is the drift fit's prediction under
    the drift the windows cannot exclude (``DriftTest.bounded_prediction``), not the
    constant-angle posterior whose σ shrinks below the drift it has seen. 100 s of A4's
    drift arm (+0.5° over 240 s on angles 0, 6, 11; seed 3: `drifting` from window 19).
    Break check: with the bound off (``DRIFT_BOUND_LEVEL = None``: the constant-angle
    posterior until the verdict) windows 12, 14 and 16 are accepted at χ²₁₄ 43–58 —
    measured, this test fails."""
    from bench.a3_known_load import chi2_of, run_calibration

    fs = cfg.sample_rate_hz
    run = simulate(cfg, load_scenario("ground-test", angles="drift"), seed=3,
                   n_samples=round(100.0 * fs))
    W = round(cfg.identification.window_s * fs)
    limit = stats.chi2.isf(1e-3, 14)
    bad, accepted = [], 0
    for k, (end, rec, theta, P) in enumerate(run_calibration(cfg, run, known_loads=True)):
        if rec["structure"] == DRIFTING:
            break
        if rec["accepted"]:
            accepted += 1
            truth = run.alpha_true[end + 1 - W:end + 1].mean(axis=0)
            c = chi2_of(theta - truth, P)
            if c > limit:
                bad.append((k + 1, round(c, 1)))
    assert accepted >= 10
    assert not bad, bad


def test_the_drift_bound_is_linearised_where_the_posterior_knows_the_angles(cfg):
    """Constant angles, the first 40 s of A4's constant arm, seed 79: every accepted run within
    χ²₁₄(1 − 10⁻³) of the truth. At window 6 the constant fit of the six window means alone
    is 8.7° off in a direction only the full moments determine; the bound's joint fit
    linearised there bent the directions the means do determine, and the run was accepted at
    χ²₁₄ 83 (bench A4 before session 13: 4 such seeds of 100 in each arm). The bound's
    prediction is now re-linearised at the last accepted posterior
    (``DriftTest.predict_bounded_at``). Break check: without the re-linearisation
    (``PeriodicIdentification._bounded`` returning its first combination) window 6 is accepted
    at χ²₁₄ 83.3 — measured, this test fails."""
    from bench.a3_known_load import chi2_of, run_calibration

    run = simulate(cfg, load_scenario("ground-test"), seed=79,
                   n_samples=round(40.0 * cfg.sample_rate_hz))
    truth = run.alpha_true[0]
    limit = stats.chi2.isf(1e-3, 14)
    scored = [(k, rec["accepted"], chi2_of(theta - truth, P))
              for k, (_, rec, theta, P) in enumerate(run_calibration(cfg, run, known_loads=True))]
    assert sum(acc for _, acc, _ in scored) >= 3
    bad = [(k, round(c, 1)) for k, acc, c in scored if acc and c > limit]
    assert not bad, bad
