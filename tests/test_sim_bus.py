"""The bus simulator (sim_bus.bus_sim), its faults (sim_bus.faults) and `rsra sim`.

Lock-step wherever possible: no sleeps, simulated time only. The one real-time test is the
comparison with lock-step itself (and the CLI, which runs in real time by definition).
"""
from __future__ import annotations

import configparser
import math
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import can
import numpy as np
import pytest
from scipy import stats

from rsra.daq.cli import main as cli_main
from rsra.sim_bus.bus_sim import Simulator
from rsra.sim_bus.drivers import LockstepSim, RealtimeSim
from rsra.sim_bus.faults import FaultSpecError, parse_faults
from test_sim_nodes import channel_name, make_physics

ROOT = Path(__file__).resolve().parents[1]
ALPHA = 1e-3  # false-alarm rate of the statistical checks


def lockstep(cfg, faults: str = "", seed: int = 7, **kw) -> LockstepSim:
    return LockstepSim(cfg, physics=make_physics(cfg, seed), seed=seed, faults=faults,
                       autostart=True, channel=channel_name("bus"), **kw)


def run_steps(sim: LockstepSim, n: int) -> list[can.Message]:
    out = []
    for _ in range(n):
        out.extend(sim.step())
    return out


def key(m: can.Message) -> tuple:
    return (m.timestamp, m.arbitration_id, bytes(m.data), m.dlc, m.is_error_frame)


def cycles(frames: list[can.Message], sync_cob: int = 0x80) -> list[list[can.Message]]:
    """Frames grouped by SYNC (each group starts with its SYNC), by frame order alone."""
    out: list[list[can.Message]] = []
    for m in frames:
        if m.arbitration_id == sync_cob and not m.is_error_frame:
            out.append([m])
        elif out:
            out[-1].append(m)
    return out


# ------------------------------------------------------------------------------------------
# an independent decoder: only struct and the EDS files read with configparser

_STRUCT = {0x0002: "b", 0x0003: "h", 0x0004: "i", 0x0005: "B", 0x0006: "H", 0x0007: "I",
           0x0008: "f", 0x0011: "d"}
_CHANNELS = {"load_cell": ["force", "status"], "accelerometer": ["x", "y", "z"],
             "rotor_speed": ["omega", "azimuth"], "balance": list("XYZLMN"),
             "drive_load": ["torque"]}


def _eds_int(text: str, node_id: int) -> int:
    return sum(int(p.strip().replace("$NODEID", str(node_id)), 0) for p in text.split("+"))


def eds_decoders(cfg) -> dict[int, tuple[str, str, struct.Struct, list[str]]]:
    """COB-ID -> (node, role, struct, channel names) from each node's EDS default TPDOs."""
    out = {}
    for n in cfg.nodes:
        cp = configparser.ConfigParser(interpolation=None)
        cp.optionxform = str
        cp.read(n.eds)
        sec = {s.lower(): cp[s] for s in cp.sections()}
        names = iter(_CHANNELS[n.role])
        for k in range(512):
            com, mp = sec.get(f"{0x1800 + k:x}sub1"), sec.get(f"{0x1a00 + k:x}sub0")
            if com is None or mp is None:
                break
            cob = _eds_int(com["DefaultValue"], n.node_id)
            fmt, chans = "<", []
            for s in range(1, int(mp["DefaultValue"], 0) + 1):
                word = int(sec[f"{0x1a00 + k:x}sub{s}"]["DefaultValue"], 0)
                idx, sub = word >> 16, (word >> 8) & 0xFF
                fmt += _STRUCT[int(sec[f"{idx:x}sub{sub}"]["DataType"], 0)]
                chans.append(next(names))
            out[cob] = (n.name, n.role, struct.Struct(fmt), chans)
    return out


def to_engineering(role: str, ch: str, raw: float) -> float:
    if role == "accelerometer":
        return raw * 9.80665e-3  # 1 count = 1 mg (docs/bus.md §1)
    if ch == "azimuth":
        return raw / 65536.0 * 2 * math.pi
    return float(raw)


_LINE = re.compile(r"^\((\d+\.\d+)\) (\S+) ([0-9A-F]+)#([0-9A-F]*)")


