"""Hub-load dynamics, fixed-gain Kalman filter designs, the per-sample and batch paths
(model.md §5–§6, docs/performance.md A2). The synthetic data are generated here, independently
of the filter: hub loads of a static part plus harmonics with slowly varying amplitude,
translational accelerations, load cells from the exact balance, model §4 noise."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats
from scipy.integrate import quad

from rsra.config.rig import load_config
from rsra.estimator.balance import inertial_loads, static_estimate
from rsra.estimator.dynamics import component_states, hub_load_dynamics, low_frequency_states
from rsra.estimator.filters import (
    INVALID,
    LOST_BEFORE,
    PREDICT_ONLY,
    ROTOR_STOPPED,
    DesignCache,
    LoadFilter,
    design_filter,
    filter_batch,
)
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.noise_budget import noise_budget

CFG = load_config()
MODEL = CFG.rig_model()
DT = CFG.sample_period_s
OMEGA = CFG.rotor.omega_nominal_rad_s
HARMONICS = CFG.filter.harmonics
OMEGA_MIN = CFG.rotor.omega_min_fraction * OMEGA
INVALID_AFTER = round(CFG.filter.invalid_after_s / DT)


def _alpha(seed: int = 11, deg: float = 2.0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, np.radians(deg), 14)


def synthetic_run(alpha, n, rng, *, omega=OMEGA, harmonics=HARMONICS, noise=True,
                  mod_depth=0.1, mod_hz=0.1, omega_of_t=None):
    """(t, H, T, z): static + harmonic hub loads with amplitude modulation, phase-continuous
    in the rotor azimuth; inertial loads of a translational motion (no angular, as the
    default rig neglects); T from the exact balance I = S T + R H; model §4 noise."""
    t = np.arange(n) * DT
    om = np.full(n, omega) if omega_of_t is None else omega_of_t(t)
    azimuth = np.concatenate([[0.0], np.cumsum(0.5 * (om[1:] + om[:-1]) * DT)])
    H = np.tile([2e3, -1.5e3, -80e3, 3e3, -4e3, 1.5e3], (n, 1))
    for k in harmonics:
        amp = rng.uniform(1e3, 4e3, 6) * np.where(np.arange(6) < 3, 1.0, 2.0)
        ph, mph = rng.uniform(0, 2 * np.pi, (2, 6))
        env = 1 + mod_depth * np.sin(2 * np.pi * mod_hz * t[:, None] + mph)
        H += amp * env * np.cos(k * azimuth[:, None] + ph)
    f = np.zeros((n, 3))
    f[:, 2] = -9.81
    f += 0.3 * np.sin(2 * np.pi * 0.7 * t[:, None] + np.array([0.0, 1.0, 2.0]))
    I = np.zeros((n, 6))
    I[:, :3] = f * MODEL.mass.mass
    S = wrench_matrix(MODEL.geometry, alpha)
    R = hub_transfer_matrix(MODEL.geometry)
    T = (I - H @ R.T) @ np.linalg.pinv(S).T
    acc = np.repeat(f[:, None, :], MODEL.accelerometers.positions.shape[0], axis=1)
    if noise:
        T = T + rng.normal(size=T.shape) * MODEL.cell_sigma
        acc = acc + rng.normal(size=acc.shape) * MODEL.accelerometers.sigma[None, :, None]
    return t, H, T, inertial_loads(MODEL, acc)


def model_data(d, n, rng):
    """u = z − S T drawn from the design's own model: x(n) = Φ x(n−1) + w, u = J x + v."""
    Lq = np.linalg.cholesky(d.Qd + 1e-12 * np.diag(np.diag(d.Qd)))
    w = rng.normal(size=(n, d.n_states)) @ Lq.T
    v = rng.normal(size=(n, 6)) @ np.linalg.cholesky(d.W).T
    X = np.empty((n, d.n_states))
    x = np.zeros(d.n_states)
    for i in range(n):
        x = d.Phi @ x + w[i]
        X[i] = x
    return X @ d.J.T + v


def _cache(**kw):
    base = {"harmonics": HARMONICS, "dt": DT, "tuning": "time_constant",
            "time_constant_s": 0.1, "low_frequency": True, "psd": "auto", "alpha": None,
            "moment_floor": 100.0, "frame": None, "redesign_band": CFG.rotor.redesign_band,
            "cache_resolution": CFG.rotor.cache_resolution, "omega_min": OMEGA_MIN,
            "omega_default": OMEGA}
    base.update(kw)
    return DesignCache(MODEL, **base)


