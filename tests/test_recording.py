"""Recording (daq.recorder) and replay (daq.replay, `rsra replay`): every frame kept, rotation,
flush, cap and full disk, the folder layout, and replay == live bit for bit."""
from __future__ import annotations

import errno
import json
import math
import threading

import can
import numpy as np
import pytest
from helpers_canopen import T0, LockstepRig, MasterRig, channel_name, period_frames, wait_until

from rsra.daq.cli import main as cli_main
from rsra.config.rig import load_config
from rsra.daq.bus.reader import FrameClock, HealthReport, Listen, Reader
from rsra.daq.bus.recorder import (
    ANGLES_FILE,
    CONFIG_FILE,
    Recorder,
    RecordingError,
    frame_files,
    recorded_config,
)
from rsra.daq.bus.replay import config_for, read_frames, replay, replay_to_bus


def samples(items) -> list:
    return [x for x in items if not isinstance(x, HealthReport)]


def health(items) -> list:
    return [x for x in items if isinstance(x, HealthReport)]


def assert_same_samples(live, replayed) -> None:
    assert len(live) == len(replayed) > 0
    for a, b in zip(live, replayed):
        assert a.same_as(b), (a, b)


FAULTS = "drop:cell_B:0.02;malformed:cell_C:0.02;unknown:0.02;lostsync:0.02;errorframe:0.02"


@pytest.mark.parametrize("fmt", ["log", "blf"])
def test_a_recording_replays_to_exactly_the_samples_seen_live(cfg, tmp_path, fmt):
    folder = tmp_path / "rec"
    rig = LockstepRig(cfg, faults=FAULTS, record=folder, record_format=fmt)
    try:
        live = rig.step(500)
        n_frames = rig.reader.tap.frames
    finally:
        rig.close()
    assert [p.name for p in frame_files(folder)] == [f"frames.{fmt}"]
    assert sum(1 for _ in read_frames([folder])) == n_frames  # every frame seen, kept
    rep = list(replay(cfg, [folder]))
    assert_same_samples(samples(live), samples(rep))
    assert [h.t for h in health(live)] == [h.t for h in health(rep)] == [T0 + 1.0, T0 + 2.0]
    for a, b in zip(health(live), health(rep)):
        assert a.health.bus == b.health.bus
        assert a.health.samples == b.health.samples
        assert a.health.nodes == b.health.nodes


def test_the_boot_sequence_and_own_transmissions_are_recorded_and_replay_exactly(cfg, tmp_path):
    folder = tmp_path / "boot"
    rig = MasterRig(cfg, record=folder, faults="reboot:cell_D@0.3")
    try:
        rig.start()
        live = rig.sync(120)
    finally:
        rig.close()
    frames = list(read_frames([folder]))
    ids = {m.arbitration_id for m in frames}
    assert 0x000 in ids  # our NMT commands
    assert {0x600 + n.node_id for n in cfg.nodes} <= ids  # our SDO requests
    assert sum(m.arbitration_id == 0x80 for m in frames) == 120  # our SYNCs
    ts = [m.timestamp for m in frames]
    assert ts == sorted(ts)  # the acquisition clock, monotone
    rep = list(replay(cfg, [folder]))
    assert_same_samples(samples(live), samples(rep))
    assert any("missing:cell_D" in s.flags for s in samples(rep))


def test_rotation_by_size_keeps_every_frame_in_order(cfg, tmp_path):
    folder = tmp_path / "rot"
    raw = dict(cfg.raw)
    raw["recording"] = {**cfg.raw.get("recording", {}), "rotate_mb": 0.02}
    from rsra.config.rig import config_dir, parse_config

    cfg_r = parse_config(raw, base_dir=config_dir())
    rig = LockstepRig(cfg_r, record=folder)
    try:
        live = rig.step(600)
        st = rig.reader.recorder.status()
    finally:
        rig.close()
    files = frame_files(folder)
    assert len(files) >= 5 and files[-1].name == "frames.log"
    assert [f.name for f in files[:-1]] == [f"frames_{i:06d}.log" for i in range(len(files) - 1)]
    assert all(f.stat().st_size < 0.02e6 + 200 for f in files)
    frames = list(read_frames([folder]))
    assert len(frames) == st["frames"] == rig.reader.tap.frames
    assert [m.timestamp for m in frames] == sorted(m.timestamp for m in frames)
    assert_same_samples(samples(live), samples(replay(cfg_r, [folder])))


