"""Which addition would determine the rest (issue 25 item 5; estimator.flight_advice,
docs/identification.md "Which additions would determine the rest"): on filter-error windows
of the flight rig's calibration filter, made directly (lock-step, no simulator): inertially
balanced transmission vibration on chosen axes, carried by the cells with their noise."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, sosfilt

from rsra.config.rig import config_dir, load_config
from rsra.estimator import flight_advice as fa

FS = 200.0
SETTLE = 100
# the flight scenario's transmission vibration, per axis at the CG (content-filtered RMS of
# its inertial loads: X Y Z in N, L M N in N·m, seed 2): X and Y carry the information
LEVELS = np.array([7000.0, 3000.0, 1500.0, 140.0, 280.0, 50.0])


@pytest.fixture(scope="module")
def rig():
    from rsra.daq.runtime.ident_worker import build_identification

    cfg = load_config(config_dir() / "flight-rig.toml")
    post, runs, _ = build_identification(cfg)
    ident = runs["filter_error"]
    stiffness = np.array([c.stiffness_N_per_m for c in cfg.cells])
    return cfg, post, ident, stiffness


def _window(rig, rms, n, seed=1):
    """(problem, θ): ``n`` samples of band-limited (5–40 Hz) inertial loads of RMS ``rms`` per
    axis, the cells carrying them (minimum strain energy) with their noise; the first SETTLE
    not scored."""
    cfg, _, ident, stiffness = rig
    from rsra.estimator.identification import FilterErrorProblem

    model = cfg.rig_model()
    rng = np.random.default_rng(seed)
    sos = butter(4, [5.0, 40.0], "bandpass", fs=FS, output="sos")
    u = sosfilt(sos, rng.standard_normal((n + 400, 6)), axis=0)[400:]
    w = u / u.std(axis=0) * np.asarray(rms, float)
    theta = ident.par.initial()
    T = w @ fa.cell_split(model, ident.par.alpha(theta), stiffness).T
    T = T + rng.standard_normal(T.shape) * model.cell_sigma
    z = w + rng.standard_normal(w.shape) * 10.0
    d = ident.design
    prob = FilterErrorProblem(ident.par, d.Phi, d.K, d.J, d.Qd, z, T, discontinuity=True,
                              settle=SETTLE)
    return prob, theta


def _advice(rig, prob, theta, candidates):
    cfg, post, ident, _ = rig
    _, de, B = prob.residual_series(theta)
    return fa.advise(ident.par, theta, de, B, ident.design,
                     {"moment_floor": cfg.identification.moment_floor_Nm}, post.sigma_max,
                     prob.n_scored, FS, candidates, None)


def _candidates(rig, levels=LEVELS):
    cfg, _, _, stiffness = rig
    sigma = cfg.accelerometers[0].sigma_m_s2
    accs = [(n, p, sigma) for n, p, _ in cfg.identification.advice.accelerometers]
    return fa.candidates_from(accs, list(zip(fa.AXES, levels)), (5.0, 40.0), stiffness)


def _information(rig, prob, theta):
    _, de, B = prob.residual_series(theta)
    return fa.window_information(de, B), B


@pytest.mark.parametrize("axis", ["X", "Y"])
def test_the_advice_names_the_excitation_of_the_axis_the_window_lacks(rig, axis):
    """A window whose transmission is not shaken on ``axis`` lacks the information that axis
    gives (X: both directions the shaken window determines; Y: most of its third); of the
    excitations (each as strong as the flight's on its
    axis) and the candidate accelerometers the advice names that axis's excitation. Break
    check: the proxy's information taken from the wrong axis (``unit[(j + 1) % 6]``) names
    another axis and fails."""
    j = fa.AXES.index(axis)
    rms = LEVELS.copy()
    rms[j] = 1e-6
    prob, theta = _window(rig, rms, 1000)
    adv = _advice(rig, prob, theta, _candidates(rig))
    full, _ = _information(rig, *_window(rig, LEVELS, 1000))
    lam_full = fa.scaled_eigenvalues(full, rig[1].sigma_max)
    k = adv["determined"]
    assert adv["next"] < 0.8 * lam_full[k]  # the axis was needed (X: for 2 directions)
    assert adv["best"]["kind"] == "manoeuvre" and adv["best"]["name"] == axis, adv["best"]
    # shaking it as the flight does gives back what the shaken window determines
    assert adv["best"]["gain"] == int(np.sum(lam_full >= 1.0)) - k
    assert adv["best"]["next"] == pytest.approx(lam_full[k], rel=0.05)
    others = [m for m in adv["manoeuvres"] + adv["accelerometers"]
              if m.get("axis", m.get("name")) != axis]
    assert all(m["next"] < adv["best"]["next"] for m in others)


def test_the_excitation_proxy_predicts_the_information_an_excitation_adds(rig):
    """The linearised proxy (transfer function of the calibration filter over the band)
    against the same window with the axis really shaken: the three largest eigenvalues of
    s M s agree within 5 % (they are 6.6, 3.0, 0.55 here)."""
    cfg, post, ident, stiffness = rig
    for j in (0, 1):
        rms = LEVELS.copy()
        rms[j] = 1e-6
        prob, theta = _window(rig, rms, 1000)
        M_without, B = _information(rig, prob, theta)
        M_with, _ = _information(rig, *_window(rig, LEVELS, 1000))
        d = ident.design
        unit = fa.excitation_information(ident.par, theta, d.Phi, d.K, d.J, B, prob.n_scored,
                                         FS, (5.0, 40.0), None, stiffness)
        lam_p = fa.scaled_eigenvalues(M_without + LEVELS[j] ** 2 * unit[j], post.sigma_max)
        lam_a = fa.scaled_eigenvalues(M_with, post.sigma_max)
        assert np.allclose(lam_p[:3], lam_a[:3], rtol=0.05), (j, lam_p[:3], lam_a[:3])


def test_a_longer_window_s_information_grows_as_its_duration(rig):
    """Doubling the scored samples doubles the information (each of the four largest
    eigenvalues within 10 % of the ratio of the scored samples), and a window longer by the
    advice's ``extra_s`` determines its next direction (eigenvalue within 1 ± 0.15). Break
    check: ``extra_s`` without the − 1 (the whole window again) puts it at 1.8 and fails."""
    _, post, _, _ = rig
    s = post.sigma_max
    p1, th = _window(rig, LEVELS, 1000)
    p2, _ = _window(rig, LEVELS, 2 * 1000 - SETTLE)
    assert p2.n_scored == 2 * p1.n_scored
    lam1 = fa.scaled_eigenvalues(_information(rig, p1, th)[0], s)
    lam2 = fa.scaled_eigenvalues(_information(rig, p2, th)[0], s)
    assert np.allclose(lam2[:4] / lam1[:4], 2.0, rtol=0.10), lam2[:4] / lam1[:4]
    adv = _advice(rig, p1, th, fa.AdviceCandidates())
    k = adv["determined"]
    extra = adv["window"]["extra_s"]
    assert extra > 0 and adv["window"]["gain"] == 1
    p3, _ = _window(rig, LEVELS, 1000 + int(round(extra * FS)))
    lam3 = fa.scaled_eigenvalues(_information(rig, p3, th)[0], s)
    assert abs(lam3[k] - 1.0) < 0.15, (adv["next"], extra, lam3[k])
    assert int(np.sum(lam3 >= 1.0)) in (k, k + 1)


def test_an_accelerometer_candidate_can_only_add_information_and_a_copy_averages_noise(rig):
    """One more triax never lowers an eigenvalue (Weyl), and one at the position of an
    existing accelerometer halves that one's noise in the solve, raising the next
    eigenvalue; the record of a window that determines every direction carries none."""
    cfg, post, ident, stiffness = rig
    prob, theta = _window(rig, LEVELS, 1000)
    sigma = cfg.accelerometers[0].sigma_m_s2
    same = [("twin", cfg.accelerometers[0].position_m, sigma)]
    cands = fa.candidates_from(same + [(n, p, sigma) for n, p, _
                                       in cfg.identification.advice.accelerometers], [],
                               (5.0, 40.0), stiffness)
    adv = _advice(rig, prob, theta, cands)
    assert len(adv["accelerometers"]) == 4 and not adv["manoeuvres"]
    for a in adv["accelerometers"]:
        assert a["next"] >= adv["next"] * (1 - 1e-9) and a["gain"] >= 0
    assert adv["accelerometers"][0]["next"] > 1.02 * adv["next"]
    assert adv["best"]["kind"] == "accelerometer"
    # every direction determined: nothing to advise
    _, de, B = prob.residual_series(theta)
    assert fa.advise(ident.par, theta, de * 1e3, B, ident.design,
                     {"moment_floor": cfg.identification.moment_floor_Nm}, post.sigma_max,
                     prob.n_scored, FS, cands) is None


def test_the_advice_is_one_sentence_an_engineer_acts_on():
    """The advice as one plain sentence (issue 51): what the window determines of the whole,
    then each addition that adds a direction, in words and units (a manoeuvre as the
    excitation along a named hub axis with its RMS), the best accelerometer even when it
    adds none (never listed as the best), and how much longer the window would need."""
    adv = {"determined": 2, "next": 0.74, "n_scored": 899,
           "accelerometers": [{"name": "deck_aft_right", "determined": 2, "gain": 0,
                               "next": 0.88}],
           "manoeuvres": [{"axis": "Y", "rms": 3000.0, "determined": 3, "gain": 1,
                           "next": 1.41},
                          {"axis": "N", "rms": 800.0, "determined": 4, "gain": 2,
                           "next": 1.2}],
           "window": {"extra_s": 1.57, "gain": 1},
           "best": {"kind": "manoeuvre", "name": "N", "gain": 2, "next": 1.2}}
    line = fa.advice_summary(adv, 14)
    assert line == ("This window determines 2 of 14 directions. A yaw (N) excitation of ~800 "
                    "N·m RMS would determine 2 more directions; a lateral (Y) excitation of "
                    "~3.0 kN RMS would determine 1 more direction; an accelerometer at "
                    "deck_aft_right would add none; about 1.6 s more of such data would "
                    "determine 1 more (the strongest undetermined direction has 0.74 of the "
                    "information it needs).")
    assert fa.advice_summary(None) is None
    assert "s more" not in fa.advice_summary({**adv, "window": {"extra_s": None}})
    assert fa.advice_summary({"determined": 0, "next": 0.1, "best": None}) == (
        "This window determines 0 directions. No listed addition would determine another "
        "direction (the strongest undetermined direction has 0.10 of the information it "
        "needs).")


def test_bad_candidates_are_refused():
    with pytest.raises(ValueError, match="axis"):
        fa.candidates_from([], [("Q", 1.0)], (5.0, 40.0))
    with pytest.raises(ValueError, match="positive"):
        fa.candidates_from([], [("X", 0.0)], (5.0, 40.0))


def test_the_worker_s_flight_records_carry_the_advice_and_ground_records_none():
    """Two 5-s windows of the `flight` scenario on the flight rig through the worker's own
    ``run_job`` (as the service cuts them: content-filtered, the azimuth's turns): each
    filter-error record carries ``advice`` (strict JSON, its figures those of the window's
    own information: ``determined`` ≥ the record's robust ``window_determined``, every
    candidate listed); a known-load record carries ``advice: null``."""
    import json

    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.ident_worker import build_identification, run_job
    from rsra.estimator.balance import inertial_loads
    from rsra.estimator.content import ContentFilter
    from rsra.estimator.filters import AzimuthTracker
    from rsra.sim_bus import load_scenario, simulate

    cfg = load_config(config_dir() / "flight-rig.toml")
    run = simulate(cfg, load_scenario("flight"), seed=2, duration_s=10.0)
    model = cfg.rig_model()
    idc = cfg.identification
    z = inertial_loads(model, run.accel)
    cf = ContentFilter(idc.content_filter_error, FS, cfg.rotor.omega_nominal_rad_s,
                       tuple(cfg.filter.harmonics), 19)
    Y = cf.process(np.hstack([run.T, z, np.zeros((len(z), 6))]))
    dpsi = AzimuthTracker(cfg.rotor.omega_nominal_rad_s, 1 / FS).turns(run.azimuth, run.omega)
    post, runs, cache = build_identification(cfg)
    w = round(idc.window_s * FS)
    records = []
    for k, mode in enumerate(("filter_error", "filter_error", "known_loads")):
        sl = slice(k * w, (k + 1) * w) if k < 2 else slice(w, 2 * w)
        n = w
        job = {"job_id": k, "mode": mode, "content": idc.content_filter_error,
               "applies_from_seq": (k + 1) * w + 200, "alpha": post.theta.copy(),
               "T": Y[sl, :7], "z": Y[sl, 7:13], "known_H": np.zeros((n, 6)),
               "seq": np.arange(sl.start, sl.stop), "t": np.arange(sl.start, sl.stop) / FS,
               "ok": np.ones(n, bool), "known": np.ones(n, bool), "omega": run.omega[sl],
               "dpsi": dpsi[sl], "missing": None}
        records.append(json.loads(dumps(run_job(cfg, runs, cache, job))))
    names = [a[0] for a in idc.advice.accelerometers]
    for rec in records[:2]:
        adv = rec["advice"]
        assert isinstance(adv, dict), rec["reason"]
        assert adv["determined"] >= rec["window_determined"]
        assert [a["name"] for a in adv["accelerometers"]] == names
        assert [m["axis"] for m in adv["manoeuvres"]] == list(fa.AXES)
        assert adv["best"]["kind"] in ("accelerometer", "manoeuvre")
        assert adv["window"]["extra_s"] > 0
        assert list(rec)[-1] == "advice"  # the addition goes at the end
    assert records[2]["mode"] == "known_loads" and records[2]["advice"] is None


def test_the_service_logs_the_advice_when_what_is_determined_changes(caplog):
    """The service log carries the advice sentence once per change of what the windows
    determine, not every window (issue 51)."""
    import logging
    from types import SimpleNamespace

    from rsra.daq.runtime.sample_loop import AnglesTally

    tally = AnglesTally(SimpleNamespace(recorder=None))
    adv = {"determined": 2, "next": 0.74, "window": {"extra_s": 1.57, "gain": 1}}
    rec = {"mode": "filter_error", "content": "vibration", "accepted": True, "names": ["a"] * 14,
           "sigma_cr": [0.001] * 14, "determined": 2, "applies_from_seq": 1}
    with caplog.at_level(logging.INFO, logger="rsra"):
        for a in (adv, adv, {**adv, "determined": 3}, None):
            tally.add({**rec, "advice": a})
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("advice:")]
    assert said == [f"advice: {fa.advice_summary(adv, 14)}",
                    f"advice: {fa.advice_summary({**adv, 'determined': 3}, 14)}"]


def test_held_windows_are_not_logged_as_rejections_and_a_status_line_follows(caplog):
    """Issue 51: a known-load window whose information is held for the next runs says so
    ("held", at debug level once the posterior is calibrated) instead of "rejected … hint:
    the loads did not vary enough"; a calibrated run logs one status line every minute of
    acquisition time; a run whose data were refused is still a rejection with its hint."""
    import logging
    from types import SimpleNamespace

    from rsra.daq.runtime.sample_loop import STATUS_PERIOD_S, AnglesTally

    tally = AnglesTally(SimpleNamespace(recorder=None))
    P = (np.eye(14) * np.radians(0.1) ** 2).tolist()
    base = {"mode": "known_loads", "content": "static", "names": ["a"] * 14, "P": P,
            "determined": 14, "sigma_cr": [0.001] * 14, "applies_from_seq": 1}
    held = {**base, "accepted": False, "reason": "not_identifiable", "detail":
            "information_ratio", "information": 0.45, "hint": "the loads did not vary enough"}
    ok = {**base, "accepted": True, "reason": None, "detail": "passed"}
    bad = {**base, "accepted": False, "reason": "inconsistent", "detail": "gate",
           "hint": "a load outside the model"}
    with caplog.at_level(logging.DEBUG, logger="rsra"):
        for t, rec in enumerate([held, ok, held, held, bad, ok]):
            tally.add({**rec, "t": 1000.0 + 5 * t})
        tally.add({**held, "t": 1000.0 + 25 + STATUS_PERIOD_S})
    got = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert got[0] == (logging.INFO, "identification held (known_loads, static): this window "
                      "adds 0.45 of what the posterior knows; its information is used with "
                      "the next windows")
    assert [lv for lv, m in got if m.startswith("identification held")] == [
        logging.INFO] + [logging.DEBUG] * 3
    rejected = [m for _, m in got if m.startswith("identification rejected")]
    assert len(rejected) == 1 and "inconsistent" in rejected[0] and "hint:" in rejected[0]
    status = [m for _, m in got if m.startswith("calibration:")]
    assert status == ["calibration: 14 of 14 directions determined, largest σ 0.100°, 1 runs "
                      "accepted, 1 windows held and used, last change 0 s ago",
                      "calibration: 14 of 14 directions determined, largest σ 0.100°, 2 runs "
                      "accepted, 4 windows held and used, last change 60 s ago"]