# ---------------------------------------------------------------------------- dynamics model §5
def test_dynamics_phi_and_van_loan_match_closed_forms():
    q = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e4
    dyn = hub_load_dynamics((1, 5), OMEGA, DT, True, psd=q)
    assert dyn.n_states == 30
    for c in range(6):
        idx = component_states((1, 5), True, c)
        for h, k in enumerate((1, 5)):
            w = k * OMEGA
            i = idx[2 * h]
            cs, sn = np.cos(w * DT), np.sin(w * DT)
            np.testing.assert_allclose(dyn.Phi[i:i + 2, i:i + 2], [[cs, sn / w], [-w * sn, cs]],
                                       rtol=1e-12, atol=1e-14)
            qin = 2 * w**2 * q[c]  # input PSD of the oscillator (module doc)

            def g(s, a, b, w=w, qin=qin):
                v = np.array([np.sin(w * s) / w, np.cos(w * s)])
                return qin * v[a] * v[b]

            ref = [[quad(g, 0, DT, args=(a, b))[0] for b in (0, 1)] for a in (0, 1)]
            np.testing.assert_allclose(dyn.Qd[i:i + 2, i:i + 2], ref, rtol=1e-9)
            # each quadrature amplitude diffuses at q_c: E[H² + Ḣ²/w²] = 2 q_c Δt
            assert dyn.Qd[i, i] + dyn.Qd[i + 1, i + 1] / w**2 == pytest.approx(2 * q[c] * DT, rel=1e-9)
        j = idx[-1]
        assert dyn.Phi[j, j] == pytest.approx(1.0, abs=1e-15) and dyn.Qd[j, j] == pytest.approx(q[c] * DT, rel=1e-12)
        # components do not couple
        others = np.setdiff1d(np.arange(30), idx)
        assert not np.any(dyn.Phi[np.ix_(idx, others)]) and not np.any(dyn.Qd[np.ix_(idx, others)])
    np.testing.assert_array_equal(dyn.C.sum(axis=1), np.full(6, 3.0))
    assert dyn.C[2, low_frequency_states((1, 5))[2]] == 1.0


# ------------------------------------------------------------------------- designs model §6
@pytest.mark.parametrize("harmonics,low_frequency,omega", [
    ((1, 5), True, OMEGA), ((1, 5), False, OMEGA), ((1, 5, 10), True, OMEGA * 1.03),
    ((1, 5), True, None),
])
@pytest.mark.parametrize("tau", [0.1, 0.3])
def test_time_constant_gain_places_the_closed_loop_eigenvalues(harmonics, low_frequency, omega, tau):
    d = design_filter(MODEL, harmonics=harmonics, omega=omega, dt=DT, time_constant_s=tau,
                      low_frequency=low_frequency, alpha=_alpha())
    r = np.exp(-DT / tau)
    want = [r * np.exp(s * 1j * k * (omega or 0) * DT) for k in d.harmonics for s in (1, -1)]
    if d.low_frequency:
        want.append(r)
    want = np.array(want)
    A = d.closed_loop
    for blk in d.blocks:  # per component: exactly the placed poles
        ix = np.asarray(blk)
        got = np.linalg.eigvals(A[np.ix_(ix, ix)])
        assert len(got) == len(want)
        for p in want:
            assert np.min(np.abs(got - p)) < 1e-9
        others = np.setdiff1d(np.arange(d.n_states), ix)
        assert np.max(np.abs(A[np.ix_(ix, others)])) < 1e-9 * np.max(np.abs(A))
    full = np.linalg.eigvals(A)  # the whole loop: every placed pole six times
    dist = np.abs(full[:, None] - want[None, :]).min(axis=1)
    assert np.max(dist) < 1e-6
    assert d.slowest_time_constant_s == pytest.approx(tau, rel=1e-9)
    np.testing.assert_allclose(d.J, hub_transfer_matrix(MODEL.geometry) @ d.C)
    # B from the Lyapunov equation of the fixed-gain error loop
    Ae = d.Phi @ (np.eye(d.n_states) - d.K @ d.J)
    P = d.P_minus
    res = Ae @ P @ Ae.T + d.Phi @ d.K @ d.W @ d.K.T @ d.Phi.T + d.Qd - P
    assert np.max(np.abs(res)) < 1e-8 * np.max(np.abs(P))
    np.testing.assert_allclose(d.B, d.J @ P @ d.J.T + d.W, rtol=1e-10)
    assert d.rotor_stopped == (omega is None)


