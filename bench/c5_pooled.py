"""C5 — the posterior pooled across recordings, over ≥ 100 seeds (docs/identification.md,
"Pooling recordings"; docs/performance.md).

Per seed: one aircraft (true angles drawn within ±4°, constant), K = 4 recordings of one sweep
of the ``ground-test`` scenario's six static conditions (60 s each, other seeds of the
simulator's off-line physics — the lock-step simulator's arrays without a bus), an hour apart;
each recording's information product made in-process exactly as ``rsra calibrate
--posterior`` makes it (the ``static`` content filter over z, T and the balance, its settling
not scored, 5-s windows' moments: ``daq.analysis.information.information_table``) and pooled by
``pooled_posterior`` from the first 1, 2 and 4 recordings. The rig's drift allowance is set to 0
here (the angles are constant: the bench scores the pooling itself; with the packaged 1e-9
rad²/s an hour apart the σ floor would be the allowance's, docs/identification.md). The step arm:
recordings 3 and 4 of the same seed simulated again with 0.5° added to every angle (random
signs), so that the four recordings hold a 0.5° step between the second and the third.

Checks (10⁻³ for the whole bench, Bonferroni):

* ``chi2_per_seed`` — the joint χ²₁₄ of each pooled posterior (K = 1, 2, 4) against the truth,
  ≤ χ²₁₄(1 − 10⁻³/(3·seeds)) for every seed and K;
* ``sigma_ratio`` — σ_K/σ_1 per seed and angle, median for K = 2 and 4 against 1/√K (within
  10 %);
* ``homogeneity_false_alarms`` — rejections at 10⁻³ of the equal-angle pools (K = 2 and 4):
  at most the binomial count that 2·seeds tests at 10⁻³ exceed with probability < 10⁻³, with
  the mean χ²/dof and a Kolmogorov–Smirnov test of the p-values' uniformity reported;
* ``step_detected`` — the fraction of seeds whose 4-recording pool with the step is rejected
  (every seed), and whether the recordings named lie on both sides of the step.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy import stats

from bench.a3_known_load import seed_map
from bench.common import arg_parser, writer_from_args

BENCH = "c5_pooled"
FALSE_ALARM = 1e-3
N_SEEDS = 100
K_MAX = 4
KS = (1, 2, 4)
STEP_DEG = 0.5
SPACING_S = 3600.0  # the recordings an hour apart (t_start)
SIGMA_RATIO_TOLERANCE = 0.10
_TINY_SAMPLES = 4000  # 20 s: three conditions (runs, proves nothing)


def _config():
    from rsra.config.rig import load_config

    cfg = load_config()
    # constant angles: no drift allowance between the recordings (module doc)
    return replace(cfg, identification=replace(cfg.identification, drift_rate_rad2_s=0.0))


def _recording_table(cfg, alpha_deg: np.ndarray, seed: int, rid: str, t_start: float,
                     n: int):
    """One recording's information table, made from the off-line physics."""
    from rsra.daq.analysis.calibrate import CalibrationData
    from rsra.daq.analysis.information import information_table
    from rsra.estimator.balance import inertial_loads
    from rsra.estimator.content import ContentFilter
    from rsra.sim_bus import load_scenario, simulate

    sc = load_scenario("ground-test", **{"angles.base": [float(a) for a in alpha_deg]})
    run = simulate(cfg, sc, seed=seed, n_samples=n)
    model = cfg.rig_model()
    x = np.hstack([inertial_loads(model, run.accel), run.T, run.H_balance])
    idc, fs = cfg.identification, cfg.sample_rate_hz
    cf = ContentFilter(idc.content_known_loads, fs, cfg.rotor.omega_nominal_rad_s,
                       tuple(cfg.filter.harmonics), x.shape[1], idc.settle_time_constants)
    y = cf.process(x)
    scored = np.ones(len(y), bool)
    scored[:cf.settle_samples] = False
    nc = model.geometry.n_cells
    data = CalibrationData(z=y[:, :6], T=y[:, 6:6 + nc], H=y[:, 6 + nc:12 + nc], q=None,
                           valid=np.ones(len(y), bool), scored=scored,
                           content=idc.content_known_loads, fs=fs, files=(rid,), segments=1,
                           samples_read=len(y), t_first=t_start)
    return information_table(cfg, data, rid), run.alpha_true[0]


