"""A recording carries what it needs to replay right, and replay refuses what it cannot replay
right (issue 46 item 3; docs/reliability.md "Replaying a recording"): frames out of order
within the reorder window, a recording joined to itself, a folder without its configuration,
a bare log of another rig, several inputs that are not one recording."""
from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import pytest
from helpers_canopen import LockstepRig

from rsra.config.rig import load_config
from rsra.daq.bus.reader import HealthReport, OfflineReader
from rsra.daq.bus.reorder import REORDER_WINDOW
from rsra.daq.bus.replay import replay
from rsra.daq.cli import main

CONFIG = Path(__file__).parents[1] / "config"
N = 240  # one whole SYNC counter cycle: joined to itself, the counter runs 240 -> 1


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    """A recording folder of the packaged ground rig (lock-step simulator, 240 samples)."""
    folder = tmp_path_factory.mktemp("rr") / "rec"
    rig = LockstepRig(load_config(), record=folder)
    try:
        rig.step(N)
    finally:
        rig.close()
    return folder


def _replay(path: Path):
    cfg = load_config()
    r = OfflineReader(cfg)
    got = [x for x in replay(cfg, [path], reader=r, finish=True)
           if not isinstance(x, HealthReport)]
    return got, r.health().to_dict()


def _same(a, b) -> bool:
    return len(a) == len(b) and all(x.same_as(y) for x, y in zip(a, b))


def test_a_log_shuffled_within_the_window_gives_the_samples_of_the_ordered_log(rec, tmp_path):
    """Before: lines 1000-3000 shuffled gave "lost 16800", samples numbered far beyond the
    real ones."""
    lines = (rec / "frames.log").read_text().splitlines(keepends=True)
    assert len(lines) > 3000
    mid = lines[1000:3001]  # 2 001 lines: every frame within 2 000 places of its own
    assert len(mid) <= REORDER_WINDOW + 1
    random.Random(46).shuffle(mid)
    shuffled = tmp_path / "shuffled.log"
    shuffled.write_text("".join(lines[:1000] + mid + lines[3001:]))
    ref, h_ref = _replay(rec / "frames.log")
    got, h = _replay(shuffled)
    assert len(ref) == N and _same(got, ref)
    assert h["samples"] == h_ref["samples"] and h["samples"]["lost"] == 0
    assert "late" not in h["bus"]


def test_frames_beyond_the_window_count_as_late_never_as_lost_samples(rec, tmp_path, capsys):
    lines = (rec / "frames.log").read_text().splitlines(keepends=True)
    moved = lines[200:260]  # 60 frames (SYNCs among them) 2 200 lines (0.8 s) late
    assert sum(" 080#" in x for x in moved) >= 3
    late = tmp_path / "late.log"
    late.write_text("".join(lines[:200] + lines[260:2460] + moved + lines[2460:]))
    got, h = _replay(late)
    assert h["bus"]["late"] == 60
    assert h["samples"]["lost"] == 0
    assert max(s.seq for s in got) == N - 1  # numbered as recorded, nothing invented
    assert main(["replay", str(late)]) == 0
    out = capsys.readouterr().out
    assert "lost 0" in out and "60 frames late" in out


def test_time_going_back_with_the_counter_following_is_a_discontinuity(rec, tmp_path,
                                                                       capsys):
    """A recording of a whole counter cycle joined to itself (counter 240 -> 1 across the
    join). Before: bad_timestamp for every later SYNC and the second half's t rewritten to
    continue the first's."""
    once = (rec / "frames.log").read_text()
    twice = tmp_path / "twice.log"
    twice.write_text(once + once)
    got, h = _replay(twice)
    assert len(got) == 2 * N
    assert [s.t for s in got[N:]] == [s.t for s in got[:N]]  # each its recorded SYNC's time
    assert h["sync"]["discontinuities"] == 1 and h["sync"]["bad_timestamp"] == 0
    assert h["samples"]["lost"] == 0
    out = tmp_path / "r.jsonl"
    assert main(["replay", str(twice), "--out", str(out)]) == 0
    assert "time went back 1 time" in capsys.readouterr().out
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    health = [r for r in recs if r["key"] == "health"][-1]
    assert health["sync"]["discontinuities"] == 1 and health["sync"]["bad_timestamp"] == 0


