"""`rsra calibrate`: off-line known-load calibration from recordings (cli.md; model.md §7).

The recordings are made here by the simulator alone in lock-step (`LockstepSim(cfg,
autostart=True, record=…)`: the nodes start by themselves and the simulator produces SYNC, as
`rsra sim --autostart --record`), with its truth file, and read back through the reader's code
path by the command under test. Two sweeps of the `ground-test` scenario's six static
conditions (120 s) are simulated once per module (≈ 12 s); each calibration reads them in ≈ 6 s.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from rsra.daq.analysis.calibrate import (
    CalibrationError,
    content_noise_gain,
    parse_params,
    plausibility,
    start_values,
)
from rsra.daq.cli import build_parser, main
from rsra.config.rig import load_config
from rsra.daq.runtime.persistence import save_posterior
from rsra.estimator.content import ContentFilter
from rsra.estimator.posterior import PosteriorState
from rsra.sim_bus.drivers import LockstepSim
from rsra.sim_bus.truth import read_truth

SWEEP_S = 60.0  # one sweep of the six static conditions (config/scenarios/ground-test.toml)
FALSE_ALARM = 1e-3
CHI2_14 = chi2.ppf(1 - FALSE_ALARM, 14)  # 36.1
CHI2_2 = chi2.ppf(1 - FALSE_ALARM, 2)  # 13.8
SIGMA_MAX_DEG = 0.2  # model §7.3: two sweeps determine every angle within model §7.4's σ_max


def _record(cfg, folder, seconds: float, seed: int, channel: str, nodes=None) -> tuple:
    folder.mkdir(parents=True, exist_ok=True)
    log, truth = folder / "run.log", folder / "truth.npz"
    kw = {} if nodes is None else {"nodes_present": nodes}
    with LockstepSim(cfg, "ground-test", seed=seed, autostart=True, record=log,
                     channel=channel, **kw) as sim:
        sim.run(seconds)
        sim.write_truth(truth)
    return log, truth


@pytest.fixture(scope="module")
def two_sweeps(cfg, tmp_path_factory):
    return _record(cfg, tmp_path_factory.mktemp("cal"), 2 * SWEEP_S, seed=11,
                   channel="calibrate-two-sweeps")


@pytest.fixture(scope="module")
def no_balance(cfg, tmp_path_factory):
    log, _ = _record(cfg, tmp_path_factory.mktemp("nobal"), 2.0, seed=3,
                     channel="calibrate-no-balance", nodes=("rotor_speed",))
    return log


def _true_angles(truth) -> np.ndarray:
    a = read_truth(truth)["alpha_true"]
    assert np.ptp(a, axis=0).max() == 0.0  # ground-test: constant angles
    return np.asarray(a[0], float)


def _run_json(argv, capsys) -> dict:
    rc = main(["calibrate", *argv, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out)


def _one_line_error(argv, capsys) -> str:
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's own errors
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


# ------------------------------------------------------------------------------------------
# the calibration against the simulator's truth

def test_calibrate_recovers_the_true_angles_and_writes_a_fragment_that_loads(
        cfg, two_sweeps, tmp_path, capsys):
    log, truth = two_sweeps
    frag = tmp_path / "angles.toml"
    res = _run_json([str(log), "--out", str(frag)], capsys)
    alpha_true = np.degrees(_true_angles(truth))
    names = cfg.rig_model().geometry.angle_names
    assert res["names"] == list(names)
    est = np.array([p["estimate"] for p in res["parameters"]])
    sig = np.array([p["sigma_cr"] for p in res["parameters"]])
    sig_mk = np.array([p["sigma_cr_corrected"] for p in res["parameters"]])
    P = np.array(res["covariance"])
    assert np.allclose(np.sqrt(np.diag(P)), sig)
    err = est - alpha_true
    chi2_joint = float(err @ np.linalg.solve(P, err))
    print(f"chi2_14 = {chi2_joint:.2f}; sigma_CR {sig.min():.3f}-{sig.max():.3f} deg, "
          f"corrected {sig_mk.min():.3f}-{sig_mk.max():.3f}; max |err| {np.abs(err).max():.3f} deg; "
          f"residual ratio {np.round(res['residuals']['ratio'], 2)}; "
          f"iterations {res['convergence']['iterations']}")
    assert res["convergence"]["status"] == "converged"
    assert chi2_joint <= CHI2_14
    assert sig.max() <= SIGMA_MAX_DEG and sig_mk.max() <= SIGMA_MAX_DEG
    assert res["information"]["determined"] == 14
    # the truth is within ±4° (ground-test): nothing implausible
    assert res["plausibility"] == {"ok": True, "flags": []}
    start = np.array([p["start"] for p in res["parameters"]])
    assert np.allclose(start, np.degrees(cfg.identification.initial_angles_rad))
    assert np.allclose([p["change_sigma"] for p in res["parameters"]], (est - start) / sig)
    # the residuals at the estimate are what the sensor noise explains (not 8× less, as they
    # would be against the unfiltered covariance, nor larger: no model error in the simulator)
    ratio = np.array(res["residuals"]["ratio"])
    assert np.all((ratio > 0.6) & (ratio < 1.25)), ratio
    d = res["data"]
    settle = ContentFilter("static", cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                           cfg.filter.harmonics, 1).settle_samples
    assert d["samples_read"] == int(2 * SWEEP_S * cfg.sample_rate_hz)
    assert d["scored"] == d["valid"] - settle and d["valid"] >= d["samples_read"] - 1
    # the next load conditions to apply (docs/identification.md): three, within the limits,
    # the first changing the thrust beyond the ground test's 76–84 kN (the load gains)
    nxt = res["next_conditions"]
    assert len(nxt) == 3 and all(c["information_gain"] > 0 for c in nxt)
    assert abs(nxt[0]["H"][2] + 80e3) > 20e3
    assert max(abs(x) for c in nxt for x in c["H"]) <= cfg.balance.full_scale_force_N
    # the fragment: merged into the config, it carries the estimates
    assert res["fragment"] == str(frag)
    text = frag.read_text()
    assert str(log) in text and "sigma" in text
    merged = load_config(overrides=tomllib.loads(text))
    assert np.allclose(np.degrees(merged.identification.initial_angles_rad), est, atol=1e-5)
    assert np.allclose(np.degrees(merged.identification.initial_angles_rad),
                       res["alpha_all_deg"], atol=1e-5)


def test_a_subset_of_parameters_is_identified_alone_from_a_recording_folder(
        cfg, two_sweeps, tmp_path, capsys):
    """--params delta_A,theta_A with the other twelve angles started at the truth (from a saved
    posterior, --angles): only the two move, and they land on the truth."""
    log, truth = two_sweeps
    folder = tmp_path / "rec"
    folder.mkdir()
    shutil.copy(log, folder / "frames.log")  # a recording folder without its own config:
    # its rig named by --config (issue 46: a folder without config.json is not replayed on a
    # guessed rig)
    alpha_true = _true_angles(truth)
    names = cfg.rig_model().geometry.angle_names
    start = alpha_true.copy()
    start[:2] = 0.0
    state = tmp_path / "start.json"
    save_posterior(state, PosteriorState(names, start, np.eye(14) * 1e-4))
    frag = tmp_path / "two.toml"
    res = _run_json([str(folder), "--params", "delta_A,theta_A", "--angles", str(state),
                     "--out", str(frag), "--config",
                     str(Path(__file__).parents[1] / "config" / "rig.toml")], capsys)
    assert res["names"] == ["delta_A", "theta_A"]
    assert [p["start"] for p in res["parameters"]] == [0.0, 0.0]
    est = np.array([p["estimate"] for p in res["parameters"]])
    err = est - np.degrees(alpha_true[:2])
    P = np.array(res["covariance"])
    chi2_two = float(err @ np.linalg.solve(P, err))
    print(f"subset: chi2_2 = {chi2_two:.2f}, err {np.round(err, 4)} deg, "
          f"sigma {np.round(np.sqrt(np.diag(P)), 4)} deg")
    assert chi2_two <= CHI2_2
    merged = load_config(overrides=tomllib.loads(frag.read_text()))
    got = np.degrees(merged.identification.initial_angles_rad)
    assert np.allclose(got[:2], est, atol=1e-5)
    assert np.allclose(got[2:], np.degrees(alpha_true[2:]), atol=1e-5)  # kept at their start


# ------------------------------------------------------------------------------------------
# refusals and help

def test_an_unknown_parameter_is_one_line_naming_it_with_close_matches(no_balance, capsys):
    line = _one_line_error(["calibrate", str(no_balance), "--params", "delta_A,thetaA"], capsys)
    assert "'thetaA'" in line and "theta_A" in line


def test_a_recording_without_the_balance_is_refused_in_one_line(no_balance, capsys):
    line = _one_line_error(["calibrate", str(no_balance)], capsys)
    assert "no known loads" in line and "balance" in line


@pytest.mark.parametrize("argv,words", [
    (["calibrate", "/no/such/run.log"], "no such file"),
    (["calibrate", "x.log", "--content", "everything"], "--content"),
    (["calibrate", "x.log", "--prior-sigma-deg", "soon"], "--prior-sigma-deg"),
    (["calibrate", "x.log", "--prior-sigma-deg", "-1"], "--prior-sigma-deg"),
    (["calibrate", "x.log", "--max-iterations", "0"], "--max-iterations"),
])
def test_bad_arguments_exit_2_with_one_line(argv, words, capsys):
    assert words in _one_line_error(argv, capsys)


def test_help_explains_every_option(capsys):
    with pytest.raises(SystemExit) as e:
        main(["calibrate", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for action in sub.choices["calibrate"]._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help != argparse.SUPPRESS, action.dest
        if action.option_strings:
            assert action.option_strings[0] in out


# ------------------------------------------------------------------------------------------
# the pieces

def test_params_expand_angles_and_refuse_repeats(cfg):
    angles = cfg.rig_model().geometry.angle_names
    assert parse_params("angles", cfg) == angles
    assert parse_params("angles, m_z,hub_x", cfg) == angles + ("m_z", "hub_x")
    with pytest.raises(CalibrationError, match="given twice"):
        parse_params("angles,delta_A", cfg)
    with pytest.raises(CalibrationError, match="hub_z"):
        parse_params("hub_q", cfg)


def test_plausibility_flags_each_kind_of_implausible_value_and_nothing_else(cfg):
    names = ("delta_A", "psi_G", "m_x", "m_y", "I_zz", "x_A", "hub_z", "z_G")
    _, conf = start_values(cfg, names)
    ok = conf + np.array([math.radians(9.9), math.radians(-9.9), 0.49 * conf[2],
                          -0.49 * conf[3], 0.49 * conf[4], 0.19, -0.19, 0.0])
    assert plausibility(cfg, names, ok, conf) == []
    bad = conf + np.array([math.radians(10.1), math.radians(-12.0), 0.51 * conf[2],
                           -1.01 * conf[3], -0.6 * conf[4], 0.21, -0.3, 0.0])
    flags = {f.name: f.problem for f in plausibility(cfg, names, bad, conf)}
    assert set(flags) == {"delta_A", "psi_G", "m_x", "m_y", "I_zz", "x_A", "hub_z"}
    assert flags["m_y"] == "not positive" and "50%" in flags["m_x"] and "0.2 m" in flags["hub_z"]


def test_fragment_for_geometry_and_mass_parameters_loads_with_the_estimates(cfg, tmp_path):
    """The [geometry], [mass] and complete [[cells]] blocks merge into the packaged config."""
    from rsra.daq.analysis.calibrate import CalibrationData, CalibrationResult, fragment_toml
    from rsra.estimator.identification import IdentificationResult

    names = ("theta_B", "x_C", "hub_z", "m_y", "I_xx")
    _, start = start_values(cfg, names)
    est = start + np.array([math.radians(1.5), 0.012, -0.003, 25.0, -40.0])
    P = np.diag([1e-6, 1e-8, 1e-8, 4.0, 9.0])
    ident = IdentificationResult(names, "known_loads", est, P, P, np.eye(5), start, P, 1.0, 2.0,
                                 4, "converged", 100)
    data = CalibrationData(z=np.zeros((1, 6)), T=np.zeros((1, 7)), H=np.zeros((1, 6)), q=None,
                           valid=np.ones(1, bool), scored=np.ones(1, bool), content="static",
                           fs=200.0, files=("run.log",), segments=1, samples_read=1)
    alpha = np.asarray(cfg.identification.initial_angles_rad, float).copy()
    alpha[3] = est[0]
    res = CalibrationResult(names, start, np.ones(5), ident, np.ones(6), np.ones(6), 5,
                            np.ones(5), 1.0, [], (1.0, 1.0), [], alpha, data, 1.0)
    merged = load_config(overrides=tomllib.loads(fragment_toml(cfg, res)))
    # the fragment is a rig layer as it stands (issue 29): `--config fragment.toml` gives the
    # same rig, each value it sets named as coming from it
    frag = tmp_path / "calibrated.toml"
    frag.write_text(fragment_toml(cfg, res))
    layered = load_config([frag])
    assert layered.effective() == merged.effective()
    assert layered.origins["geometry.hub_centre_m"] == str(frag)
    assert layered.origins["rig.name"] == "default"
    assert math.isclose(merged.identification.initial_angles_rad[3], est[0], abs_tol=1e-7)
    assert math.isclose(merged.cells[2].position_m[0], est[1], abs_tol=1e-6)
    assert math.isclose(merged.hub_centre_m[2], est[2], abs_tol=1e-6)
    assert math.isclose(merged.effective_mass_kg[1], est[3], abs_tol=1e-3)
    assert math.isclose(merged.inertia_kg_m2[0], est[4], abs_tol=1e-3)
    # everything else as configured
    assert [c.name for c in merged.cells] == [c.name for c in cfg.cells]
    for a, b in zip(merged.cells, cfg.cells):
        assert a.node == b.node and np.allclose(a.nominal_axis, b.nominal_axis)
    assert np.allclose(np.delete(merged.cells[2].position_m, 0), np.delete(cfg.cells[2].position_m, 0))
    assert merged.shaft_tilt_rad == cfg.shaft_tilt_rad


@pytest.mark.parametrize("kind", ["static", "harmonics", "broadband"])
def test_content_noise_gain_is_the_variance_ratio_of_white_noise(cfg, kind, rng):
    """The residuals' 'noise' column: σ² of white noise through the content filter."""
    n = 400_000
    x = rng.standard_normal((n, 1))
    cf = ContentFilter(kind, cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       cfg.filter.harmonics, 1)
    y = cf.process(x)[cf.settle_samples:, 0]
    g = content_noise_gain(kind, cfg)
    assert abs(float(y.var()) / g - 1.0) < 0.1, (kind, y.var(), g)


