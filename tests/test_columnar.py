"""The columnar replay (daq/bus/columnar.py) equals the streaming one (docs/cli.md §6
`--streaming`): the same samples bit for bit and the same health reports, on a ground, a
flight, a faulted (lost, malformed, unknown, error frames, a reboot), a concatenated and a
flight-rig (azimuth) recording, across block edges, on damaged text; and `rsra replay --out`
writes the same file on both paths."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import can
import pytest

from rsra.daq.bus import columnar
from rsra.daq.bus.reader import HealthReport, OfflineReader
from rsra.daq.bus.replay import ReplayError, config_for, expand, replay
from rsra.daq.cli import main as rsra_main

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
FAULTS = ("drop:cell_B:0.02;malformed:cell_C:0.02;unknown:0.02;lostsync:0.02;errorframe:0.02;"
          "reboot:cell_E@1.5")
FLIGHT_RIG = str(Path(__file__).resolve().parents[1] / "config" / "flight-rig.toml")
RECORDINGS = {  # seconds of acquisition, `rsra run` options
    "ground": (8, ["--sim", "ground-test"]),  # long enough for identification runs
    "flight": (3, ["--sim", "flight"]),
    "faulted": (3, ["--sim", "ground-test", "--faults", FAULTS]),
    "flight-rig": (3, ["--sim", "flight", "--config", FLIGHT_RIG]),
}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    """Short recordings of each kind (``rsra run --speed max --record``)."""
    root = tmp_path_factory.mktemp("columnar")
    out = {}
    for name, (seconds, args) in RECORDINGS.items():
        folder = root / name
        r = subprocess.run([sys.executable, "-m", "rsra", "run", *args, "--seed", "3",
                            "--speed", "max", "--duration", str(seconds), "--record", str(folder),
                            "--zenoh-listen", "tcp/127.0.0.1:0", "--log-level", "error"],
                           capture_output=True, text=True, timeout=180, env=ENV, check=False)
        assert r.returncode == 0, r.stderr[-2000:]
        out[name] = folder
    return out


def _items(paths, streaming: bool, block_bytes: int | None = None) -> list:
    cfg = config_for(paths)
    if streaming or block_bytes is None:
        return list(replay(cfg, paths, finish=True, streaming=streaming))
    return list(columnar.replay_columnar(OfflineReader(cfg), expand(paths), finish=True,
                                         block_bytes=block_bytes))


def assert_same_items(a: list, b: list) -> None:
    assert len(a) == len(b) > 0
    for x, y in zip(a, b):
        if isinstance(x, HealthReport):
            assert isinstance(y, HealthReport) and x == y, (x, y)
        else:
            assert not isinstance(y, HealthReport) and x.same_as(y), (x, y)


def _equal_both_ways(paths, block_bytes: int | None = None) -> list:
    ref = _items(paths, streaming=True)
    got = _items(paths, streaming=False, block_bytes=block_bytes)
    assert_same_items(ref, got)
    return ref


@pytest.mark.parametrize("kind", list(RECORDINGS))
def test_columnar_items_equal_the_streaming_ones(recordings, kind):
    items = _equal_both_ways([recordings[kind]])
    samples = [x for x in items if not isinstance(x, HealthReport)]
    assert len(samples) >= 590
    if kind == "faulted":  # the rules the columnar path hands over were exercised
        last = [x for x in items if isinstance(x, HealthReport)][-1].health
        assert last.samples.lost > 0 and last.bus.unknown > 0 and last.bus.malformed > 0
        assert last.bus.errors > 0 and any(not s.complete for s in samples)
    if kind == "flight-rig":
        assert all(s.azimuth is not None for s in samples[1:])


@pytest.mark.parametrize("kind", ["ground", "faulted", "flight-rig"])
def test_small_blocks_cut_samples_anywhere(recordings, kind):
    """Blocks of 3 000 bytes: every block edge falls somewhere inside a SYNC period."""
    _equal_both_ways([recordings[kind]], block_bytes=3000)


def _lines(folder: Path) -> list[bytes]:
    return (folder / "frames.log").read_bytes().splitlines(keepends=True)


def test_a_reboot_at_a_block_edge(recordings, tmp_path):
    lines = _lines(recordings["faulted"])
    # the rebooting node's boot-up (heartbeat state 0) after the start-up's
    boot = [i for i, ln in enumerate(lines) if b" 715#00" in ln]
    assert len(boot) >= 2, "no reboot in the faulted recording"
    k = boot[-1]
    edge = sum(len(ln) for ln in lines[:k])
    for block in (edge, edge + 1, edge - 1):
        # the first block ends right before / inside / after the boot-up line
        _equal_both_ways([recordings["faulted"]], block_bytes=block)


def test_an_out_of_order_stretch_across_a_block_edge(recordings, tmp_path):
    lines = _lines(recordings["ground"])
    k = len(lines) // 2
    stretch = lines[k:k + 40]
    lines[k:k + 40] = stretch[::-1]  # 40 frames (about three SYNC periods) backwards
    f = tmp_path / "shuffled.log"
    f.write_bytes(b"".join(lines))
    edge = sum(len(ln) for ln in lines[:k + 20])
    _equal_both_ways([f], block_bytes=edge)
    _equal_both_ways([f])


def test_concatenated_recordings(recordings, tmp_path):
    """One recording cut in two files, and one file holding a recording twice (time goes
    back: a discontinuity, counted)."""
    lines = _lines(recordings["ground"])
    a, b = tmp_path / "a.log", tmp_path / "b.log"
    k = len(lines) // 3 + 5  # inside a SYNC period
    a.write_bytes(b"".join(lines[:k]))
    b.write_bytes(b"".join(lines[k:]))
    _equal_both_ways([a, b])
    twice = tmp_path / "twice.log"
    twice.write_bytes(b"".join(lines + lines))
    items = _equal_both_ways([twice], block_bytes=len(b"".join(lines)) - 100)
    last = [x for x in items if isinstance(x, HealthReport)][-1].health
    assert last.sync.discontinuities == 1


def test_an_over_long_line_is_the_same_frame_on_both_paths(recordings, tmp_path):
    """python-can reads a 60 000-byte frame (the reader counts it malformed); a line longer
    than a block spans several."""
    lines = _lines(recordings["ground"])
    k = len(lines) // 2
    f = tmp_path / "long.log"
    long = b"(1796674406.998000) sim 711#" + b"05" * 60_000 + b" R\n"
    f.write_bytes(b"".join(lines[:k]) + long + b"".join(lines[k:]))
    items = _equal_both_ways([f], block_bytes=20_000)
    assert [x for x in items if isinstance(x, HealthReport)][-1].health.bus.malformed == 1


@pytest.mark.parametrize("bad", [
    b"(1796674406.998000) sim 711#0\xff R\n",  # not UTF-8, in the data
    b"(1796674406.998000) sim \xfe\xff 711#05 R\n",  # not UTF-8: a channel python-can splits
    b"(1796674406.998000) s\tm 711#05 R\n",  # a tab: one field more (every byte counted)
])
def test_a_damaged_line_fails_the_same_on_both_paths(recordings, tmp_path, bad):
    lines = _lines(recordings["ground"])
    k = len(lines) // 2
    f = tmp_path / "damaged.log"
    f.write_bytes(b"".join(lines[:k]) + bad + b"".join(lines[k:]))
    errors, seen = [], []
    for streaming in (True, False):
        items: list = []
        with pytest.raises(ReplayError) as e:
            for x in replay(config_for([f]), [f], finish=True, streaming=streaming):
                items.append(x)
        errors.append(str(e.value))
        seen.append(items)
    assert errors[0] == errors[1] and f":{k + 1}: not a candump frame" in errors[0]
    assert_same_items(*seen)


def test_non_utf8_in_a_channel_name_is_a_frame_on_both_paths(recordings, tmp_path):
    lines = _lines(recordings["ground"])
    lines = [ln.replace(b" sim ", b" s\xffm ") if i % 7 == 0 else ln
             for i, ln in enumerate(lines)]
    f = tmp_path / "channel.log"
    f.write_bytes(b"".join(lines))
    _equal_both_ways([f])


def test_a_recording_of_one_sample_and_an_empty_one(recordings, tmp_path):
    lines = _lines(recordings["ground"])
    first_sync = next(i for i, ln in enumerate(lines) if b" 080#" in ln)
    second = next(i for i, ln in enumerate(lines) if b" 080#" in ln and i > first_sync)
    one = tmp_path / "one.log"
    one.write_bytes(b"".join(lines[:second]))
    items = _equal_both_ways([one])
    assert sum(1 for x in items if not isinstance(x, HealthReport)) == 1
    empty = tmp_path / "empty.log"
    empty.write_bytes(b"")
    errors = []
    for streaming in (True, False):
        with pytest.raises(ReplayError) as e:
            list(replay(config_for([empty]), [empty], streaming=streaming))
        errors.append(str(e.value))
    assert errors[0] == errors[1] and "no CAN frames" in errors[0]


def test_a_cut_last_line_is_dropped_on_both_paths(recordings, tmp_path):
    data = (recordings["ground"] / "frames.log").read_bytes()
    f = tmp_path / "cut.log"
    f.write_bytes(data[:-9])  # the last line cut inside its data
    _equal_both_ways([f])


def test_blf_and_asc_take_the_columnar_path_with_the_same_items(recordings, tmp_path):
    src = recordings["faulted"] / "frames.log"
    for suffix in (".blf", ".asc"):
        dst = tmp_path / f"frames{suffix}"
        with can.LogReader(src) as r, can.Logger(dst) as w:
            for msg in r:
                w.on_message_received(msg)
        _equal_both_ways([dst])


@pytest.mark.parametrize("kind,extra", [("ground", []), ("ground", ["--recompute"]),
                                        ("faulted", []), ("flight-rig", ["--recompute"])])
def test_replay_out_writes_the_same_file_on_both_paths(recordings, tmp_path, kind, extra):
    """Every record — hub loads, channels, innovations, health, angles (accepted runs, α,
    P) — the same line on both paths (the recorded schedule, and recomputed)."""
    outs = []
    for streaming in ([], ["--streaming"]):
        out = tmp_path / f"out{len(outs)}.jsonl"
        assert rsra_main(["replay", str(recordings[kind]), "--out", str(out), *extra,
                          *streaming]) == 0
        outs.append([_without_pid(line) for line in out.read_bytes().splitlines()])
    assert outs[0] == outs[1] and sum(b'"key":"channels"' in x for x in outs[0]) >= 590
    if kind == "ground":
        assert sum(b'"key":"angles"' in x for x in outs[0]) >= 1  # an identification run


def _without_pid(line: bytes) -> bytes:
    """A record as written, but the identification worker's process id (health)."""
    return re.sub(rb'"pid":\d+', b'"pid":0', line) if line.startswith(b'{"key":"health"') \
        else line


