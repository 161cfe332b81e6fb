"""`rsra export` (daq.export): a DBC that cantools decodes to the reader's values, MCAP and
Parquet files that their own readers give back with the same numbers, the EDS files clean under
dcfchk, and refusals that leave nothing behind."""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cantools
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from helpers_canopen import LockstepRig
from mcap.reader import make_reader

from rsra.daq.cli import main as cli_main
from rsra.daq.bus.reader import HealthReport
from rsra.daq.bus.replay import read_frames, replay

ROOT = Path(__file__).resolve().parents[1]
EDS_DIR = ROOT / "config" / "eds"


@pytest.fixture(scope="module")
def recording(cfg, tmp_path_factory):
    """A short lock-step simulator recording with an over-range cell and a dropped
    accelerometer frame now and then (status bits and nulls show)."""
    folder = tmp_path_factory.mktemp("export") / "rec"
    rig = LockstepRig(cfg, faults="overrange:cell_C@0.1;drop:accel_1:0.05", record=folder)
    try:
        rig.step(240)
    finally:
        rig.close()
    return folder


@pytest.fixture(scope="module")
def results(recording, tmp_path_factory):
    """`rsra replay --out` of the recording."""
    out = tmp_path_factory.mktemp("results") / "results.jsonl"
    assert cli_main(["replay", str(recording), "--out", str(out)]) == 0
    return out


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


# -- DBC ------------------------------------------------------------------------------------
def test_cantools_decodes_a_recording_with_the_dbc_to_the_readers_values(cfg, recording,
                                                                         tmp_path, capsys):
    dbc = tmp_path / "rig.dbc"
    assert cli_main(["export", "--dbc", str(dbc)]) == 0
    assert "rig.dbc:" in capsys.readouterr().out
    db = cantools.database.load_file(str(dbc))
    # one decoded dict per SYNC period, in frame order, by cantools alone
    periods: list[dict] = []
    for msg in read_frames([recording]):
        if msg.is_error_frame or msg.is_remote_frame:
            continue
        try:
            m = db.get_message_by_frame_id(msg.arbitration_id)
        except KeyError:  # SDO, NMT: not in the DBC
            continue
        if m.name == "SYNC":
            periods.append({})
        if not periods or "TPDO" not in m.name and m.name != "SYNC":
            continue
        periods[-1].update(m.decode(bytes(msg.data), decode_choices=False))
    samples = [s for s in replay(cfg, [recording], finish=True)
               if not isinstance(s, HealthReport)]
    assert len(samples) == len(periods) >= 200
    over = optional = 0
    for s, d in zip(samples, periods):
        assert s.sync == d["SYNC_counter"]
        for i, cell in enumerate(cfg.cells):
            assert s.T[i] == d[f"{cell.node}_force"]
            assert s.cell_status[cell.name] == d[f"{cell.node}_status"]
            over += d[f"{cell.node}_status"] != 0
        for k, acc in enumerate(cfg.accelerometers):
            if math.isnan(s.accel[k][0]):  # a dropped frame: not in this period
                assert f"{acc.node}_x" not in d
            else:
                assert s.accel[k].tolist() == [d[f"{acc.node}_{a}"] for a in "xyz"]
        if s.omega is not None:  # optional nodes count from their first heartbeat on
            assert s.omega == d["rotor_speed_omega"]
            assert s.azimuth == d["rotor_speed_azimuth"]
            optional += 1
        if s.known_H is not None:
            assert s.known_H.tolist() == [d[f"balance_{a}"] for a in "XYZLMN"]
            optional += 1
    assert optional > 300
    assert over > 0  # the status bytes were exercised
    assert any(math.isnan(s.accel[0][0]) for s in samples)


def test_the_dbc_marks_real32_values_as_float_signals_with_units(cfg, tmp_path):
    dbc = tmp_path / "rig.dbc"
    assert cli_main(["export", "--dbc", str(dbc), "--config", str(ROOT / "config" / "rig.toml")]) == 0
    text = dbc.read_text(encoding="cp1252")
    assert "SIG_VALTYPE_ 401 cell_A_force : 1;" in text  # what canmatrix/SavvyCAN read
    db = cantools.database.load_file(str(dbc))
    force = db.get_message_by_name("cell_A_TPDO1").get_signal_by_name("cell_A_force")
    assert (force.is_float, force.length, force.unit) == (True, 32, "N")
    ax = db.get_message_by_name("accel_1_TPDO1").get_signal_by_name("accel_1_z")
    assert (ax.is_float, ax.is_signed, ax.unit, ax.scale) == (False, True, "m/s^2", 0.00980665)
    assert db.get_message_by_name("balance_TPDO2").get_signal_by_name("balance_L").unit == "Nm"
    assert db.get_message_by_name("SYNC").frame_id == cfg.sync.cob_id
    st = db.get_message_by_name("cell_A_TPDO1").get_signal_by_name("cell_A_status")
    assert st.choices[1] == "over-range" and st.choices[2] == "sensor fault"