def test_frames_are_flushed_at_least_once_a_second_of_acquisition_time(cfg, tmp_path):
    folder = tmp_path / "flush"
    rig = LockstepRig(cfg, record=folder)
    try:
        rig.step(100)  # 0.5 s: not flushed yet (buffered)
        size_early = (folder / "frames.log").stat().st_size
        rig.step(150)  # past 1 s of acquisition time since the first frame
        text = (folder / "frames.log").read_text()  # while the recording is still open
        lines = text.splitlines()
        assert lines and float(lines[-1].split()[0].strip("()")) >= T0 + 1.0
        assert size_early < len(text)
    finally:
        rig.close()


def test_a_quiet_bus_still_gets_its_frames_flushed(cfg, tmp_path):
    folder = tmp_path / "quiet"
    rig = LockstepRig(cfg, record=folder)
    try:
        rig.step(20)  # 0.1 s, then the bus goes quiet
        n = rig.reader.recorder.frames
        rig.reader.recorder.tick(rig.reader.now + 0.5)
        assert len((folder / "frames.log").read_text().splitlines()) < n  # still buffered
        rig.reader.recorder.tick(rig.reader.now + 1.0)  # the live idle tick, a second later
        assert len((folder / "frames.log").read_text().splitlines()) == n
    finally:
        rig.close()


def test_the_size_cap_stops_the_recording_loudly_and_acquisition_goes_on(cfg, tmp_path):
    folder = tmp_path / "cap"
    rig = LockstepRig(cfg, record=folder)
    rec = rig.reader.recorder
    rec.cap_bytes = 30_000
    try:
        rig.step(800)  # 4 s: the cap is hit after about one second
        h = rig.reader.health().to_dict()["recording"]
        assert not h["active"] and "size cap" in h["error"] and h["dropped"] > 0
        assert h["bytes"] >= 30_000
        assert rig.reader.health().to_dict()["samples"]["complete"] >= 790  # acquisition went on
    finally:
        rig.close()
    assert (folder / "frames.log").stat().st_size >= 30_000  # nothing deleted
    assert len(list(read_frames([folder]))) == rec.frames


def test_a_full_disk_stops_the_recording_loudly_and_acquisition_goes_on(cfg, tmp_path):
    folder = tmp_path / "full"
    rig = LockstepRig(cfg, record=folder)
    rec = rig.reader.recorder
    try:
        rig.step(10)
        f = rec._logger.writer.file

        def full(*a, **kw):
            raise OSError(errno.ENOSPC, "No space left on device")

        f.write = full
        f.flush = full
        rig.step(400)
        h = rig.reader.health().to_dict()["recording"]
        assert not h["active"] and "No space left on device" in h["error"]
        assert rig.reader.health().to_dict()["samples"]["complete"] >= 400
    finally:
        rig.close()
    assert (folder / "frames.log").exists()


def test_the_folder_layout_and_nothing_is_overwritten(cfg, tmp_path):
    folder = tmp_path / "layout"
    cfg_c = load_config(overrides={"calibration": {"cell_A.force": {"gain": 1.5,
                                                                    "offset": 10.0}}})
    rec = Recorder(folder, cfg_c)
    rec.write_angles({"seq": 0, "alpha": [0.0, float("nan")], "P": np.eye(2)})
    # flushed at once: readable while recording
    line = json.loads((folder / ANGLES_FILE).read_text().splitlines()[0])
    assert line == {"seq": 0, "alpha": [0.0, None], "P": [[1.0, 0.0], [0.0, 1.0]]}
    rec.stop()
    conf = json.loads((folder / CONFIG_FILE).read_text())
    assert conf["calibration"]["cell_A.force"] == {"gain": 1.5, "offset": 10.0}
    assert all((folder / n["eds"]).is_file() for n in conf["nodes"])
    again = recorded_config(folder)
    assert again.calibration == cfg_c.calibration
    assert [n.eds.read_text() for n in again.nodes] == [n.eds.read_text() for n in cfg_c.nodes]
    assert config_for([folder]).calibration == cfg_c.calibration
    with pytest.raises(RecordingError, match="already holds a recording"):
        Recorder(folder, cfg_c)
    with pytest.raises(RecordingError, match="not available"):
        Recorder(tmp_path / "other", cfg_c, fmt="trc")


