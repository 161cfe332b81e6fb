"""The rig TOML loader: the default loads; every mistake names the key, the value and the fix."""
import copy
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from rsra.config.rig import ConfigError, default_config_path, load_config
from rsra.daq.rigmodel import parse_rig


@pytest.fixture(scope="module")
def raw():
    return tomllib.loads(default_config_path().read_text())


def bad(raw, mutate):
    r = copy.deepcopy(raw)
    mutate(r)
    with pytest.raises(ConfigError) as ei:  # as the commands load a rig: parsed, then checked
        parse_rig(r, source="rig.toml", base_dir=default_config_path().parent)
    return ei.value


def test_default_loads(cfg):
    assert len(cfg.cells) == 7 and cfg.sample_rate_hz == 200.0
    assert cfg.rotor.blades == 5 and cfg.filter.harmonics == (1, 5)
    assert cfg.telemetry.prefix == "rsra/bench" and not cfg.telemetry.multicast_scouting
    assert cfg.telemetry.listen == ("tcp/127.0.0.1:7447",)
    assert {n.node_id for n in cfg.nodes} >= set(range(0x11, 0x18)) | {0x21}
    np.testing.assert_allclose(cfg.rig_model().cell_sigma, 111.206)


def test_packaged_config_is_found_outside_the_repo(tmp_path):
    out = subprocess.run([sys.executable, "-c", "from rsra.config.rig import load_config; "
                          "print(load_config().rig_name)"], cwd=tmp_path, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "bench"


@pytest.mark.parametrize("mutate,key,words", [
    (lambda r: r["mass"].__setitem__("effective_mass_kg", [1995.8, -5.0, 1995.8]),
     "mass.effective_mass_kg[1]", "> 0"),
    (lambda r: r["cells"][1].__setitem__("name", "A"), "cells[1].name", "listed twice"),
    (lambda r: r["filter"].__setitem__("tuning", "time_constnat"), "filter.tuning", "did you mean"),
    (lambda r: r["filter"].__setitem__("time_constnat_s", 0.1), "filter.time_constnat_s", "unknown key"),
    (lambda r: r["identification"].__setitem__("window_s", 10.0), "identification.window_s", "period"),
    (lambda r: r["nodes"][1].__setitem__("node_id", 0x11), "nodes[1].node_id", "already used"),
    (lambda r: r["nodes"][0].__setitem__("node_id", 200), "nodes[0].node_id", "1…127"),
    (lambda r: r["nodes"][0].__setitem__("eds", "eds/nope.eds"), "nodes[0].eds", "not found"),
    (lambda r: r["cells"][0].__setitem__("node", "cell_Z"), "cells[0].node", "no [[nodes]]"),
    (lambda r: r["geometry"].__setitem__("hub_centre_m", [0.0, 0.0]), "geometry.hub_centre_m", "3 values"),
    (lambda r: r["rig"].__setitem__("sample_rate_hz", "fast"), "rig.sample_rate_hz", "number"),
    (lambda r: r["identification"].__setitem__("content_known_loads", "dc"),
     "identification.content_known_loads", "unknown value"),
    (lambda r: r["telemetry"].__setitem__("prefix", "rsra/*"), "telemetry.prefix", "Zenoh"),
    (lambda r: r["filter"].__setitem__("harmonics", [1, 1]), "filter.harmonics", "distinct"),
    (lambda r: r["inertial"].__setitem__("angular", "least_squares"), "inertial.angular", "non-collinear"),
    (lambda r: r["identification"].__setitem__("parameters", ["delta_A", "hub_z"]),
     "identification.parameters", "angles only"),
])
def test_errors_name_key_value_and_fix(raw, mutate, key, words):
    e = bad(raw, mutate)
    assert e.key == key
    assert words in str(e)
    assert "fix:" in str(e) and e.fix


def test_singular_S_is_refused(raw):
    def coplanar(r):  # every cell vertical except one: S loses rank
        for c in r["cells"][4:]:
            c["nominal_axis"] = [0.0, 0.0, -1.0]
    e = bad(raw, coplanar)
    assert "vertical" in str(e) or "singular" in str(e)

    def on_one_point(r):  # all cells through one point along three axes: no moments resisted
        for c in r["cells"]:
            c["position_m"] = [0.0, 0.0, 0.0]
    e = bad(raw, on_one_point)
    assert "singular" in str(e) and e.key == "cells"


def test_bad_toml_and_missing_file(tmp_path):
    p = tmp_path / "rig.toml"
    p.write_text("[rig\nname=1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")


def test_cli_config_error_is_one_line_exit_2(tmp_path):
    p = tmp_path / "rig.toml"
    text = default_config_path().read_text().replace("effective_mass_kg = [1995.8,", "effective_mass_kg = [0.0,")
    p.write_text(text.replace('eds = "eds/', f'eds = "{default_config_path().parent}/eds/'))
    r = subprocess.run([sys.executable, "-m", "rsra", "noise-budget", "--config", str(p)],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "mass.effective_mass_kg[0]" in r.stderr
    assert "Traceback" not in r.stderr


# -- layers (issue 29): a rig TOML holds only what differs --------------------------------------
def _cli(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rsra", *argv], capture_output=True,
                          text=True, timeout=120, check=False)


def test_an_empty_rig_file_is_the_default_rig(cfg, tmp_path):
    """Before: `geometry = None: is missing; fix: add geometry = … to []`."""
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    got = load_config(empty)
    assert got.effective() == cfg.effective()
    assert set(got.origins.values()) == {"default"}


def test_a_rig_file_of_one_key_works_and_config_show_names_its_origin(cfg, tmp_path):
    one = tmp_path / "tilt.toml"
    one.write_text("[geometry]\nshaft_tilt_deg = 3.5\n")
    got = load_config(one)
    assert np.isclose(np.degrees(got.shaft_tilt_rad), 3.5)
    assert np.array_equal(got.hub_centre_m, cfg.hub_centre_m)  # the rest: the default's
    assert [c.position_m.tolist() for c in got.cells] == [c.position_m.tolist() for c in cfg.cells]
    assert got.origins["geometry.shaft_tilt_deg"] == str(one)
    assert got.origins["geometry.hub_centre_m"] == "default"
    r = _cli("config", "show", "--config", str(one))
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("shaft_tilt_deg"))
    assert line.split("#")[1].strip() == str(one)
    hub = next(ln for ln in r.stdout.splitlines() if ln.startswith("hub_centre_m"))
    assert hub.split("#")[1].strip() == "default"
    # what it prints is a complete rig TOML: given back as --config, the same rig
    shown = tmp_path / "shown.toml"
    shown.write_text(r.stdout)
    again = load_config(shown)
    assert np.isclose(again.shaft_tilt_rad, got.shaft_tilt_rad)
    assert [n.eds for n in again.nodes] == [n.eds for n in got.nodes]


def test_several_config_files_apply_in_order_and_extends_names_a_base(tmp_path):
    base = tmp_path / "base.toml"
    base.write_text('[rig]\nname = "base"\n[geometry]\nshaft_tilt_deg = 1.0\n')
    ext = tmp_path / "ext.toml"
    ext.write_text('extends = "base.toml"\n[geometry]\nshaft_tilt_deg = 2.0\n')
    late = tmp_path / "late.toml"
    late.write_text('[rig]\nname = "late"\n')
    got = load_config([ext, late])
    assert got.rig_name == "late" and np.isclose(np.degrees(got.shaft_tilt_rad), 2.0)
    assert got.origins["rig.name"] == str(late)
    assert got.origins["geometry.shaft_tilt_deg"] == str(ext)
    assert load_config(ext).rig_name == "base"  # from the base it extends
    loop = tmp_path / "loop.toml"
    loop.write_text('extends = "loop.toml"\n')
    with pytest.raises(ConfigError) as ei:
        load_config(loop)
    assert "circle" in str(ei.value) and "; fix: " in str(ei.value)


def test_a_bad_value_in_a_layer_is_refused_in_one_line_naming_that_file(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[geometry]\nshaft_tilt_deg = 3.0\n")
    badf = tmp_path / "bad.toml"
    badf.write_text('[filter]\nharmonics = "x"\n')
    r = _cli("config", "show", "--config", str(good), "--config", str(badf))
    assert r.returncode == 2 and r.stdout == ""
    err = r.stderr.strip()
    assert "\n" not in err and str(badf) in err and "filter.harmonics" in err and "fix:" in err
    typo = tmp_path / "typo.toml"
    typo.write_text("[geometry]\nshaft_tilt_degs = 3.0\n")
    with pytest.raises(ConfigError) as ei:
        load_config([good, typo])
    assert ei.value.source == str(typo) and 'rename it to "shaft_tilt_deg"' in str(ei.value)


def test_the_packaged_rig_as_a_layer_is_the_packaged_rig(cfg):
    got = load_config(default_config_path())
    strip = lambda d: {k: v for k, v in d.items() if k != "nodes"}  # noqa: E731
    assert strip(got.effective()) == strip(cfg.effective())
    assert [n.eds for n in got.nodes] == [n.eds for n in cfg.nodes]


def test_a_missing_key_says_where_to_add_it_and_prints_no_none(raw, tmp_path):
    """Only a rig given whole (parse_config) or an array of tables a layer replaces can lack a
    key; the line names it and its block, never `= None`."""
    e = bad(raw, lambda r: r.pop("geometry"))
    assert e.key == "geometry" and "None" not in str(e) and "is missing" in str(e)
    assert "[geometry]" in e.fix
    e = bad(raw, lambda r: r["cells"][3].pop("full_scale_N"))
    assert str(e) == ("rig.toml: cells[3].full_scale_N: is missing; fix: add full_scale_N = … "
                      "to this [[cells]] block")
    e = bad(raw, lambda r: r["geometry"].pop("hub_centre_m"))
    assert str(e).endswith("geometry.hub_centre_m: is missing; fix: add hub_centre_m = … to "
                           "[geometry]")
    # a layer replacing [[accelerometers]] with an incomplete block: named with its file
    layer = tmp_path / "acc.toml"
    layer.write_text('[[accelerometers]]\nname = "acc1"\nnode = "accel_1"\n'
                     'position_m = [0.0, 0.0, 0.0]\nfull_scale_g = 7.0\n')
    with pytest.raises(ConfigError) as ei:
        load_config(layer)
    assert str(ei.value) == (f"{layer}: accelerometers[0].accuracy_fs: is missing; fix: add "
                             "accuracy_fs = … to this [[accelerometers]] block")


def test_types_are_not_coerced(raw):
    """pydantic's strict mode: a string is not a number, a number is not a boolean."""
    e = bad(raw, lambda r: r["rig"].__setitem__("sample_rate_hz", "200"))
    assert e.key == "rig.sample_rate_hz" and "must be a finite number" in str(e)
    e = bad(raw, lambda r: r["rotor"].__setitem__("stopped", 1))
    assert e.key == "rotor.stopped" and "true or false" in str(e)
    e = bad(raw, lambda r: r["rotor"].__setitem__("blades", 5.5))
    assert e.key == "rotor.blades" and "whole number" in str(e)
    e = bad(raw, lambda r: r["cells"][2].__setitem__("position_m", [0.0, "x", 0.0]))
    assert e.key == "cells[2].position_m[1]" and "fix:" in str(e)
    cfg = parse_rig({**copy.deepcopy(raw), "heartbeat": {"producer_ms": 100.0}},
                    source="rig.toml", base_dir=default_config_path().parent)
    assert cfg.heartbeat.producer_ms == 100 and isinstance(cfg.heartbeat.producer_ms, int)


def _same(x, y, path=""):
    """Field-by-field equality of two RigConfig values (arrays exactly, EDS paths as files)."""
    import dataclasses
    from pathlib import Path

    if dataclasses.is_dataclass(x):
        assert type(x) is type(y), path
        for f in dataclasses.fields(x):
            if f.name not in ("origins", "raw", "source"):
                _same(getattr(x, f.name), getattr(y, f.name), f"{path}.{f.name}")
    elif isinstance(x, np.ndarray):
        assert x.dtype == y.dtype and np.array_equal(x, y), (path, x, y)
    elif isinstance(x, (tuple, list)):
        assert type(x) is type(y) and len(x) == len(y), (path, x, y)
        for i, (u, v) in enumerate(zip(x, y)):
            _same(u, v, f"{path}[{i}]")
    elif isinstance(x, dict):
        assert x.keys() == y.keys(), path
        for k in x:
            _same(x[k], y[k], f"{path}.{k}")
    elif isinstance(x, Path):
        assert x.resolve() == Path(y).resolve(), (path, x, y)
    else:
        assert type(x) is type(y) and x == y, (path, x, y)


def test_the_flight_rig_layer_is_the_full_copy_it_replaced(tmp_path):
    """config/flight-rig.toml was a 293-line copy of the default rig; as a layer holding only
    what differs it gives the same rig, value for value (tests/fixtures/flight-rig-full.json:
    the copy as it was, read by tomllib)."""
    import json
    from pathlib import Path

    from rsra.config.rig import config_dir, parse_config

    flight = config_dir() / "flight-rig.toml"
    full = json.loads((Path(__file__).parent / "fixtures" / "flight-rig-full.json").read_text())
    # what changed on purpose since: the default stale_fraction (issue 29 item 4: windows
    # with missing samples are used; filter-error windows refuse scattered ones), the flight
    # rig's update rule and its angles' load sensitivity (issue 25); the known-load curvature check (issue 27)
    full["identification"].update(stale_fraction=0.5, filter_error_update="consider",
                                  filter_error_floor_deg=0.05,
                                  filter_error_scattered_fraction=0.02, nonlinearity_check=True,
                                  nonlinearity_limit=1.0,
                                  angle_load_sensitivity_deg_per_unit=[0.0, 0.0, 1.0e-5,
                                                                       0.0, 0.0, 0.0],
                                  # the packaged bound on the angles' drift rate
                                  angle_drift_rate_deg_per_s=0.002)
    # issue 25 item 5: the advice's candidates (the default's band and excitations, the
    # flight rig's own accelerometer positions)
    full["identification"]["advice"] = {
        "enabled": True, "band_hz": [5.0, 40.0],
        "manoeuvre_rms": [3000.0, 3000.0, 3000.0, 200.0, 200.0, 200.0],
        "accelerometers": [{"name": "deck_aft_left", "position_m": [-0.7, -0.9, 0.35]},
                           {"name": "deck_aft_right", "position_m": [-0.7, 0.9, 0.35]},
                           {"name": "gearbox_top", "position_m": [0.0, 0.0, -0.35]}]}
    layer = load_config(flight)
    _same(layer, parse_config(full, base_dir=config_dir()))
    strip = lambda d: {k: v for k, v in d.items() if k != "nodes"}  # noqa: E731
    assert strip(layer.raw) == strip(full)
    assert [{**n, "eds": Path(n["eds"]).name} for n in layer.raw["nodes"]] == \
        [{**n, "eds": Path(n["eds"]).name} for n in full["nodes"]]
    assert len(flight.read_text().splitlines()) < 150  # was 297
    assert layer.origins["accelerometers"] == str(flight)
    assert layer.origins["rotor.harmonic_phase"] == str(flight)
    assert layer.origins["rotor.blades"] == "default"
    assert layer.origins["geometry.hub_centre_m"] == "default"
    r = _cli("config", "show", "--config", str(flight))
    assert r.returncode == 0, r.stderr
    origin = {ln.split("=")[0].strip(): ln.split("#")[-1].strip()
              for ln in r.stdout.splitlines() if "=" in ln and "#" in ln}
    assert origin["harmonic_phase"] == origin["content_filter_error"] == str(flight)
    assert origin["shaft_tilt_deg"] == origin["omega_nominal_rad_s"] == "default"


def test_a_layer_named_by_a_relative_path_finds_its_eds_files(tmp_path):
    """`rsra config show --config config/flight-rig.toml` from the source tree said
    `nodes[0].eds = 'config/eds/load_cell.eds': file not found` (the layer's EDS paths were
    made relative to the working folder, then looked up in the package's)."""
    from rsra.config.rig import config_dir

    layer = tmp_path / "sub" / "rig.toml"
    (layer.parent / "eds").mkdir(parents=True)
    for name in ("load_cell.eds", "accelerometer.eds"):
        (layer.parent / "eds" / name).write_bytes((config_dir() / "eds" / name).read_bytes())
    layer.write_text((config_dir() / "flight-rig.toml").read_text())
    r = subprocess.run([sys.executable, "-m", "rsra", "config", "show", "--config",
                        "sub/rig.toml"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    eds = [ln for ln in r.stdout.splitlines() if ln.startswith("eds =")]
    assert len(eds) == 12 and str(layer.parent / "eds" / "load_cell.eds") in eds[0]
