"""`rsra replay`: recordings through the same reader as the live service (cli.md, bus.md).

Writes one JSON object per published message with ``--out`` (``{"key": "channels", …}``,
``{"key": "health", …}``, in order, strict JSON), else prints a summary.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

from daq.config import RigConfig
from daq.reader import Reader


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from daq.cli import common_options

    p = sub.add_parser(
        name, help="feed recordings through the reader (and write the published records)",
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
    p.add_argument("--out", metavar="FILE.jsonl", default=None,
                   help='write every published record as one JSON object per line, '
                   '{"key": "channels"|"health", …payload} (strict JSON, null for missing '
                   'values); "-" for standard output')
    return p


def replay_records(cfg: RigConfig, logs: list[str], realtime: bool = False,
                   reader: Reader | None = None) -> Iterator[tuple[str, dict]]:
    """(key, payload) of every record a replay publishes, in order: ``channels`` per sample,
    ``health`` once a second of recorded time."""
    from daq.reader import HealthReport
    from daq.replay import replay

    for item in replay(cfg, logs, realtime=realtime, reader=reader):
        if isinstance(item, HealthReport):
            yield "health", item.payload
        else:
            yield "channels", item.channels_payload()


def run(args: argparse.Namespace) -> int:
    from daq.cli import UsageError
    from daq.jsonout import dumps
    from daq.replay import ReplayError, config_for, expand

    try:
        expand(args.logs)
    except ReplayError as e:
        raise UsageError(str(e)) from None
    cfg = config_for(args.logs, args.config)
    out = None
    if args.out == "-":
        out = sys.stdout
    elif args.out:
        try:
            out = open(Path(args.out), "w", encoding="utf-8")
        except OSError as e:
            raise UsageError(f"--out {args.out}: cannot write ({e.strerror})") from None
    counts = {"channels": 0, "health": 0}
    reader = Reader.offline(cfg)
    progress = _Progress(enabled=out is not sys.stdout and sys.stderr.isatty())
    try:
        for key, payload in replay_records(cfg, args.logs, args.realtime, reader):
            counts[key] = counts.get(key, 0) + 1
            if key == "health":
                progress.update(payload)
            if out is not None:
                out.write(dumps({"key": key, **payload}) + "\n")
    except (ValueError, OSError) as e:  # a corrupt or truncated log file
        raise UsageError(f"cannot read the recording: {e}") from None
    finally:
        progress.close()
        if out is not None and out is not sys.stdout:
            out.close()
    summary = _summary(counts, reader.health())
    print(summary, file=sys.stderr if out is sys.stdout else sys.stdout)
    return 0


def _summary(counts: dict, health: dict | None) -> str:
    s = f"replayed: {counts.get('channels', 0)} samples, {counts.get('health', 0)} health records"
    if health:
        b, sm = health["bus"], health["samples"]
        s += (f"; frames {b['frames']}, unknown {b['unknown']}, malformed {b['malformed']}, "
              f"error frames {b['errors']}; samples complete {sm['complete']}, incomplete "
              f"{sm['incomplete']}, lost {sm['lost']}")
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
