"""A2 — hub-load error of the load filter at the modelled harmonics vs the model §4 static bound.

Data: the off-line simulator (``sim_bus.simulate``), ``ground-test`` aircraft — the six static
conditions plus shaker harmonics at 1/rev and N_b/rev (the filter's modelled content), the
model §4 sensor noise, constant true angles — over several seeds. Estimators, both with the TRUE
angles (so only noise and filter dynamics make errors):

* the static estimate (model.md §3, report Eq 1.2), which sits at the model §4 bound;
* the load filter of the default rig (harmonics 1 and 5, low-frequency states, the report's
  time-constant tuning) at τ = 0.1 s (the report's, the target), 0.3 s and 1 s, run with
  ``filter_batch`` (bit-equivalent to the per-sample path, P3).

Scored samples: the holds of the load schedule, from 8τ after the ramp into a condition
(transients of a 20 kN·m step decay below 1 % of the bound) to the start of the next ramp;
the same samples for the static estimate. Per axis, RMS(Ĥ − H_true) / σ_§4.

Target: at τ = 0.1 s, RMS ≤ 0.8 × the bound on every axis; also the curve against τ.

**σ of the filtered hub loads** (issue 27, ``sigma_<scenario>`` lines): the service's own
per-sample path (``EstimatorPipeline``, identification off, the true angles with P_α ≈ 0 so
``sigma_angles`` ≈ 0 and the filter's term ``sigma_filter`` is the whole σ) over
``SIGMA_SEEDS`` seeds of each scenario: ``ground`` (``ground-test``, every sample from 2 s,
ramps included), ``ramps`` (its samples from each ramp's start to 1 s after its end),
``flight`` and ``turbulent`` (``flight``, angles constant; ``turbulent`` with the broadband
hub loads of A6: 2–3 kN, 1 kN·m on N, 0.5–40 Hz) and ``sweep``. Per axis: the fraction of
samples with |Ĥ − H| > 3 σ (all samples, and those not flagged `transient`) and RMS(error/σ).
Target: ≤ 0.5 % beyond 3σ on every axis of every scenario (a Gaussian: 0.27 %). The peer
figure is the former rule, σ = the static bound (angles true), on the same samples.

**Sharpness** (``sharp_<scenario>`` lines, ``paper`` too): the σ is the error's size, not a
safe multiple of it — RMS(error/σ) per axis on the samples not flagged `transient` in
[0.7, 1.3] (``paper``: ≤ 1.3), with ≤ 0.5 % beyond 3σ; the figure is the axis farthest from 1.
Seeds from ``SIGMA_FIRST_SEED`` on: none of the σ's rule was chosen on them.
"""
from __future__ import annotations

import numpy as np

from bench.common import arg_parser, ratio, simulated_sample, writer_from_args
from bench.p2_filter_step import load_filter_cache
from rsra.config.rig import load_config
from rsra.estimator.balance import inertial_loads, static_estimate
from rsra.estimator.filters import filter_batch
from rsra.estimator.noise_budget import AXES, noise_budget
from rsra.sim_bus import load_scenario, simulate

BENCH = "a2_filter_accuracy"
TAUS = (0.1, 0.3, 1.0)
TARGET_TAU = 0.1
TARGET = 0.8
SETTLE_TAUS = 8.0
SCENARIO = "ground-test"
SIGMA_SEEDS = 20
SIGMA_FIRST_SEED = 201  # seeds no part of the σ's rule was chosen on
SIGMA_TARGET = 0.5  # % of samples beyond 3σ, every axis, every scenario
# scenario, variants, seconds simulated per seed (a whole cycle of its schedule)
SIGMA_SCENARIOS = {
    "ground": ("ground-test", {}, 60.0),
    "ramps": ("ground-test", {}, 60.0),
    "flight": ("flight", {"angles": "constant"}, 120.0),
    "turbulent": ("flight", {"angles": "constant", "turbulence": True}, 120.0),
    "sweep": ("sweep", {}, 276.0),
    "paper": ("paper", {}, 60.0),
}
SHARP_BAND = (0.7, 1.3)  # RMS err/σ in the steady state: the σ is the error's size
SHARP_UPPER_ONLY = ("paper",)  # the report's quasi-static case: only the upper end holds
SKIP_S = 2.0  # the filter's start from zero state


def scored_mask(t: np.ndarray, hold_s: float, ramp_s: float, settle_s: float) -> np.ndarray:
    """Samples in a hold, ``settle_s`` after the ramp into it ended, before the next ramp."""
    phase = np.mod(t, hold_s)
    return (phase >= settle_s) & (phase < hold_s - ramp_s) & (t >= settle_s)


