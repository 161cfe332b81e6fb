"""A2 — hub-load error of the load filter at the modelled harmonics vs the §4 static bound.

Data: the off-line simulator (``sim_bus.simulate``), ``ground-test`` aircraft — the six static
conditions plus shaker harmonics at 1/rev and N_b/rev (the filter's modelled content), the
§4 sensor noise, constant true angles — over several seeds. Estimators, both with the TRUE
angles (so only noise and filter dynamics make errors):

* the static estimate (model.md §3, report Eq 1.2), which sits at the §4 bound;
* the load filter of the default rig (harmonics 1 and 5, low-frequency states, the report's
  time-constant tuning) at τ = 0.1 s (the report's, the target), 0.3 s and 1 s, run with
  ``filter_batch`` (bit-equivalent to the per-sample path, P3).

Scored samples: the holds of the load schedule, from 8τ after the ramp into a condition
(transients of a 20 kN·m step decay below 1 % of the bound) to the start of the next ramp;
the same samples for the static estimate. Per axis, RMS(Ĥ − H_true) / σ_§4.

Target: at τ = 0.1 s, RMS ≤ 0.8 × the bound on every axis; also the curve against τ.
"""
from __future__ import annotations

import numpy as np

from bench.common import arg_parser, ratio, writer_from_args
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


def scored_mask(t: np.ndarray, hold_s: float, ramp_s: float, settle_s: float) -> np.ndarray:
    """Samples in a hold, ``settle_s`` after the ramp into it ended, before the next ramp."""
    phase = np.mod(t, hold_s)
    return (phase >= settle_s) & (phase < hold_s - ramp_s) & (t >= settle_s)


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
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
        # performance.md A2: the 0.8 target is at the report's τ = 0.1 s; the other τ are
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
