"""The one JSON-lines reader (daq.jsonlines) under `rsra report`, `rsra export` and the replay
of a recording's angles.jsonl: every line bounded, a bad line the caller's to refuse or skip."""
import json
import logging

import pytest

from rsra.daq.jsonlines import json_lines


def _lines(path, max_chars=None):
    bad: list[tuple[int, str]] = []
    kw = {} if max_chars is None else {"max_chars": max_chars}
    good = list(json_lines(path, lambda n, why: bad.append((n, why)), **kw))
    return good, bad


def test_good_blank_and_bad_lines(tmp_path):
    p = tmp_path / "r.jsonl"
    p.write_bytes(b'{"key": "a", "x": 1}\n\n  \n[1, 2]\nnot json\n{"b": "\xff"}\n'
                  + b"[" * 100_000 + b"\n" + b"7" * 5000 + b"\n" + b'{"last": true}')
    good, bad = _lines(p)
    assert good == [(1, {"key": "a", "x": 1}), (4, [1, 2]), (6, {"b": "\ufffd"}),
                    (9, {"last": True})]
    assert [n for n, _ in bad] == [5, 7, 8]
    assert "not a JSON line" in bad[0][1] and "too deep" in bad[1][1]


def test_an_over_long_line_is_never_held_whole(tmp_path):
    p = tmp_path / "long.jsonl"
    p.write_text('{"a": 1}\n' + json.dumps({"x": "y" * 10_000}) + '\n{"b": 2}\n' + "z" * 25_000)
    good, bad = _lines(p, max_chars=1000)
    assert good == [(1, {"a": 1}), (3, {"b": 2})]
    assert bad == [(2, "a line longer than 1000 characters"),
                   (4, "a line longer than 1000 characters")]
    exact = tmp_path / "exact.jsonl"  # a line of exactly the bound (its newline beyond) is read
    exact.write_text(json.dumps({"x": "y" * (1000 - 9)}) + "\n")
    assert [n for n, _ in _lines(exact, max_chars=1000)[0]] == [1]


def test_the_callers_refuse_or_skip_a_bad_line(tmp_path, caplog):
    from rsra.daq.analysis.export import ExportError, read_records
    from rsra.daq.analysis.report import ReportError, load_records
    from rsra.daq.runtime.sources import read_angles_schedule

    p = tmp_path / "r.jsonl"
    p.write_text('{"key": "health"}\n{"nokey": 1}\n')
    with pytest.raises(ExportError, match=r"r.jsonl:2: a record without a \"key\"; fix:"):
        list(read_records(p))
    with pytest.raises(ReportError, match=r"r.jsonl line 2: not a JSON record"):
        load_records(p)
    p.write_text('{"key": "health"}\n{"key": ["not", "a", "name"]}\n')
    with pytest.raises(ReportError, match=r"line 2"):  # (was a TypeError: a list as a dict key)
        load_records(p)
    angles = tmp_path / "angles.jsonl"
    angles.write_text('{"initial": true, "alpha_all": [0.1]}\n{"applies_from_s')  # cut off
    with caplog.at_level(logging.WARNING):
        initial, records = read_angles_schedule(tmp_path)
    assert initial == {"initial": True, "alpha_all": [0.1]} and records == []
    assert "angles.jsonl:2: unreadable angles record skipped" in caplog.text