def main(argv: list[str] | None = None) -> int:
    ap = arg_parser(__doc__.splitlines()[0])
    ap.add_argument("--sigma-seeds", type=int, default=SIGMA_SEEDS,
                    help=f"seeds per scenario of the σ lines (default {SIGMA_SEEDS})")
    ap.add_argument("--only-sigma", action="store_true",
                    help="the σ lines alone (sigma_ and sharp_), not the τ curve")
    args = ap.parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
    if args.only_sigma:
        sigma_checks(w, cfg, tiny=args.tiny, n_seeds=args.sigma_seeds)
        return 0
    model = cfg.rig_model()
    sc = load_scenario(SCENARIO)
    seeds, n = ((1,), 2400) if args.tiny else ((1, 2, 3), round(3 * sc.duration_s
                                                                 * cfg.sample_rate_hz))
    taus = TAUS[:1] + TAUS[-1:] if args.tiny else TAUS
    omega = cfg.rotor.omega_nominal_rad_s
    designs = {tau: load_filter_cache(cfg, time_constant_s=tau).design_for(omega) for tau in taus}
    sq = {tau: np.zeros(6) for tau in taus}
    cnt = dict.fromkeys(taus, 0)
    sq_static = {tau: np.zeros(6) for tau in taus}
    bound = None
    for seed in seeds:
        run = simulate(cfg, sc, seed=seed, n_samples=n)
        alpha = run.alpha_true[0]
        if np.ptp(run.alpha_true, axis=0).max() != 0.0:
            raise RuntimeError(f"{SCENARIO}: the true angles must be constant here")
        nb = noise_budget(model, alpha).total
        bound = nb if bound is None else bound
        z = inertial_loads(model, run.accel)
        err_static = static_estimate(model, alpha, run.T, z) - run.H_true
        for tau in taus:
            m = scored_mask(run.t, sc.loads.hold_s, sc.loads.ramp_s, SETTLE_TAUS * tau)
            H = filter_batch(designs[tau], alpha, run.T, z).H
            e = (H - run.H_true)[m]
            sq[tau] += ((e / nb) ** 2).sum(0)
            sq_static[tau] += ((err_static[m] / nb) ** 2).sum(0)
            cnt[tau] += int(m.sum())
    curve = {}
    for tau in taus:
        r_f = np.sqrt(sq[tau] / cnt[tau])
        r_s = np.sqrt(sq_static[tau] / cnt[tau])
        curve[tau] = {"filter": dict(zip(AXES, r_f.round(4))),
                      "static": dict(zip(AXES, r_s.round(4))), "samples": cnt[tau]}
    for tau in taus:
        r_f = np.array(list(curve[tau]["filter"].values()))
        r_s = np.array(list(curve[tau]["static"].values()))
        worst, worst_static = float(r_f.max()), float(r_s.max())
        # docs/performance.md A2: the 0.8 target is at the report's τ = 0.1 s; the other τ are
        # the curve it asks for — reported, not decided (a longer τ lags the harmonics more)
        target = ("≤ 0.8 × the §4 bound on every axis" if tau == TARGET_TAU else
                  "reported: the curve against τ (the 0.8 target applies at τ = 0.1 s)")
        w.add(f"tau_{tau:g}s", worst, "RMS / σ_§4 (worst axis)",
              peer="static estimate, same samples (worst axis)", peer_figure=worst_static,
              ratio_value=ratio(worst_static, worst), ratio_is="peer/figure", target=target,
              met=bool(np.all(r_f <= TARGET)) if tau == TARGET_TAU else True, tau_s=tau, per_axis_filter=curve[tau]["filter"],
              per_axis_static=curve[tau]["static"], scored_samples=cnt[tau],
              bound_si=dict(zip(AXES, np.round(bound, 2))), seeds=list(seeds),
              samples_per_seed=n, scenario=SCENARIO, angles="true",
              curve={f"{k:g}": v["filter"] for k, v in curve.items()},
              settle=f"{SETTLE_TAUS:g} τ after each ramp")
    sigma_checks(w, cfg, tiny=args.tiny, n_seeds=args.sigma_seeds)
    return 0


def pipeline_run(cfg, run) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(H, sigma_filter, sigma_angles, transient) of every sample of a simulated run through
    the service's per-sample path, identification off, the true (first) angles, P_α ≈ 0."""

    from rsra.daq.runtime.pipeline import EstimatorPipeline

    p = EstimatorPipeline(cfg, run.alpha_true[0], identification=False)
    p.angles.set_covariance(cfg.rig_model().geometry.angle_names, np.eye(14) * 1e-16)
    n = len(run.t)
    H, sf, sa = np.full((n, 6), np.nan), np.full((n, 6), np.nan), np.full((n, 6), np.nan)
    tr = np.zeros(n, bool)
    status = np.zeros(7, int)
    for i in range(n):
        s = simulated_sample(run, i, status)
        first, _rest = p.stages(s)
        hub = first.records[-1][1]
        if hub["H"] is not None:
            H[i], sf[i], sa[i] = hub["H"], hub["sigma_filter"], hub["sigma_angles"]
        tr[i] = "transient" in hub["flags"]
    return H, sf, sa, tr


def ramp_mask(sc, t: np.ndarray, after_s: float = 1.0) -> np.ndarray:
    """Samples from each ramp's start to ``after_s`` after its end (a multi-condition
    schedule: the ramp into condition i+1 ends at (i+1)·hold)."""
    L = sc.loads
    phase = np.mod(t, L.hold_s)
    return (phase >= L.hold_s - L.ramp_s) | (phase < after_s)


