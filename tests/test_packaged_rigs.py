"""Packaged rigs by name (issue 51): `--config flight`, `--config default`, `extends =
"flight"`, listed by `rsra config list`; an existing path always wins."""
from __future__ import annotations

import json

import pytest

from rsra.config.rig import ConfigError, load_config, packaged_rigs
from rsra.daq.cli import main


def test_names_pick_the_packaged_rigs():
    rigs = packaged_rigs()
    assert set(rigs) >= {"default", "flight"}
    assert load_config("flight").rig_name == "flight"
    assert load_config("default").rig_name == load_config().rig_name


def test_an_existing_path_always_wins(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "flight").write_text('[rig]\nname = "mine"\n')
    assert load_config("flight").rig_name == "mine"


def test_extends_takes_a_name_and_a_file_beside_it_wins(tmp_path):
    top = tmp_path / "top.toml"
    top.write_text('extends = "flight"\n[filter]\ntime_constant_s = 0.12\n')
    cfg = load_config(top)
    assert cfg.rig_name == "flight" and cfg.filter.time_constant_s == 0.12
    (tmp_path / "flight").write_text('[rig]\nname = "beside"\n')
    assert load_config(top).rig_name == "beside"


def test_an_unknown_name_lists_the_packaged_ones(capsys):
    with pytest.raises(ConfigError, match=r"packaged rig's name \(default, flight"):
        load_config("hover")
    assert main(["config", "show", "--config", "hover"]) == 2
    err = capsys.readouterr().err
    assert "rsra config list" in err and "\n" not in err.strip()


def test_config_list(capsys):
    assert main(["config", "list"]) == 0
    out = capsys.readouterr().out
    assert "default" in out and "flight" in out and "rsra/flight" in out
    assert main(["config", "list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {r["name"]: r["rig"] for r in rows}["flight"] == "flight"
