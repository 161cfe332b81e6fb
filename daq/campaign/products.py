"""What a campaign task makes of one recording: a registry of products (:data:`PRODUCTS`).

A product is a name and a callable of a :class:`ProductContext` (the recording's source and
files, its effective rig, the options, a staging folder) that returns

* a pyarrow Table, or a list of row dicts: written as ``DIR/<name>/recording=<id>/part.parquet``
  with the recording's provenance in the file's metadata; or
* ``None``: it wrote its tables itself through :meth:`ProductContext.output` (the telemetry
  product: one table per record key, from one replay).

Every file goes under a temporary name and is renamed only when every product of the
recording succeeded, so a recording's outputs appear together or not at all (and a failed
re-run leaves the previous ones whole). A product adds what the manifest needs to
``ctx.stats``. Adding a product is one entry in :data:`PRODUCTS`.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from rsra.config.rig import RigConfig
from rsra.daq.runtime.persistence import AtomicOutput

#: the record keys of the telemetry product, each a table of the dataset
TELEMETRY_TABLES = ("hub_loads", "channels", "innovations", "angles", "health")


@dataclass
class ProductContext:
    #: the recording as named (a folder or a log file), and the files its replay reads
    source: Path
    paths: list[Path]
    #: the recording's effective rig
    cfg: RigConfig
    #: the campaign's options (JSON-ready; part of the output key)
    options: dict[str, Any]
    #: a folder of this task's own for scratch files (removed afterwards)
    staging: Path
    #: the dataset folder and the recording's id (its partition)
    dataset: Path
    recording: str
    #: provenance, written into every file's key-value metadata
    metadata: dict[str, str]
    #: what the manifest row gets (samples, lost_samples, accepted_runs, t_start, …)
    stats: dict[str, Any] = field(default_factory=dict)
    #: shown every assembled sample of the recording's one replay, in order (a product's
    #: :attr:`Product.prepare` adds itself here; the telemetry product's replay calls them)
    sample_observers: list[Callable[[Any], None]] = field(default_factory=list)
    #: … and every record it publishes (key, payload), for the products made of records
    record_sinks: list[Callable[[str, dict], None]] = field(default_factory=list)
    #: what a product's prepare keeps for its build, by product name
    state: dict[str, Any] = field(default_factory=dict)
    _outputs: dict[str, AtomicOutput] = field(default_factory=dict)

    def output(self, table: str) -> IO:
        """The binary file of ``table``'s partition of this recording (temporary until
        :meth:`commit`)."""
        target = self.dataset / table / f"recording={self.recording}" / "part.parquet"
        target.parent.mkdir(parents=True, exist_ok=True)
        out = self._outputs[table] = AtomicOutput(target, "wb")
        return out.open()

    def commit(self) -> list[str]:
        """Rename every file into place; returns the tables written."""
        for out in self._outputs.values():
            out.commit()
        return list(self._outputs)

    def discard(self) -> None:
        for out in self._outputs.values():
            out.discard()
        self._outputs.clear()


@dataclass(frozen=True)
class Product:
    name: str
    build: Callable[[ProductContext], Any]
    #: called for every product before any is built: a product that derives its table from
    #: the samples of the telemetry product's replay registers an observer here (a recording
    #: is read once)
    prepare: Callable[[ProductContext], None] | None = None
    #: whether the campaign's options ask for it (None: always)
    wanted: Callable[[dict[str, Any]], bool] | None = None


def telemetry(ctx: ProductContext) -> None:
    """The replay's records, one table per key, under the declared schemas of
    ``rsra export --parquet`` (daq.analysis.export)."""
    from rsra.daq.analysis.export import ParquetTables, parquet_schemas, vector_names
    from rsra.daq.campaign.replay import replay_to_tables

    names = vector_names(ctx.cfg)
    schemas = parquet_schemas(TELEMETRY_TABLES, names)
    outputs = {k: ctx.output(k) for k in schemas}
    tables = ParquetTables(schemas, outputs, names, metadata=ctx.metadata)
    try:
        ctx.stats.update(replay_to_tables(ctx.cfg, [ctx.source], tables, ctx.options,
                                          ctx.sample_observers, ctx.record_sinks))
    finally:
        tables.close(empty=True)
    ctx.stats["rows"] = dict(tables.counts)
    if tables.left_out:
        ctx.stats["left_out"] = {k: sorted(v) for k, v in tables.left_out.items()}


def write_table(ctx: ProductContext, name: str, result: Any) -> None:
    """A product's Table (or rows) into its partition, provenance in the metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = result if isinstance(result, pa.Table) else pa.Table.from_pylist(list(result))
    meta = {**(table.schema.metadata or {}),
            **{k.encode(): v.encode() for k, v in ctx.metadata.items()}}
    pq.write_table(table.replace_schema_metadata(meta), ctx.output(name))


def information_prepare(ctx: ProductContext) -> None:
    """The information product sees the telemetry product's replay (one read of the
    recording)."""
    from rsra.daq.analysis.information import InformationCollector

    collector = ctx.state["information"] = InformationCollector(ctx.cfg, ctx.recording)
    ctx.sample_observers.append(collector.observe)


def information(ctx: ProductContext) -> Any:
    """The recording's known-load information (daq.analysis.information: the moments of its
    windows), what `rsra campaign calibrate` pools across recordings, from the samples of
    the telemetry product's replay; the recording id is the partition's."""
    table = ctx.state["information"].table(ctx.source)
    return table.drop_columns(["recording"])


def survey_prepare(ctx: ProductContext) -> None:
    """The survey product collects the hub-load records of the telemetry product's replay
    (a recording is read once)."""
    from rsra.daq.analysis.survey_run import survey_collector

    collector = ctx.state["survey"] = survey_collector(ctx.cfg)
    ctx.record_sinks.append(collector.add)


def survey(ctx: ProductContext) -> Any:
    """The recording's loads survey at its own test points (daq.analysis.survey_run: marks,
    else the transient flag's edges), the long table of `rsra survey`, from the records of
    the telemetry product's replay."""
    from rsra.daq.analysis.survey_run import campaign_survey

    table, reason = campaign_survey(ctx.cfg, ctx.source, ctx.options,
                                    ctx.state["survey"])
    ctx.stats["survey_points"] = len(set(table.column("test_point").to_pylist()))
    if reason:
        ctx.stats["survey_reason"] = reason
    return table


#: the products of every recording, in order
PRODUCTS: list[Product] = [
    Product("telemetry", telemetry),
    Product("information", information, prepare=information_prepare),
    # the survey's Monte Carlo fatigue σ costs about as much as the replay: asked for
    Product("survey", survey, prepare=survey_prepare,
            wanted=lambda options: bool(options.get("survey"))),
]