def test_stopped_rotor_design_keeps_only_the_random_walks():
    for omega in (None, 0.0, 0.5 * OMEGA_MIN):
        d = design_filter(MODEL, harmonics=HARMONICS, omega=omega, dt=DT, omega_min=OMEGA_MIN,
                          low_frequency=False)
        assert d.rotor_stopped and d.harmonics == () and d.low_frequency and d.n_states == 6
        np.testing.assert_allclose(np.linalg.eigvals(d.closed_loop), np.exp(-DT / 0.1), rtol=1e-12)


@pytest.mark.parametrize("low_frequency", [True, False])
def test_noise_tuning_solves_the_riccati_equation_with_tau_by_default(low_frequency):
    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning="noise",
                      low_frequency=low_frequency, alpha=_alpha())
    P, J, Phi = d.P_minus, d.J, d.Phi
    B = J @ P @ J.T + d.W
    np.testing.assert_allclose(d.B, B, rtol=1e-10)
    np.testing.assert_allclose(d.K, P @ J.T @ np.linalg.inv(B), rtol=1e-8, atol=1e-12)
    res = Phi @ P @ Phi.T - Phi @ P @ J.T @ np.linalg.solve(B, J @ P @ Phi.T) + d.Qd - P
    assert np.max(np.abs(res)) < 1e-8 * np.max(np.abs(P))
    # default PSDs: the two tunings share the slowest time constant τ
    assert d.slowest_time_constant_s == pytest.approx(0.1, rel=1e-6)
    assert np.all(np.abs(np.linalg.eigvals(d.closed_loop)) < 1)


def test_auto_psd_gives_each_component_tau_alone():
    """The per-component search of model §6: a component's own Riccati gain (its whitened noise
    variance alone) has τ as slowest time constant."""
    from rsra.estimator.filters import _closed_loop_time_constants, _riccati_gain_1

    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, time_constant_s=0.3)
    Rinv = np.linalg.inv(d.R)
    r = np.diag(Rinv @ d.W @ Rinv.T)
    for c, blk in enumerate(d.blocks):
        ix = np.asarray(blk)
        Phi_c, C_c, Q_c = d.Phi[np.ix_(ix, ix)], d.C[c:c + 1, ix], d.Qd[np.ix_(ix, ix)]
        K = _riccati_gain_1(Phi_c, C_c, Q_c / r[c])
        taus = _closed_loop_time_constants((np.eye(len(ix)) - K @ C_c) @ Phi_c, DT)
        assert max(taus) == pytest.approx(0.3, rel=1e-6)


@pytest.mark.parametrize("tuning", ["noise", "time_constant"])
def test_innovation_covariance_matches_data_from_the_model(tuning):
    """Data drawn from the design's own model: the whitened innovations have unit variance.
    Riccati innovations are white, so the mean NIS over N samples is χ²_{6N}/N: a two-sided
    10⁻³ interval. The placed gain is slightly sub-optimal (mildly coloured innovations):
    twice that half-width."""
    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning=tuning)
    n, skip = 20000, 400
    u = model_data(d, n, np.random.default_rng(5))
    b = filter_batch(d, np.zeros((6, 7)), np.zeros((n, 7)), u)
    L = np.linalg.cholesky(d.B)
    w = np.linalg.solve(L, b.e[skip:].T)
    m = n - skip
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], 6 * m) / m
    half = (hi - lo) / 2 * (1.0 if tuning == "noise" else 2.0)
    assert abs(np.mean(np.sum(w**2, axis=0)) - 6.0) < half
    # and W alone (B without the prediction error) would be rejected
    w_bad = np.linalg.solve(np.linalg.cholesky(d.W), b.e[skip:].T)
    assert abs(np.mean(np.sum(w_bad**2, axis=0)) - 6.0) > 10 * half


