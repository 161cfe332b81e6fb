"""The one output rule (docs/cli.md §16, docs/reliability.md "Outputs"), over every command ×
every output option × {a device node, a FIFO nobody reads, a base the rig file ``extends``, an
input file, a symbolic link to an input}: a device is written in place (a file output) or
refused (a folder output), never replaced by a regular file; a FIFO nobody reads is refused
at once, never waited on, never replaced; an extends base, an input and a link to an input
are refused before anything is read, every input byte for byte as it was.

The device is a node made in the test's own folder (os.mknod of the null device: skipped,
saying why, without the right to make one), never a system device: a break-check run as root
cannot replace /dev/null."""
from __future__ import annotations

import hashlib
import logging
import os
import stat
from pathlib import Path

import pytest
from helpers_canopen import LockstepRig
from helpers_net import free_tcp_port

from rsra.config.rig import load_config
from rsra.daq.cli import main
from rsra.daq.runtime.persistence import OutputFile, OutputRefused


@pytest.fixture(scope="module")
def top(tmp_path_factory):
    """A recording (lock-step simulator, 150 samples), its frames as a loose file, a results
    file, and a rig file ``top.toml`` that extends ``base.toml``."""
    top = tmp_path_factory.mktemp("rule")
    rig = LockstepRig(load_config(), record=top / "rec")
    try:
        rig.step(150)
    finally:
        rig.close()
    (top / "in.log").write_bytes((top / "rec" / "frames.log").read_bytes())
    (top / "base.toml").write_text("[filter]\ntime_constant_s = 0.12\n")
    (top / "top.toml").write_text('extends = "base.toml"\n')
    cwd = os.getcwd()
    os.chdir(top)
    try:
        assert main(["replay", "rec", "--out", "results.jsonl"]) == 0
    finally:
        os.chdir(cwd)
    return top


@pytest.fixture(autouse=True)
def _root_logging():
    """`--log-file` installs a handler on the root logger: removed after each case."""
    before = list(logging.getLogger().handlers)
    yield
    root = logging.getLogger()
    for h in list(root.handlers):
        if h not in before:
            root.removeHandler(h)
            h.close()


