"""Faults under a running service (issue 46 item 5): a full disk under `rsra run --record`, the
shared bus killed under a running sim + run, a killed multiprocessing resource tracker."""
from __future__ import annotations

import json
import os
import subprocess
import uuid
from pathlib import Path

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