def one_seed(seed: int, tiny: bool = False) -> dict:
    import pyarrow as pa

    from rsra.daq.analysis.information import pooled_posterior, x_columns
    from rsra.sim_bus import load_scenario

    cfg = _config()
    cols = x_columns(cfg)
    n = _TINY_SAMPLES if tiny else round(load_scenario("ground-test").duration_s
                                         * cfg.sample_rate_hz)
    rng = np.random.default_rng([seed, 5])
    alpha_deg = np.round(rng.uniform(-4.0, 4.0, 14), 6)
    step_deg = STEP_DEG * np.where(rng.random(14) < 0.5, -1.0, 1.0)
    tabs, truth = [], None
    for k in range(K_MAX):
        t, truth = _recording_table(cfg, alpha_deg, 1000 * seed + k, f"r{k}", k * SPACING_S, n)
        tabs.append(t)
    stepped = tabs[:2] + [_recording_table(cfg, alpha_deg + step_deg, 1000 * seed + k, f"r{k}",
                                           k * SPACING_S, n)[0] for k in (2, 3)]
    out: dict = {"seed": seed}
    for K in KS:
        pc = pooled_posterior(cfg, pa.concat_tables(tabs[:K]), cols)
        e = pc.state.theta - truth
        h = pc.result.homogeneity
        out[K] = {"chi2": float(e @ np.linalg.solve(pc.state.P, e)),
                  "sigma": np.sqrt(np.diag(pc.state.P)), "status": pc.result.ident.status,
                  "hom_stat": h.statistic, "hom_dof": h.dof, "hom_p": h.p_value,
                  "reject": h.reject, "trend_p": h.trend_p_value}
    ps = pooled_posterior(cfg, pa.concat_tables(stepped), cols)
    hs = ps.result.homogeneity
    out["step"] = {"reject": hs.reject, "stat": hs.statistic, "limit": hs.limit,
                   "named": sorted(hs.disagree),
                   "both_sides": bool({0, 1} & set(hs.disagree) and {2, 3} & set(hs.disagree)),
                   "trend_p": hs.trend_p_value}
    return out


def _one_seed_tiny(seed: int) -> dict:
    return one_seed(seed, tiny=True)


def max_false_alarms(tests: int, rate: float = FALSE_ALARM, alpha: float = FALSE_ALARM) -> int:
    """The largest count of rejections that ``tests`` tests at ``rate`` reach with probability
    ≥ ``alpha`` (more is evidence, at ``alpha``, of a rate above nominal)."""
    return int(stats.binom.isf(alpha, tests, rate))


def main(argv: list[str] | None = None) -> int:
    p = arg_parser(__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=N_SEEDS, help=f"seeds (default {N_SEEDS})")
    p.add_argument("--processes", type=int, default=None,
                   help="worker processes (default: one per usable core)")
    args = p.parse_args(argv)
    w = writer_from_args(BENCH, args)
    seeds = list(range(1, 3 if args.tiny else args.seeds + 1))
    res = seed_map(_one_seed_tiny if args.tiny else one_seed, seeds, processes=args.processes)
    report(w, res, args.tiny)
    return 0


