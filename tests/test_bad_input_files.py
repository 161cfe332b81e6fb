"""Bad files and file-naming options (docs/reliability.md "Bad input"): each is one line naming
the input and the fix, exit 2 — never a hang on a FIFO, a read until MemoryError, a traceback,
a RecursionError, a 10 MB error line or a file written under a name nobody checked.

Device inputs are nodes made in the test's folder (os.mknod; skipped, saying why, without the
right to make one), never a system device."""
from __future__ import annotations

import json
import os
import stat
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers_canopen import LockstepRig
from helpers_net import free_tcp_port

from rsra.config import readfile
from rsra.config.rig import ConfigError, default_config_path, load_config
from rsra.daq.cli import main

RIG = default_config_path().read_text()


def _one_line(capsys, command: str) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"rsra {command}:")]
    assert len(lines) == 1, err
    assert "fix:" in lines[0] or " — " in lines[0], lines[0]  # (a posterior's: " — fix")
    return lines[0]


def _zenoh() -> list[str]:
    return ["--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]


def _device(path: Path, minor: int) -> None:
    try:  # 1,3: the null device; 1,5: the zero device — made here, not /dev's
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, minor))
    except (PermissionError, OSError) as e:
        pytest.skip(f"cannot make a device node here ({e.strerror}): needs CAP_MKNOD")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("badfiles") / "rec"
    rig = LockstepRig(load_config(), record=folder)
    try:
        rig.step(120)
    finally:
        rig.close()
    return folder


# -- a recording's text files ----------------------------------------------------------------

@pytest.mark.parametrize("argv", [["replay", "{rec}", "--out", "{tmp}/o.jsonl"],
                                  ["angles", "show", "{rec}"],
                                  ["angles", "show", "{rec}/angles.jsonl"],
                                  ["export", "{rec}", "--mcap", "{tmp}/o.mcap"],
                                  ["calibrate", "{rec}"]])
def test_a_non_utf8_byte_in_angles_jsonl_is_one_line_naming_the_file_and_line(
        argv, recording, tmp_path, capsys):
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(recording, rec)
    with open(rec / "angles.jsonl", "ab") as f:
        f.write(b'{"t": 1.0, "reason": "\xff\xfe"}\n')
    lines = (rec / "angles.jsonl").read_bytes().count(b"\n")
    rc = main([a.format(rec=rec, tmp=tmp_path) for a in argv])
    line = _one_line(capsys, argv[0])
    assert rc == 2
    assert "angles.jsonl" in line and "not UTF-8" in line and f"line {lines}" in line, line
    assert not list(tmp_path.glob("o.*")), "an output was left"


# -- rig files -------------------------------------------------------------------------------

def test_an_extends_chain_of_990_files_is_one_line_naming_the_limit(tmp_path, capsys):
    (tmp_path / "r0.toml").write_text("[filter]\ntime_constant_s = 0.12\n")
    for i in range(1, 990):
        (tmp_path / f"r{i}.toml").write_text(f'extends = "r{i - 1}.toml"\n')
    with pytest.raises(ConfigError, match=f"longer than {32} files.*fix:"):
        load_config(tmp_path / "r989.toml")
    assert main(["config", "show", "--config", str(tmp_path / "r989.toml")]) == 2
    assert "merge some of the bases" in _one_line(capsys, "config")


@pytest.mark.parametrize("base", ["folder", "fifo"])
def test_a_base_that_is_a_folder_or_fifo_is_named_as_such(base, tmp_path, capsys):
    if base == "folder":
        (tmp_path / "b").mkdir()
    else:
        os.mkfifo(tmp_path / "b")
    (tmp_path / "top.toml").write_text('extends = "b"\n')
    rc = main(["config", "show", "--config", str(tmp_path / "top.toml")])
    line = _one_line(capsys, "config")
    assert rc == 2
    assert ("is a folder" if base == "folder" else "is a FIFO") in line, line
    assert "not found" not in line and "top.toml" in line, line


@pytest.mark.timeout(60)  # a FIFO opened blocking would hang: failed instead
@pytest.mark.parametrize("argv, what", [
    (["config", "show", "--config", "{fifo}"], "FIFO"),
    (["config", "show", "--config", "{zero}"], "device"),
    (["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2", "--angles",
      "{fifo}", "ZENOH"], "FIFO"),
    (["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2", "--angles",
      "{zero}", "ZENOH"], "device"),
    (["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
      "--zenoh-config", "{fifo}", "ZENOH"], "FIFO"),
    (["angles", "show", "{fifo}"], "FIFO"),
    (["sim", "--scenario", "{fifo}.toml", "--duration", "0.1"], "FIFO"),
])
def test_a_fifo_or_device_given_as_a_file_is_refused_not_waited_on(argv, what, tmp_path,
                                                                  capsys):
    fifo, zero = tmp_path / "f", tmp_path / "z"
    os.mkfifo(fifo)
    os.mkfifo(tmp_path / "f.toml")
    _device(zero, 5)
    args = []
    for a in argv:
        args += _zenoh() if a == "ZENOH" else [a.format(fifo=fifo, zero=zero)]
    rc = main(args)
    line = _one_line(capsys, argv[0])
    assert rc == 2 and what in line, line


def test_a_rig_file_over_the_size_limit_is_refused_naming_the_limit(tmp_path, capsys):
    big = tmp_path / "big.toml"
    with open(big, "wb") as f:  # sparse: no disk, no memory
        f.truncate(readfile.TEXT_LIMIT + 1)
    assert main(["config", "show", "--config", str(big)]) == 2
    line = _one_line(capsys, "config")
    assert "16 MiB limit" in line, line


