"""The service end to end on the virtual bus, simulator in lock-step — the scenarios' verdicts:
ground-test converges from a 4° start, paper is never identifiable, flight with faults runs
to the end with every fault visible."""
import json

import numpy as np
import pytest

from rsra.daq.cli.options import config_for_run
from rsra.config.rig import load_config
from rsra.daq.runtime.service import Service, ServiceOptions
from rsra.estimator.noise_budget import noise_budget

CHI2_14_SINGLE = 36.1  # docs/performance.md: a single run, joint chi2_14 at 1e-3


def _run(cfg, **kw):
    opts = ServiceOptions(speed=None, zenoh=False, **kw)
    svc = Service(cfg, opts)
    recs: dict[str, list] = {}
    truth: dict[int, object] = {}

    def sink(key, payload):
        recs.setdefault(key, []).append(payload)
        if key == "hub_loads" and svc.sim is not None and svc.sim.last_sample is not None:
            s = svc.sim.last_sample
            if s.index == payload["seq"]:
                truth[payload["seq"]] = (np.array(s.H_true), np.array(s.alpha_true))

    svc.add_sink(sink)
    summary = svc.run()
    return svc, recs, truth, summary


@pytest.mark.timeout(600)
def test_ground_test_converges_from_4_degrees_and_beats_the_static_bound():
    cfg = load_config(None, overrides={"identification": {"initial_angles_deg": 4.0}})
    svc, recs, truth, summary = _run(cfg, sim="ground-test", seed=11, duration=125.0)
    assert summary["lost"] == 0
    angles = recs["angles"]
    acc = [a for a in angles if a["accepted"]]
    assert acc, [a["reason"] for a in angles]
    last = angles[-1]
    alpha_true = truth[max(truth)][1]
    e = np.array(last["alpha"]) - alpha_true
    P = np.array(last["P"])
    chi2 = float(e @ np.linalg.solve(P, e))
    sig = np.sqrt(np.diag(P))
    print("angles chi2", chi2, "max sigma deg", np.degrees(sig.max()),
          "accepted", len(acc), "of", len(angles))
    assert chi2 <= CHI2_14_SINGLE
    assert np.degrees(sig.max()) <= 0.2
    # the angles in force match the last accepted record
    assert np.allclose(svc.pipeline.alpha, acc[-1]["alpha"])
    # hub loads scored once converged: the last 20 s. Windows alternate between accepted and
    # not_identifiable once the angles have converged (a window's information no longer
    # adds), so an update may apply inside the span; converged updates move the angles by
    # less than their σ, which the static bound covers
    start = max(truth) - int(20 * cfg.sample_rate_hz)
    late = [a for a in acc if a["applies_from_seq"] >= start]
    assert late and all(a["applies_from_seq"] > acc[0]["applies_from_seq"] for a in late)
    # the load filter's random-walk states follow a 0.5 s ramp of 10–20 kN between two static
    # conditions (the last 0.5 s of each slot) with a lag of about τ = 0.1 s (3 kN·m on a
    # 15 kN·m yaw ramp): the static bound is for held loads, so the ramp and the second after
    # it are not scored
    from rsra.sim_bus.scenarios import load_scenario

    hold = load_scenario("ground-test").loads.hold_s
    fs = cfg.sample_rate_hz
    H = {h["seq"]: h["H"] for h in recs["hub_loads"]
         if h["seq"] >= start and h["H"] is not None
         and 1.0 <= (h["seq"] / fs) % hold < hold - 0.5 - 0.1}
    err = np.array([np.array(H[k]) - truth[k][0] for k in sorted(H) if k in truth])
    assert len(err) > 1000
    rms = np.sqrt((err**2).mean(axis=0))
    bound = noise_budget(cfg.rig_model(), np.array(last["alpha"])).total
    print("hub-load RMS / static bound", np.round(rms / bound, 3))
    assert np.all(rms < bound), rms / bound


@pytest.mark.timeout(300)
def test_paper_with_noise_every_run_rejected_and_angles_unchanged():
    cfg = config_for_run(None, "paper")  # the scenario starts the service at 4°
    alpha0 = cfg.identification.initial_angles_rad.copy()
    svc, recs, truth, summary = _run(cfg, sim="paper", duration=30.0)
    angles = recs["angles"]
    assert len(angles) >= 5
    assert all(not a["accepted"] for a in angles)
    assert {a["reason"] for a in angles} <= {"not_identifiable", "inconsistent"}, \
        [a["reason"] for a in angles]
    assert all(a["mode"] == "filter_error" for a in angles)  # no balance: loads unknown
    assert np.array_equal(svc.pipeline.alpha, alpha0)
    assert all(np.array_equal(np.array(a["alpha"]), alpha0) for a in angles)


@pytest.mark.timeout(300)
def test_flight_with_faults_runs_to_the_end_with_every_fault_visible():
    cfg = load_config()
    faults = ("drop:cell_B:0.05;malformed:cell_D:0.02;unknown:0.02;errorframe:0.01;"
              "lostsync:0.01;overrange:cell_E@4-5;stuck:accel_1@6-7;silent:cell_F@8-9;"
              "jitter:0.3ms")
    # the whole fault log (kept for a truth file; otherwise only its last 1 024 entries)
    svc, recs, truth, summary = _run(cfg, sim="flight", faults=faults, duration=12.0, seed=4,
                                     keep_truth=True)
    n = round(12.0 * cfg.sample_rate_hz)
    hub = recs["hub_loads"]
    assert hub[-1]["seq"] == n - 1  # ran to the end (lost samples keep their numbers)
    log = svc.sim.fault_log
    lost = sum(1 for f in log if f["kind"] == "lostsync")
    assert summary["lost"] == lost
    flags = [f for h in hub for f in h["flags"]]
    assert "missing:cell_B" in flags and "missing:cell_D" in flags
    assert "overrange:E" in flags and "missing:cell_F" in flags  # cells by name, nodes by node
    assert "predict_only" in flags and ("lost_before" in flags or lost == 0)
    assert len(recs["health"]) >= 11  # 1 Hz of acquisition time
    health = svc.reader.health().to_dict()  # at the end (the last 1 Hz record is up to 1 s older)
    bus = health["bus"]
    kinds = {f["kind"] for f in log}
    assert bus["unknown"] == sum(1 for f in log if f["kind"] == "unknown")
    assert bus["errors"] == sum(1 for f in log if f["kind"] == "errorframe")
    assert bus["malformed"] == sum(1 for f in log if f["kind"] == "malformed")
    assert {"drop", "malformed", "unknown", "errorframe", "overrange", "silent"} <= kinds
    # every queue bounded: the reader's never went past its size
    q = health["queues"]["samples"]
    assert q["max_depth"] <= q["size"] and q["dropped"] == 0
    # the silent node came back: its channels are in the last samples again
    assert all("missing:cell_F" not in h["flags"] for h in hub[-200:])
    json.dumps(health, allow_nan=False)
