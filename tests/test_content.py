"""Content filters of the identification (model.md §7): passband gain and phase, the stated
rejection, causality with state, and the balance surviving the filter."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import freqz, iirpeak, sosfreqz

from rsra.config.rig import load_config
from rsra.estimator.content import KINDS, ContentFilter, design_content_filter
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix

CFG = load_config()
FS = 1.0 / CFG.sample_period_s
OMEGA = CFG.rotor.omega_nominal_rad_s
HARMONICS = CFG.filter.harmonics
F1 = OMEGA / (2 * np.pi)


def _response(sos, freqs_hz):
    return sosfreqz(sos, worN=np.asarray(freqs_hz, float), fs=FS)[1]


def _poles(sos):
    return np.concatenate([np.roots(s[3:]) for s in sos])


@pytest.mark.parametrize("omega", [OMEGA, 0.9 * OMEGA, 1.1 * OMEGA])
def test_static_lowpass_unit_gain_and_rejection_at_one_per_rev(omega):
    sos = design_content_filter("static", FS, omega, HARMONICS)
    f1 = omega / (2 * np.pi)
    h = _response(sos, [0.0, 0.5 * f1, f1, max(HARMONICS) * f1])
    assert abs(h[0] - 1.0) < 1e-9  # static load passes unchanged
    assert abs(abs(h[1]) - np.sqrt(0.5)) < 1e-6  # −3 dB at half the 1/rev frequency
    assert 20 * np.log10(abs(h[2])) <= -20.0  # ≥ 20 dB down at 1/rev
    assert 20 * np.log10(abs(h[3])) <= -20.0
    assert len(_poles(sos)) == 4 and np.all(np.abs(_poles(sos)) < 1)


@pytest.mark.parametrize("harmonics", [(1, 5), (1, 5, 10), (1, 2), (1, 2, 3, 4, 5)])
def test_harmonics_filter_unit_gain_and_zero_phase_at_each_harmonic(harmonics):
    sos = design_content_filter("harmonics", FS, OMEGA, harmonics)
    h = _response(sos, [k * F1 for k in harmonics])
    assert np.all(np.abs(np.abs(h) - 1) <= 0.01), np.abs(h)
    assert np.all(np.abs(np.degrees(np.angle(h))) <= 3.0), np.degrees(np.angle(h))
    assert abs(_response(sos, [0.0])[0]) < 1e-9  # the static load is rejected
    assert np.all(np.abs(_poles(sos)) < 1)
    # a band-pass: at 0.4 × 1/rev at least 12 dB down (one Q = 5 peak alone: 20 dB)
    assert abs(_response(sos, [0.4 * F1])[0]) < 0.25


def test_plain_sum_of_peaks_misses_the_tolerance_the_corrected_one_meets():
    """The uncorrected parallel sum of iirpeak (Q = 5) at 1, 5, 10/rev is off by more than
    the tolerance: the correction is doing real work."""
    harmonics = (1, 5, 10)
    f = np.array([k * F1 for k in harmonics])
    plain = sum(freqz(*iirpeak(k * F1, 5.0, fs=FS), worN=f, fs=FS)[1] for k in harmonics)
    bad = (np.abs(np.abs(plain) - 1) > 0.01) | (np.abs(np.degrees(np.angle(plain))) > 3.0)
    assert np.any(bad)


def test_broadband_is_identity():
    cf = ContentFilter("broadband", FS, OMEGA, HARMONICS, 3)
    X = np.random.default_rng(0).normal(size=(50, 3))
    np.testing.assert_array_equal(cf.process(X), X)
    assert cf.settle_samples == 0


@pytest.mark.parametrize("kind", KINDS)
def test_chunks_equal_one_call_and_columns_are_independent(kind):
    rng = np.random.default_rng(1)
    X = rng.normal(size=(1000, 4)) + 5.0
    one = ContentFilter(kind, FS, OMEGA, HARMONICS, 4).process(X)
    cf = ContentFilter(kind, FS, OMEGA, HARMONICS, 4)
    chunked = np.vstack([cf.process(X[a:b]) for a, b in ((0, 1), (1, 333), (333, 1000))])
    np.testing.assert_allclose(chunked, one, rtol=1e-12, atol=1e-12)
    for j in range(4):
        alone = ContentFilter(kind, FS, OMEGA, HARMONICS, 1).process(X[:, j:j + 1])
        np.testing.assert_allclose(alone[:, 0], one[:, j], rtol=1e-12, atol=1e-12)
    cf.reset()
    np.testing.assert_allclose(cf.process(X), one, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError):
        cf.process(X[:, :3])


@pytest.mark.parametrize("kind", KINDS)
def test_sample_by_sample_is_bit_identical_to_one_call(kind):
    """The live path filters one sample at a time (its own section loop, not sosfilt):
    recordings replay bit for bit only if that equals scipy's sosfilt exactly."""
    rng = np.random.default_rng(2)
    X = rng.normal(size=(2000, 19)) * 1e3 + 50.0
    one = ContentFilter(kind, FS, OMEGA, HARMONICS, 19)
    Y = one.process(X)
    cf = ContentFilter(kind, FS, OMEGA, HARMONICS, 19)
    rows = np.vstack([cf.process(X[k:k + 1]) for k in range(len(X))])
    assert np.array_equal(rows, Y)
    assert np.array_equal(cf.process(X[:5]), one.process(X[:5]))  # the states agree too