def test_a_huge_array_is_not_echoed(tmp_path, capsys):
    """(The probe's 2 M elements take 10 s to parse here; 300 000 show the same.)"""
    p = tmp_path / "big.toml"
    p.write_text("[filter]\nharmonics = [" + ", ".join(["1"] * 300_000) + "]\n")
    assert main(["config", "show", "--config", str(p)]) == 2
    line = _one_line(capsys, "config")
    assert len(line) < 1000 and "300000 elements" in line, line[:300]


def test_an_empty_node_list_in_a_layer_is_blamed_on_that_layer(tmp_path, capsys):
    p = tmp_path / "nodes.toml"
    p.write_text("nodes = []\n")
    assert main(["config", "show", "--config", str(p)]) == 2
    line = _one_line(capsys, "config")
    assert "nodes.toml: nodes = []" in line and "packaged rig" not in line, line


@pytest.mark.parametrize("edit, key", [
    (("stiffness_N_per_m = 1.0e8", "stiffness_N_per_m = 1e-300"), "stiffness_N_per_m"),
    (("effective_mass_kg = [1995.8, 1976.3, 1995.8]",
      "effective_mass_kg = [1e-300, 1976.3, 1995.8]"), "mass.effective_mass_kg"),
])
def test_a_stiffness_or_mass_of_1e_300_names_the_key_to_change(edit, key, tmp_path, capsys):
    assert edit[0] in RIG
    p = tmp_path / "rig.toml"
    p.write_text(RIG.replace(*edit))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw numpy overflow warnings either
        rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
                   "--config", str(p), *_zenoh()])
    line = _one_line(capsys, "run")
    assert rc == 2 and key in line and "damping_ratio" not in line, line


# -- posteriors ------------------------------------------------------------------------------

def test_a_state_file_with_P_1e308_I_is_refused_in_one_line(tmp_path, capsys):
    from rsra.daq.runtime.persistence import posterior_to_json
    from rsra.estimator.posterior import PosteriorState

    names = load_config().rig_model().geometry.angle_names
    p = tmp_path / "post.json"
    text = posterior_to_json(PosteriorState(tuple(names), np.zeros(len(names)),
                                            np.eye(len(names)) * 1e-4))
    d = json.loads(text)
    d["P"] = (np.eye(len(names)) * 1e308).tolist()
    p.write_text(json.dumps(d))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["angles", "show", str(p)]) == 2
        line = _one_line(capsys, "angles")
        assert "exceeds" in line and "rsra angles reset" in line, line
        rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
                   "--angles", str(p), *_zenoh()])
    assert rc == 2 and "exceeds" in _one_line(capsys, "run")


# -- options ---------------------------------------------------------------------------------

@pytest.mark.parametrize("variant, words", [
    ("turbulence=7", ["--variant turbulence=7", "turbulence.enabled"]),
    ("angles.step_at_s=abc", ["--variant angles.step_at_s=", "list of numbers"]),
    ("__=1", ["--variant __", "unknown variant"]),
    ("noise.x=1", ["--variant noise.x=1", "unknown key"]),
])
def test_variant_errors_name_the_variant_not_the_scenario_file(variant, words, capsys):
    assert main(["sim", "--scenario", "ground-test", "--duration", "0.1", "--variant",
                 variant]) == 2
    line = _one_line(capsys, "sim")
    assert all(w in line for w in words) and "ground-test.toml" not in line, line


@pytest.mark.parametrize("command", ["run", "sim"])
def test_truth_without_npz_is_refused_not_written_under_another_name(command, tmp_path, capsys,
                                                                     monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = (["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2", *_zenoh()]
            if command == "run" else ["sim", "--scenario", "ground-test", "--duration", "0.1"])
    assert main([*argv, "--truth", "X"]) == 2
    line = _one_line(capsys, command)
    assert "X.npz" in line and "--truth X" in line, line
    assert not list(tmp_path.iterdir())


@pytest.mark.timeout(60)
def test_web_given_a_fifo_names_it(tmp_path, capsys):
    os.mkfifo(tmp_path / "f")
    assert main(["web", str(tmp_path / "f"), "--port", "0"]) == 2
    line = _one_line(capsys, "web")
    assert "FIFO" in line and "not found" not in line, line


# -- the reader itself -----------------------------------------------------------------------

def test_read_text_refuses_without_opening_for_long(tmp_path):
    os.mkfifo(tmp_path / "f")
    with pytest.raises(readfile.UnreadableFile, match="FIFO"):
        readfile.read_text(tmp_path / "f")
    (tmp_path / "d").mkdir()
    with pytest.raises(readfile.UnreadableFile, match="folder"):
        readfile.read_text(tmp_path / "d")
    (tmp_path / "t").write_bytes(b"a\nb\xffc\n")
    with pytest.raises(readfile.UnreadableFile, match="line 2, byte 2"):
        readfile.read_text(tmp_path / "t")
    with pytest.raises(readfile.UnreadableFile, match="line 2"):
        readfile.check_utf8(tmp_path / "t")
    (tmp_path / "s").write_bytes(b"x" * 11)
    with pytest.raises(readfile.UnreadableFile, match="10 bytes limit"):
        readfile.read_bytes(tmp_path / "s", limit=10)
    assert readfile.read_bytes(tmp_path / "s", limit=11) == b"x" * 11


@pytest.mark.timeout(60)
def test_a_zenoh_config_key_naming_a_fifo_is_refused_not_waited_on(tmp_path, capsys):
    os.mkfifo(tmp_path / "z.json5")
    rig = tmp_path / "rig.toml"
    rig.write_text(f'[telemetry]\nzenoh_config = "{tmp_path / "z.json5"}"\n')
    rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
               "--config", str(rig), *_zenoh()])
    line = _one_line(capsys, "run")
    assert rc == 2 and "telemetry.zenoh_config" in line and "FIFO" in line, line
