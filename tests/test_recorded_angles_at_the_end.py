"""The last windows' results reach the recording (issue 51: the live summary's last run was
missing from angles.jsonl): python-can's Notifier stops its listeners when the bus stops —
the recorder among them — and that must not close angles.jsonl while the service still
records the results of the windows being identified."""
from __future__ import annotations

import json

import can

from rsra.daq.bus.recorder import ANGLES_FILE, Recorder


def test_the_notifier_stopping_the_recorder_leaves_angles_open(cfg, tmp_path):
    folder = tmp_path / "rec"
    rec = Recorder(folder, cfg)
    bus = can.Bus(interface="virtual", channel="angles-at-the-end")
    notifier = can.Notifier(bus, [rec], timeout=0.05)
    try:
        rec.keep_angles_open = True  # what the reader sets when the service asks
        notifier.stop(2.0)  # stops every listener: Recorder.stop()
        rec.write_angles({"seq": 2999, "accepted": False})  # the last window's result
        rec.close_angles()
    finally:
        bus.shutdown()
    lines = (folder / ANGLES_FILE).read_text().splitlines()
    assert [json.loads(x)["seq"] for x in lines] == [2999]


def test_without_the_request_stop_closes_angles(cfg, tmp_path):
    rec = Recorder(tmp_path / "rec", cfg)
    rec.stop()
    rec.write_angles({"seq": 1})  # after the end: dropped, not an error
    assert (tmp_path / "rec" / ANGLES_FILE).read_text() == ""