def read_candump(path: Path) -> list[tuple[float, int, bytes]]:
    out = []
    for line in path.read_text().splitlines():
        m = _LINE.match(line)
        assert m, line
        out.append((float(m.group(1)), int(m.group(3), 16), bytes.fromhex(m.group(4))))
    return out


# ------------------------------------------------------------------------------------------

def test_same_seed_same_frames_bit_for_bit(cfg):
    spec = ("drop:*:0.05;malformed:cell_B:0.02;unknown:0.02;errorframe:0.02;lostsync:0.02;"
            "jitter:0.3ms;reboot:cell_G@0.7;stuck:accel_1.z@0.2-0.9;overrange:cell_A@0.3-0.6")
    runs = []
    for seed in (11, 11, 12):
        with lockstep(cfg, spec, seed=seed) as sim:
            runs.append([key(m) for m in run_steps(sim, 300)])
    assert len(runs[0]) > 300 * 9
    assert runs[0] == runs[1]
    assert runs[0] != runs[2]


def test_frames_reach_the_bus_in_order_with_simulated_timestamps(cfg):
    with lockstep(cfg) as sim:
        rx = can.Bus(interface="virtual", channel=sim.channel, receive_own_messages=False)
        try:
            sent = run_steps(sim, 50)
            got = []
            while (m := rx.recv(0)) is not None:
                got.append(m)
        finally:
            rx.shutdown()
    assert [key(m) for m in got] == [key(m) for m in sent]
    ts = np.array([m.timestamp for m in got])
    assert np.all(np.diff(ts) > 0)  # serialised at the EDS bit rate, 1 µs resolution
    syncs = [m for m in got if m.arbitration_id == 0x80]
    np.testing.assert_allclose([m.timestamp for m in syncs], np.arange(50) * cfg.sample_period_s,
                               atol=1e-3)
    assert [m.data[0] for m in syncs] == list(range(1, 51))  # CiA 301 counter from 1
    # per SYNC: the TPDOs in identifier order (bus arbitration), every configured TPDO once
    cobs = sorted(c.cob_id for n in sim.nodes for c in n.tpdo_configs())
    for grp in cycles(got)[1:]:
        assert [m.arbitration_id for m in grp if 0x180 <= m.arbitration_id < 0x580] == cobs


def test_sync_counter_wraps_at_the_configured_overflow(cfg):
    with lockstep(cfg) as sim:
        frames = run_steps(sim, 2 * cfg.sync.counter_overflow + 5)
    counters = [m.data[0] for m in frames if m.arbitration_id == cfg.sync.cob_id]
    expected = [k % cfg.sync.counter_overflow + 1 for k in range(len(counters))]
    assert counters == expected


