"""Bad input: frames, EDS files and config values that are wrong in every way we can think
of, and the ways hypothesis finds. No exception escapes the reader, no non-finite value
reaches the load filter's state or a published record, every bad thing is counted, and
every bad file or key is refused with an error that names it and says what to do.

The bounded runs here take a few seconds; ``RSRA_FUZZ_EXAMPLES=N`` runs N examples per
property instead (docs/reliability.md records the long run).
"""
from __future__ import annotations

import copy
import itertools
import math
import os
import struct
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rsra.config.rig import ConfigError, config_dir, default_config_path, load_config, parse_config
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.jsonout import dumps
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.bus.reader import HealthReport, OfflineReader

EXAMPLES = int(os.environ.get("RSRA_FUZZ_EXAMPLES", "100"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=False,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ_SMALL = settings(FUZZ, max_examples=max(1, EXAMPLES // 3))
T0 = 1_700_000_000.0
DT = 0.005

_cfg = load_config()
_table = DecodeTable(_cfg)
TPDO_COBS = sorted(_table.tpdos)
SYNC_COB = _cfg.sync.cob_id
KNOWN = OfflineReader(_cfg)._known_cob_ids()
FLAG_PREFIXES = ("missing:", "overrange:", "fault:")
FLAG_WORDS = {"lost_before", "predict_only", "invalid", "rotor_stopped"}

# REAL32 values that break naive code: NaN (quiet and signalling payloads), ±inf, the largest
# finite, the smallest denormal, -0
SPECIAL_F32 = [struct.pack("<I", b) for b in (0x7FC00000, 0x7FA00001, 0xFFC00000, 0x7F800000,
                                               0xFF800000, 0x7F7FFFFF, 0xFF7FFFFF, 0x00000001,
                                               0x80000000)]


@st.composite
def frame(draw):
    """One bus event: a SYNC (any counter byte, any length), a configured TPDO (right or
    wrong length, any bytes, REAL32 specials spliced in), an unknown or extended COB-ID, an
    error frame or a remote frame."""
    kind = draw(st.sampled_from(["sync", "sync", "tpdo", "tpdo", "tpdo", "tpdo", "special",
                                 "unknown", "extended", "error", "remote"]))
    if kind == "sync":
        n = draw(st.sampled_from([1, 1, 1, 1, 0, 2, 8]))
        return ("data", SYNC_COB, draw(st.binary(min_size=n, max_size=n)), False)
    if kind in ("tpdo", "special"):
        cob = draw(st.sampled_from(TPDO_COBS))
        length = _table.tpdos[cob].length
        n = draw(st.sampled_from([length] * 6 + [0, length - 1, length + 1, 8]))
        n = max(0, min(8, n))
        data = bytearray(draw(st.binary(min_size=n, max_size=n)))
        if kind == "special" and n >= 4:
            at = draw(st.integers(0, n - 4))
            data[at:at + 4] = draw(st.sampled_from(SPECIAL_F32))
        return ("data", cob, bytes(data), False)
    if kind == "unknown":
        cob = draw(st.integers(0, 0x7FF).filter(lambda c: c not in KNOWN))
        return ("data", cob, draw(st.binary(max_size=8)), False)
    if kind == "extended":  # mostly on the configured COB-IDs: they must not pass as ours
        cob = draw(st.one_of(st.sampled_from(TPDO_COBS + [SYNC_COB]),
                             st.integers(0, 0x1FFFFFFF)))
        n = draw(st.sampled_from([_table.tpdos[cob].length if cob in _table.tpdos else 1, 8]))
        return ("data", cob, draw(st.binary(min_size=n, max_size=n)), True)
    if kind == "error":
        return ("error", draw(st.integers(0, 0x1FFFFFFF)), b"", False)
    return ("remote", draw(st.sampled_from(TPDO_COBS + [SYNC_COB])), b"", False)


@st.composite
def bus_traffic(draw):
    """A realistic run of complete periods, with arbitrary frames spliced in anywhere, and
    timestamps that mostly advance (sometimes repeat or go back: the tap must cope)."""
    import can
    from helpers_canopen import period_frames

    n_periods = draw(st.integers(0, 12))
    msgs = []
    for k in range(n_periods):
        msgs.extend(period_frames(_cfg, k, T0 + k * DT))
    for _ in range(draw(st.integers(1, 40))):
        kind, cob, data, ext = draw(frame())
        at = draw(st.integers(0, len(msgs)))
        t = msgs[at - 1].timestamp if at else T0
        t += draw(st.sampled_from([0.0, 1e-6, 1e-4, -1e-3, DT, 3 * DT]))
        m = can.Message(timestamp=t, arbitration_id=cob, data=data, is_extended_id=ext,
                        is_error_frame=kind == "error", is_remote_frame=kind == "remote",
                        check=False)
        msgs.insert(at, m)
    return msgs


@pytest.fixture(scope="module")
def pipeline():
    return EstimatorPipeline(_cfg, _cfg.identification.initial_angles_rad, identification=True)


def _check_sample(s) -> None:
    for name in ("T", "accel"):
        a = np.asarray(getattr(s, name), float)
        assert not np.isinf(a).any(), (name, a)  # missing is NaN, never ±inf
    for v in (s.omega, s.azimuth):
        assert v is None or math.isfinite(v)
    for a in (s.known_H, s.drive):
        assert a is None or np.isfinite(a).all()
    for f in s.flags:
        assert f in FLAG_WORDS or f.startswith(FLAG_PREFIXES), f
    assert s.complete == (not s.missing)
    assert ("lost_before" in s.flags) == (s.lost_before > 0)


def _check_records(pipe, out) -> None:
    x = pipe.load_filter.state
    assert np.isfinite(x).all(), x
    for key, payload in out.records:
        text = dumps(payload)  # strict JSON: raises on NaN/inf
        if key == "hub_loads":
            for k in ("H", "H_static"):
                v = payload[k]
                assert v is None or np.isfinite(np.asarray(v, float)).all()
            assert (payload["H"] is None) == ("invalid" in payload["flags"])
        elif key == "innovations":
            assert payload["e"] is None or np.isfinite(payload["e"]).all()
            assert payload["nis"] is None or math.isfinite(payload["nis"])
        assert "NaN" not in text and "Infinity" not in text
    for ch in pipe.calibration.content.values():
        for arr in vars(ch).values():
            if isinstance(arr, np.ndarray) and arr.dtype.kind == "f":
                assert np.isfinite(arr).all()


@FUZZ
@given(msgs=bus_traffic())
def test_arbitrary_frames_never_raise_and_never_reach_the_filter_as_non_finite(msgs, pipeline):
    r = OfflineReader(_cfg)
    for m in msgs:
        r.feed(m)
    r.assembler.finish()
    items = r.poll()
    tap, asm = r.tap, r.assembler
    assert tap.frames == len(msgs) and tap.callback_errors == 0
    samples = [s for s in items if not isinstance(s, HealthReport)]
    assert len(samples) == asm.emitted == asm.complete + asm.incomplete
    # every bad frame is counted somewhere
    n_err = sum(m.is_error_frame for m in msgs)
    assert tap.errors == n_err
    # extended identifiers (on our COB-IDs too) and unknown ones: counted, never used
    n_unknown = sum(not m.is_error_frame and (m.is_extended_id or m.arbitration_id not in KNOWN)
                    for m in msgs)
    assert tap.unknown == n_unknown
    prev = None
    for s in samples:
        _check_sample(s)
        if prev is not None:  # lost samples keep their numbers
            assert s.seq - prev.seq - 1 == s.lost_before
        prev = s
    assert sum(s.lost_before for s in samples) <= asm.lost
    # into the estimator: a fresh filter state per example, the calibration branch shared
    pipeline.load_filter.reset()
    pipeline.first_seq = pipeline._last_seq = None
    for s in samples:
        out = pipeline.process(s)
        _check_records(pipeline, out)


@FUZZ_SMALL
@given(data=st.data())
def test_extended_frames_on_the_configured_cob_ids_change_no_sample(data):
    """A 29-bit frame whose identifier equals a TPDO's or the SYNC's COB-ID is another
    device's frame: counted unknown, and the samples are those of the frames without it."""
    import can
    from helpers_canopen import period_frames

    clean = []
    for k in range(8):
        clean.extend(period_frames(_cfg, k, T0 + k * DT))
    mixed = []
    n_ext = 0
    for m in clean:
        mixed.append(m)
        for cob in data.draw(st.lists(st.sampled_from(TPDO_COBS + [SYNC_COB]), max_size=2)):
            n = _table.tpdos[cob].length if cob in _table.tpdos else 1
            mixed.append(can.Message(timestamp=m.timestamp, arbitration_id=cob,
                                     data=data.draw(st.binary(min_size=n, max_size=n)),
                                     is_extended_id=True))
            n_ext += 1

    def run(msgs):
        r = OfflineReader(_cfg)
        for m in msgs:
            r.feed(m)
        r.assembler.finish()
        return r, [s for s in r.poll() if not isinstance(s, HealthReport)]

    _, ref = run(clean)
    r, got = run(mixed)
    assert len(got) == len(ref) and all(a.same_as(b) for a, b in zip(got, ref))
    assert r.tap.unknown == n_ext and r.assembler.duplicate == 0


@FUZZ_SMALL
@given(counters=st.lists(st.integers(0, 255), min_size=1, max_size=60),
       drop=st.lists(st.booleans(), min_size=60, max_size=60))
def test_any_sync_counter_sequence_is_counted_not_trusted(counters, drop):
    """Any counter sequence, one SYNC per period (docs/reliability.md "SYNC counter and frame
    times"): counters out of range are malformed; a counter repeating the last one is a
    duplicate SYNC (no sample, no seq); otherwise the counter's skip is the number lost (no
    sequence here is long enough for a whole counter cycle to fit in its times); a count the
    frame times cannot hold re-stamps the SYNC; the numbering and the clock never break."""
    from helpers_canopen import period_frames

    r = OfflineReader(_cfg)
    ov = _cfg.sync.counter_overflow
    for k, c in enumerate(counters):
        frames = period_frames(_cfg, k, T0 + k * DT, counter=c)
        if drop[k]:
            frames = frames[:-1]  # the accelerometer's TPDO lost: incomplete
        for m in frames:
            r.feed(m)
    r.assembler.finish()
    samples = [s for s in r.poll() if not isinstance(s, HealthReport)]
    asm = r.assembler
    valid = [c for c in counters if 1 <= c <= ov]
    assert asm.malformed == len(counters) - len(valid)
    dups = sum(b == a for a, b in itertools.pairwise(valid))
    assert asm.duplicate_sync == dups and len(samples) == len(valid) - dups
    kept = [c for i, c in enumerate(valid) if i == 0 or c != valid[i - 1]]
    expected_lost = sum((b - (a % ov + 1)) % ov for a, b in itertools.pairwise(kept))
    assert asm.lost == expected_lost == sum(s.lost_before for s in samples)
    assert [s.sync for s in samples] == kept
    for a, b in itertools.pairwise(samples):
        assert b.seq - a.seq - 1 == b.lost_before and b.t >= a.t
    assert 0 <= asm.clock.bad_timestamp <= max(0, len(kept) - 1)


@FUZZ
@given(cob=st.integers(0, 0x7FF), data=st.binary(max_size=8))
def test_the_decode_table_refuses_what_it_cannot_decode_with_a_plain_error(cob, data):
    try:
        out = _table.decode(cob, data)
    except KeyError:
        assert cob not in _table.tpdos
        return
    except ValueError as e:
        assert "expected" in str(e) and len(data) != _table.tpdos[cob].length
        return
    assert set(out) == {c.key for c in _table.channels[_table.tpdos[cob].start:
                                                       _table.tpdos[cob].stop]}


# --------------------------------------------------------------------------------------
# EDS files canopen cannot parse

EDS = config_dir() / "eds" / "load_cell.eds"


def _with_eds(tmp_path, content: bytes):
    p = tmp_path / "cell_C.eds"
    p.write_bytes(content)
    raw = copy.deepcopy(_cfg.raw)
    raw["nodes"][2]["eds"] = str(p)
    return parse_config(raw, base_dir=config_dir())


def _partial_dummy(text: str) -> str:
    # canopen's import_eds fails when [DummyUsage] lists only some of Dummy0001…0007
    return "\n".join(line for line in text.splitlines() if not line.startswith("Dummy0005"))


@pytest.mark.parametrize("make", [
    lambda t: b"",
    lambda t: b"garbage [[[ not an eds\n",
    lambda t: t.encode()[: len(t) // 2],
    lambda t: b"\xff\xfe\x00\x81" * 100,
    lambda t: t.replace("[1800sub1]", "[1800sub1]\n[1800sub1]").encode(),
    lambda t: _partial_dummy(t).encode(),
    lambda t: t.replace("DataType=0x0008", "DataType=banana").encode(),
], ids=["empty", "garbage", "truncated", "binary", "duplicate-section", "partial-dummy",
        "bad-datatype"])
def test_an_eds_canopen_cannot_parse_is_a_one_line_error_naming_the_node(tmp_path, make):
    cfg = _with_eds(tmp_path, make(EDS.read_text()))
    with pytest.raises(ConfigError) as e:
        DecodeTable(cfg)
    msg = str(e.value)
    assert e.value.key == "nodes[2].eds" and "cell_C.eds" in msg and "fix:" in msg
    assert "\n" not in msg


@FUZZ_SMALL
@given(data=st.data())
def test_any_corruption_of_an_eds_is_either_usable_or_a_config_error(tmp_path_factory, data):
    raw = bytearray(EDS.read_bytes())
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "cut", "dup"]))
        i = data.draw(st.integers(0, len(raw) - 1))
        if op == "flip":
            raw[i] = data.draw(st.integers(0, 255))
        elif op == "cut":
            del raw[i:i + data.draw(st.integers(1, 200))]
        else:
            raw[i:i] = raw[i:i + data.draw(st.integers(1, 200))]
        if not raw:
            break
    cfg = _with_eds(tmp_path_factory.mktemp("eds"), bytes(raw))
    try:
        DecodeTable(cfg)
    except ConfigError as e:
        assert "fix:" in str(e) and "\n" not in str(e)


def test_the_service_refuses_a_bad_eds_before_starting_the_simulator(tmp_path):
    """`rsra run --sim` used to die with a traceback from inside the simulator's nodes."""
    folder = tmp_path / "rig"
    (folder / "eds").mkdir(parents=True)
    for p in (config_dir() / "eds").glob("*.eds"):
        (folder / "eds" / p.name).write_bytes(p.read_bytes())
    (folder / "eds" / "load_cell.eds").write_text("garbage [[[ not an eds\n")
    (folder / "rig.toml").write_text(default_config_path().read_text())
    r = subprocess.run([sys.executable, "-m", "rsra", "run", "--config", str(folder / "rig.toml"),
                        "--sim", "ground-test", "--speed", "max", "--duration", "1"],
                       capture_output=True, text=True, timeout=120, check=False,
                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "nodes[0].eds" in r.stderr and "fix:" in r.stderr


# --------------------------------------------------------------------------------------
# every config key, wrong: named, with a fix (extends tests/test_config.py to every leaf)

def _leaves(node, path=""):
    """(dotted path, value) of every scalar or list leaf of the default rig TOML."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, f"{path}.{k}" if path else k)
    elif isinstance(node, list) and node and all(isinstance(x, dict) for x in node):
        for i, v in enumerate(node):
            yield from _leaves(v, f"{path}[{i}]")
    else:
        yield path, node


def _set(raw, path, value):
    import re

    parts = re.findall(r"[^.\[\]]+|\[\d+\]", path)
    node = raw
    for p in parts[:-1]:
        node = node[int(p[1:-1])] if p.startswith("[") else node[p]
    last = parts[-1]
    if last.startswith("["):
        node[int(last[1:-1])] = value
    else:
        node[last] = value


RAW = tomllib.loads(default_config_path().read_text())
LEAVES = sorted(dict(_leaves(RAW)))


def _refused(raw):
    with pytest.raises(ConfigError) as e:
        parse_config(raw, source="rig.toml", base_dir=default_config_path().parent)
    return e.value


@pytest.mark.parametrize("path", LEAVES)
def test_every_key_of_the_wrong_type_is_named_with_a_fix(path):
    raw = copy.deepcopy(RAW)
    _set(raw, path, {"not": "a value"})  # a table: no leaf of the rig TOML takes one
    e = _refused(raw)
    assert e.key == path or e.key.startswith(path), (e.key, path)
    assert e.fix and "fix:" in str(e) and e.problem


NUMERIC = [p for p in LEAVES if isinstance(dict(_leaves(RAW))[p], (int, float))
           and not isinstance(dict(_leaves(RAW))[p], bool)]


@pytest.mark.parametrize("path", NUMERIC)
def test_every_number_that_is_not_finite_is_named_with_a_fix(path):
    raw = copy.deepcopy(RAW)
    _set(raw, path, float("nan"))
    e = _refused(raw)
    assert e.key == path or e.key.startswith(path), (e.key, path)
    assert "fix:" in str(e)


@pytest.mark.parametrize("table", sorted(k for k, v in RAW.items() if isinstance(v, dict)))
def test_an_unknown_key_in_any_table_is_named(table):
    raw = copy.deepcopy(RAW)
    raw[table]["surely_a_typo"] = 1
    e = _refused(raw)
    assert e.key == f"{table}.surely_a_typo" and "fix:" in str(e)
    # [calibration] is keyed by channel: a stray key there is a malformed entry
    assert ("unknown key" in str(e)) or (table == "calibration" and "table" in str(e))
