"""Maximum-likelihood identification (model.md §7): derivatives, the two residual modes,
Levenberg–Marquardt, Cramér–Rao bounds, and the Monte Carlo decisions of performance.md A3."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from rsra.estimator.balance import inertial_loads, measurement_covariance
from rsra.estimator.content import ContentFilter
from rsra.estimator.filters import design_filter
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.identification import (
    FilterErrorProblem,
    FilterErrorState,
    KnownLoadProblem,
    Parameterisation,
    coloured_residual_information,
    innovation_covariance,
    levenberg_marquardt,
    relaxation_estimate,
    residual_autocorrelation,
    scored_mask,
)
from synthetic import (
    GROUND_TEST_CONDITIONS,
    TruthGeometry,
    decisions,
    paper_run,
    small_design,
    static_run,
)

DEG = np.pi / 180


def _static_content(cfg, run, model):
    """z, T, H_m through the project's `static` content filter (one causal filter for all)."""
    z = inertial_loads(model, run.accel)
    cf = ContentFilter("static", cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       cfg.filter.harmonics, 19)
    X = cf.process(np.hstack([z, run.T, run.H_m]))
    return X[:, :6], X[:, 6:13], X[:, 13:], cf.settle_samples


def _known_load_problem(cfg, model, seed=3, condition_s=2.0, names=None):
    rng = np.random.default_rng(seed)
    alpha = rng.uniform(-4, 4, 14) * DEG
    run = static_run(cfg, alpha, rng, sweeps=1, condition_s=condition_s, ramp_s=0.2)
    z = inertial_loads(model, run.accel)
    par = Parameterisation(model, names, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    return KnownLoadProblem(par, z, run.T, run.H_m), alpha


def _calibration_design(cfg, model):
    return design_filter(model, harmonics=tuple(cfg.filter.harmonics),
                         omega=cfg.rotor.omega_nominal_rad_s, dt=cfg.sample_period_s,
                         tuning=cfg.filter.tuning, time_constant_s=cfg.filter.time_constant_s,
                         low_frequency=False, psd=cfg.filter.process_noise_psd,
                         alpha=cfg.identification.initial_angles_rad,
                         moment_floor=cfg.identification.moment_floor_Nm, frame=cfg.hub_frame)


# ------------------------------------------------------------------------------------------
# the synthetic truth is independent of estimator.geometry — and agrees with it
# ------------------------------------------------------------------------------------------
def test_synthetic_truth_agrees_with_estimator_geometry(cfg, model):
    geo = TruthGeometry(cfg)
    a = np.random.default_rng(0).uniform(-0.1, 0.1, 14)
    np.testing.assert_allclose(geo.S(a), wrench_matrix(model.geometry, a), atol=1e-12)
    for frame in ("body", "shaft"):
        np.testing.assert_allclose(geo.R(frame), hub_transfer_matrix(model.geometry, frame),
                                   atol=1e-12)


def test_synthetic_balance_holds_and_split_is_minimum_norm(cfg, model):
    rng = np.random.default_rng(1)
    a = rng.uniform(-4, 4, 14) * DEG
    run = static_run(cfg, a, rng, sweeps=1, condition_s=1.0, noise=False)
    S, R = TruthGeometry(cfg).S(a), TruthGeometry(cfg).R("body")
    np.testing.assert_allclose(run.T_true @ S.T + run.H @ R.T, run.I, atol=1e-6)
    # minimum strain energy with equal stiffness: T lies in the row space of S
    null = scipy.linalg.null_space(S)
    assert np.abs(run.T_true @ null).max() < 1e-6


# ------------------------------------------------------------------------------------------
# analytic derivatives against finite differences
# ------------------------------------------------------------------------------------------
def test_dW_dalpha_matches_finite_differences(cfg, model):
    par = Parameterisation(model, moment_floor=100.0, known_loads=True)
    th = np.random.default_rng(2).uniform(-3, 3, 14) * DEG
    t = par.terms(th)
    h = 1e-6
    for j in range(14):
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        fd = (measurement_covariance(model, tp, 100.0, True)
              - measurement_covariance(model, tm, 100.0, True)) / (2 * h)
        np.testing.assert_allclose(t.dW[j], fd, rtol=1e-6, atol=1e-6 * np.abs(t.W).max())


def test_known_load_gradient_and_information_vs_finite_differences(cfg, model):
    prob, alpha = _known_load_problem(cfg, model)
    th = alpha + np.random.default_rng(4).uniform(-2, 2, 14) * DEG  # residuals well above noise
    ev = prob.evaluate(th)
    h = 1e-7
    g_fd = np.empty(14)
    de_fd = []
    for j in range(14):
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        g_fd[j] = (prob.evaluate(tp, False).cost - prob.evaluate(tm, False).cost) / (2 * h)
        de_fd.append((prob.residual_series(tp)[0] - prob.residual_series(tm)[0]) / (2 * h))
    np.testing.assert_allclose(ev.gradient, g_fd, rtol=1e-5, atol=1e-6 * np.abs(g_fd).max())
    de_fd = np.stack(de_fd, axis=2)
    e, de, W = prob.residual_series(th)
    np.testing.assert_allclose(de, de_fd, rtol=1e-5, atol=1e-6 * np.abs(de).max())
    M_fd = np.einsum("nai,ab,nbj->ij", de_fd, np.linalg.inv(W), de_fd)
    np.testing.assert_allclose(ev.information, M_fd, rtol=1e-5)
    # the ∂W terms matter: dropping them changes the gradient
    g_fixed = prob.evaluate(th, fixed_weight=W).gradient
    assert np.abs(g_fixed - ev.gradient).max() > 1e-3 * np.abs(ev.gradient).max()


@pytest.mark.parametrize("which", ["small", "project"])
def test_filter_error_sensitivities_and_gradient_vs_finite_differences(cfg, model, which):
    d = small_design(cfg) if which == "small" else _calibration_design(cfg, model)
    rng = np.random.default_rng(5)
    run, _, _ = paper_run(cfg, rng, duration_s=1.5, alpha_true=rng.uniform(-2, 2, 14) * DEG)
    z = inertial_loads(model, run.accel)
    par = Parameterisation(model, moment_floor=100.0, known_loads=False)
    th = rng.uniform(-3, 3, 14) * DEG
    ns = d.Phi.shape[0]
    # a continued state: x and ∂x/∂θ from a previous window, referred to another θ
    state = FilterErrorState(rng.normal(0, 1e3, ns), rng.normal(0, 1e4, (ns, 14)),
                             th + 0.01)
    valid = np.ones(len(z), bool)
    valid[100:105] = False
    prob = FilterErrorProblem(par, d.Phi, d.K, d.J, d.Qd, z, run.T, valid=valid, settle=20,
                              state=state, discontinuity=True)
    e, de, _ = prob.innovations(th)
    ev = prob.evaluate(th)
    h = 1e-7
    g_fd = np.empty(14)
    for j in range(14):
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        ep, _, _ = prob.innovations(tp, derivatives=False)
        em, _, _ = prob.innovations(tm, derivatives=False)
        fd = (ep - em) / (2 * h)
        np.testing.assert_allclose(de[:, :, j], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
        g_fd[j] = (prob.evaluate(tp, False).cost - prob.evaluate(tm, False).cost) / (2 * h)
    np.testing.assert_allclose(ev.gradient, g_fd, rtol=1e-5, atol=1e-6 * np.abs(g_fd).max())
    # ∂B/∂θ (Lyapunov sensitivities) against finite differences of B(θ)
    t = par.terms(th)
    B, dB = innovation_covariance(d.Phi, d.K, d.J, d.Qd, t.W, t.dW)
    for j in (0, 9, 13):
        tp, tm = th.copy(), th.copy()
        tp[j] += 1e-4  # B is solved to ~1e-12 relative: a larger step keeps rounding out
        tm[j] -= 1e-4
        Bp, _ = innovation_covariance(d.Phi, d.K, d.J, d.Qd, par.terms(tp).W)
        Bm, _ = innovation_covariance(d.Phi, d.K, d.J, d.Qd, par.terms(tm).W)
        np.testing.assert_allclose(dB[j], (Bp - Bm) / 2e-4, rtol=1e-5,
                                   atol=1e-6 * np.abs(dB[j]).max())


def test_innovation_covariance_is_the_filters_own_at_the_design_angles(cfg, model):
    d = _calibration_design(cfg, model)
    W = measurement_covariance(model, cfg.identification.initial_angles_rad,
                               cfg.identification.moment_floor_Nm)
    B, _ = innovation_covariance(d.Phi, d.K, d.J, d.Qd, W)
    np.testing.assert_allclose(B, d.B, rtol=1e-8, atol=1e-10 * np.abs(d.B).max())


def test_batch_modal_equals_per_sample_loop_and_lyapunov_eigenbasis(cfg, model):
    for tuning in ("time_constant", "noise"):
        d = design_filter(model, harmonics=tuple(cfg.filter.harmonics),
                          omega=cfg.rotor.omega_nominal_rad_s, dt=cfg.sample_period_s,
                          tuning=tuning, low_frequency=False,
                          moment_floor=cfg.identification.moment_floor_Nm)
        rng = np.random.default_rng(6)
        run, _, _ = paper_run(cfg, rng, duration_s=3.0)
        z = inertial_loads(model, run.accel)
        valid = np.ones(len(z), bool)
        valid[50:53] = False
        valid[300:420] = False  # a gap longer than `gap`: the filter settles after it
        par = Parameterisation(model, moment_floor=100.0, known_loads=False)
        th = rng.uniform(-2, 2, 14) * DEG
        out = {}
        for method in ("loop", "modal"):
            prob = FilterErrorProblem(par, d.Phi, d.K, d.J, d.Qd, z, run.T, valid=valid,
                                      settle=40, gap=100, method=method)
            assert prob.method == method
            out[method] = (prob.evaluate(th), prob.innovations(th))
        a, b = out["loop"], out["modal"]
        np.testing.assert_allclose(a[1][0], b[1][0], atol=1e-9 * np.abs(a[1][0]).max())
        np.testing.assert_allclose(a[1][1], b[1][1], atol=1e-9 * np.abs(a[1][1]).max())
        np.testing.assert_allclose(a[0].gradient, b[0].gradient, rtol=1e-9)
        np.testing.assert_allclose(a[0].end_state.x, b[0].end_state.x, rtol=1e-9, atol=1e-6)
        t = par.terms(th)
        B0, dB0 = innovation_covariance(d.Phi, d.K, d.J, d.Qd, t.W, t.dW)
        B1, dB1 = prob._innovation_covariance(t.W, t.dW)
        np.testing.assert_allclose(B1, B0, rtol=1e-8, atol=1e-12 * np.abs(B0).max())
        np.testing.assert_allclose(dB1, dB0, rtol=1e-8, atol=1e-10 * np.abs(dB0).max())


def test_state_and_sensitivities_continue_across_windows(cfg, model):
    """Two windows chained through FilterErrorState equal one long run at the same θ, and the
    carried sensitivities make the second window's ∂e exact (finite differences of the whole)."""
    d = small_design(cfg)
    rng = np.random.default_rng(7)
    run, _, _ = paper_run(cfg, rng, duration_s=2.0, alpha_true=rng.uniform(-1, 1, 14) * DEG)
    z = inertial_loads(model, run.accel)
    par = Parameterisation(model, moment_floor=100.0, known_loads=False)
    th = rng.uniform(-2, 2, 14) * DEG
    k = 150
    whole = FilterErrorProblem(par, d.Phi, d.K, d.J, d.Qd, z, run.T)
    e_all, de_all, _ = whole.innovations(th)
    first = FilterErrorProblem(par, d.Phi, d.K, d.J, d.Qd, z[:k], run.T[:k])
    ev1 = first.evaluate(th)
    second = FilterErrorProblem(par, d.Phi, d.K, d.J, d.Qd, z[k:], run.T[k:],
                                state=ev1.end_state)
    e2, de2, _ = second.innovations(th)
    np.testing.assert_allclose(e2, e_all[k:], atol=1e-8 * np.abs(e_all).max())
    np.testing.assert_allclose(de2, de_all[k:], atol=1e-8 * np.abs(de_all).max())
    # at another θ the carried state is extrapolated to first order: the error is O(Δθ²)
    th2 = th + 0.2 * DEG
    e_all2, _, _ = whole.innovations(th2, derivatives=False)
    e22, _, _ = second.innovations(th2, derivatives=False)
    lin_err = np.abs(e22 - e_all2[k:]).max()
    first_order = np.abs(de2 @ (th2 - th)).max()
    assert lin_err < 0.05 * first_order


def test_scored_mask_settles_after_start_and_long_gaps():
    valid = np.ones(100, bool)
    valid[30:33] = False  # short gap: no settle
    valid[60:75] = False  # long gap: settle 5 after it
    s = scored_mask(valid, settle=5, gap=10, start_discontinuity=True)
    assert not s[:5].any() and s[5:30].all()
    assert not s[30:33].any() and s[33:60].all()
    assert not s[60:80].any() and s[80:].all()


def test_coloured_residual_information_equals_the_direct_double_sum():
    rng = np.random.default_rng(8)
    N, p, L = 300, 3, 12
    e = np.cumsum(rng.normal(size=(N, 6)), axis=0) * 0.1 + rng.normal(size=(N, 6))
    e -= e.mean(axis=0)
    de = rng.normal(size=(N, 6, p))
    A = rng.normal(size=(6, 6))
    W = A @ A.T + 6 * np.eye(6)
    Q, lag = coloured_residual_information(e, de, W, L)
    R = residual_autocorrelation(e, L)
    Wi = np.linalg.inv(W)
    G = Wi @ de

    def gamma(k):  # E[e_n e_{n+k}ᵀ] estimated, k of either sign
        return R[k] if k >= 0 else R[-k].T

    # Var(Σ G_iᵀ e_i) = Σ_i Σ_j G_iᵀ E[e_i e_jᵀ] G_j, lags up to the first zero crossing
    Q_direct = np.zeros((p, p))
    for i in range(N):
        for j in range(max(0, i - lag), min(N, i + lag + 1)):
            Q_direct += G[i].T @ gamma(j - i) @ G[j]
    np.testing.assert_allclose(Q, Q_direct, rtol=1e-9)
    # R(k) by FFT equals the plain sum
    np.testing.assert_allclose(R[3], e[:-3].T @ e[3:] / N, rtol=1e-10)


def test_white_residuals_leave_the_bound_unchanged():
    rng = np.random.default_rng(9)
    N, p = 20000, 4
    W = np.diag([4.0, 1.0, 9.0, 1.0, 2.0, 1.0])
    e = rng.normal(size=(N, 6)) * np.sqrt(np.diag(W))
    de = rng.normal(size=(N, 6, p))
    M = np.einsum("nai,ab,nbj->ij", de, np.linalg.inv(W), de)
    Q, lag = coloured_residual_information(e, de, W, 50)
    assert lag <= 3  # the whitened autocorrelation crosses zero at once
    np.testing.assert_allclose(np.diag(Q) / np.diag(M), 1.0, atol=0.05)


# ------------------------------------------------------------------------------------------
# parameters other than angles (checked finite differences) and subsets
# ------------------------------------------------------------------------------------------
def test_non_angle_parameters_have_checked_derivatives(cfg, model):
    names = ("delta_A", "psi_F", "x_A", "z_C", "hub_x", "m_z", "I_yy")
    prob, alpha = _known_load_problem(cfg, model, names=names)
    par = prob.par
    th = par.initial() + np.array([1 * DEG, -1 * DEG, 0.01, -0.01, 0.005, 20.0, 5.0])
    assert par.check_derivatives(th) < 1e-6
    ev = prob.evaluate(th)
    g_fd = np.empty(len(names))
    for j in range(len(names)):
        h = 1e-4 * max(1.0, abs(th[j]))
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        g_fd[j] = (prob.evaluate(tp, False).cost - prob.evaluate(tm, False).cost) / (2 * h)
    np.testing.assert_allclose(ev.gradient, g_fd, rtol=1e-4)


def test_a_cell_position_and_a_mass_are_identified(cfg, model):
    """Truth with cell A 3 cm further forward and m_z 60 kg heavier; the estimator starts at
    the configured values and identifies [angles, x_A, m_z] with priors 5 cm and 200 kg."""
    cells = list(cfg.cells)
    cells[0] = dataclasses.replace(cells[0], position_m=cells[0].position_m + [0.03, 0, 0])
    mass = np.asarray(cfg.effective_mass_kg, float) + [0, 0, 60.0]
    true_cfg = dataclasses.replace(cfg, cells=tuple(cells), effective_mass_kg=mass)
    rng = np.random.default_rng(10)
    alpha = rng.uniform(-2, 2, 14) * DEG
    run = static_run(true_cfg, alpha, rng, sweeps=2)
    z, T, H, settle = _static_content(cfg, run, model)  # z with the configured masses
    names = model.geometry.angle_names + ("x_A", "m_z")
    par = Parameterisation(model, names, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    scored = np.arange(len(z)) >= settle
    prob = KnownLoadProblem(par, z, T, H, scored=scored)
    th0 = par.initial()
    P0 = np.diag([5 * DEG] * 14 + [0.05, 200.0]) ** 2
    res = levenberg_marquardt(prob, th0, P0)
    assert res.status == "converged"
    truth = np.concatenate([alpha, [cells[0].position_m[0], mass[2]]])
    err = res.theta - truth
    assert err @ np.linalg.solve(res.P, err) <= 36.1
    assert res.sigma_cr[14] < 0.01 and res.sigma_cr[15] < 20.0  # well determined


def test_angle_subset_leaves_the_others_at_their_base_values(cfg, model):
    rng = np.random.default_rng(11)
    alpha = rng.uniform(-3, 3, 14) * DEG
    run = static_run(cfg, alpha, rng, sweeps=1)
    z, T, H, settle = _static_content(cfg, run, model)
    names = ("delta_E", "psi_E", "theta_G")
    base = alpha.copy()
    base[[8, 9, 12]] = 0.0  # the other angles known exactly
    par = Parameterisation(model, names, base, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    prob = KnownLoadProblem(par, z, T, H, scored=np.arange(len(z)) >= settle)
    res = levenberg_marquardt(prob, np.zeros(3), np.eye(3) * (5 * DEG) ** 2)
    err = res.theta - alpha[[8, 9, 12]]
    assert res.status == "converged" and err @ np.linalg.solve(res.P, err) <= 16.3  # χ²₃
    np.testing.assert_allclose(par.alpha(res.theta)[[0, 1, 13]], base[[0, 1, 13]])


# ------------------------------------------------------------------------------------------
# Levenberg–Marquardt behaviour
# ------------------------------------------------------------------------------------------
def test_lm_never_raises_J_and_reports_not_converged_and_diverged(cfg, model):
    prob, alpha = _known_load_problem(cfg, model, condition_s=3.0)
    th0, P0 = np.full(14, 4 * DEG), np.eye(14) * (5 * DEG) ** 2
    res = levenberg_marquardt(prob, th0, P0)
    assert res.status == "converged" and res.sound
    assert np.all(np.diff(res.history) <= 0)  # every accepted step lowers J
    assert res.iterations <= 10
    short = levenberg_marquardt(prob, th0, P0, max_iterations=1)
    assert short.status == "not_converged" and not short.sound
    # non-finite data: diverged, never a number
    z = prob._x[:, :6].copy()
    z[10, 2] = np.nan
    bad = KnownLoadProblem(prob.par, z, prob._x[:, 6:13], prob._x[:, 13:19])
    res_bad = levenberg_marquardt(bad, th0, P0)
    assert res_bad.status == "diverged" and not res_bad.sound


def test_warm_start_reaches_the_same_minimum_as_the_literal_lm(cfg, model):
    """The frozen-weight warm start only changes the path: from a 4° start the literal LM
    (no warm start, many iterations) and the warm-started one end at the same minimum."""
    prob, alpha = _known_load_problem(cfg, model, condition_s=3.0)
    th0, P0 = np.full(14, 4 * DEG), np.eye(14) * (5 * DEG) ** 2
    lit = levenberg_marquardt(prob, th0, P0, max_iterations=200, warm_start=False)
    warm = levenberg_marquardt(prob, th0, P0, max_iterations=200, warm_start=True)
    assert lit.status == warm.status == "converged"
    assert warm.cost == pytest.approx(lit.cost, rel=1e-4)
    d = warm.theta - lit.theta
    assert float(d @ np.linalg.solve(lit.P, d)) < 0.05  # far inside the posterior
    # the warm start needs fewer full-objective evaluations to get there
    assert warm.iterations <= lit.iterations


# ------------------------------------------------------------------------------------------
# A3: known loads, `static` content, two sweeps, from a 4° start — Monte Carlo
# ------------------------------------------------------------------------------------------
def _a3_seed(cfg, model, par, seed, max_lag=None):
    rng = np.random.default_rng(1000 + seed)
    alpha = rng.uniform(-4, 4, 14) * DEG
    run = static_run(cfg, alpha, rng, sweeps=2)
    z, T, H, settle = _static_content(cfg, run, model)
    prob = KnownLoadProblem(par, z, T, H, scored=np.arange(len(z)) >= settle)
    res = levenberg_marquardt(prob, np.full(14, 4 * DEG), np.eye(14) * (5 * DEG) ** 2,
                              max_lag=max_lag)
    return res, alpha


@pytest.mark.parametrize("n_seeds", [100])
def test_a3_known_load_static_two_sweeps_monte_carlo(cfg, model, n_seeds):
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    lag = int(5 * cfg.filter.time_constant_s * cfg.sample_rate_hz)
    errs, covs, sig, sigc, iters = [], [], [], [], []
    for seed in range(n_seeds):
        # the coloured-residual bound on every tenth seed (it costs as much as the fit)
        res, alpha = _a3_seed(cfg, model, par, seed, max_lag=lag if seed % 10 == 0 else None)
        assert res.status in ("converged", "not_converged") and np.isfinite(res.cost), seed
        errs.append(res.theta - alpha)
        covs.append(res.P)
        sig.append(res.sigma_cr)
        iters.append(res.iterations if res.status == "converged" else np.inf)
        if res.P_corrected is not None:
            sigc.append(res.sigma_cr_corrected / res.sigma_cr)
    # model §7's LM from a 4° start takes 5–8 iterations here, rarely more than the configured
    # 10 (measured: 1 seed in 100 needs 11) — a not_converged run would be rejected, not wrong
    assert np.mean(np.isfinite(iters)) >= 0.98
    dec = decisions(np.array(errs), np.array(covs))
    assert dec.chi2_limit == pytest.approx(48.7, abs=0.05)
    assert dec.z_limit == pytest.approx(3.97, abs=0.005)
    assert dec.passed, dec.summary()
    assert np.max(sig) <= 0.2 * DEG  # every σ_CR ≤ 0.2°
    ratio = np.array(sigc)
    # the static content leaves residuals correlated over ~0.3 s; with W the unfiltered
    # covariance the conventional bound is already right to within a few per cent
    assert np.all((ratio > 0.95) & (ratio < 1.3)), ratio


# ------------------------------------------------------------------------------------------
# The report's relaxation (W = (1/N) Σ e eᵀ, Gauss–Newton) against ours — model §7 conditions
# ------------------------------------------------------------------------------------------
def test_relaxation_is_biased_where_the_effective_variance_is_not(cfg, model):
    """Known loads, one static load level (vertical cells near 15 kN), shaker harmonics of
    1–8 kN and kN·m, broadband content, five seconds (model §7). 100 seeds, both estimators
    without a prior from the 4° start. The relaxation's errors are several times what its
    bounds claim, with a clear mean (bias); ours is unbiased within its spread."""
    n = 100
    ranges = [(1, np.full(6, 1e3), np.full(6, 8e3)), ("blades", np.full(6, 1e3), np.full(6, 8e3))]
    par = Parameterisation(model, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    ev_err, rx_err, rx_sig, ev_sig = [], [], [], []
    for seed in range(n):
        rng = np.random.default_rng(seed)
        alpha = rng.uniform(-4, 4, 14) * DEG
        run = static_run(cfg, alpha, rng, conditions=GROUND_TEST_CONDITIONS[:1], sweeps=1,
                         condition_s=5.0, ramp_s=0.0, shaker=ranges)
        prob = KnownLoadProblem(par, inertial_loads(model, run.accel), run.T, run.H_m)
        th0 = np.full(14, 4 * DEG)
        ours = levenberg_marquardt(prob, th0, None, max_iterations=50)
        assert ours.status == "converged"
        th_r, P_r, _ = relaxation_estimate(prob, th0)
        ev_err.append(ours.theta - alpha)
        ev_sig.append(ours.sigma_cr)
        rx_err.append(th_r - alpha)
        rx_sig.append(np.sqrt(np.diag(P_r)))
    ev_err, rx_err = np.array(ev_err), np.array(rx_err)
    se = lambda x: x.std(axis=0, ddof=1) / np.sqrt(n)  # noqa: E731
    # relaxation: bias detected at the Bonferroni level, errors ≫ claimed bounds
    assert np.max(np.abs(rx_err.mean(axis=0)) / se(rx_err)) > 3.97
    rms_rx = np.sqrt((rx_err**2).mean(axis=0))
    assert np.max(rms_rx / np.mean(rx_sig, axis=0)) > 3.0
    assert np.max(np.abs(rx_err.mean(axis=0))) > 1.5 * DEG
    # effective variance: the mean error of each angle is well inside its spread, and at most
    # a third of the relaxation's
    assert np.all(np.abs(ev_err.mean(axis=0)) < 0.5 * ev_err.std(axis=0, ddof=1))
    assert np.max(np.abs(ev_err.mean(axis=0))) < np.max(np.abs(rx_err.mean(axis=0))) / 3
