"""`rsra export`: files other tools open (docs/cli.md §14) — a DBC of the bus, MCAP and Parquet of the
telemetry (daq.export).

Outputs are written by the one writer (daq.runtime.persistence.OutputFile): under a temporary
name beside the target and renamed only when complete, so a refused or failed export leaves no
partial file (and removes a --parquet folder it made); a device or a read pipe in place.
"""
from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

from rsra.daq.runtime.persistence import OutputFile, OutputRefused

TELEMETRY_SUFFIXES = (".jsonl", ".json")


OUTPUTS = {"dbc": "file", "mcap": "file", "parquet": "folder"}  # against the inputs (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="write a DBC of the bus, or MCAP / Parquet files of the telemetry",
        description="--dbc FILE: a DBC of the rig's bus from its EDS files and config (every "
        "TPDO with float signals for REAL32 values, units and calibration; SYNC, heartbeats, "
        "EMCY), for cantools, SavvyCAN, PlotJuggler, asammdf. --mcap FILE / --parquet DIR: "
        "the telemetry of a `rsra replay --out` file (RESULTS.jsonl), or of recordings, which "
        "are replayed first exactly as `rsra replay` does: MCAP with one JSON topic per key "
        "(Foxglove, Lichtblick, PlotJuggler), Parquet with one table per key (pandas, polars, "
        "DuckDB).")
    common_options(p, units=False)
    p.add_argument("inputs", nargs="*", metavar="RESULTS.jsonl|LOG|DIR",
                   help="a telemetry file written by `rsra replay --out`, or recordings "
                   "(frame files or recording folders, as for `rsra replay`)")
    p.add_argument("--dbc", metavar="FILE", default=None, help="write a DBC of the bus")
    p.add_argument("--mcap", metavar="FILE", default=None, help="write the telemetry as MCAP")
    p.add_argument("--parquet", metavar="DIR", default=None,
                   help="write the telemetry as Parquet, one <key>.parquet per key in DIR")
    return p


class _Staged:
    """The export's outputs, each an :class:`~rsra.daq.runtime.persistence.OutputFile` (the
    one writer: a regular file renamed into place when complete, a device or a read pipe
    written in place, anything else refused); ``commit`` makes them all, ``discard`` drops
    them (and the --parquet folder when we made it)."""

    def __init__(self) -> None:
        self.files: list[OutputFile] = []
        self.made_dir: Path | None = None

    def file(self, target: Path, mode: str = "wb") -> IO:
        from rsra.daq.cli.options import UsageError

        out = OutputFile(target, mode)
        self.files.append(out)
        try:
            return out.open()
        except OutputRefused as e:
            raise UsageError(str(e)) from None
        except OSError as e:
            raise UsageError(f"{target}: cannot write there ({e.strerror}); fix: create the "
                             "folder or write elsewhere") from None

    def folder(self, target: Path) -> None:
        from rsra.daq.cli.options import UsageError

        if target.exists() and not target.is_dir():
            raise UsageError(f"--parquet {target}: is a file; fix: give a folder")
        if not target.exists():
            try:
                target.mkdir()
            except OSError as e:
                raise UsageError(f"--parquet {target}: cannot create ({e.strerror}); fix: "
                                 "create its parent folder or write elsewhere") from None
            self.made_dir = target

    def commit(self) -> None:
        for out in self.files:
            out.commit()
        self.files.clear()
        self.made_dir = None

    def discard(self) -> None:
        for out in self.files:
            out.discard()
        self.files.clear()
        if self.made_dir is not None:
            try:
                self.made_dir.rmdir()
            except OSError:
                pass
            self.made_dir = None


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.analysis.export import ExportError
    from rsra.daq.bus.replay import ReplayError, config_for, expand

    if not (args.dbc or args.mcap or args.parquet):
        raise UsageError("nothing to write; fix: give --dbc FILE, --mcap FILE or --parquet DIR")
    telemetry = None
    logs: list[str] = []
    if args.inputs:
        tel = [p for p in args.inputs if Path(p).suffix.lower() in TELEMETRY_SUFFIXES]
        if tel and len(args.inputs) > 1:
            raise UsageError(f"{tel[0]}: a telemetry file among other inputs; fix: export "
                             "one telemetry file at a time, on its own")
        if tel:
            telemetry = Path(tel[0])
            if not telemetry.is_file():
                raise UsageError(f"{telemetry}: no such file; fix: give a file written by "
                                 "`rsra replay --out`")
        else:
            try:
                expand(args.inputs)
            except ReplayError as e:
                raise UsageError(f"{e}" + ("" if "fix:" in str(e) else (
                    "; fix: give recordings (frame files or recording folders) or a "
                    "RESULTS.jsonl written by `rsra replay --out`"))) from None
            logs = list(args.inputs)
    elif args.mcap or args.parquet:
        raise UsageError("--mcap and --parquet need the telemetry to export; fix: give a "
                         "RESULTS.jsonl from `rsra replay --out`, or recordings")
    cfg = config_for(logs, args.config, several="parts") if logs else load_rig(args.config)

    staged = _Staged()
    done: list[str] = []
    try:
        dbc_out = staged.file(Path(args.dbc)) if args.dbc else None
        mcap_out = staged.file(Path(args.mcap)) if args.mcap else None
        if args.parquet:
            staged.folder(Path(args.parquet))
        if dbc_out is not None:
            from rsra.daq.analysis.export import build_dbc

            db = build_dbc(cfg)
            # as cantools.database.dump_file writes a DBC: cp1252, its own CRLF line ends
            dbc_out.write(db.as_dbc_string().encode("cp1252", errors="replace"))
            done.append(f"{args.dbc}: {len(db.messages)} messages, "
                        f"{sum(len(m.signals) for m in db.messages)} signals")
        if mcap_out is not None or args.parquet:
            with tempfile.TemporaryFile("w+", encoding="utf-8") as scratch:
                source = telemetry
                if telemetry is None:
                    _replay(cfg, logs, scratch, UsageError)
                try:
                    done += _telemetry(cfg, source, scratch, args, mcap_out, staged)
                except ExportError as e:
                    raise UsageError(str(e)) from None
        staged.commit()
    except BaseException:
        staged.discard()
        raise
    for line in done:
        print(line)
    return 0


