"""A3 — known-load identification over ≥ 100 seeds of the off-line physics (docs/performance.md).

Per seed: the ground-test aircraft (constant true angles drawn within ±4°, ``static``
content, the reference balance on the bus), two sweeps of the six static conditions
(120 s), identified from the configured starting angles exactly as the service does: the
calibration branch of ``daq.pipeline`` (one causal content filter over load cells, inertial
loads and balance; a window of ``window_s`` every ``period_s``) feeding the identification
worker's own code (``daq.ident_worker.build_identification`` / ``run_job``: periodic
Levenberg–Marquardt runs and the sequential posterior with its gates). The content filter
runs over the whole run at once, which equals the service's per-sample calls (its state
carries over exactly); a fault-free simulation has every channel valid.

Decisions at an overall false-alarm rate of 10⁻³ (Bonferroni over seeds and angles), on the
final posterior (θ, P) against the true angles:

* per seed, the joint χ²₁₄ of the error against P ≤ χ²₁₄(1 − 10⁻³/seeds) (48.7 for 100);
* the mean normalised error of each angle within norm.isf(10⁻³/28) = 3.97 standard errors;
* the spread Σ (error/σ_CR)² of each angle inside the χ²_seeds bounds for 10⁻³/28 a tail;
* every σ_CR ≤ 0.2° (the configured ``sigma_max``); the coloured-residual-corrected bound
  (Morelli & Klein) of the last accepted run is reported beside the conventional one.

Seeds run one process per core (spawned, single-threaded BLAS). ``run_calibration`` and
``seed_statistics`` are shared with A4 and A5.
"""
from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Callable, Iterator

import numpy as np
from scipy import stats

from bench.common import BLAS_ENV, arg_parser, use_single_thread_blas, writer_from_args

BENCH = "a3_known_load"
FALSE_ALARM = 1e-3
SINGLE_RUN_CHI2 = float(stats.chi2.isf(FALSE_ALARM, 14))  # 36.1: one run (a test, a hold-out)
N_SEEDS = 100
SWEEPS = 2


# ------------------------------------------------------------------------------ the harness
def run_calibration(cfg, run, *, known_loads: bool, initial_state=None,
                    lacking: np.ndarray | None = None
                    ) -> Iterator[tuple[int, dict, np.ndarray, np.ndarray]]:
    """The service's calibration branch over an off-line run: yields, per window,
    (last sample, the angles record, posterior θ, posterior P) in window order.
    ``initial_state``: a saved posterior to start from (``--angles``). ``lacking``: samples
    that lack an input (a dropped frame: the sample is not measured), as the pipeline
    treats them: the content filter's input holds the last complete sample
    (estimator.content.hold_missing), the sample is not ``ok`` (not scored)."""
    from rsra.daq.runtime.ident_worker import build_identification, run_job
    from rsra.estimator.balance import inertial_loads
    from rsra.estimator.content import ContentFilter, hold_missing

    model = cfg.rig_model()
    idc, fs = cfg.identification, cfg.sample_rate_hz
    post, runs, cache = build_identification(cfg, initial_state)
    mode = "known_loads" if known_loads else "filter_error"
    content = idc.content_known_loads if known_loads else idc.content_filter_error
    # daq.pipeline: x = [T, z, H] through one causal content filter per mode
    cf = ContentFilter(content, fs, cfg.rotor.omega_nominal_rad_s, tuple(cfg.filter.harmonics),
                       7 + 6 + 6)
    z = inertial_loads(model, run.accel)
    H = run.H_balance if known_loads else np.zeros((len(z), 6))
    ok = np.ones(len(z), bool) if lacking is None else ~np.asarray(lacking, bool)
    Y = cf.process(hold_missing(np.hstack([run.T, z, H]), ok))
    period, window = round(idc.period_s * fs), round(idc.window_s * fs)
    delay = round(idc.apply_delay_s * fs)
    n = len(Y)
    seq = np.arange(n)
    dpsi = None
    if cfg.rotor.harmonic_phase == "azimuth":  # the pipeline's AzimuthTracker, sample by sample
        from rsra.estimator.filters import AzimuthTracker

        dpsi = AzimuthTracker(cfg.rotor.omega_nominal_rad_s, 1.0 / fs).turns(
            run.azimuth, run.omega)
    for j, end in enumerate(range(period, n + 1, period)):
        sl = slice(max(0, end - window), end)
        m = end - sl.start
        job = {"job_id": j, "mode": mode, "content": content, "applies_from_seq": end - 1 + delay,
               "alpha": post.theta.copy(), "T": Y[sl, :7], "z": Y[sl, 7:13],
               "known_H": Y[sl, 13:], "seq": seq[sl], "t": run.t[sl], "ok": ok[sl].copy(),
               "known": np.full(m, known_loads), "omega": run.omega[sl]}
        if dpsi is not None:
            job["dpsi"] = dpsi[sl]
        okw = ok[sl]
        if okw.any():  # the pipeline's WindowBuffer: the raw means of the complete samples
            job["T_mean"], job["z_mean"] = run.T[sl][okw].mean(0), z[sl][okw].mean(0)
        rec = run_job(cfg, runs, cache, job)
        yield end - 1, rec, post.theta.copy(), post.P.copy()


