"""One device-profile table (config.devices): a sensor role added to it, with its EDS, is
picked up by the rig file, the reader's decode tables, the DBC export's units and the
simulated node — no other table to edit."""
import copy
import tomllib

import pytest

from rsra.config import devices
from rsra.config.devices import DEVICE_PROFILES, ChannelProfile, DeviceProfile
from rsra.config.rig import ConfigError, config_dir, default_config_path, parse_config

# A pressure probe: a scaled INTEGER16 pressure (10 Pa a count) and a REAL32 temperature
PROBE = DeviceProfile("pressure_probe", (
    ChannelProfile("p", 0x2400, 1, 10.0, "Pa", "INTEGER16"),
    ChannelProfile("temp", 0x2400, 2, 1.0, "degC", "REAL32", required=False)))
NODE_ID = 0x51


def _probe_eds(tmp_path, mapped=(0x24000110, 0x24000220)):
    """The probe's EDS: the drive-load node's with object 0x2400 (two values) in place of
    0x2300, mapped by TPDO1 (``mapped``: its mapping entries)."""
    text = (config_dir() / "eds" / "drive_load.eds").read_text()
    head, _, _ = text.partition("[2300]")
    head = head.replace("1=0x2300", "1=0x2400").replace(
        "DefaultValue=0x23000120", f"DefaultValue=0x{mapped[0]:08X}")
    if len(mapped) > 1:
        head = head.replace("[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
                            "DataType=0x0005\nAccessType=rw\nDefaultValue=1",
                            "[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\n"
                            f"DataType=0x0005\nAccessType=rw\nDefaultValue={len(mapped)}")
        head = head.replace("[1A00sub2]\nParameterName=Mapped object 2\nObjectType=0x7\n"
                            "DataType=0x0007\nAccessType=rw\nDefaultValue=0x00000000",
                            "[1A00sub2]\nParameterName=Mapped object 2\nObjectType=0x7\n"
                            f"DataType=0x0007\nAccessType=rw\nDefaultValue=0x{mapped[1]:08X}")
    obj = ("[2400]\nParameterName=Pressure probe\nObjectType=0x9\nSubNumber=3\n\n"
           "[2400sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\n"
           "DataType=0x0005\nAccessType=ro\nDefaultValue=2\nPDOMapping=0\n\n"
           "[2400sub1]\nParameterName=Pressure (10 Pa)\nObjectType=0x7\nDataType=0x0003\n"
           "AccessType=ro\nDefaultValue=0\nPDOMapping=1\n\n"
           "[2400sub2]\nParameterName=Temperature (degC)\nObjectType=0x7\nDataType=0x0008\n"
           "AccessType=ro\nDefaultValue=0\nPDOMapping=1\n")
    path = tmp_path / "pressure_probe.eds"
    path.write_text(head + obj)
    return path


def _rig(eds):
    raw = tomllib.loads(default_config_path().read_text())
    raw = copy.deepcopy(raw)
    raw["nodes"].append({"name": "probe", "role": "pressure_probe", "node_id": NODE_ID,
                         "eds": str(eds), "required": False})
    return parse_config(raw, source="rig.toml", base_dir=default_config_path().parent)


@pytest.fixture
def probe_role(monkeypatch):
    monkeypatch.setitem(DEVICE_PROFILES, PROBE.role, PROBE)


def test_without_its_entry_the_role_is_an_unknown_choice_naming_the_known_ones(tmp_path):
    with pytest.raises(ConfigError) as ei:
        _rig(_probe_eds(tmp_path))
    assert ei.value.key == "nodes[10].role" and "unknown value" in str(ei.value)
    assert '"load_cell", "accelerometer"' in ei.value.fix and "pressure_probe" not in ei.value.fix


def test_a_new_role_is_one_entry_and_its_eds(probe_role, tmp_path):
    from rsra.daq.analysis.export import build_dbc
    from rsra.daq.bus.decoder import DecodeTable
    from rsra.sim_bus.nodes import NMT_START, SimNode

    eds = _probe_eds(tmp_path)
    cfg = _rig(eds)  # the rig file takes the role
    # the reader's decode table: the channels by the profile's objects, with its scales
    table = DecodeTable(cfg)
    p, temp = (table.channels[table.index(k)] for k in ("probe.p", "probe.temp"))
    assert (p.scale, temp.scale, p.is_status) == (10.0, 1.0, False)
    # the DBC export: the profile's units and scale
    db = build_dbc(cfg, table)
    sig = {s.name: s for m in db.messages for s in m.signals}
    assert (sig["probe_p"].unit, sig["probe_temp"].unit) == ("Pa", "degC")
    assert sig["probe_p"].scale == 10.0 and sig["probe_p"].is_signed
    # the simulated node: its channels, encoded to the profile's scale, on the bus
    node = SimNode("probe", PROBE.role, NODE_ID, eds, clock=lambda: 0.0)
    assert node.channel_names == ("p", "temp")
    node.boot(0.0)
    node.nmt(NMT_START, NODE_ID, 0.0)
    node.update({"p": 101_327.0, "temp": 21.5})  # 10 132.7 counts
    (frame,) = node.sync(1)
    assert frame.cob_id == 0x180 + NODE_ID
    assert table.decode(frame.cob_id, frame.data) == {"probe.p": 101_330.0, "probe.temp": 21.5}
    # and the whole simulated bus carries the node (the rig's other nodes unchanged)
    import threading

    from rsra.sim_bus.nodeset import NodeSet

    nodes = NodeSet(cfg, None, clock=lambda: 0.0, lock=threading.RLock())
    assert "probe" in nodes.by_name and nodes.by_name["probe"].channel_names == ("p", "temp")


def test_the_reader_refuses_an_eds_without_a_required_channel(probe_role, tmp_path):
    from rsra.daq.bus.decoder import DecodeTable

    cfg = _rig(_probe_eds(tmp_path, mapped=(0x24000220,)))  # the temperature only
    with pytest.raises(ConfigError, match=r"no TPDO maps the pressure_probe channel 'p'"):
        DecodeTable(cfg)


def test_the_packaged_profiles_are_the_bus_contract():
    """docs/bus.md §1 "Nodes": the objects, data types and units of each role."""
    want = {
        "load_cell": [("force", 0x6130, 1, "REAL32", "N"), ("status", 0x6150, 1, "UNSIGNED8", "")],
        "accelerometer": [(a, 0x6401, k, "INTEGER16", "m/s^2") for k, a in enumerate("xyz", 1)],
        "rotor_speed": [("omega", 0x2100, 1, "REAL32", "rad/s"),
                        ("azimuth", 0x2100, 2, "UNSIGNED16", "rad")],
        "balance": [(n, 0x2200, k, "REAL32", "N" if k <= 3 else "Nm")
                    for k, n in enumerate("XYZLMN", 1)],
        "drive_load": [("torque", 0x2300, 1, "REAL32", "Nm")],
    }
    got = {r: [(c.name, c.index, c.subindex, c.data_type, c.unit) for c in p.channels]
           for r, p in DEVICE_PROFILES.items()}
    assert got == want
    assert DEVICE_PROFILES["accelerometer"].channel("x").scale == devices.MILLI_G
    assert DEVICE_PROFILES["rotor_speed"].channel("azimuth").scale == devices.TURN
    assert DEVICE_PROFILES["load_cell"].channel("status").scale is None
    assert DEVICE_PROFILES["drive_load"].required == ()