def test_calibrate_selects_the_load_gain_structure_and_writes_its_fragment(cfg):
    """Issue 19: on a recording whose angles move with the load (0.025°/kN of each cell's
    own load) under the `calibration` design (17 conditions, held 5 s here), `rsra calibrate`
    runs the structure test over the recording's windows, selects `cell_load_angles` and
    writes ``[identification.structure]``; the fragment loads, and a pipeline built from it
    uses the structure from the start (its angles and the z correction). The recording is
    the off-line physics through the calibrate path's own content filter (no bus: fast).
    Break-checked: with ``structure_of`` returning no fit the fragment has no structure
    block and the test fails."""
    from rsra.daq.analysis.calibrate import CalibrationData, calibrate, fragment_toml, structure_of
    from rsra.daq.runtime.pipeline import EstimatorPipeline
    from rsra.estimator.balance import inertial_loads
    from rsra.sim_bus import load_scenario, simulate

    sc = load_scenario("calibration", **{"angles.mode": "cell_load",
                                         "angles.cell_gain_deg_per_kN": 0.025,
                                         "angles.resolution_deg": 0.0001,
                                         "loads.hold_s": 5.0, "duration_s": 85.0})
    fs = cfg.sample_rate_hz
    run = simulate(cfg, sc, seed=4, n_samples=round(85.0 * fs))
    cf = ContentFilter("static", fs, cfg.rotor.omega_nominal_rad_s, cfg.filter.harmonics, 19)
    Y = cf.process(np.hstack([inertial_loads(cfg.rig_model(), run.accel), run.T,
                              run.H_balance]))
    n = len(Y)
    valid = np.ones(n, bool)
    scored = valid.copy()
    scored[:cf.settle_samples] = False
    data = CalibrationData(z=Y[:, :6], T=Y[:, 6:13], H=Y[:, 13:], q=None, valid=valid,
                           scored=scored, content="static", fs=fs, files=("sim",), segments=1,
                           samples_read=n)
    result = calibrate(cfg, data)
    struct = structure_of(cfg, result)
    assert struct["structure"] == "not_constant"
    assert struct["candidates"][0]["structure"] == "cell_load_angles"
    fit = struct["structure_fit"]
    assert fit is not None and fit["structure"] == "cell_load_angles"
    text = fragment_toml(cfg, result, struct)
    assert "[identification.structure]" in text
    merged = load_config(overrides=tomllib.loads(text))
    got = merged.identification.structure_fit
    assert got["structure"] == "cell_load_angles"
    assert np.allclose(got["beta"], fit["beta"], rtol=1e-12, atol=0)
    assert np.allclose(got["alpha0"], fit["alpha0"], atol=1e-8)
    # the true gains within the fit's σ (χ² over the 14 gains at 10⁻³)
    from rsra.sim_bus.physics import AircraftPhysics
    g_true = AircraftPhysics(cfg, sc, seed=4).cell_gain
    u = (np.array(fit["beta"]) - g_true) / np.array(fit["beta_sigma"])
    assert float(u @ u) <= chi2.isf(FALSE_ALARM, 14)
    pipe = EstimatorPipeline(merged, merged.identification.initial_angles_rad,
                             identification=False)
    pipe.angles.set_structure(got)
    assert pipe.structure is not None and pipe.structure.structure == "cell_load_angles"


