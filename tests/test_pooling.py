"""A posterior pooled across recordings (docs/identification.md, "Pooling recordings"):
estimator.pooling on the independent synthetic generator (tests/synthetic.py: truth built with
scipy's Rotation, quasi-static ground-test sweeps), the information tables and the pooled
posterior of daq.analysis.information, and `rsra campaign calibrate` on a tiny dataset made
here (a manifest and information tables only)."""
from __future__ import annotations

import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.stats import chi2

from rsra.daq.analysis.calibrate import CalibrationData
from rsra.daq.analysis.information import (
    PoolingError,
    information_table,
    pooled_posterior,
    x_columns,
)
from rsra.daq.campaign import calibrate as campaign_calibrate
from rsra.estimator.balance import inertial_loads
from rsra.estimator.content import ContentFilter
from rsra.estimator.identification import KnownLoadProblem, Parameterisation, levenberg_marquardt
from rsra.estimator.pooling import Recording, pool, window_statistics

from synthetic import static_run

FALSE_ALARM = 1e-3
RAD = math.radians(1.0)


def _filtered(cfg, run) -> tuple[np.ndarray, np.ndarray]:
    """x = [z, T, H] through the `static` content filter, its settling not scored."""
    model = cfg.rig_model()
    x = np.hstack([inertial_loads(model, run.accel), run.T, run.H_m])
    cf = ContentFilter("static", cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       tuple(cfg.filter.harmonics), x.shape[1],
                       cfg.identification.settle_time_constants)
    y = cf.process(x)
    scored = np.ones(len(y), bool)
    scored[:cf.settle_samples] = False
    return y, scored


