"""Files other tools open: a DBC of the bus, MCAP and Parquet of the telemetry (`rsra export`).

* :func:`build_dbc` — a cantools database of the rig's bus, built from the same EDS-driven
  decode tables as the reader (daq.decoder): every TPDO of every configured node with its
  COB-ID, layout, data types (REAL32 as float signals), calibration and units, the SYNC
  with its counter, heartbeats and EMCY. So a candump log decodes in cantools, SavvyCAN,
  PlotJuggler or asammdf to the values the reader decodes.
* :func:`write_mcap` / :func:`write_parquet` — telemetry records (``{"key": …, …payload}``,
  the lines of ``rsra replay --out``) to MCAP (JSON messages with JSON schemas, log times
  from the acquisition clock) and to Parquet (one table per key, typed columns, units in the
  schema metadata). Both schemas are declared once per key (:data:`FIELDS`, with the rig's
  names for the Parquet columns: :func:`declared_columns`), never taken from the data, so
  the files of two recordings of a rig have the same schemas and concatenate.

Field names, types and units of the payloads: :data:`FIELDS`, kept equal to the tables of
docs/telemetry.md by tests/test_export.py.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from rsra.config.devices import MILLI_G, device_profile
from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import (
    STATUS_FAULT,
    STATUS_OVERRANGE,
    DecodeTable,
    od_variable,
)
from rsra.config.units import AXIS_KIND
from rsra.daq.jsonlines import json_lines
from rsra.daq.runtime.schema import FIELDS, VEC6, json_schema, log_time_ns  # noqa: F401 - FIELDS re-exported

AXES = ("X", "Y", "Z", "L", "M", "N")
AXIS_UNIT = {"force": "N", "moment": "N·m"}

# CiA 303-2 unit codes (numerator byte of a CiA 404 "physical unit" object such as 0x6131)
CIA_303_2_UNITS = {0x00: "", 0x01: "m", 0x02: "kg", 0x03: "s", 0x10: "rad", 0x20: "Hz",
                   0x21: "N", 0x22: "Pa", 0x23: "J", 0x24: "W"}
NMT_STATES = {0: "boot-up", 4: "stopped", 5: "operational", 127: "pre-operational"}
COB_EMCY = 0x080
COB_HEARTBEAT = 0x700


class ExportError(ValueError):
    """Input that cannot be exported (one line, names the input and the fix)."""


def _ident(text: str) -> str:
    """A DBC identifier (C identifier) from a node/channel name."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return s if re.match(r"[A-Za-z_]", s) else f"n_{s}"


def eds_unit(od, index: int, sub: int) -> str | None:
    """The unit a CiA 404 physical-unit object (index+1, e.g. 0x6131 for 0x6130) gives for
    ``index:sub``, or None when the EDS has none or an unknown code."""
    try:
        code = od[index + 1][sub].default
    except (KeyError, TypeError):
        return None
    if not isinstance(code, int) or code & 0xFF00FFFF:  # only 10^0 and no denominator
        return None
    return CIA_303_2_UNITS.get((code >> 16) & 0xFF)


def build_dbc(cfg: RigConfig, table: DecodeTable | None = None):
    """A :class:`cantools.database.can.Database` of the rig's bus (see the module doc)."""
    from cantools.database.can import Database, Message, Node

    table = table or DecodeTable(cfg)
    period_ms = max(1, round(1000.0 / cfg.sample_rate_hz))
    messages: list = []
    nodes = [Node(name="rsra", comment="the service: CANopen master and SYNC producer")]
    for nl in table.nodes:
        node = _ident(nl.name)
        nodes.append(Node(name=node, comment=f"{nl.role}, node id {nl.node_id}, EDS "
                                             f"{Path(nl.eds).name}"))
        for lay in nl.tpdos:
            messages.append(Message(
                frame_id=lay.cob_id, name=_ident(f"{nl.name}_TPDO{lay.number}"),
                length=lay.length, signals=_tpdo_signals(nl, lay, table), senders=[node],
                send_type="Cyclic", cycle_time=period_ms,
                comment=f"TPDO{lay.number} of {nl.name} (on SYNC)"))
        messages += _node_messages(nl, node, cfg.heartbeat.producer_ms)
    messages.append(_sync_message(cfg, period_ms))
    messages.sort(key=lambda m: m.frame_id)
    return Database(messages=messages, nodes=nodes,
                    version=f"rsra rig {cfg.rig_name}")