@pytest.mark.parametrize("kind", KINDS)
def test_balance_holds_in_the_filtered_data(kind):
    """One filter on T, z and the known loads: z = S T + R H stays exact, start-up included."""
    rng = np.random.default_rng(2)
    n = 800
    t = np.arange(n) / FS
    S = wrench_matrix(CFG.rig_model().geometry, rng.normal(0, 0.03, 14))
    R = hub_transfer_matrix(CFG.rig_model().geometry)
    H = np.array([1e3, -2e3, -8e4, 5e3, 1e3, -2e3]) + 3e3 * np.cos(OMEGA * t[:, None] + rng.uniform(0, 6, 6))
    T = 2e4 + rng.normal(0, 3e3, (n, 7))
    z = T @ S.T + H @ R.T
    cf = ContentFilter(kind, FS, OMEGA, HARMONICS, 7 + 6 + 6)
    Y = cf.process(np.hstack([T, z, H]))
    Tf, zf, Hf = Y[:, :7], Y[:, 7:13], Y[:, 13:]
    np.testing.assert_allclose(zf, Tf @ S.T + Hf @ R.T, rtol=0, atol=1e-9 * np.max(np.abs(z)))


def test_time_domain_passband_after_settling():
    """A 1/rev and an N_b/rev sinusoid riding on a static load: after ``settle_samples``
    the harmonics filter returns the sinusoids (1 % amplitude, 3° phase) without the static
    part, and the static filter returns the static load and rejects the sinusoids by 20 dB."""
    n = 3000
    t = np.arange(n) / FS
    harm = 2e3 * np.cos(OMEGA * t + 0.4) + 1e3 * np.cos(HARMONICS[-1] * OMEGA * t - 1.0)
    x = (5e4 + harm)[:, None]
    ch = ContentFilter("harmonics", FS, OMEGA, HARMONICS, 1)
    y = ch.process(x)[:, 0]
    s = ch.settle_samples
    assert 0 < s < n // 2
    err = y[s:] - harm[s:]
    assert np.max(np.abs(err)) < 0.01 * 3e3 + 3e3 * np.radians(3)
    cs = ContentFilter("static", FS, OMEGA, HARMONICS, 1)
    ys = cs.process(x)[:, 0]
    ss = cs.settle_samples
    assert np.max(np.abs(ys[ss:] - 5e4)) <= 0.1 * 3e3  # 20 dB below the harmonics
    # started at the first sample's steady state: a constant passes from the first sample
    c = ContentFilter("static", FS, OMEGA, HARMONICS, 1).process(np.full((100, 1), 7.0))
    np.testing.assert_allclose(c, 7.0, rtol=1e-12)


def test_bad_arguments():
    with pytest.raises(ValueError):
        design_content_filter("notch", FS, OMEGA, HARMONICS)
    with pytest.raises(ValueError):
        design_content_filter("static", FS, 0.0, HARMONICS)
    with pytest.raises(ValueError):
        design_content_filter("harmonics", FS, OMEGA, (1, 50))  # beyond Nyquist


@pytest.mark.parametrize("kind", KINDS)
def test_a_short_gap_is_filtered_as_interpolated_once_it_closes(kind):
    """Sample by sample (MissingHold + correct_past_inputs, the service's calibration branch)
    the content filter's output at every usable sample equals the block filter over
    hold_missing's input (gaps of up to MAX_INTERPOLATED interpolated, longer ones held), and
    at the usable samples after a short gap it differs from a plain hold."""
    from rsra.estimator.content import MAX_INTERPOLATED, MissingHold, hold_missing

    rng = np.random.default_rng(5)
    n, ch = 1500, 4
    t = np.arange(n) / FS
    X = (np.sin(2 * np.pi * F1 * t)[:, None] * [1.0, 2.0, -0.5, 0.3]
         + 0.1 * rng.standard_normal((n, ch)) + [3.0, -1.0, 0.0, 10.0])
    usable = rng.random(n) > 0.15
    usable[200:200 + MAX_INTERPOLATED + 3] = False  # one gap too long to interpolate
    usable[:3] = False  # before the first complete sample: passed as it is
    live, hold = ContentFilter(kind, FS, OMEGA, HARMONICS, ch), MissingHold()
    out = np.empty_like(X)
    for k in range(n):
        x = hold.input(X[k], bool(usable[k]))
        c = hold.correction()
        if c is not None:
            live.correct_past_inputs(c)
        out[k] = live.process(x[None, :])[0]
    block = ContentFilter(kind, FS, OMEGA, HARMONICS, ch).process(hold_missing(X, usable))
    np.testing.assert_allclose(out[usable], block[usable], rtol=0, atol=1e-9)
    held = X.copy()
    idx = np.maximum.accumulate(np.where(usable, np.arange(n), -1))
    held[~usable & (idx >= 0)] = X[idx[~usable & (idx >= 0)]]
    plain = ContentFilter(kind, FS, OMEGA, HARMONICS, ch).process(held)
    if kind != "broadband":
        assert np.abs(plain[usable] - block[usable]).max() > 1e-3
    # the long gap stays held: the row just before its end is the last usable one
    assert np.array_equal(hold_missing(X, usable)[200 + MAX_INTERPOLATED + 2], X[199])
