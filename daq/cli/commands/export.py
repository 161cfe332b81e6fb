"""`rsra export`: files other tools open (docs/cli.md §14), one option per format of the
registry (daq.analysis.export_formats.EXPORT_FORMATS: a DBC of the bus, MCAP and Parquet of the
telemetry); this command names none of them.

Outputs are written by the one writer (daq.runtime.persistence.OutputFile): under a temporary
name beside the target and renamed only when complete, so a refused or failed export leaves no
partial file (and removes a --parquet folder it made); a device or a read pipe in place.
"""
from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO

from rsra.daq.analysis.export_formats import EXPORT_FORMATS, ExportJob, Records
from rsra.daq.runtime.persistence import OutputFile, OutputRefused

TELEMETRY_SUFFIXES = (".jsonl", ".json")


class _FormatOutputs(Mapping[str, str]):
    """Each registered format's option against the inputs (daq.cli.outputs): "file" or
    "folder", read from the registry when the parser is built."""

    def __getitem__(self, name: str) -> str:
        return EXPORT_FORMATS[name].output

    def __iter__(self) -> Iterator[str]:
        return iter(EXPORT_FORMATS)

    def __len__(self) -> int:
        return len(EXPORT_FORMATS)


OUTPUTS = _FormatOutputs()  # against the inputs (daq.cli.outputs)


def _options(telemetry: bool | None = None) -> list[str]:
    """``--<name> METAVAR`` of every format (``telemetry``: only those that need, or do not
    need, the telemetry)."""
    return [f"--{n} {f.metavar}" for n, f in EXPORT_FORMATS.items()
            if telemetry is None or f.telemetry == telemetry]


def _either(words: list[str], conj: str) -> str:
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} {conj} {words[-1]}"


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="write " + _either([f.title for f in EXPORT_FORMATS.values()], "or"),
        description=" ".join(f.description for f in EXPORT_FORMATS.values()) + " The "
        "telemetry comes from a `rsra replay --out` file (RESULTS.jsonl), or from recordings, "
        "which are replayed first exactly as `rsra replay` does.")
    common_options(p, units=False)
    p.add_argument("inputs", nargs="*", metavar="RESULTS.jsonl|LOG|DIR",
                   help="a telemetry file written by `rsra replay --out`, or recordings "
                   "(frame files or recording folders, as for `rsra replay`)")
    for option, fmt in EXPORT_FORMATS.items():
        p.add_argument(f"--{option}", metavar=fmt.metavar, default=None, help=fmt.help)
    return p


class _Staged:
    """The export's outputs, each an :class:`~rsra.daq.runtime.persistence.OutputFile` (the
    one writer: a regular file renamed into place when complete, a device or a read pipe
    written in place, anything else refused); ``commit`` makes them all, ``discard`` drops
    them (and a folder we made). The :class:`~rsra.daq.analysis.export_formats.Outputs` of
    every format."""

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

    def folder(self, target: Path, option: str) -> None:
        from rsra.daq.cli.options import UsageError

        if target.exists() and not target.is_dir():
            raise UsageError(f"{option} {target}: is a file; fix: give a folder")
        if not target.exists():
            try:
                target.mkdir()
            except OSError as e:
                raise UsageError(f"{option} {target}: cannot create ({e.strerror}); fix: "
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


def _inputs(args: argparse.Namespace) -> tuple[Path | None, list[str]]:
    """The telemetry file, or the recordings, the inputs name (both empty: none given)."""
    from rsra.daq.cli.options import UsageError
    from rsra.daq.bus.replay import ReplayError, expand

    if not args.inputs:
        return None, []
    tel = [p for p in args.inputs if Path(p).suffix.lower() in TELEMETRY_SUFFIXES]
    if tel and len(args.inputs) > 1:
        raise UsageError(f"{tel[0]}: a telemetry file among other inputs; fix: export "
                         "one telemetry file at a time, on its own")
    if tel:
        telemetry = Path(tel[0])
        if not telemetry.is_file():
            raise UsageError(f"{telemetry}: no such file; fix: give a file written by "
                             "`rsra replay --out`")
        return telemetry, []
    try:
        expand(args.inputs)
    except ReplayError as e:
        raise UsageError(f"{e}" + ("" if "fix:" in str(e) else (
            "; fix: give recordings (frame files or recording folders) or a "
            "RESULTS.jsonl written by `rsra replay --out`"))) from None
    return None, list(args.inputs)


def run(args: argparse.Namespace) -> int:
    from rsra.daq.analysis.export import ExportError
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.bus.replay import config_for

    chosen = [(f"--{n}", Path(getattr(args, n)), fmt) for n, fmt in EXPORT_FORMATS.items()
              if getattr(args, n, None)]
    if not chosen:
        raise UsageError(f"nothing to write; fix: give {_either(_options(), 'or')}")
    telemetry, logs = _inputs(args)
    if not args.inputs and any(fmt.telemetry for _, _, fmt in chosen):
        needy = [o.split()[0] for o in _options(telemetry=True)]
        raise UsageError(f"{_either(needy, 'and')} need the telemetry to export; fix: give a "
                         "RESULTS.jsonl from `rsra replay --out`, or recordings")
    cfg = config_for(logs, args.config, several="parts") if logs else load_rig(args.config)

    staged = _Staged()
    done: list[str] = []
    try:
        formats = [fmt(option, target, staged) for option, target, fmt in chosen]
        for f in formats:  # every output claimed before any work
            f.claim()
        with tempfile.TemporaryFile("w+", encoding="utf-8") as scratch:
            job = ExportJob(cfg, " ".join(args.inputs),
                            _records(cfg, telemetry, logs, scratch, args) if args.inputs
                            else None)
            for f in sorted(formats, key=lambda f: f.telemetry):  # the rig's first
                try:
                    done += f.write(job)
                except ExportError as e:
                    raise UsageError(str(e)) from None
        staged.commit()
    except BaseException:
        staged.discard()
        raise
    for line in done:
        print(line)
    return 0


def _records(cfg, telemetry: Path | None, logs: list[str], scratch, args) -> Records:
    """The telemetry records, read again from the start on every call: the telemetry
    file's, or those of the recordings replayed into ``scratch`` (once, at the first call);
    ExportError when there are none."""
    import json

    from rsra.daq.cli.options import UsageError
    from rsra.daq.analysis.export import ExportError, read_records

    replayed = False

    def records() -> Iterator[tuple[str, dict]]:
        nonlocal replayed
        if telemetry is not None:
            yield from read_records(telemetry)
            return
        if not replayed:
            _replay(cfg, logs, scratch, UsageError)
            replayed = True
        scratch.seek(0)
        for line in scratch:
            rec = json.loads(line)
            yield rec.pop("key"), rec

    def checked() -> Iterator[tuple[str, dict]]:
        first = records()
        head = next(first, None)
        if head is None:
            raise ExportError(f"{telemetry or ' '.join(args.inputs)}: no telemetry records; "
                              "fix: give a file written by `rsra replay --out`, or a "
                              "recording with samples")
        yield head
        yield from first

    return checked


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
