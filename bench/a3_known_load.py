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

Arms (``--arms``; default both): ``clean`` — the run as simulated (the decisions above);
``drop_cell_A`` — the same seeds with 10 % of cell_A's frames dropped at random (issue 29: a
sample lacking a cell is held in the content filter and left out of the likelihood, as the
service does with ``drop:cell_A:0.1``). The drop arm reports the fraction of runs accepted (the
clean arm's as its peer), the joint χ²₁₄ of every accepted run's posterior against its window's
truth (10⁻³ over the seeds × runs tested), the decisions above on its final posteriors, σ honesty
(RMS err/σ per angle and the fraction beyond 3σ over the accepted runs) and ``samples_used``.
``--extend`` adds the arms' lines to the latest full run of this bench.

Seeds run one process per core (spawned, single-threaded BLAS; ``--processes`` to choose).
``run_calibration`` and ``seed_statistics`` are shared with A4 and A5.
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
ARMS = ("clean", "drop_cell_A")
DROP_NODE, DROP_P = "cell_A", 0.1  # the drop arm: each cell_A frame lost with this probability


# ------------------------------------------------------------------------------ the harness
def run_calibration(cfg, run, *, known_loads: bool, initial_state=None,
                    lacking: np.ndarray | None = None, lacking_label: str | None = None,
                    posterior_out: list | None = None
                    ) -> Iterator[tuple[int, dict, np.ndarray, np.ndarray]]:
    """The service's calibration branch over an off-line run: yields, per window,
    (last sample, the angles record, posterior θ, posterior P) in window order.
    ``initial_state``: a saved posterior to start from (``--angles``). ``lacking``: samples
    that lack an input (a dropped frame: the sample is not measured), as the pipeline
    treats them: the content filter's input holds the last complete sample, a short gap
    interpolated once it closes (estimator.content.hold_missing), the sample is not ``ok``
    (not scored);
    ``posterior_out``: a list the run's ``SequentialPosterior`` is appended to (its
    ``state()`` is what ``identification.state_file`` would hold). ``lacking_label`` names the input they lack (its flag, e.g. ``missing:cell_A``: the record's
    ``missing_inputs``; default ``unusable``, as a sample with no flag saying why)."""
    from rsra.daq.runtime.ident_worker import build_identification, run_job
    from rsra.estimator.balance import inertial_loads
    from rsra.estimator.content import ContentFilter, hold_missing

    model = cfg.rig_model()
    idc, fs = cfg.identification, cfg.sample_rate_hz
    post, runs, cache = build_identification(cfg, initial_state)
    if posterior_out is not None:  # the caller's handle on the posterior (its saved state)
        posterior_out.append(post)
    mode = "known_loads" if known_loads else "filter_error"
    content = idc.content_known_loads if known_loads else idc.content_filter_error
    # daq.pipeline: x = [T, z, H] through one causal content filter per mode
    cf = ContentFilter(content, fs, cfg.rotor.omega_nominal_rad_s, tuple(cfg.filter.harmonics),
                       7 + 6 + 6)
    z = inertial_loads(model, run.accel)
    H = run.H_balance if known_loads else np.zeros((len(z), 6))
    ok = np.ones(len(z), bool) if lacking is None else ~np.asarray(lacking, bool)
    missing = None
    if lacking is not None:  # the pipeline's bits of reasons.input_labels
        from rsra.daq.runtime.reasons import input_labels

        labels = input_labels(cfg)
        bit = labels.index(lacking_label) if lacking_label in labels else len(labels) - 1
        missing = np.where(ok, np.uint64(0), np.uint64(1 << bit))
    X = np.hstack([run.T, z, H])
    X[~ok, :13] = 0.0  # what the pipeline has of a sample not measured: no cells, no inertial
    Y = cf.process(hold_missing(X, ok))
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
        if missing is not None:
            job["missing"] = missing[sl].copy()
        rec = run_job(cfg, runs, cache, job)
        # the covariance the service states (records, files): the load spread added
        yield (end - 1, rec, post.reference.reported_theta(post.theta),
               post.reference.reported(post.P))


def _nanmax(x: np.ndarray) -> float | None:
    """The largest finite value; None when there is none (no accepted run: a tiny run)."""
    x = np.asarray(x, float)
    return float(np.nanmax(x)) if np.isfinite(x).any() else None


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


def drop_mask(seed: int, n: int, p: float = DROP_P) -> np.ndarray:
    """The drop arm's lost samples: each of cell_A's n frames lost with probability p, drawn
    from the seed (a stream of its own: the simulation's draws are the clean arm's)."""
    return np.random.default_rng([seed, 29]).random(n) < p


def one_arm(seed: int, arm: str = "clean", tiny: bool = False) -> dict:
    from rsra.config.rig import load_config
    from rsra.sim_bus import load_scenario, simulate

    cfg = load_config()
    sc = load_scenario("ground-test")
    n = _TINY_SAMPLES if tiny else round(SWEEPS * sc.duration_s * cfg.sample_rate_hz)
    run = simulate(cfg, sc, seed=seed, n_samples=n)
    lacking = drop_mask(seed, n) if arm == "drop_cell_A" else None
    w = round(cfg.identification.window_s * cfg.sample_rate_hz)
    reasons: Counter = Counter()
    last_acc = None
    theta = P = None
    runs = []
    for end, rec, theta, P in run_calibration(cfg, run, known_loads=True, lacking=lacking,
                                              lacking_label=f"missing:{DROP_NODE}"):
        reasons[rec["reason"] or "accepted"] += 1
        if rec["accepted"]:
            last_acc = rec
            truth = run.alpha_true[max(0, end + 1 - w):end + 1].mean(0)
            miss = {m["input"]: m["fraction"] for m in rec.get("missing_inputs") or []}
            runs.append({"err": theta - truth, "sigma": np.sqrt(np.diag(P)),
                         "chi2": chi2_of(theta - truth, P),
                         "samples_used": rec.get("samples_used"),
                         "window": min(w, end + 1),
                         "missing": miss.get(f"missing:{DROP_NODE}", 0.0)})
    corr = None
    if last_acc is not None and last_acc.get("sigma_cr_corrected") is not None:
        corr = (np.asarray(last_acc["sigma_cr_corrected"], float)
                / np.asarray(last_acc["sigma_cr"], float))
    return {"seed": seed, "arm": arm, "err": theta - run.alpha_true[-1], "P": P,
            "reasons": dict(reasons), "runs_total": sum(reasons.values()), "accepted_runs": runs,
            "dropped_fraction": None if lacking is None else float(lacking.mean()),
            "corrected_over_conventional": corr,
            "last_run_sigma_cr": None if last_acc is None else last_acc["sigma_cr"]}


def one_seed(seed: int, tiny: bool = False) -> dict:
    """The clean arm of one seed (A4 and A5 compare with it)."""
    return one_arm(seed, "clean", tiny)


def _one_seed_tiny(seed: int) -> dict:
    return one_seed(seed, tiny=True)


class _Seed:
    """Picklable fn over seeds for ``seed_map``: the selected arms of one seed."""

    def __init__(self, arms: tuple[str, ...], tiny: bool) -> None:
        self.arms, self.tiny = arms, tiny

    def __call__(self, seed: int) -> dict:
        return {arm: one_arm(seed, arm, self.tiny) for arm in self.arms}


def accepted_run_statistics(rows: list[dict], false_alarm: float = FALSE_ALARM) -> dict:
    """Every accepted run's posterior against its window's truth, over an arm's seeds: the
    acceptance, the joint χ²₁₄ (limit at 10⁻³ over the seeds × runs tested), σ honesty per
    angle (RMS err/σ, fraction beyond 3σ) and the samples the likelihood used."""
    n_runs = sum(r["runs_total"] for r in rows)
    acc = [x for r in rows for x in r["accepted_runs"]]
    limit = float(stats.chi2.isf(false_alarm / max(n_runs, 1), 14))
    chi2 = np.array([x["chi2"] for x in acc]) if acc else np.zeros(0)
    u = np.array([x["err"] / x["sigma"] for x in acc]) if acc else np.zeros((0, 14))
    used = [x["samples_used"] / x["window"] for x in acc if x["samples_used"] is not None]
    return {"runs": n_runs, "accepted": len(acc), "accepted_fraction": len(acc) / max(n_runs, 1),
            "seeds_without_accepted_run": sum(1 for r in rows if not r["accepted_runs"]),
            "chi2_limit": limit, "chi2_max": float(chi2.max()) if acc else 0.0,
            "chi2_over_limit": int((chi2 > limit).sum()),
            "chi2_over_single_run_limit": int((chi2 > SINGLE_RUN_CHI2).sum()),
            "chi2_mean": float(chi2.mean()) if acc else None,
            "rms_z": np.sqrt((u**2).mean(0)) if acc else np.full(14, np.nan),
            "beyond_3_sigma": float((np.abs(u) > 3).mean()) if acc else 0.0,
            "samples_used_fraction": float(np.mean(used)) if used else None,
            "samples_used_min_fraction": float(np.min(used)) if used else None,
            "missing_fraction": float(np.mean([x["missing"] for x in acc])) if acc else None}


def main(argv: list[str] | None = None) -> int:
    p = arg_parser(__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=N_SEEDS,
                   help=f"number of seeds (default {N_SEEDS}; fewer only when time is short)")
    p.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS),
                   help="the arms to run (default: all)")
    p.add_argument("--extend", action="store_true",
                   help="add these arms' lines to the latest full run of this bench")
    p.add_argument("--processes", type=int, default=None,
                   help="worker processes (default: one per usable core)")
    args = p.parse_args(argv)
    w = writer_from_args(BENCH, args)
    if args.extend and not args.tiny:
        from bench.common import latest_run, read_lines
        prev = latest_run(read_lines(w.path))
        if prev:
            w.run_id = prev[0]["run_id"]
    arms = tuple(a for a in ARMS if a in args.arms)
    seeds = list(range(1, 3 if args.tiny else args.seeds + 1))
    res = seed_map(_Seed(arms, args.tiny), seeds, processes=args.processes)
    clean = None
    for arm in arms:
        rows = [r[arm] for r in res]
        if arm == "clean":
            clean = accepted_run_statistics(rows)
            _report_clean(w, rows, args.tiny, clean)
        else:
            _report_drop(w, arm, rows, args.tiny, clean)
    return 0


