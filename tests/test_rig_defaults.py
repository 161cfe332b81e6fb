"""Each default of the rig TOML is written once, in the schema (config.rigfile): the loader's
dataclasses (config.rig) are built from the validated tables and write none of their own."""
import copy
import dataclasses
import math
import tomllib

import pytest

from rsra.config import rig, rigfile
from rsra.config.rig import default_config_path, parse_config


@pytest.fixture(scope="module")
def raw():
    return tomllib.loads(default_config_path().read_text())


@pytest.fixture
def schema_default():
    """Change a schema table's default for one test (the tables rebuilt, then restored)."""
    changed: list[tuple[type, str, object]] = []

    def change(table: type, key: str, value: object) -> None:
        changed.append((table, key, table.model_fields[key].default))
        table.model_fields[key].default = value
        table.model_rebuild(force=True)
        rigfile.RigFile.model_rebuild(force=True)

    yield change
    for table, key, old in reversed(changed):
        table.model_fields[key].default = old
        table.model_rebuild(force=True)
    rigfile.RigFile.model_rebuild(force=True)


# (table, key, the schema's new default, the RigConfig path, the value it must then hold)
CHANGES = [
    ("identification", rigfile.IdentificationTable, "filter_error_scattered_fraction", 0.05,
     "identification.filter_error_scattered_fraction", 0.05),
    ("identification", rigfile.IdentificationTable, "angle_limit_deg", 7.0,
     "identification.angle_limit_rad", math.radians(7.0)),
    ("simulator", rigfile.SimulatorTable, "damping_ratio", 0.03, "simulator.damping_ratio", 0.03),
    ("stuck", rigfile.StuckTable, "max_delay_s", 0.25, "stuck.max_delay_s", 0.25),
    ("rotor", rigfile.RotorTable, "harmonic_phase", "azimuth", "rotor.harmonic_phase", "azimuth"),
    ("telemetry", rigfile.TelemetryTable, "innovations_hz", 10.0, "telemetry.innovations_hz",
     10.0),
]


@pytest.mark.parametrize("section,table,key,new,path,want", CHANGES,
                         ids=[f"{c[0]}.{c[2]}" for c in CHANGES])
def test_a_default_changed_in_the_schema_reaches_the_rig_config(
        raw, schema_default, section, table, key, new, path, want):
    r = copy.deepcopy(raw)
    r[section].pop(key, None)  # the packaged rig gives most keys: leave this one to the default
    schema_default(table, key, new)
    value = parse_config(r)
    for part in path.split("."):
        value = getattr(value, part)
    assert value == pytest.approx(want) if isinstance(want, float) else value == want


def test_the_dataclasses_write_no_default_of_their_own():
    # every field the rig TOML gives comes from the schema; only what is not in the file (the
    # raw tables, the origins of the values) may have a default here
    own = []
    for name, obj in vars(rig).items():
        if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == rig.__name__:
            own += [f"{name}.{f.name}" for f in dataclasses.fields(obj)
                    if f.default is not dataclasses.MISSING
                    or f.default_factory is not dataclasses.MISSING]
    assert own == ["RigConfig.raw", "RigConfig.origins"]