@pytest.mark.slow
def test_calibrate_with_structure_end_to_end_over_the_bus(cfg, tmp_path, capsys):
    """The bus path of issue 19 end to end (slow: ≈ 2.5 min; `make test-all`): the simulated
    aircraft with load-dependent angles (0.025°/kN of each cell's own load) under the
    `calibration` design is recorded from the bus (candump log, lock-step), `rsra calibrate`
    reads the recording through the service's reader, selects `cell_load_angles` and writes
    `[identification.structure]`; a service started with that fragment merged into its config
    uses the structure from its first sample and its hub loads on the same aircraft are within
    1.5× the static bound on held loads, and closer to the truth than with the constant-angle
    calibration alone (measured: 0.97–1.10 against 0.97–1.19 of the bound)."""
    from rsra.daq.runtime.service import Service, ServiceOptions
    from rsra.estimator.noise_budget import noise_budget
    from rsra.sim_bus.scenarios import load_scenario

    variants = {"angles.mode": "cell_load", "angles.cell_gain_deg_per_kN": 0.025,
                "angles.resolution_deg": 0.0001, "loads.hold_s": 5.0, "duration_s": 85.0}
    sc = load_scenario("calibration", **variants)
    log = tmp_path / "cal.log"
    with LockstepSim(cfg, sc, seed=4, autostart=True, record=log,
                     channel="calibrate-structure-e2e") as sim:
        sim.run(85.0)
    frag = tmp_path / "cal.toml"
    res = _run_json([str(log), "--out", str(frag)], capsys)
    struct = res["structure"]
    assert struct["structure"] == "not_constant", struct
    assert struct["structure_fit"]["structure"] == "cell_load_angles"
    text = frag.read_text()
    assert "[identification.structure]" in text
    merged = load_config(overrides=tomllib.loads(text))

    def hub_error(config) -> tuple[np.ndarray, object]:
        svc = Service(config, ServiceOptions(sim="calibration", scenario_variants=variants,
                                             speed=None, duration=40.0, zenoh=False, seed=4,
                                             identification=False, keep_truth=True))
        hubs = []
        svc.add_sink(lambda k, p: hubs.append(p) if k == "hub_loads" else None)
        svc.run()
        truth = svc.sim.truth_arrays()
        H_true = np.asarray(truth["H_true"], float)
        i = np.array([h["seq"] for h in hubs])
        Hs = np.array([h["H_static"] for h in hubs], float)
        held = np.array(["transient" not in h["flags"] for h in hubs]) & (i >= 200)
        e = Hs[held] - H_true[i[held]]
        return np.sqrt(np.nanmean(e**2, axis=0)), svc

    bound = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad).total
    with_structure, svc = hub_error(merged)
    assert svc.pipeline.structure is not None
    assert svc.pipeline.structure.structure == "cell_load_angles"
    constant = load_config(overrides={"identification": {
        k: v for k, v in tomllib.loads(text)["identification"].items() if k != "structure"}})
    without, _ = hub_error(constant)
    print("hub-load RMS / static bound with the structure", np.round(with_structure / bound, 2),
          "constant angles only", np.round(without / bound, 2))
    assert np.all(with_structure / bound <= 1.5)
    assert np.max(without / bound) > np.max(with_structure / bound)