# --------------------------------------------------------------------- batch == step
@pytest.mark.parametrize("tuning,kw", [
    ("time_constant", {}), ("time_constant", {"time_constant_s": 1.0}), ("noise", {}),
    ("noise", {"time_constant_s": 1.0}), ("time_constant", {"low_frequency": False}),
    ("noise", {"low_frequency": False}), ("time_constant", {"omega_default": None}),
    ("noise", {"omega_default": None}),
])
def test_batch_equals_the_per_sample_loop(tuning, kw):
    """P3's batch path is the per-sample recursion: Ĥ, e, x⁺, x_last and NIS to 1e-9 of
    each axis' range, from a random x0 with non-trivial angles. N spans several column
    blocks of the batch products and more samples than the x0 response is tracked for
    (τ = 0.1 s), or fewer (τ = 1 s); two chunks continue exactly from x_last. The design
    with its decomposition removed (the generic modal path) agrees too."""
    rng = np.random.default_rng(3)
    alpha = _alpha()
    cache = _cache(tuning=tuning, **kw)
    lf = LoadFilter(cache, alpha, INVALID_AFTER)
    n, cut = 9000, 4100
    _, _, T, z = synthetic_run(alpha, n, rng)
    x0 = rng.normal(0, 1e3, lf.design.n_states)
    lf.reset(x0)
    steps = [lf.step(T[i], z[i]) for i in range(n)]
    ref = {"x": np.array([s.x for s in steps]), "e": np.array([s.e for s in steps]),
           "H": np.array([s.H for s in steps])}
    scale = {k: np.max(np.abs(v), axis=0) for k, v in ref.items()}
    generic = filter_batch(dataclasses.replace(lf.design, rotation=None), alpha, T, z, x0=x0)
    for b in (filter_batch(lf.design, alpha, T, z, x0=x0), generic):
        for name, got in (("x", b.x_plus), ("e", b.e), ("H", b.H)):
            assert np.all(np.isfinite(got)), name
            assert np.max(np.abs(got - ref[name]) / scale[name]) < 1e-9, name
        np.testing.assert_allclose(b.x_last, lf.state, rtol=0, atol=1e-9 * np.max(np.abs(lf.state)))
    b = filter_batch(lf.design, alpha, T, z, x0=x0)
    nis = np.array([s.nis for s in steps])
    w = np.linalg.solve(np.linalg.cholesky(lf.design.B), b.e.T)
    np.testing.assert_allclose(nis, np.sum(w**2, axis=0), rtol=1e-9)
    # chunks continue exactly from x_last
    b1 = filter_batch(lf.design, alpha, T[:cut], z[:cut], x0=x0)
    b2 = filter_batch(lf.design, alpha, T[cut:], z[cut:], x0=b1.x_last)
    np.testing.assert_allclose(b2.H, b.H[cut:], rtol=0, atol=1e-9 * np.max(np.abs(b.H)))
    xp, e, H, _ = b  # unpacks like the tuple of the API
    assert xp.shape == (n, lf.design.n_states) and e.shape == H.shape == (n, 6)


@pytest.mark.parametrize("tuning", ["time_constant", "noise"])
def test_batch_of_one_and_two_samples(tuning):
    rng = np.random.default_rng(6)
    alpha = _alpha(3)
    lf = LoadFilter(_cache(tuning=tuning), alpha, INVALID_AFTER)
    _, _, T, z = synthetic_run(alpha, 2, rng)
    x0 = rng.normal(0, 1e3, lf.design.n_states)
    lf.reset(x0)
    steps = [lf.step(T[i], z[i]) for i in range(2)]
    for n in (1, 2):
        b = filter_batch(lf.design, alpha, T[:n], z[:n], x0=x0)
        for name, got in (("H", b.H), ("e", b.e), ("x", b.x_plus)):
            want = np.array([getattr(s, name) for s in steps[:n]])
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.max(np.abs(want)))
        np.testing.assert_allclose(b.x_last, steps[n - 1].x, rtol=1e-10,
                                   atol=1e-10 * np.max(np.abs(steps[n - 1].x)))


@pytest.mark.parametrize("tuning", ["time_constant", "noise"])
def test_batch_does_not_hold_the_state_history(tuning):
    """Ĥ, e and x_last without the N × n state history (P3: it costs more than all of
    them): the batch's peak allocation stays below that history's size alone."""
    import tracemalloc

    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning=tuning)
    rng = np.random.default_rng(7)
    n = 20000
    T, z = rng.normal(size=(n, 7)), rng.normal(size=(n, 6))
    filter_batch(d, np.zeros((6, 7)), T[:10], z[:10])  # the design's plan, made once
    tracemalloc.start()
    try:
        b = filter_batch(d, np.zeros((6, 7)), T, z)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.all(np.isfinite(b.H)) and np.all(np.isfinite(b.e))
    assert peak < n * d.n_states * 8, peak / (n * 48)