def _replay(cfg, logs: list[str], scratch, usage) -> None:
    replay_to_jsonl(cfg, logs, scratch, usage)
    scratch.flush()


def replay_to_jsonl(cfg, logs: list[str], out, on_error: Callable[[str], Exception]
                    ) -> dict:
    """A recording through the service's replay path (the same as `rsra replay --out`):
    every published record as a JSON line into the text stream ``out``."""
    from can.io.blf import BLFParseError

    from rsra.config.rig import ConfigError
    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.service import Service, ServiceOptions
    from rsra.estimator.posterior import PosteriorFileError

    service = Service(cfg, ServiceOptions(replay=list(logs), zenoh=False))  # no publishing

    def sink(key: str, payload: dict) -> None:
        out.write(dumps({"key": key, **payload}) + "\n")

    service.add_sink(sink)
    try:
        return service.run()
    except PosteriorFileError as e:
        raise on_error(str(e)) from None
    except ConfigError:
        raise
    except (ValueError, OSError, BLFParseError) as e:  # a corrupt or truncated log file
        why = " ".join(str(e).split())
        raise on_error(f"cannot read the recording: {why}" + (
            "" if "fix:" in why else "; fix: give an undamaged recording")) from None


def _telemetry(cfg, source: Path | None, scratch, args, mcap_out: IO | None,
               staged: _Staged) -> list[str]:
    """Export the telemetry records (from ``source``, or the replayed ``scratch`` stream)."""
    import json

    from rsra.daq.analysis.export import (
        ExportError,
        parquet_schemas,
        read_records,
        vector_names,
        write_mcap,
        write_parquet,
    )

    def records():
        if source is not None:
            yield from read_records(source)
            return
        scratch.seek(0)
        for line in scratch:
            rec = json.loads(line)
            yield rec.pop("key"), rec

    if next(records(), None) is None:
        raise ExportError(f"{source or ' '.join(args.inputs)}: no telemetry records; fix: give a "
                          "file written by `rsra replay --out`, or a recording with samples")
    out = []
    if mcap_out is not None:
        meta = {"rig": cfg.rig_name, "source": " ".join(args.inputs),
                "units": "SI: N, N·m, m/s², rad, rad/s; t in UNIX seconds (docs/telemetry.md)"}
        counts = write_mcap(records(), mcap_out, cfg.telemetry.prefix, metadata=meta)
        out.append(f"{args.mcap}: " + ", ".join(f"{k} {n}" for k, n in counts.items()))
    if args.parquet:
        names = vector_names(cfg)
        keys = list(dict.fromkeys(k for k, _ in records()))
        # declared schemas (independent of the data); a pass over the data only for keys
        # rsra does not publish
        schemas = parquet_schemas(keys, names, records())
        folder = Path(args.parquet)
        paths = {k: staged.file(folder / f"{k}.parquet") for k in schemas}
        left_out: dict[str, set[str]] = {}
        counts = write_parquet(records(), schemas, paths,  # type: ignore[arg-type]
                               names, left_out=left_out)  # (file objects: pyarrow takes either)
        out.append(f"{args.parquet}: " + ", ".join(f"{k}.parquet {n} rows"
                                                   for k, n in counts.items()))
        for k, cols in left_out.items():
            out.append(f"{args.parquet}: {k}: values of undeclared fields left out: "
                       f"{', '.join(sorted(cols)[:8])}{' …' if len(cols) > 8 else ''}")
    return out