def _recordings(cfg, alphas, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """One sweep of the six static conditions per true-angle vector (quasi-static)."""
    rng = np.random.default_rng(seed)
    return [_filtered(cfg, static_run(cfg, a, rng, sweeps=1)) for a in alphas]


def _par(cfg):
    return Parameterisation(cfg.rig_model(), None, np.zeros(14),
                            moment_floor=cfg.identification.moment_floor_Nm, known_loads=True)


def _recs(data, t=None) -> list[Recording]:
    out = []
    for k, (y, sc) in enumerate(data):
        _, n, _, G = window_statistics(y, sc, 1000)
        out.append(Recording(f"r{k}", G.sum(0), int(n.sum()), math.nan if t is None else t[k]))
    return out


def _truth(seed: int) -> np.ndarray:
    return np.radians(np.random.default_rng(seed).uniform(-4, 4, 14))


# ------------------------------------------------------------------------------------------
# estimator.pooling


def test_pooling_equals_identifying_the_concatenation_and_counts_the_prior_once(cfg):
    """Pooled from K = 3 recordings' moments = one identification of their concatenated data
    (the prior once): θ within 1e-9 rad, P within 1e-8 relative. The prior is tight here
    (σ 0.05°, comparable to one sweep's information) so a prior counted K times moves both far
    beyond the tolerance; and P⁻¹ − Σ M_k is the prior's information, once."""
    alpha = _truth(1)
    data = _recordings(cfg, [alpha] * 3, seed=2)
    par = _par(cfg)
    P_p = np.eye(14) * (0.05 * RAD) ** 2
    theta_p = alpha + 0.05 * RAD * np.random.default_rng(3).standard_normal(14)
    res = pool(par, _recs(data), theta_p, P_p)
    y = np.vstack([d[0] for d in data])
    sc = np.concatenate([d[1] for d in data])
    one = levenberg_marquardt(KnownLoadProblem(par, y[:, :6], y[:, 6:13], y[:, 13:], scored=sc),
                              theta_p, P_p)
    assert res.ident.status == one.status == "converged"
    assert np.abs(res.theta - one.theta).max() < 1e-9
    assert np.abs(res.P / one.P - 1).max() < 1e-8
    prior_info = np.linalg.inv(res.P) - sum(res.information)
    assert np.allclose(prior_info, np.linalg.inv(P_p), rtol=1e-4, atol=1e-6 * np.abs(
        np.linalg.inv(P_p)).max())


def test_homogeneity_passes_equal_angles_and_names_a_half_degree_step(cfg):
    """Four recordings of one aircraft agree (χ² within its 1e-3 limit, nobody named); the
    same with 0.5° added to every angle (random signs) from the third recording on is
    rejected and the test names recordings on both sides of the step."""
    alpha = _truth(4)
    par = _par(cfg)
    P_p = np.eye(14) * (5 * RAD) ** 2
    t = [0.0, 3600.0, 7200.0, 10800.0]
    same = pool(par, _recs(_recordings(cfg, [alpha] * 4, seed=5), t), np.zeros(14), P_p)
    h = same.homogeneity
    assert h.dof == 3 * 14 and not h.reject and h.disagree == []
    assert h.statistic <= chi2.isf(FALSE_ALARM, h.dof)
    step = 0.5 * RAD * np.where(np.random.default_rng(6).random(14) < 0.5, -1, 1)
    moved = pool(par, _recs(_recordings(cfg, [alpha, alpha, alpha + step, alpha + step],
                                        seed=5), t), np.zeros(14), P_p)
    hm = moved.homogeneity
    print(f"equal: χ² {h.statistic:.1f} on {h.dof}; step: {hm.statistic:.1f}, sequential "
          f"{np.round(hm.sequential, 1)}, leave-one-out {np.round(hm.leave_one_out, 1)}")
    assert hm.reject and hm.statistic > 10 * hm.limit
    assert int(np.nanargmax(hm.sequential)) == 2  # the change is at the third recording
    assert {0, 1} & set(hm.disagree) and {2, 3} & set(hm.disagree)
    # the trend over time sees the step as a slope
    assert hm.trend_p_value is not None and hm.trend_p_value < FALSE_ALARM
    assert same.homogeneity.trend_p_value > FALSE_ALARM


def test_the_drift_allowance_widens_the_posterior_and_states_its_floor(cfg):
    """With the rig's random walk between recordings a day apart the posterior (about the
    angles at the last recording) is wider than the constant-angle one, the step between
    recordings is tested against the allowance, and the floor on σ is stated."""
    alpha = _truth(7)
    par = _par(cfg)
    P_p = np.eye(14) * (5 * RAD) ** 2
    recs = _recs(_recordings(cfg, [alpha] * 3, seed=8), [0.0, 86400.0, 2 * 86400.0])
    const = pool(par, recs, np.zeros(14), P_p)
    walk = pool(par, recs, np.zeros(14), P_p, drift_rate=1e-9)
    s0, s1 = np.sqrt(np.diag(const.P)), np.sqrt(np.diag(walk.P))
    assert np.all(s1 > s0)
    assert walk.sigma_floor is not None and np.all(walk.sigma_floor > 0)
    assert const.sigma_floor is None
    e = walk.theta - alpha
    assert float(e @ np.linalg.solve(walk.P, e)) <= chi2.isf(FALSE_ALARM, 14)
    assert not walk.homogeneity.reject


# ------------------------------------------------------------------------------------------
# information tables and the pooled posterior (daq.analysis.information)


def _data(cfg, y, sc) -> CalibrationData:
    return CalibrationData(z=y[:, :6], T=y[:, 6:13], H=y[:, 13:19], q=None,
                           valid=np.ones(len(y), bool), scored=sc, content="static",
                           fs=cfg.sample_rate_hz, files=("x",), segments=1,
                           samples_read=len(y), t_first=0.0)


def _tables(cfg, alphas, seed=9):
    return [information_table(cfg, _data(cfg, y, sc), f"rec{k}")
            for k, (y, sc) in enumerate(_recordings(cfg, alphas, seed))]


def test_information_table_schema_and_the_posterior_it_pools(cfg):
    """One row per 5-s window, the documented columns; the windows' moments sum to the
    recording's; the pooled posterior is the state file's (14 angles, P, reference load near
    the ground test's thrust, the rig fingerprint) and within its χ²₁₄ limit of the truth."""
    alpha = _truth(10)
    tabs = _tables(cfg, [alpha, alpha])
    t = tabs[0]
    assert t.column_names == ["recording", "rig_fingerprint", "content", "t_start", "window",
                              "first_sample", "n_scored", "sum", "moments"]
    meta = t.schema.metadata
    assert meta[b"rsra.information.version"] == b"1"
    assert json.loads(meta[b"rsra.information.columns"]) == x_columns(cfg)
    assert t.num_rows == 12  # 60 s in 5-s windows
    pooled = pooled_posterior(cfg, pa.concat_tables(tabs), x_columns(cfg))
    st = pooled.state
    assert st.names == cfg.rig_model().geometry.angle_names and st.P.shape == (14, 14)
    assert st.rig is not None and st.reference_load is not None
    assert -90e3 < st.reference_load[2] < -70e3  # thrust near 80 kN up (z down)
    e = st.theta - alpha
    assert float(e @ np.linalg.solve(st.P, e)) <= chi2.isf(FALSE_ALARM, 14)
    assert pooled.homogeneous and len(pooled.report()["recordings"]) == 2


def test_recordings_of_two_rigs_are_refused(cfg):
    alpha = _truth(11)
    tabs = _tables(cfg, [alpha, alpha])
    other = tabs[1].set_column(1, "rig_fingerprint",
                               pa.array(['{"other": 1}'] * tabs[1].num_rows))
    with pytest.raises(PoolingError, match="2 rigs"):
        pooled_posterior(cfg, pa.concat_tables([tabs[0], other]), x_columns(cfg))


# ------------------------------------------------------------------------------------------
# rsra campaign calibrate on a tiny dataset


def _dataset(cfg, root, alphas, fingerprints=None, seed=12):
    from rsra.daq.analysis.information import fingerprint_text

    tabs = _tables(cfg, alphas, seed)
    ids = [f"rec{k}" for k in range(len(tabs))]
    fps = fingerprints or [fingerprint_text(cfg)] * len(tabs)
    for rid, t in zip(ids, tabs):
        folder = root / "information" / f"recording={rid}"
        folder.mkdir(parents=True)
        pq.write_table(t.drop_columns(["recording"]), folder / "part.parquet")
    pq.write_table(pa.table({"recording": ids, "rig_fingerprint": fps,
                             "t_start": [3600.0 * k for k in range(len(ids))],
                             "status": ["ok"] * len(ids)}), root / "manifest.parquet")
    return ids


def _campaign(argv, capsys) -> tuple[int, str, str]:
    import argparse

    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    campaign_calibrate.add_parser(sub, "calibrate")
    args = p.parse_args(["calibrate", *argv])
    rc = campaign_calibrate.run(args)
    out, err = capsys.readouterr()
    return rc, out, err


def test_campaign_calibrate_writes_a_posterior_and_the_homogeneity_table(cfg, tmp_path, capsys):
    from rsra.daq.runtime.persistence import load_posterior

    alpha = _truth(13)
    ds = tmp_path / "ds"
    ids = _dataset(cfg, ds, [alpha] * 3)
    out = tmp_path / "P.json"
    rc, text, err = _campaign(["--dataset", str(ds), "--out", str(out)], capsys)
    assert rc == 0, err
    assert "they agree" in text and str(out) in text
    st = load_posterior(out)
    e = st.theta - alpha
    assert float(e @ np.linalg.solve(st.P, e)) <= chi2.isf(FALSE_ALARM, 14)
    hom = pq.read_table(ds / "calibration" / "homogeneity.parquet")
    assert hom.column("recording").to_pylist() == ids
    whole = json.loads(hom.schema.metadata[b"rsra.homogeneity"])
    assert whole["homogeneity"]["reject"] is False
    # a subset by id
    rc, text, _ = _campaign(["--dataset", str(ds), "--recordings", "rec0", "rec2", "--out",
                             str(out), "--json"], capsys)
    assert rc == 0 and [r["recording"] for r in json.loads(text)["recordings"]] == ["rec0", "rec2"]


def test_campaign_calibrate_refuses_to_write_when_the_recordings_disagree(cfg, tmp_path, capsys):
    alpha = _truth(14)
    step = 0.5 * RAD * np.where(np.random.default_rng(15).random(14) < 0.5, -1, 1)
    ds = tmp_path / "ds"
    _dataset(cfg, ds, [alpha, alpha, alpha + step, alpha + step])
    out = tmp_path / "P.json"
    rc, text, err = _campaign(["--dataset", str(ds), "--out", str(out)], capsys)
    assert rc == 1 and not out.exists()
    assert "disagree" in err and "rec" in err.split("at 1e-3):")[1]
    assert (ds / "calibration" / "homogeneity.parquet").is_file()


@pytest.mark.parametrize("case, words", [
    ("two_rigs", "2 rigs"), ("unknown_id", "not in the manifest"),
    ("no_manifest", "no manifest.parquet"), ("foreign_out", "replaces only a posterior"),
])
def test_campaign_calibrate_bad_input_is_one_line_exit_2(cfg, tmp_path, capsys, case, words):
    from rsra.daq.analysis.information import fingerprint_text

    alpha = _truth(16)
    ds = tmp_path / "ds"
    out = tmp_path / "P.json"
    argv = ["--dataset", str(ds), "--out", str(out)]
    if case == "two_rigs":
        _dataset(cfg, ds, [alpha, alpha], [fingerprint_text(cfg), '{"other": 1}'])
    elif case == "unknown_id":
        _dataset(cfg, ds, [alpha])
        argv += ["--recordings", "nope"]
    elif case == "no_manifest":
        ds.mkdir()
    else:
        _dataset(cfg, ds, [alpha])
        out.write_text("not a posterior\n")
    rc, text, err = _campaign(argv, capsys)
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err
    if case == "foreign_out":
        assert out.read_text() == "not a posterior\n"
    else:
        assert not out.exists()