def _common(rows: list[dict], tiny: bool, arm: str) -> dict:
    from rsra.config.rig import load_config
    from rsra.sim_bus import load_scenario

    cfg = load_config()
    reasons: Counter = Counter()
    for r in rows:
        reasons.update(r["reasons"])
    n_seed = _TINY_SAMPLES if tiny else round(
        SWEEPS * load_scenario("ground-test").duration_s * cfg.sample_rate_hz)
    out = {"seeds": len(rows), "scenario": "ground-test", "sweeps": None if tiny else SWEEPS,
           "samples_per_seed": n_seed, "content": cfg.identification.content_known_loads,
           "start": "configured initial angles", "run_reasons": dict(reasons),
           "angle_names": cfg.rig_model().geometry.angle_names, "false_alarm": FALSE_ALARM}
    if arm != "clean":
        out["arm"] = arm
        out["dropped"] = f"{DROP_NODE} frames, probability {DROP_P:g} each"
        out["dropped_fraction_mean"] = float(np.mean([r["dropped_fraction"] for r in rows]))
    return out


def _report_clean(w, res: list[dict], tiny: bool, acc: dict) -> None:
    from rsra.config.rig import load_config
    cfg = load_config()
    sigma_max = float(np.rad2deg(cfg.identification.sigma_max_rad))
    err = np.array([r["err"] for r in res])
    P = np.array([r["P"] for r in res])
    st = seed_statistics(err, P)
    sig_deg = np.rad2deg(st["sigma"])
    corr = [r["corrected_over_conventional"] for r in res if r["corrected_over_conventional"]
            is not None]
    corr_stats = None if not corr else {
        "median_per_angle": np.median(np.array(corr), axis=0).round(3),
        "max": float(np.max(corr))}
    common = _common(res, tiny, "clean")
    names = common["angle_names"]
    w.add("chi2_per_seed", st["chi2_max"], "χ²₁₄ (largest over seeds)",
          peer=None, target=f"≤ {st['chi2_limit']:.1f} on every seed (10⁻³ overall)",
          met=st["chi2_over_limit"] == 0, chi2_limit=st["chi2_limit"],
          seeds_over_limit=st["chi2_over_limit"], chi2_mean=st["chi2_mean"],
          seeds_over_single_run_limit_36_1=st["chi2_over_single_run_limit"],
          chi2_per_seed=np.round(st["chi2"], 2),
          accepted_runs={k: v for k, v in acc.items() if k != "rms_z"},
          accepted_runs_rms_z=dict(zip(names, np.round(acc["rms_z"], 3))), **common)
    w.add("mean_error", st["mean_z_max"], "standard errors (largest |mean| over angles)",
          target=f"every angle's mean error within {st['z_limit']:.2f} standard errors",
          met=st["mean_z_max"] <= st["z_limit"], mean_z=dict(zip(names, st["mean_z"].round(2))),
          mean_error_deg=dict(zip(names, np.rad2deg(err.mean(0)).round(4))), **common)
    lo, hi = st["spread_bounds"]
    w.add("spread", float(st["spread_ratio"].max()), "Σ(err/σ_CR)²/seeds (largest angle)",
          target=f"every angle's Σ(err/σ_CR)² within [{lo:.1f}, {hi:.1f}] (χ²_{len(res)}, "
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


def _report_drop(w, arm: str, rows: list[dict], tiny: bool, clean: dict | None) -> None:
    """The drop arm's lines; the clean arm of the same run (when run) as the peer."""
    from rsra.config.rig import load_config
    cfg = load_config()
    sigma_max = float(np.rad2deg(cfg.identification.sigma_max_rad))
    acc = accepted_run_statistics(rows)
    st = seed_statistics(np.array([r["err"] for r in rows]), np.array([r["P"] for r in rows]))
    sig_deg = np.rad2deg(st["sigma"])
    common = _common(rows, tiny, arm)
    names = common["angle_names"]
    peer = "clean arm (same seeds)" if clean is not None else None

    def pf(key: str):
        return None if clean is None else clean[key]

    w.add(f"{arm}_accepted", acc["accepted_fraction"], "fraction of runs accepted",
          peer=peer, peer_figure=pf("accepted_fraction"),
          target="runs accepted in every seed (the calibration is not switched off)",
          met=acc["seeds_without_accepted_run"] == 0, runs=acc["runs"],
          accepted=acc["accepted"], seeds_without_accepted_run=acc["seeds_without_accepted_run"],
          samples_used_fraction_mean=acc["samples_used_fraction"],
          samples_used_fraction_min=acc["samples_used_min_fraction"],
          missing_inputs_fraction_mean=acc["missing_fraction"], **common)
    w.add(f"{arm}_accepted_runs_chi2", acc["chi2_max"],
          "χ²₁₄ (worst accepted run's posterior against its window's truth)",
          peer=peer, peer_figure=pf("chi2_max"),
          target=f"≤ {acc['chi2_limit']:.1f} (10⁻³ over seeds × runs tested)",
          met=acc["chi2_over_limit"] == 0, chi2_limit=acc["chi2_limit"],
          runs_over_limit=acc["chi2_over_limit"],
          runs_over_single_run_limit_36_1=acc["chi2_over_single_run_limit"],
          chi2_mean=acc["chi2_mean"], **common)
    w.add(f"{arm}_chi2_per_seed", st["chi2_max"], "χ²₁₄ of the final posterior (largest over "
          "seeds)", target=f"≤ {st['chi2_limit']:.1f} on every seed (10⁻³ overall)",
          met=st["chi2_over_limit"] == 0, seeds_over_limit=st["chi2_over_limit"],
          chi2_mean=st["chi2_mean"], mean_z=dict(zip(names, st["mean_z"].round(2))),
          mean_z_limit=st["z_limit"], mean_error_met=bool(st["mean_z_max"] <= st["z_limit"]),
          **common)
    lo, hi = st["spread_bounds"]
    rms = acc["rms_z"]
    w.add(f"{arm}_sigma_honest", float(st["spread_ratio"].max()),
          "Σ(err/σ)²/seeds of the final posterior (largest angle)",
          target=f"every angle's Σ(err/σ)² within [{lo:.1f}, {hi:.1f}] (χ²_{len(rows)}, "
          "10⁻³/28 a tail); RMS err/σ and the fraction beyond 3σ over accepted runs reported",
          met=st["spread_ok"], spread=dict(zip(names, st["spread"].round(1))),
          smallest_ratio=float(st["spread_ratio"].min()),
          accepted_runs_rms_z=dict(zip(names, np.round(rms, 3))),
          accepted_runs_rms_z_max=_nanmax(rms),
          accepted_runs_beyond_3_sigma=acc["beyond_3_sigma"],
          clean_accepted_runs_rms_z_max=None if clean is None else _nanmax(clean["rms_z"]),
          clean_accepted_runs_beyond_3_sigma=pf("beyond_3_sigma"),
          sigma_max_deg=float(sig_deg.max()), sigma_max_met=bool(sig_deg.max() <= sigma_max),
          sigma_median_deg=dict(zip(names, np.median(sig_deg, axis=0).round(3))), **common)


if __name__ == "__main__":
    raise SystemExit(main())