def _tpdo_signals(nl, lay, table: DecodeTable) -> list:
    """The signals of one TPDO, in its mapping's order (a dummy entry is padding)."""
    profile = device_profile(nl.role)
    signals = []
    bit = 0
    codes = iter(lay.codes)
    entries = iter(range(lay.start, lay.stop))
    for e in lay.mapping:
        index, sub, bits = e >> 16, (e >> 8) & 0xFF, e & 0xFF
        if 0x0001 <= index <= 0x0007:  # dummy mapping: padding
            bit += bits
            continue
        code, c = next(codes), table.channels[next(entries)]
        signals.append(_signal(nl, c, code, index, sub, bit, profile))
        bit += signals[-1].length
    return signals


def _signal(nl, c, code: str, index: int, sub: int, bit: int, profile):
    """The signal of channel ``c`` (object ``index:sub``, struct code ``code``) at ``bit``:
    a status byte by its flags, a value by its calibration and unit."""
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    comment = (f"0x{index:04X}:{sub} {od_variable(nl.od, index, sub).name}"
               f"{'; bit 0 over-range, bit 1 sensor fault' if c.is_status else ''}")
    if c.wrap is not None:
        comment += "; 0..2^bits = 0..2pi"
    if c.is_status:
        conv = BaseConversion.factory(scale=1, offset=0, choices=_STATUS_CHOICES)  # type: ignore[arg-type]  # cantools annotates OrderedDict, documents and reads any dict
        unit = ""
    else:
        conv = BaseConversion.factory(scale=c.gain * c.scale, offset=c.offset,
                                      is_float=code in "fd")
        unit, comment = _value_unit(nl, c, index, sub, profile), comment + _count_note(c)
    return Signal(name=_ident(f"{nl.name}_{c.name}"), start=bit, length=8 * _struct_size(code),
                  byte_order="little_endian", is_signed=code in "bhiqfd" and code != "?",
                  conversion=conv, unit=unit or None, comment=comment, receivers=["rsra"])


def _value_unit(nl, c, index: int, sub: int, profile) -> str:
    """A value's unit: the EDS's physical-unit object, else the device profile's ('' none)."""
    known = profile.at(index, sub)
    return eds_unit(nl.od, index, sub) or (known.unit if known else "")


def _count_note(c) -> str:
    """An accelerometer axis counted in milli-g says so."""
    return "; 1 count = 1 mg" if c.name in ("x", "y", "z") and c.scale == MILLI_G else ""


_STATUS_CHOICES = {0: "ok", STATUS_OVERRANGE: "over-range", STATUS_FAULT: "sensor fault",
                   STATUS_OVERRANGE | STATUS_FAULT: "over-range and sensor fault"}


def _node_messages(nl, node: str, heartbeat_ms: int) -> list:
    """A node's heartbeat and EMCY messages."""
    from cantools.database.can import Message, Signal
    from cantools.database.conversion import BaseConversion

    return [Message(
        frame_id=COB_HEARTBEAT + nl.node_id, name=_ident(f"{nl.name}_heartbeat"), length=1,
        senders=[node], cycle_time=heartbeat_ms, comment="NMT heartbeat",
        signals=[Signal(name=_ident(f"{nl.name}_nmt_state"), start=0, length=7,
                        conversion=BaseConversion.factory(choices=dict(NMT_STATES)),  # type: ignore[arg-type]  # cantools annotates OrderedDict, documents and reads any dict
                        receivers=["rsra"])]), Message(
        frame_id=COB_EMCY + nl.node_id, name=_ident(f"{nl.name}_EMCY"), length=8,
        senders=[node], comment="emergency (CiA 301)", signals=[
            Signal(name=_ident(f"{nl.name}_emcy_code"), start=0, length=16,
                   receivers=["rsra"]),
            Signal(name=_ident(f"{nl.name}_emcy_register"), start=16, length=8,
                   receivers=["rsra"]),
            Signal(name=_ident(f"{nl.name}_emcy_info"), start=24, length=40,
                   receivers=["rsra"], comment="manufacturer-specific bytes")])]