def report(w, res: list[dict], tiny: bool) -> None:
    S = len(res)
    common = {"seeds": S, "recordings_per_seed": K_MAX, "scenario": "ground-test, one sweep "
              "(60 s) per recording" if not tiny else "ground-test, 20 s (tiny)",
              "spacing_s": SPACING_S, "drift_rate_rad2_s": 0.0, "false_alarm": FALSE_ALARM}
    chi2_limit = float(stats.chi2.isf(FALSE_ALARM / (len(KS) * S), 14))
    chi2 = {K: np.array([r[K]["chi2"] for r in res]) for K in KS}
    worst = max(float(c.max()) for c in chi2.values())
    over = {K: int((chi2[K] > chi2_limit).sum()) for K in KS}
    w.add("chi2_per_seed", worst, "χ²₁₄ (largest over seeds and K = 1, 2, 4)",
          target=f"≤ {chi2_limit:.1f} for every seed and K (10⁻³ over {len(KS)}×{S})",
          met=sum(over.values()) == 0, chi2_limit=chi2_limit,
          over_limit={str(K): over[K] for K in KS},
          chi2_mean={str(K): float(chi2[K].mean()) for K in KS},
          chi2_max={str(K): float(chi2[K].max()) for K in KS},
          not_converged={str(K): sum(r[K]["status"] != "converged" for r in res) for K in KS},
          **common)
    sig1 = np.array([r[1]["sigma"] for r in res])
    ratios = {K: np.median(np.array([r[K]["sigma"] for r in res]) / sig1) for K in KS[1:]}
    per_angle = {K: np.median(np.array([r[K]["sigma"] for r in res]) / sig1, axis=0)
                 for K in KS[1:]}
    dev = max(abs(ratios[K] * math.sqrt(K) - 1.0) for K in KS[1:])
    w.add("sigma_ratio", float(ratios[4]), "median σ₄/σ₁ (1/√4 = 0.5)",
          peer="1/√K", peer_figure=0.5, ratio_value=float(ratios[4] / 0.5),
          ratio_is="σ₄/σ₁ ÷ 1/√4",
          target=f"σ_K/σ₁ within {SIGMA_RATIO_TOLERANCE:.0%} of 1/√K for K = 2 and 4",
          met=bool(dev <= SIGMA_RATIO_TOLERANCE),
          median_ratio={"1": 1.0, **{str(K): float(ratios[K]) for K in KS[1:]}},
          per_angle_ratio={str(K): np.round(per_angle[K], 3) for K in KS[1:]},
          sigma_1_median_deg=np.round(np.degrees(np.median(sig1, axis=0)), 4), **common)
    pv = np.array([r[K]["hom_p"] for r in res for K in KS[1:]])
    stat_dof = np.array([r[K]["hom_stat"] / r[K]["hom_dof"] for r in res for K in KS[1:]])
    fa = int(sum(r[K]["reject"] for r in res for K in KS[1:]))
    limit = max_false_alarms(len(pv))
    ks = stats.kstest(pv, "uniform")
    w.add("homogeneity_false_alarms", fa, f"rejections of {len(pv)} equal-angle pools",
          peer="nominal 10⁻³ × tests", peer_figure=FALSE_ALARM * len(pv),
          target=f"≤ {limit} (binomial, 10⁻³) of {len(pv)} tests at 10⁻³",
          met=fa <= limit, mean_chi2_over_dof=float(stat_dof.mean()),
          mean_chi2_over_dof_se=float(stat_dof.std(ddof=1) / math.sqrt(len(stat_dof)))
          if len(stat_dof) > 1 else None,
          p_value_uniform_ks=float(ks.pvalue), p_value_min=float(pv.min()),
          trend_false_alarms=int(sum(r[4]["trend_p"] is not None
                                     and r[4]["trend_p"] < FALSE_ALARM for r in res)),
          **common)
    det = [r["step"]["reject"] for r in res]
    w.add("step_detected", float(np.mean(det)), f"fraction of seeds ({STEP_DEG:g}° step on "
          "every angle between recordings 2 and 3 of 4)",
          target="1 (every seed rejected at 10⁻³)", met=all(det),
          named_both_sides=int(sum(r["step"]["both_sides"] for r in res)),
          statistic_over_limit_min=float(min(r["step"]["stat"] / r["step"]["limit"]
                                             for r in res)),
          trend_detected=int(sum(r["step"]["trend_p"] is not None
                                 and r["step"]["trend_p"] < FALSE_ALARM for r in res)),
          **common)


if __name__ == "__main__":
    raise SystemExit(main())