def chi2_of(err: np.ndarray, P: np.ndarray) -> float:
    return float(err @ np.linalg.solve(P, err))


def seed_statistics(err: np.ndarray, P: np.ndarray, false_alarm: float = FALSE_ALARM) -> dict:
    """The decisions of docs/performance.md over seeds: err (S, p) final errors, P (S, p, p) the
    reported covariances."""
    S, p = err.shape
    sig = np.sqrt(np.einsum("sii->si", P))
    u = err / sig
    chi2 = np.array([chi2_of(e, Pk) for e, Pk in zip(err, P)])
    chi2_limit = float(stats.chi2.isf(false_alarm / S, p))
    z_limit = float(stats.norm.isf(false_alarm / (2 * p)))
    mean_z = u.mean(0) * math.sqrt(S)
    spread = (u**2).sum(0)
    lo = float(stats.chi2.ppf(false_alarm / (2 * p), S))
    hi = float(stats.chi2.isf(false_alarm / (2 * p), S))
    return {
        "seeds": S, "chi2": chi2, "chi2_limit": chi2_limit, "chi2_max": float(chi2.max()),
        "chi2_over_limit": int((chi2 > chi2_limit).sum()),
        "chi2_over_single_run_limit": int((chi2 > SINGLE_RUN_CHI2).sum()),
        "chi2_mean": float(chi2.mean()),
        "mean_z": mean_z, "z_limit": z_limit, "mean_z_max": float(np.abs(mean_z).max()),
        "spread": spread, "spread_bounds": (lo, hi),
        "spread_ok": bool(np.all((spread >= lo) & (spread <= hi))),
        "spread_ratio": spread / S, "sigma": sig,
    }


def seed_map(fn: Callable[[int], dict], seeds: list[int], processes: int | None = None
             ) -> list[dict]:
    """fn over seeds, one spawned process per usable core (single-threaded BLAS)."""
    use_single_thread_blas()
    if processes is None:
        try:
            processes = len(os.sched_getaffinity(0))
        except AttributeError:
            processes = os.cpu_count() or 1
    processes = max(1, min(processes, len(seeds)))
    if processes == 1:
        return [fn(s) for s in seeds]
    import multiprocessing as mp
    old = {k: os.environ.get(k) for k in BLAS_ENV}
    os.environ.update(BLAS_ENV)  # inherited by the spawned workers before numpy loads
    try:
        with mp.get_context("spawn").Pool(processes) as pool:
            return pool.map(fn, seeds, chunksize=1)
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# ------------------------------------------------------------------------------ A3
_TINY_SAMPLES = 2000


def one_seed(seed: int, tiny: bool = False) -> dict:
    from rsra.config.rig import load_config
    from rsra.sim_bus import load_scenario, simulate

    cfg = load_config()
    sc = load_scenario("ground-test")
    n = _TINY_SAMPLES if tiny else round(SWEEPS * sc.duration_s * cfg.sample_rate_hz)
    run = simulate(cfg, sc, seed=seed, n_samples=n)
    reasons: Counter = Counter()
    last_acc = None
    theta = P = None
    for _, rec, theta, P in run_calibration(cfg, run, known_loads=True):
        reasons[rec["reason"] or "accepted"] += 1
        if rec["accepted"]:
            last_acc = rec
    corr = None
    if last_acc is not None and last_acc.get("sigma_cr_corrected") is not None:
        corr = (np.asarray(last_acc["sigma_cr_corrected"], float)
                / np.asarray(last_acc["sigma_cr"], float))
    return {"seed": seed, "err": theta - run.alpha_true[-1], "P": P, "reasons": dict(reasons),
            "corrected_over_conventional": corr,
            "last_run_sigma_cr": None if last_acc is None else last_acc["sigma_cr"]}


