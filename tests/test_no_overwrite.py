"""No command writes over its input (issue 27 item 0; docs/cli.md §16): the same path, a
symbolic link, a hard link, a file of an input recording folder, a name that would join an
input recording — each refused with one line, exit 2, before anything is read, every input
byte for byte as it was; and an output is renamed into place only when complete, so a failed
run leaves the old file whole."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
from helpers_canopen import LockstepRig

from rsra.config.rig import load_config
from rsra.daq.cli import main


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A real recording folder (lock-step simulator, 150 samples) and a copy of its frames as
    a loose file, a symbolic link and a hard link to it."""
    top = tmp_path_factory.mktemp("ow")
    folder = top / "rec"
    rig = LockstepRig(load_config(), record=folder)
    try:
        rig.step(150)
    finally:
        rig.close()
    loose = top / "in.log"
    loose.write_bytes((folder / "frames.log").read_bytes())
    (top / "b.log").write_bytes(loose.read_bytes())
    (top / "sym.log").symlink_to(loose.name)
    os.link(loose, top / "hard.log")
    return top


def _digest(top: Path) -> dict[str, str]:
    return {str(p.relative_to(top)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(top.rglob("*")) if p.is_file() and not p.is_symlink()}


CASES = {  # name: (argv, words of the one line)
    "replay into its folder's frames": (["replay", "rec", "--out", "rec/frames.log"],
                                        ["is the input rec/frames.log"]),
    "replay onto its own file": (["replay", "in.log", "--out", "in.log"], ["is the input in.log"]),
    "the same file spelled otherwise": (["replay", "in.log", "--out", "rec/../in.log"],
                                        ["is the input in.log"]),
    "a symbolic link to the input": (["replay", "in.log", "--out", "sym.log"],
                                     ["symbolic link to the input in.log"]),
    "a hard link to the input": (["replay", "in.log", "--out", "hard.log"],
                                 ["hard link", "the input in.log"]),
    "the second of two inputs": (["replay", "in.log", "b.log", "--out", "b.log"],
                                 ["is the input b.log"]),
    "the recorded angle schedule": (["replay", "rec", "--out", "rec/angles.jsonl"],
                                    ["is the input rec/angles.jsonl"]),
    "a name that would join the recording": (["replay", "rec", "--out", "rec/frames_000001.log"],
                                             ["would become part of the input recording rec"]),
    "into the recording's eds folder": (["replay", "rec", "--out", "rec/eds/new.eds"],
                                        ["would become part of the input recording rec"]),
    "run's log file onto its posterior": (["run", "--sim", "ground-test", "--angles", "in.log",
                                           "--log-file", "in.log"],
                                          ["--log-file in.log", "is the input --angles in.log"]),
    "calibrate's fragment onto the schedule": (["calibrate", "rec", "--out", "rec/angles.jsonl"],
                                               ["--out rec/angles.jsonl", "is the input"]),
    "export's MCAP onto the frames": (["export", "rec", "--mcap", "rec/frames.log"],
                                      ["--mcap rec/frames.log", "is the input"]),
    "export's Parquet into the recording": (["export", "rec", "--parquet", "rec"],
                                            ["--parquet rec", "input folder rec"]),
    "sweep's plots into the recording": (["sweep", "rec", "--out", "rec"],
                                         ["--out rec", "input folder rec"]),
    "the rig file as calibrate's fragment": (["calibrate", "rec", "--config", "rig.toml",
                                              "--out", "rig.toml"],
                                             ["is the input --config rig.toml"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_an_output_that_is_an_input_is_refused_before_anything_is_read(name, recording, capsys,
                                                                        monkeypatch):
    argv, words = CASES[name]
    monkeypatch.chdir(recording)
    (recording / "rig.toml").write_text("")  # (only its identity matters: never read)
    before = _digest(recording)
    names = sorted(recording.rglob("*"))
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"rsra {argv[0]}: error: "), lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert _digest(recording) == before  # every input byte for byte as it was
    assert sorted(recording.rglob("*")) == names  # nothing created


def test_a_new_file_beside_a_recording_is_allowed(recording, monkeypatch, capsys):
    monkeypatch.chdir(recording)
    out = recording / "rec" / "results.jsonl"
    try:
        assert main(["replay", "rec", "--out", str(out)]) == 0
        assert out.stat().st_size > 0
    finally:
        out.unlink(missing_ok=True)


def test_a_failed_replay_leaves_the_old_file_whole_and_no_temporary(recording, tmp_path,
                                                                   monkeypatch, capsys):
    from rsra.daq.runtime import service as service_mod

    out = tmp_path / "old.jsonl"
    out.write_text("the old results\n")
    real_run = service_mod.Service.run

    def failing_run(self):
        seen = []

        def explode(key, payload):  # after the --out file has taken 50 records
            seen.append(key)
            if len(seen) > 50:
                raise RuntimeError("a failure half-way")
        self.add_sink(explode)
        return real_run(self)

    monkeypatch.setattr(service_mod.Service, "run", failing_run)
    assert main(["replay", str(recording / "rec"), "--out", str(out)]) == 1
    assert "a failure half-way" in capsys.readouterr().err
    assert out.read_text() == "the old results\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.jsonl"]


def test_an_output_through_a_symbolic_link_replaces_the_target_and_keeps_the_link(
        recording, tmp_path, capsys):
    target = tmp_path / "target.jsonl"
    target.write_text("old\n")
    link = tmp_path / "link.jsonl"
    link.symlink_to(target.name)
    assert main(["replay", str(recording / "rec"), "--out", str(link)]) == 0
    assert link.is_symlink() and target.read_text().count("\n") > 10


@pytest.mark.parametrize("argv, words", [
    (["replay", "in.log", "--out", "/proc/nope"], ["--out /proc/nope: cannot be written there",
                                                  "fix: write elsewhere"]),
    (["replay", "/dev/zero", "--out", "o.jsonl"], ["/dev/zero: not a regular file"]),
    (["replay", "empty.log", "--out", "o.jsonl"], ["empty.log: no CAN frames in it",
                                                  "an empty recording"]),
])
def test_unwritable_out_a_device_and_an_empty_recording_are_one_line_exit_2(
        argv, words, recording, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in.log").write_bytes((recording / "in.log").read_bytes())
    (tmp_path / "empty.log").write_text("")
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not (tmp_path / "o.jsonl").exists()


def test_time_going_back_is_a_discontinuity_not_lost_samples_or_rewritten_times(
        recording, tmp_path, capsys):
    """The same log concatenated twice (issue 27 item 3): every sample of both halves, none
    lost, the second half at its own (recorded) times, the jump counted and reported once."""
    import json

    rig = LockstepRig(load_config(), record=tmp_path / "long")  # 1.5 s: more than 1 s back
    try:
        rig.step(300)
    finally:
        rig.close()
    once = (tmp_path / "long" / "frames.log").read_text()
    (tmp_path / "twice.log").write_text(once + once)
    out = tmp_path / "r.jsonl"
    assert main(["replay", str(tmp_path / "twice.log"), "--out", str(out)]) == 0
    io = capsys.readouterr()
    assert "time went back 1 time" in io.out
    assert io.err.count("time goes back") == 1  # the log line, once
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    hub = [r for r in recs if r["key"] == "hub_loads"]
    n = len(hub) // 2
    assert len(hub) == 2 * n and n >= 290
    assert [r["t"] for r in hub[n:]] == [r["t"] for r in hub[:n]]  # times as recorded
    assert [r["seq"] for r in hub] == list(range(2 * n))  # no seq skipped: nothing lost
    health = [r for r in recs if r["key"] == "health"][-1]
    assert health["samples"]["lost"] == 0
    assert health["sync"]["discontinuities"] == 1
    assert health["sync"]["bad_timestamp"] == 0