@pytest.mark.parametrize("low_frequency", [True, False])
def test_noise_design_is_the_full_riccati_solution(low_frequency):
    """The noise tuning is designed as six single-output Riccati problems in rotated
    whitened coordinates (M W' Mᵀ = I, M diag(q) Mᵀ diagonal); that must be the solution of
    the 30-state equation with the design's own Qd and W, solved directly."""
    from scipy.linalg import solve_discrete_are

    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning="noise",
                      low_frequency=low_frequency, alpha=_alpha())
    P = solve_discrete_are(d.Phi.T, d.J.T, d.Qd, d.W)
    K = np.linalg.solve(d.J @ P @ d.J.T + d.W, d.J @ P).T
    assert np.max(np.abs(d.P_minus - P)) < 1e-8 * np.max(np.abs(P))
    assert np.max(np.abs(d.K - K)) < 1e-8 * np.max(np.abs(K))
    # and W does couple the whitened components (the rotation is not the identity)
    Rinv = np.linalg.inv(d.R)
    Wn = Rinv @ d.W @ Rinv.T
    assert np.max(np.abs(Wn - np.diag(np.diag(Wn)))) > 0.05 * np.max(np.diag(Wn))
    np.testing.assert_allclose(d.rotation @ Wn @ d.rotation.T, np.eye(6), atol=1e-10)


def test_set_alpha_rebuilds_the_wrench_matrix():
    rng = np.random.default_rng(4)
    a1, a2 = _alpha(1), _alpha(2)
    _, _, T, z = synthetic_run(a1, 400, rng)
    lf = LoadFilter(_cache(), a1, INVALID_AFTER)
    for i in range(200):
        lf.step(T[i], z[i])
    lf.set_alpha(a2)
    x = lf.state  # shifted on the random-walk states (see the test below), else unchanged
    got = np.array([lf.step(T[i], z[i]).H for i in range(200, 400)])
    ref = filter_batch(lf.design, wrench_matrix(MODEL.geometry, a2), T[200:], z[200:], x0=x).H
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))


# --------------------------------------------------------------- accuracy (A2)
def test_load_filter_beats_the_static_bound_at_the_harmonics():
    """docs/performance.md A2: true angles, τ = 0.1 s, RMS error ≤ 0.8 × the model §4 static bound on
    every axis; the static estimate itself sits at the bound (checks the generator)."""
    alpha = _alpha()
    bound = noise_budget(MODEL, alpha).total
    _, H, T, z = synthetic_run(alpha, 8000, np.random.default_rng(8))
    Hs = static_estimate(MODEL, alpha, T, z)
    static_ratio = np.sqrt(np.mean((Hs - H) ** 2, axis=0)) / bound
    assert np.all(np.abs(static_ratio - 1) < 0.05), static_ratio
    for tuning in ("time_constant", "noise"):
        d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning=tuning,
                          time_constant_s=0.1, alpha=alpha)
        Hf = filter_batch(d, alpha, T, z).H
        skip = 400
        ratio = np.sqrt(np.mean((Hf[skip:] - H[skip:]) ** 2, axis=0)) / bound
        assert np.all(ratio <= 0.8), (tuning, ratio)


# ------------------------------------------------------------------ Ω redesign model §5
def test_design_cache_band_and_rounding():
    cache = _cache()
    d0 = cache.design_for(OMEGA)
    assert cache.design_for(OMEGA * 1.004) is d0  # inside the ±0.5 % band: no redesign
    assert cache.design_for(OMEGA * 0.996) is d0
    d1 = cache.design_for(OMEGA * 1.006)
    assert d1 is not d0 and abs(d1.omega / (OMEGA * 1.006) - 1) <= CFG.rotor.cache_resolution / 2 + 1e-12
    assert cache.design_for(OMEGA * 1.0065) is d1  # band around d1's design point
    made = cache.designs_made
    assert cache.design_for(OMEGA, current=d1) is d0  # back outside d1's band: from the cache
    assert cache.designs_made == made
    # prefilled grid: later redesigns anywhere in the range are cache hits
    pre = _cache()
    assert pre.prefill(0.99 * OMEGA, 1.01 * OMEGA) == pre.designs_made >= 20
    made = pre.designs_made
    for om in np.linspace(0.99, 1.01, 17) * OMEGA:
        pre.design_for(om)
    assert pre.designs_made == made
    # a stopped rotor; no rotor-speed data: the configured Ω, or stopped when so configured
    assert cache.design_for(0.5 * OMEGA_MIN).rotor_stopped
    assert not cache.design_for(None).rotor_stopped
    assert _cache(omega_default=None).design_for(None).rotor_stopped