def _sync_message(cfg: RigConfig, period_ms: int):
    """The SYNC, with its counter byte when the rig counts."""
    from cantools.database.can import Message, Signal

    overflow = cfg.sync.counter_overflow
    signals = [Signal(name="SYNC_counter", start=0, length=8,
                      comment=f"1..{overflow}, then 1 again")] if overflow else []
    return Message(
        frame_id=cfg.sync.cob_id, name="SYNC", length=1 if overflow else 0, signals=signals,
        senders=["rsra"] if cfg.sync.producer == "service" else None, send_type="Cyclic",
        cycle_time=period_ms, comment=f"CANopen SYNC: one sample per SYNC, "
                                      f"{cfg.sample_rate_hz:g} Hz")


def _struct_size(code: str) -> int:
    import struct

    return struct.calcsize("<" + code)


def dbc_text(cfg: RigConfig) -> str:
    """The DBC file text of :func:`build_dbc` (cantools' own writer)."""
    return build_dbc(cfg).as_dbc_string()


# -- telemetry records (JSONL of `rsra replay --out`) ------------------------------------------
def read_records(path: Path) -> Iterator[tuple[str, dict]]:
    """(key, payload) of every line of a telemetry JSONL file; ExportError on a bad line."""
    def bad(n: int, why: str) -> NoReturn:
        raise ExportError(f"{path}:{n}: {why}; fix: give a file written by `rsra replay --out`")

    try:
        for n, rec in json_lines(path, bad):
            if not isinstance(rec, dict) or not isinstance(rec.get("key"), str):
                bad(n, 'a record without a "key"')
            key = rec.pop("key")
            yield key, rec
    except OSError as e:
        raise ExportError(f"{path}: cannot read ({e.strerror}); fix: check the path and "
                          "its permissions") from None


def write_mcap(records: Iterable[tuple[str, dict]], out, prefix: str,
               metadata: dict[str, str] | None = None) -> dict[str, int]:
    """Write the records to an MCAP stream ``out`` (binary file object): one channel per key
    (topic ``<prefix>/<key>``, JSON messages, JSON schema), log and publish time from the
    acquisition clock. Returns the message count per key."""
    from mcap.writer import Writer

    from rsra.daq.jsonout import dumps

    w = Writer(out)
    w.start(profile="", library="rsra")
    channels: dict[str, int] = {}
    counts: dict[str, int] = {}
    last = 0
    for key, payload in records:
        cid = channels.get(key)
        if cid is None:
            sch = json_schema(key) if key in FIELDS else {"type": "object"}
            sid = w.register_schema(name=f"rsra.{key}", encoding="jsonschema",
                                    data=json.dumps(sch).encode())
            cid = channels[key] = w.register_channel(
                topic=f"{prefix}/{key}", message_encoding="json", schema_id=sid)
        last = log_time_ns(payload, last)
        seq = payload.get("seq")
        w.add_message(cid, log_time=last, publish_time=last, data=dumps(payload).encode(),
                      sequence=seq if isinstance(seq, int) and 0 <= seq < 2**32 else 0)
        counts[key] = counts.get(key, 0) + 1
    if metadata:
        w.add_metadata("rsra", metadata)
    w.finish()
    return counts


# -- Parquet: one table per key, flat typed columns ------------------------------------------
_VEC6_PATHS = ("H", "H_static", "sigma_angles", "sigma_filter", "I", "known_H", "e")
def _components(key: str, path: str, value: list, payload: dict,
                names: dict[str, tuple[str, ...]]) -> tuple[str, ...] | None:
    """Names of the elements of a list field that becomes one column per element."""
    if path in _VEC6_PATHS:
        return AXES if len(value) == 6 else None
    by_key = _COMPONENTS_BY_KEY.get(key)
    return by_key(path, value, payload, names) if by_key else None


def _channel_components(path: str, value: list, payload: dict,
                        names: dict[str, tuple[str, ...]]) -> tuple[str, ...] | None:
    """Cells, accelerometers and external loads by the rig's names; an accelerometer's x, y, z."""
    if path in ("T", "accel", "drive"):
        return _if_sized(names.get(path, ()), value)
    return ("x", "y", "z") if path.startswith("accel.") and len(value) == 3 else None