def test_replay_help_imports_no_scipy():
    code = ("import sys\nfrom rsra.daq.cli import main\ntry:\n    main(['replay', '--help'])\n"
            "except SystemExit:\n    pass\nprint(sorted(m for m in sys.modules "
            "if m.split('.')[0] in ('scipy', 'matplotlib', 'pyarrow', 'zenoh')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60, env=ENV, check=True)
    assert "--streaming" in r.stdout
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout[-500:]


@pytest.mark.parametrize("block_bytes", [None, 3000, 200_000])
def test_frames_out_of_order_take_the_streaming_reorder_stage_on_the_columnar_path(
        recordings, tmp_path, block_bytes):
    """The reorder rule written once (daq.bus.reorder): 2 000 lines shuffled (within the
    window: the ordered log's samples) and one frame moved 2 300 lines later (beyond it, within a second: late)
    give the streaming path's items on the columnar path, whatever the block size."""
    import random

    lines = _lines(recordings["ground"])
    k = len(lines) // 4
    part = lines[k:k + 2000]
    random.Random(7).shuffle(part)
    lines[k:k + 2000] = part
    j = k + 2500
    lines.insert(j + 2300, lines.pop(j))  # one frame beyond the window (~0.9 s of traffic)
    f = tmp_path / "shuffled.log"
    f.write_bytes(b"".join(lines))
    items = _equal_both_ways([f], block_bytes=block_bytes)
    last = [x for x in items if isinstance(x, HealthReport)][-1].health
    assert last.bus.late == 1


def test_a_line_longer_than_any_frame_is_read_only_to_its_limit_on_both_paths(recordings,
                                                                             tmp_path):
    """A 3 MB line of NUL bytes in the middle of a log (a damaged disk): neither path reads it
    whole — its first MAX_LINE_CHARS stand for it, the same error naming the line on both; at
    the end of the file (no newline) it is a cut line, dropped, the frames before it kept."""
    from rsra.daq.bus.logfiles import MAX_LINE_CHARS

    lines = _lines(recordings["ground"])
    k = len(lines) // 2
    nul = b"\0" * 3_000_000
    mid = tmp_path / "mid.log"
    mid.write_bytes(b"".join(lines[:k]) + nul + b"\n" + b"".join(lines[k:]))
    errors = []
    for streaming in (True, False):
        with pytest.raises(ReplayError) as e:
            list(replay(config_for([mid]), [mid], finish=True, streaming=streaming))
        errors.append(str(e.value))
    assert errors[0] == errors[1] and f":{k + 1}: not a candump frame" in errors[0]
    end = tmp_path / "end.log"
    end.write_bytes(b"".join(lines) + nul)
    items = _equal_both_ways([end], block_bytes=MAX_LINE_CHARS // 3)
    assert len([x for x in items if not isinstance(x, HealthReport)]) >= 590


def test_neither_reader_holds_an_over_long_line(tmp_path, monkeypatch):
    """What the readers hold of a 3 MB line: at most MAX_LINE_CHARS (and its newline)."""
    from rsra.daq.bus.logfiles import MAX_LINE_CHARS, _CompleteLines

    f = tmp_path / "nul.log"
    good = b"(1796674406.998000) sim 711#05 R\n"
    f.write_bytes(good + b"\0" * 3_000_000 + b"\n" + good)
    lines = _CompleteLines(f)
    try:
        got = list(lines)
    finally:
        lines.close()
    assert [len(x) for x in got] == [len(good), MAX_LINE_CHARS + 1, len(good)]
    seen: list[int] = []
    real = columnar.CandumpBlocks._lines

    def lines_of(self, chunk):
        seen.append(max(len(x) for x in chunk.split(b"\n")))
        return real(self, chunk)

    monkeypatch.setattr(columnar.CandumpBlocks, "_lines", lines_of)
    with pytest.raises(ReplayError):
        list(columnar.CandumpBlocks(f, block_bytes=64 * 1024))
    assert seen and max(seen) <= MAX_LINE_CHARS
