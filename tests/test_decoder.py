"""PDO decode tables from the EDS mapping (daq.decoder): layouts, units, calibration, errors."""
from __future__ import annotations

import configparser
import copy
import functools
import math
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers_canopen import ACCEL, CELL, PAIR, ROTOR
from hypothesis import given, settings
from hypothesis import strategies as st

from rsra.config.rig import G0, ConfigError, config_dir, load_config, parse_config
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.bus.reader import quantise_us

EDS_DIR = config_dir() / "eds"


@functools.cache
def _default_table() -> DecodeTable:
    return DecodeTable(load_config())
_CODES = {0x0003: "h", 0x0005: "B", 0x0006: "H", 0x0008: "f"}


def _eds_layouts(path: Path, node_id: int) -> dict[int, str]:
    """COB-ID -> struct format, read with configparser straight from the EDS text."""
    p = configparser.ConfigParser()
    p.optionxform = str
    p.read(path)
    out = {}
    for n in range(8):
        comm, mp = f"{0x1800 + n:04X}sub1", f"{0x1A00 + n:04X}"
        if comm not in p:
            continue
        cob = eval(p[comm]["DefaultValue"].replace("$NODEID", str(node_id)))
        fmt = "<"
        for s in range(1, int(p[f"{mp}sub0"]["DefaultValue"], 0) + 1):
            e = int(p[f"{mp}sub{s}"]["DefaultValue"], 0)
            obj = f"{e >> 16:04X}sub{(e >> 8) & 0xFF}"
            fmt += _CODES[int(p[obj]["DataType"], 0)]
        out[cob] = fmt
    return out


def test_every_tpdo_of_the_eds_has_its_precompiled_struct(cfg):
    table = DecodeTable(cfg)
    expected = {}
    for nc in cfg.nodes:
        expected.update(_eds_layouts(nc.eds, nc.node_id))
    assert {cob: lay.struct.format for cob, lay in table.tpdos.items()} == expected
    # the default rig: seven cells 0x191…0x197, accelerometer 0x1A1, rotor 0x1B1, balance x3
    assert sorted(table.tpdos) == [0x191, 0x192, 0x193, 0x194, 0x195, 0x196, 0x197, 0x1A1,
                                   0x1B1, 0x1C1, 0x2C1, 0x3C1]
    for lay in table.tpdos.values():
        assert lay.length == lay.struct.size <= 8
        assert lay.transmission_type == 1
    # one bit per TPDO, one channel slice per node, in config order
    bits = [lay.bit for lay in table.tpdos.values()]
    assert len(set(bits)) == len(bits) and all(b & (b - 1) == 0 for b in bits)
    assert [n.name for n in table.nodes] == [n.name for n in cfg.nodes]


def test_decoded_units_follow_bus_md(cfg):
    table = DecodeTable(cfg)
    out = table.decode(0x191, CELL.pack(-12345.5, 0x03))
    assert out == {"cell_A.force": -12345.5, "cell_A.status": 3.0}
    out = table.decode(0x1A1, ACCEL.pack(1, -2, -1000))
    # 1 count = 1 mg of specific force; at rest z reads -1000 mg = -g
    assert out["accel_1.x"] == pytest.approx(1e-3 * G0, rel=1e-15)
    assert out["accel_1.y"] == pytest.approx(-2e-3 * G0, rel=1e-15)
    assert out["accel_1.z"] == pytest.approx(-G0, rel=1e-15)
    out = table.decode(0x1B1, ROTOR.pack(19.4, 16384))
    assert out["rotor_speed.omega"] == pytest.approx(19.4, rel=1e-7)
    assert out["rotor_speed.azimuth"] == pytest.approx(math.pi / 2, rel=1e-15)  # 65536 ↔ 2π
    out = table.decode(0x2C1, PAIR.pack(80000.0, -2500.0))
    assert out == {"balance.Z": 80000.0, "balance.L": -2500.0}


def test_calibration_gain_and_offset_per_channel():
    cfg = load_config(overrides={"calibration": {
        "cell_B.force": {"gain": 1.01, "offset": -50.0},
        "accel_1.z": {"gain": 0.98, "offset": 0.05},
        "rotor_speed.azimuth": {"offset": 0.1}}})
    table = DecodeTable(cfg)
    f = np.float32(2000.25)
    assert table.decode(0x192, CELL.pack(f, 0))["cell_B.force"] == pytest.approx(1.01 * f - 50.0)
    assert table.decode(0x191, CELL.pack(f, 0))["cell_A.force"] == f  # others untouched
    assert table.decode(0x1A1, ACCEL.pack(0, 0, -1000))["accel_1.z"] == \
        pytest.approx(0.98 * -G0 + 0.05)
    assert table.decode(0x1B1, ROTOR.pack(1.0, 0))["rotor_speed.azimuth"] == pytest.approx(0.1)
    # the vectors used per sample carry the same numbers
    i = table.index("cell_B.force")
    assert (table.gain[i], table.offset[i]) == (1.01, -50.0)


