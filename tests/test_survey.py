"""The loads survey (estimator/survey.py, daq/analysis/survey.py, `rsra survey`, `rsra mark`)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.stats import binom

from rsra.daq.analysis import survey as sv
from rsra.daq.runtime.marks import MarkError, mark_payload, parse_mark
from rsra.estimator import survey as num

DT = 0.005
TAU = 0.1


def _azimuth(n: int, omega0: float = 19.4, seed: int = 0) -> np.ndarray:
    """A rotor whose speed varies by ±5 % (slow) with a 0.8 Hz governor wobble on top."""
    t = np.arange(n) * DT
    omega = omega0 * (1 + 0.05 * np.sin(2 * np.pi * t / 7.0) + 0.01 * np.sin(2 * np.pi * 0.8 * t))
    return np.cumsum(omega) * DT + np.random.default_rng(seed).uniform(0, 2 * np.pi)


def test_harmonics_on_the_measured_azimuth_with_a_varying_rotor_speed():
    n = 4000
    psi = _azimuth(n)
    y = 500.0 + 3000.0 * np.cos(psi - np.radians(40.0)) + 1200.0 * np.cos(5 * psi + np.radians(
        100.0)) + np.random.default_rng(1).normal(0, 50.0, n)
    wrapped = np.mod(psi, 2 * np.pi)  # as the rotor-speed node sends it
    model = num.ErrorModel(np.full(n, 50.0), 0.0)
    h = {x.order: x for x in num.harmonics(y, num.unwrap_azimuth(wrapped), [1, 2, 5], model)}
    assert h[1].amplitude == pytest.approx(3000.0, abs=4 * h[1].amplitude_sigma)
    assert h[1].phase_deg == pytest.approx(40.0, abs=0.5)
    assert h[5].amplitude == pytest.approx(1200.0, abs=4 * h[5].amplitude_sigma)
    assert h[5].phase_deg == pytest.approx(-100.0, abs=0.5)
    assert h[2].amplitude < 4 * h[2].amplitude_sigma
    # the same fit on a nominal Ω (what the survey never does) smears the harmonics
    nominal = np.arange(n) * DT * 19.4 + psi[0]
    h_nom = {x.order: x for x in num.harmonics(y, nominal, [1, 2, 5], model)}
    assert abs(h_nom[5].amplitude - 1200.0) > 300.0


def test_whole_revolutions_leave_out_the_partial_ends():
    psi = num.unwrap_azimuth(np.mod(_azimuth(2000), 2 * np.pi))
    revs = num.whole_revolutions(psi)
    assert revs
    for i0, i1 in revs:
        turns = np.floor(psi[i0:i1] / (2 * np.pi))
        assert (turns == turns[0]).all()
        assert math.floor(psi[i0 - 1] / (2 * np.pi)) == turns[0] - 1
        assert math.floor(psi[i1] / (2 * np.pi)) == turns[0] + 1


def test_test_point_sigma_holds_for_errors_correlated_across_samples():
    """The mean over a point: a common angle error and a filter error coloured over τ. Over
    M Monte Carlo points the count beyond 3σ must stay within the binomial 10⁻³ limit of a
    Gaussian's 0.27 %, and that beyond 1σ above its 10⁻³ lower limit (not conservative
    either); the √N rule of the per-sample σ fails it."""
    n, M = 2000, 600
    rng = np.random.default_rng(7)
    T = rng.normal(0.0, 1.0, (n, 7)) * 0.05 + 1.0  # the cell loads of a held condition
    sens = rng.normal(0.0, 25.0, (7, 3))  # the axis's angle sensitivity times √P
    model = num.ErrorModel(np.full(n, 300.0), math.exp(-DT / TAU), T, sens)
    w = np.full(n, 1.0 / n)
    sigma = float(num.functional_sigma(w, model)[0])
    err = num.draw_errors(model, M, rng) @ w
    per_sample = math.sqrt(300.0 ** 2 + float(np.mean(np.sum((T @ sens) ** 2, axis=1))))
    limit = binom.isf(1e-3, M, 2 * 0.00135)
    assert np.sum(np.abs(err) > 3 * sigma) <= limit
    assert np.sum(np.abs(err) > sigma) >= binom.ppf(1e-3, M, 0.3173)
    assert np.sum(np.abs(err) > 3 * per_sample / math.sqrt(n)) > limit  # the √N rule fails


def test_rainflow_and_del_of_a_known_series():
    y = np.array([0.0, 10.0, 0.0, 10.0, 0.0])  # two full cycles of range 10
    r, c = num.rainflow_ranges(y)
    assert float(np.sum(c[r == 10.0])) == pytest.approx(2.0)
    n, dels = num.fatigue(y, [4.0], reference_cycles=2.0)
    assert n == pytest.approx(2.0) and dels[0] == pytest.approx(10.0)
    _, dels = num.fatigue(y, [4.0], reference_cycles=32.0)
    assert dels[0] == pytest.approx(10.0 * (2 / 32) ** 0.25)


def _data(n: int, azimuth: bool) -> sv.SurveyData:
    t = 1000.0 + np.arange(n) * DT
    psi = _azimuth(n)
    H = np.zeros((n, 6))
    H[:, 2] = -80000.0 + 3000.0 * np.cos(psi) + 1000.0 * np.cos(5 * psi)
    H[:, 4] = 2000.0 * np.cos(psi - 1.0)
    rng = np.random.default_rng(3)
    Hs = H + rng.normal(0.0, 100.0, H.shape)
    return sv.SurveyData(t=t, seq=np.arange(n), H=H + rng.normal(0, 20.0, H.shape), H_static=Hs,
                         sigma_angles=np.full((n, 6), 50.0), sigma_filter=np.full((n, 6), 100.0),
                         transient=np.zeros(n, bool),
                         azimuth=np.mod(psi, 2 * np.pi) if azimuth else np.full(n, np.nan),
                         T=np.full((n, 7), np.nan))


RIG = sv.SurveyRig(blades=5, modelled=(1, 5), dt=DT, time_constant_s=TAU,
                   bound=np.full(6, 100.0), angle_names=tuple(f"a{i}" for i in range(14)))


def _rows(data):
    tp = sv.TestPoint("hover", float(data.t[0]), float(data.t[-1]), "file")
    rows = sv.survey(data, [tp], RIG, sv.SurveyOptions(draws=4))
    return {(r["axis"], r["quantity"]): r for r in rows}


def test_survey_of_a_point_names_its_estimates():
    rows = _rows(_data(3000, azimuth=True))
    assert rows[("Z", "mean")]["value"] == pytest.approx(-80000.0, abs=100.0)
    assert rows[("Z", "h1_amplitude")]["value"] == pytest.approx(3000.0, rel=0.02)
    assert rows[("Z", "h1_amplitude")]["estimate"] == "H"
    assert rows[("Z", "h3_amplitude")]["estimate"] == "H_static"
    assert rows[("Z", "alternating")]["value"] == pytest.approx(4000.0, rel=0.03)
    assert rows[("M", "h1_phase_deg")]["value"] == pytest.approx(math.degrees(1.0), abs=1.0)
    assert rows[("Z", "rainflow_cycles")]["unit"] == "cycles"
    assert ("Z", "del_m4") in rows and ("Z", "del_m10") in rows
    assert all(r["sigma"] > 0 for r in rows.values()
               if math.isfinite(r["value"]) and r["quantity"] != "rainflow_cycles")
    assert rows[("Z", "rainflow_cycles")]["sigma"] >= 0  # a count the noise may not change


def test_without_azimuth_harmonics_and_alternating_are_absent_with_the_reason():
    rows = _rows(_data(3000, azimuth=False))
    for q in ("h1_amplitude", "h5_phase_deg", "alternating", "alternating_max"):
        r = rows[("Z", q)]
        assert math.isnan(r["value"]) and math.isnan(r["sigma"])
        assert "no measured azimuth" in r["note"] and "nominal" in r["note"]
    assert math.isfinite(rows[("Z", "mean")]["value"])  # the rest is there


def test_alternating_leaves_a_manoeuvres_quasi_static_change_out():
    """Half the peak-to-peak per revolution of the periodic part: a roll's raised-cosine
    excursion (15 kN·m in 3 s, several kN·m within one revolution) adds nothing to it (a fit
    of the harmonics alone folds the drift into them — break-checked: without the drift
    term the largest half is off by 14 %)."""
    n = 1400
    psi = _azimuth(n)
    t = np.arange(n) * DT
    roll = 15000.0 * 0.5 * (1 - np.cos(2 * np.pi * np.clip(t - 1.0, 0, 3.0) / 3.0))
    y = roll + 3000.0 * np.cos(psi) + 1000.0 * np.cos(5 * psi)
    pu = num.unwrap_azimuth(np.mod(psi, 2 * np.pi))
    rv = num.per_revolution(y, pu, num.whole_revolutions(pu), [1, 2, 3, 4, 5])
    steady = num.per_revolution(3000.0 * np.cos(psi) + 1000.0 * np.cos(5 * psi), pu,
                                num.whole_revolutions(pu), [1, 2, 3, 4, 5])
    np.testing.assert_allclose(np.mean(rv.halves), np.mean(steady.halves), rtol=0.03)
    assert np.max(rv.halves) == pytest.approx(np.max(steady.halves), rel=0.05)


def test_a_few_samples_without_azimuth_or_cell_loads_keep_the_harmonics():
    """Incomplete samples (no azimuth, no cell loads) inside a point: the harmonics and the
    alternating load come from the samples that have them, and the angle error from the cell
    loads where they exist (not the fully correlated bound of every sample)."""
    d = _data(3000, azimuth=True)
    d.T = np.full((3000, 7), 2.0e4)
    full = _rows_rig(d)
    d.azimuth[[400, 401, 1500]] = np.nan
    d.T[[400, 401, 1500]] = np.nan
    gaps = _rows_rig(d)
    for q in ("h1_amplitude", "h5_amplitude", "alternating"):
        a, b = full[("Z", q)], gaps[("Z", q)]
        assert b["value"] == pytest.approx(a["value"], rel=0.02), q
        assert b["sigma"] == pytest.approx(a["sigma"], rel=0.1), q


def test_an_unmodelled_harmonics_sigma_sees_the_noise_near_it():
    """H_static's error near 3/rev a narrow-band vibration (σ 300 N) where the static bound
    says white 100 N, under a 1/rev and a varying 5/rev of kN: the 3/rev amplitude's σ from
    the revolutions' scatter holds (noise alone: Rayleigh, 1.1 % beyond 3σ; the count within
    its binomial 10⁻³ limit over M points). Break-checked: with the white model alone 292 of
    the 300 points are beyond 3σ; fitting 3/rev without 1/rev and 5/rev leaks them into it
    (17 beyond, the limit 10)."""
    from scipy.signal import butter, sosfilt

    n, M = 2000, 300
    rng = np.random.default_rng(11)
    sos = butter(2, [7.0, 12.0], btype="band", fs=1 / DT, output="sos")
    beyond = 0
    for m in range(M):
        psi = _azimuth(n, seed=m)
        t = np.arange(n) * DT
        true = 3000.0 * np.cos(psi) + 2000.0 * (1 + 0.3 * np.sin(2 * np.pi * t / 15.0)) \
            * np.cos(5 * psi + 0.4)
        e = sosfilt(sos, rng.normal(0.0, 1.0, n + 400))[400:]
        y = true + 300.0 * e / e.std()
        pu = num.unwrap_azimuth(np.mod(psi, 2 * np.pi))
        orders = [1, 2, 3, 4, 5]
        scatter = num.revolution_scatter(y, pu, num.whole_revolutions(pu), orders, [3])
        h = {x.order: x for x in num.harmonics(y, pu, orders,
                                               num.ErrorModel(np.full(n, 100.0), 0.0),
                                               scatter=scatter)}[3]
        beyond += h.amplitude > 3 * h.amplitude_sigma
    assert beyond <= binom.isf(1e-3, M, math.exp(-4.5)), beyond


def _rows_rig(data):
    rig = sv.SurveyRig(blades=5, modelled=(1, 5), dt=DT, time_constant_s=TAU,
                       bound=np.full(6, 100.0), angle_names=tuple(f"a{i}" for i in range(14)),
                       sensitivity=lambda a: np.full((6, 7, 14), 1e-3))
    data.angles = [sv.AngleState(-1, np.zeros(14), np.eye(14) * 1e-6)]
    tp = sv.TestPoint("hover", float(data.t[0]), float(data.t[-1]), "file")
    return {(r["axis"], r["quantity"]): r
            for r in sv.survey(data, [tp], rig, sv.SurveyOptions(draws=4))}


def test_test_points_from_marks_transient_edges_and_toml(tmp_path):
    marks = [{"t": 10.0, "name": "hover"}, {"t": 20.0, "name": "40 kt"}, {"t": 25.0, "end": True},
             {"t": 30.0, "name": "80 kt"}]
    pts = sv.points_from_marks(marks, t_end=40.0)
    assert [(p.name, p.start, p.end) for p in pts] == [("hover", 10.0, 20.0), ("40 kt", 20.0, 25.0),
                                                       ("80 kt", 30.0, 40.0)]
    t = np.arange(0, 10, 0.005)
    tr = (t > 3) & (t < 3.5)
    held = sv.points_from_transient(t, tr)
    assert [p.name for p in held] == ["held 1", "held 2"]
    assert held[0].end <= 3.0 < 3.5 <= held[1].start
    f = tmp_path / "tp.toml"
    f.write_text('time = "from_start"\n[[test_point]]\nname = "a"\nstart = 1.0\nend = 2.0\n')
    assert sv.points_from_toml(f, t0=100.0) == [sv.TestPoint("a", 101.0, 102.0, "file")]
    f.write_text('[[test_point]]\nname = "a"\nstart = 2.0\nend = 1.0\n')
    with pytest.raises(sv.SurveyError, match="end > start"):
        sv.points_from_toml(f, t0=0.0)


def test_a_mark_from_outside_is_checked():
    assert parse_mark(mark_payload("hover 40 kt")) == {"name": "hover 40 kt"}
    assert parse_mark(mark_payload(None)) == {"end": True}
    for bad in (b"\xff\xfe", b"[1]", b'{"name": ""}', b'{"name": "a", "x": 1}',
                json.dumps({"name": "x" * 201}).encode(), b'{"name": "a\\u0007"}',
                b"{" + b" " * 2000 + b"}"):
        with pytest.raises(MarkError):
            parse_mark(bad)


# ---------------------------------------------------------------------------------------------
# the command line, end to end on a short recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from rsra.daq.cli import main
    from tests.helpers_net import free_tcp_port

    folder = tmp_path_factory.mktemp("survey") / "rec"
    rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "6",
               "--record", str(folder), "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"])
    assert rc == 0
    return folder


def test_survey_command_end_to_end(recording, tmp_path, capsys):
    import pyarrow.parquet as pq

    from rsra.daq.cli import main

    out = tmp_path / "out"
    assert main(["survey", str(recording), "--out", str(out), "--draws", "3",
                 "--units", "us"]) == 0
    for name in sv.SURVEY_FILES:
        assert (out / name).stat().st_size > 0
    table = pq.read_table(out / "survey.parquet")
    assert tuple(table.column_names) == sv.COLUMNS
    rows = table.to_pylist()
    assert {r["test_point"] for r in rows} == {"condition 1"}  # the scenario's (2 s … 6 s)
    assert {r["axis"] for r in rows} == set("XYZLMN")
    assert {r["unit"] for r in rows if r["quantity"] == "mean"} == {"lbf", "ft·lbf"}
    assert "h5_phase_deg" in {r["quantity"] for r in rows}
    assert "## Z [lbf]" in (out / "survey.md").read_text()


@pytest.mark.parametrize("case", ["missing", "bad_toml", "into_input", "bad_slopes"])
def test_survey_bad_input_one_line_exit_2(case, recording, tmp_path, capsys):
    from rsra.daq.cli import main

    out = tmp_path / "out"
    argv = ["survey", str(recording), "--out", str(out)]
    if case == "missing":
        argv[1] = str(tmp_path / "nothing")
    elif case == "bad_toml":
        (tmp_path / "tp.toml").write_text("[[test_point]]\nname = 'x'\n")
        argv += ["--test-points", str(tmp_path / "tp.toml")]
    elif case == "into_input":
        argv[3] = str(recording)
    else:
        argv += ["--sn-slopes", "four"]
    with pytest.raises(SystemExit) if case == "bad_slopes" else _nothing() as e:
        rc = main(argv)
    rc = e.value.code if case == "bad_slopes" else rc
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not out.exists()  # no empty output left
    assert "marks.jsonl" not in {p.name for p in recording.iterdir()}


class _nothing:
    value = None

    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def test_a_campaign_dataset_is_surveyed_per_recording(tmp_path):
    """`<key>/recording=<id>/*.parquet` with the columns of `rsra export --parquet`."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from rsra.estimator.noise_budget import AXES

    d = _data(1200, azimuth=True)
    hub = {"seq": d.seq, "t": d.t, "frame": ["body"] * len(d.t),
           "flags": [["transient"] if 500 <= i < 520 else [] for i in range(len(d.t))]}
    for name, arr in (("H", d.H), ("H_static", d.H_static), ("sigma_angles", d.sigma_angles),
                      ("sigma_filter", d.sigma_filter)):
        hub.update({f"{name}.{a}": arr[:, k] for k, a in enumerate(AXES)})
    ch = {"seq": d.seq, "t": d.t, "azimuth": d.azimuth,
          **{f"T.{c}": np.full(len(d.t), 1e4) for c in "ABCDEFG"}}
    for rid in ("r1", "r2"):
        for key, cols in (("hub_loads", hub), ("channels", ch)):
            part = tmp_path / "ds" / key / f"recording={rid}"
            part.mkdir(parents=True)
            pq.write_table(pa.table(cols), part / "part-0.parquet")
    assert sv.is_dataset(tmp_path / "ds")
    data = sv.load_dataset(tmp_path / "ds", RIG.angle_names)
    assert sorted(data) == ["r1", "r2"]
    np.testing.assert_allclose(data["r1"].H, d.H)
    np.testing.assert_allclose(data["r1"].azimuth, d.azimuth)
    assert data["r1"].transient.sum() == 20
    from rsra.daq.cli import main

    assert main(["survey", str(tmp_path / "ds"), "--out", str(tmp_path / "o"), "--draws",
                 "2"]) == 0
    rows = pq.read_table(tmp_path / "o" / "survey.parquet").to_pylist()
    assert {r["recording"] for r in rows} == {"r1", "r2"}
    assert {r["test_point"] for r in rows} == {"r1: held 1", "r1: held 2", "r2: held 1",
                                               "r2: held 2"}
    for rid in ("r1", "r2"):  # a report per recording, with its own test points only
        sub = tmp_path / "o" / "recordings" / f"r_{rid}"
        md = (sub / "survey.md").read_text()
        assert f"{rid}: held 2" in md and ("r2" if rid == "r1" else "r1") + ":" not in md
        assert (sub / "survey_loads.png").stat().st_size > 0