def sigma_checks(w, cfg, *, tiny: bool = False, n_seeds: int = SIGMA_SEEDS) -> None:
    seeds = (SIGMA_FIRST_SEED,) if tiny else tuple(range(SIGMA_FIRST_SEED,
                                                         SIGMA_FIRST_SEED + n_seeds))
    for key, (name, variants, dur) in SIGMA_SCENARIOS.items():
        sc = load_scenario(name, **variants)
        c = load_config(overrides=sc.rig_overrides) if sc.rig_overrides else cfg
        nb = noise_budget(c.rig_model(), None).total
        beyond = np.zeros(6)
        beyond_nt = np.zeros(6)
        beyond_old = np.zeros(6)
        sq = np.zeros(6)
        sq_nt = np.zeros(6)
        count = count_nt = 0
        per_seed = []
        med = []
        for seed in seeds:
            run = simulate(c, sc, seed=seed, duration_s=12.0 if tiny else dur)
            nb = noise_budget(c.rig_model(), run.alpha_true[0]).total
            H, sf, sa, tr = pipeline_run(c, run)
            m = (run.t - run.t[0] >= SKIP_S) & np.isfinite(H).all(1)
            if key == "ramps":
                m &= ramp_mask(sc, run.t - run.t[0])
            sig = np.sqrt(sf ** 2 + sa ** 2)
            r = np.abs(H - run.H_true)[m] / sig[m]
            rt = r[~tr[m]]
            sq_nt += (rt ** 2).sum(0)
            beyond += (r > 3).sum(0)
            beyond_nt += (rt > 3).sum(0)
            beyond_old += (np.abs(H - run.H_true)[m] / nb > 3).sum(0)
            sq += (r ** 2).sum(0)
            count += len(r)
            count_nt += len(rt)
            per_seed.append(float(100 * (r > 3).mean(0).max()))
            med.append(np.median(sig[m] / nb, 0))
        frac = 100 * beyond / count
        frac_nt = 100 * beyond_nt / max(count_nt, 1)
        frac_old = 100 * beyond_old / count
        rms = np.sqrt(sq / count)
        worst = float(frac.max())
        w.add(f"sigma_{key}", worst, "% beyond 3σ (worst axis)",
              peer="σ = the static bound alone (the former rule), same samples (worst axis)",
              peer_figure=float(frac_old.max()), ratio_value=None,
              target=f"≤ {SIGMA_TARGET:g} % beyond 3σ on every axis",
              met=bool(np.all(frac <= SIGMA_TARGET)),
              scenario=name, variants=variants, seeds=list(seeds),
              seconds_per_seed=12.0 if tiny else dur, samples=count,
              beyond_3sigma_pct=dict(zip(AXES, np.round(frac, 4))),
              beyond_3sigma_pct_not_transient=dict(zip(AXES, np.round(frac_nt, 4))),
              samples_not_transient=count_nt,
              rms_error_over_sigma=dict(zip(AXES, np.round(rms, 3))),
              former_rule_beyond_3bound_pct=dict(zip(AXES, np.round(frac_old, 3))),
              median_sigma_over_bound=dict(zip(AXES, np.round(np.median(med, 0), 3))),
              worst_seed_pct=round(max(per_seed), 4))
        sharpness_line(w, key, name, variants, seeds, np.sqrt(sq_nt / max(count_nt, 1)),
                       frac_nt, count_nt)


def sharpness_line(w, key: str, name: str, variants: dict, seeds, rms: np.ndarray,
                   beyond: np.ndarray, count: int) -> None:
    """The σ's size against the error's in the steady state (samples not `transient`):
    RMS(err/σ) per axis in SHARP_BAND (a σ far above the error is safe but useless)."""
    lo, hi = SHARP_BAND
    upper_only = key in SHARP_UPPER_ONLY
    ok = rms <= hi if upper_only else (rms >= lo) & (rms <= hi)
    target = (f"≤ {hi:g} on every axis" if upper_only else
              f"in [{lo:g}, {hi:g}] on every axis") + f", ≤ {SIGMA_TARGET:g} % beyond 3σ"
    far = int(np.argmax(np.abs(np.log(rms))))  # the axis farthest from 1
    w.add(f"sharp_{key}", float(rms[far]), "RMS error/σ, steady state (axis farthest from 1)",
          peer=None, peer_figure=None, ratio_value=None, target=target,
          met=bool(np.all(ok) and np.all(beyond <= SIGMA_TARGET)), scenario=name,
          variants=variants, seeds=list(seeds), samples_not_transient=count,
          axis=AXES[far], rms_error_over_sigma_not_transient=dict(zip(AXES, np.round(rms, 3))),
          beyond_3sigma_pct_not_transient=dict(zip(AXES, np.round(beyond, 4))))


if __name__ == "__main__":
    raise SystemExit(main())
