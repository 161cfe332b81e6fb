"""A6 — flight identification that the data cannot fool, over ≥ 100 seeds of the off-line
physics (issue 14; docs/identification.md, the information rule of filter-error runs).

Per seed, four arms, each identified as the service does (``bench.a3_known_load.
run_calibration`` in filter-error mode: the calibration branch and the worker's own code):

* ``flight_true`` — the ``flight`` scenario as it is, from the true angles (the truth at trim,
  prior σ as configured);
* ``flight_ground`` — the same flight from the seed's ground posterior: a ``ground-test`` run
  (known loads, one sweep) of the same aircraft (its constant angles = the flight truth at
  trim), carried into flight as a saved posterior would be;
* ``turbulence`` — the flight with broadband hub loads (``[turbulence]``: 0.5–40 Hz, 2–3 kN
  and kN·m RMS) besides its manoeuvres, from the true angles;
* ``power`` — flight content that does carry information: fuselage-borne base vibration, no
  turbulence, no manoeuvres, constant rotor speed, three triaxial accelerometers (angular
  accelerations measured: ``angular = "least_squares"``), ``vibration`` content, from the true
  angles (rig overrides in ``POWER_RIG``; ``max_iterations`` 40).

The truth of a window is the mean of the true angles over it (the angles move with thrust).
Decisions at an overall false-alarm rate of 10⁻³:

* every accepted run's posterior, and every arm's final posterior, within the joint
  χ²₁₄(1 − 10⁻³/(seeds × runs tested)) of the truth, against its own P;
* no accepted run whose window determines nothing (``window_determined`` = 0);
* hub-load RMS error with the updates not worse than without, per axis: one-sided paired
  t-test over seeds at 10⁻³ (the load filter of the service over the run, with the angles
  applied where the records say, against the same filter at the starting angles);
* ``power``: runs accepted and σ shrinking in every seed (a gate that rejects everything
  fails here).
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np
from scipy import stats

from bench.a3_known_load import run_calibration, seed_map
from bench.common import arg_parser, writer_from_args

BENCH = "a6_flight"
FALSE_ALARM = 1e-3
N_SEEDS = 100
FLIGHT_S = 15.0  # three runs: the shortest that decides (the first manoeuvre starts at 15 s)
POWER_S = 10.0
GROUND_S = 60.0  # one sweep of the six conditions
ARMS = ("flight_true", "flight_ground", "turbulence", "power")
# three triaxial accelerometers on the transmission (non-collinear): angular accelerations
POWER_POSITIONS = ((0.7, -0.9, 0.35), (0.7, 0.9, 0.35), (-0.7, 0.0, 0.35))
_TINY = {"flight": 10.0, "power": 10.0, "ground": 20.0}


def power_rig() -> dict:
    """Rig overrides of the power arm: the default rig's accelerometer, three times."""
    import tomllib

    from rsra.config.rig import default_config_path

    raw = tomllib.loads(default_config_path().read_text(encoding="utf-8"))
    acc0 = raw["accelerometers"][0]
    node0 = next(n for n in raw["nodes"] if n["role"] == "accelerometer")
    accs = [dict(acc0, name=f"acc{i + 1}", node=f"accel_{i + 1}", position_m=list(p))
            for i, p in enumerate(POWER_POSITIONS)]
    nodes = [n for n in raw["nodes"] if n["role"] != "accelerometer"]
    nodes += [dict(node0, name=f"accel_{i + 1}", node_id=node0["node_id"] + i)
              for i in range(len(POWER_POSITIONS))]
    return {"accelerometers": accs, "nodes": nodes, "inertial": {"angular": "least_squares"},
            "identification": {"content_filter_error": "vibration", "max_iterations": 40}}


def _scenario(arm: str):
    from rsra.sim_bus import load_scenario

    if arm == "turbulence":
        return load_scenario("flight", turbulence=True)
    if arm == "power":  # no manoeuvres, constant rotor speed
        import tomllib

        from rsra.sim_bus.scenarios import parse_scenario, scenario_dir
        raw = tomllib.loads((scenario_dir() / "flight.toml").read_text(encoding="utf-8"))
        raw.pop("manoeuvres", None)
        raw["rotor"]["omega_variation"] = 0.0
        return parse_scenario(raw, source="flight.toml (A6 power arm)")
    return load_scenario("flight")