def test_redesign_on_omega_change_keeps_the_output_continuous():
    """Ω ramps 3 % (phase-continuous truth, no noise): the filter redesigns as Ω leaves the
    band; the state carries over unchanged, the step in Ĥ at a redesign is no larger than
    its neighbours', and tracking beats the filter that never redesigns."""
    alpha = _alpha()
    n = 2400

    def om(t):
        return OMEGA * (1 + 0.03 * np.clip((t - 4.0) / 4.0, 0, 1))

    t, H, T, z = synthetic_run(alpha, n, np.random.default_rng(2), noise=False, mod_depth=0.0,
                               omega_of_t=om)
    errs = {}
    for redesign in (True, False):
        lf = LoadFilter(_cache(), alpha, INVALID_AFTER)
        Hh, switches = np.empty((n, 6)), []
        for i in range(n):
            if redesign:
                before, x = lf.design, lf.state
                lf.set_omega(om(t[i]))
                if lf.design is not before:
                    switches.append(i)
                    np.testing.assert_array_equal(lf.state, x)
            Hh[i] = lf.step(T[i], z[i]).H
        errs[redesign] = np.max(np.abs(Hh - H)[400:], axis=0)
        if redesign:
            assert len(switches) >= 4
            dH = np.abs(np.diff(Hh, axis=0))
            sw = np.array(switches)
            ratio = dH[sw - 1] / np.maximum(dH[sw - 2], dH[sw])
            assert np.max(ratio) < 1.5, ratio
    assert np.all(errs[True] < 0.3 * errs[False])


