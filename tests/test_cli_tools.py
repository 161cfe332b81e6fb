"""The bench-rig commands `rsra nodes`, `rsra zero` and `rsra angles show|reset` (docs/cli.md §10–§12).

Bus tests run the simulator's CANopen nodes on python-can's virtual bus (real threads: the
commands talk SDO to them; each test its own channel). Nothing waits for a fixed time: the
commands end on their own (heartbeats heard, SDO answered, --seconds of acquisition time).
Statistical tolerances are 5 σ of the mean (false alarm ≈ 6e-7 per check, < 1e-3 per test).
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import re

import numpy as np
import pytest
from helpers_canopen import channel_name

from rsra.daq.cli import build_parser, main
from rsra.config.rig import G0, config_dir, load_config, parse_config
from rsra.daq.runtime.persistence import load_posterior, save_posterior
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.posterior import PosteriorState

EDS = config_dir() / "eds"
RIG = config_dir() / "rig.toml"
PRE_OPERATIONAL = 0x7F


# ------------------------------------------------------------------------------------------
# helpers

def rest_scenario(Z: float = 0.0, nodes_present=("rotor_speed", "balance")):
    """The aircraft at rest: gravity and sensor noise, no rotor harmonics, true angles 0 (the
    configured initial angles), optionally a static thrust Z (N, body axes)."""
    from rsra.sim_bus.scenarios import parse_scenario

    return parse_scenario({
        "scenario": {"name": "rest", "duration_s": 60.0, "seed": 11,
                     "nodes_present": list(nodes_present)},
        "loads": {"conditions": [[0.0, 0.0, Z, 0.0, 0.0, 0.0]]},
        "angles": {"mode": "constant", "base": 0.0}})


@contextlib.contextmanager
def live_sim(sim_cfg, scenario, channel: str, seed: int = 5):
    """The simulator in real time, threaded (it serves NMT/SDO/SYNC as they arrive), in follow
    mode: its nodes boot, heartbeat and wait for a master."""
    from rsra.sim_bus.drivers import RealtimeSim
    from rsra.sim_bus.physics import AircraftPhysics

    sim = RealtimeSim(sim_cfg, physics=AircraftPhysics(sim_cfg, scenario, seed=seed),
                      channel=channel, seed=seed)
    sim.start()
    try:
        yield sim
    finally:
        sim.close()


def write_config(tmp_path, calibration: str = "[calibration]\n", name: str = "rig.toml",
                 replace: dict[str, str] | None = None):
    """A copy of the packaged rig config with its [calibration] table replaced (the EDS paths
    fall back to the packaged folder)."""
    text = RIG.read_text(encoding="utf-8")
    assert text.count("\n[calibration]\n") == 1
    text = text.replace("\n[calibration]\n", "\n" + calibration.rstrip("\n") + "\n", 1)
    for old, new in (replace or {}).items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def cfg_with_eds(cfg, tmp_path, edits: dict[int, tuple[str, object]]):
    """The rig with some nodes' EDS replaced by edited copies (node index -> (eds, edit))."""
    raw = copy.deepcopy(cfg.raw)
    for index, (eds_name, edit) in edits.items():
        eds = tmp_path / f"edited_{index}_{eds_name}"
        eds.write_text(edit((EDS / eds_name).read_text()))
        raw["nodes"][index]["eds"] = str(eds)
    return parse_config(raw, base_dir=config_dir())


