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
