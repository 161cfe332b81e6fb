"""The structure test of constant angles against the competing structures (issue 19;
estimator/structure.py, docs/identification.md "When the angles are not constant").

Size and power are checked on window means drawn exactly from the balance model (each window's
samples carry the configured sensor noise, so its mean residual has covariance W/n), which
runs in milliseconds per window; the service path (simulator → content filter → worker code)
is checked for the record field and the no-cycle property.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import stats

from rsra.config.rig import load_config
from rsra.estimator.balance import accelerometer_covariance
from rsra.estimator.geometry import hub_transfer_matrix, skew, wrench_matrix
from rsra.estimator.structure import (
    STRUCTURES,
    StructureTest,
    design_ranks,
    fit_constant,
    parameter_names,
    spend,
    test_structures as structure_fits,
)

GROUND = np.array([[0.0, 0.0, -80e3, 0, 0, 0], [10e3, 0, -76e3, 0, 0, 0], [0, 10e3, -84e3, 0, 0, 0],
                   [0, 0, -78e3, 20e3, 0, 0], [0, 0, -82e3, 0, 20e3, 0],
                   [0, 0, -80e3, 0, 0, 15e3]])


def design17() -> np.ndarray:
    """2^(6−2) fractional factorial (E = ABC on thrust, F = BCD on yaw) plus a centre point."""
    rows = [[0.0, 0.0, -80e3, 0.0, 0.0, 0.0]]
    for a, b, c, d in itertools.product([-1, 1], repeat=4):
        rows.append([1e4 * a, 1e4 * b, -80e3 - 1e4 * a * b * c, 2e4 * c, 2e4 * d,
                     1.5e4 * b * c * d])
    return np.array(rows)


@pytest.fixture(scope="module")
def model():
    return load_config().rig_model()


def _windows(model, rng, H_conds, alpha, *, n=40, sweeps=1, truth=None, beta=None):
    """Window samples [z, T, H] of static conditions: T the minimum-strain split of the true
    wrench, every channel with its configured noise. ``truth``: a structure in the data."""
    g = model.geometry
    R0 = hub_transfer_matrix(g, "body")
    mass_g = np.concatenate([model.mass.mass * np.array([0, 0, 9.80665]), np.zeros(3)])
    Sz = accelerometer_covariance(model) + np.diag([0, 0, 0, 1, 1, 1]) * 100.0**2
    Lz = np.linalg.cholesky(Sz)
    sT, sH = np.asarray(model.cell_sigma), np.asarray(model.balance_sigma)
    out = []
    for _ in range(sweeps):
        for H in H_conds:
            Ht, a, R = H.copy(), alpha.copy(), R0.copy()
            extra = np.zeros(6)
            if truth == "hub_position":
                R[3:, :3] = skew(g.hub_position + beta)
            elif truth == "external_load":
                extra = beta.reshape(6, 3) @ H[:3]
            Hb = H.copy()
            if truth == "balance":  # the balance reads H_b with H_true = D H_b
                Rp = np.eye(3) + skew(beta[6:])
                D = np.zeros((6, 6))
                D[:3, :3], D[3:, 3:] = Rp @ np.diag(1 + beta[:3]), Rp @ np.diag(1 + beta[3:6])
                Hb = np.linalg.solve(D, H)
            z = -mass_g  # at rest: z = S T + R H (+ extra)
            S = wrench_matrix(g, a)
            T = np.linalg.lstsq(S, z - R @ Ht - extra, rcond=None)[0]
            if truth == "cell_load_angles":
                for _ in range(3):  # the angles move with the cell loads they make
                    a = alpha + beta * T[np.arange(14) // 2]
                    S = wrench_matrix(g, a)
                    T = np.linalg.lstsq(S, z - R @ Ht, rcond=None)[0]
            x = np.hstack([z + rng.standard_normal((n, 6)) @ Lz.T,
                           T + rng.standard_normal((n, 7)) * sT,
                           Hb + rng.standard_normal((n, 6)) * sH])
            out.append(x)
    return out


def test_spending_sums_to_the_overall_rate():
    assert sum(spend(k) for k in range(1, 200001)) == pytest.approx(1e-3, rel=1e-4)


def test_the_statistic_is_chi2_with_the_rank_as_dof(model):
    """Size, one look: constant angles, ground-test design; q_s/rank has mean 1 and the
    exceedances at a 5 % level per structure stay within a binomial 10⁻³ band over 100 runs.
    A three-condition design tests with the rank (≤ 4 after the 14 angles), not the nominal
    count. The dof claim is structural: rank ≤ residual dof < nominal."""
    rng = np.random.default_rng(7)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    runs = 100
    q = {s: [] for s in STRUCTURES}
    exceed = {s: 0 for s in STRUCTURES}
    for _ in range(runs):
        xs = _windows(model, rng, GROUND, alpha)
        means, counts = np.array([x.mean(0) for x in xs]), np.array([len(x) for x in xs], float)
        a = fit_constant(model, alpha + np.radians(0.05), means, counts, 100.0)
        fits, _ = structure_fits(model, a, means, counts, 100.0, 0.05 * len(STRUCTURES))
        for f in fits:
            q[f.structure].append(f.statistic / f.rank)
            exceed[f.structure] += f.statistic > f.limit
    se = {s: np.sqrt(2.0 / max(f.rank, 1) / runs) for s, f in zip(STRUCTURES, fits)}
    for s in STRUCTURES:
        assert abs(np.mean(q[s]) - 1.0) < 3.3 * se[s] + 0.05, (s, np.mean(q[s]))
        assert exceed[s] <= stats.binom.isf(1e-3, runs, 0.05), (s, exceed[s])
    # three conditions: 18 equations, 14 angle directions → at most 4 testable directions.
    # Windows of 1000 samples as in the service: with 40 the one weakly determined angle
    # direction is too uncertain for the linearisation (measured: mean ratio 1.7 at 40,
    # 0.84 at 1000)
    q3 = []
    for _ in range(30):
        xs = _windows(model, rng, GROUND[[0, 1, 3]], alpha, n=1000)
        means, counts = np.array([x.mean(0) for x in xs]), np.array([len(x) for x in xs], float)
        fits, info = structure_fits(model, fit_constant(model, alpha, means, counts, 100.0),
                                    means, counts, 100.0, 0.05)
        ext = fits[list(STRUCTURES).index("external_load")]
        assert 0 < ext.rank <= info["residual_dof"] <= 18 - 14 < ext.nominal
        q3.append(ext.statistic / ext.rank)
    assert abs(np.mean(q3) - 1.0) < 0.4, np.mean(q3)


def test_sequential_false_alarms_stay_within_the_overall_rate(model):
    """The alpha spending over looks: with the overall rate set to 0.2 (to be measurable in
    60 runs of 12 looks), the runs that ever say not_constant stay below the binomial 10⁻³
    limit of 0.2."""
    rng = np.random.default_rng(11)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    runs, said = 60, 0
    for _ in range(runs):
        st = StructureTest(model, 100.0, false_alarm=0.2, min_samples=10)
        ever = False
        for x in _windows(model, rng, GROUND, alpha, sweeps=2):
            ever |= st.add_window(x, alpha).structure == "not_constant"
        said += ever
    assert said <= stats.binom.isf(1e-3, runs, 0.2), said


@pytest.mark.parametrize("truth,beta", [
    ("hub_position", np.array([0.004, -0.004, 0.008])),
    ("balance", np.array([0.002, -0.002, 0.001, 0.002, 0, -0.002, 0.0005, -0.0005, 0.0005])),
    ("external_load", np.array([-0.01, 0, 0, 0, 0, 0, 0, 0, 0, 0, -0.02, 0, 0, 0, 0, 0, 0, 0])),
    ("cell_load_angles", np.radians(0.03e-3) * np.resize([1.0, -1.0, -1.0, 1.0], 14)),
])
def test_the_richer_design_selects_the_true_structure(model, truth, beta):
    """Power: on the 17-condition design every structure is rejected against constant angles
    and the true one is ranked first, explains the data, and is selected with its parameters
    near the truth. Break-checked: ranking by the statistic alone (no misfit, no p-value)
    fails for the hub-position truth. Windows of 1000 samples (the service's 5 s): with 200
    the balance errors here (0.2 %, 0.03°) leave the external load explaining the data within
    χ²₁ of the balance (misfit 76.9 against 63.0, margin 22.5) — not separated, and nothing
    is selected (the selection rule, docs/identification.md)."""
    rng = np.random.default_rng(3)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    st = StructureTest(model, 100.0, min_samples=10)
    for x in _windows(model, rng, design17(), alpha, n=1000, truth=truth, beta=beta):
        v = st.add_window(x, alpha)
    assert v.structure == "not_constant"
    assert v.candidates[0]["structure"] == truth and v.candidates[0]["explains"]
    assert v.selected is not None and v.selected["structure"] == truth
    err = (v.selected["beta"] - beta) / v.selected["sigma"]
    assert np.all(np.abs(err) < 5.0), err


def test_the_ground_test_design_cannot_separate_hub_position_from_external_load(model):
    """The six conditions: 36 equations, the angles take 14; every structure has fewer
    testable directions than in the 17-condition design, and the hub position lies inside
    the external load's span (union rank = the external load's)."""
    rng = np.random.default_rng(5)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    m6 = np.array([x.mean(0) for x in _windows(model, rng, GROUND, alpha)])
    m17 = np.array([x.mean(0) for x in _windows(model, rng, design17(), alpha)])
    r6, r17 = design_ranks(model, alpha, m6), design_ranks(model, alpha, m17)
    assert r6["angle_rank"] == 14 and r6["equations"] == 36
    assert r17["rank"] == {s: len(parameter_names(s, model)) for s in STRUCTURES}
    pair = r6["pairs"]["hub_position+external_load"]
    assert pair["shared"] == r6["rank"]["hub_position"] == 3


def test_a_change_in_time_restarts_the_accumulation_instead_of_rejecting(model):
    """A 1° step of every angle after one sweep (A4): the windows at loads seen before show it
    as a change in time; the test restarts and never says not_constant. Break-checked: with
    the time test off (time_level 0) it says not_constant at the first windows after the
    step."""
    rng = np.random.default_rng(9)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    step = np.radians(1.0) * rng.choice([-1.0, 1.0], 14)
    st = StructureTest(model, 100.0, min_samples=10)
    verdicts = []
    for a in (alpha, alpha + step):
        for x in _windows(model, rng, GROUND, a, n=200):
            verdicts.append(st.add_window(x, alpha).structure)
    assert "not_constant" not in verdicts
    assert st.restarts >= 1


def _calibration(cfg, sc, seed, sweeps=2):
    from bench.a3_known_load import run_calibration
    from rsra.sim_bus import simulate
    run = simulate(cfg, sc, seed=seed, n_samples=round(sweeps * sc.duration_s * cfg.sample_rate_hz))
    return [rec for _, rec, _, _ in run_calibration(cfg, run, known_loads=True)]


LOAD_DEPENDENT = {"angles": "linear", "angles.linear_deg_per_unit": [2e-5, 2e-5, 1e-5, 1e-5, 1e-5, 1e-5],
                  "angles.resolution_deg": 0.001}


@pytest.mark.slow
def test_load_dependent_ground_test_four_sweeps_never_resets():
    """The longer run: four sweeps of the load-dependent ground-test, two seeds."""
    from rsra.sim_bus import load_scenario
    cfg = load_config()
    for seed in (2, 3):
        recs = _calibration(cfg, load_scenario("ground-test", **LOAD_DEPENDENT), seed, sweeps=4)
        assert recs[-1]["structure"] == "not_constant"
        assert not any(r["reason"] == "reset" for r in recs)


def test_structure_jacobians_are_the_derivatives_of_the_structure_residuals(model):
    """∂m/∂β of every structure against central differences of the exact residual."""
    from rsra.estimator.structure import structure_jacobian, structure_residual
    rng = np.random.default_rng(4)
    alpha = np.radians(rng.uniform(-4, 4, 14))
    x = _windows(model, rng, design17()[5:6], alpha, n=10)[0].mean(0)
    steps = {"cell_load_angles": 1e-11, "hub_position": 1e-6, "balance": 1e-7,
             "external_load": 1e-6}
    for st in STRUCTURES:
        p = len(parameter_names(st, model))
        J = structure_jacobian(st, model, alpha, x)
        h = steps[st]
        fd = np.stack([-(structure_residual(st, model, alpha, h * e, x)
                         - structure_residual(st, model, alpha, -h * e, x)) / (2 * h)
                       for e in np.eye(p)], axis=1)
        assert np.abs(fd - J).max() < 1e-6 * np.abs(J).max(), st


def test_load_dependent_ground_test_says_not_constant_without_the_reset_cycle():
    """The issue's symptom, service path (simulator → content filter → the worker's code):
    angles moving 0.1–0.4° with the load, the six-condition ground-test, two sweeps. Every
    known-load record carries ``structure``; it ends ``not_constant`` with the ranked
    candidates (the top one explaining the data); after the verdict no run is accepted and no reset happens.
    Break-checked: without the not_constant branch in SequentialPosterior.update this test
    fails (and with the structure test off the run goes accepted → inconsistent → reset →
    accepted: seed 1 resets at windows 10 and 21)."""
    from rsra.sim_bus import load_scenario
    cfg = load_config()
    recs = _calibration(cfg, load_scenario("ground-test", **LOAD_DEPENDENT), seed=1)
    assert all(r["structure"] in ("constant", "not_constant", "undetermined") for r in recs)
    kinds = [r["structure"] for r in recs]
    assert kinds[-1] == "not_constant"
    first = kinds.index("not_constant")
    assert all(k == "not_constant" for k in kinds[first:])
    assert not any(r["reason"] == "reset" for r in recs)
    assert not any(r["accepted"] for r in recs[first:])
    cands = recs[-1]["candidates"]
    assert len(cands) >= 2 and cands[0]["explains"]
    assert {"statistic", "dof", "parameters", "per_kN"} <= set(cands[0])


def test_thrust_dependent_angles_are_rejected_at_the_first_runs_and_nothing_moves_after():
    """Issue 25 (session 18): the ground test with angles following the thrust (1° per 100 kN,
    the flight rig, seed 2). The cold start's looks gave no verdict (the constant fit does not
    converge from 0°) and the constant-angle runs on them were accepted 3.7° off (χ²₁₄ 210–330
    against the truth); then, once `not_constant`, the drift test's trend moved the posterior
    up to 75° through rejected runs. Now the look is judged again at the run's own estimate
    (the constant fit's misfit where Gauss–Newton diverges at its minimum) — `not_constant` by
    the 7th window — and while it stands nothing moves the posterior.
    Break-checked: without ``StructureTest.rejudge`` the first `not_constant` is the 11th
    window (this fails); without the `not_constant` branch of ``_follow_drift`` the posterior
    moves at window 20 (this fails)."""
    from bench.a6_flight import flight_rig_path
    from bench.a3_known_load import run_calibration
    from rsra.sim_bus import load_scenario, simulate
    cfg = load_config(flight_rig_path())
    run = simulate(cfg, load_scenario("ground-test", angles="linear"), seed=2, duration_s=120)
    out = [(rec, th, P) for _, rec, th, P in run_calibration(cfg, run, known_loads=True)]
    kinds = [r["structure"] for r, _, _ in out]
    first = kinds.index("not_constant")
    assert first <= 6, kinds
    assert all(k == "not_constant" for k in kinds[first:])
    assert not any(r["accepted"] for r, _, _ in out[first:])
    th0, P0 = out[first][1], out[first][2]
    for r, th, P in out[first:]:
        assert np.array_equal(th, th0) and np.array_equal(P, P0), r["seq"]


def test_a_cold_start_look_is_judged_at_the_runs_estimate():
    """Constant angles, the same start: the first accepted run's look (no verdict from 0°)
    is judged at the run's own estimate — `constant`, not `undetermined` (break-checked:
    without the re-judgement it says `undetermined`)."""
    from bench.a6_flight import flight_rig_path
    from bench.a3_known_load import run_calibration
    from rsra.sim_bus import load_scenario, simulate
    cfg = load_config(flight_rig_path())
    run = simulate(cfg, load_scenario("ground-test"), seed=2, duration_s=30)
    recs = [rec for _, rec, _, _ in run_calibration(cfg, run, known_loads=True)]
    acc = [r for r in recs if r["accepted"]]
    assert acc and acc[0]["structure"] == "constant"
    assert not any(r["structure"] == "not_constant" for r in recs)


def test_filter_error_records_carry_no_structure():
    from rsra.estimator.posterior import AnglesRecord
    rec = AnglesRecord(t=None, seq=1, mode="filter_error", content="harmonics", accepted=False,
                       reason="not_identifiable", names=("a",), alpha=np.zeros(1),
                       P=np.eye(1), sigma_cr=None, sigma_cr_corrected=None, determined=0,
                       information=None, nu=None, cost=None, iterations=0, window=(0, 1),
                       applies_from_seq=None)
    assert "structure" not in rec.to_dict()


# ------------------------------------------------------------------------------------------
# The selected structure in the service's hub loads (issue 19, "Done means")
# ------------------------------------------------------------------------------------------
CELL_LOAD = {"angles.mode": "cell_load", "angles.cell_gain_deg_per_kN": 0.025,
             "angles.resolution_deg": 0.0001}


def service_hub_errors(cfg, scenario, seed, *, hold_s, structure=True, sweeps=1):
    """The service's estimator path in lock-step without the bus: the simulator's samples
    through ``EstimatorPipeline`` (hub loads, calibration branch), every identification job
    run by the worker's own ``handle_job`` and delivered at once (lock-step). Returns per
    condition (held part: from 2 s after its start, samples not flagged ``transient``) the
    RMS of (H − H_true) over the static bound per axis, (C, 6), the first sample of each
    condition, and the sample the structure was applied from (None: never), and the last
    angles record. ``structure=False``: the pipeline ignores ``structure_fit`` (the constant
    angles, as before issue 19)."""
    from types import SimpleNamespace

    from rsra.daq.runtime.ident_worker import build_identification, handle_job
    from rsra.daq.runtime.pipeline import EstimatorPipeline
    from rsra.estimator.noise_budget import noise_budget
    from rsra.estimator.transient import TRANSIENT
    from rsra.sim_bus import simulate

    n = round(sweeps * scenario.duration_s * cfg.sample_rate_hz)
    run = simulate(cfg, scenario, seed=seed, n_samples=n)
    post, runs, cache = build_identification(cfg)
    p = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad)
    if not structure:
        p.angles.set_structure = lambda fit: None
    H = np.full((n, 6), np.nan)
    transient = np.zeros(n, bool)
    applied, last = None, None
    for i in range(n):
        s = SimpleNamespace(seq=i, sync=i % 240 + 1, t=float(run.t[i]), T=run.T[i],
                            accel=run.accel[i], flags=[], drive=None, omega=float(run.omega[i]),
                            azimuth=float(run.azimuth[i]), known_H=run.H_balance[i],
                            cell_status=np.zeros(7, int), lost_before=0)
        out = p.process(s)
        hub = next(r for k, r in out.records if k == "hub_loads")
        if hub["H"] is not None:
            H[i] = hub["H"]
        transient[i] = TRANSIENT in hub["flags"]
        if applied is None and p.structure is not None:
            applied = i
        if out.job is not None:
            res = handle_job(cfg, post, runs, cache, out.job, None)
            last = res.record.to_dict()
            p.deliver(res.record, arrival_seq=i, job_id=out.job.job_id)
    bound = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad,
                         cfg.hub_frame).total
    hold = round(hold_s * cfg.sample_rate_hz)
    starts = np.arange(0, n - hold + 1, hold)
    ratios = []
    for s0 in starts:
        m = np.zeros(n, bool)
        m[s0 + round(2.0 * cfg.sample_rate_hz):s0 + hold] = True
        m &= ~transient & np.isfinite(H).all(axis=1)
        e = H[m] - run.H_true[m]
        ratios.append(np.sqrt(np.mean(e**2, axis=0)) / bound)
    return np.array(ratios), starts, applied, last


def test_the_selected_structure_brings_the_hub_loads_within_their_bounds():
    """Done means (issue 19): a ground test whose angles move with the load (every angle
    0.025°/kN of its own cell's load, 0.2–0.5° between conditions), the ``calibration``
    design (17 conditions, held 5 s here), the service's path in lock-step: the structure
    test selects ``cell_load_angles``, the worker fits it, the record carries
    ``structure_fit`` and the pipeline applies it; from then on the hub loads of every
    condition are within the static bound on every axis (RMS over the held samples).
    Measured (seed 3): selected at the 7th window, the last ten conditions at ≤ 0.62 of the
    bound (worst axis N); the first seven, before, up to 2.9. Break-checked: with the
    pipeline ignoring ``structure_fit`` (``structure=False``) the same ten conditions reach
    4.9× the bound on N (four of them over 1) and the test fails."""
    from rsra.sim_bus import load_scenario
    cfg = load_config()
    sc = load_scenario("calibration", **CELL_LOAD, **{"loads.hold_s": 5.0, "duration_s": 85.0})
    ratios, starts, applied, last = service_hub_errors(cfg, sc, seed=3, hold_s=5.0)
    assert last["structure"] == "not_constant"
    assert last["candidates"][0]["structure"] == "cell_load_angles"
    fit = last["structure_fit"]
    assert fit is not None and fit["structure"] == "cell_load_angles"
    assert applied is not None
    after = starts + round(2.0 * cfg.sample_rate_hz) >= applied  # held under the structure
    assert after.sum() >= 10  # the conditions after the structure is in force (10 of 17)
    assert ratios[after].max() <= 1.0, np.round(ratios[after], 2)


def test_the_pipeline_correction_is_the_structure_hub_load_model(model):
    """``StructureCorrection`` (what the per-sample path applies) against the exact static
    estimate of each structure (``structure.hub_loads``): exact for the transfer-matrix
    structures and the balance, first order for the load-dependent angles (0.5° between the
    reference and the load, up to 0.75° at 3σ: measured ≤ 6.9 N, N·m; bounds are hundreds).
    Break-checked:
    the sign of B flipped fails the cell-load case (1 157 N)."""
    from rsra.estimator.structure import StructureCorrection, hub_loads

    rng = np.random.default_rng(2)
    g = model.geometry
    alpha = np.radians(rng.uniform(-3, 3, 14))
    T_ref = np.abs(rng.normal(15e3, 3e3, 7))
    T = T_ref + rng.normal(0, 10e3, (20, 7))
    z = rng.normal(0, 2e3, (20, 6))
    betas = {"cell_load_angles": np.radians(0.025e-3) * rng.choice([-1.0, 1.0], 14),
             "hub_position": rng.normal(0, 0.005, 3),
             "balance": np.concatenate([rng.normal(0, 0.003, 6), rng.normal(0, 1e-3, 3)]),
             "external_load": rng.normal(0, 0.01, 18)}
    R0i = np.linalg.inv(hub_transfer_matrix(g, "body"))
    for st, beta in betas.items():
        fit = {"structure": st, "alpha0": alpha.tolist(), "beta": beta.tolist(),
               "T_ref": T_ref.tolist()}
        c = StructureCorrection(model, fit)
        S = wrench_matrix(g, c.alpha)
        H = np.array([R0i @ (c.correct(zn, Tn) - S @ Tn) for zn, Tn in zip(z, T)])
        exact = hub_loads(st, model, alpha, beta, z, T)
        tol = 10.0 if st == "cell_load_angles" else 1e-6
        assert np.abs(H - exact).max() <= tol, st
