"""Posterior files are ours only (issue 13, "Never touch what is not ours"): the configured
``identification.state_file`` is replaced only when it is a posterior of ours, our own
temporary files are removed on start (and nothing else), and a saved posterior carries the
rig fingerprint and is refused on another rig or outside the angles' physical range."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers_net import free_tcp_port

from rsra.daq.cli import main
from rsra.config.rig import ConfigError, load_config
from rsra.daq.runtime.persistence import load_posterior, own_temp_pid, save_posterior, temp_prefix
from rsra.daq.runtime.posterior_file import classify, load_checked, prepare_state_file
from rsra.daq.runtime.service import Service, ServiceOptions
from rsra.estimator.identification import IdentificationResult
from rsra.estimator.posterior import (
    PosteriorFileError,
    PosteriorState,
    SequentialPosterior,
    rig_fingerprint,
)

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "config" / "rig.toml"
DEG = math.pi / 180
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def _config_file(tmp_path: Path, state_file: str = "", replace: dict | None = None,
                 name: str = "rig.toml") -> Path:
    text = RIG.read_text(encoding="utf-8")
    pairs = {'state_file = ""': f"state_file = {json.dumps(str(state_file))}",
             **(replace or {})}
    for old, new in pairs.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _snapshot(root: Path) -> dict:
    """Every path under root with its type, size, content and mtime: 'untouched' means equal."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        body = p.read_bytes() if p.is_file() and not p.is_symlink() else None
        out[str(p.relative_to(root))] = (st.st_mode, st.st_size, st.st_mtime_ns, body)
    return out


def _state(cfg, theta=None, rig=True) -> PosteriorState:
    names = cfg.rig_model().geometry.angle_names
    theta = np.zeros(14) if theta is None else np.asarray(theta, float)
    return PosteriorState(names, theta, np.eye(14) * (1 * DEG) ** 2, 100, 0.5,
                          rig_fingerprint(cfg.rig_model().geometry) if rig else None)