def _one_line_exit_2(argv, capsys, *words) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.mark.parametrize("how", ["missing", "device", "unparsable"])
def test_a_folder_without_a_readable_config_needs_config(rec, tmp_path, capsys, how):
    """Before: replayed on the packaged default rig, exit 0 (a flight-rig recording: H off
    by a median of 621 N)."""
    folder = tmp_path / "rec"
    shutil.copytree(rec, folder)
    cfg_file = folder / "config.json"
    cfg_file.unlink()
    if how == "device":
        cfg_file.symlink_to("/dev/zero")
    elif how == "unparsable":
        cfg_file.write_text("{")
    out = tmp_path / "o.jsonl"
    _one_line_exit_2(["replay", str(folder), "--out", str(out)], capsys, str(folder),
                     "config.json", "--config")
    assert not out.exists()
    # with the rig named it replays
    assert main(["replay", str(folder), "--config", str(CONFIG / "rig.toml")]) == 0


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    """A recording folder of the packaged flight rig (100 samples)."""
    from rsra.daq.rigmodel import load_rig

    folder = tmp_path_factory.mktemp("rrf") / "flight"
    rig = LockstepRig(load_rig(CONFIG / "flight-rig.toml"), record=folder)
    try:
        rig.step(100)
    finally:
        rig.close()
    return folder


def test_a_bare_log_of_another_rig_is_refused_naming_config(flight, rec, capsys):
    _one_line_exit_2(["replay", str(flight / "frames.log")], capsys, "frames.log",
                     "do not fit the packaged default rig", "--config")
    # the rig's own log (bare) replays on the default rig as before; with --config, too
    assert main(["replay", str(rec / "frames.log")]) == 0
    assert main(["replay", str(flight / "frames.log"), "--config",
                 str(CONFIG / "flight-rig.toml")]) == 0


def test_several_inputs_only_as_consecutive_parts_of_one_recording(rec, flight, tmp_path,
                                                                   capsys):
    """Before: `rsra replay A B` of two recordings exited 0 with one stream on A's rig."""
    log = rec / "frames.log"
    _one_line_exit_2(["replay", str(rec), str(flight)], capsys, str(rec), str(flight),
                     "different rigs")
    _one_line_exit_2(["replay", str(log), str(log)], capsys, "not consecutive parts")
    copy = tmp_path / "copy"
    shutil.copytree(rec, copy)
    _one_line_exit_2(["export", str(rec), str(copy), "--mcap", str(tmp_path / "o.mcap")],
                     capsys, str(rec), str(copy), "not consecutive parts")
    # a recording cut in two (at a line) is accepted as its two parts, in order
    lines = log.read_text().splitlines(keepends=True)
    (tmp_path / "a.log").write_text("".join(lines[:1700]))
    (tmp_path / "b.log").write_text("".join(lines[1700:]))
    out = tmp_path / "parts.jsonl"
    assert main(["replay", str(tmp_path / "a.log"), str(tmp_path / "b.log"),
                 "--out", str(out)]) == 0
    assert "samples complete 240, incomplete 0, lost 0" in capsys.readouterr().out
    _one_line_exit_2(["replay", str(tmp_path / "b.log"), str(tmp_path / "a.log")], capsys,
                     "b.log", "a.log", "not consecutive parts")


def test_calibrate_takes_recordings_of_one_rig_and_refuses_two_rigs(rec, flight, tmp_path,
                                                                    capsys):
    from rsra.daq.bus.replay import config_for

    copy = tmp_path / "copy"
    shutil.copytree(rec, copy)
    assert config_for([rec, copy]).rig_name == config_for([rec]).rig_name  # pooled: fine
    _one_line_exit_2(["calibrate", str(rec), str(flight), "--out", str(tmp_path / "c.toml")],
                     capsys, str(rec), str(flight), "different rigs", "one rig together")