def _angle_components(path: str, value: list, payload: dict,
                      names: dict[str, tuple[str, ...]]) -> tuple[str, ...] | None:
    """The angles by the names the record gives them."""
    if path in ("alpha", "sigma_cr", "sigma_cr_corrected", "drift.rate", "drift.rate_sigma"):
        return _if_sized(tuple(payload.get("names") or ()), value)
    return None


def _if_sized(names: tuple[str, ...], value: list) -> tuple[str, ...] | None:
    return names if len(names) == len(value) else None


_COMPONENTS_BY_KEY = {"channels": _channel_components, "angles": _angle_components}


def flatten(key: str, payload: dict, names: dict[str, tuple[str, ...]]) -> dict[str, Any]:
    """One row: nested objects and named vectors as dotted columns (``H.X``, ``T.A``,
    ``nodes.cell_A.state``); lists of objects (EMCY histories) as JSON text."""
    row: dict[str, Any] = {}

    def walk(path: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{path}.{k}" if path else str(k), x)
        elif isinstance(v, list) and (comp := _components(key, path, v, payload, names)):
            cols: Sequence[str | None] = comp
            if key == "angles":  # by name (the rig's angles), and as the list in `names` order
                row[path] = v
                known = names.get("angles")
                cols = [c if not known or c in known else None for c in comp]
            for c, x in zip(cols, v):
                if c is not None:
                    walk(f"{path}.{c}", x)
        elif isinstance(v, list) and any(isinstance(x, dict) for x in v):
            row[path] = json.dumps(v)
        else:
            row[path] = v

    walk("", payload)
    if key == "angles":
        row.update(_sigma_deg(payload, names.get("angles")))
        row[ADVICE_TEXT] = _advice_text(payload)
    return row


ADVICE_TEXT = "advice_text"  # the angles table's column: the advice as the log says it


def _advice_text(payload: dict) -> str | None:
    """The sentence of a filter-error record's ``advice`` (estimator.flight_advice), None
    where the record has none."""
    from rsra.estimator.flight_advice import advice_summary

    names = payload.get("names")
    return advice_summary(payload.get("advice"),
                          len(names) if isinstance(names, list) and names else None)


SIGMA_DEG = "sigma_deg"  # the angles table's column prefix: each angle's posterior σ in degrees


def _sigma_deg(payload: dict, known: Sequence[str] | None) -> dict[str, float | None]:
    """``sigma_deg.<angle>``: √P_ii of the record's posterior covariance, in degrees, for each
    of the rig's angles the record names (None where P is missing or not a variance)."""
    names, P = payload.get("names"), payload.get("P")
    if not isinstance(names, list) or not isinstance(P, list) or len(P) != len(names):
        return {}
    return {f"{SIGMA_DEG}.{name}": _sigma_deg_of(P[i], i, len(names))
            for i, name in enumerate(names) if not known or name in known}


def _sigma_deg_of(row: Any, i: int, n: int) -> float | None:
    """√P_ii in degrees from row i of an n×n covariance, None where it is not a variance."""
    v = row[i] if isinstance(row, list) and len(row) == n else None
    if isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0.0:
        return math.degrees(math.sqrt(v))
    return None


_FIELD_RES = {key: [(re.compile("^" + re.escape(p).replace(re.escape("<node>"), "[^.]+")
                                .replace(re.escape("<cell>"), "[^.]+") + "$"), p, u)
                    for p, _, u in fields] for key, fields in FIELDS.items()}


def column_unit(key: str, column: str) -> str:
    """The unit of a flat column, from :data:`FIELDS` ('' when none)."""
    parts = column.split(".")
    if key == "angles" and parts[0] == SIGMA_DEG:
        return "deg"
    for n in range(len(parts), 0, -1):
        head = ".".join(parts[:n])
        for rx, _, unit in _FIELD_RES.get(key, ()):
            if rx.match(head):
                if unit == VEC6 and n < len(parts):
                    return AXIS_UNIT[AXIS_KIND[AXES.index(parts[n])]] \
                        if parts[n] in AXES else unit
                return unit
    return ""


_SCALAR_KINDS = ((bool, "bool"), (int, "int"), (float, "float"), (str, "str"))  # bool before int
# a list's kind by the kinds of its elements, the first row that holds them all
_LIST_KINDS = ((frozenset({"int"}), "list:int"), (frozenset({"int", "float"}), "list:float"),
               (frozenset({"str"}), "list:str"),
               (frozenset({"list:", "list:int", "list:float"}), "list:list"))


def _kind(v: Any) -> str:
    kind = next((name for t, name in _SCALAR_KINDS if isinstance(v, t)), None)
    if kind is not None:
        return kind
    return _list_kind(v) if isinstance(v, list) else "json"


def _list_kind(v: list) -> str:
    inner = {_kind(x) for x in v if x is not None}
    if not inner:
        return "list:"
    return next((name for allowed, name in _LIST_KINDS if inner <= allowed), "json")


# the Arrow type of a column (or of a list column's elements) by the kinds seen in it, the first
# row that holds them all; a list of lists is a list of float lists
_ARROW_OF_KINDS = ((frozenset({"bool"}), "bool_"), (frozenset({"int"}), "int64"),
                   (frozenset({"int", "float"}), "float64"), (frozenset({"str"}), "string"),
                   (frozenset({"list"}), "float64 list"))


def _arrow_type(kinds: set[str]):
    """The Arrow type of an undeclared column from the kinds of its values (:func:`_kind`):
    one type of scalar, or lists of one type of element; anything mixed is JSON text."""
    import pyarrow as pa

    if not kinds:
        return pa.null()
    lists = all(k.startswith("list:") for k in kinds)
    elements = {k.removeprefix("list:") for k in kinds} - {""} if lists else kinds
    if not elements:  # only empty lists
        return pa.list_(pa.string())
    typ = _arrow_of_kinds(elements)
    if typ is None:
        return pa.string()  # anything mixed: JSON text
    return pa.list_(typ) if lists else typ


def _arrow_of_kinds(kinds: set[str]):
    import pyarrow as pa

    name = next((name for allowed, name in _ARROW_OF_KINDS if kinds <= allowed), None)
    if name is None:
        return None
    return pa.list_(pa.float64()) if name == "float64 list" else getattr(pa, name)()


# -- the declared Arrow schema of each key (FIELDS and the rig's names; never the data) ---------
_BY_NAME = {("channels", "T"): "T", ("channels", "drive"): "drive",
            ("angles", "alpha"): "angles", ("angles", "sigma_cr"): "angles",
            ("angles", "sigma_cr_corrected"): "angles"}


def _arrow_of(jtype: str):
    import pyarrow as pa

    scalar = {"integer": pa.int64(), "number": pa.float64(), "string": pa.string(),
              "boolean": pa.bool_()}
    if jtype in scalar:
        return scalar[jtype]
    if jtype.startswith("array:") and jtype != "array:object":
        inner = _arrow_of(jtype[6:])
        if not pa.types.is_string(inner) or jtype == "array:string":
            return pa.list_(inner)
    return pa.string()  # objects without declared fields, lists of objects: JSON text


def declared_columns(key: str, names: dict[str, tuple[str, ...]]) -> list[tuple[str, str]]:
    """(column, JSON type) of ``key``'s table, in :data:`FIELDS` order: nested objects as
    dotted columns, ``<node>``/``<cell>`` for each of the rig's, named vectors one column
    per element (``H.X``, ``T.<cell>``, ``accel.<acc>.z``, ``alpha.<angle>`` beside the list
    ``alpha``), lists of objects as JSON text. From the declaration and the rig alone, so
    two recordings of a rig give the same columns, whatever their data."""
    fields = FIELDS[key]
    parents = {p.rsplit(".", 1)[0] for p, _, _ in fields if "." in p}
    out: list[tuple[str, str]] = []
    for path, jtype, unit in fields:
        if "[]" in path or (jtype == "object" and path in parents):
            continue  # inside a JSON-text column, or a parent of declared columns
        for col in _expand(path, names):
            out += _field_columns(key, path, col, jtype, unit, names)
    if key == "angles":
        out.append((ADVICE_TEXT, "string"))
    return out


def _expand(path: str, names: dict[str, tuple[str, ...]]) -> list[str]:
    """A declared path with each ``<node>``/``<cell>`` part replaced by each of the rig's."""
    paths = [""]
    for part in path.split("."):
        subs = names.get(part, (part,)) if part.startswith("<") else (part,)
        paths = [f"{p}.{x}" if p else x for p in paths for x in subs]
    return paths


def _field_columns(key: str, path: str, col: str, jtype: str, unit: str,
                   names: dict[str, tuple[str, ...]]) -> list[tuple[str, str]]:
    """The columns of one declared field: a six-vector by axis, the accelerometers by name
    and axis, the angles' covariance beside each angle's σ, a named vector by the rig's
    names (the angles' also as the list), anything else itself."""
    if path in _VEC6_PATHS and unit == VEC6:
        return [(f"{col}.{a}", "number") for a in AXES]
    if key == "channels" and path == "accel":
        return [(f"accel.{a}.{x}", "number") for a in names.get("accel", ()) for x in "xyz"]
    if key == "angles" and path == "P":
        return [(col, jtype)] + [(f"{SIGMA_DEG}.{n}", "number") for n in names.get("angles", ())]
    if (key, path) not in _BY_NAME:
        return [(col, jtype)]
    itself = [(col, jtype)] if key == "angles" else []
    return itself + [(f"{col}.{n}", "number") for n in names.get(_BY_NAME[key, path], ())]


def parquet_schemas(keys: Iterable[str], names: dict[str, tuple[str, ...]],
                    records: Iterable[tuple[str, dict]] | None = None):
    """The Arrow schema of every key's table: declared (:func:`declared_columns`) for the
    keys of :data:`FIELDS`, units from it as field metadata ``unit`` and as the schema
    metadata ``units``. A key outside the declaration (a file from elsewhere) has its
    columns and types taken from ``records`` (a pass over the data) instead."""
    schemas = {}
    undeclared = [k for k in dict.fromkeys(keys) if k not in FIELDS]
    inferred = _inferred_columns(records or (), set(undeclared))
    for key in dict.fromkeys(keys):
        if key in FIELDS:
            cols = [(c, _arrow_of(t)) for c, t in declared_columns(key, names)]
        else:
            cols = [(c, _arrow_type(kinds)) for c, kinds in inferred.get(key, {}).items()]
        schemas[key] = _schema(key, cols)
    return schemas


def _schema(key: str, cols: list[tuple[str, Any]]):
    """The Arrow schema of ``key``'s (column, type) list, each column's unit as its field
    metadata and all of them as the schema metadata ``units``."""
    import pyarrow as pa

    fields, units = [], {}
    for col, typ in cols:
        unit = column_unit(key, col)
        units[col] = unit
        fields.append(pa.field(col, typ, nullable=True,
                               metadata={"unit": unit} if unit else None))
    return pa.schema(fields, metadata={
        "rsra.key": key, "units": json.dumps(units, ensure_ascii=False),
        "source": "rsra export (docs/telemetry.md)"})


def _inferred_columns(records: Iterable[tuple[str, dict]], keys: set[str]
                      ) -> dict[str, dict[str, set[str]]]:
    cols: dict[str, dict[str, set[str]]] = {}
    if not keys:
        return cols
    for key, payload in records:
        if key not in keys:
            continue
        c = cols.setdefault(key, {})
        for col, v in flatten(key, payload, {}).items():
            kinds = c.setdefault(col, set())
            if v is not None:
                kinds.add(_kind(v))
    return cols


def _cells(values: list, typ) -> list:
    """A column's values as its declared type takes them: JSON text for what is not a string
    in a string column, a float for an integer in a float column (decided once a column)."""
    import pyarrow as pa

    if pa.types.is_string(typ):
        return [v if v is None or isinstance(v, str) else json.dumps(v) for v in values]
    if pa.types.is_floating(typ):
        return [float(v) if isinstance(v, int) else v for v in values]
    return values


def _with_metadata(sch, metadata: dict[str, str]):
    """The schema with ``metadata`` (provenance) added to its key-value metadata."""
    return sch.with_metadata({**(sch.metadata or {}),
                              **{a.encode(): b.encode() for a, b in metadata.items()}})


class ParquetTables:
    """Rows of every key into its own Parquet file under its declared schema, pushed one
    record at a time (:meth:`add`) and written ``batch`` rows at a time (bounded memory);
    :meth:`close` writes the rest. ``outputs[key]`` is a path or a binary file object (an
    atomic output: daq.runtime.persistence.AtomicOutput). ``metadata`` (provenance) is added
    to every file's key-value metadata. ``counts`` the rows per key; a value in a column the
    schema does not declare, or of another type than declared, is left out and its column
    named in ``left_out`` (the declaration is incomplete: tests/test_export.py keeps it
    complete for what rsra publishes)."""

    def __init__(self, schemas: dict, outputs: dict[str, Any], names: dict[str, tuple[str, ...]],
                 batch: int = 4096, left_out: dict[str, set[str]] | None = None,
                 metadata: dict[str, str] | None = None):
        if metadata:
            schemas = {k: _with_metadata(sch, metadata) for k, sch in schemas.items()}
        #: the Arrow schema of each key's file
        self.schemas: dict = schemas
        #: where each key's file goes (path or binary file object)
        self.outputs = outputs
        #: the rig's names the vectors are flattened by (:func:`vector_names`)
        self.names = names
        #: rows held per key before a write
        self.batch = batch
        #: rows written per key
        self.counts: dict[str, int] = {k: 0 for k in schemas}
        #: columns whose values were left out, per key
        self.left_out: dict[str, set[str]] = {} if left_out is None else left_out
        self._writers: dict[str, Any] = {}
        self._pending: dict[str, list[dict]] = {k: [] for k in schemas}
        self._declared = {k: set(sch.names) for k, sch in schemas.items()}

    def add(self, key: str, payload: dict) -> None:
        row = flatten(key, payload, self.names)
        cols = self._declared[key]
        for col, v in row.items():
            if v is not None and col not in cols:
                self.left_out.setdefault(key, set()).add(col)
        pending = self._pending[key]
        pending.append(row)
        if len(pending) >= self.batch:
            self._flush(key)

    def _flush(self, key: str) -> None:
        import pyarrow as pa

        rows = self._pending[key]
        if not rows:
            return
        sch = self.schemas[key]
        arrays = [self._column(key, rows, f) for f in sch]
        self._write(key, pa.Table.from_arrays(arrays, schema=sch))
        rows.clear()

    def _write(self, key: str, table) -> None:
        import pyarrow.parquet as pq

        if key not in self._writers:
            self._writers[key] = pq.ParquetWriter(self.outputs[key], self.schemas[key])
        self._writers[key].write_table(table)
        self.counts[key] += table.num_rows

    def _column(self, key: str, rows: list[dict], f):
        """One column of the batch; a value of another type than declared is left out."""
        import pyarrow as pa

        name = f.name
        values = _cells([r.get(name) for r in rows], f.type)
        try:
            return pa.array(values, type=f.type)
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            kept = []
            for v in values:
                try:
                    pa.array([v], type=f.type)
                    kept.append(v)
                except (pa.ArrowInvalid, pa.ArrowTypeError):
                    kept.append(None)
                    self.left_out.setdefault(key, set()).add(f.name)
            return pa.array(kept, type=f.type)

    def close(self, empty: bool = False) -> None:
        """Write what is pending and close the files; ``empty``: a key without rows still
        gets its file (its schema, no rows), so every key of a dataset has its file."""
        try:
            for key in self.schemas:
                self._flush(key)
                if empty and key not in self._writers:
                    self._write(key, self.schemas[key].empty_table())
        finally:
            for w in self._writers.values():
                w.close()
            self._writers.clear()


def write_parquet(records: Iterable[tuple[str, dict]], schemas: dict, paths: dict[str, Path],
                  names: dict[str, tuple[str, ...]], batch: int = 4096,
                  left_out: dict[str, set[str]] | None = None) -> dict[str, int]:
    """Rows of every key into its Parquet file (``paths[key]``) under its schema
    (:class:`ParquetTables`). Returns the row count per key; values left out are named in
    ``left_out``."""
    tables = ParquetTables(schemas, dict(paths), names, batch, left_out)
    try:
        for key, payload in records:
            tables.add(key, payload)
    finally:
        tables.close()
    return tables.counts


def vector_names(cfg: RigConfig) -> dict[str, tuple[str, ...]]:
    """The rig's names the Parquet columns are declared with: cells, accelerometers, external
    loads (the vectors of ``channels``), nodes (``health``), angles (``angles``)."""
    cells = tuple(c.name for c in cfg.cells)
    return {"T": cells, "<cell>": cells,
            "accel": tuple(a.name for a in cfg.accelerometers),
            "drive": tuple(e.name for e in cfg.external_loads),
            "<node>": tuple(n.name for n in cfg.nodes),
            "angles": tuple(cfg.rig_model().geometry.angle_names)}

