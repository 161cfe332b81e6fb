"""`rsra report`: plots and a summary from a replay's or a run's JSONL (docs/cli.md §7; daq/analysis/report.py)."""
from __future__ import annotations

import argparse
from pathlib import Path

from rsra.daq.cli.outputs import REPORT_FILES

OUTPUTS = {"out": REPORT_FILES}  # checked against the inputs before any work (daq.cli.outputs)
INPUTS = ("truth",)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="plots and a summary from published records (JSONL), with truth if any",
        description="Reads the records a run or replay wrote with --out (one JSON object per "
        "line, {\"key\": \"hub_loads\"|\"channels\"|\"angles\"|\"innovations\"|\"health\", …}) "
        "and, optionally, the simulator's truth file, and writes PNG plots and summary.md / "
        "summary.json: hub loads (filter H and static H_static) against truth with the static "
        "noise-budget band, angle estimates with their Cramér-Rao bands and accepted/rejected "
        "runs, the normalised innovations against their chi-square(6) band, and spectra of the "
        "load cells and hub loads with 1/rev and N_b/rev marked. Plots whose records are absent "
        "are skipped and the summary says so.")
    common_options(p)
    p.add_argument("results", metavar="RESULTS.jsonl",
                   help="records written by `rsra replay --out`, `rsra listen --json` or `rsra demo --report` (JSON lines)")
    p.add_argument("--truth", metavar="FILE.npz", default=None,
                   help="the simulator's truth file (rsra sim --truth): adds truth to the plots "
                   "and the errors to the summary; records are matched to truth samples by "
                   "time (nearest within half a sample), else by sample number")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="folder for the PNG plots and summary.md/summary.json (default: "
                   "<RESULTS>-report beside the results file)")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.analysis.report import ReportError, write_report
    from rsra.sim_bus.truth import read_truth

    results = Path(args.results)
    out = Path(args.out) if args.out else results.parent / f"{results.stem}-report"
    cfg = load_rig(args.config)
    try:
        rep = write_report(cfg, results, args.truth, out, units=args.units,
                           read_truth=read_truth)
    except ReportError as e:
        raise UsageError(str(e)) from None
    print(rep.markdown_brief())
    return 0
