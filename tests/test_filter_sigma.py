"""The filtered hub loads' σ from what the filter can and cannot follow (issue 27;
estimator/filter_sigma.py, docs/identification.md "The σ of the filtered hub loads")."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.estimator.filter_sigma import (
    FilterSigma,
    error_gain,
    filter_sigma_batch,
    modelled_covariance,
)
from rsra.estimator.balance import inertial_loads
from rsra.estimator.filters import filter_batch
from rsra.estimator.noise_budget import noise_budget
from rsra.daq.rigmodel import design_cache
from rsra.sim_bus import load_scenario, simulate

# The claim (docs/identification.md): ≤ 0.5 % of the samples beyond 3σ on every axis. Monte
# Carlo of this test's run (20 s turbulent flight, 20 seeds): at most 0.19 % on any axis of any
# seed (mean 0.004–0.09 %); the former σ (the static bound alone) 43–47 % on the worst axis.
LIMIT_PCT = 0.5
SKIP_S = 2.0
SHARP_S = 12.0  # seconds of the calibrated ground test scored for the σ's size
SHARP_SEED = 7


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _pipeline(cfg, run, flags: bool = False):
    from rsra.daq.runtime.pipeline import EstimatorPipeline

    p = EstimatorPipeline(cfg, run.alpha_true[0], identification=False)
    p.angles.set_covariance(cfg.rig_model().geometry.angle_names, np.eye(14) * 1e-16)
    n = len(run.t)
    H, sf, sa = (np.full((n, 6), np.nan) for _ in range(3))
    tr = np.zeros(n, bool)
    for i in range(n):
        s = SimpleNamespace(seq=i, sync=i % 240 + 1, t=float(run.t[i]), T=run.T[i],
                            accel=run.accel[i], flags=[], drive=None, omega=float(run.omega[i]),
                            azimuth=float(run.azimuth[i]), known_H=run.H_balance[i],
                            cell_status=np.zeros(7, int), lost_before=0)
        hub = [r for k, r in p.process(s).records if k == "hub_loads"][0]
        if hub["H"] is not None:
            H[i], sf[i], sa[i] = hub["H"], hub["sigma_filter"], hub["sigma_angles"]
        tr[i] = "transient" in hub["flags"]
    return (H, sf, sa, tr) if flags else (H, sf, sa)


def test_turbulent_flight_within_three_sigma_on_every_axis(cfg):
    """A short turbulent flight (broadband hub loads the filter does not model, 2–3 kN) from
    the simulator through the service's per-sample path: the fraction of samples beyond 3σ
    of the published σ of H (sqrt(sigma_angles² + sigma_filter²)) is within the limit on
    every axis; with the former σ (the static bound, no filter term) it is not — break check
    (measured: removing the innovation term from FilterSigma fails this test too)."""
    sc = load_scenario("flight", angles="constant", turbulence=True)
    run = simulate(cfg, sc, seed=5, duration_s=12.0)
    H, sf, sa = _pipeline(cfg, run)
    m = run.t - run.t[0] >= SKIP_S
    err = np.abs(H - run.H_true)[m]
    frac = 100 * (err / np.sqrt(sf ** 2 + sa ** 2)[m] > 3).mean(axis=0)
    assert np.all(frac <= LIMIT_PCT), frac
    bound = noise_budget(cfg.rig_model(), run.alpha_true[0]).total
    former = 100 * (err / bound > 3).mean(axis=0)
    assert former.max() > LIMIT_PCT  # the σ without the filter's term is exceeded
    # the filter's term widens σ where the loads are broadband (Z: 3 kN), not on a quiet axis
    assert np.median(sf[m][:, 2]) > 1.3 * bound[2]


def sharpness(cfg, seed: int, duration_s: float = SHARP_S):
    """(RMS err/σ (6,), % beyond 3σ (6,)) of a calibrated ground test (the true angles, P_α ≈ 0:
    sigma_angles ≈ 0) in its steady state: samples from SKIP_S on, not flagged `transient`."""
    sc = load_scenario("ground-test")
    run = simulate(cfg, sc, seed=seed, duration_s=duration_s)
    H, sf, sa, tr = _pipeline(cfg, run, flags=True)
    m = (run.t - run.t[0] >= SKIP_S) & ~tr
    r = np.abs(H - run.H_true)[m] / np.sqrt(sf ** 2 + sa ** 2)[m]
    return np.sqrt((r ** 2).mean(0)), 100 * (r > 3).mean(0)


def test_calibrated_ground_test_sigma_is_the_size_of_the_error(cfg):
    """The published σ of H is the error's size, not a bound far above it: RMS err/σ in
    [0.7, 1.3] on every axis with ≤ 0.5 % beyond 3σ (a seed no parameter was chosen on).
    Monte Carlo of this run over 24 seeds (100–123): RMS per axis mean 0.81–0.87, s.d.
    0.019–0.029 — 0.7 is ≥ 3.9 s.d. below every axis' mean (≤ 3·10⁻⁴ false alarms over the six),
    1.3 far above; beyond 3σ at most 0.05 % (limit 0.5). Break-checked: the former floor at the
    static bound gives RMS 0.38–0.46 on this seed and fails it."""
    rms, beyond = sharpness(cfg, seed=SHARP_SEED)
    assert np.all((rms >= 0.7) & (rms <= 1.3)), rms
    assert np.all(beyond <= LIMIT_PCT), beyond


def test_the_error_identity_and_the_batch_path(cfg):
    """Ĥ = H_static − G' R⁻¹ e exactly (the relation the σ rests on), and the batch σ equals
    the per-sample one."""
    model = cfg.rig_model()
    sc = load_scenario("flight", angles="constant", turbulence=True)
    run = simulate(cfg, sc, seed=2, duration_s=3.0)
    design = design_cache(cfg).design_for(cfg.rotor.omega_nominal_rad_s)
    alpha = run.alpha_true[0]
    z = inertial_loads(model, run.accel)
    res = filter_batch(design, alpha, run.T, z)
    from rsra.estimator.balance import static_estimate
    Hs = static_estimate(model, alpha, run.T, z)
    G = error_gain(design)
    Rinv = np.linalg.inv(design.R)
    np.testing.assert_allclose(res.H, Hs - (res.e @ Rinv.T) @ G.T, rtol=0, atol=1e-6)
    dt, tau = 1.0 / cfg.sample_rate_hz, cfg.filter.time_constant_s
    fs = FilterSigma(dt, tau)
    per = np.array([fs.update(design, e).copy() for e in res.e])
    np.testing.assert_allclose(filter_sigma_batch(design, res.e, dt, tau), per, rtol=1e-9)
    assert fs.update(design, None) is fs.sigma  # predict-only: σ stays


def test_an_unmodelled_load_path_at_a_modelled_harmonic_is_in_sigma(cfg):
    """`sweep`'s roll torque (0.3 N·m per N of the shaker's Y force) at the shaker's N_b/rev:
    the balance carries it, H does not, and the filter follows it with no innovation. The
    reference balance on the bus shows it (ReferenceSigma): L within 3σ. Break-check: without
    the reference's term (the rule of the cells and accelerometers alone) L is beyond 3σ on
    far more than the limit (measured 29 % of L on this run)."""
    sc = load_scenario("sweep", **{"shaker.axes": ["Y"], "shaker.levels_lbf": [800.0],
                                   "shaker.sweep_s": 6.0})
    run = simulate(cfg, sc, seed=11, duration_s=sc.shaker.cycle_s)
    H, sf, sa = _pipeline(cfg, run)
    m = run.t - run.t[0] >= SKIP_S
    err = np.abs(H - run.H_true)[m]
    frac = 100 * (err / np.sqrt(sf ** 2 + sa ** 2)[m] > 3).mean(axis=0)
    assert np.all(frac <= LIMIT_PCT), frac
    # it is there: beyond 3 × the σ the cells and accelerometers give for a held load
    design = design_cache(cfg).design_for(cfg.rotor.omega_nominal_rad_s)
    held = np.sqrt(np.diag(modelled_covariance(design)))
    assert np.abs(run.unmodelled[m][:, 3]).max() > 3 * held[3]


def test_reference_sigma_is_the_error_the_reference_shows():
    """ReferenceSigma on its own: d = Ĥ − H_ref of known spread — the excess is its variance less
    the reference's own noise, σ widened to it and never narrowed; no reading: σ unchanged."""
    from rsra.estimator.filter_sigma import ReferenceSigma

    rng = np.random.default_rng(4)
    noise = np.full(6, 10.0)
    ref = ReferenceSigma(1 / 200, 0.1, noise ** 2)
    sigma = np.array([50.0, 50, 50, 500, 500, 500])
    assert ref.widen(sigma) is sigma  # nothing seen yet
    ref.update(np.full(6, np.nan))  # a reading not finite: not taken
    assert ref.excess is None
    spread = np.array([200.0, 200, 200, 10, 10, 10])  # the first three: errors beyond σ
    for _ in range(4000):
        ref.update(rng.standard_normal(6) * spread)
    wide = ref.widen(sigma)
    # the slow average over 2 s (400 samples) of a χ²₁: ±10 % (1 s.d. 7 %), the max of two ≥ it
    assert np.all(wide[:3] > 0.85 * 200) and np.all(wide[:3] < 1.3 * 200)
    np.testing.assert_array_equal(wide[3:], sigma[3:])  # 10 ≈ the noise: nothing to add