def _one_seed_tiny(seed: int) -> dict:
    return one_seed(seed, tiny=True)


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    from rsra.config.rig import load_config
    cfg = load_config()
    sigma_max = float(np.rad2deg(cfg.identification.sigma_max_rad))
    seeds = list(range(1, 3 if args.tiny else N_SEEDS + 1))
    res = seed_map(_one_seed_tiny if args.tiny else one_seed, seeds)
    err = np.array([r["err"] for r in res])
    P = np.array([r["P"] for r in res])
    st = seed_statistics(err, P)
    sig_deg = np.rad2deg(st["sigma"])
    reasons: Counter = Counter()
    for r in res:
        reasons.update(r["reasons"])
    corr = [r["corrected_over_conventional"] for r in res if r["corrected_over_conventional"]
            is not None]
    corr_stats = None if not corr else {
        "median_per_angle": np.median(np.array(corr), axis=0).round(3),
        "max": float(np.max(corr))}
    names = cfg.rig_model().geometry.angle_names
    from rsra.sim_bus import load_scenario
    n_seed = _TINY_SAMPLES if args.tiny else round(
        SWEEPS * load_scenario("ground-test").duration_s * cfg.sample_rate_hz)
    common = {"seeds": len(seeds), "scenario": "ground-test", "sweeps": None if args.tiny else SWEEPS,
                  "samples_per_seed": n_seed, "content": cfg.identification.content_known_loads,
                  "start": "configured initial angles", "run_reasons": dict(reasons),
                  "angle_names": names, "false_alarm": FALSE_ALARM}
    w.add("chi2_per_seed", st["chi2_max"], "χ²₁₄ (largest over seeds)",
          peer=None, target=f"≤ {st['chi2_limit']:.1f} on every seed (10⁻³ overall)",
          met=st["chi2_over_limit"] == 0, chi2_limit=st["chi2_limit"],
          seeds_over_limit=st["chi2_over_limit"], chi2_mean=st["chi2_mean"],
          seeds_over_single_run_limit_36_1=st["chi2_over_single_run_limit"],
          chi2_per_seed=np.round(st["chi2"], 2), **common)
    w.add("mean_error", st["mean_z_max"], "standard errors (largest |mean| over angles)",
          target=f"every angle's mean error within {st['z_limit']:.2f} standard errors",
          met=st["mean_z_max"] <= st["z_limit"], mean_z=dict(zip(names, st["mean_z"].round(2))),
          mean_error_deg=dict(zip(names, np.rad2deg(err.mean(0)).round(4))), **common)
    lo, hi = st["spread_bounds"]
    w.add("spread", float(st["spread_ratio"].max()), "Σ(err/σ_CR)²/seeds (largest angle)",
          target=f"every angle's Σ(err/σ_CR)² within [{lo:.1f}, {hi:.1f}] (χ²_{len(seeds)}, "
          "10⁻³/28 a tail)", met=st["spread_ok"],
          spread=dict(zip(names, st["spread"].round(1))),
          smallest_ratio=float(st["spread_ratio"].min()), **common)
    w.add("sigma_cr", float(sig_deg.max()), "° (largest σ_CR over seeds and angles)",
          target=f"every σ_CR ≤ {sigma_max:g}°", met=bool(sig_deg.max() <= sigma_max),
          sigma_cr_median_deg=dict(zip(names, np.median(sig_deg, axis=0).round(3))),
          seeds_with_any_sigma_over=int((sig_deg.max(axis=1) > sigma_max).sum()),
          seeds_over_with_reasons={r["seed"]: r["reasons"] for r, s in zip(res, sig_deg)
                                   if s.max() > sigma_max},
          coloured_corrected_over_conventional_last_run=corr_stats, **common)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
