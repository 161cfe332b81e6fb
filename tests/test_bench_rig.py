"""The bench rig's topology in real time, bounded (issue 17): the shared-bus server
(`rsra bus`), `rsra sim` in one process, `rsra nodes` against it, then `rsra run` in another
and an independent Zenoh subscriber (this process) — the live CANopen master booting,
supervising and recovering nodes that live in another process. Nothing here asserts timing."""
from __future__ import annotations

import http.client
import json
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("can_remote", reason="python-can-remote (the shared bus) is not installed")
zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh is not installed")

from rsra.daq.runtime.telemetry import viewer_config  # noqa: E402
from tests.helpers_net import free_tcp_port  # noqa: E402
from tests.helpers_proc import die_with_parent as _die_with_parent  # noqa: E402
from tests.helpers_proc import spawn as _spawn  # noqa: E402

RUN_S = 6.0  # samples of acquisition time the service runs for
REBOOT_AT = 2.0  # simulated seconds: cell_C power-cycles, the live master must restart it


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _port_free(port: int) -> bool:
    """A new server can listen on ``port`` (as rsra bus would: connections the old one
    closed may linger in TIME_WAIT, which SO_REUSEADDR allows, a listener does not)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            return False
        return True


def _upgrade_status(port: int, origin: str | None) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    headers = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
               "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
               "Sec-WebSocket-Protocol": "can.json.v1"}
    if origin:
        headers["Origin"] = origin
    conn.request("GET", "/", headers=headers)
    status = conn.getresponse().status
    conn.close()
    return status


def test_bench_rig_across_processes_on_the_shared_bus(cfg, tmp_path):
    port, zport = free_tcp_port(), free_tcp_port()
    url = f"ws://127.0.0.1:{port}/"
    ep = f"tcp/127.0.0.1:{zport}"
    children: list[subprocess.Popen] = []
    logs = {n: open(tmp_path / f"{n}.log", "w+") for n in ("bus", "sim", "run")}
    hub, health = [], []
    lock = threading.Lock()

    def on_hub(s):
        with lock:
            hub.append(json.loads(s.payload.to_string()))

    def on_health(s):
        with lock:
            health.append(json.loads(s.payload.to_string()))

    try:
        bus = _spawn(["bus", "--port", str(port)], stderr=logs["bus"])
        children.append(bus)
        deadline = time.monotonic() + 30
        while not _port_open(port):
            assert bus.poll() is None and time.monotonic() < deadline, "rsra bus did not start"
            time.sleep(0.1)
        # a web page's WebSocket (browsers always send Origin) is refused
        assert _upgrade_status(port, "http://evil.example") == 403
        sim = _spawn(["sim", "--scenario", "ground-test", "--interface", "remote",
                      "--channel", url, "--seed", "4", "--faults", f"reboot:cell_C@{REBOOT_AT}"],
                     stderr=logs["sim"])
        children.append(sim)
        # rsra nodes before the master starts (two SDO clients never cross)
        nodes = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            r = subprocess.run([sys.executable, "-m", "rsra", "nodes", "--interface", "remote",
                                "--channel", url, "--json"], capture_output=True, text=True,
                               timeout=120, preexec_fn=_die_with_parent)
            if r.returncode == 0:
                nodes = json.loads(r.stdout)
                break
            assert sim.poll() is None, "rsra sim died"
            time.sleep(0.5)
        assert nodes is not None and nodes["ok"], r.stdout + r.stderr
        assert {n["name"] for n in nodes["nodes"]} >= {f"cell_{c}" for c in "ABCDEFG"}

        prefix = cfg.telemetry.prefix
        with zenoh.open(viewer_config([], listen=[ep])) as z:
            subs = [z.declare_subscriber(f"{prefix}/hub_loads", on_hub),
                    z.declare_subscriber(f"{prefix}/health", on_health)]
            run = _spawn(["run", "--interface", "remote", "--channel", url, "--duration",
                          str(RUN_S), "--zenoh-connect", ep, "--zenoh-listen",
                          f"tcp/127.0.0.1:{free_tcp_port()}"], stdout=subprocess.PIPE,
                         stderr=logs["run"])
            children.append(run)
            out, _ = run.communicate(timeout=180)
            time.sleep(0.3)
            for s in subs:
                s.undeclare()
        logs["run"].seek(0)
        run_err = logs["run"].read()
        assert run.returncode == 0, run_err
        assert "Traceback" not in run_err and "Exception ignored" not in run_err, run_err
        summary = json.loads(out.strip().splitlines()[-1])["summary"]
        assert summary["samples"] > 0

        with lock:
            seqs = [h["seq"] for h in hub]
            assert seqs and seqs == sorted(set(seqs)), "samples out of order or repeated"
            # complete samples arrive (every node reported). How many is a matter of timing
            # on a loaded machine (answers after the next SYNC): not asserted; the recovery of
            # the rebooted node is judged by the master's health below
            complete = [h for h in hub if not any(f.startswith("missing:") for f in h["flags"])]
            assert complete
            # the rebooted node was seen booting again and restarted by the live master
            last = health[-1]
        assert last["nodes"]["cell_C"]["boots"] >= 2, last["nodes"]["cell_C"]
        assert last["nodes"]["cell_C"]["state"] == "operational", last["nodes"]["cell_C"]

        sim.send_signal(signal.SIGINT)
        assert sim.wait(timeout=30) == 0
        bus.send_signal(signal.SIGTERM)
        assert bus.wait(timeout=30) == 0
        for n in ("sim", "bus"):
            logs[n].seek(0)
            text = logs[n].read()
            assert "Traceback" not in text and "Exception ignored" not in text, text
        logs["bus"].seek(0)
        assert "1 browser connection(s) refused" in logs["bus"].read()
        assert _port_free(port), "the shared bus's port was not released"
    finally:
        for p in children:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        for f in logs.values():
            f.close()
