"""The file formats `rsra export` writes, in a registry (the shape of python-can's
``MESSAGE_WRITERS``): each format is one :class:`ExportFormat` subclass and one entry in
:data:`EXPORT_FORMATS`, which gives the command its option (``--<name> FILE|DIR``), the
check of that output against the inputs, its help and what it writes. The command
(daq.cli.commands.export) names no format itself.

A format writes from the rig alone (``telemetry = False``: the DBC of the bus) or from the
telemetry records, ``(key, payload)`` pairs read again from the start on every call of
:attr:`ExportJob.records` (the lines of a `rsra replay --out` file, or of recordings
replayed first). Its outputs go through the command's staging (:class:`Outputs`): a file
renamed into place only when the whole export succeeded, a folder removed again if the
export made it and failed.

This module imports no writer library at import (the command line builds its options from
it): each format imports what it writes with when it writes.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, ClassVar, Protocol

if TYPE_CHECKING:
    from rsra.config.rig import RigConfig

Records = Callable[[], Iterator[tuple[str, dict]]]


class Outputs(Protocol):
    """Where a format's outputs are claimed (the command's staging)."""

    def file(self, target: Path, mode: str = "wb") -> IO:
        """A file opened for writing, made whole at the end of a successful export."""
        ...

    def folder(self, target: Path, option: str) -> None:
        """A folder to write files into (made if missing; ``option`` names it in errors)."""
        ...


@dataclass(frozen=True)
class ExportJob:
    """What one export writes from."""

    #: the rig (the recording's own, or --config)
    cfg: RigConfig
    #: the inputs as the user named them (provenance in the files' metadata)
    source: str
    #: the telemetry records, from the start on every call; None when no input was given
    records: Records | None


class ExportFormat(ABC):
    """One format: its option (``--<key>`` of its :data:`EXPORT_FORMATS` entry) writes
    ``target``. :meth:`claim` takes the output before any work (a refused target stops the
    export before it reads anything); :meth:`write` writes it and returns the lines the
    command prints."""

    #: what it writes, in the command's help ("a DBC of the bus")
    title: ClassVar[str]
    #: the option's argument
    metavar: ClassVar[str] = "FILE"
    #: what the argument is against the inputs (daq.cli.outputs): "file" or "folder"
    output: ClassVar[str] = "file"
    #: the option's help
    help: ClassVar[str]
    #: its sentence in the command's description
    description: ClassVar[str]
    #: written from the telemetry records (True) or from the rig alone (False)
    telemetry: ClassVar[bool] = True

    def __init__(self, option: str, target: Path, outputs: Outputs):
        #: the option that asked for it ("--dbc")
        self.option = option
        #: what the option named
        self.target = target
        #: the command's staging
        self.outputs = outputs
        #: the claimed file (file formats), after :meth:`claim`
        self.out: IO | None = None

    def claim(self) -> None:
        """Take the output: a file opened for writing, or a folder made."""
        if self.output == "folder":
            self.outputs.folder(self.target, self.option)
        else:
            self.out = self.outputs.file(self.target)

    @abstractmethod
    def write(self, job: ExportJob) -> list[str]:
        """Write the output; the lines saying what it holds."""


class DbcFormat(ExportFormat):
    """A DBC of the rig's bus (daq.analysis.export.build_dbc)."""

    title = "a DBC of the bus"
    help = "write a DBC of the bus"
    description = ("--dbc FILE: a DBC of the rig's bus from its EDS files and config (every "
                   "TPDO with float signals for REAL32 values, units and calibration; SYNC, "
                   "heartbeats, EMCY), for cantools, SavvyCAN, PlotJuggler, asammdf.")
    telemetry = False

    def write(self, job: ExportJob) -> list[str]:
        from rsra.daq.analysis.export import build_dbc

        assert self.out is not None
        db = build_dbc(job.cfg)
        # as cantools.database.dump_file writes a DBC: cp1252, its own CRLF line ends
        self.out.write(db.as_dbc_string().encode("cp1252", errors="replace"))
        return [f"{self.target}: {len(db.messages)} messages, "
                f"{sum(len(m.signals) for m in db.messages)} signals"]


class McapFormat(ExportFormat):
    """The telemetry as MCAP (daq.analysis.export.write_mcap)."""

    title = "an MCAP file of the telemetry"
    help = "write the telemetry as MCAP"
    description = ("--mcap FILE: MCAP with one JSON topic per key (Foxglove, Lichtblick, "
                   "PlotJuggler).")

    def write(self, job: ExportJob) -> list[str]:
        from rsra.daq.analysis.export import write_mcap

        assert self.out is not None and job.records is not None
        meta = {"rig": job.cfg.rig_name, "source": job.source,
                "units": "SI: N, N·m, m/s², rad, rad/s; t in UNIX seconds (docs/telemetry.md)"}
        counts = write_mcap(job.records(), self.out, job.cfg.telemetry.prefix, metadata=meta)
        return [f"{self.target}: " + ", ".join(f"{k} {n}" for k, n in counts.items())]


class ParquetFormat(ExportFormat):
    """The telemetry as Parquet, one table per key under its declared schema
    (daq.analysis.export.parquet_schemas, write_parquet)."""

    metavar = "DIR"
    output = "folder"
    title = "Parquet files of the telemetry"
    help = "write the telemetry as Parquet, one <key>.parquet per key in DIR"
    description = "--parquet DIR: Parquet with one table per key (pandas, polars, DuckDB)."

    def write(self, job: ExportJob) -> list[str]:
        from rsra.daq.analysis.export import parquet_schemas, vector_names, write_parquet

        records = job.records
        assert records is not None
        names = vector_names(job.cfg)
        keys = list(dict.fromkeys(k for k, _ in records()))
        # declared schemas (independent of the data); a pass over the data only for keys
        # rsra does not publish
        schemas = parquet_schemas(keys, names, records())
        paths = {k: self.outputs.file(self.target / f"{k}.parquet") for k in schemas}
        left_out: dict[str, set[str]] = {}
        counts = write_parquet(records(), schemas, paths,  # type: ignore[arg-type]
                               names, left_out=left_out)  # (file objects: pyarrow takes either)
        out = [f"{self.target}: " + ", ".join(f"{k}.parquet {n} rows" for k, n in counts.items())]
        for k, cols in left_out.items():
            out.append(f"{self.target}: {k}: values of undeclared fields left out: "
                       f"{', '.join(sorted(cols)[:8])}{' …' if len(cols) > 8 else ''}")
        return out


#: The formats `rsra export` writes, by option name: one entry per format.
EXPORT_FORMATS: dict[str, type[ExportFormat]] = {
    "dbc": DbcFormat,
    "mcap": McapFormat,
    "parquet": ParquetFormat,
}