def one_line_error(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def subparser(*names: str) -> argparse.ArgumentParser:
    p = build_parser()
    for name in names:
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        p = sub.choices[name]
    return p


# ------------------------------------------------------------------------------------------
# --help and usage errors

@pytest.mark.parametrize("path", [("nodes",), ("zero",), ("angles",), ("angles", "show"),
                                  ("angles", "reset")])
def test_every_help_explains_every_option(path, capsys):
    with pytest.raises(SystemExit) as e:
        main([*path, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for action in subparser(*path)._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help != argparse.SUPPRESS, action.dest
        if action.option_strings:
            assert action.option_strings[0] in out
    if path == ("zero",):  # the targets are documented where the user looks
        assert "gravity" in out and "dead-weight" in out


@pytest.mark.parametrize("argv,words", [
    (["nodes"], "--interface"),
    (["nodes", "--interface", "virtual", "--timeout", "0"], "--timeout"),
    (["nodes", "--interface", "no-such-interface", "--channel", "x"], "cannot open the bus"),
    (["nodes", "--config", "/no/such/rig.toml", "--interface", "virtual"], "file not found"),
    (["zero"], "--interface"),
    (["zero", "--interface", "virtual", "--seconds", "-1"], "--seconds"),
    (["zero", "--interface", "virtual", "--seconds", "soon"], "--seconds"),
    (["zero", "--interface", "virtual", "--min-samples", "1"], "--min-samples"),
    (["zero", "--interface", "virtual", "--max-offset-fs", "0"], "--max-offset-fs"),
    (["zero", "--interface", "virtual", "--units", "imperial"], "--units"),
    (["angles"], "ACTION"),
    (["angles", "show"], "STATE"),
    (["angles", "forget", "x.json"], "forget"),
    (["angles", "show", "x.json", "--units", "cgs"], "--units"),
])
def test_bad_arguments_exit_2_with_one_line(argv, words, capsys):
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's own errors
        rc = e.code
    assert rc == 2
    line = one_line_error(capsys.readouterr().err)
    assert line.startswith("rsra") and words in line


# ------------------------------------------------------------------------------------------
# rsra nodes

def _nodes_json(capsys, argv) -> tuple[int, dict]:
    rc = main(["nodes", "--json", *argv])
    return rc, json.loads(capsys.readouterr().out)


def test_nodes_finds_the_aircrafts_nodes_and_reports_an_absent_optional_one(cfg, capsys):
    ch = channel_name("nodes")
    with live_sim(cfg, rest_scenario(nodes_present=("rotor_speed",)), ch) as sim:
        rc, out = _nodes_json(capsys, ["--interface", "virtual", "--channel", ch,
                                       "--timeout", "1"])
        assert rc == 0 and out["ok"] is True
        by = {n["name"]: n for n in out["nodes"]}
        assert set(by) == {n.name for n in cfg.nodes}
        present = [n.name for n in sim.nodes]
        assert "balance" not in present
        for name in present:
            d, od = by[name], sim.by_name[name].od
            assert d["status"] == "ok" and d["heard"] and d["sdo"], d
            assert d["state"] == "pre-operational"  # booted, waiting for a master
            assert d["device_type"] == od[0x1000].default
            assert [d["identity"][k] for k in ("vendor-ID", "product code", "revision number",
                                               "serial number")] == \
                [od[0x1018][s].default for s in (1, 2, 3, 4)]
        assert by["balance"]["status"] == "missing" and by["balance"]["ok"] is True
        assert not by["balance"]["heard"] and not by["balance"]["sdo"]

        rc = main(["nodes", "--interface", "virtual", "--channel", ch])  # default wait
        text = capsys.readouterr().out
        assert rc == 0
        assert "absent (optional)" in text and "node balance (id 0x41)" in text
        # a check that starts nothing: no NMT start, no SYNC
        assert all(n.state == PRE_OPERATIONAL for n in sim.nodes)
        assert len(sim.sync_info) == 0


def test_nodes_names_each_mismatch_with_both_values_and_exits_1(cfg, tmp_path, capsys):
    sim_cfg = cfg_with_eds(cfg, tmp_path, {
        2: ("load_cell.eds", lambda s: s.replace("DefaultValue=0x00000404",
                                                 "DefaultValue=0x00000405")),
        7: ("accelerometer.eds", lambda s: s.replace("DefaultValue=0x64010210",
                                                     "DefaultValue=0x64010310")),
    })
    ch = channel_name("nodes-mismatch")
    with live_sim(sim_cfg, rest_scenario(), ch):
        rc, out = _nodes_json(capsys, ["--interface", "virtual", "--channel", ch])
        assert rc == 1 and out["ok"] is False
        by = {n["name"]: n for n in out["nodes"]}
        assert [(m["object"], m["expected"], m["actual"]) for m in by["cell_C"]["mismatches"]] \
            == [("0x1018:2 (product code)", 0x404, 0x405)]
        assert [(m["object"], m["expected"], m["actual"]) for m in by["accel_1"]["mismatches"]] \
            == [("0x1A00:2 (TPDO1 mapped object 2)", 0x64010210, 0x64010310)]
        assert {n for n, d in by.items() if d["status"] != "ok"} == {"cell_C", "accel_1"}

        rc = main(["nodes", "--interface", "virtual", "--channel", ch])
        text = capsys.readouterr().out
        assert rc == 1
        assert ("node cell_C: 0x1018:2 (product code) reads 0x00000405, the EDS says "
                "0x00000404") in text
        assert ("node accel_1: 0x1A00:2 (TPDO1 mapped object 2) reads 0x64010310, the EDS says "
                "0x64010210") in text


def test_nodes_a_required_node_at_another_id_is_missing_and_exits_1(cfg, tmp_path, capsys):
    # the config expects cell_F at 0x18; the aircraft's cell_F answers at 0x16
    path = write_config(tmp_path, replace={'name = "cell_F"\nrole = "load_cell"\nnode_id = 0x16':
                                           'name = "cell_F"\nrole = "load_cell"\nnode_id = 0x18'})
    ch = channel_name("nodes-id")
    with live_sim(cfg, rest_scenario(), ch):
        rc, out = _nodes_json(capsys, ["--config", str(path), "--interface", "virtual",
                                       "--channel", ch, "--timeout", "0.5"])
    assert rc == 1 and out["ok"] is False
    by = {n["name"]: n for n in out["nodes"]}
    assert by["cell_F"]["node_id"] == 0x18
    assert by["cell_F"]["status"] == "missing" and by["cell_F"]["ok"] is False
    assert all(d["status"] == "ok" for n, d in by.items() if n != "cell_F")


# ------------------------------------------------------------------------------------------
# rsra zero: the pure part

def _rest_channels(cfg, rng, n: int, offsets: dict[str, float], cell_noise=None):
    """Synthetic rest readings in channel_specs order: truth satisfies S T = I with f = −g
    (min-norm reactions plus a self-stress), plus offsets and white noise at the config σ."""
    from rsra.daq.analysis.tare import channel_specs
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.estimator.balance import inertial_load_matrix

    specs = channel_specs(cfg, DecodeTable(cfg))
    model = cfg.rig_model()
    S = wrench_matrix(model.geometry, cfg.identification.initial_angles_rad)
    I_rest = inertial_load_matrix(model) @ np.array([0.0, 0.0, -G0])
    null = np.linalg.svd(S)[2][-1]
    T_true = np.linalg.pinv(S) @ I_rest + 700.0 * null
    truth = np.zeros(len(specs))
    truth[:7] = T_true
    truth[7:10] = [0.0, 0.0, -G0]
    sig = np.array([s.sigma if s.sigma is not None else 0.0 for s in specs])
    noise = rng.standard_normal((n, len(specs))) * sig
    if cell_noise is not None:
        noise[:, :7] += cell_noise
    off = np.array([offsets.get(s.key, 0.0) for s in specs])
    return specs, truth + off + noise, truth, S, I_rest


def test_tare_targets_make_the_static_estimate_zero_and_recover_the_offsets(cfg, rng):
    from rsra.daq.analysis.tare import tare

    n = 2000
    offsets = {"cell_A.force": 800.0, "cell_E.force": -300.0, "cell_G.force": 120.0,
               "accel_1.x": 0.2, "accel_1.z": -0.3, "balance.M": 35.0}
    specs, values, truth, S, I_rest = _rest_channels(cfg, rng, n, offsets)
    res = tare(cfg, specs, values)
    assert res.ok, res.problems
    by = {c.spec.key: c for c in res.channels}
    T_target = np.array([by[f"{c.node}.force"].target for c in cfg.cells])
    np.testing.assert_allclose(S @ T_target, I_rest, atol=1e-6 * np.abs(I_rest).max())
    # old offset 0 → the new offset is minus the channel's zero error (what the sensor adds)
    P = np.linalg.pinv(S) @ S  # equal cell σ: the σ-weighted correction is orthogonal
    o = np.array([offsets.get(f"{c.node}.force", 0.0) for c in cfg.cells])
    new_cells = np.array([by[f"{c.node}.force"].new_offset for c in cfg.cells])
    sig_T = cfg.cells[0].sigma_N
    np.testing.assert_allclose(new_cells, -(P @ o), atol=5 * sig_T / math.sqrt(n))
    for key in ("accel_1.x", "accel_1.y", "accel_1.z"):
        sig = cfg.accelerometers[0].sigma_m_s2
        assert abs(by[key].new_offset + offsets.get(key, 0.0)) < 5 * sig / math.sqrt(n)
    for j, ax in enumerate("XYZLMN"):
        key = f"balance.{ax}"
        tol = 5 * cfg.balance.sigma[j] / math.sqrt(n)
        assert abs(by[key].new_offset + offsets.get(key, 0.0)) < tol
    # what the rig read before the tare: the offsets' hub load, R⁻¹(I − S T̄)
    model = cfg.rig_model()
    R = hub_transfer_matrix(model.geometry)
    f_err = np.array([offsets["accel_1.x"], 0.0, offsets["accel_1.z"]])
    expected_H = np.linalg.solve(R, np.r_[model.mass.mass * f_err, 0, 0, 0] - S @ o)
    # noise of Ĥ over n samples, per axis (accelerometer term dominates): ≤ 2 kN / √n · 5
    assert np.all(np.abs(res.hub_loads_now - expected_H) < 5 * 2000.0 / math.sqrt(n))


def test_tare_sigma_test_has_the_false_alarm_rate_it_claims(rng):
    """(n−1)s²/σ² ~ χ²(n−1): the fraction of white-noise records refused ≈ the rate asked."""
    from rsra.daq.analysis.tare import _sigma_factor

    trials, n, alpha = 4000, 200, 0.05
    s = rng.standard_normal((trials, n)).std(axis=1, ddof=1)
    rate = float(np.mean(s > _sigma_factor(n, 1, alpha)))
    assert abs(rate - alpha) < 4 * math.sqrt(alpha * (1 - alpha) / trials)


def test_tare_refuses_a_varying_load_a_big_shift_a_status_bit_and_few_samples(cfg, rng):
    from rsra.daq.analysis.tare import tare

    n = 1000
    t = np.arange(n) / cfg.sample_rate_hz
    shaker = 1.2 * cfg.cells[0].sigma_N * np.sin(2 * np.pi * 3.1 * t)[:, None] * np.ones(7)
    specs, values, *_ = _rest_channels(cfg, rng, n, {}, cell_noise=shaker)
    res = tare(cfg, specs, values)
    assert any("cell_A.force varies" in p for p in res.problems)

    specs, values, *_ = _rest_channels(cfg, rng, n, {"cell_B.force": 3000.0, "accel_1.y": 2.0})
    res = tare(cfg, specs, values, status_counts={"overrange:C": 4})
    assert any(p.startswith("cell_B.force would shift by") for p in res.problems)
    assert any(p.startswith("accel_1.y would shift by") and "not level" in p
               for p in res.problems)
    assert any("load cell C reported over-range in 4 samples" in p for p in res.problems)

    specs, values, *_ = _rest_channels(cfg, rng, 60, {})
    res = tare(cfg, specs, values)
    assert [p for p in res.problems if p.startswith("too few samples")]


# ------------------------------------------------------------------------------------------
# rsra zero on the bus

INJECTED = {  # the reader's calibration: zero errors the tare must find (the sim has none)
    "cell_A.force": (1.0, 800.0), "cell_E.force": (1.0, -300.0), "accel_1.z": (1.0, 0.3),
    "accel_1.x": (1.0, -0.2), "balance.X": (1.002, 0.0), "balance.Z": (1.0, 250.0),
    "rotor_speed.omega": (1.0, 0.05), "rotor_speed.azimuth": (1.0, 0.1),
}


def _calibration_toml(entries: dict[str, tuple[float, float]]) -> str:
    return "[calibration]\n" + "".join(f'"{k}" = {{ gain = {g!r}, offset = {o!r} }}\n'
                                      for k, (g, o) in entries.items())


def test_zero_writes_a_fragment_that_loads_and_removes_the_zero_errors(cfg, tmp_path, capsys):
    path = write_config(tmp_path, _calibration_toml(INJECTED), name="reader.toml")
    sim_cfg = load_config(overrides={"rotor": {"omega_nominal_rad_s": 1e-6}})  # stopped
    ch = channel_name("zero")
    out = tmp_path / "zero.toml"
    with live_sim(sim_cfg, rest_scenario(), ch):
        rc = main(["zero", "--config", str(path), "--interface", "virtual", "--channel", ch,
                   "--seconds", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    text = out.read_text()
    assert "gravity" in text and "dead-weight" in text
    n = {k: int(v) for k, v in re.findall(r'^"([^"]+)" = .*, n (\d+), target', text, re.M)}
    assert min(n.values()) >= 100
    # the fragment is what load_config reads: merged into a config copy
    merged = load_config(write_config(tmp_path, text, name="merged.toml"))
    cal = merged.calibration
    assert cal["rotor_speed.azimuth"] == INJECTED["rotor_speed.azimuth"]  # not tared: kept
    assert cal["balance.X"][0] == 1.002  # gains kept
    # truth: the simulated sensors have no zero error, the rig is level, the true angles are
    # the configured ones; so the right new offsets are 0 (up to the cells' self-stress)
    model = merged.rig_model()
    S = wrench_matrix(model.geometry, merged.identification.initial_angles_rad)
    P = np.linalg.pinv(S) @ S
    o = np.array([INJECTED.get(f"{c.node}.force", (1.0, 0.0))[1] for c in cfg.cells])
    new = np.array([cal[f"{c.node}.force"][1] for c in cfg.cells])
    tol = 5 * cfg.cells[0].sigma_N / math.sqrt(min(n[f"{c.node}.force"] for c in cfg.cells))
    np.testing.assert_allclose(new, o - P @ o, atol=tol)  # the null-space part of o stays
    for ax in "xyz":
        key = f"accel_1.{ax}"
        tol = 5 * cfg.accelerometers[0].sigma_m_s2 / math.sqrt(n[key]) + 0.5e-3 * G0  # 1 mg counts
        assert abs(cal[key][1]) < tol, (key, cal[key])
    for j, ax in enumerate("XYZLMN"):
        key = f"balance.{ax}"
        gain = INJECTED.get(key, (1.0, 0.0))[0]
        assert abs(cal[key][1]) < 5 * gain * cfg.balance.sigma[j] / math.sqrt(n[key]), key
    assert abs(cal["rotor_speed.omega"][1]) < 1e-5


@pytest.mark.parametrize("omega,Z,seconds,words", [
    (19.4, 0.0, "1", "the rotor is turning: rotor_speed.omega reaches 19.4 rad/s"),
    (1e-6, -20000.0, "1", "balance.Z would shift by 2e+04"),
    (1e-6, 0.0, "0.25", "too few samples"),
])
def test_zero_refuses_and_writes_nothing(omega, Z, seconds, words, tmp_path, capsys):
    sim_cfg = load_config(overrides={"rotor": {"omega_nominal_rad_s": omega}})
    ch = channel_name("zero-refuse")
    out = tmp_path / "zero.toml"
    with live_sim(sim_cfg, rest_scenario(Z=Z), ch):
        rc = main(["zero", "--interface", "virtual", "--channel", ch, "--seconds", seconds,
                   "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1
    assert not out.exists()
    refusals = [ln for ln in err.splitlines() if ln.startswith("rsra zero: refused:")]
    assert any(words in ln for ln in refusals), err
    assert "Traceback" not in err


# ------------------------------------------------------------------------------------------
# rsra angles

def _posterior(cfg, rng, det: int) -> PosteriorState:
    """A posterior whose covariance has `det` eigenvalues (sigma_max/2)² and the rest
    (2 sigma_max)², along random orthogonal directions."""
    names = cfg.rig_model().geometry.angle_names
    smax = cfg.identification.sigma_max_rad
    Q = np.linalg.qr(rng.standard_normal((14, 14)))[0]
    lam = np.r_[np.full(det, (smax / 2) ** 2), np.full(14 - det, (2 * smax) ** 2)]
    P = (Q * lam) @ Q.T
    P = 0.5 * (P + P.T)
    return PosteriorState(names, np.radians(rng.uniform(-3, 3, 14)), P, 1234, 56.25)


def test_angles_show_reports_angles_sigma_determined_directions_and_condition(cfg, rng,
                                                                              tmp_path, capsys):
    st = _posterior(cfg, rng, det=9)
    path = tmp_path / "post.json"
    save_posterior(path, st)
    for units in ("si", "us"):  # angles are degrees in both
        assert main(["angles", "show", str(path), "--json", "--units", units]) == 0
        d = json.loads(capsys.readouterr().out)
        np.testing.assert_allclose(d["angles_deg"], np.degrees(st.theta), rtol=1e-12)
        np.testing.assert_allclose(d["sigma_deg"], np.degrees(np.sqrt(np.diag(st.P))),
                                   rtol=1e-12)
        assert d["determined"] == 9 and d["parameters"] == 14
        assert d["condition"] == pytest.approx(16.0, rel=1e-9)  # (2 smax)² / (smax/2)²
        smax_deg = math.degrees(cfg.identification.sigma_max_rad)
        assert len(d["undetermined_directions"]) == 5
        assert all(u["sigma_deg"] == pytest.approx(2 * smax_deg, rel=1e-9)
                   for u in d["undetermined_directions"])
        assert d["determined_parameters"] == (np.sqrt(np.diag(st.P)) <= cfg.identification
                                              .sigma_max_rad).tolist()
        assert d["applies_from_seq"] == 1234 and d["matches_config"] is True
    assert main(["angles", "show", str(path)]) == 0
    text = capsys.readouterr().out
    assert "determined directions: 9 of 14" in text and "condition number 16" in text


def test_angles_reset_writes_the_configured_prior_and_show_reads_it_back(cfg, rng, tmp_path,
                                                                         capsys):
    conf = write_config(tmp_path, replace={"initial_angles_deg = 0.0": "initial_angles_deg = 2.0",
                                           "prior_sigma_deg = 5.0": "prior_sigma_deg = 3.0"})
    path = tmp_path / "post.json"
    save_posterior(path, _posterior(cfg, rng, det=9))
    assert main(["angles", "reset", "--config", str(conf), str(path)]) == 0
    line = capsys.readouterr().out.strip()
    assert "replaced a posterior of 14 parameters with 9 determined directions" in line
    assert "initial 2°, σ 3°" in line
    names = cfg.rig_model().geometry.angle_names
    st = load_posterior(path, names)  # what the service's --angles reads
    np.testing.assert_allclose(st.theta, np.radians(np.full(14, 2.0)), rtol=1e-15)
    np.testing.assert_allclose(st.P, np.diag(np.full(14, np.radians(3.0) ** 2)), rtol=1e-15)
    assert st.applies_from_seq is None and st.t is None
    assert main(["angles", "show", "--config", str(conf), str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["determined"] == 0 and d["condition"] == pytest.approx(1.0)
    np.testing.assert_allclose(d["angles_deg"], 2.0, rtol=1e-12)
    np.testing.assert_allclose(d["sigma_deg"], 3.0, rtol=1e-12)
    # a new file is created, but no folder for it (nothing the user did not name)
    fresh = tmp_path / "new" / "state.json"
    assert main(["angles", "reset", str(fresh)]) == 2
    capsys.readouterr()
    assert not fresh.parent.exists()
    fresh.parent.mkdir()
    assert main(["angles", "reset", str(fresh)]) == 0
    assert "created it" in capsys.readouterr().out
    np.testing.assert_array_equal(load_posterior(fresh, names).theta,
                                  cfg.identification.initial_angles_rad)


def test_angles_a_corrupt_file_is_a_one_line_error(cfg, rng, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["angles", "show", str(bad)]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert str(bad) in line and "not readable JSON" in line
    # a posterior whose covariance is not positive definite
    st = _posterior(cfg, rng, det=3)
    st.P[0, 0] = -1.0
    neg = tmp_path / "neg.json"
    neg.write_text(json.dumps(st.to_dict()))
    assert main(["angles", "show", str(neg)]) == 2
    assert "not positive definite" in one_line_error(capsys.readouterr().err)
    # reset replaces a damaged posterior (truncated, or numerically broken) ...
    good = tmp_path / "trunc.json"
    save_posterior(good, _posterior(cfg, rng, det=3))
    good.write_text(good.read_text()[:60])
    for damaged in (good, neg):
        assert main(["angles", "reset", str(damaged)]) == 0
        assert "replaced a damaged posterior" in capsys.readouterr().out
        load_posterior(damaged, cfg.rig_model().geometry.angle_names)
    # ... but leaves a file that is not a posterior alone (a wrong path)
    other = tmp_path / "rig.toml"
    other.write_text(RIG.read_text())
    assert main(["angles", "reset", str(other)]) == 2
    assert "refusing to overwrite" in one_line_error(capsys.readouterr().err)
    assert other.read_text() == RIG.read_text()


def test_no_identification_reaches_the_service_from_run_demo_and_replay(tmp_path, capsys):
    """Issue 14: `--no-identification` on `run`, `demo` and `replay` (and `--angles` on
    `demo`); replay refuses it with `--recompute`."""
    from rsra.daq.cli.commands.run import options_from_args

    p = build_parser()
    args = p.parse_args(["run", "--sim", "flight", "--no-identification", "--angles", "a.json"])
    opts = options_from_args(args)
    assert opts.identification is False and opts.angles == "a.json"
    assert options_from_args(p.parse_args(["run", "--sim", "flight"])).identification is True
    args = p.parse_args(["demo", "--angles", "a.json", "--no-identification"])
    assert args.angles == "a.json" and args.identification is False
    assert p.parse_args(["replay", "x.log", "--no-identification"]).identification is False
    out = tmp_path / "out.jsonl"
    assert main(["replay", "x.log", "--recompute", "--no-identification", "--out",
                 str(out)]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert "--recompute" in line and "--no-identification" in line and not out.exists()