def _digest(top: Path) -> dict[str, str]:
    return {str(p.relative_to(top)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(top.rglob("*")) if p.is_file() and not p.is_symlink()}


def _zenoh() -> list[str]:
    return ["--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]


# command: (argv before the output option, the input a link points to, the output options:
# option -> "file" or "folder", and the suffix a file output's name needs)
COMMANDS = {
    "replay": (lambda: ["replay", "in.log", "--config", "top.toml"], "in.log",
               {"--out": ("file", ".jsonl")}),
    "calibrate": (lambda: ["calibrate", "in.log", "--config", "top.toml"], "in.log",
                  {"--out": ("file", ".toml")}),
    "export": (lambda: ["export", "in.log", "--config", "top.toml"], "in.log",
               {"--dbc": ("file", ".dbc"), "--mcap": ("file", ".mcap"),
                "--parquet": ("folder", "")}),
    "sweep": (lambda: ["sweep", "in.log", "--config", "top.toml"], "in.log",
              {"--out": ("folder", "")}),
    "report": (lambda: ["report", "results.jsonl", "--config", "top.toml"], "results.jsonl",
               {"--out": ("folder", "")}),
    "zero": (lambda: ["zero", "--interface", "virtual", "--channel", "rule-zero", "--seconds",
                      "0.1", "--config", "top.toml"], "top.toml", {"--out": ("file", ".toml")}),
    "run": (lambda: ["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
                     "--no-identification", "--config", "top.toml", *_zenoh()], "top.toml",
            {"--truth": ("file", ".npz"), "--record": ("folder", ""),
             "--log-file": ("file", ".log")}),
    "sim": (lambda: ["sim", "--scenario", "ground-test", "--duration", "0.1", "--channel",
                     "rule-sim", "--config", "top.toml"], "top.toml",
            {"--truth": ("file", ".npz"), "--record": ("file", ".log")}),
    "demo": (lambda: ["demo", "--speed", "max", "--duration", "0.2", "--config", "top.toml",
                      *_zenoh()], "top.toml",
             {"--report": ("folder", ""), "--record": ("folder", "")}),
}
KINDS = ("device", "fifo", "extends base", "input file", "symlink to input")
MATRIX = [(c, o, k) for c, (_, _, outs) in COMMANDS.items() for o in outs for k in KINDS]


def make_device(path: Path) -> None:
    """A character device node of the null device in the test's folder (not /dev/null)."""
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except (PermissionError, OSError) as e:
        pytest.skip(f"cannot make a device node here ({e.strerror}): needs CAP_MKNOD")


def _kind(path: Path) -> str:
    mode = os.lstat(path).st_mode
    return ("device" if stat.S_ISCHR(mode) else "fifo" if stat.S_ISFIFO(mode)
            else "link" if stat.S_ISLNK(mode) else "file" if stat.S_ISREG(mode) else "other")


@pytest.mark.timeout(60)  # a FIFO waited on would hang the case: failed instead
@pytest.mark.parametrize("command, option, kind", MATRIX,
                         ids=[f"{c} {o} {k}" for c, o, k in MATRIX])
def test_the_output_rule(command, option, kind, top, tmp_path, monkeypatch, capsys):
    argv, input_file, outputs = COMMANDS[command]
    shape, suffix = outputs[option]
    monkeypatch.chdir(top)
    before = _digest(top)
    if kind == "device":
        target = tmp_path / f"null{suffix}"
        make_device(target)
    elif kind == "fifo":
        target = tmp_path / f"fifo{suffix}"
        os.mkfifo(target)
    elif kind == "extends base":
        target = top / "base.toml"
    elif kind == "input file":
        target = top / input_file
    else:
        target = tmp_path / f"link{suffix}"
        target.symlink_to(top / input_file)
    was = _kind(target)
    rc = main([*argv(), option, str(target)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert _kind(target) == was, f"{target} was a {was}, is now a {_kind(target)}"
    assert _digest(top) == before, "an input changed"
    if kind == "device" and shape == "file":
        return  # written in place (the command's own outcome is its business)
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"rsra {command}:")]
    assert len(lines) == 1 and "fix:" in lines[0], err
    words = {"device": "not a folder", "fifo": "FIFO",
             "extends base": "input" if shape == "file" else "not a folder",
             "input file": "input" if shape == "file" else "not a folder",
             "symlink to input": "input" if shape == "file" else "not a folder"}[kind]
    assert words in lines[0], lines[0]
    assert option in lines[0] or str(target) in lines[0], lines[0]


def test_a_device_output_is_written_in_place(tmp_path):
    node = tmp_path / "null"
    make_device(node)
    with OutputFile(node) as f:
        f.write("x" * 100)
    assert _kind(node) == "device"
    assert not [p for p in tmp_path.iterdir() if p != node], "a temporary file was left"


def test_a_fifo_with_a_reader_is_written_in_place_and_the_reader_gets_everything(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    r = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader, as `cat fifo` would be
    try:
        out = OutputFile(fifo)
        out.check()  # keeps the write end: closing it would give the reader an end of file
        with out as f:
            f.write("hello\n")
        assert os.read(r, 100) == b"hello\n"
    finally:
        os.close(r)
    assert _kind(fifo) == "fifo"


def test_a_fifo_nobody_reads_is_refused_without_waiting(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OutputRefused, match="FIFO .* nobody reads.*fix:"):
        OutputFile(fifo).open()
    assert _kind(fifo) == "fifo"


def test_a_folder_is_refused_by_the_writer(tmp_path):
    with pytest.raises(OutputRefused, match="is a folder; fix:"):
        OutputFile(tmp_path).open()


def test_a_posterior_that_is_both_angles_and_state_file_stays_allowed(top, tmp_path,
                                                                       monkeypatch, capsys):
    """The documented way to continue a calibration: `--angles P --state-file P`. It is read
    in full before the first save replaces it."""
    from rsra.daq.runtime.persistence import save_posterior
    from rsra.estimator.posterior import PosteriorState
    import numpy as np

    names = load_config().rig_model().geometry.angle_names
    state = PosteriorState(tuple(names), np.zeros(len(names)), np.eye(len(names)) * 1e-4,
                           None, None)
    post = tmp_path / "post.json"
    save_posterior(post, state)
    monkeypatch.chdir(top)
    rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "0.2",
               "--angles", str(post), "--state-file", str(post), *_zenoh()])
    assert rc == 0, capsys.readouterr().err


@pytest.mark.parametrize("which", ["rig", "eds"])
def test_the_packaged_rig_and_its_eds_files_are_inputs_too(which):
    """Checked through the rule's own API, not by running a command: with the check broken,
    a command would overwrite the package's own files."""
    import argparse

    from rsra.config.rig import config_dir, default_config_path
    from rsra.daq.cli.options import UsageError
    from rsra.daq.cli.outputs import Inputs

    target = default_config_path() if which == "rig" else \
        config_dir() / load_config().nodes[0].eds
    inputs = Inputs().add_args(argparse.Namespace(config=None))
    with pytest.raises(UsageError, match="the input .*fix:"):
        inputs.check("--dbc", target)


def test_dev_stdout_piped_to_another_program_is_written_in_place(tmp_path):
    """`rsra export --dbc /dev/stdout | …`: /dev/stdout is a link to a pipe that realpath
    cannot follow; the kernel can, and the pipe has a reader."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "rsra", "export", "--dbc", "/dev/stdout"],
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr.decode()
    assert r.stdout.startswith(b'VERSION "') and b"BO_ " in r.stdout
    assert not list(tmp_path.iterdir())
