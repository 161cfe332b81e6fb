"""The shared bus (daq.sharedbus, `rsra bus`): python-can-remote's server on loopback,
browser origins refused, the port released, a client closed once (issue 17)."""
from __future__ import annotations

import http.client
import socket
import time

import can
import pytest

pytest.importorskip("can_remote", reason="python-can-remote (the shared bus) is not installed")

from rsra.canbus import shutdown_bus  # noqa: E402
from rsra.daq.bus.sharedbus import BusServer  # noqa: E402


def _upgrade(port: int, origin: str | None) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    headers = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
               "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
               "Sec-WebSocket-Protocol": "can.json.v1"}
    if origin is not None:
        headers["Origin"] = origin
    conn.request("GET", "/", headers=headers)
    status = conn.getresponse().status
    conn.close()
    return status


def test_frames_pass_between_clients_and_a_browser_origin_is_refused():
    with BusServer(port=0, channel="t-share") as srv:
        assert srv.server.server_address[0] == "127.0.0.1" and srv.url.startswith("ws://127.")
        a = can.Bus(channel=srv.url, interface="remote")
        b = can.Bus(channel=srv.url, interface="remote")
        try:
            a.send(can.Message(arbitration_id=0x80, data=b"\x07", is_extended_id=False))
            m = b.recv(5)
            assert m is not None and m.arbitration_id == 0x80 and bytes(m.data) == b"\x07"
            for origin in ("http://evil.example", "null", "http://127.0.0.1:8000"):
                assert _upgrade(srv.port, origin) == 403
            assert srv.refused == 3
            assert _upgrade(srv.port, None) == 101  # python-can-remote's clients send none
        finally:
            shutdown_bus(a)
            shutdown_bus(b)
        port = srv.port
    with socket.socket() as s:  # released: a new server can listen there
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()


def test_a_client_whose_connection_the_server_dropped_is_closed_once():
    """python-can-remote's client: its shutdown raises ValueError (fd -1) when the server
    already closed the connection, and __del__ tries again; shutdown_bus closes it once."""
    with BusServer(port=0, channel="t-drop") as srv:
        bus = can.Bus(channel=srv.url, interface="remote")
        bus.remote_protocol.send_periodic_stop(0x123)  # no such task: the server drops us
        deadline = time.monotonic() + 5
        with pytest.raises(Exception):  # noqa: B017 - the library's WebsocketClosed
            while time.monotonic() < deadline:
                bus.recv(0.5)
        shutdown_bus(bus)  # no exception
        assert bus._is_shutdown  # so python-can's __del__ does not shut it down again


@pytest.mark.parametrize("argv, word", [(["--port", "70000"], "--port"),
                                        (["--interface", "nosuch", "--port", "0"], "nosuch")])
def test_rsra_bus_bad_input_is_one_line_exit_2(capsys, argv, word):
    from rsra.daq.cli import main

    assert main(["bus", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and word in err and "Traceback" not in err


# --------------------------------------------------------------------------------------
# the master's own copy of a frame comes back before any answer to it (rsra.canbus)

@pytest.mark.parametrize("echo_first", [True, False])
def test_the_senders_own_copy_is_queued_before_an_instant_answer(echo_first):
    """A responder opened first that answers the instant the frame reaches its queue (a
    thread switch between python-can's puts, made certain here): with python-can's plain
    virtual bus the answer overtakes the sender's own copy; with EchoFirstVirtualBus it never
    does. The plain case is asserted too, so the test shows it guards something."""
    from rsra.canbus import EchoFirstVirtualBus, open_bus

    ch = f"echo-first-{echo_first}"
    responder = can.Bus(interface="virtual", channel=ch)
    sender = (open_bus(interface="virtual", channel=ch, receive_own_messages=True)
              if echo_first else
              can.Bus(interface="virtual", channel=ch, receive_own_messages=True))
    assert isinstance(sender, EchoFirstVirtualBus) == echo_first
    put = responder.queue.put

    def answer_at_once(msg, *a, **kw):
        put(msg, *a, **kw)
        if msg.arbitration_id == 0x80:
            responder.send(can.Message(arbitration_id=0x193, data=b"\x01",
                                       is_extended_id=False))

    responder.queue.put = answer_at_once
    try:
        sender.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        order = [sender.recv(1.0).arbitration_id for _ in range(2)]
    finally:
        responder.shutdown()
        sender.shutdown()
    assert order == ([0x80, 0x193] if echo_first else [0x193, 0x80])


@pytest.mark.timeout(120)
def test_when_the_shared_bus_stops_the_simulator_says_so_and_keeps_its_truth(tmp_path):
    """`rsra bus` stopped under a running `rsra sim` (any order of stopping is allowed):
    the simulator ends with one line naming the failure, exit 1, no traceback, and the truth
    file the user asked for is written."""
    import subprocess
    import sys

    truth = tmp_path / "truth.npz"
    with BusServer(port=0, channel="t-gone") as srv:
        proc = subprocess.Popen(
            [sys.executable, "-m", "rsra", "sim", "--scenario", "ground-test", "--autostart",
             "--interface", "remote", "--channel", srv.url, "--truth", str(truth)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            line = proc.stdout.readline()  # its start line
            assert "rsra sim:" in line, line
            while "samples" not in (line := proc.stdout.readline()) or " 0 samples" in line:
                assert line, "the simulator ended before producing samples"
        except BaseException:
            proc.kill()
            raise
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, out
    assert "Traceback" not in out and "internal error" not in out, out
    assert "the bus failed" in out and f"truth in {truth}" in out, out
    assert truth.exists() and truth.stat().st_size > 0


def test_a_bus_that_keeps_failing_is_retried_with_a_growing_pause(caplog):
    """The service's reader (FrameTap.on_error, python-can's Notifier calls it on a failed
    read): counted, logged once per distinct failure, and retried after a pause that doubles
    while no frame arrives (10 ms … 1 s: a bus that is gone for good does not spin the bus
    thread); a frame in between starts again without a pause."""
    import logging

    from rsra.config.rig import load_config
    from rsra.daq.bus import reader as reader_mod

    pauses = []
    caplog.set_level(logging.ERROR, logger="rsra.daq.bus.reader")
    tap = reader_mod.OfflineReader(load_config()).tap
    tap.pause = pauses.append  # (a bus reader's: its stop event's wait, ended by close())
    recovered = []
    tap.recovered = lambda: recovered.append(tap.frames)
    gone = OSError("the server closed the connection")
    for _ in range(10):
        tap.on_error(gone)
    assert pauses == [0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.0, 1.0]
    assert tap.errors == 10 and "server closed" in tap.last_callback_error
    assert sum("bus read failed" in r.getMessage() for r in caplog.records) == 1
    import can

    tap.on_message_received(can.Message(arbitration_id=0x7FF, data=b"", timestamp=1.0))
    assert recovered == [1]  # reading again: the reader clears python-can's kept failure
    pauses.clear()
    tap.on_error(gone)  # a frame was read since: retried at once
    tap.on_error(gone)
    assert pauses == [0.01]