@pytest.mark.parametrize("key,problem", [("cell_A.forse", "no such channel"),
                                         ("cell_A.status", "bit field")])
def test_bad_calibration_keys_are_refused(key, problem):
    cfg = load_config(overrides={"calibration": {key: {"gain": 2.0}}})
    with pytest.raises(ConfigError, match=problem) as e:
        DecodeTable(cfg)
    assert key in str(e.value)


def test_wrong_frame_length_is_refused(cfg):
    table = DecodeTable(cfg)
    with pytest.raises(ValueError, match="expected 5"):
        table.decode(0x191, b"\x00" * 4)


def _cfg_with_eds(cfg, tmp_path, edit) -> object:
    text = (EDS_DIR / "load_cell.eds").read_text()
    eds = tmp_path / "bad_cell.eds"
    eds.write_text(edit(text))
    raw = copy.deepcopy(cfg.raw)
    raw["nodes"][2]["eds"] = str(eds)
    return parse_config(raw, base_dir=config_dir())


@pytest.mark.parametrize("edit,problem", [
    (lambda s: s.replace("[1800sub2]\nParameterName=Transmission type\nObjectType=0x7\n"
                         "DataType=0x0005\nAccessType=rw\nDefaultValue=1",
                         "[1800sub2]\nParameterName=Transmission type\nObjectType=0x7\n"
                         "DataType=0x0005\nAccessType=rw\nDefaultValue=254"),
     "transmission type 1"),
    (lambda s: s.replace("DefaultValue=0x61500108", "DefaultValue=0x61500110"), "cannot be mapped"),
    (lambda s: s.replace("DefaultValue=0x61500108", "DefaultValue=0x61600108"), "does not define"),
    (lambda s: s.replace("DefaultValue=0x61500108", "DefaultValue=0x00000000")
     .replace("[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
              "DataType=0x0005\nAccessType=rw\nDefaultValue=2",
              "[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
              "DataType=0x0005\nAccessType=rw\nDefaultValue=1"), "'status'"),
])
def test_an_eds_the_reader_cannot_use_is_refused_with_the_key(cfg, tmp_path, edit, problem):
    bad = _cfg_with_eds(cfg, tmp_path, edit)
    with pytest.raises(ConfigError, match=problem) as e:
        DecodeTable(bad)
    assert "cell_C" in str(e.value) or "nodes[2]" in str(e.value)


def test_node_ids_move_the_cob_ids(cfg):
    raw = copy.deepcopy(cfg.raw)
    raw["nodes"][0]["node_id"] = 0x61
    table = DecodeTable(parse_config(raw, base_dir=config_dir()))
    assert 0x1E1 in table.tpdos and 0x191 not in table.tpdos
    assert table.tpdos[0x1E1].node == "cell_A"


@settings(max_examples=200, deadline=None)
@given(force=st.floats(-1.2e5, 1.2e5, width=32), status=st.integers(0, 255),
       xyz=st.tuples(*[st.floats(-7 * G0, 7 * G0)] * 3),
       az=st.floats(0.0, 2 * math.pi, exclude_max=True))
def test_encode_decode_round_trip_within_the_resolution(force, status, xyz, az):
    table = _default_table()
    out = table.decode(0x193, table.encode({"cell_C.force": force, "cell_C.status": status}, 0x193))
    assert out == {"cell_C.force": force, "cell_C.status": float(status)}
    keys = ("accel_1.x", "accel_1.y", "accel_1.z")
    out = table.decode(0x1A1, table.encode(dict(zip(keys, xyz)), 0x1A1))
    for k, v in zip(keys, xyz):
        assert abs(out[k] - v) <= 0.5e-3 * G0 * (1 + 1e-12)  # half a count (mg)
    out = table.decode(0x1B1, table.encode({"rotor_speed.omega": 19.0, "rotor_speed.azimuth": az},
                                           0x1B1))
    d = (out["rotor_speed.azimuth"] - az + math.pi) % (2 * math.pi) - math.pi
    assert abs(d) <= math.pi / 65536 * (1 + 1e-9)  # half a count of 2π/65536


def test_timestamps_quantise_to_values_the_recordings_keep(rng):
    """The reader's 1 µs quantiser: within half a µs (plus float error), idempotent, and the
    candump %.6f round trip gives the quantised value back exactly (replay == live)."""
    t = 1.7e9 + rng.uniform(0, 1e6, 20000)
    t = np.concatenate([t, rng.uniform(0, 100, 2000), np.round(t[:2000], 6)])
    for x in t.tolist():
        q = quantise_us(x)
        assert abs(q - x) <= 0.5e-6 + 4 * math.ulp(x)
        assert quantise_us(q) == q
        assert float(f"{q:.6f}") == q
        assert q == round(q, 6)


def test_struct_formats_are_little_endian(cfg):
    table = DecodeTable(cfg)
    assert all(lay.struct.format.startswith("<") for lay in table.tpdos.values())
    assert struct.unpack("<f", table.encode({"cell_A.force": 1.0, "cell_A.status": 0},
                                            0x191)[:4]) == (1.0,)