def _listen() -> list[str]:
    """A free loopback port for the service's Zenoh session (never the default 7447)."""
    return ["--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------------------
# identification.state_file: only a posterior of ours is ever replaced


def test_a_state_file_naming_a_folder_is_a_config_error_and_the_folder_is_untouched(tmp_path):
    """The issue's reproduction (there, the system's temporary folder was renamed to
    `*.corrupt`): `rsra run` exits 2 with one line naming the key, before acquisition, and
    the folder, its contents and its siblings are exactly as they were."""
    work = tmp_path / "work"
    folder = work / "shared-tmp"
    (folder / "sub").mkdir(parents=True)
    (folder / "someone-elses.txt").write_text("keep me")
    (folder / "sub" / "x.bin").write_bytes(b"\x00\x01")
    conf = _config_file(tmp_path, str(folder))
    before = _snapshot(work)
    r = subprocess.run([sys.executable, "-m", "rsra", "run", "--config", str(conf), "--sim",
                        "ground-test", "--speed", "max", "--duration", "1", *_listen()],
                       capture_output=True, text=True, timeout=120, check=False, env=ENV,
                       cwd=tmp_path)
    assert r.returncode == 2, (r.returncode, r.stderr)
    line = _one_line(r.stderr)
    assert "identification.state_file" in line and str(folder) in line and "folder" in line
    assert r.stdout == ""  # no summary: the service never started
    assert _snapshot(work) == before


def _fifo(p: Path) -> None:
    os.mkfifo(p)


@pytest.mark.parametrize("make,problem", [
    (lambda p: p.mkdir(), "is a folder"),
    (_fifo, "not a regular file"),
    (lambda p: p.write_text(RIG.read_text()), "not a posterior file"),
    (lambda p: p.write_bytes(b"\x00\x00 half-written by a dying disk"), "not a posterior file"),
    (lambda p: p.write_text(""), "damaged posterior"),
    (lambda p: p.write_text('{"format": "rsra-posterior", "version": 2, "rig": {"ce'),
     "damaged posterior"),
], ids=["folder", "fifo", "toml", "binary", "empty", "truncated"])
def test_a_state_file_that_is_not_our_posterior_is_refused_before_acquisition(
        tmp_path, make, problem):
    state = tmp_path / "posterior.json"
    make(state)
    before = _snapshot(tmp_path)
    cfg = load_config(overrides={"identification": {"state_file": str(state)}})
    svc = Service(cfg, ServiceOptions(sim="ground-test", seed=1, speed=None, duration=1.0,
                                      zenoh=False))
    with pytest.raises(ConfigError) as e:
        svc.run()
    assert e.value.key == "identification.state_file" and problem in str(e.value)
    assert svc.samples == 0 and svc.sim is None and svc.worker is None
    assert _snapshot(tmp_path) == before  # nothing renamed, created or deleted


def test_a_state_file_of_another_rig_is_refused_unless_accepted(cfg, tmp_path):
    state = tmp_path / "posterior.json"
    other = _state(cfg)
    other.rig["hub_position_m"] = [0.0, 0.0, -0.5]
    save_posterior(state, other)
    cfg2 = load_config(overrides={"identification": {"state_file": str(state)}})
    with pytest.raises(ConfigError, match=r"hub_position_m: \[0.0, 0.0, -0.5\] in the file"):
        prepare_state_file(cfg2)
    (warning,) = prepare_state_file(cfg2, accept_rig_mismatch=True)
    assert "another rig" in warning and "--accept-rig-mismatch" in warning
    # a posterior of ours of this rig, or no file at all: fine, nothing said
    save_posterior(state, _state(cfg))
    assert prepare_state_file(cfg2) == []
    state.unlink()
    assert prepare_state_file(cfg2) == [] and not state.exists()


def test_classify_is_the_rule_angles_reset_applies(cfg, tmp_path, capsys):
    folder = tmp_path / "d"
    folder.mkdir()
    assert classify(folder)[0] == "foreign"
    assert main(["angles", "reset", str(folder)]) == 2
    assert "folder" in _one_line(capsys.readouterr().err) and folder.is_dir()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert main(["angles", "reset", str(fifo)]) == 2  # would block reading it before
    assert "refusing to overwrite" in _one_line(capsys.readouterr().err)
    assert classify(tmp_path / "absent.json")[0] == "absent"


# ------------------------------------------------------------------------------------------
# temporary files of an interrupted save

KILLED_WRITER = """
import sys, time
import rsra.daq.runtime.persistence as a
def stall(fd):
    print("writing", flush=True)
    time.sleep(60)
a.os.fsync = stall
a.write_text_atomic(sys.argv[1], "half")
"""


def test_a_killed_save_leaves_a_temp_file_that_the_next_start_removes_and_nothing_else(
        cfg, tmp_path):
    state = tmp_path / "posterior.json"
    save_posterior(state, _state(cfg))
    # a writer killed with SIGKILL in the middle of a save (the real code path)
    p = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(state)], cwd=ROOT, env=ENV,
                         stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "writing"
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        p.stdout.close()
    (left,) = [q for q in tmp_path.iterdir() if q.name.endswith(".tmp")]
    assert own_temp_pid(left.name, state.name) == p.pid
    # what must stay: a user's files, another target's temp, a live writer's temp, a folder
    # named like ours, and the old (pre-pid) temp names, which are ambiguous
    keep = [tmp_path / "foo.tmp", tmp_path / ".posterior.json.tmp",
            tmp_path / ".posterior.json.abcd1234.tmp",
            tmp_path / f".other.json.rsra-tmp.{p.pid}.abcd1234.tmp",
            tmp_path / f"{temp_prefix(state)}abcd1234.tmp",  # this (live) process
            tmp_path / f".posterior.json.rsra-tmp.{p.pid}.abcd1234.tmp.bak"]
    for k in keep:
        k.write_text("user data")
    folder_like = tmp_path / f".posterior.json.rsra-tmp.{p.pid}.zzzz9999.tmp"
    folder_like.mkdir()
    cfg2 = load_config(overrides={"identification": {"state_file": str(state)}})
    assert prepare_state_file(cfg2) == []
    assert not left.exists()
    assert all(k.read_text() == "user data" for k in keep) and folder_like.is_dir()
    np.testing.assert_array_equal(load_posterior(state).theta, np.zeros(14))


