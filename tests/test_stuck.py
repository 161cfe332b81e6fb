"""Stuck-channel detection (daq/runtime/stuck.py): the false-alarm arithmetic against Monte Carlo,
the run lengths of the default rig against an independent computation, the detector's
flags sample by sample, untestable channels, and the pipeline treating a stuck cell as a
faulted one (predict-only, out of the identification window).

The end-to-end tests (the simulator's `stuck:` fault through the service, flags on exactly
the k-th to the last frozen sample, Ĥ identical to a missing cell) are in test_faults_e2e.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm, poisson

from rsra.config.rig import ConfigError, load_config
from rsra.config.devices import MILLI_G
from rsra.daq.runtime.stuck import (
    SECONDS_PER_HOUR,
    StuckDetector,
    StuckMonitor,
    plan,
    quantum,
    run_probability,
)

ALPHA = 1e-3  # two-sided false-alarm rate of every statistical check here


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _levels(sigma: float, q: float, mu: float) -> np.ndarray:
    """P_j of every grid level (scipy.stats, written out independently of daq.stuck)."""
    j = np.arange(-math.ceil(12 * sigma / q) - 3, math.ceil(12 * sigma / q) + 4)
    return norm.cdf((j + 0.5) * q, loc=mu, scale=sigma) - norm.cdf((j - 0.5) * q, loc=mu,
                                                                    scale=sigma)


@pytest.mark.parametrize("ratio", [0.3, 1.0, 4.0, 20.0])
@pytest.mark.parametrize("k", [2, 3, 5])
def test_run_probability_is_the_worst_offset_of_the_exact_sum(ratio, k):
    q = 1.0
    sigma = ratio * q
    worst = max((_levels(sigma, q, mu) ** k).sum() for mu in np.linspace(0, 0.5, 101))
    assert run_probability(sigma, q, k) == pytest.approx(worst, rel=1e-3)


@pytest.mark.parametrize("k", [2, 3, 4, 7])
def test_the_asymptotic_form_agrees_with_the_exact_sum_where_it_takes_over(k):
    from rsra.daq.runtime import stuck

    r = stuck.ASYMPTOTIC_RATIO
    exact = float(np.max(stuck._exact_runs(r, 1.0, k)))
    asym = run_probability(r * (1 + 1e-12), 1.0, k)  # just above: the asymptotic branch
    assert asym == pytest.approx(exact, rel=1e-3)


@pytest.mark.parametrize("ratio,k", [(0.8, 3), (2.0, 3), (5.0, 2)])
def test_monte_carlo_runs_of_equal_readings_match_the_model(ratio, k):
    """Honest channel at rest: constant value + white Gaussian noise, rounded to the grid.
    The number of runs that reach k equal readings (what the detector counts as episodes)
    against its expectation N Σ_j (1 − P_j) P_j^k, a Poisson count at 1e-3 two-sided."""
    rng = np.random.default_rng(11)
    q, sigma, mu = 1.0, ratio, 0.2
    n_ch, n = 200, 4000
    x = np.round((mu + sigma * rng.standard_normal((n, n_ch))) / q) * q
    det = StuckDetector(np.full(n_ch, k))
    for row in x:
        det.update(row)
    P = _levels(sigma, q, mu)
    expected = (n - k) * n_ch * float(((1 - P) * P ** k).sum())
    lo, hi = poisson.ppf(ALPHA / 2, expected), poisson.isf(ALPHA / 2, expected)
    assert expected > 20 and lo <= det.episodes.sum() <= hi, (det.episodes.sum(), expected)


def test_the_default_rig_run_lengths_meet_the_false_alarm_rate(cfg):
    fs = cfg.sample_rate_hz
    rate = cfg.stuck.false_alarm_per_hour
    chans = plan(cfg)
    assert [c.key for c in chans] == [f"{c.node}.force" for c in cfg.cells] + [
        f"{a.node}.{x}" for a in cfg.accelerometers for x in "xyz"]
    for c in chans:
        # the quanta, independently: a REAL32 force's spacing at full scale (numpy), and
        # the accelerometer count of the bus contract (1 mg)
        if c.key.endswith(".force"):
            fsN = next(x.full_scale_N for x in cfg.cells if c.key.startswith(x.node))
            assert c.q == float(np.spacing(np.float32(fsN)))
            assert c.flag.startswith("fault:")
        else:
            assert c.q == pytest.approx(MILLI_G)
            assert c.flag == f"fault:{cfg.accelerometers[0].name}"
        assert c.k is not None
        # the smallest k that meets the rate (worst offset, exact sum, union bound)
        worst = lambda k: max((_levels(c.sigma, c.q, mu) ** k).sum()  # noqa: E731
                              for mu in np.linspace(0, 0.5, 21)) if c.sigma / c.q < 50 else \
            run_probability(c.sigma, c.q, k)
        n_hour = SECONDS_PER_HOUR * fs
        assert n_hour * worst(c.k) <= rate * 1.001
        assert n_hour * worst(c.k - 1) > rate or c.k == 2


def test_float_quantum_follows_the_largest_raw_value():
    # REAL32 at 1000 (2^9 ≤ 1000 < 2^10): spacing 2^(9-23); a gain of 2 halves the raw range
    assert quantum("f", 1.0, 1000.0) == 2.0 ** -14
    assert quantum("f", 2.0, 1000.0) == 2.0 * 2.0 ** (8 - 23)
    assert quantum("h", 0.5, 1e6) == 0.5  # integers: one count


def test_honest_channels_at_rest_are_not_flagged(cfg):
    """Every tested channel of the default rig, 200 copies each, at rest (constant true
    value + configured noise, encoded as the bus carries it: REAL32 forces, INTEGER16 counts)
    for 60 s: 200 · 10 channels · 60 s = 33 channel-hours. At the configured rate (1e-6 per
    channel-hour) a flag here has probability < 4e-5."""
    mon = StuckMonitor(cfg)
    rng = np.random.default_rng(5)
    copies = 200
    chans = mon.channels
    n_cells = len(cfg.cells)
    det = StuckDetector(np.repeat([c.k for c in chans], copies))
    truth_T = np.repeat(np.array([c.full_scale_N for c in cfg.cells]) * 0.61, copies)
    truth_a = np.repeat(np.array([0.3, -0.2, -9.81]), copies)
    sig = np.repeat([c.sigma for c in chans], copies)
    for _ in range(int(60 * cfg.sample_rate_hz)):
        e = rng.standard_normal(len(sig)) * sig
        T = (truth_T + e[: n_cells * copies]).astype(np.float32).astype(float)
        a = np.round((truth_a + e[n_cells * copies:]) / MILLI_G) * MILLI_G
        det.update(np.concatenate([T, a]))
    assert det.samples.sum() == 0 and det.episodes.sum() == 0
    assert (det.run.max() < det.k).all()


def test_the_detector_flags_a_frozen_stretch_from_its_kth_sample_to_its_end():
    rng = np.random.default_rng(2)
    k = np.array([4, 7, 0])  # the third channel is untested
    det = StuckDetector(k)
    x = rng.standard_normal((60, 3))
    x[10:30, 0] = x[10, 0]  # frozen for 20 samples from 10
    x[20:40, 1] = x[20, 1]
    x[:, 2] = 1.0  # untested: constant for ever, never flagged
    x[15, 0] = np.nan  # a missing reading inside the run: neither ends it nor is flagged
    hits = np.array([det.update(row) for row in x])
    # sample 15 is missing, so the 4th present equal reading is sample 14
    assert np.flatnonzero(hits[:, 0]).tolist() == [13, 14] + list(range(16, 30))
    assert np.flatnonzero(hits[:, 1]).tolist() == list(range(26, 40))
    assert not hits[:, 2].any()
    assert det.episodes.tolist() == [1, 1, 0] and det.samples.tolist() == [16, 14, 0]


def test_the_detector_matches_a_scalar_reference_on_random_streams():
    """The vectorised in-place update (the estimator's per-sample path) against a plain
    per-channel loop of the definition: runs of exactly equal present readings, NaN neither
    extending nor ending a run, flagged from the k-th, k = 0 never; explained channels keep
    their run but are not flagged or counted."""
    rng = np.random.default_rng(7)
    k = np.array([2, 3, 5, 0, 4, 1])
    n, m = 3000, len(k)
    # few levels and many NaNs: long runs, runs broken by NaN, restarts at the same value
    x = rng.integers(0, 3, (n, m)).astype(float)
    x[rng.random((n, m)) < 0.2] = np.nan
    explained = rng.random((n, m)) < 0.1
    det = StuckDetector(k)
    value, run = [math.nan] * m, [0] * m
    episodes, samples = [0] * m, [0] * m
    for t in range(n):
        got = det.update(x[t], explained[t])
        want = []
        for c in range(m):
            v = x[t, c]
            if math.isfinite(v):
                run[c] = run[c] + 1 if v == value[c] else 1
                value[c] = v
            hit = math.isfinite(v) and k[c] > 0 and run[c] >= k[c] and not explained[t, c]
            episodes[c] += hit and run[c] == k[c]
            samples[c] += hit
            want.append(hit)
        assert got.tolist() == want, t
        assert det.run.tolist() == run, t
    assert det.episodes.tolist() == episodes and det.samples.tolist() == samples
    assert min(samples[:3]) > 0 and samples[3] == 0  # the stream exercised the flagging


@pytest.mark.parametrize("python_first", [False, True])
def test_the_fresh_sample_shortcut_matches_the_scalar_reference(python_first):
    """Every run length >= 2 (the rigs' case): a sample whose readings are all present and
    all new takes the shortcut (runs restart at 1, nothing flagged). On continuous streams
    with frozen stretches, NaN, inf and huge values the
    state and the flags are those of the per-channel definition, sample by sample — also
    when each sample is first offered to the Python shortcut (``update_fresh``, what the
    monitor does), its state brought up to date only when read."""
    rng = np.random.default_rng(11)
    k = np.array([2, 3, 4, 0, 6])
    n, m = 4000, len(k)
    x = rng.standard_normal((n, m))
    for _ in range(60):  # frozen stretches of 1-8 samples, some channels at once
        t0, L = rng.integers(1, n - 10), rng.integers(1, 9)
        cols = rng.random(m) < 0.5
        x[t0:t0 + L, cols] = x[t0 - 1, cols]
    x[rng.random((n, m)) < 0.01] = np.nan
    x[rng.random((n, m)) < 0.003] = np.inf
    x[rng.random(n) < 0.01, 0] = 1e300
    det = StuckDetector(k)
    assert det._fresh_ok
    value, run = [math.nan] * m, [0] * m
    episodes, samples, shortcut = [0] * m, [0] * m, 0
    for t in range(n):
        if python_first and det.update_fresh(x[t].tolist()):
            got = det.stuck
        else:
            got = det.update(x[t])
        want = []
        fresh = all(math.isfinite(v) and v != value[c] for c, v in enumerate(x[t]))
        shortcut += fresh
        for c in range(m):
            v = x[t, c]
            if math.isfinite(v):
                run[c] = run[c] + 1 if v == value[c] else 1
                value[c] = v
            hit = math.isfinite(v) and k[c] > 0 and run[c] >= k[c]
            episodes[c] += hit and run[c] == k[c]
            samples[c] += hit
            want.append(hit)
        assert got.tolist() == want, t
        assert det.run.tolist() == run, t
        assert det.n_stuck == sum(want), t
        assert det.fresh == fresh, t  # the pipeline skips its own finiteness test on it
        assert np.array_equal(det.value, value, equal_nan=True), t
    assert det.episodes.tolist() == episodes and det.samples.tolist() == samples
    assert min(samples[:3]) > 0 and shortcut > n // 2  # both paths exercised


def test_a_status_flag_explains_a_constant_cell(cfg):
    """An over-range cell reads full scale (constant): its status says why; not `stuck` too."""
    mon = StuckMonitor(cfg)
    k = mon.channels[0].k
    T = np.linspace(1000.0, 2000.0, 7)
    acc = np.array([[0.1, 0.2, -9.8]])
    rng = np.random.default_rng(0)
    out = []
    for i in range(3 * k):
        flags = ("overrange:A",) if i < 2 * k else ()
        jitter = rng.standard_normal(7)
        jitter[0] = 0.0
        out.append(mon.update(T + jitter, acc + rng.standard_normal((1, 3)), flags))
    assert all(f == [] for f in out[: 2 * k])
    assert all(f == ["fault:A"] for f in out[2 * k:])  # still frozen once the status clears


def test_a_channel_below_its_quantum_is_listed_untested_and_never_flagged():
    quiet = load_config(overrides={"accelerometers": [{
        "name": "acc1", "node": "accel_1", "position_m": [0.0, 0.0, 0.0], "full_scale_g": 7.0,
        "accuracy_fs": 2.0e-5}]})  # sigma = 0.14 mg < 1 mg / 2
    mon = StuckMonitor(quiet)
    assert mon.untested == ["accel_1.x", "accel_1.y", "accel_1.z"]
    T = np.arange(7.0)
    acc = np.array([[0.0, 0.0, -9.80665]])
    for i in range(200):
        assert mon.update(T + i, acc) == []
    assert mon.health()["stuck_untested"] == mon.untested


def test_stuck_config_errors_name_the_key_and_the_fix():
    with pytest.raises(ConfigError) as e:
        load_config(overrides={"stuck": {"false_alarm_per_hour": 2.0}})
    assert e.value.key == "stuck.false_alarm_per_hour" and "1e-6" in e.value.fix
    with pytest.raises(ConfigError) as e:
        load_config(overrides={"stuck": {"max_delay_s": 0}})
    assert e.value.key == "stuck.max_delay_s"
    with pytest.raises(ConfigError) as e:
        load_config(overrides={"stuck": {"enable": True}})
    assert e.value.key == "stuck.enable" and "enabled" in e.value.fix


def test_a_stuck_cell_is_predict_only_and_out_of_the_identification_window(cfg):
    """Through the lock-step simulator's `stuck:` fault and the pipeline (identification on):
    the flagged samples are predict-only, without a static estimate, and marked not ok in
    the calibration window — as a faulted cell's are."""
    from helpers_canopen import LockstepRig

    from rsra.daq.runtime.pipeline import EstimatorPipeline
    from rsra.daq.bus.reader import HealthReport

    rig = LockstepRig(cfg, faults="stuck:cell_C@0.5-1.0", seed=4)
    pipe = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=True)
    hub = {}
    try:
        for s in rig.step(300):
            if not isinstance(s, HealthReport):
                hub[s.seq] = pipe.process(s).records[0][1]
        log = rig.sim.fault_log
    finally:
        rig.close()
    a, b = [e["sample"] for e in log if e["kind"] == "stuck"]
    k = next(c.k for c in pipe.stuck.channels if c.key == "cell_C.force")
    flagged = sorted(q for q, h in hub.items() if "fault:C" in h["flags"])
    assert flagged == list(range(a + k - 1, b))
    for q in flagged:
        assert "predict_only" in hub[q]["flags"] and hub[q]["H_static"] is None
    w = pipe.calibration.buffer.window()
    ok = dict(zip(w["seq"].tolist(), w["ok"].tolist()))
    assert not any(ok[q] for q in flagged)
    assert all(ok[q] for q in range(b, b + 50))
    assert all(ok[q] for q in range(10, a + k - 1))
    h = pipe.stuck.health()
    assert h["stuck_episodes"] == 1 and h["stuck_samples"] == len(flagged)
    assert h["stuck_now"] == []