def test_the_dbc_carries_the_calibration_of_every_channel(rng):
    """Every TPDO of a calibrated rig: cantools' value == the decode table's, any frame."""
    from rsra.config.rig import load_config
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.daq.analysis.export import build_dbc

    cfg = load_config(overrides={"calibration": {
        "cell_B.force": {"gain": 1.01, "offset": -50.0},
        "accel_1.z": {"gain": 0.98, "offset": 0.05},
        "balance.M": {"gain": 1.002, "offset": 3.0}}})
    table = DecodeTable(cfg)
    db = cantools.database.Database()
    db.add_dbc_string(build_dbc(cfg, table).as_dbc_string())  # through the DBC text
    for cob, lay in table.tpdos.items():
        m = db.get_message_by_frame_id(cob)
        for _ in range(50):
            data = rng.integers(0, 256, lay.length, dtype=np.uint8).tobytes()
            ours = table.decode(cob, data)
            theirs = m.decode(data, decode_choices=False)
            assert len(ours) == len(theirs)
            for key, v in ours.items():
                w = theirs[key.replace(".", "_")]
                assert v == w or (math.isnan(v) and math.isnan(w)), (key, v, w)


def test_the_eds_unit_objects_say_what_the_decoder_assumes(cfg):
    import canopen

    from rsra.config.devices import device_profile
    from rsra.daq.analysis.export import eds_unit

    od = canopen.import_od(str(EDS_DIR / "load_cell.eds"), 0x11)
    assert od[0x6131][1].default == 0x00210000  # CiA 303-2: newton, 10^0
    assert eds_unit(od, 0x6130, 1) == device_profile("load_cell").channel("force").unit == "N"


# -- EDS lint -------------------------------------------------------------------------------
def _dcfchk() -> list[str]:
    exe = Path(sys.executable).parent / "dcfchk"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("dcfchk")
    if found:
        return [found]
    pytest.importorskip("dcf", reason="dcfchk (PyPI dcf-tools, the `test` extra)")
    return [sys.executable, "-m", "dcf.cli"]


@pytest.mark.parametrize("eds", sorted(p.name for p in EDS_DIR.glob("*.eds")))
def test_the_shipped_eds_files_pass_dcfchk(cfg, eds):
    node_id = next((n.node_id for n in cfg.nodes if Path(n.eds).name == eds), 1)
    r = subprocess.run([*_dcfchk(), "-n", str(node_id), "-p", str(EDS_DIR / eds)],
                       check=False, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "Warning" not in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


# -- MCAP -----------------------------------------------------------------------------------
def _conforms(value, schema: dict, path: str = "") -> None:
    """The subset of JSON Schema the export writes: type lists, properties,
    additionalProperties, items."""
    kinds = {"null": type(None), "boolean": bool, "string": str, "object": dict,
             "array": list, "number": (int, float), "integer": int}
    types = schema.get("type")
    if types is not None:
        types = [types] if isinstance(types, str) else types
        ok = any(isinstance(value, kinds[t]) and not (t in ("number", "integer")
                                                     and isinstance(value, bool))
                 for t in types)
        assert ok, f"{path}: {value!r} is not {types}"
    if isinstance(value, dict):
        for k, v in value.items():
            sub = schema.get("properties", {}).get(k, schema.get("additionalProperties"))
            assert sub is not None, f"{path}.{k}: not in the schema"
            _conforms(v, sub, f"{path}.{k}")
    elif isinstance(value, list) and "items" in schema:
        for i, v in enumerate(value):
            _conforms(v, schema["items"], f"{path}[{i}]")


def _mcap_messages(path: Path) -> list[tuple[str, int, dict, dict]]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, json.loads(m.data), json.loads(sch.data))
                for sch, ch, m in make_reader(f).iter_messages(log_time_order=False)]