# ------------------------------------------------------------------------------------------
# format version 2: the rig fingerprint


def test_the_worker_saves_version_2_with_the_rig_fingerprint(cfg, tmp_path):
    from rsra.daq.runtime.ident_worker import build_identification

    post, _, _ = build_identification(cfg)
    path = tmp_path / "p.json"
    save_posterior(path, post.state())
    raw = json.loads(path.read_text())
    assert raw["format"] == "rsra-posterior" and raw["version"] == 2
    g = cfg.rig_model().geometry
    assert [c["name"] for c in raw["rig"]["cells"]] == list(g.cell_names)
    np.testing.assert_array_equal([c["position_m"] for c in raw["rig"]["cells"]],
                                  g.cell_positions)
    np.testing.assert_array_equal([c["nominal_axis"] for c in raw["rig"]["cells"]],
                                  g.cell_axes)
    np.testing.assert_array_equal(raw["rig"]["hub_position_m"], g.hub_position)
    assert raw["rig"]["angle_names"] == list(g.angle_names)
    st, warning = load_checked(cfg, path)
    assert warning is None and st.rig == raw["rig"]


@pytest.mark.parametrize("old,new,item", [
    ("position_m = [-0.738, 0.945, 0.354]", "position_m = [-0.7, 0.945, 0.354]",
     "cells[2].position_m (cell C)"),
    ('name = "E"', 'name = "E2"', "cells[4].name"),
    ("hub_centre_m = [0.051, 0.0, -0.408]", "hub_centre_m = [0.051, 0.0, -0.5]",
     "hub_position_m"),
], ids=["position", "name", "hub"])
def test_a_posterior_of_another_rig_is_refused_naming_the_item(cfg, tmp_path, old, new, item):
    path = tmp_path / "p.json"
    save_posterior(path, _state(cfg))
    other = load_config(_config_file(tmp_path, replace={old: new}))
    with pytest.raises(PosteriorFileError) as e:
        load_checked(other, path)
    assert item in str(e.value) and "--accept-rig-mismatch" in str(e.value)
    assert str(e.value).count("\n") == 0
    st, warning = load_checked(other, path, accept_rig_mismatch=True)
    assert item in warning and "used anyway" in warning


def test_a_nominal_axis_change_is_a_different_rig(cfg, tmp_path):
    path = tmp_path / "p.json"
    st = _state(cfg)
    st.rig["cells"][6]["nominal_axis"] = [1.0, 0.01, 0.0]
    save_posterior(path, st)
    with pytest.raises(PosteriorFileError, match=r"cells\[6\]\.nominal_axis \(cell G\)"):
        load_checked(cfg, path)


def test_a_version_1_file_is_used_with_a_one_line_warning(cfg, tmp_path, capsys):
    path = tmp_path / "v1.json"
    save_posterior(path, _state(cfg, rig=False))
    assert json.loads(path.read_text())["version"] == 1
    st, warning = load_checked(cfg, path)
    assert "version 1" in warning and "\n" not in warning
    np.testing.assert_array_equal(st.theta, np.zeros(14))


def test_rsra_run_refuses_another_rigs_posterior_and_accepts_it_when_told(cfg, tmp_path,
                                                                        capsys):
    path = tmp_path / "p.json"
    st = _state(cfg)
    st.rig["cells"][0]["position_m"] = [0.7, -0.945, 0.354]
    save_posterior(path, st)
    argv = ["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
            "--angles", str(path), "--log-level", "warning", *_listen()]
    assert main(argv) == 2
    line = _one_line(capsys.readouterr().err)
    assert "cells[0].position_m (cell A)" in line and str(path) in line
    assert main(argv + ["--accept-rig-mismatch"]) == 0
    err = capsys.readouterr().err
    assert "used anyway" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------
# the physical range of the angles


@pytest.mark.parametrize("value,text", [(100.0, "outside the physical range"),
                                        (1e300, "outside the physical range"),
                                        (-11 * DEG, "outside the physical range"),
                                        (float("nan"), "non-finite")])
