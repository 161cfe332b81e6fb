"""`rsra report`: plots and a summary from published records (JSONL) and the simulator's truth.

* end to end: a lock-step `ground-test` recording with truth → `rsra replay --recompute --out`
  (the service's estimator writes hub_loads, innovations, angles) → `rsra report`: every plot
  made, readable sizes, not blank; a JSONL with channels only skips the other plots and says so;
* numbers: records synthesised from an off-line truth with known errors (H = truth + noise of
  known σ, final angles = truth + a known error with a known covariance, NIS drawn from χ²₆)
  give back those numbers — with records in simulated time (aligned by t), in UNIX time with
  the service started later (aligned by seq, offset found from the SYNC counters), and one
  sample off (which the summary must show as a large error);
* usage errors exit 2 with one line; --help explains the options.
"""
from __future__ import annotations

import itertools
import json
import os

import numpy as np
import pytest

from rsra.daq.cli import main
from rsra.daq.jsonout import dumps
from rsra.sim_bus.truth import read_truth

_chan = itertools.count()
E2E_SECONDS = 6.0  # one identification window (5 s) plus its settling


def _png_ok(path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        size = im.size
        px = np.asarray(im.convert("L"), float)
    assert 1000 <= size[0] <= 1600 and 700 <= size[1] <= 1400, (path.name, size)
    assert (px < 200).mean() > 0.02 and px.std() > 20, f"{path.name} looks blank"
    return size


@pytest.fixture(scope="module")
def e2e(tmp_path_factory, cfg):
    """A short lock-step ground-test recording, its truth, and the replay's records."""
    from rsra.sim_bus.drivers import LockstepSim
    from rsra.sim_bus.physics import AircraftPhysics
    from rsra.sim_bus.scenarios import load_scenario

    d = tmp_path_factory.mktemp("report")
    sim = LockstepSim(cfg, physics=AircraftPhysics(cfg, load_scenario("ground-test"), seed=5),
                      autostart=True, record=str(d / "run.log"),
                      channel=f"test-report-{os.getpid()}-{next(_chan)}")
    try:
        with sim:
            sim.run(E2E_SECONDS)
        sim.write_truth(d / "truth.npz")
    finally:
        sim.close()
    assert main(["replay", str(d / "run.log"), "--recompute", "--out",
                 str(d / "results.jsonl")]) == 0
    return d


def test_report_end_to_end(e2e, capsys):
    keys = [json.loads(line)["key"] for line in open(e2e / "results.jsonl")]
    counts = {k: keys.count(k) for k in set(keys)}
    n = int(E2E_SECONDS * 200)
    assert counts["channels"] == counts["hub_loads"] == n
    assert counts["angles"] >= 1 and counts["innovations"] > 0
    out = e2e / "rep"
    assert main(["report", str(e2e / "results.jsonl"), "--truth", str(e2e / "truth.npz"),
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "by phase" in printed and "H start" in printed  # issue 28: never mixed
    # the innovations with their verdict, overall and per state of the load (issue 19)
    inn = json.loads((out / "summary.json").read_text())["innovations"]
    assert inn["verdict"] in ("consistent", "conservative", "inconsistent")
    assert set(inn["by_state"]) == {"held", "transient"}
    assert set(inn["by_phase"]) == {"start", "transient", "steady"}
    line = [ln for ln in printed.splitlines() if "innovations, whole run" in ln][0]
    assert line.endswith(("consistent", "CONSERVATIVE", "INCONSISTENT"))
    for name in ("hub_loads.png", "hub_load_errors.png", "angles.png", "innovations.png",
                 "spectra.png"):
        _png_ok(out / name)
    s = json.loads((out / "summary.json").read_text())
    assert s["inputs"]["records"] == counts
    # lock-step: the records' t is simulated time, so truth aligns by time, all records
    assert s["inputs"]["alignment"] in ("sync_time", "t") and s["inputs"]["matched"] == 1.0
    errs = s["hub_loads"]["errors"]
    for k in ("H", "H_static"):
        assert len(errs[k]["rms_error"]) == 6 and all(np.isfinite(errs[k]["rms_error"]))
    assert s["angles"]["runs"] == counts["angles"]
    assert len(s["angles"]["final"]["error_deg"]) == 14
    assert s["skipped"] == {}
    md = (out / "summary.md").read_text()
    assert "## Hub loads" in md and "## Angles" in md and "![angles.png](angles.png)" in md


def test_absent_records_are_skipped_and_said(e2e, capsys):
    lines = [ln for ln in open(e2e / "results.jsonl") if json.loads(ln)["key"] in
             ("channels", "health")]
    (e2e / "channels.jsonl").write_text("".join(lines))
    out = e2e / "rep_channels"
    assert main(["report", str(e2e / "channels.jsonl"), "--out", str(out)]) == 0
    capsys.readouterr()
    s = json.loads((out / "summary.json").read_text())
    assert s["plots"] == ["spectra.png"]
    assert set(s["skipped"]) == {"hub_loads.png", "hub_load_errors.png", "angles.png",
                                 "innovations.png"}
    assert s["hub_loads"] == {"skipped": "no hub_loads records"}
    _png_ok(out / "spectra.png")
    assert "Skipped: no angles records" in (out / "summary.md").read_text()


# ---------------------------------------------------------------------------------------------
# numbers from synthetic records with known errors

N = 1200
K_FILTER = 0.5  # the synthetic "filter" error is this fraction of the static σ


@pytest.fixture(scope="module")
def synth_truth(tmp_path_factory, cfg):
    from rsra.sim_bus import simulate, write_truth

    d = tmp_path_factory.mktemp("synth")
    run = simulate(cfg, "ground-test", seed=11, n_samples=N)
    return write_truth(d / "truth.npz", run)


def _synthetic_records(cfg, truth, *, t_offset=0.0, shift=0, first=0):
    """Records for truth samples first… (seq from 0), with times t + t_offset, and the truth
    they claim shifted by ``shift`` samples. Returns (lines, expected dict)."""
    from rsra.estimator.noise_budget import noise_budget

    rng = np.random.default_rng(2024)
    sig = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad, "body").total
    H = np.asarray(truth["H_true"])
    alpha = np.asarray(truth["alpha_true"])
    t = np.asarray(truth["t"])
    sc = np.asarray(truth["sync_counter"])
    lines = []
    n_inn = 0
    nis_all = []
    for seq, i in enumerate(range(first, len(t) - abs(shift))):
        j = i + shift  # the truth sample the estimate really belongs to
        flags = ["missing:cell_A"] if seq % 100 == 7 else []
        lines.append({"key": "hub_loads", "seq": seq, "sync": int(sc[i]),
                      "t": float(t[i] + 4e-4 + t_offset), "frame": "body",
                      "H": H[j] + K_FILTER * sig * rng.standard_normal(6),
                      "H_static": H[j] + sig * rng.standard_normal(6), "omega": 19.4,
                      "flags": flags})
        if seq % 10 == 0:
            nis = float(rng.chisquare(6))
            nis_all.append((float(t[i] + 4e-4 + t_offset), nis))  # as written
            lines.append({"key": "innovations", "seq": seq, "t": float(t[i] + 4e-4 + t_offset),
                          "e": rng.standard_normal(6), "nis": nis})
            n_inn += 1
    # identification runs every second; the last one with a known error and covariance
    names = list(cfg.rig_model().geometry.angle_names)
    A = rng.standard_normal((14, 14))
    P = (A @ A.T / 14 + np.eye(14)) * np.radians(0.2) ** 2
    e_final = np.linalg.cholesky(P) @ rng.standard_normal(14)
    run_idx = list(range(first + 199, len(t) - abs(shift), 200))
    for k, i in enumerate(run_idx):
        last = k == len(run_idx) - 1
        err = e_final if last else np.radians(0.5) * rng.standard_normal(14)
        lines.append({"key": "angles", "t": float(t[i] + 4e-4 + t_offset), "seq": i - first,
                      "mode": "known_loads", "content": "static", "accepted": k != 2,
                      "reason": None if k != 2 else "inconsistent", "names": names,
                      "alpha": alpha[i + shift] + err, "P": P,
                      "sigma_cr": np.sqrt(np.diag(P)), "determined": 14})
    expected = {"sigma": sig, "P": P, "e_final": e_final, "flags": sum(
        1 for ln in lines if ln["key"] == "hub_loads" and ln["flags"]), "runs": len(run_idx),
        "nis": nis_all}
    return [dumps(ln) for ln in lines], expected


def _summary(cfg, tmp_path, truth_path, **kw):
    from rsra.daq.analysis.report import load_records, load_truth, summarise

    tr = load_truth(truth_path, read_truth)
    lines, exp = _synthetic_records(cfg, tr, **kw)
    p = tmp_path / "synthetic.jsonl"
    p.write_text("\n".join(lines) + "\n")
    _, s = summarise(cfg, load_records(p), tr)
    return s, exp


def _check_numbers(s, exp, cfg):
    errs = s["hub_loads"]["errors"]
    n_h = errs["H"]["samples"]
    n_s = errs["H_static"]["samples"]
    # RMS of n Gaussian samples: relative standard error 1/sqrt(2n); 3.3 of them (1e-3)
    tol_h, tol_s = 3.3 / np.sqrt(2 * n_h), 3.3 / np.sqrt(2 * n_s)
    np.testing.assert_allclose(errs["H_static"]["rms_over_sigma_static"], 1.0, atol=tol_s)
    np.testing.assert_allclose(errs["H"]["rms_over_sigma_static"], K_FILTER,
                               atol=K_FILTER * tol_h)
    np.testing.assert_allclose(s["hub_loads"]["sigma_static"], exp["sigma"], rtol=1e-12)
    # angles: the joint chi-square with the posterior covariance, exactly
    j = s["angles"]["joint_chi2"]
    e = exp["e_final"]
    assert j["value"] == pytest.approx(float(e @ np.linalg.solve(exp["P"], e)), rel=1e-9)
    assert j["dof"] == 14
    np.testing.assert_allclose(s["angles"]["final"]["error_over_sigma"],
                               e / np.sqrt(np.diag(exp["P"])), rtol=1e-9)
    assert s["angles"]["runs"] == exp["runs"]
    assert s["angles"]["rejected"] == {"inconsistent": 1}
    # innovations: the settled records' NIS, their mean
    settle = s["innovations"]["settle_s"]
    t0 = exp["nis"][0][0]
    nis = np.array([v for t, v in exp["nis"] if t - t0 >= settle])
    assert s["innovations"]["records"] == len(nis)
    assert s["innovations"]["mean_nis"] == pytest.approx(nis.mean(), rel=1e-12)
    assert s["flags"]["hub_loads"] == {"missing:cell_A": exp["flags"]}


def test_numbers_aligned_by_time(synth_truth, cfg, tmp_path):
    s, exp = _summary(cfg, tmp_path, synth_truth)
    assert s["inputs"]["alignment"] == "t" and s["inputs"]["matched"] == 1.0
    _check_numbers(s, exp, cfg)


def test_numbers_aligned_by_seq_and_sync_counter(synth_truth, cfg, tmp_path):
    """UNIX times that match no truth time, and the service started 37 samples after the
    simulator: seq 0 is truth sample 37, found from the SYNC counters."""
    s, exp = _summary(cfg, tmp_path, synth_truth, t_offset=1.7e9, first=37)
    assert s["inputs"]["alignment"] == "seq" and s["inputs"]["matched"] == 1.0
    _check_numbers(s, exp, cfg)


def test_one_sample_misalignment_shows(synth_truth, cfg, tmp_path):
    """Estimates that belong to the next truth sample: the summary must show errors well above
    the bound on the moment axes, which carry the rotor harmonics (the test can fail)."""
    s, _ = _summary(cfg, tmp_path, synth_truth, shift=1)
    r = np.array(s["hub_loads"]["errors"]["H_static"]["rms_over_sigma_static"])
    assert r[3:].max() > 1.5


def test_us_units_and_shaft_frame(synth_truth, cfg, tmp_path):
    """US units scale the numbers; records in shaft axes are compared with the truth turned
    into shaft axes (C_sᵀ), so the errors stay at their σ."""
    from rsra.daq.analysis.report import load_records, load_truth, summarise
    from rsra.config.units import FT_LBF_NM, LBF_N

    tr = load_truth(synth_truth, read_truth)
    lines, exp = _synthetic_records(cfg, tr)
    p = tmp_path / "a.jsonl"
    p.write_text("\n".join(lines) + "\n")
    _, si = summarise(cfg, load_records(p), tr, "si")
    _, us = summarise(cfg, load_records(p), tr, "us")
    scale = np.array([1 / LBF_N] * 3 + [1 / FT_LBF_NM] * 3)
    np.testing.assert_allclose(us["hub_loads"]["errors"]["H"]["rms_error"],
                               np.array(si["hub_loads"]["errors"]["H"]["rms_error"]) * scale)
    assert us["units"] == ["lbf"] * 3 + ["ft·lbf"] * 3
    # the same estimates re-expressed in shaft axes
    from rsra.estimator.geometry import shaft_rotation

    C = shaft_rotation(cfg.rig_model().geometry, "shaft")
    shaft = []
    for ln in lines:
        r = json.loads(ln)
        if r["key"] == "hub_loads":
            r["frame"] = "shaft"
            for k in ("H", "H_static"):
                h = np.array(r[k])
                r[k] = np.concatenate([C.T @ h[:3], C.T @ h[3:]])
        shaft.append(dumps(r))
    p2 = tmp_path / "shaft.jsonl"
    p2.write_text("\n".join(shaft) + "\n")
    _, sh = summarise(cfg, load_records(p2), tr, "si")
    assert sh["hub_loads"]["frame"] == "shaft"
    # the RMS per axis changes a little (σ mixes between x and z), the total does not
    a = np.array(si["hub_loads"]["errors"]["H_static"]["rms_error"])
    b = np.array(sh["hub_loads"]["errors"]["H_static"]["rms_error"])
    assert np.sum(b[:3] ** 2) == pytest.approx(np.sum(a[:3] ** 2), rel=1e-9)
    assert np.sum(b[3:] ** 2) == pytest.approx(np.sum(a[3:] ** 2), rel=1e-9)


# ---------------------------------------------------------------------------------------------
# usage


@pytest.mark.parametrize("argv, text", [
    (["report", "/nonexistent/results.jsonl"], "no such file"),
    (["report", "{tmp}/bad.jsonl"], "line 2"),
    (["report", "{tmp}/ok.jsonl", "--truth", "{tmp}/missing.npz"], "--truth"),
    (["report", "{tmp}/ok.jsonl", "--truth", "{tmp}/bad.jsonl"], "not a truth file"),
    (["report", "{tmp}/ok.jsonl", "--units", "furlongs"], "invalid choice"),
    (["report"], "required"),
])
def test_bad_arguments_exit_2_with_one_line(argv, text, tmp_path, capsys):
    ok = '{"key":"channels","seq":0,"t":0.0,"T":[1,2,3,4,5,6,7],"omega":null}\n'
    (tmp_path / "ok.jsonl").write_text(ok)
    (tmp_path / "bad.jsonl").write_text(ok + "{not json\n")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert text in err and "\n" not in err and "Traceback" not in err


def test_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["report", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for opt in ("--truth", "--out", "--units", "--config", "RESULTS.jsonl"):
        assert opt in out


def test_accuracy_by_phase_against_the_published_sigma(synth_truth, cfg, tmp_path, capsys):
    """The hub-load errors split by phase — before the first accepted calibration, transient,
    calibrated steady state — each sample judged against the σ its record published
    (sqrt(sigma_angles² + bound²); sigma_filter in place of the bound for H when carried),
    not the static bound; the innovations split the same way (issue 28)."""
    from rsra.daq.analysis.report import load_records, load_truth, summarise
    from rsra.estimator.noise_budget import noise_budget

    tr = load_truth(synth_truth, read_truth)
    bound = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad, "body").total
    rng = np.random.default_rng(28)
    H, t = np.asarray(tr["H_true"]), np.asarray(tr["t"])
    cal, moving = 400, range(700, 800)  # calibrated from sample 400; a ramp at 700-799
    lines = []
    for seq in range(len(t)):
        sa = (10.0 if seq < cal else 0.5) * bound  # the uncalibrated start: large sigma_angles
        sf = 0.3 * bound  # the filter's own σ, carried: H's σ uses it, H_static's the bound
        sH, sS = np.sqrt(sa**2 + sf**2), np.sqrt(sa**2 + bound**2)
        k = 5.0 if seq in moving else 1.0  # the filter lags the ramp: 5 σ
        lines.append({"key": "hub_loads", "seq": seq, "sync": 0, "t": float(t[seq] + 4e-4),
                      "frame": "body", "H": H[seq] + k * sH * rng.standard_normal(6),
                      "H_static": H[seq] + sS * rng.standard_normal(6), "omega": 19.4,
                      "sigma_angles": sa, "sigma_filter": sf,
                      "flags": (["transient"] if seq in moving else [])
                      + (["angles_uncertain"] if seq < cal else [])})
        if seq % 10 == 0:
            nis = float(rng.chisquare(6)) * (20.0 if seq in moving else 1.0)
            lines.append({"key": "innovations", "seq": seq, "t": float(t[seq] + 4e-4),
                          "e": [0.0] * 6, "nis": nis})
    names = list(cfg.rig_model().geometry.angle_names)
    lines.append({"key": "angles", "t": float(t[cal - 1]), "seq": cal - 100, "accepted": True,
                  "reason": None, "mode": "known_loads", "content": "static", "names": names,
                  "alpha": [0.0] * 14, "P": (np.eye(14) * 1e-6).tolist(), "determined": 14,
                  "applies_from_seq": cal})
    p = tmp_path / "phases.jsonl"
    p.write_text("\n".join(dumps(x) for x in lines) + "\n")
    _, s = summarise(cfg, load_records(p), tr)
    bp = s["hub_loads"]["by_phase"]
    assert bp["calibrated_from_seq"] == cal
    settle_n = round(s["hub_loads"]["settle_s"] * cfg.sample_rate_hz)
    assert abs(bp["H"]["start"]["samples"] - (cal - settle_n)) <= 1  # once the filter settled
    assert bp["H_static"]["start"]["samples"] == cal
    assert bp["H"]["transient"]["samples"] == len(moving)
    assert bp["H"]["steady"]["samples"] == len(t) - cal - len(moving)
    for name in ("H", "H_static"):
        for phase in ("start", "steady"):
            v = bp[name][phase]
            tol = 3.3 / np.sqrt(2 * v["samples"])  # RMS of n Gaussians: 1e-3 either side
            np.testing.assert_allclose(v["rms_over_sigma"], 1.0, atol=tol)
            assert max(v["beyond_3sigma"]) <= 0.02  # 0.27 % expected
    assert min(bp["H"]["transient"]["rms_over_sigma"]) > 4.0
    assert min(bp["H"]["transient"]["beyond_3sigma"]) > 0.3
    ph = s["innovations"]["by_phase"]
    assert ph["transient"]["verdict"] == "inconsistent"
    assert ph["steady"]["verdict"] == "consistent" and ph["start"]["records"] > 0
    from rsra.daq.analysis.report import Report

    text = Report(tmp_path, [], {}, s).markdown_brief()
    assert "H steady" in text and "calibrated steady state" in text and "beyond" in text
    # a run started from calibrated angles (a saved posterior: its first sample not flagged
    # angles_uncertain) has no start phase
    first = json.loads(lines and dumps(lines[0]))
    first["flags"] = []
    p.write_text("\n".join([dumps(first)] + [dumps(x) for x in lines[1:]]) + "\n")
    _, s = summarise(cfg, load_records(p), tr)
    assert s["hub_loads"]["by_phase"]["calibrated_from_seq"] == 0
    assert s["hub_loads"]["by_phase"]["H_static"]["start"] is None


def _phase_run(cfg, tr, tmp_path, initial=None, started_calibrated=False):
    """Synthetic records over the truth: calibrated from sample 400, a ramp at 700–799, one
    accepted run whose posterior σ (P) differs from its σ_CR."""
    H, t = np.asarray(tr["H_true"]), np.asarray(tr["t"])
    cal, moving = 400, range(700, 800)
    lines = [] if initial is None else [{"key": "angles", **initial}]
    for seq in range(len(t)):
        flags = ["transient"] if seq in moving else []
        if seq < cal and not started_calibrated:
            flags.append("angles_uncertain")
        lines.append({"key": "hub_loads", "seq": seq, "sync": 0, "t": float(t[seq] + 4e-4),
                      "frame": "body", "H": H[seq], "H_static": H[seq], "omega": 19.4,
                      "sigma_angles": [1.0] * 6, "sigma_filter": [1.0] * 6, "flags": flags})
    names = list(cfg.rig_model().geometry.angle_names)
    lines.append({"key": "angles", "t": float(t[cal - 1]), "seq": cal - 100, "accepted": True,
                  "reason": None, "mode": "known_loads", "content": "static", "names": names,
                  "alpha": [0.01] * 14, "P": (np.eye(14) * 0.02**2).tolist(),
                  "sigma_cr": [0.005] * 14, "determined": 14, "applies_from_seq": cal})
    p = tmp_path / "phase_run.jsonl"
    p.write_text("\n".join(dumps(x) for x in lines) + "\n")
    return p, t, cal, moving


def test_report_phases_as_time_spans_and_the_angles_band_is_the_posterior(synth_truth, cfg,
                                                                          tmp_path):
    """The plots' phase shading comes from the records: start until the first accepted
    calibration applies, the flagged ramp as transient, steady around it (issue 51); the
    angles band is the posterior's sqrt(diag P), the run's σ_CR only its own marker; before
    the first run the state the run started from — its starting record where the results
    carry one, nothing drawn for a saved posterior they do not carry, else the prior."""
    from rsra.daq.analysis.report import (_starting_state, _angle_records, angle_steps,
                                          load_records,
                                          load_truth, phase_spans, prepare)

    tr = load_truth(synth_truth, read_truth)
    p, t, cal, moving = _phase_run(cfg, tr, tmp_path)
    d = prepare(cfg, load_records(p), tr)
    spans = phase_spans(d)
    assert [s[2] for s in spans] == ["start", "steady", "transient", "steady"]
    dt = cfg.sample_period_s
    rel = t - d.t0 + 4e-4
    assert spans[0][1] == pytest.approx(rel[cal - 1] + dt / 2, abs=1e-6)
    assert spans[2][0] == pytest.approx(rel[moving[0]] - dt / 2, abs=1e-6)
    assert spans[2][1] == pytest.approx(rel[moving[-1]] + dt / 2, abs=1e-6)
    runs = _angle_records(d)
    np.testing.assert_allclose(runs[0]["sigma"], 0.005)  # the run's own σ_CR (its marker)
    tt, A, S, _ = angle_steps(d, runs)
    np.testing.assert_allclose(S[1:], 0.02)  # the band: the posterior after each run
    a0, s0, what = _starting_state(d)
    assert what == "the configured prior"
    np.testing.assert_allclose(s0, cfg.identification.prior_sigma_rad)
    names = list(cfg.rig_model().geometry.angle_names)
    ini = {"initial": True, "names": names, "alpha": [0.03] * 14,
           "P": (np.eye(14) * 0.04**2).tolist()}
    p, *_ = _phase_run(cfg, tr, tmp_path, initial=ini, started_calibrated=True)
    d = prepare(cfg, load_records(p), tr)
    a0, s0, what = _starting_state(d)
    assert what == "the run's starting posterior"
    np.testing.assert_allclose(a0, 0.03)
    np.testing.assert_allclose(s0, 0.04)
    assert [s[2] for s in phase_spans(d)][0] == "steady"  # no start phase
    p, *_ = _phase_run(cfg, tr, tmp_path, started_calibrated=True)
    a0, s0, what = _starting_state(prepare(cfg, load_records(p), tr))
    assert "saved posterior" in what and np.isnan(a0).all() and np.isnan(s0).all()


def test_nis_verdict_judges_the_mean_of_correlated_records():
    """A NIS whose mean is too low is `conservative` even when few records fall below the
    χ²₆ band (issue 51: the steady-state NIS at 3.5–4.6 against 6 read `consistent`); the
    mean is judged at the records' worth as independent ones, so correlated records of the
    right size stay `consistent` (Monte Carlo, 300 AR(1) series: at most 2 false alarms,
    the binomial limit for 1e-3 is 1, the correlation estimate adds a little)."""
    from scipy import stats

    from rsra.daq.analysis.report import FALSE_ALARM, effective_records, nis_consistency

    lo, hi = stats.chi2.ppf(FALSE_ALARM / 2, 6), stats.chi2.isf(FALSE_ALARM / 2, 6)
    rng = np.random.default_rng(51)

    def ar_nis(n, phi):
        x = rng.standard_normal(6)
        e = np.empty((n, 6))
        for i in range(n):
            x = phi * x + np.sqrt(1 - phi**2) * rng.standard_normal(6)
            e[i] = x
        return (e**2).sum(axis=1)

    low = 0.75 * rng.chisquare(6, 2000)  # mean 4.5: 0.1 % below the band, as in a real run
    v = nis_consistency(low, lo, hi)
    assert v["below"] < v["limit"] and v["verdict"] == "conservative"
    false = [nis_consistency(ar_nis(2000, 0.8), lo, hi)["verdict"] for _ in range(300)]
    assert len(false) - false.count("consistent") <= 2
    assert nis_consistency(0.7 * ar_nis(2000, 0.8), lo, hi)["verdict"] == "conservative"
    assert nis_consistency(1.4 * ar_nis(2000, 0.8), lo, hi)["verdict"] == "inconsistent"
    white = effective_records(rng.chisquare(6, 4000))
    assert 0.85 * 4000 <= white <= 4000
    assert effective_records(ar_nis(4000, 0.9)) < 0.3 * 4000


def test_the_report_says_the_last_advice_in_a_sentence(synth_truth, cfg, tmp_path):
    """A filter-error window's advice reaches the report (summary, headline, Markdown) as the
    sentence `rsra listen` shows (issue 51)."""
    from rsra.daq.analysis.report import Report, _markdown, load_records, load_truth, summarise

    tr = load_truth(synth_truth, read_truth)
    p, t, cal, _ = _phase_run(cfg, tr, tmp_path)
    names = list(cfg.rig_model().geometry.angle_names)
    adv = {"determined": 11, "next": 0.5, "window": {"extra_s": 4.0, "gain": 1},
           "accelerometers": [], "manoeuvres": [{"axis": "Z", "rms": 5000.0, "determined": 12,
                                                 "gain": 1, "next": 1.3}],
           "best": {"kind": "manoeuvre", "name": "Z", "gain": 1, "next": 1.3}}
    extra = {"key": "angles", "t": float(t[-1]), "seq": len(t) - 1, "accepted": True,
             "reason": None, "mode": "filter_error", "content": "vibration", "names": names,
             "alpha": [0.0] * 14, "P": (np.eye(14) * 1e-4).tolist(), "determined": 11,
             "applies_from_seq": len(t), "advice": adv}
    with open(p, "a") as f:
        f.write(dumps(extra) + "\n")
    _, s = summarise(cfg, load_records(p), tr)
    sentence = s["angles"]["advice"]["sentence"]
    assert sentence.startswith("This window determines 11 of 14 directions. A vertical (Z) "
                               "excitation of ~5.0 kN RMS would determine 1 more direction")
    assert sentence in Report(tmp_path, [], {}, s).markdown_brief()
    assert sentence in _markdown({**s, "plots": [], "skipped": {}}, "si")
