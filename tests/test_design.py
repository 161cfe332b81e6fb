"""The experiment design (estimator/design.py, daq/runtime/next_conditions.py; issue 19): the
information of a condition, the D-optimal order of the `calibration` scenario, the
recommendation in `rsra calibrate` and in the live known-load `angles` records."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.estimator.design import (
    cell_gain_prior,
    cell_gain_structure,
    cell_loads,
    constant_angle_structure,
    feasible,
    greedy_order,
    log_det_covariance_path,
    next_conditions,
    rest_inertial_loads,
)
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.identification import KnownLoadProblem, Parameterisation
from rsra.sim_bus import load_scenario

N_SAMPLES = 1000.0
FLOOR = 100.0


@pytest.fixture(scope="module")
def rig():
    cfg = load_config()
    model = cfg.rig_model()
    alpha = np.radians(np.random.default_rng(19).uniform(-4, 4, 14))
    return cfg, model, alpha


def _structures(model, alpha):
    P = np.eye(14) * math.radians(5.0) ** 2
    const = constant_angle_structure(model, alpha, P, N_SAMPLES, moment_floor=FLOOR)
    gain = cell_gain_structure(model, alpha, cell_gain_prior(math.radians(5.0)), N_SAMPLES,
                               moment_floor=FLOOR)
    return const, gain


def test_cell_loads_satisfy_the_balance(rig):
    _, model, alpha = rig
    H = load_scenario("calibration").loads.conditions
    T = cell_loads(model, alpha, H)
    S = wrench_matrix(model.geometry, alpha)
    R0 = hub_transfer_matrix(model.geometry, "body")
    resid = rest_inertial_loads(model)[None] - T @ S.T - H @ R0.T
    assert np.abs(resid).max() < 1e-6
    # gravity is in the rest loads: m_z g on Z, downwards (z down, accelerometers read −g)
    assert rest_inertial_loads(model)[2] == pytest.approx(-model.mass.mass[2] * 9.80665)


def test_feasible_keeps_the_cells_within_full_scale(rig):
    cfg, model, alpha = rig
    fs = np.array([c.full_scale_N for c in cfg.cells])
    # 150 kN on X: within the balance's 200 kN, but cell G alone carries X (111 kN full scale)
    H = np.array([[0, 0, -80e3, 0, 0, 0], [150e3, 0, -80e3, 0, 0, 0], [0, 0, -400e3, 0, 0, 0],
                  [0, 0, -80e3, 60e3, 0, 0]])
    ok = feasible(model, alpha, H, cell_full_scale=fs, force_limit=200e3, moment_limit=50e3)
    assert ok.tolist() == [True, False, False, False]


def test_information_function_equals_the_identifications_information(rig):
    """A condition held for n noise-free samples: the Gauss–Newton information the
    identification computes from the data equals the design's information function."""
    _, model, alpha = rig
    H = load_scenario("calibration").loads.conditions[3]
    n = 50
    T = np.repeat(cell_loads(model, alpha, H), n, axis=0)
    z = np.repeat(rest_inertial_loads(model)[None], n, axis=0)
    par = Parameterisation(model, None, alpha, moment_floor=FLOOR, known_loads=True)
    M_data = KnownLoadProblem(par, z, T, np.repeat(H[None], n, axis=0)).evaluate(
        par.initial()).information
    const = constant_angle_structure(model, alpha, np.eye(14), n, moment_floor=FLOOR)
    M_design = const.information(H[None])[0]
    np.testing.assert_allclose(M_design, M_data, rtol=1e-9, atol=1e-9 * np.abs(M_data).max())
    # the load-gain structure's angle block is the same information
    gain = cell_gain_structure(model, alpha, np.eye(28), n, moment_floor=FLOOR)
    np.testing.assert_allclose(gain.information(H[None])[0][:14, :14], M_data,
                               rtol=1e-9, atol=1e-9 * np.abs(M_data).max())


def test_cell_gain_information_by_finite_differences(rig):
    """∂e/∂κ of the load-gain structure against a finite difference of the residual with
    α_j → α_j + κ_j T_cell(j)."""
    from rsra.estimator.design import cell_gain_jacobian

    _, model, alpha = rig
    H = load_scenario("calibration").loads.conditions[5]
    T = cell_loads(model, alpha, H)[0]
    D = cell_gain_jacobian(model, alpha, T)[0]
    cell = np.repeat(np.arange(7), 2)
    h = 1e-12  # rad per N
    for j in (0, 9, 13):
        a_p, a_m = alpha.copy(), alpha.copy()
        a_p[j] += h * T[cell[j]]
        a_m[j] -= h * T[cell[j]]
        de = -(wrench_matrix(model.geometry, a_p) - wrench_matrix(model.geometry, a_m)) @ T / (2 * h)
        np.testing.assert_allclose(D[:, 14 + j], de, rtol=1e-5, atol=1e-6 * np.abs(de).max())