def test_a_loaded_posterior_outside_the_physical_range_is_refused(cfg, tmp_path, value, text):
    path = tmp_path / "p.json"
    d = _state(cfg).to_dict()
    d["theta"][3] = value
    path.write_text(json.dumps(d))  # NaN as the token NaN (json allows it on reading)
    with pytest.raises(PosteriorFileError) as e:
        load_checked(cfg, path, accept_rig_mismatch=True)
    assert text in str(e.value) and "\n" not in str(e.value)
    if "range" in text:
        assert cfg.rig_model().geometry.angle_names[3] in str(e.value)
    # just inside: used
    d["theta"][3] = 9.99 * DEG
    path.write_text(json.dumps(d))
    assert load_checked(cfg, path)[0].theta[3] == pytest.approx(9.99 * DEG)


def test_rsra_run_refuses_theta_100_rad_in_one_line(cfg, tmp_path, capsys):
    path = tmp_path / "p.json"
    save_posterior(path, _state(cfg, theta=np.r_[100.0, np.zeros(13)]))
    assert main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
                 "--angles", str(path), *_listen()]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "delta_A = 100 rad" in line and "angle_limit_deg" in line


def test_angle_limit_is_configurable_and_checks_the_initial_angles(tmp_path):
    cfg = load_config()
    assert cfg.identification.angle_limit_rad == pytest.approx(10 * DEG)
    wide = load_config(overrides={"identification": {"angle_limit_deg": 20.0,
                                                     "initial_angles_deg": 15.0}})
    assert wide.identification.angle_limit_rad == pytest.approx(20 * DEG)
    with pytest.raises(ConfigError, match="initial_angles_deg.*physical range"):
        load_config(overrides={"identification": {"initial_angles_deg": 15.0}})
    with pytest.raises(ConfigError, match="angle_limit_deg"):
        load_config(overrides={"identification": {"angle_limit_deg": -1.0}})


def _result(post, theta, M):
    th_p, P_p = post.prior(5.0)
    P = np.linalg.inv(M + np.linalg.inv(P_p))
    return IdentificationResult(post.names, "known_loads", np.asarray(theta, float), P, None,
                                M, th_p, P_p, 1.0, 2.0, 3, "converged", 100)


def test_an_identification_result_outside_the_range_is_rejected_out_of_range(cfg):
    names = cfg.rig_model().geometry.angle_names
    theta0 = np.full(14, 9.5 * DEG)
    M = np.eye(14) * 1e8
    kw = dict(window=(0, 999), mode="known_loads", content="static")
    for inside, reason in ((9.9, None), (10.1, "out_of_range"), (-10.1, "out_of_range")):
        post = SequentialPosterior.from_config(cfg.identification, names, names, theta0=theta0)
        theta, P = post.theta.copy(), post.P.copy()
        run = theta0.copy()
        run[5] = inside * DEG  # 0.4-0.6° from a 5° prior: consistent, informative
        rec = post.update(_result(post, run, M), **kw)
        assert rec.reason == reason, (inside, rec.reason)
        assert rec.accepted == (reason is None)
        if reason is not None:  # nothing changes
            np.testing.assert_array_equal(post.theta, theta)
            np.testing.assert_array_equal(post.P, P)
            assert rec.to_dict()["reason"] == "out_of_range"


