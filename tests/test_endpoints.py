"""Zenoh endpoints: a bad one is a one-line configuration error (exit 2) before anything
starts; `state/config` reports the endpoints the session really uses."""
from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import time
import tomllib

import pytest
import zenoh

from rsra.config.rig import ConfigError, default_config_path, load_config, parse_config
from rsra.daq.runtime.service import Outputs, ServiceOptions
from rsra.daq.runtime.telemetry import viewer_config
from tests.helpers_net import free_tcp_port

RAW = tomllib.loads(default_config_path().read_text())
BAD = ["nonsense", "tcp/", "tcp/127.0.0.1", "tcp/127.0.0.1:99999", "tcp/localhost:port",
       "foo/1.2.3.4:5", "tcp/::1:7447", "/127.0.0.1:7447"]
GOOD = ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:0", "udp/10.0.0.1:7447", "tcp/[::1]:7447",
        "tls/rig.local:7447", "tcp/127.0.0.1:7447?prio=1", "unixsock-stream//tmp/z.sock"]


@pytest.mark.parametrize("key", ["listen", "connect"])
@pytest.mark.parametrize("ep", BAD)
def test_a_bad_endpoint_is_a_config_error_naming_the_key(key, ep):
    raw = copy.deepcopy(RAW)
    raw["telemetry"][key] = ["tcp/127.0.0.1:7447", ep] if key == "listen" else [ep]
    with pytest.raises(ConfigError) as e:
        parse_config(raw, source="rig.toml", base_dir=default_config_path().parent)
    assert e.value.key == f"telemetry.{key}" and "fix:" in str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("ep", GOOD)
def test_good_endpoints_are_accepted(ep):
    raw = copy.deepcopy(RAW)
    raw["telemetry"]["listen"] = [ep]
    parse_config(raw, source="rig.toml", base_dir=default_config_path().parent)


def _rsra(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "rsra", *args], capture_output=True, text=True,
                          timeout=timeout, check=False,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})


def test_rsra_run_with_listen_nonsense_exits_2_in_one_line(tmp_path):
    """Before: exit 1 with Zenoh's Rust source paths (and no config key named)."""
    text = default_config_path().read_text().replace(
        'listen = ["tcp/127.0.0.1:7447"]', 'listen = ["nonsense"]')
    assert 'listen = ["nonsense"]' in text
    (tmp_path / "rig.toml").write_text(text)
    (tmp_path / "eds").symlink_to(default_config_path().parent / "eds")
    r = _rsra("run", "--config", str(tmp_path / "rig.toml"), "--sim", "ground-test",
              "--speed", "max", "--duration", "1")
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "telemetry.listen" in r.stderr and "nonsense" in r.stderr and ".rs" not in r.stderr


def test_a_bad_zenoh_listen_option_exits_2_in_one_line():
    r = _rsra("run", "--sim", "ground-test", "--speed", "max", "--duration", "1",
              "--zenoh-listen", "tcp/127.0.0.1:70000")
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "--zenoh-listen" in r.stderr and ".rs" not in r.stderr


def test_state_config_reports_the_endpoint_the_service_listens_on():
    """Before: state/config said tcp/127.0.0.1:7447 whatever --zenoh-listen said."""
    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    out = Outputs(cfg, ServiceOptions(zenoh_listen=[ep]))
    try:
        with zenoh.open(viewer_config([ep])) as v:
            reply = None
            for _ in range(20):
                got = [json.loads(r.ok.payload.to_string())
                       for r in v.get(f"{cfg.telemetry.prefix}/state/config", timeout=2) if r.ok]
                if got:
                    reply = got[0]
                    break
                time.sleep(0.1)
        assert reply is not None
        assert reply["telemetry"]["listen"] == [ep]
        assert reply["telemetry"]["connect"] == []
    finally:
        out.close()