def hub_load_rms(cfg, run, schedule: list[tuple[int, np.ndarray]], alpha0: np.ndarray,
                 skip: int) -> np.ndarray:
    """RMS error (6,) of the service's load filter over the run against the true hub loads,
    the angles switching at the given samples (one design at the nominal rotor speed, the
    state carried across switches)."""
    from rsra.estimator.balance import inertial_loads
    from rsra.daq.rigmodel import design_cache
    from rsra.estimator.filters import filter_batch

    model = cfg.rig_model()
    cache = design_cache(cfg, model=model, omega_min=0.0)
    design = cache.design_for(cfg.rotor.omega_nominal_rad_s)
    z = inertial_loads(model, run.accel)
    n = len(z)
    cuts = [(0, alpha0)] + [(int(s), a) for s, a in schedule if 0 < s < n]
    H = np.empty((n, 6))
    x = None
    for (a, alpha), (b, _) in zip(cuts, cuts[1:] + [(n, None)]):
        res = filter_batch(design, alpha, run.T[a:b], z[a:b], x0=x)
        H[a:b] = res.H
        x = res.x_last
    e = H[skip:] - run.H_true[skip:]
    return np.sqrt(np.mean(e * e, axis=0))


def one_arm(seed: int, arm: str, tiny: bool = False) -> dict:
    from rsra.config.rig import load_config
    from rsra.estimator.posterior import PosteriorState
    from rsra.sim_bus import load_scenario, simulate

    power = arm == "power"
    base_cfg = load_config(overrides=power_rig() if power else None)
    dur = (_TINY["power" if power else "flight"] if tiny
           else POWER_S if power else FLIGHT_S)
    run = simulate(base_cfg, _scenario(arm), seed=seed, duration_s=dur)
    alpha0 = run.alpha_true[0].copy()  # the truth at trim (t = 0)
    ov = power_rig() if power else {}
    ov.setdefault("identification", {})
    ov["identification"] = dict(ov["identification"],
                                initial_angles_deg=np.degrees(alpha0).tolist())
    cfg = load_config(overrides=ov)
    initial = None
    if arm == "flight_ground":
        g_cfg = load_config()
        gs = load_scenario("ground-test", **{"angles.base": np.degrees(alpha0).tolist(),
                                             "angles.mode": "constant"})
        g_run = simulate(g_cfg, gs, seed=seed,
                         duration_s=_TINY["ground"] if tiny else GROUND_S)
        theta = P = None
        for _, _, theta, P in run_calibration(g_cfg, g_run, known_loads=True):
            pass
        names = g_cfg.rig_model().geometry.angle_names
        initial = PosteriorState(tuple(names), theta, P)
    sigma0 = None
    out = {"seed": seed, "arm": arm, "runs": [], "reasons": Counter()}
    schedule = []
    theta = P = None
    for end, rec, theta, P in run_calibration(cfg, run, known_loads=False,
                                              initial_state=initial):
        if sigma0 is None:
            sigma0 = np.sqrt(np.diag(initial.P if initial is not None else
                                     np.eye(14) * cfg.identification.prior_sigma_rad**2))
        window = slice(max(0, end + 1 - round(cfg.identification.window_s
                                              * cfg.sample_rate_hz)), end + 1)
        truth = run.alpha_true[window].mean(0)
        err = theta - truth
        chi2 = float(err @ np.linalg.solve(P, err))
        out["reasons"][f"{rec['reason'] or 'accepted'}:{rec.get('detail')}"] += 1
        out["runs"].append({"accepted": bool(rec["accepted"]), "chi2": chi2,
                            "window_determined": int(rec.get("window_determined") or 0)})
        if rec["accepted"]:
            schedule.append((int(rec["applies_from_seq"]), np.asarray(rec["alpha"], float)))
    final_truth = run.alpha_true[-round(cfg.identification.window_s * cfg.sample_rate_hz):].mean(0)
    ferr = theta - final_truth
    out["final_chi2"] = float(ferr @ np.linalg.solve(P, ferr))
    out["sigma_shrink"] = float(np.min(np.sqrt(np.diag(P)) / sigma0))
    skip = round(1.0 * cfg.sample_rate_hz)
    start_alpha = initial.theta if initial is not None else alpha0
    out["rms_with"] = hub_load_rms(cfg, run, schedule, start_alpha, skip)
    out["rms_without"] = (out["rms_with"] if not schedule
                          else hub_load_rms(cfg, run, [], start_alpha, skip))
    out["reasons"] = dict(out["reasons"])
    return out


