"""`rsra sweep`: the report's frequency-domain evaluation of a shake-test sweep (docs/cli.md §8;
report Phase I, Eq 1.3–1.5, Table I, Figures 4–18; daq/analysis/sweep.py)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


# what --out DIR receives (daq.analysis.sweep), checked against the inputs before any work
OUTPUTS = {"out": ("sweep_table.txt", "sweep.json", "sweep_transfer_functions.png",
                   "sweep_unmodelled_phase.png",
                   *(f"sweep_error_{a}.png" for a in ("X", "Y", "Z", "L", "M", "N")))}


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="frequency-domain evaluation of a shake-test sweep (report Phase I)",
        description="Replays a shake-test recording (candump .log, .blf, .asc, … or a recording "
        "folder) through the reader and evaluates the static rigid-body model against the "
        "reference balance, as the report's Phase I did (Eq 1.3-1.5): finds the excitation "
        "segments (axis, level) in the balance data, computes the transfer functions of the load "
        "cells, inertial loads, estimation error and reconstructed unmodelled load to the "
        "excitation (H1 estimator), and writes the estimation error against frequency per "
        "excitation axis beside the instrumentation-noise budget (Table I) and the unmodelled "
        "load's gain and phase relative to the excitation (Figure 18: near 180 deg = elastic). "
        "Uses the configured (nominal) angles, body axes.")
    common_options(p)
    p.add_argument("logs", nargs="+", metavar="LOG|DIR",
                   help="recording files (in the order given) or recording folders, with the "
                   "reference balance on the bus")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="folder for the PNG plots, sweep_table.txt and sweep.json (default: "
                   "<first recording>-sweep beside it)")
    return p


def _default_out(first: str) -> Path:
    p = Path(first)
    return p.parent / f"{p.name if p.is_dir() else p.stem}-sweep"


def _check_writable(out: Path) -> None:
    from rsra.daq.cli.options import UsageError

    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: is a file; give a folder")
    p = out
    while not p.exists():
        p = p.parent
    if not os.access(p, os.W_OK):
        raise UsageError(f"--out {out}: cannot create the folder (permission denied in {p}); "
                         "give a writable folder")


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.persistence import write_text_atomic
    from rsra.daq.bus.replay import ReplayError, config_for, expand
    from rsra.daq.analysis.sweep import sweep_json, sweep_table

    try:
        expand(args.logs)
    except ReplayError as e:
        raise UsageError(str(e)) from None
    out = Path(args.out) if args.out else _default_out(args.logs[0])
    _check_writable(out)  # created once the recording has been read: a bad one leaves nothing
    cfg = config_for(args.logs, args.config)
    data, result, plots = _analyse(args, cfg, out)
    table = sweep_table(result, args.units)
    write_text_atomic(out / "sweep_table.txt", table + "\n")
    write_text_atomic(out / "sweep.json", dumps(sweep_json(result, args.units)) + "\n")
    print(table)
    print(f"\nwrote {out / 'sweep_table.txt'}, {out / 'sweep.json'} and "
          f"{len(plots)} plots in {out}")
    _print_notes(result, data)
    return 0


def _analyse(args: argparse.Namespace, cfg, out: Path):
    """The recording replayed, analysed and plotted into ``out`` (created now): (data,
    result, plots); what cannot be read or analysed: one line (exit 2)."""
    from rsra.daq.cli.options import UsageError
    from rsra.daq.analysis.sweep import SweepError, analyse_sweep, load_sweep_data, plot_sweep

    status = _Status(sys.stderr.isatty())
    try:
        status.say("replaying the recording")
        try:
            data = load_sweep_data(cfg, args.logs)
        except SweepError as e:
            raise UsageError(f"{args.logs[0]}: {e}") from None
        except (ValueError, OSError) as e:  # a corrupt or truncated log file
            raise UsageError(f"cannot read the recording: {e}") from None
        status.say(f"analysing {len(data.t)} samples")
        try:
            result = analyse_sweep(cfg, data)
        except SweepError as e:
            raise UsageError(f"{args.logs[0]}: {e}") from None
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UsageError(f"--out {out}: cannot create the folder ({e.strerror}); give a "
                             "writable folder") from None
        status.say("plotting")
        plots = plot_sweep(result, out, args.units)
    finally:
        status.close()
    return data, result, plots


def _print_notes(result, data) -> None:
    """What was left out of the analysis and what was interpolated (stderr)."""
    if result.excluded:
        secs = sum(s.stop - s.start for s in result.excluded) / result.fs
        print(f"note: {len(result.excluded)} stretches of oscillating load ({secs:.1f} s) on "
              "several axes at once are not a shaker excitation and were left out",
              file=sys.stderr)
    if data.filled:
        print(f"note: {data.filled} of {len(data.t)} samples were missing or incomplete and "
              "were interpolated", file=sys.stderr)


class _Status:
    """A one-line progress indicator on a terminal (rich), silent otherwise."""

    def __init__(self, enabled: bool):
        self.st = None
        if enabled:
            from rich.console import Console

            self.st = Console(stderr=True).status("rsra sweep")
            self.st.start()

    def say(self, text: str) -> None:
        if self.st is not None:
            self.st.update(f"rsra sweep: {text} …")

    def close(self) -> None:
        if self.st is not None:
            self.st.stop()