def test_peaks_against_the_rigs_limits():
    d = _data(1500, azimuth=True)
    tp = sv.TestPoint("p", float(d.t[0]), float(d.t[-1]), "file")
    opts = sv.SurveyOptions(draws=2, limits=(math.nan, math.nan, 100000.0) + (math.nan,) * 3)
    rows = {(r["axis"], r["quantity"]): r for r in sv.survey(d, [tp], RIG, opts)}
    r = rows[("Z", "peak_fraction_of_limit")]
    assert r["value"] == pytest.approx(-rows[("Z", "min")]["value"] / 100000.0)
    assert r["sigma"] == pytest.approx(rows[("Z", "min")]["sigma"] / 100000.0)
    assert ("X", "peak_fraction_of_limit") not in rows


def test_the_campaign_survey_product_takes_the_recordings_marks(recording, tmp_path):
    """The campaign's `survey` product of one recording: its marks as test points (a mark
    lasts until the next one or the end mark), the long table's columns less `recording`
    (the partition's); a recording without marks: the transient flag's edges."""
    import shutil

    from rsra.daq.analysis.survey_run import campaign_survey, survey_collector
    from rsra.daq.bus.replay import config_for, expand, read_frames
    from rsra.daq.runtime.service import Service, ServiceOptions

    def collected(cfg, rec):  # the records of the telemetry product's replay
        col = survey_collector(cfg)
        service = Service(cfg, ServiceOptions(replay=[str(rec)], zenoh=False))
        service.add_sink(col.add)
        service.run()
        return col

    t0 = float(next(read_frames(expand([str(recording)]))).timestamp)  # the samples' time
    rec = tmp_path / "marked"
    shutil.copytree(recording, rec)
    marks = [{"t": t0 + 1.0, "name": "hover 40 kt"}, {"t": t0 + 2.5, "name": "level 80 kt"},
             {"t": t0 + 3.5, "end": True}]
    (rec / "marks.jsonl").write_text("".join(json.dumps(m) + "\n" for m in marks))
    cfg = config_for([str(rec)], None)
    table, reason = campaign_survey(cfg, rec, {"survey_draws": 2}, collected(cfg, rec))
    rows = table.to_pylist()
    assert reason is None and table.column_names == [c for c in sv.COLUMNS if c != "recording"]
    assert {(r["test_point"], r["t_start"], r["t_end"]) for r in rows} == {
        ("hover 40 kt", t0 + 1.0, t0 + 2.5), ("level 80 kt", t0 + 2.5, t0 + 3.5)}
    assert len(rows) == 2 * 6 * len({r["quantity"] for r in rows})
    (rec / "marks.jsonl").unlink()
    table, _ = campaign_survey(cfg, rec, {"survey_draws": 2}, collected(cfg, rec))
    assert set(table.column("test_point").to_pylist()) == {"held 1"}