def test_lockstep_follow_mode_pump_and_on_sync_are_deterministic(cfg):
    """Lock-step behind an external master without any thread: the master's NMT and SYNC frames
    are handled in order by pump(); on_sync() is the same without the SYNC frame. Both answer
    exactly what the autostart simulator sends for the same seed."""
    n = 30
    with lockstep(cfg, seed=9) as ref_sim:
        ref = [(m.arbitration_id, bytes(m.data)) for m in run_steps(ref_sim, n)
               if 0x180 <= m.arbitration_id < 0x580]
    chan = channel_name("follow")
    sim = LockstepSim(cfg, physics=make_physics(cfg, 9), seed=9, channel=chan)
    master = can.Bus(interface="virtual", channel=chan, receive_own_messages=False,
                     preserve_timestamps=True)
    try:
        with sim:
            assert sim.network.notifier is None
            master.send(can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False))
            for k in range(n // 2):
                master.send(can.Message(arbitration_id=0x80, data=[k + 1], timestamp=k * 0.005,
                                        is_extended_id=False))
            assert sim.pump() == 1 + n // 2
            got = []
            while (m := master.recv(0)) is not None:
                got.append(m)
            direct = []
            for k in range(n // 2, n):
                direct += sim.on_sync(k + 1, k * 0.005)
        assert sim.now() == pytest.approx((n - 1) * 0.005)
    finally:
        master.shutdown()
    tp = [(m.arbitration_id, bytes(m.data)) for m in got + direct if 0x180 <= m.arbitration_id < 0x580]
    assert tp == ref


def test_the_aircraft_and_its_lockstep_driver_start_no_thread(cfg):
    """The Simulator has no mode: threads are a driver's (RealtimeSim, FollowSim); neither the
    bare aircraft nor LockstepSim starts one, booting, stepping or answering."""
    before = set(threading.enumerate())
    bare = Simulator(cfg, physics=make_physics(cfg, 2), seed=2, channel=channel_name("bare"))
    with lockstep(cfg, seed=2) as sim, bare:
        run_steps(sim, 3)
        bare.answer_sync(1, 0.005)
        assert bare.pump() == 0
        assert {t for t in threading.enumerate() if t.is_alive()} <= before
        assert sim.network.notifier is None and bare.network.notifier is None


@pytest.mark.timeout(60)
def test_lockstep_and_real_time_give_the_same_samples(cfg):
    n = 80  # 0.4 s of real time
    with lockstep(cfg, seed=5) as sim:
        ref = [(m.arbitration_id, bytes(m.data)) for m in run_steps(sim, n)
               if m.arbitration_id == 0x80 or 0x180 <= m.arbitration_id < 0x580]
    chan = channel_name("rt")
    rx = can.Bus(interface="virtual", channel=chan, receive_own_messages=False)
    try:
        sim = RealtimeSim(cfg, physics=make_physics(cfg, 5), seed=5, autostart=True, channel=chan)
        with sim:
            assert sim.run(duration=n * cfg.sample_period_s) == n
        got = []
        while (m := rx.recv(0)) is not None:
            if m.arbitration_id == 0x80 or 0x180 <= m.arbitration_id < 0x580:
                got.append((m.arbitration_id, bytes(m.data)))
    finally:
        rx.shutdown()
    assert got == ref
    assert sim._ticker is not None and not sim._ticker.is_alive()


def check_record_against_truth(cfg, frames: list[tuple[float, int, bytes]], truth: dict,
                               dropped: set[tuple[int, str]] = frozenset()) -> dict[str, int]:
    """Decode every TPDO of a recording (grouped by the SYNC before it) and compare it with the
    truth file's channels of that sample, within the encoding's resolution. Returns the number
    of TPDOs checked per role."""
    dec = eds_decoders(cfg)
    cells = {c.node: i for i, c in enumerate(cfg.cells)}
    accs = {a.node: k for k, a in enumerate(cfg.accelerometers)}
    f32 = 2.0 ** -24  # REAL32 relative rounding
    k, checked = -1, defaultdict(int)
    seen: set[tuple[int, str]] = set()
    for _, cob, data in frames:
        if cob == cfg.sync.cob_id:
            k += 1
            assert data[0] == truth["sync_counter"][k]
            continue
        if cob not in dec or k < 0:
            continue
        node, role, st, chans = dec[cob]
        vals = dict(zip(chans, (to_engineering(role, c, v) for c, v in zip(chans, st.unpack(data)))))
        if role == "load_cell":
            i = cells[node]
            assert abs(vals["force"] - truth["T"][k, i]) <= f32 * abs(truth["T"][k, i])
            assert vals["status"] == truth["cell_status"][k, i]
        elif role == "accelerometer":
            assert np.all(np.abs(np.array([vals["x"], vals["y"], vals["z"]]) - truth["accel"][k, accs[node]])
                          <= 0.5 * 9.80665e-3 + 1e-9)  # half a count (1 mg)
        elif role == "rotor_speed":
            assert abs(vals["omega"] - truth["omega"][k]) <= f32 * abs(truth["omega"][k])
            d = math.remainder(vals["azimuth"] - truth["azimuth"][k], 2 * math.pi)
            assert abs(d) <= math.pi / 65536 + 1e-12  # half a count of 2π/65536
        elif role == "balance":
            for c, v in vals.items():
                ref = truth["H_balance"][k, "XYZLMN".index(c)]
                assert abs(v - ref) <= f32 * abs(ref)
        checked[role] += 1
        seen.add((k, node))
    assert k + 1 == len(truth["index"])
    assert not seen & set(dropped)
    return checked


def test_record_decodes_back_to_the_truth_channels(cfg, tmp_path):
    from rsra.sim_bus.truth import read_truth

    path = tmp_path / "run.log"
    with lockstep(cfg, seed=3, record=path) as sim:
        run_steps(sim, 400)
    truth = read_truth(sim.write_truth(tmp_path / "truth.npz"))
    checked = check_record_against_truth(cfg, read_candump(path), truth)
    for n in sim.nodes:
        assert checked[n.role] >= 400 * len(n.tpdo_configs()), n.role
    # the simulator's own in-memory record agrees with the truth file
    np.testing.assert_array_equal(sim.samples.arrays()["H_true"], truth["H_true"])
    assert truth["meta"]["seed"] == 3


# ------------------------------------------------------------------------------------------
# faults: each kind on the bus as specified and in the truth

N = 400  # 2 s at 200 samples/s


def by_sample(frames: list[can.Message]) -> list[list[can.Message]]:
    return cycles(frames)


def faults_of(sim: Simulator, kind: str) -> list[dict]:
    return [f for f in sim.fault_log if f["kind"] == kind]


def binomial_ok(count: int, n: int, p: float) -> bool:
    lo, hi = stats.binom.ppf(ALPHA / 2, n, p), stats.binom.isf(ALPHA / 2, n, p)
    return lo <= count <= hi


def test_fault_drop(cfg):
    with lockstep(cfg, "drop:cell_A:0.2") as sim:
        groups = by_sample(run_steps(sim, N))
    cob = sim.by_name["cell_A"].tpdo_configs()[0].cob_id
    missing = {i for i, g in enumerate(groups) if not any(m.arbitration_id == cob for m in g)}
    logged = {f["sample"] for f in faults_of(sim, "drop")}
    assert missing == logged and all(f["node"] == "cell_A" for f in faults_of(sim, "drop"))
    assert binomial_ok(len(missing), N, 0.2)
    others = [c.cob_id for n in sim.nodes if n.name != "cell_A" for c in n.tpdo_configs()]
    assert all(sum(m.arbitration_id in others for m in g) == len(others) for g in groups)


def test_fault_malformed(cfg):
    with lockstep(cfg, "malformed:accel_1:0.1") as sim:
        groups = by_sample(run_steps(sim, N))
    cfg_t = sim.by_name["accel_1"].tpdo_configs()[0]
    bad = {i for i, g in enumerate(groups) for m in g
           if m.arbitration_id == cfg_t.cob_id and len(m.data) != cfg_t.length}
    logged = faults_of(sim, "malformed")
    assert bad == {f["sample"] for f in logged}
    assert all(f["length"] == cfg_t.length - 1 and f["expected"] == cfg_t.length for f in logged)
    assert binomial_ok(len(bad), N, 0.1)


def _force(g: list[can.Message], cob: int) -> tuple[float, int]:
    return next(struct.unpack("<fB", m.data) for m in g if m.arbitration_id == cob)


def test_fault_stuck(cfg):
    with lockstep(cfg, "stuck:cell_B@0.5-1.0") as sim:
        groups = by_sample(run_steps(sim, N))
    cob = sim.by_name["cell_B"].tpdo_configs()[0].cob_id
    f = [_force(g, cob)[0] for g in groups]
    assert len(set(f[100:200])) == 1 and f[100] == np.float32(sim.samples[100].T[1])
    assert len(set(f[:100])) > 50 and len(set(f[200:])) > 150
    assert [(e["sample"], e["event"]) for e in faults_of(sim, "stuck")] == [(100, "start"), (200, "end")]


def test_fault_overrange_and_sensor_with_emcy(cfg):
    with lockstep(cfg, "overrange:cell_C@0.5-1.0;sensor:cell_D@1.5") as sim:
        groups = by_sample(run_steps(sim, N))
    c = sim.by_name["cell_C"]
    force_status = [_force(g, c.tpdo_configs()[0].cob_id) for g in groups]
    inside = range(100, 200)
    fs = cfg.cells[2].full_scale_N
    assert all(abs(force_status[i][0]) == np.float32(fs) and force_status[i][1] & 1 for i in inside)
    assert not any(s & 1 for i, (_, s) in enumerate(force_status) if i not in inside)
    emcy = [(i, struct.unpack("<HB5s", m.data)[:2]) for i, g in enumerate(groups) for m in g
            if m.arbitration_id == c.emcy_cob_id]
    # the over-range code with the generic-error bit, then the error reset with a clear register
    assert emcy == [(100, (0xFF01, 0x01)), (200, (0x0000, 0x00))]
    d = sim.by_name["cell_D"]
    st = [_force(g, d.tpdo_configs()[0].cob_id)[1] for g in groups]
    assert all(s & 2 for s in st[300:]) and not any(s & 2 for s in st[:300])
    emcy_d = [i for i, g in enumerate(groups) for m in g if m.arbitration_id == d.emcy_cob_id]
    assert emcy_d == [300]
    assert [(e["node"], e["sample"], e["event"]) for e in faults_of(sim, "overrange")] == \
        [("cell_C", 100, "start"), ("cell_C", 200, "end")]
    assert [(e["node"], e["sample"], e["event"]) for e in faults_of(sim, "sensor")] == \
        [("cell_D", 300, "start")]


def test_fault_silent(cfg):
    with lockstep(cfg, "silent:accel_1@0.5-1.2") as sim:
        frames = run_steps(sim, N)
    nid = sim.by_name["accel_1"].node_id
    mine = [m for m in frames if m.arbitration_id & 0x7F == nid and m.arbitration_id != 0x80]
    t = np.array([m.timestamp for m in mine])
    assert not np.any((t > 0.5 + 1e-3) & (t < 1.2 - 1e-3))
    assert np.any(t < 0.5) and np.any(t > 1.2)
    assert any(m.arbitration_id == 0x700 + nid and m.timestamp > 1.2 for m in mine)  # heartbeats resume
    assert [(e["sample"], e["event"]) for e in faults_of(sim, "silent")] == [(100, "start"), (240, "end")]


def test_fault_reboot_waits_for_nmt_start(cfg):
    with lockstep(cfg, "reboot:cell_E@0.5") as sim:
        master = can.Bus(interface="virtual", channel=sim.channel, receive_own_messages=False,
                         preserve_timestamps=True)
        try:
            groups = by_sample(run_steps(sim, 200))
            node = sim.by_name["cell_E"]
            master.send(can.Message(arbitration_id=0, data=[1, node.node_id], is_extended_id=False))
            groups += by_sample(run_steps(sim, 40))
        finally:
            master.shutdown()
    cob = node.tpdo_configs()[0].cob_id
    has = [any(m.arbitration_id == cob for m in g) for g in groups]
    assert all(has[:100]) and not any(has[100:200]) and all(has[200:])
    boot = [i for i, g in enumerate(groups) for m in g
            if m.arbitration_id == 0x700 + node.node_id and m.data == b"\x00"]
    assert boot == [100]
    hb = [m.data[0] for g in groups[101:200] for m in g if m.arbitration_id == 0x700 + node.node_id]
    assert hb and set(hb) == {0x7F}  # pre-operational until the master starts it
    assert [(e["node"], e["sample"]) for e in faults_of(sim, "reboot")] == [("cell_E", 100)]


def test_fault_unknown_cob_ids(cfg):
    with lockstep(cfg, "unknown:0.05;unknown:0x7AB:0.05") as sim:
        groups = by_sample(run_steps(sim, N))
        known = sim.known_cob_ids()
    odd = [(i, m.arbitration_id) for i, g in enumerate(groups) for m in g
           if m.arbitration_id not in known]
    logged = [(f["sample"], f["cob_id"]) for f in faults_of(sim, "unknown")]
    assert sorted(odd) == sorted(logged) and odd
    assert {c for _, c in odd} == {0x7AB, sim._unknown_cob}


def test_fault_lost_sync(cfg):
    with lockstep(cfg, "lostsync:0.1") as sim:
        frames = run_steps(sim, N)
    counters = [m.data[0] for m in frames if m.arbitration_id == 0x80]
    lost = {f["sample"] for f in faults_of(sim, "lostsync")}
    assert len(counters) == N - len(lost) and binomial_ok(len(lost), N, 0.1)
    present = [k for k in range(N) if k not in lost]
    assert counters == [k % cfg.sync.counter_overflow + 1 for k in present]  # skipped values
    assert sim.sync_arrays()["sync_lost"].sum() == len(lost)
    per_sync = [sum(0x180 <= m.arbitration_id < 0x580 for m in g) for g in cycles(frames)]
    assert set(per_sync) == {sum(len(n.tpdo_configs()) for n in sim.nodes)}  # none lost-cycle TPDOs


def test_fault_sync_jitter(cfg):
    sigma = 0.4e-3
    with lockstep(cfg, f"jitter:{sigma * 1e3}ms") as sim:
        frames = run_steps(sim, N)
    ts = np.array([m.timestamp for m in frames if m.arbitration_id == 0x80])
    offsets = np.array([f["offset_s"] for f in faults_of(sim, "jitter")])
    assert len(offsets) == N
    nominal = np.arange(N) * cfg.sample_period_s
    # the SYNC goes out at nominal + offset (late only by a frame still on the bus)
    late = ts - (nominal + offsets)
    assert np.all(late > -1e-6) and np.all(late < 0.6e-3)
    assert np.all(np.abs(offsets) <= 3 * sigma + 1e-12)
    chi2 = np.sum(offsets ** 2) / sigma ** 2  # clipped at 3σ: slightly below χ²(N) on average
    assert stats.chi2.ppf(ALPHA / 2, N) * 0.97 <= chi2 <= stats.chi2.isf(ALPHA / 2, N)


def test_fault_error_frames(cfg, tmp_path):
    path = tmp_path / "err.log"
    with lockstep(cfg, "errorframe:0.05", record=path) as sim:
        groups = by_sample(run_steps(sim, N))
    err = [i for i, g in enumerate(groups) for m in g if m.is_error_frame]
    assert err == [f["sample"] for f in faults_of(sim, "errorframe")] and err
    back = [m for m in can.LogReader(str(path)) if m.is_error_frame]
    assert len(back) == len(err)


def test_fault_window_and_node_wildcard(cfg):
    with lockstep(cfg, "drop:*:0.5@1.0-1.5") as sim:
        run_steps(sim, N)
    samples = {f["sample"] for f in faults_of(sim, "drop")}
    assert samples and min(samples) >= 200 and max(samples) < 300
    assert {f["node"] for f in faults_of(sim, "drop")} == {n.name for n in sim.nodes}


@pytest.mark.parametrize("spec, token, words", [
    ("drop:cell_A:0.1;reboot:cell_X@12.5", "reboot:cell_X@12.5", "cell_X"),
    ("drop:cell_A:1.5", "drop:cell_A:1.5", "outside"),
    ("dorp:cell_A:0.1", "dorp:cell_A:0.1", "did you mean 'drop'"),
    ("silent:accel_1@22-20", "silent:accel_1@22-20", "ends before"),
    ("reboot:cell_C", "reboot:cell_C", "needs a time"),
    ("stuck:accel_1.w", "stuck:accel_1.w", "no channel"),
    ("overrange:accel_1", "overrange:accel_1", "no status"),
    ("jitter:fast", "jitter:fast", "not a time"),
    ("lostsync:0.1", "lostsync:0.1", "--autostart"),
])
def test_fault_spec_errors_name_the_bad_token(cfg, spec, token, words):
    with pytest.raises(FaultSpecError) as e:
        Simulator(cfg, physics=make_physics(cfg), faults=spec, autostart="lostsync" not in spec,
                  channel=channel_name("spec"))
    assert repr(token) in str(e.value) and words in str(e.value)


def test_fault_spec_parses_units_and_windows():
    f = parse_faults(" jitter:500us ; drop:*:10%@1-2 ; silent:accel_1@20 ")
    assert f[0].value == pytest.approx(5e-4) and f[1].value == pytest.approx(0.1)
    assert (f[1].node, f[1].start, f[1].end) == ("*", 1.0, 2.0)
    assert (f[2].start, f[2].end) == (20.0, math.inf)


# ------------------------------------------------------------------------------------------
# rsra sim

def test_cli_sim_autostart_records_and_writes_truth(cfg, tmp_path, capsys):
    from rsra.sim_bus.truth import read_truth

    rec, truth_path = tmp_path / "run.log", tmp_path / "truth.npz"
    rc = cli_main(["sim", "--scenario", "ground-test", "--autostart", "--duration", "0.5",
                   "--record", str(rec), "--truth", str(truth_path), "--seed", "4",
                   "--channel", channel_name("cli"), "--faults", "drop:cell_A:0.2"])
    assert rc == 0
    truth = read_truth(truth_path)
    assert len(truth["index"]) == 100 and truth["meta"]["scenario"] == "ground-test"
    drops = {(f["sample"], f["node"]) for f in truth["faults"] if f["kind"] == "drop"}
    assert drops and {n for _, n in drops} == {"cell_A"}
    checked = check_record_against_truth(cfg, read_candump(rec), truth, drops)
    assert checked["load_cell"] == 7 * 100 - len(drops)
    assert "samples" in capsys.readouterr().err


def test_cli_run_variant_reaches_the_simulated_aircraft_and_its_truth(tmp_path):
    """`rsra run --sim ground-test --variant angles=step --variant angles.step_at_s=[0.5]`:
    the true angles step by 1° at 0.5 s (without the variants they stay constant), and the
    truth file names the variants."""
    from helpers_net import free_tcp_port

    from rsra.sim_bus.truth import read_truth

    def run(*variants: str) -> dict:
        path = tmp_path / f"t{len(variants)}.npz"
        rc = cli_main(["run", "--sim", "ground-test", "--speed", "max", "--duration", "1",
                       "--no-identification", "--truth", str(path), "--seed", "3",
                       "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", *variants])
        assert rc == 0
        return read_truth(path)

    plain = run()
    stepped = run("--variant", "angles=step", "--variant", "angles.step_at_s=[0.5]")
    assert np.ptp(plain["alpha_true"], axis=0).max() == 0.0
    move = np.degrees(np.abs(stepped["alpha_true"][-1] - stepped["alpha_true"][0]))
    assert np.allclose(move, 1.0, atol=1e-9)
    assert np.array_equal(stepped["alpha_true"][0], plain["alpha_true"][0])
    assert stepped["meta"]["variants"] == {"angles": "step", "angles.step_at_s": [0.5]}


def test_cli_sim_bad_faults_exit_2(capsys):
    rc = cli_main(["sim", "--scenario", "ground-test", "--autostart", "--duration", "0.1",
                   "--channel", channel_name("cli"), "--faults", "drop:nobody:0.1"])
    assert rc == 2
    assert "'drop:nobody:0.1'" in capsys.readouterr().err


@pytest.mark.timeout(60)
def test_cli_sim_ctrl_c_is_clean(tmp_path):
    rec = tmp_path / "run.log"
    p = subprocess.Popen([sys.executable, "-m", "rsra", "sim", "--scenario", "ground-test",
                          "--autostart", "--record", str(rec)], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and "samples" not in (p.stderr.readline() or "samples"):
            pass  # wait for the first progress line (1 s of running)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "stopped (Ctrl-C)" in err and "Traceback" not in err
    frames = read_candump(rec)  # the log is complete and parses
    assert sum(cob == 0x80 for _, cob, _ in frames) >= 100


def _ignore_sigint() -> None:  # what a shell does to a background job `rsra sim … &`
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("how", ["SIGINT", "SIGINT-background", "SIGTERM"])
def test_cli_sim_truth_written_on_stop(tmp_path, how):
    """`rsra sim --truth` stopped by Ctrl-C or SIGTERM (also when started as a background job,
    SIGINT ignored) writes the truth so far, atomically, and says where (issue 28)."""
    from rsra.sim_bus.truth import read_truth

    truth_path = tmp_path / "t.npz"
    p = subprocess.Popen([sys.executable, "-m", "rsra", "sim", "--scenario", "ground-test",
                          "--autostart", "--truth", str(truth_path),
                          "--channel", f"truth-stop-{how}-{os.getpid()}"], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_ignore_sigint if how == "SIGINT-background" else None)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and "samples" not in (p.stderr.readline() or "samples"):
            pass  # wait for the first progress line (1 s of running)
        p.send_signal(signal.SIGTERM if how == "SIGTERM" else signal.SIGINT)
        out, err = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)
    assert p.returncode == 0, err
    stopped = "SIGTERM" if how == "SIGTERM" else "Ctrl-C"
    assert f"stopped ({stopped})" in err and "Traceback" not in err, err
    assert f"truth in {truth_path}" in err, err
    truth = read_truth(truth_path)
    assert len(truth["index"]) >= 100 and truth["meta"]["scenario"] == "ground-test"
    assert [f.name for f in tmp_path.iterdir()] == ["t.npz"]  # no temporary file left
