"""Faults under a running service (issue 46 item 5): a full disk under `rsra run --record`, the
shared bus killed under a running sim + run, a killed multiprocessing resource tracker."""
from __future__ import annotations

import json
import os
import subprocess
import uuid
from pathlib import Path

import numpy as np
import pytest
from helpers_net import free_tcp_port

from rsra.daq.cli import main


@pytest.fixture
def small_disk(tmp_path):
    """A 256 kB tmpfs (root only; skipped, saying so, without the right to mount one)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs to fill (needs root): {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_a_full_disk_stops_the_recording_cleanly_and_the_run_exits_non_zero(small_disk,
                                                                            capsys):
    """Before: the service logged ERRORs, left a 0-byte truth.npz, exited 0 and its summary
    had no `recording` entry."""
    rec = small_disk / "R"
    rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "6",
               "--record", str(rec), "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"])
    out, err = capsys.readouterr()
    assert rc == 1
    summary = json.loads(out.strip().splitlines()[-1])["summary"]
    assert summary["samples"] >= 1000  # the service ran on, all 6 s of it
    r = summary["recording"]
    assert r["complete"] is False and "No space left on device" in r["error"]
    assert r["frames"] > 0 and r["dropped"] > 0
    assert "the recording stopped early" in err and "fix:" in err
    assert not any(p.stat().st_size == 0 for p in rec.rglob("*") if p.is_file()), \
        [p.name for p in rec.rglob("*") if p.is_file() and p.stat().st_size == 0]
    assert not (rec / "truth.npz").exists()  # not a 0-byte file: not at all
    assert "truth" in summary and "no partial file" in err
    # what was recorded replays (its cut last line dropped)
    assert main(["replay", str(rec)]) == 0


def _start(argv: list[str], log: Path) -> subprocess.Popen:
    import sys

    return subprocess.Popen([sys.executable, "-m", "rsra", *argv], stdout=open(log, "w"),
                            stderr=subprocess.STDOUT)


def _wait_port(port: int, within_s: float = 30.0) -> None:
    import socket
    import time

    end = time.monotonic() + within_s
    while time.monotonic() < end:
        with socket.socket() as sk:
            if sk.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"nothing listens on port {port} after {within_s} s")


def _wait_line(log: Path, text: str, within_s: float = 30.0) -> None:
    import time

    end = time.monotonic() + within_s
    while time.monotonic() < end:
        if log.exists() and text in log.read_text():
            return
        time.sleep(0.1)
    raise AssertionError(f"{log.name}: no {text!r} after {within_s} s")


def _stop(*procs) -> None:
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _complete_samples(reader, n: int, within_s: float) -> int:
    import time

    from rsra.daq.bus.reader import HealthReport

    got, end = 0, time.monotonic() + within_s
    while got < n and time.monotonic() < end:
        item = reader.get(0.2)
        if item is not None and not isinstance(item, HealthReport) and item.complete:
            got += 1
    return got


@pytest.mark.timeout(150)
def test_the_shared_bus_killed_and_started_again_is_recovered_without_a_restart(
        tmp_path, caplog):
    """Before: `Exception in thread rsra-sync: … BrokenPipeError`, the SYNC producer died and
    nothing recovered. Now the reader opens the shared bus again when it is back (its reads
    paced by the growing pause) and the supervised SYNC producer sends again: samples
    resume in the same reader — `rsra run` is not restarted."""
    import logging
    import time

    from rsra.config.rig import load_config
    from rsra.daq.bus.reader import Reader

    caplog.set_level(logging.WARNING)
    port = free_tcp_port()
    url = f"ws://127.0.0.1:{port}/"
    channel = f"rr-{uuid.uuid4().hex[:8]}"
    bus = sim = None
    reader = None
    try:
        bus = _start(["bus", "--port", str(port), "--channel", channel], tmp_path / "bus1.log")
        _wait_port(port)
        sim = _start(["sim", "--scenario", "ground-test", "--interface", "remote",
                      "--channel", url], tmp_path / "sim1.log")
        _wait_line(tmp_path / "sim1.log", "rsra sim:")
        reader = Reader(load_config(), interface="remote", channel=url).start()
        assert _complete_samples(reader, 200, 30) == 200
        bus.kill()  # the shared bus goes away under the running sim + reader
        bus.wait()
        sim.wait(30)  # (the simulator ends on its own: the bus failed)
        time.sleep(1.0)
        while reader.get(0.1) is not None:  # what was queued before
            pass
        bus = _start(["bus", "--port", str(port), "--channel", channel], tmp_path / "bus2.log")
        _wait_port(port)
        sim = _start(["sim", "--scenario", "ground-test", "--interface", "remote",
                      "--channel", url], tmp_path / "sim2.log")
        t0 = time.monotonic()
        _wait_line(tmp_path / "sim2.log", "rsra sim:")
        assert _complete_samples(reader, 200, 45) == 200, caplog.text  # samples resume
        print(f"samples resumed within {time.monotonic() - t0:.1f} s of the bus's restart")
        assert not [r for r in caplog.records if "Traceback" in r.getMessage()]
        assert "the bus is back" in caplog.text and "SYNC sent again" in caplog.text
    finally:
        if reader is not None:
            reader.close()
        _stop(sim, bus)


def _children(pid: int) -> list[tuple[int, str]]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append((int(d.name), cmd))
    return out


@pytest.mark.timeout(120)
def test_a_killed_resource_tracker_is_one_line_not_tracebacks(tmp_path):
    """Before: 6 `KeyError: '/mp-…'` tracebacks at the end of the run."""
    import signal
    import sys
    import time

    proc = subprocess.Popen(
        [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--speed", "1",
         "--duration", "8", "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        end = time.monotonic() + 60
        tracker = None
        while tracker is None and time.monotonic() < end and proc.poll() is None:
            tracker = next((pid for pid, cmd in _children(proc.pid)
                            if "resource_tracker" in cmd), None)
            time.sleep(0.1)
        assert tracker is not None, "no resource tracker started"
        os.kill(tracker, signal.SIGKILL)  # (a process of this run's, found by its parent)
        out, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "KeyError" not in err, err
    lines = [x for x in err.splitlines() if "resource tracker" in x]
    assert len(lines) == 1 and "has gone" in lines[0], err
    assert json.loads(out.strip().splitlines()[-1])["summary"]["samples"] > 0


@pytest.mark.timeout(180)
def test_rsra_run_goes_on_through_a_restart_of_the_shared_bus(tmp_path):
    """The same through the command: `rsra run` on the shared bus, `rsra bus` killed and
    started again on the same port (with a new `rsra sim`): the run resumes by itself, its
    recording holds complete samples after the gap, it ends normally (exit 0)."""
    import sys
    import time

    port = free_tcp_port()
    url = f"ws://127.0.0.1:{port}/"
    channel = f"rr-{uuid.uuid4().hex[:8]}"
    bus = sim = run = None
    try:
        bus = _start(["bus", "--port", str(port), "--channel", channel], tmp_path / "bus1.log")
        _wait_port(port)
        sim = _start(["sim", "--scenario", "ground-test", "--interface", "remote",
                      "--channel", url], tmp_path / "sim1.log")
        _wait_line(tmp_path / "sim1.log", "rsra sim:")
        run = subprocess.Popen(
            [sys.executable, "-m", "rsra", "run", "--interface", "remote", "--channel", url,
             "--duration", "25", "--record", str(tmp_path / "R"), "--no-identification",
             "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--log-level", "info"],
            stdout=subprocess.PIPE, stderr=open(tmp_path / "run.log", "w"), text=True)
        _wait_line(tmp_path / "run.log", "service started", 60)
        time.sleep(3.0)
        bus.kill()
        bus.wait()
        sim.wait(30)
        time.sleep(2.0)
        bus = _start(["bus", "--port", str(port), "--channel", channel], tmp_path / "bus2.log")
        _wait_port(port)
        sim = _start(["sim", "--scenario", "ground-test", "--interface", "remote",
                      "--channel", url], tmp_path / "sim2.log")
        out, _ = run.communicate(timeout=120)
    finally:
        _stop(run, sim, bus)
    log = (tmp_path / "run.log").read_text()
    assert run.returncode == 0, log[-2000:]
    assert "Traceback" not in log and "Exception in thread" not in log, log[-2000:]
    assert "the bus is back" in log and "SYNC sent again" in log
    summary = json.loads(out.strip().splitlines()[-1])["summary"]
    assert summary["sync_gaps"]["count"] >= 1
    # the recording: complete samples after the longest SYNC gap (the bus's restart)
    from rsra.config.rig import load_config
    from rsra.daq.bus.reader import HealthReport
    from rsra.daq.bus.replay import replay

    got = [s for s in replay(load_config(), [tmp_path / "R"]) if not isinstance(s, HealthReport)]
    t = np.array([s.t for s in got])
    cut = int(np.argmax(np.diff(t))) + 1
    assert t[cut] - t[cut - 1] > 2.0
    assert sum(s.complete for s in got[cut:]) >= 200