def test_mcap_reads_back_to_the_same_records_at_acquisition_times(cfg, results, tmp_path):
    out = tmp_path / "run.mcap"
    assert cli_main(["export", str(results), "--mcap", str(out)]) == 0
    recs = _records(results)
    msgs = _mcap_messages(out)
    assert len(msgs) == len(recs) > 400
    prefix = cfg.telemetry.prefix
    for rec, (topic, log_time, data, schema) in zip(recs, msgs):
        key = rec.pop("key")
        assert topic == f"{prefix}/{key}"
        assert data == rec  # same numbers, nulls included
        assert log_time == round(rec["t"] * 1e9)
        _conforms(data, schema, key)
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    encodings = {s.encoding for s in summary.schemas.values()}
    assert encodings == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}


def test_a_recording_is_exported_through_the_replay_path(results, recording, tmp_path):
    """RECORDING → the same messages as its `rsra replay --out` file."""
    a, b = tmp_path / "from_jsonl.mcap", tmp_path / "from_recording.mcap"
    assert cli_main(["export", str(results), "--mcap", str(a)]) == 0
    assert cli_main(["export", str(recording), "--mcap", str(b)]) == 0
    assert [m[:3] for m in _mcap_messages(a)] == [m[:3] for m in _mcap_messages(b)]


# -- Parquet --------------------------------------------------------------------------------
def test_parquet_tables_read_back_to_the_same_numbers_with_units(cfg, results, tmp_path):
    out = tmp_path / "pq"
    assert cli_main(["export", str(results), "--parquet", str(out)]) == 0
    recs = _records(results)
    keys = sorted({r["key"] for r in recs})
    assert sorted(p.stem for p in out.iterdir()) == keys
    hub = pq.read_table(out / "hub_loads.parquet")
    rows = [r for r in recs if r["key"] == "hub_loads"]
    assert hub.num_rows == len(rows)
    for k, axis in enumerate("XYZLMN"):
        assert hub.column(f"H.{axis}").to_pylist() == [
            None if r["H"] is None else r["H"][k] for r in rows]
        assert hub.column(f"H_static.{axis}").to_pylist() == [
            None if r["H_static"] is None else r["H_static"][k] for r in rows]
    assert hub.column("seq").to_pylist() == [r["seq"] for r in rows]
    assert hub.column("flags").to_pylist() == [r["flags"] for r in rows]
    sch = hub.schema
    assert sch.field("seq").type == pa.int64() and sch.field("t").type == pa.float64()
    assert sch.field("flags").type == pa.list_(pa.string())
    assert sch.field("H.X").metadata[b"unit"] == b"N"
    assert sch.field("H.L").metadata[b"unit"] == "N·m".encode()
    assert json.loads(sch.metadata[b"units"])["omega"] == "rad/s"

    ch = pq.read_table(out / "channels.parquet")
    crow = [r for r in recs if r["key"] == "channels"]
    for i, cell in enumerate(cfg.cells):
        assert ch.column(f"T.{cell.name}").to_pylist() == [r["T"][i] for r in crow]
        assert ch.column(f"status.{cell.name}").to_pylist() == [
            r["status"].get(cell.name) for r in crow]
    acc = cfg.accelerometers[0].name
    assert ch.column(f"accel.{acc}.z").to_pylist() == [r["accel"][0][2] for r in crow]
    assert None in ch.column(f"accel.{acc}.z").to_pylist()  # the dropped frames
    assert ch.schema.field(f"accel.{acc}.z").metadata[b"unit"] == "m/s²".encode()
    assert ch.schema.field(f"status.{cfg.cells[0].name}").type == pa.int64()
    health = pq.read_table(out / "health.parquet").to_pandas()  # pandas reads it too
    hrow = [r for r in recs if r["key"] == "health"]
    assert health["bus.frames"].tolist() == [r["bus"]["frames"] for r in hrow]
    assert health["nodes.cell_A.state"].tolist() == [r["nodes"]["cell_A"]["state"]
                                                     for r in hrow]


def test_parquet_angles_by_parameter_name(tmp_path):
    names = ["delta_A", "theta_A"]
    rec = {"key": "angles", "t": 1.5, "seq": 10, "mode": "known_loads", "content": "static",
           "accepted": True, "reason": None, "names": names, "alpha": [0.001, -0.002],
           "P": [[1e-6, 0.0], [0.0, 2e-6]], "sigma_cr": None, "sigma_cr_corrected": None,
           "window": [0, 10], "iterations": 3}
    src = tmp_path / "angles.jsonl"
    src.write_text(json.dumps(rec) + "\n" + json.dumps({**rec, "seq": 20, "t": 2.5}) + "\n")
    assert cli_main(["export", str(src), "--parquet", str(tmp_path / "pq")]) == 0
    t = pq.read_table(tmp_path / "pq" / "angles.parquet")
    assert t.column("alpha.theta_A").to_pylist() == [-0.002, -0.002]
    assert t.schema.field("alpha.theta_A").metadata[b"unit"] == b"rad"
    assert t.column("P").to_pylist()[0] == rec["P"]
    assert t.schema.field("P").type == pa.list_(pa.list_(pa.float64()))
    assert t.column("window").to_pylist() == [[0, 10], [0, 10]]


