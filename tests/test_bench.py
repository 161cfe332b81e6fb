"""The benchmarks (bench/) run in their tiny configuration and write well-formed result lines.

Benchmarks are not tests: nothing here asserts a timing or a target being met — only that
every benchmark still runs, so none of them can rot, and that its lines carry what
docs/performance.md asks for (figure, peer, ratio, target, decision, machine, versions).
"""
from __future__ import annotations

import importlib
import json

import pytest

from bench.common import (
    MODULES,
    ResultWriter,
    check_line,
    latest_run,
    read_lines,
    render_results,
)


@pytest.mark.parametrize("module", MODULES)
def test_benchmark_runs_tiny(module, tmp_path, capsys):
    mod = importlib.import_module(f"bench.{module}")
    assert mod.main(["--tiny", "--out", str(tmp_path)]) == 0
    lines = read_lines(tmp_path / f"{module}.jsonl")
    assert lines, f"bench.{module} wrote no result line"
    for line in lines:
        check_line(line)
        assert line["bench"] == module and line["tiny"] is True
    printed = [json.loads(s) for s in capsys.readouterr().out.splitlines() if s.startswith("{")]
    assert [p["check"] for p in printed] == [ln["check"] for ln in lines]
    assert len({ln["run_id"] for ln in lines}) == 1


def test_check_line_rejects_malformed(tmp_path):
    w = ResultWriter("p2_filter_step", out_dir=tmp_path, echo=False)
    good = w.add("x", 1.0, "µs", target="≤ 1", met=True, peer="p", peer_figure=2.0,
                 ratio_value=2.0, ratio_is="peer/figure")
    check_line(good)
    for bad in ({**good, "met": None}, {**good, "figure": "fast"}, {**good, "target": ""},
                {**good, "peer": None}, {k: v for k, v in good.items() if k != "machine"}):
        with pytest.raises(ValueError):
            check_line(bad)


def test_results_table_from_latest_full_runs(tmp_path):
    old = ResultWriter("p3_batch", out_dir=tmp_path, echo=False)
    old.run_id = "20000101T000000Z-1"
    old.add("time_constant", 1.0, "samples/s", target="t", met=False)
    tiny = ResultWriter("p3_batch", out_dir=tmp_path, tiny=True, echo=False)
    tiny.add("time_constant", 3.0, "samples/s", target="t", met=True)
    new = ResultWriter("p3_batch", out_dir=tmp_path, echo=False)
    new.run_id = "20990101T000000Z-2"
    new.add("time_constant", 2_000_000.0, "samples/s", target="t", met=True,
            peer="loop", peer_figure=100_000.0, ratio_value=20.0, ratio_is="figure/peer")
    run = latest_run(read_lines(tmp_path / "p3_batch.jsonl"))
    assert [ln["figure"] for ln in run] == [2_000_000.0]
    text = render_results(tmp_path, tmp_path / "RESULTS.md", command="python -m bench.run_all")
    assert "2,000,000" in text and "20.0 (figure/peer)" in text
    assert "| p1_decode | — | not run |" in text
    assert (tmp_path / "RESULTS.md").read_text() == text
