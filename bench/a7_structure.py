"""A7 — the structure test: constant angles against the competing structures (issue 19).

Monte Carlo over seeds of the off-line physics; the structure test of the service
(``estimator.structure.StructureTest``, one look per known-load window) on the windows of the
calibration branch (one causal ``static`` content filter over inertial loads, load cells and
balance; 5-s windows, the content filter's settling unscored), without the Levenberg–Marquardt
runs (the test does not use them). Arms per seed:

* ``constant`` — ``ground-test``, constant angles, two sweeps (24 looks);
* ``step`` — ``ground-test`` with A4's step (1° on every angle, random sign) after the first
  sweep, two sweeps (24 looks): a change in time, not a load dependence;
* ``constant_calibration`` — the ``calibration`` scenario's design (2^(6−2) fractional
  factorial plus a centre point: 17 conditions; held 5 s instead of its 10 s to halve the
  cost, one sweep, 17 looks), constant angles;
* one arm per competing structure on the same design: ``cell_load_angles`` (every angle moves
  0.025°/kN of its own cell's static load, random sign; 0.2–0.4° between conditions),
  ``hub_position`` (hub centre off by 5 mm per axis, random signs), ``balance`` (scale errors
  0.3 % per axis and 0.05° alignment per axis, random signs), ``external_load`` (the report's
  Phase I load: x-force 1 % of X and roll torque 0.02 N·m/N of Y, opposite in phase).

Decisions (10⁻³ overall):

* size: the runs that ever say ``not_constant`` in the constant and step arms are at most the
  binomial 10⁻³ limit of the test's own rate 10⁻³ over the seeds (0 or 1 of 100, 2 of 200);
* power/selection: in every seed of every structure arm the verdict is ``not_constant`` and the
  selected structure is the true one;
* the selected structure's estimate against the truth (A3's decisions): per seed the joint χ²
  of the error of [α0, β] against the fit's covariance ≤ χ²_p(1 − 10⁻³/seeds);
* hub loads: per condition window, the static estimate under the selected structure minus the
  true hub load (window means), over the static bound per axis (noise budget, one sample): on
  every axis at every condition ≤ 1, beside the same with the constant-angle fit.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import stats

from bench.common import arg_parser, writer_from_args

BENCH = "a7_structure"
FALSE_ALARM = 1e-3
N_SEEDS = 100
STRUCTURE_ARMS = ("cell_load_angles", "hub_position", "balance", "external_load")
HOLD_S = 5.0
CALIBRATION_CONDITIONS = 17  # the `calibration` scenario's


def arm_variants(arm: str, seed: int) -> tuple[dict, dict]:
    """(scenario variants, the truth of the structure's parameters)."""
    rng = np.random.default_rng(10_000 + seed)
    var: dict = {}
    truth: dict = {}
    if arm in ("constant", "step"):
        if arm == "step":
            var.update({"angles": "step", "angles.step_at_s": [60.0]})
        return var, truth
    var.update({"loads.hold_s": HOLD_S, "duration_s": HOLD_S * CALIBRATION_CONDITIONS})
    if arm == "cell_load_angles":
        var.update({"angles.mode": "cell_load", "angles.cell_gain_deg_per_kN": 0.025,
                    "angles.resolution_deg": 0.0001})
    elif arm == "hub_position":
        off = 0.005 * rng.choice([-1.0, 1.0], 3)
        var["rig_errors.hub_offset_m"] = off.tolist()
        truth["beta"] = off
    elif arm == "balance":
        sc_ = 0.003 * rng.choice([-1.0, 1.0], 6)
        al = 0.05 * rng.choice([-1.0, 1.0], 3)
        var.update({"rig_errors.balance_scale": sc_.tolist(),
                    "rig_errors.balance_align_deg": al.tolist()})
        truth["beta"] = np.concatenate([sc_, np.radians(al)])
    elif arm == "external_load":
        var.update({"unmodelled": True, "unmodelled.x_N_per_N_X": 0.01,
                    "unmodelled.roll_Nm_per_N_Y": 0.02, "unmodelled.phase_deg": 180.0})
        U = np.zeros((6, 3))
        U[0, 0], U[3, 1] = -0.01, -0.02  # cos 180° = −1 on the static load
        truth["beta"] = U.reshape(-1)
    return var, truth


def run_arm(cfg, arm: str, seed: int, tiny: bool = False) -> dict:
    from rsra.estimator.balance import inertial_loads
    from rsra.estimator.content import ContentFilter
    from rsra.estimator.structure import StructureTest, fit_constant, hub_loads
    from rsra.sim_bus import load_scenario, simulate
    from rsra.sim_bus.physics import AircraftPhysics

    model, fs = cfg.rig_model(), cfg.sample_rate_hz
    var, truth = arm_variants(arm, seed)
    sc = load_scenario("ground-test" if arm in ("constant", "step") else "calibration", **var)
    if arm not in ("constant", "step"):
        assert len(sc.loads.conditions) == CALIBRATION_CONDITIONS
    n = round((2 if arm in ("constant", "step") else 1) * sc.duration_s * fs)
    if tiny:
        n = min(n, round(20 * fs))
    run = simulate(cfg, sc, seed=seed, n_samples=n)
    cf = ContentFilter("static", fs, cfg.rotor.omega_nominal_rad_s, tuple(cfg.filter.harmonics),
                       39)
    z = inertial_loads(model, run.accel)
    # the truth through the same content filter as the data (its lag behind a ramp included)
    Y = cf.process(np.hstack([z, run.T, run.H_balance, run.H_true, run.alpha_true]))
    st = StructureTest(model, cfg.identification.moment_floor_Nm)
    alpha0 = np.asarray(cfg.identification.initial_angles_rad, float)
    P = round(5.0 * fs)
    verdicts, windows, a_true = [], [], []
    ends = list(range(P, len(Y) + 1, P))
    for k, end in enumerate(ends):
        x = Y[end - P:end]
        # the joint fits at the last look only (what the decisions judge; the verdict of
        # every look comes from the linear statistics either way)
        st.joint_fits = k == len(ends) - 1
        if k == 0:
            x = x[cf.settle_samples:]
        v = st.add_window(x[:, :19], alpha0)
        verdicts.append(v.structure)
        windows.append(x.mean(axis=0))
        a_true.append(windows[-1][25:39])
    out = {"arm": arm, "seed": seed, "ever_not_constant": "not_constant" in verdicts,
           "final": verdicts[-1], "restarts": st.restarts,
           "first_not_constant": verdicts.index("not_constant") + 1
           if "not_constant" in verdicts else None,
           "top": v.candidates[0]["structure"] if v.candidates else None,
           "selected": None if v.selected is None else v.selected["structure"]}
    if arm not in STRUCTURE_ARMS:
        return out
    # the truth of [α0, β]
    phys = AircraftPhysics(cfg, sc, seed=seed)
    beta_true = phys.cell_gain if arm == "cell_load_angles" else truth["beta"]
    # hub loads per window: constant-angle fit vs the selected structure, over the static bound
    from rsra.estimator.noise_budget import noise_budget
    bound = noise_budget(model, alpha0, "body").total
    W = np.array(windows)
    means = np.array([c.mean for c in st.clusters])
    counts = np.array([c.n for c in st.clusters], float)
    a_const = fit_constant(model, alpha0, means, counts, cfg.identification.moment_floor_Nm)
    zT = (W[:, :6], W[:, 6:13])
    Hc = hub_loads("constant", model, a_const, None, *zT)
    out["hub_error_constant"] = float(np.max(np.abs(Hc - W[:, 19:25]) / bound))
    if v.selected is not None and v.selected["structure"] == arm:
        sel = v.selected
        Hs = hub_loads(arm, model, sel["alpha"], sel["beta"], *zT)
        out["hub_error_selected"] = float(np.max(np.abs(Hs - W[:, 19:25]) / bound))
        out["hub_ratio_axes_selected"] = np.max(np.abs(Hs - W[:, 19:25]) / bound, axis=0).tolist()
        out["hub_ratio_axes_constant"] = np.max(np.abs(Hc - W[:, 19:25]) / bound, axis=0).tolist()
        # A3's decision against each condition's truth: the angles in force at the condition
        # (α0 + g∘T_c for the cell-load gains, α0 otherwise), χ²₁₄ against the fit's covariance
        na = len(sel["alpha"])
        chis = []
        for wmean, at in zip(W, a_true):
            Jc = np.hstack([np.eye(na), np.diag(wmean[6:13][np.arange(na) // 2])
                            if arm == "cell_load_angles" else np.zeros((na, len(sel["beta"])))])
            ac = sel["alpha"] + (sel["beta"] * wmean[6:13][np.arange(na) // 2]
                                 if arm == "cell_load_angles" else 0.0)
            ea = ac - at
            chis.append(float(ea @ np.linalg.solve(Jc @ sel["P"] @ Jc.T, ea)))
        out["chi2_conditions_max"] = max(chis)
        out["conditions"] = len(chis)
        err = np.concatenate([sel["alpha"] - phys.alpha_base, sel["beta"] - beta_true])
        Pj = sel["P"]
        out["chi2"] = float(err @ np.linalg.solve(Pj, err))
        out["dof"] = len(err)
        sig = np.sqrt(np.diag(Pj))
        out["u"] = (err / sig).tolist()
    return out


def one_seed(seed: int, tiny: bool = False) -> list[dict]:
    from rsra.config.rig import load_config
    cfg = load_config()
    arms = ("constant", "step", "constant_calibration") + STRUCTURE_ARMS
    return [run_arm(cfg, arm, seed, tiny) for arm in arms]


def _one_seed_tiny(seed: int) -> list[dict]:
    return one_seed(seed, tiny=True)


def _map_with_progress(fn, seeds: list[int], processes: int | None = None
                       ) -> list[list[dict]]:
    """fn over seeds, one spawned single-threaded process per core; every finished seed is
    appended to $A7_PROGRESS (JSON lines) when set, so that a cut-short run keeps its seeds."""
    import json
    import multiprocessing as mp
    import os

    from bench.common import BLAS_ENV, jsonable, use_single_thread_blas
    use_single_thread_blas()
    progress = os.environ.get("A7_PROGRESS")
    try:
        procs = len(os.sched_getaffinity(0))
    except AttributeError:
        procs = os.cpu_count() or 1
    procs = max(1, min(processes or procs, len(seeds)))
    out = []
    old = {k: os.environ.get(k) for k in BLAS_ENV}
    os.environ.update(BLAS_ENV)
    try:
        with mp.get_context("spawn").Pool(procs) as pool:
            for rs in pool.imap_unordered(fn, seeds):
                out.append(rs)
                if progress:
                    with open(progress, "a", encoding="utf-8") as f:
                        f.write(json.dumps(jsonable(rs)) + "\n")
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return out


def main(argv: list[str] | None = None) -> int:
    p = arg_parser(__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=N_SEEDS, help=f"seeds (default {N_SEEDS})")
    p.add_argument("--first-seed", type=int, default=1,
                   help="the first seed (default 1): split a run over machines or sessions")
    p.add_argument("--processes", type=int, default=None,
                   help="worker processes (default: one per core)")
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error("--seeds must be at least 1")
    w = writer_from_args(BENCH, args)
    first = args.first_seed
    seeds = list(range(first, first + (1 if args.tiny else args.seeds)))
    res = [r for rs in _map_with_progress(_one_seed_tiny if args.tiny else one_seed, seeds,
                                          args.processes)
           for r in rs]
    report(res, len(seeds), w)
    return 0


def report(res: list[dict], S: int, w) -> None:
    """The decisions of the module docstring over S seeds' arm results, as result lines."""
    by = {a: [r for r in res if r["arm"] == a] for a in ("constant", "step",
                                                         "constant_calibration",
                                                         *STRUCTURE_ARMS)}
    size_limit = int(stats.binom.isf(FALSE_ALARM, S, FALSE_ALARM))
    common = {"seeds": S, "false_alarm": FALSE_ALARM}
    for arm in ("constant", "step", "constant_calibration"):
        rs = by[arm]
        k = sum(r["ever_not_constant"] for r in rs)
        w.add(f"size_{arm}", k, "runs ever saying not_constant",
              target=f"≤ {size_limit} of {S} (binomial 10⁻³ limit of the test's rate 10⁻³)",
              met=k <= size_limit, finals={f: sum(r["final"] == f for r in rs)
                                         for f in ("constant", "not_constant", "undetermined")},
              restarts=sum(r["restarts"] for r in rs), **common)
    chi2_limit = None
    for arm in STRUCTURE_ARMS:
        rs = by[arm]
        right = sum(r["selected"] == arm for r in rs)
        said = sum(r["final"] == "not_constant" for r in rs)
        chis = [r["chi2"] for r in rs if "chi2" in r]
        dof = next((r["dof"] for r in rs if "dof" in r), None)
        chi2_limit = float(stats.chi2.isf(FALSE_ALARM / S, dof)) if dof else math.inf
        he_s = [r["hub_error_selected"] for r in rs if "hub_error_selected" in r]
        he_c = [r["hub_error_constant"] for r in rs]
        firsts = [r["first_not_constant"] for r in rs if r["first_not_constant"]]
        w.add(f"select_{arm}", right / S, "fraction of seeds selecting the true structure",
              target="1.0 (every seed), verdict not_constant", met=right == S and said == S,
              not_constant=said, top=dict(zip(*np.unique([str(r["top"]) for r in rs],
                                                          return_counts=True))),
              first_look_median=float(np.median(firsts)) if firsts else None, **common)
        if not chis:  # no seed selected the structure (e.g. --tiny: too few conditions)
            w.skip(f"estimate_{arm}", "no seed selected the structure",
                   target=f"≤ {chi2_limit:.1f} on every seed (10⁻³ over seeds)")
            w.skip(f"hub_loads_{arm}", "no seed selected the structure",
                   target="≤ 1 on every axis at every condition, every seed")
            continue
        w.add(f"estimate_{arm}", max(chis),
              f"χ²_{dof} of [α0, β] against the fit's covariance (largest over seeds)",
              target=f"≤ {chi2_limit:.1f} on every seed (10⁻³ over seeds)",
              met=bool(chis) and len(chis) == S and max(chis) <= chi2_limit,
              chi2_mean=float(np.mean(chis)) if chis else None, dof=dof, **common)
        cc = [r["chi2_conditions_max"] for r in rs if "chi2_conditions_max" in r]
        ncond = next((r["conditions"] for r in rs if "conditions" in r), 1)
        cc_limit = float(stats.chi2.isf(FALSE_ALARM / (S * ncond), 14))
        w.add(f"angles_per_condition_{arm}", max(cc),
              "χ²₁₄ of the angles at each condition against its truth (A3; largest over seeds "
              "and conditions)",
              target=f"≤ {cc_limit:.1f} (10⁻³ over seeds × {ncond} conditions)",
              met=len(cc) == S and max(cc) <= cc_limit, **common)
        axes = ("X", "Y", "Z", "L", "M", "N")
        ax_s = np.max([r["hub_ratio_axes_selected"] for r in rs
                       if "hub_ratio_axes_selected" in r], axis=0)
        ax_c = np.max([r["hub_ratio_axes_constant"] for r in rs
                       if "hub_ratio_axes_constant" in r], axis=0)
        w.add(f"hub_loads_{arm}", max(he_s),
              "largest |Ĥ − H| / static bound over axes and conditions (window means)",
              target="≤ 1 on every axis at every condition, every seed (selected structure)",
              met=bool(he_s) and len(he_s) == S and max(he_s) <= 1.0,
              constant_model=max(he_c), constant_model_median=float(np.median(he_c)),
              per_axis_selected=dict(zip(axes, np.round(ax_s, 3).tolist())),
              per_axis_constant=dict(zip(axes, np.round(ax_c, 3).tolist())),
              **common)


if __name__ == "__main__":
    raise SystemExit(main())