def _other_run(results: Path, tmp_path: Path) -> Path:
    """A second telemetry file whose data differ in every way a schema could follow: a
    vector null throughout (known_H), every angles run accepted (reason null throughout),
    no health record, fewer rows."""
    out = tmp_path / "other.jsonl"
    lines = []
    for rec in _records(results)[:300]:
        if rec["key"] == "health":
            continue
        if rec["key"] == "channels":
            rec["known_H"] = None
        lines.append(json.dumps(rec))
    angles = {"key": "angles", "t": 1.5, "seq": 10, "mode": "known_loads",
              "content": "static", "accepted": True, "reason": None, "names": ["delta_A"],
              "alpha": [0.001], "P": [[1e-6]], "window": [0, 10], "iterations": 3}
    lines.append(json.dumps(angles))
    out.write_text("\n".join(lines) + "\n")
    return out


def _angles_file(tmp_path: Path) -> Path:
    """Angles records with a rejected run (a reason) and a structure fit."""
    names = ["delta_A", "theta_A", "x_A"]
    rec = {"key": "angles", "t": 1.5, "seq": 10, "mode": "known_loads", "content": "static",
           "accepted": False, "reason": "stale_input", "names": names,
           "alpha": [0.001, -0.002, 0.5], "P": [[1e-6, 0, 0], [0, 2e-6, 0], [0, 0, 1e-6]],
           "window": [0, 10], "iterations": 3, "candidates": [{"structure": "constant"}],
           "structure_fit": {"structure": "constant", "parameters": ["a"], "alpha0": [0.1]}}
    out = tmp_path / "angles.jsonl"
    out.write_text(json.dumps(rec) + "\n")
    return out


def test_parquet_schemas_are_declared_not_taken_from_the_data_and_datasets_concatenate(
        cfg, results, tmp_path):
    """Issue 29: `channels.parquet` had an all-null `known_H` column beside `known_H.X…N`
    (from seq 0's null), the angles table's `reason` was of type null when every run was
    accepted: two recordings' files did not concatenate. The schema of each key is now
    declared (FIELDS and the rig's names), the same for every file of a rig."""
    from rsra.daq.analysis.export import FIELDS, parquet_schemas, vector_names

    a, b = tmp_path / "a", tmp_path / "b"
    other = _other_run(results, tmp_path)
    assert cli_main(["export", str(results), "--parquet", str(a)]) == 0
    assert cli_main(["export", str(other), "--parquet", str(b)]) == 0
    declared = parquet_schemas(FIELDS, vector_names(cfg))
    assert not (a / "angles.parquet").exists()  # (the fixture's run is too short for one)
    assert cli_main(["export", str(_angles_file(tmp_path)), "--parquet", str(a / "x")]) == 0
    (a / "x" / "angles.parquet").rename(a / "angles.parquet")
    for key in ("hub_loads", "channels", "innovations", "angles"):
        ta, tb = pq.read_table(a / f"{key}.parquet"), pq.read_table(b / f"{key}.parquet")
        for t in (ta, tb):
            assert t.schema.equals(declared[key]), key  # names, types, order
            assert t.schema.metadata[b"units"] == declared[key].metadata[b"units"]
        assert not [f.name for f in ta.schema if pa.types.is_null(f.type)], key
        assert pa.concat_tables([ta, tb]).num_rows == ta.num_rows + tb.num_rows
    ch = pq.read_table(b / "channels.parquet")
    assert "known_H" not in ch.schema.names and ch.column("known_H.X").null_count == ch.num_rows
    assert ch.schema.field("known_H.X").type == pa.float64()
    assert pq.read_table(b / "angles.parquet").schema.field("reason").type == pa.string()
    # the two folders as one dataset (pyarrow.dataset, as pandas/DuckDB/polars read them)
    import pyarrow.dataset as ds

    both = ds.dataset([str(a / "hub_loads.parquet"), str(b / "hub_loads.parquet")])
    assert both.to_table().num_rows == sum(
        1 for p in (results, other) for r in _records(p) if r["key"] == "hub_loads")