def test_angles_show_names_the_rig_difference_and_the_version(cfg, tmp_path, capsys):
    path = tmp_path / "p.json"
    st = _state(cfg)
    save_posterior(path, st)
    assert main(["angles", "show", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["version"] == 2 and d["rig_difference"] is None
    st.rig["angle_names"][0] = "delta_Z"
    save_posterior(path, st)
    assert main(["angles", "show", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["rig_difference"].startswith("angle_names")
    assert main(["angles", "show", str(path)]) == 0
    assert "note: saved on another rig (angle_names" in capsys.readouterr().out


def test_a_replay_never_writes_state_file_not_even_when_it_recomputes(tmp_path, capsys):
    """identification.state_file is the live service's output: a replay (recomputed, or
    recomputed because the recording holds no schedule) saves no posterior over it."""
    rec = tmp_path / "rec"
    # 40 s: the first run accepted comes after the cold start's curvature check (~20 s)
    assert main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "40",
                 "--record", str(rec), "--log-level", "error", *_listen()]) == 0
    (rec / "angles.jsonl").unlink()  # a recording without a schedule: recomputed
    capsys.readouterr()
    cfg = load_config()
    post = tmp_path / "ground-posterior.json"
    save_posterior(post, _state(cfg, theta=np.full(14, 0.5 * DEG)))
    folder = tmp_path / "d"
    folder.mkdir()
    for state_file in (post, folder):
        conf = _config_file(tmp_path, str(state_file))
        before = _snapshot(tmp_path)
        out = tmp_path / f"out-{state_file.name}.jsonl"
        assert main(["replay", str(rec), "--recompute", "--config", str(conf),
                     "--out", str(out), "--log-level", "error"]) == 0
        capsys.readouterr()
        accepted = [r for r in map(json.loads, out.read_text().splitlines())
                    if r["key"] == "angles" and r.get("accepted")]
        assert accepted  # there was something to save
        out.unlink()
        assert _snapshot(tmp_path) == before


def test_a_state_file_in_a_missing_folder_is_a_config_error_and_no_folder_is_made(tmp_path,
                                                                                  capsys):
    conf = _config_file(tmp_path, str(tmp_path / "nodir" / "sub" / "post.json"))
    before = _snapshot(tmp_path)
    assert main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.3",
                 "--config", str(conf), "--log-level", "error", *_listen()]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "identification.state_file" in line and "does not exist" in line
    assert _snapshot(tmp_path) == before and not (tmp_path / "nodir").exists()


def test_a_save_keeps_the_mode_of_the_file_it_replaces(cfg, tmp_path):
    p = tmp_path / "posterior.json"
    save_posterior(p, _state(cfg))
    os.chmod(p, 0o640)
    save_posterior(p, _state(cfg, theta=np.full(14, 1 * DEG)))
    assert (os.stat(p).st_mode & 0o777) == 0o640
    new = tmp_path / "new.json"
    umask = os.umask(0o022)
    try:
        save_posterior(new, _state(cfg))
    finally:
        os.umask(umask)
    assert (os.stat(new).st_mode & 0o777) == 0o644


def test_a_save_through_a_symbolic_link_replaces_the_target_and_keeps_the_link(cfg, tmp_path):
    target = tmp_path / "real" / "posterior.json"
    target.parent.mkdir()
    save_posterior(target, _state(cfg))
    link = tmp_path / "state.json"
    link.symlink_to(target)
    save_posterior(link, _state(cfg, theta=np.full(14, 1 * DEG)))
    assert link.is_symlink() and os.readlink(link) == str(target)
    np.testing.assert_allclose(load_posterior(target).theta, 1 * DEG)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["posterior.json", "real",
                                                             "state.json"]


def _fit(cfg):
    n = cfg.rig_model().geometry.n_cells
    return {"structure": "cell_load_angles",
            "parameters": [f"g_{a}" for a in cfg.rig_model().geometry.angle_names],
            "alpha0": [0.01] * 2 * n, "beta": [1e-8] * 2 * n, "alpha0_sigma": [1e-4] * 2 * n,
            "beta_sigma": [None] * 2 * n, "T_ref": [1e4] * n}


def test_an_old_posterior_without_a_structure_section_still_loads(cfg, tmp_path):
    """The posterior format grows an optional ``structure`` section (issue 19: the selected
    structure the hub loads use); a file written before it — no such key — loads as before,
    with no structure, and a file with it round-trips. Break-checked: requiring the key in
    posterior_from_json fails the first half."""
    from rsra.daq.runtime.ident_worker import build_identification

    post, _, _ = build_identification(cfg)
    path = tmp_path / "old.json"
    save_posterior(path, post.state())
    raw = json.loads(path.read_text())
    assert "structure" not in raw  # what every file before issue 19 looks like
    st, warning = load_checked(cfg, path)
    assert warning is None and st.structure is None
    post.structure_fit = _fit(cfg)
    save_posterior(path, post.state())
    st, _ = load_checked(cfg, path)
    assert st.structure == _fit(cfg)
    post2, _, _ = build_identification(cfg, st)
    assert post2.structure_fit == _fit(cfg)
    raw = json.loads(path.read_text())
    raw["structure"] = [1, 2]
    path.write_text(json.dumps(raw))
    with pytest.raises(PosteriorFileError, match="structure"):
        load_posterior(path)


def test_run_state_file_option_then_angles_show_reads_it_and_the_recording(tmp_path, capsys):
    """`rsra run --state-file PATH` (the option beside identification.state_file) saves the
    posterior; `rsra angles show` reads it, and reads the recording's angles.jsonl (its last
    applied record) and the recording folder alike (issue 28)."""
    state, rec = tmp_path / "p.json", tmp_path / "R"
    assert main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "40",
                 "--record", str(rec), "--state-file", str(state), *_listen()]) == 0
    capsys.readouterr()
    assert load_posterior(state).applies_from_seq is not None  # an accepted run was saved
    assert main(["angles", "show", str(state), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["applies_from_seq"] is not None
    lines = [json.loads(x) for x in (rec / "angles.jsonl").read_text().splitlines()]
    last = [r for r in lines if r.get("accepted")][-1]
    for arg in (rec / "angles.jsonl", rec):
        assert main(["angles", "show", str(arg), "--json"]) == 0
        d = json.loads(capsys.readouterr().out)
        assert d["source"]["record"] == "last_applied"
        np.testing.assert_allclose(d["angles_deg"], np.degrees(last["alpha"]), rtol=1e-12)
        assert d["applies_from_seq"] == last["applies_from_seq"]
    assert main(["angles", "show", str(rec / "angles.jsonl")]) == 0
    assert "last applied angles record" in capsys.readouterr().out


def test_angles_show_recording_last_applied_and_the_records_after_it(cfg, tmp_path, capsys):
    names = list(cfg.rig_model().geometry.angle_names)
    P = (np.eye(14) * DEG**2).tolist()
    lines = [{"initial": True, "names": names, "alpha": [0.0] * 14, "P": P,
              "alpha_all": [0.0] * 14, "applies_from_seq": None},
             {"accepted": True, "reason": None, "names": names, "alpha": [0.01] * 14, "P": P,
              "applies_from_seq": 1199, "t": 6.0},
             {"accepted": False, "reason": "reset", "names": names, "alpha": [0.01] * 14,
              "P": (np.eye(14) * 4 * DEG**2).tolist(), "applies_from_seq": 1199, "t": 11.0}]
    f = tmp_path / "angles.jsonl"
    f.write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert main(["angles", "show", str(f), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["source"] == {"record": "last_applied", "index": 1, "records": 2, "after": 1,
                           "reset_after": True, "advice": None}
    np.testing.assert_allclose(d["angles_deg"], np.degrees(0.01))
    np.testing.assert_allclose(d["sigma_deg"], 1.0)
    f.write_text(json.dumps(lines[0]) + "\n" + json.dumps(lines[2]) + "\n")
    assert main(["angles", "show", str(f), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["source"]["record"] == "initial" and d["applies_from_seq"] is None
    f.write_text("")
    assert main(["angles", "show", str(f)]) == 2
    assert "holds no angles record" in capsys.readouterr().err


def test_angles_show_prints_each_angles_95_percent_range_and_the_physical_limit(cfg, tmp_path,
                                                                                capsys):
    """issue 27 item 3: a range per angle (± 1.96 σ) beside σ, and one line saying what it is."""
    path = tmp_path / "p.json"
    st = _state(cfg)
    save_posterior(path, st)
    assert main(["angles", "show", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    a, s = np.array(d["angles_deg"]), np.array(d["sigma_deg"])
    lo, hi = np.array(d["range_deg"]).T
    assert np.allclose(lo, a - 1.959964 * s) and np.allclose(hi, a + 1.959964 * s)
    assert d["angle_limit_deg"] == pytest.approx(10.0)
    assert main(["angles", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "95 % range (deg)" in out and f"{lo[0]:+.3f} … {hi[0]:+.3f}" in out
    assert "range: angle ± 1.96 σ" in out and "within ±10°" in out