@pytest.mark.slow
def test_each_test_point_source_on_a_campaign_dataset(recording, tmp_path):
    """A campaign of two recordings, one with operator marks: its `survey` table has each
    recording's own test points (the marks; the transient flag's edges where there are
    none), and `rsra survey DATASET` finds the marks and the simulator's schedule through
    the manifest's recording folders, or takes a TOML's time ranges."""
    import shutil

    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    from rsra.daq.cli import main

    from rsra.daq.bus.replay import expand, read_frames

    t0 = float(next(read_frames(expand([str(recording)]))).timestamp)  # the samples' time
    recs = tmp_path / "recs"
    shutil.copytree(recording, recs / "marked")
    shutil.copytree(recording, recs / "plain")
    marks = [{"t": t0 + 1.0, "name": "hover 40 kt"}, {"t": t0 + 2.5, "name": "level 80 kt"},
             {"t": t0 + 3.5, "end": True}]
    (recs / "marked" / "marks.jsonl").write_text("".join(json.dumps(m) + "\n" for m in marks))
    ds = tmp_path / "ds"
    assert main(["campaign", "run", "--dataset", str(ds), "--pool", "--workers", "1",
                 "--survey", str(recs)]) == 0
    table = pads.dataset(ds / "survey", partitioning="hive").to_table().to_pylist()
    points = {(r["recording"].split("-")[0], r["test_point"]) for r in table}
    assert points == {("marked", "hover 40 kt"), ("marked", "level 80 kt"),
                      ("plain", "held 1")}, points
    assert {r["t_end"] for r in table if r["test_point"] == "level 80 kt"} == {t0 + 3.5}

    def survey_of(source: str) -> set[str]:
        out = tmp_path / f"o-{source.replace('/', '_')}"
        assert main(["survey", str(ds), "--out", str(out), "--draws", "2", "--test-points",
                     source]) == 0
        return {r["test_point"].split(": ", 1)[1] + "@" + r["recording"].split("-")[0]
                for r in pq.read_table(out / "survey.parquet").to_pylist()}

    assert survey_of("auto") == {"hover 40 kt@marked", "level 80 kt@marked",
                                 "condition 1@plain"}
    assert survey_of("scenario") == {"condition 1@marked", "condition 1@plain"}
    toml = tmp_path / "tp.toml"
    toml.write_text('time = "from_start"\n[[test_point]]\nname = "first"\nstart = 2.5\n'
                    'end = 4.5\n')
    assert survey_of(str(toml)) == {"first@marked", "first@plain"}


def test_the_rig_files_limits_are_the_surveys_unless_an_axis_is_given(tmp_path):
    """`[limits]` in the rig file (N, N·m; 0: none) are what `rsra survey` reports peaks
    against; `--limit AXIS=VALUE` (in the --units) replaces that axis only."""
    from rsra.config.rig import load_config
    from rsra.daq.cli.commands.survey import _limits

    rig = tmp_path / "rig.toml"
    rig.write_text('extends = "default"\n[limits]\nZ = 90000.0\nM = 20000.0\n')
    cfg = load_config(str(rig))
    assert cfg.limits.per_axis()[2] == 90000.0 and cfg.limits.per_axis()[4] == 20000.0
    assert math.isnan(cfg.limits.per_axis()[0])
    got = _limits([("M", 5000.0)], "si", cfg.limits.per_axis())
    assert got[2] == 90000.0 and got[4] == 5000.0 and math.isnan(got[0])
    lbf = _limits([("Z", 1000.0)], "us", cfg.limits.per_axis())[2]  # 1000 lbf in N
    assert lbf == pytest.approx(4448.22, rel=1e-5)
