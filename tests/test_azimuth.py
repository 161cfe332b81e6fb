"""Harmonic states driven by the rotor's measured azimuth (issue 25; docs/model.md §5):
the fixed-gain filter with Φ(Δψ) against a brute-force time-varying Kalman filter with Ω
varying ±2 %, the per-sample path against the reference loop, the azimuth tracker's refusals."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_filters import DT, HARMONICS, INVALID_AFTER, MODEL, OMEGA, _alpha, synthetic_run  # noqa: E402

from rsra.estimator.dynamics import hub_load_dynamics  # noqa: E402
from rsra.estimator.filters import (  # noqa: E402
    AZIMUTH_MISSING,
    AzimuthTracker,
    DesignCache,
    LoadFilter,
    azimuth_transition,
    design_filter,
)
from rsra.estimator.geometry import wrench_matrix  # noqa: E402

N = 3000
SKIP = 400  # 20 τ: the start-up transient


def _flight_data(variation=0.02, period_s=8.0, seed=3):
    rng = np.random.default_rng(seed)
    alpha = _alpha()

    def om_t(t):
        return OMEGA * (1 + variation * np.sin(2 * np.pi * t / period_s))

    t, H, T, z = synthetic_run(alpha, N, rng, omega_of_t=om_t)
    om = om_t(t)
    az = np.concatenate([[0.0], np.cumsum(0.5 * (om[1:] + om[:-1]) * DT)])
    dpsi = np.diff(np.concatenate([[-OMEGA * DT], az]))
    return alpha, H, T, z, om, az, dpsi


def _fixed_gain(d, u, Phin):
    x = np.zeros(d.n_states)
    out = np.empty((len(u), 6))
    for i in range(len(u)):
        xm = Phin[i] @ x
        x = xm + d.K @ (u[i] - d.J @ xm)
        out[i] = d.C @ x
    return out


def _brute_force_kf(d, u, dpsi):
    """The time-varying Kalman filter: Φ_n, Q_n of the oscillators at the speed of each
    step (Δψ_n/Δt), covariance and gain propagated every sample."""
    x = np.zeros(d.n_states)
    P = d.P_minus.copy()
    out = np.empty((len(u), 6))
    eye = np.eye(d.n_states)
    for i in range(len(u)):
        dyn = hub_load_dynamics(HARMONICS, dpsi[i] / DT, DT, True, psd=d.psd)
        xm = dyn.Phi @ x
        Pm = dyn.Phi @ P @ dyn.Phi.T + dyn.Qd
        K = Pm @ d.J.T @ np.linalg.inv(d.J @ Pm @ d.J.T + d.W)
        x = xm + K @ (u[i] - d.J @ xm)
        P = (eye - K @ d.J) @ Pm
        out[i] = d.C @ x
    return out


def _rms(a):
    return np.sqrt(np.mean(a[SKIP:] ** 2, axis=0))


def test_transition_is_the_design_phi_at_the_design_turn():
    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT)
    np.testing.assert_allclose(azimuth_transition(d, OMEGA * DT), d.Phi, atol=1e-12)
    # and the exact oscillator at any other speed (Δψ = Ω' Δt), up to the Ḣ scaling
    Pn = azimuth_transition(d, 1.02 * OMEGA * DT)
    assert np.all(np.abs(np.linalg.eigvals(Pn)) == pytest.approx(1.0, abs=1e-12))


def test_fixed_gain_azimuth_filter_equals_the_time_varying_kalman_filter():
    """Ω ±2 %: the constant Riccati gain with Φ(Δψ) gives the brute-force time-varying KF's
    estimate to within 2 % of that filter's own error (measured 0.3–1.1 %); the design's Φ
    (azimuth ignored) is 15–120 % off on five of the six axes."""
    alpha, H, T, z, om, az, dpsi = _flight_data()
    d = design_filter(MODEL, harmonics=HARMONICS, omega=OMEGA, dt=DT, tuning="noise")
    u = z - T @ wrench_matrix(MODEL.geometry, alpha).T
    Hb = _brute_force_kf(d, u, dpsi)
    Ha = _fixed_gain(d, u, azimuth_transition(d, dpsi))
    Hd = _fixed_gain(d, u, np.broadcast_to(d.Phi, (N,) + d.Phi.shape))
    err_b = _rms(Hb - H)
    assert np.all(_rms(Ha - Hb) <= 0.02 * err_b), (_rms(Ha - Hb) / err_b)
    assert np.sum(_rms(Hd - Hb) > 0.1 * err_b) >= 4  # the check can fail: without the azimuth
    assert np.all(_rms(Ha - H) <= 1.01 * err_b)


@pytest.mark.parametrize("tuning", ["time_constant", "noise"])
def test_load_filter_azimuth_mode_is_the_reference_recursion(tuning):
    alpha, H, T, z, om, az, dpsi = _flight_data()
    cache = DesignCache(MODEL, harmonics=HARMONICS, dt=DT, tuning=tuning,
                        omega_default=OMEGA)
    f = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=True)
    d = f.design
    u = z - T @ wrench_matrix(MODEL.geometry, alpha).T
    ref = _fixed_gain(d, u, azimuth_transition(d, dpsi))
    tr = AzimuthTracker(OMEGA, DT)
    tr.step(az[0] - OMEGA * DT)
    out = np.empty_like(ref)
    for i in range(N):
        f.set_omega(om[i])  # within the held band: no redesign
        r = f.step(T[i], z[i], dpsi=tr.step(az[i] % (2 * np.pi), om[i]))
        assert AZIMUTH_MISSING not in r.flags
        out[i] = r.H
    assert f.design is d
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6 * np.max(np.abs(ref)))
    # better than the design's Φ on the harmonics (the same filter, azimuth ignored)
    g = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=False)
    old = np.array([g.step(T[i], z[i]).H for i in range(N)])
    assert np.all(_rms(out - H) < _rms(old - H) * 1.0001)
    assert np.mean(_rms(out - H) / _rms(old - H)) < 0.85


def test_missing_stale_and_jumping_azimuth_fall_back_with_a_flag():
    alpha, H, T, z, om, az, dpsi = _flight_data()
    cache = DesignCache(MODEL, harmonics=HARMONICS, dt=DT, omega_default=OMEGA)
    f = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=True)
    g = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=False)
    tr = AzimuthTracker(OMEGA, DT)
    feed = az % (2 * np.pi)
    feed[100:110] = np.nan  # missing
    feed[200:230] = feed[199]  # stale (frozen)
    feed[300] += 1.0  # a jump
    for i in range(400):
        dp = tr.step(None if np.isnan(feed[i]) else feed[i], om[i])
        r = f.step(T[i], z[i], dpsi=dp)
        g.step(T[i], z[i])
        bad = (i == 0 or 100 <= i <= 110 or 200 <= i <= 230 or i in (300, 301))
        assert (AZIMUTH_MISSING in r.flags) == bad, i
        if i < 100:
            pass
    # with no azimuth at all it is today's filter exactly (up to rounding)
    f2 = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=True)
    g2 = LoadFilter(cache, alpha, INVALID_AFTER, omega=OMEGA, azimuth=False)
    for i in range(300):
        a, b = f2.step(T[i], z[i]), g2.step(T[i], z[i])
        np.testing.assert_allclose(a.H, b.H, rtol=1e-9, atol=1e-6)
        assert AZIMUTH_MISSING in a.flags and AZIMUTH_MISSING not in b.flags


def test_tracker_unwraps_over_lost_samples():
    tr = AzimuthTracker(OMEGA, DT)
    assert tr.step(6.2) is None  # nothing before
    d = tr.step((6.2 + 4 * OMEGA * DT) % (2 * np.pi), OMEGA, steps=4)
    assert d == pytest.approx(4 * OMEGA * DT, rel=1e-12)
    assert tr.step(None) is None and tr.step(1.0) is None  # a gap: no turn across it