def test_a_recording_from_mid_flight_decodes_by_the_eds_mapping(cfg, tmp_path):
    folder = tmp_path / "full_run"
    rig = LockstepRig(cfg, record=folder)
    try:
        live = samples(rig.step(300))
    finally:
        rig.close()
    frames = list(read_frames([folder]))
    cut = frames[len(frames) // 2 + 3:]  # no boot-up, no start: mid-sample
    rep = samples(replay(cfg, frames=cut))
    by_t = {s.t: s for s in live}
    assert len(rep) >= 140
    first = rep[0].t
    for s in rep[1:]:  # the first SYNC after the cut starts the first whole sample
        ref = by_t[s.t]
        assert s.sync == ref.sync and s.seq == ref.seq - by_t[rep[1].t].seq + 1
        np.testing.assert_array_equal(s.T, ref.T)
        np.testing.assert_array_equal(s.accel, ref.accel)
        assert s.omega == ref.omega and np.array_equal(s.known_H, ref.known_H)
    assert first < rep[1].t


def test_replay_at_recorded_timing_onto_a_bus(cfg, tmp_path):
    """can.MessageSync onto a virtual bus, a live reader on the other end: same samples."""
    folder = tmp_path / "rt"
    rig = LockstepRig(cfg, record=folder)
    try:
        rig.step(40)  # 0.2 s of recording
    finally:
        rig.close()
    expected = samples(replay(cfg, [folder]))
    ch = channel_name("replay-bus")
    rx = can.Bus(interface="virtual", channel=ch, receive_own_messages=False,
                 preserve_timestamps=True)
    tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
    r = Reader(cfg, rx, nodes=Listen(), clock=FrameClock())
    try:
        r.start()
        sent = replay_to_bus([folder], tx)
        wait_until(lambda: r.tap.frames >= sent, what="the frames")
        got = samples(r.poll())
    finally:
        r.close()
        rx.shutdown()
        tx.shutdown()
    assert_same_samples(expected, got)


def test_rsra_replay_writes_strict_json_lines(cfg, tmp_path, capsys):
    folder = tmp_path / "cli"
    rig = LockstepRig(cfg, faults="drop:accel_1:0.05", record=folder)
    try:
        live = rig.step(450)
    finally:
        rig.close()
    out = tmp_path / "out.jsonl"
    assert cli_main(["replay", str(folder), "--out", str(out)]) == 0
    assert "replayed: 450 samples, 2 health records" in capsys.readouterr().out

    def no_nan(x):
        raise ValueError(f"non-strict JSON constant {x}")

    recs = [json.loads(line, parse_constant=no_nan) for line in out.read_text().splitlines()]
    assert [r["key"] for r in recs].count("channels") == 450
    assert [r["key"] for r in recs].count("health") == 2
    ch = [r for r in recs if r["key"] == "channels"]
    for r, s in zip(ch, samples(live)):
        assert (r["seq"], r["t"]) == (s.seq, s.t)
        assert r["T"] == s.T.tolist()
        assert r["accel"] == [[None if math.isnan(v) else v for v in row]
                              for row in s.accel.tolist()]
    assert any(r["accel"] == [[None, None, None]] for r in ch)  # a dropped accelerometer frame


def test_rsra_replay_usage_errors(tmp_path, capsys):
    assert cli_main(["replay", str(tmp_path / "nope.log")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli_main(["replay", str(tmp_path / "empty")]) == 2
    assert "no frames" in capsys.readouterr().err


def test_asc_replays_the_same_values_with_relative_times(cfg, tmp_path):
    folder = tmp_path / "asc"
    rig = LockstepRig(cfg, record=folder, record_format="asc")
    try:
        live = samples(rig.step(100))
    finally:
        rig.close()
    rep = samples(replay(cfg, [folder]))
    assert len(rep) == len(live)
    for a, b in zip(live, rep):
        np.testing.assert_array_equal(a.T, b.T)
        assert (a.seq, a.sync, a.flags) == (b.seq, b.sync, b.flags)
        assert b.t - rep[0].t == pytest.approx(a.t - live[0].t, abs=2e-6)


def test_recording_is_thread_safe_for_angles(cfg, tmp_path):
    rec = Recorder(tmp_path / "threads", cfg)
    msgs = period_frames(cfg, 0, T0)
    ths = [threading.Thread(target=lambda i=i: [rec.write_angles({"i": i, "k": k})
                                                for k in range(50)]) for i in range(4)]
    for t in ths:
        t.start()
    for m in msgs:
        rec.on_message_received(m)
    for t in ths:
        t.join()
    rec.stop()
    lines = (tmp_path / "threads" / ANGLES_FILE).read_text().splitlines()
    assert sorted((json.loads(x)["i"], json.loads(x)["k"]) for x in lines) == \
        [(i, k) for i in range(4) for k in range(50)]


def test_a_last_line_cut_anywhere_is_dropped_never_read_as_a_wrong_frame(cfg, tmp_path):
    """A crash can cut the last line of a candump recording anywhere; the cut line is dropped,
    whatever is left of it. Every cut position of the last line is tried (deterministic): cut
    in its data field, a candump line still parses — as a shorter, wrong frame."""
    rec = Recorder(tmp_path / "whole", cfg)
    msgs = period_frames(cfg, 0, T0) + period_frames(cfg, 1, T0 + cfg.sample_period_s)
    for m in msgs:
        rec.on_message_received(m)
    rec.stop()
    path = frame_files(tmp_path / "whole")[0]
    text = path.read_text()
    whole = list(read_frames([path]))
    assert len(whole) == len(msgs)
    last = text.rstrip("\n").rsplit("\n", 1)[1]
    assert len(whole[-1].data) >= 2  # the data field can be cut to a shorter frame
    head = text[:len(text) - len(last) - 1]
    cut_file = tmp_path / "cut.log"
    for n in range(len(last) + 1):  # the whole line without its newline, down to nothing
        cut_file.write_text(head + last[:n])
        got = list(read_frames([cut_file]))
        assert len(got) == len(whole) - 1, n
        assert all(a.equals(b) for a, b in zip(got, whole)), n


def test_recording_channel_names_are_stable_short_and_true():
    """Issue 29: `rsra-7f5122f5bc50` (17 characters, new every run) with --sim, `vcan0`
    (wrong) with --interface remote, `ws://127.0.0.1:P/` from `sim --record`: can-utils'
    canplayer refuses interface names of 16 characters or more."""
    from rsra.canbus import recording_channel

    assert recording_channel("socketcan", "can0") == "can0"
    assert recording_channel("socketcan", "vcan0") == "vcan0"
    assert recording_channel("remote", "ws://127.0.0.1:54701/") == "remote"
    assert recording_channel("virtual", "rsra-7f5122f5bc50") == "virtual"
    assert recording_channel("virtual", "rsra-7f5122f5bc50", sim=True) == "sim"
    assert recording_channel("pcan", "PCAN_USBBUS1") == "PCAN_USBBUS1"
    assert recording_channel("kvaser", 0) == "0"


def test_the_service_with_the_simulator_records_channel_sim(tmp_path):
    from rsra.daq.runtime.service import Service, ServiceOptions

    cfg = load_config()
    rec = tmp_path / "rec"
    Service(cfg, ServiceOptions(sim="ground-test", speed=None, duration=0.3, zenoh=False,
                                identification=False, record=str(rec))).run()
    lines = (rec / "frames.log").read_text().splitlines()
    assert len(lines) > 100
    assert {ln.split()[1] for ln in lines} == {"sim"}  # every frame, ours and the nodes'
    # the simulator's own recording (`rsra sim --record`) names its bus the same way
    from helpers_canopen import make_sim

    sim_rec = tmp_path / "sim.log"
    sim = make_sim(cfg, channel_name("simrec"), record=sim_rec, autostart=True)
    try:
        for _ in range(20):
            sim.step()
    finally:
        sim.close()
    names = {ln.split()[1] for ln in sim_rec.read_text().splitlines()}
    assert names <= {"sim"} and names


def test_answers_built_ahead_are_recorded_under_the_channel_sim(tmp_path):
    """The real-time simulator sends most answers built ahead (``prepare_next``,
    ``send_built_many``); `rsra sim --record` must name those frames `sim` too."""
    import can

    from rsra.sim_bus.bus_sim import Simulator
    from rsra.sim_bus.physics import AircraftPhysics
    from rsra.sim_bus.scenarios import load_scenario

    cfg = load_config()
    chan = channel_name("built")
    log = tmp_path / "sim.log"
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        sim = Simulator(cfg, physics=AircraftPhysics(cfg, load_scenario("ground-test"), seed=3),
                        seed=3, channel=chan, record=log)
        with sim:
            master.send(can.Message(arbitration_id=0, is_extended_id=False, data=[1, 0]))
            sim.pump()
            for k in range(1, 8):
                sim.prepare_next()
                sim.pump()
                sim.answer_sync(k, k * sim.dt)
        assert sim.prepared >= 1  # answers did go out as built ahead
    finally:
        master.shutdown()
    names = {ln.split()[1] for ln in log.read_text().splitlines()}
    assert names == {"sim"}
