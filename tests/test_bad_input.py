"""Every bad input: one line naming the input and the fix, no traceback, exit 2 (1 for what is
not the input's fault: a full disk, a port in use), and nothing left behind by an input refused
before acquisition starts (docs/cli.md §16; issue 13). The probe table of docs/reliability.md "Bad input
at the command line" is this file's table."""
from __future__ import annotations

import dataclasses
import errno
import json
import os
import socket
from pathlib import Path

import can
import numpy as np
import pytest
from helpers_canopen import LockstepRig
from helpers_net import free_tcp_port

from rsra.daq.cli import main
from rsra.config.rig import ConfigError, config_dir, load_config

RIG = (config_dir() / "rig.toml").read_text(encoding="utf-8")
GROUND = (config_dir() / "scenarios" / "ground-test.toml").read_text(encoding="utf-8")


def _rig(tmp: Path, old: str, new: str) -> str:
    assert old in RIG
    p = tmp / "rig.toml"
    p.write_text(RIG.replace(old, new, 1), encoding="utf-8")
    return str(p)


def _sim_run(config: str, *extra: str) -> list[str]:
    return ["run", "--config", config, "--sim", "ground-test", "--speed", "max",
            "--duration", "3", "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", *extra]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A real recording folder (lock-step simulator, 150 samples)."""
    folder = tmp_path_factory.mktemp("rec") / "rec"
    rig = LockstepRig(load_config(), record=folder)
    try:
        rig.step(150)
    finally:
        rig.close()
    return folder


def _copy_recording(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for p in src.rglob("*"):
        if p.is_file():
            (dst / p.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
            (dst / p.relative_to(src)).write_bytes(p.read_bytes())
    return dst


def _good_blf(path: Path) -> bytes:
    with can.BLFWriter(str(path)) as w:
        for i in range(2000):
            w.on_message_received(can.Message(arbitration_id=0x80, data=bytes([i % 240]),
                                              timestamp=1000.0 + 0.005 * i,
                                              is_extended_id=False))
    return path.read_bytes()


# -- the inputs ------------------------------------------------------------------------------
def junk_blf(tmp, rec):
    (tmp / "junk.blf").write_bytes(np.random.default_rng(1).bytes(3000))
    return ["replay", str(tmp / "junk.blf")]


def flipped_blf(tmp, rec):
    b = bytearray(_good_blf(tmp / "flipped.blf"))
    for i in range(200, len(b), 97):
        b[i] ^= 0xFF
    (tmp / "flipped.blf").write_bytes(bytes(b))
    return ["replay", str(tmp / "flipped.blf")]


def inf_stamp(tmp, rec):
    (tmp / "inf.log").write_text("(inf) can0 080#01\n(1000.000000) can0 080#00\n")
    return ["replay", str(tmp / "inf.log")]


def text_log(tmp, rec):
    (tmp / "notes.log").write_text("hello world\nthis is not candump\n")
    return ["replay", str(tmp / "notes.log")]


def cut_config(tmp, rec):
    folder = _copy_recording(rec, tmp / "cut")
    text = (folder / "config.json").read_text()
    (folder / "config.json").write_text(text[: len(text) // 2])
    return ["replay", str(folder)]


def schedule_without_seq(tmp, rec):
    folder = _copy_recording(rec, tmp / "noseq")
    names = load_config().rig_model().geometry.angle_names
    initial = {"initial": True, "names": list(names), "alpha": [0.0] * 14,
               "alpha_all": [0.0] * 14, "applies_from_seq": None}
    rec2 = {"names": list(names), "alpha": [0.01] * 14, "accepted": True}
    (folder / "angles.jsonl").write_text(json.dumps(initial) + "\n" + json.dumps(rec2) + "\n")
    return ["replay", str(folder)]


def harmonic_200(tmp, rec):
    return _sim_run(_rig(tmp, "harmonics = [1, 5]", "harmonics = [1, 5, 200]"))


def position_1e308(tmp, rec):  # issue 27: leaked a raw numpy overflow warning before
    return _sim_run(_rig(tmp, "position_m = [0.738, -0.945, 0.354]",
                         "position_m = [1e308, -0.945, 0.354]"))


def rate_7(tmp, rec):
    return _sim_run(_rig(tmp, "sample_rate_hz = 200.0", "sample_rate_hz = 7.0"))


def zero_gain(tmp, rec):
    return _sim_run(_rig(tmp, "[calibration]\n", '[calibration]\n"cell_A.force" = { gain = 0.0 }\n'))


def tiny_window(tmp, rec):
    return _sim_run(_rig(tmp, "window_s = 5.0", "window_s = 0.001"))


def sync_on_a_tpdo(tmp, rec):
    return _sim_run(_rig(tmp, "cob_id = 0x80", "cob_id = 0x191"))  # cell_A's TPDO1


def sync_on_a_heartbeat(tmp, rec):
    return _sim_run(_rig(tmp, "cob_id = 0x80", "cob_id = 0x721"))  # accel_1's heartbeat


def demo_bad_fault(tmp, rec):
    return ["demo", "--faults", "drop:cell_Q:0.1", "--duration", "1", "--speed", "max",
            "--report", str(tmp / "report"), "--record", str(tmp / "demo-rec")]


def nan_loads(tmp, rec):
    old = "[    0.0,     0.0, -80000.0,     0.0,     0.0,     0.0],"
    assert old in GROUND
    (tmp / "nan.toml").write_text(GROUND.replace(old, old.replace("0.0],", "nan],"), 1))
    return ["run", "--sim", str(tmp / "nan.toml"), "--speed", "max", "--duration", "1",
            "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]


def scenario_above_nyquist(tmp, rec):  # issue 27: aliased silently before
    old = 'order = "blades"'
    assert old in GROUND
    (tmp / "alias.toml").write_text(GROUND.replace(old, "order = 40", 1))
    return ["run", "--sim", str(tmp / "alias.toml"), "--speed", "max", "--duration", "1",
            "--record", str(tmp / "R"), "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]


def config_folder(tmp, rec):
    (tmp / "conf").mkdir()
    return ["noise-budget", "--config", str(tmp / "conf")]


def log_file_nowhere(tmp, rec):
    return _sim_run(str(config_dir() / "rig.toml"), "--log-file", str(tmp / "nodir" / "x.log"))


def _sim(command, *extra):
    def make(tmp, rec):
        if command == "sim":
            return ["sim", "--scenario", "ground-test", "--autostart", "--duration", "1", *extra]
        return [command, "--sim" if command == "run" else "--scenario", "ground-test",
                "--speed", "max", "--duration", "1",
                "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", *extra]
    return make


def truth_nowhere(command):
    def make(tmp, rec):
        return _sim(command, "--truth", str(tmp / "nodir" / "t.npz"))(tmp, rec)
    return make


def rate_1e9(tmp, rec):
    return _sim_run(_rig(tmp, "sample_rate_hz = 200.0", "sample_rate_hz = 1e9"))


def listen_bad(*extra):
    def make(tmp, rec):
        return ["listen", "--zenoh-connect", f"tcp/127.0.0.1:{free_tcp_port()}", *extra]
    return make


def sweep_junk(tmp, rec):
    (tmp / "junk.blf").write_bytes(b"\0" * 100)
    return ["sweep", str(tmp / "junk.blf"), "--out", str(tmp / "sweep-out")]


# (inputs, exit status, words the one line must hold)
CASES = {
    "junk.blf": (junk_blf, 2, ["junk.blf", "BLFParseError", "fix:"]),
    "blf with flipped bytes": (flipped_blf, 2, ["flipped.blf", "zlib.error", "fix:"]),
    "candump line stamped (inf)": (inf_stamp, 2, ["inf.log:1", "finite", "fix:"]),
    "text file named .log": (text_log, 2, ["notes.log:1", "'hello world'", "fix:"]),
    "config.json cut short": (cut_config, 2, ["config.json", "not valid JSON", "--config"]),
    "angles record without applies_from_seq": (
        schedule_without_seq, 2, ["angles.jsonl:2", "applies_from_seq", "--recompute"]),
    "harmonics = [1, 5, 200]": (
        harmonic_200, 2, ["filter.harmonics", "harmonic 200", "Nyquist", "sample_rate_hz"]),
    "sample_rate_hz = 7.0": (rate_7, 2, ["filter.harmonics", "harmonic 5",
                                         "Nyquist frequency 3.5 Hz"]),
    "cell position 1e308": (position_1e308, 2, ["cells[0].position_m[0] = 1e+308",
                                                "more than 100 m", "fix:"]),
    "gain = 0.0": (zero_gain, 2, ["calibration.cell_A.force.gain", "fix:"]),
    "window_s = 0.001": (tiny_window, 2, ["identification.window_s", "one sample"]),
    "sync cob_id on a TPDO": (sync_on_a_tpdo, 2, ["sync.cob_id", "TPDO1", "cell_A"]),
    "sync cob_id on a heartbeat": (sync_on_a_heartbeat, 2, ["sync.cob_id", "heartbeat",
                                                           "accel_1"]),
    "demo --faults drop:cell_Q": (demo_bad_fault, 2, ["cell_Q", "did you mean 'cell_G'"]),
    "scenario with NaN loads": (nan_loads, 2, ["loads.conditions[0][5]", "finite"]),
    "scenario harmonic above Nyquist": (scenario_above_nyquist, 2, [
        "alias.toml: harmonics[1].order = 40", "Nyquist frequency 100 Hz", "fix:"]),
    "--config naming a folder": (config_folder, 2, ["--config", "is a folder", "fix:"]),
    "--log-file in a missing folder": (log_file_nowhere, 2, ["--log-file", "fix:"]),
    "sweep of a junk file": (sweep_junk, 2, ["junk.blf", "BLFParseError"]),
    "run --seed -5": (_sim("run", "--seed", "-5"), 2, ["--seed", ">= 0"]),
    "demo --seed -5": (_sim("demo", "--seed", "-5"), 2, ["--seed", ">= 0"]),
    "sim --seed -5": (_sim("sim", "--seed", "-5"), 2, ["--seed", ">= 0"]),
    "run --duration inf": (_sim("run", "--duration", "inf"), 2, ["--duration", "finite"]),
    "demo --duration inf": (_sim("demo", "--duration", "inf"), 2, ["--duration", "finite"]),
    "sim --duration inf": (_sim("sim", "--duration", "inf"), 2, ["--duration", "finite"]),
    "run --truth in a missing folder": (truth_nowhere("run"), 2, ["--truth", "no folder",
                                                                   "fix:"]),
    "sim --truth in a missing folder": (truth_nowhere("sim"), 2, ["--truth", "no folder",
                                                                   "fix:"]),
    "sample_rate_hz = 1e9": (rate_1e9, 2, ["rig.sample_rate_hz", "at most"]),
    "listen --duration -1": (listen_bad("--duration", "-1"), 2, ["--duration", "> 0"]),
    "listen --count -1": (listen_bad("--count", "-1"), 2, ["--count", "> 0"]),
    "run --variant angles=sideways": (_sim("run", "--variant", "angles=sideways"), 2,
                                      ["angles", "sideways", "fix:"]),
    "demo --variant nosuch=1": (_sim("demo", "--variant", "nosuch=1"), 2,
                                ["variant nosuch", "unknown variant", "fix:"]),
    "sim --variant angles": (_sim("sim", "--variant", "angles"), 2,
                             ["--variant", "not KEY=VALUE"]),
    "run --foxglove nohost": (_sim("run", "--foxglove", "nohost"), 2,
                              ["--foxglove", "'nohost' is not HOST:PORT", "fix:"]),
    "demo --foxglove 127.0.0.1:99999": (_sim("demo", "--foxglove", "127.0.0.1:99999"), 2,
                                        ["--foxglove", "port 99999", "fix:"]),
    "replay --foxglove 127.0.0.1:x": (
        lambda tmp, rec: ["replay", str(rec), "--foxglove", "127.0.0.1:x"], 2,
        ["--foxglove", "'x'", "not a whole number", "fix:"]),
    "run --foxglove no.such.host.invalid:8765": (
        _sim("run", "--foxglove", "no.such.host.invalid:8765"), 2,
        ["--foxglove", "unknown host", "fix:"]),
}


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("name", list(CASES))
def test_every_bad_input_is_one_line_with_its_fix_and_leaves_nothing(name, tmp_path, recording,
                                                                      capsys, monkeypatch):
    make, status, words = CASES[name]
    monkeypatch.chdir(tmp_path)
    argv = make(tmp_path, recording)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    try:
        rc = main(argv)
    except SystemExit as e:  # a bad option: argparse's own exit (status 2, one line)
        rc = e.code
    line = _one_line(capsys.readouterr().err)
    assert rc == status, line
    for w in words:
        assert w in line, (w, line)
    assert line.startswith(f"rsra {argv[0]}: ")
    # refused before acquisition: nothing created (no recording, report, output file)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_replay_out_is_created_only_by_a_record_and_a_damaged_tail_keeps_what_came_before(
        tmp_path, recording, capsys):
    out = tmp_path / "out.jsonl"
    (tmp_path / "junk.blf").write_bytes(b"\0" * 100)
    assert main(["replay", str(tmp_path / "junk.blf"), "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err)
    assert not out.exists()  # refused before a record: no empty file
    out.write_text("kept\n")
    assert main(["replay", str(tmp_path / "junk.blf"), "--out", str(out)]) == 2
    capsys.readouterr()
    assert out.read_text() == "kept\n"  # an existing file is left as it was
    # a recording whose last part is damaged: the records before the bad line are written,
    # and the one line says so (docs/bus.md §5: what was replayed is not thrown away)
    lines = (recording / "frames.log").read_text().splitlines(keepends=True)
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines[:1000]) + "garbage line\n" + "".join(lines[1000:]))
    assert main(["replay", str(bad), "--out", str(out)]) == 2
    line = _one_line(capsys.readouterr().err)
    n = len(out.read_text().splitlines())
    assert n > 50
    assert "bad.log:1001" in line and f"holds the {n} records before it" in line


def test_replay_out_on_a_full_disk_is_one_line_exit_1(recording, capsys):
    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full")
    assert main(["replay", str(recording), "--out", "/dev/full"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "/dev/full: --out cannot be written (No space left on device)" in line


def test_a_replay_that_publishes_nothing_still_writes_its_empty_out(tmp_path, capsys):
    # frames, but no SYNC: no sample (an empty recording is refused: test_no_overwrite.py)
    (tmp_path / "hb.log").write_text("(1700000000.000000) can0 701#05\n")
    assert main(["replay", str(tmp_path / "hb.log"), "--out", str(tmp_path / "o.jsonl")]) == 0
    assert (tmp_path / "o.jsonl").read_text() == ""


def _busy_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s, s.getsockname()[1]


@pytest.mark.parametrize("command", ["replay", "run"])
def test_a_zenoh_port_in_use_is_one_line_naming_zenoh_listen(command, tmp_path, recording,
                                                             capsys):
    s, port = _busy_port()
    ep = f"tcp/127.0.0.1:{port}"
    try:
        if command == "replay":
            argv = ["replay", str(recording), "--publish", "--zenoh-listen", ep,
                    "--out", str(tmp_path / "out.jsonl")]
        else:
            argv = ["run", "--sim", "ground-test", "--speed", "max", "--duration", "1",
                    "--zenoh-listen", ep, "--record", str(tmp_path / "rec")]
        rc = main(argv)
    finally:
        s.close()
    line = _one_line(capsys.readouterr().err)
    assert rc == 1
    assert f"cannot listen on {ep}" in line and "--zenoh-listen" in line and "in use" in line
    assert ".rs:" not in line and ".cargo" not in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["run", "replay", "demo"])
def test_a_foxglove_port_in_use_is_one_line_exit_2_and_nothing_started(command, tmp_path,
                                                                       recording, capsys):
    s, port = _busy_port()
    addr = f"127.0.0.1:{port}"
    try:
        if command == "replay":
            argv = ["replay", str(recording), "--out", str(tmp_path / "out.jsonl"),
                    "--foxglove", addr]
        else:
            argv = [command, "--sim" if command == "run" else "--scenario", "ground-test",
                    "--speed", "max", "--duration", "1", "--record", str(tmp_path / "rec"),
                    "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--foxglove", addr]
            if command == "demo":
                argv += ["--report", str(tmp_path / "report")]
        rc = main(argv)
    finally:
        s.close()
    line = _one_line(capsys.readouterr().err)
    assert rc == 2, line
    assert line.startswith(f"rsra {command}: error: --foxglove {addr}: cannot listen")
    assert "in use" in line and "fix:" in line
    assert list(tmp_path.iterdir()) == []  # no recording, --out or report


def test_record_on_a_full_disk_is_one_line_exit_1_and_leaves_nothing(tmp_path, capsys):
    # a folder where every file write fails with ENOSPC: config.json is /dev/full
    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full")
    folder = tmp_path / "rec"
    folder.mkdir()
    (folder / "config.json").symlink_to("/dev/full")
    argv = ["run", "--sim", "ground-test", "--speed", "max", "--duration", "1",
            "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--record", str(folder)]
    rc = main(argv)
    line = _one_line(capsys.readouterr().err)
    assert rc == 1
    assert str(folder) in line and "No space left on device" in line and "fix:" in line
    assert [p.name for p in folder.iterdir()] == ["config.json"]  # ours removed, not theirs


def test_a_recording_that_cannot_start_removes_only_what_it_created(cfg, tmp_path, monkeypatch):
    from rsra.daq.bus import recorder as rec_mod

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rec_mod.json, "dump", full)
    target = tmp_path / "a" / "b"
    with pytest.raises(OSError) as e:
        rec_mod.Recorder(target, cfg)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []  # the folders it made are gone too
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("user's")
    with pytest.raises(OSError):
        rec_mod.Recorder(tmp_path / "mine", cfg)
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]


def test_a_sync_cob_id_on_an_eds_tpdo_is_refused_by_the_decode_table(cfg):
    # the config check covers the predefined connection set; a TPDO COB-ID an EDS moves
    # elsewhere is checked by the decode table, before any bus is opened
    from rsra.daq.bus.decoder import DecodeTable

    bad = dataclasses.replace(cfg, sync=dataclasses.replace(cfg.sync, cob_id=0x191))
    with pytest.raises(ConfigError, match=r"sync\.cob_id.*cell_A TPDO1 COB-ID 0x191.*SYNC"):
        DecodeTable(bad)


def test_a_filter_that_cannot_be_designed_is_a_config_error(tmp_path):
    # below Nyquist with its design band, but 34 Hz is too slow for tau = 0.1 s
    import math

    from rsra.daq.runtime.pipeline import EstimatorPipeline

    fs = 5 * 19.4 / (math.pi * 0.9)
    cfg = load_config(_rig(tmp_path, "sample_rate_hz = 200.0", f"sample_rate_hz = {fs!r}"))
    with pytest.raises(ConfigError, match=r"filter = .*cannot be designed.*fix:"):
        EstimatorPipeline(cfg, np.zeros(14), identification=False)


def test_an_unexpected_error_is_one_line_exit_1():
    from rsra.daq.cli import describe_error

    assert describe_error(RuntimeError("boom\nsecond line")) == (
        1, "internal error: RuntimeError: boom second line (please report it; RSRA_DEBUG=1 "
        "shows the traceback)")
    assert describe_error(OSError(errno.ENOSPC, "No space left on device", "/x"))[0] == 1
    assert describe_error(ConfigError("a.b", 1, "bad", "fix it"))[0] == 2