def test_recommended_order_reduces_log_det_faster_than_the_scenario_order(rig):
    """The `calibration` scenario's 17 conditions in the D-optimal order: log det P of both
    structures is at or below the file order's after every number of conditions, and the
    summed area between the curves is positive."""
    _, model, alpha = rig
    structures = _structures(model, alpha)
    C = load_scenario("calibration").loads.conditions
    assert C.shape == (17, 6)
    order = greedy_order(structures, C)
    assert sorted(order) == list(range(17)) and order != list(range(17))
    total_file = sum(log_det_covariance_path(s, C, range(17)) for s in structures)
    total_greedy = sum(log_det_covariance_path(s, C, order) for s in structures)
    assert np.all(total_greedy <= total_file + 1e-9)
    assert total_greedy[-1] == pytest.approx(total_file[-1])  # the same 17 in the end
    assert np.sum(total_file - total_greedy) > 20.0  # nats·conditions: measured 105 (seed 19)


def test_ground_test_cannot_determine_load_gains_and_the_recommendation_moves_thrust(rig):
    """Six ground-test conditions (thrust 76–84 kN) leave the per-cell load gains at their
    prior; the next condition recommended changes the thrust by more than the ground test
    spans, and adds information about the gains."""
    cfg, model, alpha = rig
    const, gain = _structures(model, alpha)
    G = load_scenario("ground-test").loads.conditions
    M_gain = gain.M0 + gain.information(G).sum(0) * 2  # two sweeps
    sig = np.sqrt(np.diag(np.linalg.inv(M_gain)))[14:]
    prior = np.sqrt(np.diag(np.linalg.inv(gain.M0)))[14:]
    assert np.all(sig > 0.75 * prior)  # measured 0.79–1.00 of the prior (seed 19)
    # one sweep of the `calibration` design (thrust 60 / 100 kN) determines them far better
    Cal = load_scenario("calibration").loads.conditions
    sig_cal = np.sqrt(np.diag(np.linalg.inv(gain.M0 + gain.information(Cal).sum(0))))[14:]
    assert np.median(sig_cal / prior) < 0.4  # measured 0.21
    P_const = np.linalg.inv(const.M0 + const.information(G).sum(0) * 2)
    from dataclasses import replace
    structures = [replace(const, M0=np.linalg.inv(P_const)), replace(gain, M0=M_gain)]
    fs = np.array([c.full_scale_N for c in cfg.cells])
    from rsra.estimator.design import candidate_grid
    grid = candidate_grid([200e3] * 3 + [50e3] * 3)
    grid = grid[feasible(model, alpha, grid, cell_full_scale=fs, force_limit=200e3,
                         moment_limit=50e3)]
    recs = next_conditions(structures, grid, 3)
    assert len(recs) == 3
    from rsra.estimator.design import information_gains
    assert recs[0].information_gain == pytest.approx(
        information_gains(structures, grid).sum(1).max(), rel=1e-12)
    first = recs[0]
    assert abs(first.H[2] + 80e3) > 20e3  # thrust well outside the ground test's 76–84 kN
    assert first.by_structure["cell_gain"] > first.by_structure["constant"] > 0
    # greedy gains do not grow (submodularity of log det)
    gains = [r.information_gain for r in recs]
    assert gains[0] >= gains[1] >= gains[2] > 0
    # every recommendation within the limits
    assert feasible(model, alpha, np.array([r.H for r in recs]), cell_full_scale=fs,
                    force_limit=200e3, moment_limit=50e3).all()


def test_live_known_load_records_carry_next_conditions():
    """The identification worker's known-load records carry `next_conditions` (a list of
    {H, information_gain, by_structure}), filter-error records do not."""
    from bench.a3_known_load import run_calibration
    from rsra.sim_bus import simulate

    cfg = load_config()
    run = simulate(cfg, "ground-test", seed=3, duration_s=15.0)
    recs = [r for _, r, _, _ in run_calibration(cfg, run, known_loads=True)]
    assert recs
    for r in recs:
        nxt = r["next_conditions"]
        assert isinstance(nxt, list) and len(nxt) == 3
        for c in nxt:
            assert set(c) == {"H", "information_gain", "by_structure"} and len(c["H"]) == 6
            assert c["information_gain"] > 0 and set(c["by_structure"]) == {"constant",
                                                                             "cell_gain"}
    # the record is JSON-safe
    from rsra.daq.jsonout import dumps
    dumps(recs[-1])
