"""`rsra calibrate RECORDING… --posterior P.json` end to end (docs/cli.md): two recordings of
one aircraft (the simulator alone in lock-step, `ground-test` with the same true angles, other
seeds), pooled into a posterior that `rsra angles show` reads and `rsra replay --angles` uses.
Each recording is 30 s (three of the six static conditions; ≈ 2 s to simulate)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import chi2

from rsra.daq.cli import main
from rsra.daq.runtime.persistence import load_posterior
from rsra.estimator.angle_uncertainty import hub_angle_quadratic, hub_angle_sensitivity
from rsra.estimator.balance import inertial_loads, static_estimate
from rsra.sim_bus import load_scenario
from rsra.sim_bus.drivers import LockstepSim
from rsra.sim_bus.truth import read_truth

FALSE_ALARM = 1e-3
SECONDS = 30.0


def _record(cfg, folder, seed: int, base_deg: list[float]) -> None:
    folder.mkdir(parents=True)
    sc = load_scenario("ground-test", **{"angles.base": base_deg})
    with LockstepSim(cfg, sc, seed=seed, autostart=True, record=folder / "run.log",
                     channel=f"pooling-cli-{seed}") as sim:
        sim.run(SECONDS)
        sim.write_truth(folder / "truth.npz")


@pytest.fixture(scope="module")
def two_recordings(cfg, tmp_path_factory):
    root = tmp_path_factory.mktemp("pool")
    base = [round(float(v), 3) for v in np.random.default_rng(20).uniform(-3, 3, 14)]
    for k, seed in enumerate((21, 22)):
        _record(cfg, root / f"r{k}", seed, base)
    return root


def _replay_hub_loads(rec, out, *extra) -> tuple[np.ndarray, np.ndarray]:
    assert main(["replay", str(rec / "run.log"), "--no-identification", "--out", str(out),
                 *extra]) == 0
    H, sig = [], []
    for line in out.read_text().splitlines():
        r = json.loads(line)
        if r["key"] == "hub_loads" and r["H_static"] is not None:
            H.append(r["H_static"])
            sig.append(r["sigma_angles"])
    return np.array(H), np.array(sig)


def test_calibrate_posterior_round_trips_through_angles_show_and_replay(
        cfg, two_recordings, tmp_path, capsys):
    root = two_recordings
    post = tmp_path / "P.json"
    logs = [str(root / f"r{k}" / "run.log") for k in range(2)]
    assert main(["calibrate", *logs, "--posterior", str(post), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)["posterior"]
    assert rep["homogeneity"]["reject"] is False
    assert [r["recording"] for r in rep["recordings"]] == logs
    st = load_posterior(post)
    truth = read_truth(root / "r0" / "truth.npz")
    alpha = truth["alpha_true"][0]
    e = st.theta - alpha
    assert float(e @ np.linalg.solve(st.P, e)) <= chi2.isf(FALSE_ALARM, 14)
    assert st.reference_load is not None and st.rig is not None
    # rsra angles show reads it
    assert main(["angles", "show", str(post), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert np.allclose(shown["angles_deg"], np.degrees(st.theta))
    assert np.allclose(shown["sigma_deg"], np.degrees(np.sqrt(np.diag(st.P))))
    # rsra replay --angles uses it: hub loads from its angles (nearer the truth than the
    # recording's starting 0°) with its covariance (sigma_angles = √diag(J P Jᵀ), model §7)
    H1, s1 = _replay_hub_loads(root / "r1", tmp_path / "with.jsonl", "--angles", str(post))
    tr = read_truth(root / "r1" / "truth.npz")
    model = cfg.rig_model()
    n = len(H1)
    H0 = static_estimate(model, np.zeros(14), tr["T"][:n], inertial_loads(model, tr["accel"][:n]))
    rms1 = np.sqrt(np.mean((H1 - tr["H_true"][:n]) ** 2, axis=0))
    rms0 = np.sqrt(np.mean((H0 - tr["H_true"][:n]) ** 2, axis=0))
    A = hub_angle_sensitivity(model.geometry, st.theta)
    T = tr["T"][:n]
    want = np.sqrt(np.einsum("ni,kim,nm->nk", T, hub_angle_quadratic(A, st.P), T)).mean(0)
    P0 = np.eye(14) * cfg.identification.prior_sigma_rad ** 2
    prior = np.sqrt(np.einsum("ni,kim,nm->nk", T, hub_angle_quadratic(A, P0), T)).mean(0)
    print(f"H_static RMS error with the posterior {np.round(rms1)}, at 0° {np.round(rms0)}; "
          f"sigma_angles {np.round(s1.mean(0))}, from P {np.round(want)}, prior {np.round(prior)}")
    assert np.all(rms1[[1, 3, 5]] < 0.8 * rms0[[1, 3, 5]]) and np.all(rms1 < 1.05 * rms0)
    assert np.all((s1.mean(0) > 0.5 * want) & (s1.mean(0) < 2 * want))
    assert np.all(s1.mean(0) < 0.2 * prior)


def test_calibrate_posterior_refuses_what_it_may_not_replace(cfg, two_recordings, tmp_path,
                                                            capsys):
    log = str(two_recordings / "r0" / "run.log")
    foreign = tmp_path / "notes.json"
    foreign.write_text("{}\n")
    for argv, words in (([log, "--posterior", str(foreign)], "replaces only a posterior"),
                        ([log, "--posterior", str(tmp_path / "P.json"), "--params", "delta_A"],
                         "only with --params angles")):
        assert main(["calibrate", *argv]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1
    assert foreign.read_text() == "{}\n" and not (tmp_path / "P.json").exists()


def test_the_information_product_of_a_recording_pools_to_the_calibrate_posterior(
        cfg, two_recordings, tmp_path, capsys):
    """The campaign's `information` product (one file per recording, no recording column: the
    partition names it) read back and pooled gives the posterior `calibrate --posterior`
    writes from the same recordings."""
    import pyarrow.parquet as pq

    from rsra.daq.analysis.information import (
        information_product,
        pooled_posterior,
        read_information,
    )

    files = {}
    for k in range(2):
        stage = tmp_path / f"stage{k}"
        stage.mkdir()
        summary = information_product(two_recordings / f"r{k}" / "run.log", cfg,
                                      {"recording": f"r{k}"}, stage)
        assert summary["windows"] == 6 and summary["reason"] is None
        assert "recording" not in pq.read_schema(stage / "part.parquet").names
        files[f"r{k}"] = [stage / "part.parquet"]
    table, cols = read_information(files)
    pooled = pooled_posterior(cfg, table, cols)
    post = tmp_path / "P.json"
    logs = [str(two_recordings / f"r{k}" / "run.log") for k in range(2)]
    assert main(["calibrate", *logs, "--posterior", str(post), "--json"]) == 0
    capsys.readouterr()
    st = load_posterior(post)
    assert np.allclose(pooled.state.theta, st.theta, rtol=0, atol=1e-12)
    assert np.allclose(pooled.state.P, st.P, rtol=1e-9)
    assert np.allclose(pooled.state.reference_load, st.reference_load)