def test_every_field_rsra_publishes_is_declared(cfg, results, tmp_path):
    """Nothing of a replay's records is left out of the declared Parquet columns, and every
    message conforms to its key's declared JSON Schema (the MCAP writer's)."""
    from rsra.daq.analysis.export import (
        json_schema,
        parquet_schemas,
        read_records,
        vector_names,
        write_parquet,
    )

    names = vector_names(cfg)
    recs = list(read_records(results))
    schemas = parquet_schemas([k for k, _ in recs], names)
    left_out: dict = {}
    write_parquet(recs, schemas, {k: tmp_path / f"{k}.parquet" for k in schemas}, names,
                  left_out=left_out)
    assert left_out == {}
    for key, payload in recs:
        _conforms(payload, json_schema(key), key)


def test_mcap_schemas_are_declared_not_taken_from_the_data(cfg, results, tmp_path):
    from rsra.daq.analysis.export import json_schema

    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    assert cli_main(["export", str(results), "--mcap", str(a)]) == 0
    assert cli_main(["export", str(_other_run(results, tmp_path)), "--mcap", str(b)]) == 0
    for f in (a, b):
        with open(f, "rb") as fh:
            summary = make_reader(fh).get_summary()
        for sch in summary.schemas.values():
            key = sch.name.removeprefix("rsra.")
            assert json.loads(sch.data) == json_schema(key), key


# -- the payload table is the documented one -------------------------------------------------
def _documented_fields() -> dict[str, list[tuple[str, str]]]:
    text = (ROOT / "docs" / "telemetry.md").read_text(encoding="utf-8")
    out: dict[str, list[tuple[str, str]]] = {}
    key = None
    fields_table = False
    for line in text.splitlines():
        m = re.match(r"### (?:\d+\.\d+ )?`<prefix>/(\w+)`$", line)  # "### 2.1 `<prefix>/…`"
        if m:
            key = m.group(1)
            out[key] = []
        elif line.startswith("#"):
            key = None
        elif line.startswith("| field | unit |"):
            fields_table = True
        elif not line.startswith("|"):
            fields_table = False
        elif key and fields_table and line.startswith("| `"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            field = re.match(r"`([^`]+)`", cells[0]).group(1)
            out[key].append((field, "" if cells[1] == "—" else cells[1]))
    return out


def test_the_export_schemas_are_the_documented_payloads():
    from rsra.daq.analysis.export import FIELDS

    assert {k: [(p, u) for p, _, u in v] for k, v in FIELDS.items()} == _documented_fields()


# -- refusals -------------------------------------------------------------------------------
def _one_line_exit_2(capsys, argv) -> str:
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rsra export: error: "), err
    assert "Traceback" not in err and "; fix: " in err, err
    return err


def test_bad_input_is_refused_in_one_line_and_leaves_no_file(results, tmp_path, capsys):
    bad = tmp_path / "bad.jsonl"
    lines = results.read_text().splitlines()
    bad.write_text("\n".join(lines[:50] + ["{not json"] + lines[50:100]) + "\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.mcap").write_text("old")
    before = sorted(os.listdir(out))
    err = _one_line_exit_2(capsys, ["export", str(bad), "--mcap", str(out / "keep.mcap"),
                                    "--parquet", str(out / "pq"), "--dbc", str(out / "x.dbc")])
    assert "bad.jsonl:51" in err
    assert sorted(os.listdir(out)) == before  # no partial, temporary or new file or folder
    assert (out / "keep.mcap").read_text() == "old"
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    assert "no telemetry records" in _one_line_exit_2(
        capsys, ["export", str(empty), "--mcap", str(out / "e.mcap")])
    assert "no such file" in _one_line_exit_2(
        capsys, ["export", str(tmp_path / "nope.jsonl"), "--mcap", str(out / "n.mcap")])
    assert "no such file or folder" in _one_line_exit_2(
        capsys, ["export", str(tmp_path / "nope.log"), "--parquet", str(out / "n")])
    junk = tmp_path / "junk.blf"
    junk.write_bytes(bytes(range(256)) * 8)
    assert "cannot read the recording" in _one_line_exit_2(
        capsys, ["export", str(junk), "--mcap", str(out / "j.mcap"), "--parquet",
                 str(out / "jpq")])
    assert "nothing to write" in _one_line_exit_2(capsys, ["export", str(results)])
    assert "need the telemetry" in _one_line_exit_2(capsys, ["export", "--mcap",
                                                             str(out / "m.mcap")])
    assert "no folder" in _one_line_exit_2(
        capsys, ["export", "--dbc", str(tmp_path / "no" / "such" / "dir.dbc")])
    assert sorted(os.listdir(out)) == before
