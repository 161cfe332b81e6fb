"""`--foxglove`: the Foxglove WebSocket output, checked with a protocol client (the `websockets`
library speaking the SDK's subprotocol), not the Foxglove app (not installable offline here).

Every telemetry key advertised with its JSON schema; every message valid against it, equal to
the JSONL record of the same run (the `--out` sink) and logged at its acquisition time; a web
page's Origin refused; the server closed and its port released at exit. No timing asserted.
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest
from helpers_net import free_tcp_port

pytest.importorskip("foxglove", reason="needs foxglove-sdk (a dependency of rsra)")
websockets = pytest.importorskip("websockets", reason="needs the websockets library")

from rsra.daq.runtime import foxglove_out  # noqa: E402
from rsra.config.rig import load_config  # noqa: E402
from rsra.daq.analysis.export import FIELDS, json_schema  # noqa: E402
from rsra.daq.runtime.foxglove_out import SUBPROTOCOL, FoxgloveOutput  # noqa: E402
from rsra.daq.runtime.service import Service, ServiceOptions, jsonl_sink  # noqa: E402

try:
    import jsonschema
except ImportError:  # pragma: no cover - installed with the test extra
    jsonschema = None

pytestmark = pytest.mark.timeout(300)  # a hang (a publish that waits for a client) fails

MESSAGE_DATA = 1  # binary opcode of a server message (topic data)


def _connect(port: int, **kw):
    return websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                              open_timeout=10, max_size=2**24, **kw)


async def _hello(ws) -> dict[str, dict]:
    """serverInfo, then the advertised channels by topic."""
    info = json.loads(await asyncio.wait_for(ws.recv(), 10))
    assert info["op"] == "serverInfo"
    channels: dict[str, dict] = {}
    while len(channels) < len(FIELDS):
        msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
        if msg["op"] == "advertise":
            channels.update({c["topic"]: c for c in msg["channels"]})
    return channels


async def _subscribe(ws, channels: dict[str, dict]) -> dict[int, str]:
    subs = {i: topic for i, topic in enumerate(sorted(channels), start=1)}
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}))
    return subs


def _decode(frame: bytes) -> tuple[int, int, dict]:
    op, sub, log_time = struct.unpack_from("<BIQ", frame, 0)
    assert op == MESSAGE_DATA
    return sub, log_time, json.loads(frame[13:])


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def test_every_key_is_served_with_its_schema_its_record_and_its_acquisition_time(
        cfg, tmp_path, monkeypatch):
    """Lock-step run (ground test, 2.5 s, identification every second: hub loads, channels,
    innovations, health, angles records): the client is subscribed before the first record
    (a sink holds it), and the backlog is larger than the run, so every record must arrive."""
    monkeypatch.setattr(foxglove_out, "BACKLOG", 100_000)
    out = tmp_path / "records.jsonl"
    opts = ServiceOptions(sim="ground-test", speed=None, duration=2.5, zenoh=False,
                          foxglove="127.0.0.1:0", foxglove_announce=lambda line: None)
    fast = dataclasses.replace(cfg, identification=dataclasses.replace(
        cfg.identification, period_s=1.0, window_s=1.0, apply_delay_s=0.2))
    svc = Service(fast, opts)
    jsink, jclose = jsonl_sink(out)
    svc.add_sink(jsink)
    port_known, subscribed = threading.Event(), threading.Event()

    def hold_first(key, payload):
        if not port_known.is_set():
            port_known.set()
            assert subscribed.wait(20)

    svc.add_sink(hold_first)
    result = {}
    th = threading.Thread(target=lambda: result.update(svc.run()), daemon=True)
    th.start()
    assert port_known.wait(60)
    fox = svc.outputs.foxglove
    prefix = cfg.telemetry.prefix

    async def client():
        got: list[tuple[str, int, dict]] = []
        async with _connect(fox.port) as ws:
            channels = await _hello(ws)
            subs = await _subscribe(ws, channels)
            for _ in range(500):  # the SDK has taken the subscriptions
                if all(ch.has_sinks() for ch in fox.channels.values()):
                    break
                await asyncio.sleep(0.01)
            subscribed.set()
            while True:
                try:
                    frame = await asyncio.wait_for(ws.recv(), 30)
                except websockets.ConnectionClosed:
                    break  # the service closed the server at its end
                if isinstance(frame, bytes):
                    sub, t_ns, msg = _decode(frame)
                    got.append((subs[sub], t_ns, msg))
        return channels, got

    channels, got = asyncio.run(client())
    th.join(60)
    jclose()
    assert not th.is_alive()
    # every key advertised, JSON with the JSON schema of docs/telemetry.md (daq.export)
    assert set(channels) == {f"{prefix}/{k}" for k in FIELDS}
    for key in FIELDS:
        c = channels[f"{prefix}/{key}"]
        assert (c["encoding"], c["schemaEncoding"], c["schemaName"]) == (
            "json", "jsonschema", f"rsra.{key}")
    schemas = {t: json.loads(c["schema"]) for t, c in channels.items()}
    assert schemas == {f"{prefix}/{k}": json_schema(k) for k in FIELDS}
    records: dict[str, list[dict]] = {}
    for line in out.read_text().splitlines():
        rec = json.loads(line)
        records.setdefault(f"{prefix}/{rec.pop('key')}", []).append(rec)
    received: dict[str, list[tuple[int, dict]]] = {}
    for topic, t_ns, msg in got:
        received.setdefault(topic, []).append((t_ns, msg))
    assert set(records) == {f"{prefix}/{k}" for k in ("hub_loads", "channels", "innovations",
                                                      "health", "angles")}
    for topic, recs in records.items():
        msgs = received.get(topic, [])
        assert [m for _, m in msgs] == recs, topic  # values equal, none lost, in order
        assert [t for t, _ in msgs] == [round(r["t"] * 1e9) for r in recs], topic
        if jsonschema is not None:
            validator = jsonschema.Draft202012Validator(schemas[topic])
            for _, m in msgs:
                validator.validate(m)
    last = records[f"{prefix}/health"][-1]["foxglove"]
    assert last["clients"] == 1 and last["refused"] == 0 and last["published"] > 0
    assert svc.outputs.foxglove is None  # closed with the service


def test_a_schema_refuses_a_payload_of_the_wrong_type(cfg):
    """The schemas can fail: a string where the docs say a number is refused."""
    if jsonschema is None:
        pytest.skip("needs jsonschema")

    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"seq": 1, "t": "noon", "H": [1.0]}, json_schema("hub_loads"))


def test_a_web_page_origin_is_refused_and_a_named_one_let_in():
    fox = FoxgloveOutput("rsra/test", "127.0.0.1", 0, allowed_origins=["https://app.example"],
                         announce=lambda line: None)
    try:
        async def attempts():
            with pytest.raises(websockets.InvalidStatus) as e:
                async with _connect(fox.port, origin="https://evil.example"):
                    pass
            assert e.value.response.status_code == 403
            for origin in (None, "https://app.example"):
                async with _connect(fox.port, origin=origin) as ws:
                    assert len(await _hello(ws)) == len(FIELDS)

        asyncio.run(attempts())
        assert fox.gate.refused == 1 and fox.gate.connections == 2
    finally:
        fox.close()


def test_a_client_that_stops_reading_never_blocks_publishing_and_loses_the_oldest():
    """A subscribed client that reads nothing while 240 messages of 100 kB (24 MB, more than
    every socket buffer on the way) are published: every publish returns, and when the client
    reads again it gets the newest message and not all of them (the SDK dropped the oldest
    for it). The relay holds nothing back: it only passes on what the SDK sends."""
    fox = FoxgloveOutput("rsra/test", "127.0.0.1", 0, backlog=16, announce=lambda line: None)
    n = 240
    try:
        async def stalled():
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.connect(("127.0.0.1", fox.port))
            async with _connect(fox.port, sock=sock, max_queue=1) as ws:
                channels = await _hello(ws)
                await _subscribe(ws, {t: c for t, c in channels.items()
                                      if t.endswith("/health")})
                for _ in range(500):
                    if fox.channels["health"].has_sinks():
                        break
                    await asyncio.sleep(0.01)
                pad = "x" * 100_000
                for i in range(n):  # from this thread: it must never wait for the client
                    fox.publish("health", {"t": 1000.0 + i, "seq": i, "warnings": [pad]})
                assert fox.published == n
                seqs = []
                while not seqs or seqs[-1] != n - 1:
                    _, t_ns, msg = _decode(await asyncio.wait_for(ws.recv(), 30))
                    assert t_ns == round(msg["t"] * 1e9)
                    seqs.append(msg["seq"])
                return seqs

        seqs = asyncio.run(stalled())
    finally:
        fox.close()
    assert seqs == sorted(seqs) and seqs[-1] == n - 1
    assert len(seqs) < n  # the oldest were dropped, not queued without bound


def test_rsra_run_serves_then_closes_its_server_and_releases_the_port(tmp_path):
    port = free_tcp_port()
    cmd = [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--duration", "2",
           "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--no-identification",
           "--log-level", "warning", "--foxglove", f"127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        async def client():
            deadline = time.monotonic() + 60
            while True:
                try:
                    ws = await _connect(port)
                    break
                except OSError:
                    assert proc.poll() is None and time.monotonic() < deadline
                    await asyncio.sleep(0.2)
            async with ws:
                channels = await _hello(ws)
                subs = await _subscribe(ws, {t: c for t, c in channels.items()
                                             if t.endswith("/hub_loads")})
                frame = await asyncio.wait_for(ws.recv(), 30)
                sub, t_ns, msg = _decode(frame)
                assert subs[sub].endswith("/hub_loads") and t_ns == round(msg["t"] * 1e9)
                with pytest.raises(websockets.ConnectionClosed):  # closed at the end
                    while True:
                        await asyncio.wait_for(ws.recv(), 60)

        asyncio.run(client())
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert f"Foxglove WebSocket on ws://127.0.0.1:{port}" in err
    with pytest.raises(ConnectionRefusedError):  # nobody listens there any more
        socket.create_connection(("127.0.0.1", port), timeout=5).close()
    with socket.socket() as s:  # released: a new server binds it at once (as servers do,
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # past the closed
        s.bind(("127.0.0.1", port))  # connections' TIME_WAIT)
        s.listen()


def test_the_option_defaults_to_loopback_8765_and_a_wider_bind_says_its_risk():
    from rsra.daq.cli import build_parser
    from rsra.daq.runtime.foxglove_out import risk_line

    p = build_parser()
    assert p.parse_args(["run", "--sim", "ground-test", "--foxglove"]).foxglove \
        == "127.0.0.1:8765"
    assert p.parse_args(["replay", "rec", "--foxglove"]).foxglove == "127.0.0.1:8765"
    assert p.parse_args(["demo"]).foxglove is None  # off unless asked
    for host in ("127.0.0.1", "127.0.0.2", "::1", "localhost"):
        assert risk_line(host, 8765) is None
    for host in ("0.0.0.0", "192.168.1.10", "::"):
        line = risk_line(host, 8765)
        assert "not loopback" in line and "no authentication" in line
    lines = []
    fox = FoxgloveOutput("rsra/test", "127.0.0.1", 0, announce=lines.append)
    fox.close()
    assert lines == [f"Foxglove WebSocket on ws://127.0.0.1:{fox.port} (open it in Foxglove: "
                     "Open connection → Foxglove WebSocket)"]
