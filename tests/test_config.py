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
