"""Telemetry publisher: strict JSON, DROP publishers, state queryables, liveliness, and
`rsra listen --json` in a separate process."""
import json
import subprocess
import sys
import time

import zenoh

from rsra.config.rig import load_config
from rsra.daq.runtime.telemetry import TelemetryPublisher, viewer_config, zenoh_config
from tests.helpers_net import free_tcp_port


def test_publish_query_and_listen_subprocess(tmp_path):
    cfg = load_config()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as s:
        pub = TelemetryPublisher(s, "rsra/test", {"rig": {"name": "bench"},
                                                  "telemetry": {"zenoh_config": "<removed>"}})
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "rsra", "listen", "--prefix", "rsra/test", "--json",
                 "--zenoh-connect", ep, "--count", "5", "--duration", "30"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            # the subscriber announces itself; publish until it has its five messages
            seq = 0
            deadline = time.monotonic() + 25
            while proc.poll() is None and time.monotonic() < deadline:
                pub.publish("hub_loads", {"seq": seq, "H": [float("nan"), 1.0, 2, 3, 4, 5]})
                seq += 1
                time.sleep(0.02)
            out, err = proc.communicate(timeout=10)
            assert proc.returncode == 0, err
            recs = [json.loads(line) for line in out.splitlines()]
            assert len(recs) == 5
            assert all(r["key"] == "hub_loads" and r["H"][0] is None for r in recs)
            seqs = [r["seq"] for r in recs]
            assert seqs == sorted(seqs)

            pub.publish("angles", {"seq": 7, "alpha": [0.0] * 14})
            with zenoh.open(viewer_config([ep])) as v:
                replies = {}
                for _ in range(20):
                    replies = {str(r.ok.key_expr): json.loads(r.ok.payload.to_string())
                               for r in v.get("rsra/test/state/*", timeout=2) if r.ok}
                    if len(replies) >= 2:
                        break
                    time.sleep(0.1)
                assert replies["rsra/test/state/angles"]["seq"] == 7
                assert replies["rsra/test/state/config"]["telemetry"]["zenoh_config"] == "<removed>"
                alive = [str(r.ok.key_expr) for r in v.liveliness().get("rsra/test/alive", timeout=2)]
                assert alive == ["rsra/test/alive"]
        finally:
            pub.close()


def test_default_zenoh_config_is_loopback_only_without_multicast():
    cfg = load_config()
    conf = zenoh_config(cfg.telemetry)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    v = viewer_config(["tcp/127.0.0.1:7447"])
    assert json.loads(v.get_json("listen/endpoints")) == []
    assert json.loads(v.get_json("scouting/multicast/enabled")) is False


def test_an_idle_publisher_runs_no_python_code():
    """Nothing polls for state queries: a thread polling every 10 ms woke the GIL 100 times a
    second (an idle service's CPU 9.4 ms/s with it, 0.04 ms/s without). The queryable is a
    Zenoh callback answering from the cached bytes; idle, no Python function is called in any
    thread the publisher started (counted with a profile hook, not timed)."""
    import threading

    calls = []

    def count(frame, event, arg):
        if event in ("call", "c_call"):
            calls.append(threading.current_thread().name)

    cfg = load_config()
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[], connect=[])) as s:
        threading.setprofile(count)  # threads started from here on
        try:
            pub = TelemetryPublisher(s, "rsra/idle")
        finally:
            threading.setprofile(None)
        try:
            pub.publish("angles", {"seq": 3, "alpha": [0.0] * 14})
            replies = [r.ok for r in s.get("rsra/idle/state/angles", timeout=2) if r.ok]
            assert [json.loads(r.payload.to_string())["seq"] for r in replies] == [3]
            time.sleep(0.2)
            calls.clear()
            time.sleep(1.0)  # idle: a 10-ms poll would make >= 100 calls here
            assert calls == []
        finally:
            pub.close()
