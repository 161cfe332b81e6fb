"""Nothing the service claims to have is lost: a recording survives `kill -9` of the service
with at most the last flush interval missing and replays to the same estimates the service
published; the size cap and a full disk stop the recording loudly while acquisition goes
on. (Replay of a recording with faults, bit for bit: tests/test_faults_e2e.py.)
"""
from __future__ import annotations

import errno
import itertools
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import zenoh
from helpers_net import free_tcp_port

from rsra.config.rig import load_config
from rsra.daq.jsonout import dumps
from rsra.daq.bus.replay import read_frames
from rsra.daq.runtime.service import Service, ServiceOptions
from rsra.daq.runtime.telemetry import viewer_config

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
KILL_AFTER_S = 12.0  # acquisition time before the kill: two identification runs applied


def _children(pid: int) -> list[int]:
    """Direct children of a process we started (the identification worker)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def test_a_recording_survives_kill_9_and_replays_to_what_was_published(cfg, tmp_path):
    rec = tmp_path / "rec"
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    got: dict[int, str] = {}  # seq -> hub_loads payload text, as the service published it
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        text = sample.payload.to_string()
        seq = json.loads(text)["seq"]
        with lock:
            got[seq] = text

    with zenoh.open(viewer_config([], listen=[ep])) as z:
        sub = z.declare_subscriber(f"{cfg.telemetry.prefix}/hub_loads", on_sample)
        proc = subprocess.Popen(
            [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--speed", "max",
             "--duration", "3600", "--seed", "4", "--record", str(rec), "--zenoh-listen",
             f"tcp/127.0.0.1:{free_tcp_port()}", "--zenoh-connect", ep,
             "--log-level", "warning"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
        workers: list[int] = []
        try:
            deadline = time.monotonic() + 300
            n_kill = round(KILL_AFTER_S * cfg.sample_rate_hz)
            while True:  # wait (poll) until the run is well under way, then kill it
                assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
                assert time.monotonic() < deadline, "the service did not get going"
                workers = _children(proc.pid) or workers
                with lock:
                    if got and max(got) >= n_kill:
                        break
                time.sleep(0.05)
            proc.send_signal(signal.SIGKILL)
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
            for pid in workers:  # the orphaned identification worker: ours, end it by id
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            proc.stderr.close()
        time.sleep(0.2)  # the last samples still in the loopback socket
        sub.undeclare()
    assert proc.returncode == -signal.SIGKILL
    with lock:
        published = dict(got)
    last_pub = json.loads(published[max(published)])

    # what survived: whole frames only (a cut last line is dropped), in order, no hole
    frames = list(read_frames([rec]))
    assert len(frames) > 1000
    t_rec = frames[-1].timestamp
    assert [m.timestamp for m in frames] == sorted(m.timestamp for m in frames)
    counters = [m.data[0] for m in frames if m.arbitration_id == cfg.sync.cob_id]
    ov = cfg.sync.counter_overflow
    assert all(b == a % ov + 1 for a, b in itertools.pairwise(counters))  # no SYNC missing
    # at most the last flush interval lost: every frame up to flush_s before the last sample
    # the service published is on disk (the recorder writes a frame before the sample that
    # contains it is published)
    assert last_pub["t"] - t_rec <= cfg.recording.flush_s + cfg.sample_period_s
    lost_s = last_pub["t"] - t_rec

    # the surviving folder replays, and reproduces what the service published, bit for bit
    out = tmp_path / "replay.jsonl"
    r = subprocess.run([sys.executable, "-m", "rsra", "replay", str(rec), "--out", str(out)],
                       capture_output=True, text=True, timeout=600, env=ENV, check=False)
    assert r.returncode == 0, r.stderr
    replayed = {}
    for line in out.read_text().splitlines():
        d = json.loads(line)
        if d.pop("key") == "hub_loads":
            replayed[d["seq"]] = dumps(d)
    assert set(replayed) == set(range(len(replayed)))  # seq 0… with no hole
    # the last recorded sample may have been cut by the kill part-way through its TPDOs: the
    # replay passes it on flagged with what is missing (never made up); every whole one matches
    last = max(replayed)
    if replayed[last] != published.get(last, replayed[last]):
        assert any(f.startswith("missing:") for f in json.loads(replayed[last])["flags"])
        del replayed[last]
    common = sorted(set(replayed) & set(published))
    assert len(common) > 0.5 * len(replayed)
    assert [replayed[k] for k in common] == [published[k] for k in common]
    angles = (rec / "angles.jsonl").read_text().splitlines()
    assert json.loads(angles[0])["initial"] and len(angles) >= 2  # schedule kept too
    print(f"kill -9: {len(frames)} frames kept, {len(replayed)} samples replayed, "
          f"{len(published)} received live; {lost_s:.3f} s of acquisition lost")


def _run(cfg, duration, **kw):
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=None, duration=duration,
                                      zenoh=False, identification=False, seed=3, **kw))
    health: list[dict] = []
    n = {"hub_loads": 0}

    def sink(key, payload):
        if key == "health":
            health.append(json.loads(dumps(payload)))
        elif key == "hub_loads":
            n["hub_loads"] += 1

    svc.add_sink(sink)
    summary = svc.run()
    return svc, summary, health, n["hub_loads"]


def test_the_size_cap_stops_the_recording_loudly_and_acquisition_goes_on(tmp_path, caplog):
    cap_mb = 0.2
    cfg = load_config(overrides={"recording": {"cap_mb": cap_mb}})
    rec = tmp_path / "cap"
    with caplog.at_level(logging.ERROR):
        svc, summary, health, n = _run(cfg, 5.0, record=str(rec))
    assert summary["samples"] == n == 1000  # acquisition went on to the end
    stopped = [h for h in health if not h["recording"]["active"]]
    assert stopped and "size cap" in stopped[0]["recording"]["error"]
    assert all(h["recording"]["active"] for h in health[: len(health) - len(stopped)])
    final = svc.reader.recorder.status()
    assert final["dropped"] > 0 and final["frames"] + final["dropped"] == svc.reader.tap.frames
    size = sum(p.stat().st_size for p in rec.glob("frames*"))
    # the cap is checked every 256 frames: overshoot by at most that many lines
    assert cap_mb * 1e6 <= size <= cap_mb * 1e6 + 256 * 80
    assert sum("size cap" in r.getMessage() for r in caplog.records
               if r.levelno >= logging.ERROR) >= 1
    assert len(list(read_frames([rec]))) == final["frames"]  # what was kept is readable


def test_a_full_disk_stops_the_recording_loudly_and_acquisition_goes_on(cfg, tmp_path, caplog,
                                                                       monkeypatch):
    written = {"n": 0}
    real = can.SizedRotatingLogger.on_message_received

    def filling_disk(self, msg):
        written["n"] += 1
        if written["n"] > 3000:  # about one second of frames, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, msg)

    monkeypatch.setattr(can.SizedRotatingLogger, "on_message_received", filling_disk)
    rec = tmp_path / "full"
    with caplog.at_level(logging.ERROR):
        svc, summary, health, n = _run(cfg, 4.0, record=str(rec))
    assert summary["samples"] == n == 800
    errors = [h["recording"]["error"] for h in health if h["recording"]["error"]]
    assert errors and "No space left on device" in errors[0]
    assert not health[-1]["recording"]["active"]
    assert any("No space left on device" in r.getMessage() for r in caplog.records)
    st = svc.reader.recorder.status()
    assert st["frames"] == 3000 and st["frames"] + st["dropped"] == svc.reader.tap.frames
    # the angle schedule is still written after the frames stopped (bus.md: never lost)
    assert json.loads((rec / "angles.jsonl").read_text().splitlines()[0])["initial"]
