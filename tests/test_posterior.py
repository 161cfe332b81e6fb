"""The sequential posterior of model.md §7: decisions, persistence, and the periodic runs on
synthetic data (windows against the batch, an angle step, the report's Phase II set-up)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scipy.stats import chi2
from synthetic import TruthGeometry, harmonic_state, paper_run, static_run

from rsra.daq.jsonout import sanitise
from rsra.daq.runtime.persistence import load_posterior, save_posterior
from rsra.estimator.balance import inertial_loads, measurement_covariance
from rsra.estimator.content import ContentFilter
from rsra.estimator.filters import design_filter
from rsra.estimator.identification import (
    FilterErrorProblem,
    FilterErrorState,
    IdentificationResult,
    KnownLoadProblem,
    Parameterisation,
    levenberg_marquardt,
)
from rsra.estimator.posterior import (
    PeriodicIdentification,
    PosteriorFileError,
    PosteriorState,
    SequentialPosterior,
    consistency_gate,
    information_ratio,
)

DEG = np.pi / 180


def _post(cfg, model, theta0=None, **kw):
    names = model.geometry.angle_names
    p = SequentialPosterior.from_config(cfg.identification, names, names, theta0=theta0)
    # the linear-Gaussian worlds below draw their truth from the prior (σ 5°): no physical
    # range here (test_a_result_outside_the_physical_range_is_rejected covers it)
    p.limit = np.full(len(names), np.inf)
    for k, v in kw.items():
        setattr(p, k, v)
    return p


def _result(names, prior_mean, prior_cov, theta, M, status="converged", cost=1.0,
            cost_start=2.0):
    P = np.linalg.inv(M + np.linalg.inv(prior_cov))
    return IdentificationResult(tuple(names), "known_loads", np.asarray(theta, float), P, None,
                                M, np.asarray(prior_mean, float), prior_cov, cost, cost_start,
                                3, status, 100)


def _linear_run(post, rng, M, shift=None, dt=5.0):
    """A linear-Gaussian run: truth drawn from the prior (+ shift), data information M."""
    th_p, P_p = post.prior(dt)
    truth = rng.multivariate_normal(th_p, P_p) + (0 if shift is None else shift)
    y = rng.multivariate_normal(truth, np.linalg.inv(M))  # the window's own estimate
    P = np.linalg.inv(M + np.linalg.inv(P_p))
    theta = P @ (M @ y + np.linalg.solve(P_p, th_p))
    return _result(post.names, th_p, P_p, theta, M), truth


# ------------------------------------------------------------------------------------------
# decisions
# ------------------------------------------------------------------------------------------
def test_prior_is_inflated_by_the_random_walk(cfg, model):
    post = _post(cfg, model)
    q = cfg.identification.drift_rate_rad2_s
    th, P = post.prior(5.0)
    np.testing.assert_allclose(P, post.P + 5.0 * q * np.eye(14))
    np.testing.assert_allclose(np.diag(post.P0), cfg.identification.prior_sigma_rad**2)
    np.testing.assert_allclose(th, cfg.identification.initial_angles_rad)
    other = SequentialPosterior.from_config(cfg.identification, ("delta_A", "x_A"),
                                            model.geometry.angle_names,
                                            other_prior_sigma={"x_A": 0.05},
                                            theta0=np.array([0.0, 0.738]))
    _, P2 = other.prior(10.0)
    np.testing.assert_allclose(np.diag(P2), [(5 * DEG) ** 2 + 10 * q, 0.05**2])
    np.testing.assert_allclose(other.sigma_max, [0.2 * DEG, 0.04 * 0.05])
    with pytest.raises(ValueError, match="prior sigma"):
        SequentialPosterior.from_config(cfg.identification, ("x_A",), model.geometry.angle_names)


def test_gate_accepts_a_consistent_linear_world_at_the_stated_rate(cfg, model):
    """Truth drawn from the prior, data with information M: ν ~ χ²_d, so the gate rejects
    about 1e-3 of runs; with 3000 runs more than 12 rejections has probability < 1e-3."""
    rng = np.random.default_rng(1)
    post = _post(cfg, model)
    A = rng.normal(size=(14, 6))
    M = A @ A.T * 1e5 + np.eye(14) * 10.0  # some directions determined, some not
    rejected = 0
    nus = []
    for _ in range(3000):
        res, _ = _linear_run(post, rng, M)
        nu, d, ok = consistency_gate(res.theta - res.prior_mean, res.prior_cov, res.P)
        nus.append((nu, d))
        rejected += not ok
    assert rejected <= 12
    d = nus[0][1]
    assert d == 14 and abs(np.mean([n for n, _ in nus]) - d) < 0.5  # E[χ²_d] = d


def test_gate_uses_only_directions_the_data_moved(cfg, model):
    P_p = np.diag([1.0, 1.0, 1.0])
    P_post = np.diag([0.5, 1.0 - 1e-12, 1.0])  # only direction 0 is informed
    nu, d, ok = consistency_gate(np.array([1.0, 5.0, 5.0]), P_p, P_post)
    assert d == 1 and nu == pytest.approx(1.0 / 0.5) and ok
    nu, d, ok = consistency_gate(np.array([3.0, 0.0, 0.0]), P_p, P_post)
    assert nu == pytest.approx(18.0) and not ok  # χ²_1(0.999) = 10.8


def test_information_ratio_is_relative_to_the_prior():
    P_p = np.diag([4.0, 1.0])
    M = np.diag([0.1, 0.5])
    assert information_ratio(P_p, M) == pytest.approx(0.5)
    assert information_ratio(P_p * 4, M) == pytest.approx(2.0)


def test_sound_runs_only_and_every_rejection_keeps_the_posterior(cfg, model):
    rng = np.random.default_rng(2)
    post = _post(cfg, model)
    M = np.eye(14) * 1e6
    kw = dict(window=(0, 999), mode="known_loads", content="static")
    res, _ = _linear_run(post, rng, M)
    theta0, P0 = post.theta.copy(), post.P.copy()
    for status, reason in (("not_converged", "not_converged"), ("diverged", "diverged")):
        res.status = status
        rec = post.update(res, **kw)
        assert not rec.accepted and rec.reason == reason
        np.testing.assert_array_equal(rec.alpha, theta0)
        np.testing.assert_array_equal(rec.P, P0)
    res.status = "converged"
    res.cost = res.cost_start + 1.0  # J increased: not sound
    assert post.update(res, **kw).reason == "diverged"
    res.cost = 0.5
    res.theta = res.theta.copy()
    res.theta[3] = np.nan
    assert post.update(res, **kw).reason == "diverged"
    rec = post.update(None, **kw)
    assert rec.reason == "stale_input"
    res2, _ = _linear_run(post, rng, M)
    # more than stale_fraction (50 %) of samples lacking an input: what is left is too little
    rec = post.update(res2, missing_fraction=0.51, **kw)
    assert rec.reason == "stale_input" and not rec.accepted
    np.testing.assert_array_equal(post.theta, theta0)
    # a run whose data add little is not_identifiable (and passes the gate)
    small, _ = _linear_run(post, rng, np.eye(14) * 1.0)
    rec = post.update(small, **kw)
    assert rec.reason == "not_identifiable" and rec.information < 1
    np.testing.assert_array_equal(post.P, P0)
    # finally an informative consistent run is accepted and applies after the delay
    rec = post.update(res2, apply_delay_samples=200, **kw)
    assert rec.accepted and rec.reason is None and rec.applies_from_seq == 1199
    np.testing.assert_array_equal(post.theta, res2.theta)


def test_reset_after_three_inconsistent_runs_in_a_row(cfg, model):
    rng = np.random.default_rng(3)
    post = _post(cfg, model)
    M = np.eye(14) * 1e6
    kw = dict(window=(0, 999), mode="known_loads", content="static")
    rec = post.update(_linear_run(post, rng, M)[0], **kw)
    assert rec.accepted
    jump = np.full(14, 1 * DEG)
    theta_before = post.theta.copy()
    reasons = []
    for k in range(3):
        res, _ = _linear_run(post, rng, M, shift=jump)
        reasons.append(post.update(res, **kw).reason)
        if k == 0:  # a run rejected before the gate neither extends nor breaks the streak
            reasons.append(post.update(None, **kw).reason)
    assert reasons == ["inconsistent", "stale_input", "inconsistent", "reset"]
    np.testing.assert_allclose(post.P, post.P0)  # reopened ...
    np.testing.assert_array_equal(post.theta, theta_before)  # ... around the current mean
    res, _ = _linear_run(post, rng, M, shift=jump)
    assert post.update(res, **kw).reason is None  # learning again
    # an accepted run breaks the streak
    post2 = _post(cfg, model)
    post2.update(_linear_run(post2, rng, M)[0], **kw)
    seq = [post2.update(_linear_run(post2, rng, M, shift=jump)[0], **kw).reason,
           post2.update(_linear_run(post2, rng, M)[0], **kw).reason]
    seq += [post2.update(_linear_run(post2, rng, M, shift=jump)[0], **kw).reason
            for _ in range(2)]
    assert seq == ["inconsistent", None, "inconsistent", "inconsistent"]


def test_literal_order_keeps_low_information_runs_from_the_gate(cfg, model):
    rng = np.random.default_rng(4)
    post = _post(cfg, model, gate_low_information=False)
    post.P = np.eye(14) * (0.1 * DEG) ** 2
    M = np.eye(14) / (0.2 * DEG) ** 2  # ratio 0.25 < 1
    res, _ = _linear_run(post, rng, M, shift=np.full(14, 2 * DEG))
    rec = post.update(res, window=(0, 9), mode="known_loads", content="static")
    assert rec.reason == "not_identifiable" and rec.nu is None
    post.gate_low_information = True
    rec = post.update(res, window=(0, 9), mode="known_loads", content="static")
    assert rec.reason == "inconsistent" and rec.nu > chi2.ppf(0.999, rec.gate_dof)


def test_determined_directions_late_results_and_strict_json(cfg, model):
    post = _post(cfg, model)
    rng = np.random.default_rng(5)
    M = np.diag([1 / (0.1 * DEG) ** 2] * 5 + [1 / (1 * DEG) ** 2] * 9)
    res, _ = _linear_run(post, rng, M)
    rec = post.update(res, window=(1000, 1999), mode="known_loads", content="static",
                      apply_delay_samples=200, arrived_seq=2500, t=12.5)
    assert rec.accepted and rec.late and rec.applies_from_seq == 2501
    assert rec.determined == 5 and rec.undetermined.shape == (14, 9)
    d = rec.to_dict()
    for key in ("t", "seq", "mode", "content", "accepted", "reason", "names", "alpha", "P",
                "sigma_cr", "sigma_cr_corrected", "determined", "information", "nu", "cost",
                "iterations", "window", "applies_from_seq", "late"):
        assert key in d
    rec.nu = float("nan")
    text = json.dumps(sanitise(rec.to_dict()), allow_nan=False)  # the shell's one converter
    assert json.loads(text)["nu"] is None and json.loads(text)["window"] == [1000, 1999]


# ------------------------------------------------------------------------------------------
# persistence
# ------------------------------------------------------------------------------------------
def test_save_and_load_round_trip_atomically(tmp_path, cfg, model):
    names = model.geometry.angle_names
    rng = np.random.default_rng(6)
    A = rng.normal(size=(14, 14))
    st = PosteriorState(names, rng.normal(size=14) * DEG, A @ A.T * 1e-6 + np.eye(14) * 1e-8,
                        applies_from_seq=1234, t=17.5)
    path = tmp_path / "state" / "angles.json"
    with pytest.raises(FileNotFoundError):  # no folder is created for it
        save_posterior(path, st)
    assert not path.parent.exists()
    path.parent.mkdir()
    save_posterior(path, st)
    back = load_posterior(path, names)
    np.testing.assert_array_equal(back.theta, st.theta)
    np.testing.assert_array_equal(back.P, st.P)
    assert (back.applies_from_seq, back.t, back.names) == (1234, 17.5, names)
    assert os.listdir(path.parent) == ["angles.json"]  # no temporary left behind
    post = _post(cfg, model)
    post.restore(back)
    np.testing.assert_array_equal(post.theta, st.theta)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: "{not json", "not readable JSON"),
    (lambda d: json.dumps({**d, "format": "x"}), "not a posterior"),
    (lambda d: json.dumps({**d, "version": 7}), "version"),
    (lambda d: json.dumps({k: v for k, v in d.items() if k != "P"}), "missing"),
    (lambda d: json.dumps({**d, "theta": d["theta"][:3]}), "shapes"),
    (lambda d: json.dumps({**d, "theta": [float("nan")] * 14}), "non-finite"),
    (lambda d: json.dumps({**d, "P": (np.triu(np.ones((14, 14)))).tolist()}), "symmetric"),
    (lambda d: json.dumps({**d, "P": (-np.eye(14)).tolist()}), "positive definite"),
    (lambda d: json.dumps({**d, "names": ["a"] * 14}), "differ"),
    (lambda d: json.dumps({**d, "applies_from_seq": "soon"}), "applies_from_seq"),
])
def test_a_corrupt_posterior_file_is_refused_clearly(tmp_path, model, mutate, message):
    names = model.geometry.angle_names
    good = PosteriorState(names, np.zeros(14), np.eye(14) * 1e-4).to_dict()
    path = tmp_path / "angles.json"
    path.write_text(mutate(good))
    with pytest.raises(PosteriorFileError, match=message) as exc:
        load_posterior(path, names)
    assert str(path) in str(exc.value)


def test_missing_posterior_file_is_refused(tmp_path):
    with pytest.raises(PosteriorFileError, match="no such file"):
        load_posterior(tmp_path / "nope.json")


# ------------------------------------------------------------------------------------------
# periodic runs on synthetic data
# ------------------------------------------------------------------------------------------
def _ground(cfg, model, seed, sweeps, step=False):
    rng = np.random.default_rng(seed)
    alpha = rng.uniform(-4, 4, 14) * DEG
    jump = 1 * DEG * rng.choice([-1, 1], 14)
    run = static_run(cfg, alpha, rng, sweeps=sweeps, step=jump if step else None,
                     step_time_s=sweeps * 30.0)
    z = inertial_loads(model, run.accel)
    cf = ContentFilter("static", cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       cfg.filter.harmonics, 19)
    X = cf.process(np.hstack([z, run.T, run.H_m]))
    start = alpha + 0.5 * DEG * rng.choice([-1, 1], 14)
    return run, X, cf.settle_samples, start


def _runner(cfg, model, post, mode, content, content_settle, design=None):
    idc, fs = cfg.identification, cfg.sample_rate_hz
    tau = design.slowest_time_constant_s if design is not None else cfg.filter.time_constant_s
    return PeriodicIdentification(
        model, post, mode, content, fs, idc.moment_floor_Nm, idc.max_iterations,
        int(round(idc.apply_delay_s * fs)), tau, settle_time_constants=idc.settle_time_constants,
        content_settle_samples=content_settle, gap_samples=int(round(idc.gap_s * fs)),
        design=design)


def _windows(cfg, n):
    W = int(round(cfg.identification.window_s * cfg.sample_rate_hz))
    return [(k * W, (k + 1) * W) for k in range(n // W)]


@pytest.mark.parametrize("seed", [700, 701, 702, 703])
def test_periodic_windows_converge_to_the_batch_result(cfg, model, seed):
    """Two sweeps of the six static conditions as 5-s windows against one batch run on the
    same data and prior, from the cold start of the issue (true angles up to 4° from the
    starting 0, σ 5°).

    Known-load runs re-solve the exact likelihood of every window since the last fold
    (docs/identification.md "Findings that bear on the spec", Re-linearisation), and windows not identifiable on their own
    are held for the next run, so with the default ``min_information`` the sequential
    posterior is the batch one too: the joint χ² of the difference against the batch
    covariance ≤ 36.1, and against the truth ≤ 36.1. (Without re-linearisation — the plain
    Gaussian summaries of model §7.4 — the first one-condition windows are summarised 4° from the
    truth and 11 of 288 runs over 12 seeds were rejected `inconsistent` with constant
    angles: docs/identification.md.)"""
    run, X, settle, _ = _ground(cfg, model, seed, sweeps=2)
    start = np.zeros(14)
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    P0 = np.eye(14) * cfg.identification.prior_sigma_rad**2
    batch = levenberg_marquardt(
        KnownLoadProblem(par, X[:, :6], X[:, 6:13], X[:, 13:],
                         scored=np.arange(len(X)) >= settle), start, P0, max_iterations=30)
    assert batch.status == "converged"
    e = batch.theta - run.alpha[-1]
    assert e @ np.linalg.solve(batch.P, e) <= 36.1
    for min_information in (1e-9, cfg.identification.min_information):
        post = _post(cfg, model, theta0=start, min_information=min_information)
        runner = _runner(cfg, model, post, "known_loads", "static", settle)
        recs = [runner.run_window(X[a:b, :6], X[a:b, 6:13], X[a:b, 13:], seq0=a)
                for a, b in _windows(cfg, len(X))]
        reasons = [r.reason for r in recs]
        assert "reset" not in reasons and "inconsistent" not in reasons, reasons
        assert reasons.count(None) >= 10
        e = post.theta - run.alpha[-1]
        assert e @ np.linalg.solve(post.P, e) <= 36.1
        d = post.theta - batch.theta
        assert d @ np.linalg.solve(batch.P, d) <= 36.1, (min_information, reasons)
        assert np.all(np.sqrt(np.diag(post.P)) <= 1.5 * np.sqrt(np.diag(batch.P)))


def test_accumulated_moments_are_the_likelihood_of_the_joined_windows(cfg, model):
    """Re-linearisation rests on V being a function of the moments G = Σ x xᵀ: the problem
    of window 2 with window 1's moments has the cost, gradient and information of the two
    windows as one (no log-det term, W the same for every sample)."""
    run, X, settle, start = _ground(cfg, model, 704, sweeps=1)
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    W = 1000
    a, b = slice(0, W), slice(W, 2 * W)
    one = KnownLoadProblem(par, X[a, :6], X[a, 6:13], X[a, 13:])
    two = KnownLoadProblem(par, X[b, :6], X[b, 6:13], X[b, 13:])
    both = KnownLoadProblem(par, X[:2 * W, :6], X[:2 * W, 6:13], X[:2 * W, 13:])
    joined = two.with_moments(one.G, one.n_scored)
    th = start + 0.3 * DEG
    e1, e2 = joined.evaluate(th), both.evaluate(th)
    assert joined.n_scored == both.n_scored == 2 * W
    np.testing.assert_allclose(e1.cost, e2.cost, rtol=1e-10)
    np.testing.assert_allclose(e1.gradient, e2.gradient, rtol=1e-8, atol=1e-12 * abs(e2.cost))
    np.testing.assert_allclose(e1.information, e2.information, rtol=1e-8)
    # the earlier window's information, for the coloured-residual bound
    np.testing.assert_allclose(joined.uncorrelated_information(th),
                               one.evaluate(th).information, rtol=1e-8)
    assert joined.residual_series(th)[0].shape == (W, 6)  # the new window's series


def test_held_and_accumulated_windows_make_the_batch_posterior(cfg, model):
    """A window not identifiable on its own is held and counted with the next one, and every
    accepted window's moments are re-solved with the next: after [weak, strong, strong] the
    posterior is the batch posterior of the three windows from the first prior."""
    run, X, settle, start = _ground(cfg, model, 705, sweeps=1)
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    W = int(round(cfg.identification.window_s * cfg.sample_rate_hz))
    post = _post(cfg, model, theta0=start)
    runner = _runner(cfg, model, post, "known_loads", "static", 0)
    # window 0: loads scaled to 0.1 % (information ×1e-6) and judged against a raised
    # min_information, so it is held whatever its exact information ratio
    k = 1e-3
    post.min_information = 1e12
    recs = [runner.run_window(k * X[:W, :6], k * X[:W, 6:13], k * X[:W, 13:], seq0=0)]
    assert recs[0].reason == "not_identifiable" and post.moments.windows_held == 1
    post.min_information = cfg.identification.min_information
    for j in (1, 2):
        sl = slice(j * W, (j + 1) * W)
        recs.append(runner.run_window(X[sl, :6], X[sl, 6:13], X[sl, 13:], seq0=j * W))
    assert [r.reason for r in recs[1:]] == [None, None], [r.reason for r in recs]
    assert post.moments.windows_held == 0
    Xb = np.vstack([k * X[:W], X[W:3 * W]])
    batch = levenberg_marquardt(KnownLoadProblem(par, Xb[:, :6], Xb[:, 6:13], Xb[:, 13:]),
                                start, post.P0, max_iterations=30)
    assert batch.status == "converged"
    d = post.theta - batch.theta
    assert d @ np.linalg.solve(batch.P, d) <= 1e-3
    L = np.linalg.cholesky(batch.P)
    Li = np.linalg.inv(L)
    lam = np.linalg.eigvalsh(Li @ post.P @ Li.T)  # 1 in every direction when equal
    assert np.all(np.abs(lam - 1) < 0.02), lam
    # a reset forgets the accumulation and starts again from the first prior's covariance
    post.P = post.P0.copy()
    post.fold()
    assert post.moments.G_acc is None and post.moments.G_held is None
    np.testing.assert_allclose(post.anchor_prior(0.0)[1], post.P0)


def test_one_window_leaves_the_unseen_directions_at_their_prior(cfg, model):
    """One 5-s window at the first load level (thrust only). The directions it cannot see are
    found independently — noise-free regressors from the synthetic truth and finite
    differences of its own S — and keep ≥ 90 % of their prior σ in the posterior."""
    run, X, settle, start = _ground(cfg, model, 703, sweeps=1)
    post = _post(cfg, model, theta0=start)
    runner = _runner(cfg, model, post, "known_loads", "static", settle)
    W = int(round(cfg.identification.window_s * cfg.sample_rate_hz))
    rec = runner.run_window(X[:W, :6], X[:W, 6:13], X[:W, 13:], seq0=0)
    assert rec.accepted, rec.reason
    # independent information of that window about the true angles
    geo = TruthGeometry(cfg)
    cf = ContentFilter("static", cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       cfg.filter.harmonics, 7)
    Tf = cf.process(run.T_true)[settle:W]
    a = run.alpha[0]
    Winv = np.linalg.inv(measurement_covariance(model, a, cfg.identification.moment_floor_Nm,
                                                known_loads=True))
    D = np.empty((len(Tf), 6, 14))
    for j in range(14):
        ap, am = a.copy(), a.copy()
        ap[j] += 1e-6
        am[j] -= 1e-6
        D[:, :, j] = Tf @ ((geo.S(ap) - geo.S(am)) / 2e-6).T
    M_true = np.einsum("nai,ab,nbj->ij", D, Winv, D)
    L = np.linalg.cholesky(post.P0)
    lam, V = np.linalg.eigh(L.T @ M_true @ L)
    Li = np.linalg.inv(L)
    ratio = np.sqrt(np.einsum("ik,ij,jk->k", V, Li @ post.P @ Li.T, V))  # σ_post / σ_prior
    unseen = lam < 0.2  # the window alone would shrink σ by less than 9 %
    assert unseen.sum() >= 2 and (lam > 1e3).sum() >= 3  # one load level: some of each
    assert np.all(ratio[unseen] >= 0.9), ratio
    # and every direction as much as the independent information says (1/√(1+λ))
    np.testing.assert_allclose(ratio, 1 / np.sqrt(1 + lam), rtol=0.2, atol=0.01)


@pytest.mark.parametrize("seed", [500, 501])
def test_an_angle_step_is_detected_and_learned_again(cfg, model, seed):
    """A4: four sweeps, true angles step 1° (random sign each) half-way. The step is detected
    (reset) within a sweep and the joint χ² against the new truth is back under 36.1 within
    two further sweeps and stays there. (A reset can also happen in the first sweep while the
    posterior is still forming — seed 500 has one, 1 run in 8 measured — and costs nothing:
    the posterior is learned again.)"""
    run, X, settle, start = _ground(cfg, model, seed, sweeps=4, step=True)
    post = _post(cfg, model, theta0=start)
    runner = _runner(cfg, model, post, "known_loads", "static", settle)
    wins = _windows(cfg, len(X))
    k_step = len(wins) // 2
    reasons, chis = [], []
    for a, b in wins:
        rec = runner.run_window(X[a:b, :6], X[a:b, 6:13], X[a:b, 13:], seq0=a)
        reasons.append(rec.reason)
        e = rec.alpha - run.alpha[b - 1]
        chis.append(e @ np.linalg.solve(rec.P, e))
    assert chis[k_step - 1] <= 36.1  # learned before the step
    assert "reset" not in reasons[12:k_step]  # no false alarm once the posterior has formed
    after = [k for k in range(k_step, len(reasons)) if reasons[k] == "reset"]
    assert after and after[0] < k_step + 12  # detected within a sweep
    ok = [k for k in range(after[0], len(chis)) if all(c <= 36.1 for c in chis[k:])]
    assert ok and ok[0] <= k_step + 24  # back within two further sweeps


# ------------------------------------------------------------------------------------------
# the report's Phase II set-up (loads unknown, two harmonics, no inertia): A5
# ------------------------------------------------------------------------------------------
def _calibration_design(cfg, model):
    return design_filter(model, harmonics=tuple(cfg.filter.harmonics),
                         omega=cfg.rotor.omega_nominal_rad_s, dt=cfg.sample_period_s,
                         tuning=cfg.filter.tuning, time_constant_s=cfg.filter.time_constant_s,
                         low_frequency=False, psd=cfg.filter.process_noise_psd,
                         alpha=cfg.identification.initial_angles_rad,
                         moment_floor=cfg.identification.moment_floor_Nm, frame=cfg.hub_frame)


@pytest.mark.parametrize("seed", [1201, 1202])
def test_paper_setup_with_noise_is_never_identifiable(cfg, model, seed):
    design = _calibration_design(cfg, model)
    rng = np.random.default_rng(seed)
    run, _, _ = paper_run(cfg, rng, duration_s=60.0)
    z = inertial_loads(model, run.accel)
    cf = ContentFilter(cfg.identification.content_filter_error, cfg.sample_rate_hz,
                       cfg.rotor.omega_nominal_rad_s, cfg.filter.harmonics, 13)
    X = cf.process(np.hstack([z, run.T]))
    start = np.full(14, 4 * DEG)  # the scenario starts the service at 4°
    post = _post(cfg, model, theta0=start)
    P0 = post.P.copy()
    runner = _runner(cfg, model, post, "filter_error", "harmonics", cf.settle_samples, design)
    infos = []
    for a, b in _windows(cfg, len(X)):
        rec = runner.run_window(X[a:b, :6], X[a:b, 6:], seq0=a)
        assert rec.reason == "not_identifiable", (a, rec.reason, rec.information)
        infos.append(rec.information)
        np.testing.assert_array_equal(rec.alpha, start)
    np.testing.assert_array_equal(post.P, P0)
    assert max(infos) < 0.5  # about 0.09 once settled (model §7: "about 0.12")


def test_paper_setup_noise_free_from_the_true_initial_state(cfg, model):
    """What the report's simulation did: noise-free, the calibration filter started in the
    simulator's own initial state, no prior. Then e(θ_true) ≡ 0 and ML recovers the angles
    exactly from the 4° start — even scoring only after the 5τ settling. With the filter
    started anywhere else (zero), or with the σ = 5° prior and settling, it does not."""
    design = _calibration_design(cfg, model)
    rng = np.random.default_rng(1201)
    run, coef, orders = paper_run(cfg, rng, duration_s=5.0, noise=False)
    z = inertial_loads(model, run.accel)
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=False)
    ns = design.Phi.shape[0]
    x0 = harmonic_state(design, coef, cfg.rotor.omega_nominal_rad_s, orders)
    true_start = FilterErrorState(np.linalg.solve(design.Phi, x0), np.zeros((ns, 14)),
                                  np.zeros(14))
    settle = int(np.ceil(cfg.identification.settle_time_constants
                         * design.slowest_time_constant_s * cfg.sample_rate_hz))
    th0 = np.full(14, 4 * DEG)

    def problem(state, settle_n):
        return FilterErrorProblem(par, design.Phi, design.K, design.J, design.Qd, z, run.T,
                                  state=state, settle=settle_n, discontinuity=settle_n > 0)

    e, _, _ = problem(true_start, 0).innovations(np.zeros(14), derivatives=False)
    assert np.abs(e).max() < 1e-6 * np.abs(run.T).max()  # the filter sits on the truth
    for s in (0, settle):
        res = levenberg_marquardt(problem(true_start, s), th0, None, max_iterations=50)
        assert res.status == "converged" and np.abs(res.theta).max() < 1e-3 * DEG
    # with the prior and the settling the window carries almost no information
    P0 = np.eye(14) * cfg.identification.prior_sigma_rad**2
    res = levenberg_marquardt(problem(true_start, settle), th0, P0)
    assert information_ratio(P0, res.information) < 0.01
    # started in the zero state (never the truth in practice) it wanders off
    res = levenberg_marquardt(problem(None, settle), th0, None, max_iterations=50)
    assert np.abs(res.theta).max() > 10 * DEG