def one_seed(seed: int, tiny: bool = False) -> dict:
    return {arm: one_arm(seed, arm, tiny) for arm in ARMS}


def _one_seed_tiny(seed: int) -> dict:
    return one_seed(seed, tiny=True)


def paired_not_worse(with_: np.ndarray, without: np.ndarray, false_alarm: float) -> dict:
    """One-sided paired t-test per axis of H0 'with updates is not worse'; rejected (worse)
    when the mean increase is beyond the 1 − false_alarm point (Bonferroni over 6 axes)."""
    d = with_ - without  # (seeds, 6)
    S = len(d)
    mean = d.mean(0)
    sd = d.std(0, ddof=1) if S > 1 else np.zeros(6)
    t = np.where(sd > 0, mean / np.where(sd > 0, sd, 1.0) * math.sqrt(S), 0.0)
    limit = float(stats.t.isf(false_alarm / 6, max(S - 1, 1)))
    return {"t": t, "limit": limit, "worse": bool(np.any(t > limit)),
            "mean_relative_change": mean / without.mean(0)}


def main(argv: list[str] | None = None) -> int:
    p = arg_parser(__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=N_SEEDS,
                   help=f"number of seeds (default {N_SEEDS}; fewer only when time is short)")
    args = p.parse_args(argv)
    w = writer_from_args(BENCH, args)
    seeds = list(range(1, 3 if args.tiny else args.seeds + 1))
    res = seed_map(_one_seed_tiny if args.tiny else one_seed, seeds, processes=2)
    for arm in ARMS:
        rows = [r[arm] for r in res]
        runs = [x for r in rows for x in r["runs"]]
        n_tested = max(len(runs), 1)
        limit = float(stats.chi2.isf(FALSE_ALARM / n_tested, 14))  # seeds × runs tested
        acc = [x for x in runs if x["accepted"]]
        worst_acc = max((x["chi2"] for x in acc), default=0.0)
        final = np.array([r["final_chi2"] for r in rows])
        empty_acc = sum(1 for x in acc if x["window_determined"] == 0)
        reasons: Counter = Counter()
        for r in rows:
            reasons.update(r["reasons"])
        pw = paired_not_worse(np.array([r["rms_with"] for r in rows]),
                              np.array([r["rms_without"] for r in rows]), FALSE_ALARM)
        common = {"arm": arm, "seeds": len(rows), "runs": len(runs), "accepted": len(acc),
                  "reasons": dict(reasons), "chi2_limit": limit,
                  "duration_s": (POWER_S if arm == "power" else FLIGHT_S)}
        w.add(f"{arm}_consistency", max(worst_acc, float(final.max())),
              "χ²₁₄ (worst accepted run or final posterior against the window truth)",
              target=f"≤ {limit:.1f} (10⁻³ over seeds × runs), no accepted run whose window "
              "determines nothing", met=bool(max(worst_acc, final.max()) <= limit
                                              and empty_acc == 0),
              accepted_fraction=len(acc) / n_tested, accepted_without_window_information=empty_acc,
              final_chi2_max=float(final.max()), worst_accepted_chi2=worst_acc, **common)
        w.add(f"{arm}_hub_loads", float(pw["t"].max()),
              "paired t (largest axis; > 0: worse with updates)",
              target=f"with updates not worse than without on every axis (t ≤ {pw['limit']:.2f})",
              met=not pw["worse"], mean_relative_change=pw["mean_relative_change"], **common)
        if arm == "power":
            shrink = np.array([r["sigma_shrink"] for r in rows])
            seeds_ok = sum(1 for r in rows if any(x["accepted"] for x in r["runs"])
                           and r["sigma_shrink"] < 1.0)
            w.add("power_learns", seeds_ok / len(rows), "fraction of seeds with runs accepted "
                  "and σ shrinking", target="1.0 (every seed)", met=seeds_ok == len(rows),
                  smallest_sigma_ratio_median=float(np.median(shrink)),
                  accepted_fraction=len(acc) / n_tested, **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
