"""`rsra replay`: recordings through the same reader as the live service (docs/cli.md §6,
docs/bus.md §5).

Writes one JSON object per published message with ``--out`` (``{"key": "channels", …}``,
``{"key": "health", …}``, in order, strict JSON), else prints a summary.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rsra.daq.bus.health import Health


OUTPUTS = {"out": "file"}  # checked against the inputs before any work (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options
    from rsra.daq.cli.options import add_no_identification

    p = sub.add_parser(
        name, help="feed recordings through the reader and the estimator (and write every record)",
        description="Feeds recordings (candump .log, .blf, .asc, … files, or a recording "
        "folder written by `rsra run --record`) through the same reader as the live service: "
        "decoding by the EDS mapping (recordings that start mid-flight included), sample "
        "assembly by frame order, node health. As fast as possible unless --realtime. With a "
        "recording folder and no --config, the folder's own effective configuration is used.")
    common_options(p, units=False)
    p.add_argument("logs", nargs="+", metavar="LOG|DIR",
                   help="recording files (replayed in the order given) or recording folders")
    p.add_argument("--realtime", action="store_true",
                   help="pace the frames at their recorded timing (can.MessageSync)")
    p.add_argument("--streaming", action="store_true",
                   help="feed every frame one by one through the reader (the reference path; "
                   "by default the recording is read in blocks and the clean SYNC periods are "
                   "assembled per block, with the same records)")
    p.add_argument("--out", metavar="FILE.jsonl", default=None,
                   help='write every published record as one JSON object per line, '
                   '{"key": "channels"|"health", …payload} (strict JSON, null for missing '
                   'values); "-" for standard output')
    p.add_argument("--publish", action="store_true",
                   help="also publish every record over Zenoh (as the live service does)")
    from rsra.daq.runtime.foxglove_out import add_options as add_foxglove_options

    add_foxglove_options(p)
    p.add_argument("--recompute", action="store_true",
                   help="run the identification again (deterministically) instead of using "
                   "the recording's angle schedule")
    p.add_argument("--angles", metavar="STATE", default=None,
                   help="start from a saved posterior instead of the recording's")
    from rsra.daq.cli.options import add_accept_option

    add_accept_option(p)
    add_no_identification(p, help="neither the recorded angle schedule nor a recomputed "
                          "identification: the angles stay at the recording's starting angles "
                          "(or --angles) for the whole replay")
    p.add_argument("--zenoh-config", metavar="FILE", default=None, help="with --publish")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP",
                   help="with --publish (default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="with --publish")
    p.add_argument("--log-level", default="warning",
                   choices=("debug", "info", "warning", "error"), help="default warning")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.cli.options import setup_logging
    from rsra.daq.jsonout import dumps
    from rsra.daq.bus.replay import config_for
    from rsra.daq.runtime.service import Service, ServiceOptions

    setup_logging(args.log_level, None)
    if args.recompute and not args.identification:
        raise UsageError("--recompute and --no-identification contradict each other; give one")
    _check_recordings(args.logs)
    cfg = config_for(args.logs, args.config, several="parts")
    from rsra.daq.runtime.foxglove_out import check_option

    check_option(args)  # a taken port: refused before anything starts
    out: _LazyFile | TextIO | None = None
    if args.out == "-":
        out = sys.stdout
    elif args.out:
        out = _LazyFile(Path(args.out))
    opts = ServiceOptions(replay=list(args.logs), recompute=args.recompute, realtime=args.realtime,
                          streaming=args.streaming,
                          angles=args.angles, zenoh=args.publish,
                          accept_rig_mismatch=args.accept_rig_mismatch,
                          identification=args.identification,
                          zenoh_config=args.zenoh_config, zenoh_listen=args.zenoh_listen,
                          zenoh_connect=args.zenoh_connect, foxglove=args.foxglove,
                          foxglove_origins=args.foxglove_allow_origin)
    service = Service(cfg, opts)
    service.install_signal_handlers()
    progress = _Progress(enabled=out is not sys.stdout and sys.stderr.isatty())

    def sink(key: str, payload: dict) -> None:
        if key == "health":
            progress.update(payload)
        if out is not None:
            out.write(dumps({"key": key, **payload}) + "\n")

    service.add_sink(sink)
    try:
        summary = _replay(service, out, args.out)
    finally:
        progress.close()
        if out is not None and out is not sys.stdout:
            out.close()
    counts = summary.get("published", {})
    health = service.reader.health() if service.reader is not None else None
    text = _summary(counts, health)
    text += (f"; identification runs {summary.get('identification_runs', 0)} "
             f"(accepted {summary.get('accepted', 0)})")
    stream = sys.stderr if out is sys.stdout else sys.stdout
    print(text, file=stream)
    note = schedule_note(summary.get("angles_schedule"))
    if note:
        print(note, file=stream)
    return 0


def _check_recordings(logs: list[str]) -> None:
    """The recordings named exist and each is a recording with frames: refused (one line,
    exit 2) before any work."""
    from rsra.daq.bus.replay import ReplayError, check_readable, expand
    from rsra.daq.cli.options import UsageError

    try:
        check_readable(expand(logs))
    except ReplayError as e:
        raise UsageError(str(e)) from None


def _replay(service, out, name: str | None) -> dict:
    """The replay's summary; what was replayed kept in --out (``name``; Ctrl-C included),
    and before a damaged recording, what was replayed before it."""
    from rsra.daq.bus.replay import ReplayError

    try:
        summary = service.run()
        if isinstance(out, _LazyFile):
            out.commit()  # Ctrl-C included: what was replayed is kept
    except ReplayError as e:  # a damaged recording: what was replayed before it is kept
        if isinstance(out, _LazyFile) and out.records:
            out.commit()
            raise ReplayError(f"{e} ({name} holds the {out.records} records before "
                              "it)") from None
        raise
    return summary


class _LazyFile:
    """The --out file, written under a temporary name beside it (daq.cli.outputs) and renamed
    into place when the replay ends: a replay refused before it publishes anything (a damaged
    recording, a bad config, a Zenoh port in use) or one that fails leaves no empty file and
    leaves an existing one as it was. Where it cannot be written is checked at once."""

    def __init__(self, path: Path):
        from rsra.daq.cli.options import UsageError
        from rsra.daq.runtime.persistence import OutputFile

        self.path = path
        self.records = 0
        parent = path.parent if str(path.parent) else Path(".")
        if path.is_dir():
            raise UsageError(f"--out {path}: is a folder; fix: give a file name")
        if not parent.is_dir():
            raise UsageError(f"--out {path}: no folder {parent}; fix: create it or write elsewhere")
        if not os.access(path if path.exists() else parent, os.W_OK):
            raise UsageError(f"--out {path}: cannot write there (permission denied); fix: "
                             "write elsewhere")
        self.output = OutputFile(path)

    def write(self, text: str) -> None:
        try:
            self.output.open().write(text)
        except OSError as e:  # a full disk: exit 1, one line naming the file
            raise OSError(e.errno, f"--out cannot be written ({e.strerror or e})",
                          str(self.path)) from None
        self.records += 1

    def commit(self) -> None:
        """The records written so far become the file (an empty replay gives an empty file)."""
        self.output.commit()

    def close(self) -> None:
        self.output.discard()  # after commit: nothing left to remove


def schedule_note(sch: dict | None) -> str | None:
    """One line: where the replay's angles came from (recomputed, or the recorded schedule,
    and whether that schedule was empty or partial)."""
    if not sch:
        return None
    if sch["source"] == "off":
        return ("angles: identification off (--no-identification): the angles stayed at the "
                "starting angles")
    if sch["source"] == "recomputed":
        if sch["why"] == "--recompute":
            return "angles: identification recomputed (--recompute)"
        return ("angles: the recording holds no angle schedule (no angles.jsonl): "
                "identification recomputed")
    return _recorded_schedule_note(sch)


def _recorded_schedule_note(sch: dict) -> str:
    """The recorded schedule: empty, partial (where it ends) or whole; whether it holds the
    starting angles."""
    start = ("its starting angles" if sch["initial"] else
             "the configured initial angles or --angles (it holds no starting angles)")
    if sch["records"] == 0 or sch.get("last_applies_from_seq") is None:
        return (f"angles: {sch['file']} holds no angles record: the angles stayed at {start} "
                "(--recompute to identify)")
    n = sch["records"]
    text = f"angles: the recorded schedule, {n} record{'s' if n != 1 else ''}"
    if sch.get("partial"):
        text = (f"angles: the recorded schedule is partial: it ends at sample "
                f"{sch['last_applies_from_seq']} ({n} record{'s' if n != 1 else ''}), "
                f"{sch['uncovered_s']:.1f} s before the end of the recording; the last recorded "
                "angles held from there (--recompute to identify)")
    if not sch["initial"]:
        text += ("; it holds no starting angles: started from the configured initial angles "
                 "or --angles")
    return text


def _summary(counts: dict, health: Health | None) -> str:
    from rsra.daq.bus.reorder import REORDER_WINDOW

    s = f"replayed: {counts.get('channels', 0)} samples, {counts.get('health', 0)} health records"
    if health is not None:
        b, sm = health.bus, health.samples
        s += (f"; frames {b.frames}, unknown {b.unknown}, malformed {b.malformed}, "
              f"error frames {b.errors}; samples complete {sm.complete}, incomplete "
              f"{sm.incomplete}, lost {sm.lost}")
        if b.late:
            s += (f"; {b.late} frame{'s' if b.late != 1 else ''} late (further out of time "
                  f"order than the reorder window of {REORDER_WINDOW} frames: left out)")
        g = health.sync.gaps
        if g:
            s += (f"; {g} SYNC gap{'s' if g != 1 else ''} over 1 s (the longest "
                  f"{health.sync.gap_longest_s:.1f} s: the SYNC producer stalled or the bus "
                  "paused)")
        n = health.sync.discontinuities
        if n:
            s += (f"; time went back {n} time{'s' if n != 1 else ''} (a discontinuity: "
                  "recordings joined?), no sample invented")
    return s


class _Progress:
    """Recorded seconds replayed, on the terminal only (rich)."""

    def __init__(self, enabled: bool):
        self.live = None
        self.t0: float | None = None
        if enabled:
            from rich.progress import Progress, TextColumn, TimeElapsedColumn

            self.live = Progress(TextColumn("replaying: {task.description}"),
                                 TimeElapsedColumn(), transient=True)
            self.task = self.live.add_task("", total=None)
            self.live.start()

    def update(self, health: dict) -> None:
        if self.live is None or health.get("t") is None:
            return
        if self.t0 is None:
            self.t0 = health["t"]
        n = health["samples"]["complete"] + health["samples"]["incomplete"]
        self.live.update(self.task, description=f"{health['t'] - self.t0:.0f} s of recording, "
                         f"{n} samples")

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