# ------------------------------------------------------------ predict-only, lost, stopped
def test_predict_only_lost_and_invalid():
    alpha = _alpha()
    _, _, T, z = synthetic_run(alpha, 400, np.random.default_rng(6))
    lf = LoadFilter(_cache(), alpha, INVALID_AFTER)
    d = lf.design
    for i in range(100):
        r = lf.step(T[i], z[i])
        assert r.flags == () and r.H is not None and r.e is not None and r.nis >= 0
    x = lf.state
    r = lf.step(T[100], z[100], measured=False)
    assert r.flags == (PREDICT_ONLY,) and r.e is None and r.nis is None
    np.testing.assert_allclose(r.x, d.Phi @ x, rtol=1e-14)
    np.testing.assert_allclose(r.H, d.C @ r.x, rtol=1e-14)
    for k in range(2, INVALID_AFTER):
        r = lf.step(T[100], z[100], measured=False)
        assert r.H is not None and INVALID not in r.flags, k
    r = lf.step(T[100], z[100], measured=False)  # 0.5 s of predict-only steps
    assert r.H is None and r.flags == (PREDICT_ONLY, INVALID)
    r = lf.step(T[101], z[101])
    assert r.H is not None and r.flags == ()
    # lost samples: Φ^k then the measured step, flagged, and the same as k predict-only steps
    twin = LoadFilter(_cache(), alpha, INVALID_AFTER)
    twin.reset(lf.state)
    r_lost = lf.step(T[102], z[102], lost=3)
    for _ in range(3):
        twin.step(T[102], z[102], measured=False)
    r_ref = twin.step(T[102], z[102])
    assert r_lost.flags == (LOST_BEFORE,)
    np.testing.assert_allclose(r_lost.x, r_ref.x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(r_lost.H, r_ref.H, rtol=1e-12, atol=1e-9)
    # a long gap counts towards invalid
    r = lf.step(T[103], z[103], measured=False, lost=INVALID_AFTER)
    assert r.H is None and set(r.flags) == {PREDICT_ONLY, INVALID, LOST_BEFORE}
    # returned arrays are not the filter's own state
    r = lf.step(T[104], z[104])
    r.x[:] = 0.0
    assert np.any(lf.state != 0.0)


def test_rotor_stopped_keeps_estimate_continuous_and_tracks_static_load():
    alpha = _alpha()
    _, _, T, z = synthetic_run(alpha, 1200, np.random.default_rng(9), noise=False, mod_depth=0.0)
    lf = LoadFilter(_cache(), alpha, INVALID_AFTER)
    for i in range(600):
        r = lf.step(T[i], z[i])
    H_before = lf.design.C @ lf.state
    lf.set_omega(0.5 * OMEGA_MIN)
    assert lf.design.rotor_stopped and lf.design.n_states == 6
    np.testing.assert_allclose(lf.design.C @ lf.state, H_before, rtol=1e-12)
    # a static load (the harmonics gone): the random walks converge to it
    _, Hs, Ts, zs = synthetic_run(alpha, 600, np.random.default_rng(9), harmonics=(), noise=False)
    for i in range(600):
        r = lf.step(Ts[i], zs[i])
        assert ROTOR_STOPPED in r.flags
    np.testing.assert_allclose(r.H, Hs[-1], rtol=0, atol=1e-6 * np.max(np.abs(Hs)))
    # the rotor starts again: harmonic states come back at zero, H_0 carries over
    lf.set_omega(OMEGA)
    assert not lf.design.rotor_stopped and lf.design.n_states == 30
    np.testing.assert_allclose(lf.design.C @ lf.state, r.H, rtol=1e-12)
    np.testing.assert_allclose(lf.state[low_frequency_states(HARMONICS)], r.H, rtol=1e-12)
    assert lf.step(T[600], z[600]).flags == ()


def test_stopped_configured_without_rotor_speed():
    lf = LoadFilter(_cache(omega_default=None), _alpha(), INVALID_AFTER)
    assert lf.design.rotor_stopped
    r = lf.step(np.zeros(7), np.zeros(6))
    assert r.flags == (ROTOR_STOPPED,)
    r = lf.step(np.zeros(7), np.zeros(6), measured=False)
    assert r.flags == (PREDICT_ONLY, ROTOR_STOPPED)


def test_new_angles_move_the_estimate_at_once_without_a_transient(cfg, model):
    """set_alpha: Ĥ jumps by exactly the static estimate's change, R⁻¹ (S_old − S_new) T, and
    the innovations after it show no step (a filter left alone would ring for ~5 τ)."""
    from rsra.estimator.balance import static_estimate
    from rsra.estimator.filters import DesignCache, LoadFilter

    cache = DesignCache(model, harmonics=(1, 5), dt=0.005, tuning="time_constant",
                        time_constant_s=0.1, low_frequency=True, psd="auto",
                        alpha=np.zeros(14), moment_floor=100.0, frame=None, omega_min=1.9,
                        omega_default=19.4)
    rng = np.random.default_rng(5)
    T = rng.normal(0, 2e4, 7)
    z = rng.normal(0, 1e3, 6)
    a_new = np.radians(rng.uniform(-1, 1, 14))
    f = LoadFilter(cache, np.zeros(14), 100)
    for _ in range(400):
        f.step(T, z)
    H_before = f.design.C @ f.state
    f.set_alpha(a_new)
    H_after = f.design.C @ f.state
    expected = (static_estimate(model, a_new, T[None], z[None])[0]
                - static_estimate(model, np.zeros(14), T[None], z[None])[0])
    assert np.abs(expected).max() > 100.0  # the change is large
    np.testing.assert_allclose(H_after - H_before, expected, atol=1e-6 * np.abs(expected).max())
    # the constant data are now explained by the new angles: no innovation step
    r = f.step(T, z)
    assert np.abs(r.e).max() < 1e-6 * np.abs(expected).max()
    np.testing.assert_allclose(r.H, static_estimate(model, a_new, T[None], z[None])[0],
                               rtol=1e-9, atol=1e-6)


def test_has_design_says_exactly_when_design_for_would_design():
    """The live first step (daq pipeline.first_step_is_quick) asks has_design before the bus
    thread takes a sample: it must agree with design_for on every kind of rotor speed — the
    band around the design in use, a cached grid point, a new one, stopped, None."""
    cache = _cache()
    w0 = 2 * np.pi * 3.5
    current = cache.design_for(w0)
    for w in [w0, w0 * 1.003, w0 * 1.02, w0 * 1.02, w0 * 0.95, None, 0.0, w0 * 1.02001, w0]:
        said = cache.has_design(w, current=current)
        before = cache.designs_made
        current = cache.design_for(w, current=current)
        assert said == (cache.designs_made == before), w
