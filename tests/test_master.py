"""The CANopen master (daq.master) against canopen LocalNodes and against the simulator; the
whole reader against simulator truth and injected faults (lock-step: simulated time only;
the master's SDO exchanges are real-time protocol steps, nothing is timed)."""
from __future__ import annotations

import copy
import math
import struct
from collections import Counter, defaultdict

import numpy as np
import pytest
from helpers_canopen import T0, LocalSlaves, LockstepRig, MasterRig, channel_name, wait_until

from rsra.config.rig import G0, config_dir, load_config, parse_config
from rsra.daq.bus.master import BootError
from rsra.daq.bus.reader import (BootNodes, BootNodesSyncOnDemand, FrameClock, HealthReport, Reader,
                                 WallClock)

EDS = config_dir() / "eds"


def samples(items) -> list:
    return [x for x in items if not isinstance(x, HealthReport)]


def _reader(cfg, ch, **kw) -> Reader:
    kw.setdefault("nodes", BootNodesSyncOnDemand())
    kw.setdefault("clock", FrameClock())
    return Reader(cfg, interface="virtual", channel=ch, **kw)


# ------------------------------------------------------------------------------------------
# against canopen LocalNodes


def test_boot_resets_verifies_configures_and_starts_every_node():
    cfg = load_config(overrides={"heartbeat": {"producer_ms": 50}})
    ch = channel_name("boot")
    slaves = LocalSlaves(cfg, ch)
    r = _reader(cfg, ch)
    try:
        r.start()
        wait_until(lambda: sum(c == 0x01 for _, c in slaves.nmt_log) == len(cfg.nodes),
                   what="NMT start of every node")
        by_node = defaultdict(list)
        for name, cmd in slaves.nmt_log:
            by_node[name].append(cmd)
        assert all(cmds == [0x82, 0x01] for cmds in by_node.values())  # reset comm, start
        assert set(by_node) == {n.name for n in cfg.nodes}
        # every reset went out before the first start (boot, then start)
        first_start = next(i for i, (_, c) in enumerate(slaves.nmt_log) if c == 0x01)
        assert all(c == 0x82 for _, c in slaves.nmt_log[:first_start])
        assert all(slaves.heartbeat_ms(n.name) == 50 for n in cfg.nodes)  # 0x1017 set
        nodes = r.health().to_dict()["nodes"]
        assert nodes["cell_A"]["identity"] == {"vendor-ID": 0xA5A, "product code": 0x404,
                                               "revision number": 0x10000, "serial number": 1}
        assert nodes["accel_1"]["identity"]["product code"] == \
            r.table.node("accel_1").identity[2]
        assert all(d["state"] == "booting" and d["boots"] == 1 for d in nodes.values())
    finally:
        r.close()
        slaves.close()


@pytest.mark.parametrize("node,index,sub,value,expected,what", [
    ("cell_C", 0x1018, 2, 0x405, 0x404, "0x1018:2 (product code)"),
    ("cell_E", 0x1018, 1, 0xBAD, 0xA5A, "0x1018:1 (vendor-ID)"),
    ("cell_A", 0x1000, 0, 0x00040195, 0x00040194, "0x1000 (device type)"),
    ("accel_1", 0x1A00, 2, 0x64010310, 0x64010210, "0x1A00:2 (TPDO1 mapped object 2)"),
    ("cell_G", 0x1800, 2, 254, 1, "0x1800:2 (TPDO1 transmission type)"),
    ("balance", 0x1801, 1, 0x2C2, 0x2C1, "0x1801:1 (TPDO2 COB-ID)"),
])
def test_a_mismatch_stops_the_start_naming_node_object_and_both_values(node, index, sub, value,
                                                                       expected, what, cfg):
    ch = channel_name("mismatch")
    data = struct.pack("<I", value)[:slaves_len(index, sub)]
    slaves = LocalSlaves(cfg, ch, overrides={(node, index, sub): data})
    r = _reader(cfg, ch)
    try:
        with pytest.raises(BootError) as e:
            r.start()
        text = str(e.value)
        assert node in text and what in text
        assert f"0x{value:08X}" in text and f"0x{expected:08X}" in text
        assert (e.value.node, e.value.expected, e.value.actual) == (node, expected, value)
        assert not any(c == 0x01 for _, c in slaves.nmt_log)  # nobody was started
    finally:
        r.close()
        slaves.close()


def slaves_len(index: int, sub: int) -> int:
    """Byte size of the object (UNSIGNED8 transmission type, else UNSIGNED32)."""
    return 1 if (0x1800 <= index < 0x1A00 and sub == 2) else 4


def test_a_required_node_missing_at_boot_stops_the_start():
    cfg = load_config(overrides={"heartbeat": {"boot_timeout_s": 0.2}})
    ch = channel_name("required")
    slaves = LocalSlaves(cfg, ch, absent=("cell_F",))
    r = _reader(cfg, ch)
    try:
        with pytest.raises(BootError, match=r"node cell_F: \(id 0x16\) is required but sent no "
                                            r"boot-up or heartbeat within 0.2 s"):
            r.start()
        assert not any(c == 0x01 for _, c in slaves.nmt_log)
    finally:
        r.close()
        slaves.close()


def test_an_optional_node_missing_is_reported_and_the_start_goes_on():
    cfg = load_config(overrides={"heartbeat": {"boot_timeout_s": 0.2}})
    ch = channel_name("optional")
    slaves = LocalSlaves(cfg, ch, absent=("balance",))
    r = _reader(cfg, ch)
    try:
        r.start()
        wait_until(lambda: sum(c == 0x01 for _, c in slaves.nmt_log) == len(cfg.nodes) - 1,
                   what="NMT start")
        nodes = r.health().to_dict()["nodes"]
        assert nodes["balance"]["state"] == "missing" and not nodes["balance"]["required"]
        # every other node was heard booting and started; LocalSlaves send no periodic
        # heartbeat, so a slow machine may see the watchdog call them "lost" after that:
        # the property is that they booted, were started and are not "missing"
        others = {n: d for n, d in nodes.items() if n != "balance"}
        assert all(d["boots"] >= 1 and d["heartbeat_age"] is not None
                   and d["state"] in ("booting", "lost") for d in others.values()), nodes
    finally:
        r.close()
        slaves.close()


def test_the_service_produces_sync_with_the_counter():
    """python-can periodic send at the sample rate, counter 1…overflow (asserts that it runs
    and what it sends, not its timing)."""
    cfg = load_config()
    ch = channel_name("sync")
    slaves = LocalSlaves(cfg, ch)
    r = _reader(cfg, ch, nodes=BootNodes(), clock=WallClock())
    try:
        r.start()
        wait_until(lambda: r.assembler.emitted >= 4, what="four SYNC periods")
        got = samples(r.poll())
        assert [s.sync for s in got[:4]] == [1, 2, 3, 4]
        # the LocalNodes send no TPDOs: every sample passed on at the next SYNC, all missing
        assert set(got[0].missing) >= {c.node for c in cfg.cells}
    finally:
        r.close()
        slaves.close()


def test_invalid_reader_combinations_have_no_spelling(cfg):
    """Issue 16: what differs per source is a class or a policy object, and what cannot work
    together cannot be written (no run-time flag checks left)."""
    import inspect

    from rsra.daq.bus.reader import (BlockQueue, DropQueue, Listen, LockstepReader,
                                     OfflineReader, RestartNodes)

    # SYNC on demand only on the on-demand master; supervise() only on the restart policy
    assert hasattr(BootNodesSyncOnDemand(), "send_sync")
    assert not hasattr(BootNodes(), "send_sync") and not hasattr(Listen(), "send_sync")
    assert not hasattr(BootNodes(), "supervise") and hasattr(RestartNodes(), "supervise")
    # only a lock-step reader is pumped; only an offline reader is fed without a bus
    assert hasattr(LockstepReader, "pump") and not hasattr(Reader, "pump")
    assert not hasattr(OfflineReader, "pump") and not hasattr(OfflineReader, "start")
    # an offline reader takes no node policy and no clock; a lock-step reader no clock
    assert {"nodes", "clock"}.isdisjoint(inspect.signature(OfflineReader).parameters)
    assert "clock" not in inspect.signature(LockstepReader).parameters
    with pytest.raises(TypeError):
        OfflineReader(cfg, nodes=BootNodes())
    # no mode keyword is left on any reader
    for cls in (Reader, LockstepReader, OfflineReader):
        params = set(inspect.signature(cls).parameters)
        assert params.isdisjoint({"master", "restart_nodes", "periodic_sync", "wall_clock",
                                  "overflow", "offline", "queue_size"}), cls
    assert "notifier" not in inspect.signature(Reader.start).parameters
    # the defaults: live reader drops, lock-step reader blocks
    assert isinstance(Reader(cfg, interface="virtual").items, DropQueue)
    assert isinstance(LockstepReader(cfg).items, BlockQueue)


def test_own_sync_needs_own_messages_on_a_given_bus(cfg):
    import can

    bus = can.Bus(interface="virtual", channel=channel_name("own"), receive_own_messages=False)
    try:
        with pytest.raises(ValueError, match="receive_own_messages"):
            Reader(cfg, bus=bus).start()
    finally:
        bus.shutdown()


# ------------------------------------------------------------------------------------------
# against the simulator


def _sim_cfg_with_eds(cfg, tmp_path, node_index: int, eds_name: str, edit):
    eds = tmp_path / f"sim_{eds_name}"
    eds.write_text(edit((EDS / eds_name).read_text()))
    raw = copy.deepcopy(cfg.raw)
    raw["nodes"][node_index]["eds"] = str(eds)
    return parse_config(raw, base_dir=config_dir())


def test_boot_and_start_with_the_simulator(cfg):
    rig = MasterRig(cfg)
    try:
        rig.start()
        out = samples(rig.sync(30))
        nodes = rig.reader.health().to_dict()["nodes"]
        assert all(d["state"] == "operational" for d in nodes.values())
        assert all(s.complete for s in out[1:])  # sample 0: optional nodes not yet seen alive
        assert out[-1].omega is not None and out[-1].known_H is not None
        assert [s.seq for s in out] == list(range(30))
    finally:
        rig.close()


@pytest.mark.parametrize("node_index,eds,edit,what", [
    (2, "load_cell.eds", lambda s: s.replace("DefaultValue=0x00000404", "DefaultValue=0x00000405"),
     "0x1018:2 (product code) reads 0x00000405, the EDS says 0x00000404"),
    (7, "accelerometer.eds", lambda s: s.replace("DefaultValue=0x64010210",
                                                  "DefaultValue=0x64010310"),
     "0x1A00:2 (TPDO1 mapped object 2) reads 0x64010310, the EDS says 0x64010210"),
])
def test_a_simulated_node_with_the_wrong_identity_or_mapping_stops_the_start(
        cfg, tmp_path, node_index, eds, edit, what):
    sim_cfg = _sim_cfg_with_eds(cfg, tmp_path, node_index, eds, edit)
    rig = MasterRig(cfg, sim_cfg=sim_cfg)
    try:
        with pytest.raises(BootError) as e:
            rig.start()
        assert str(e.value) == f"node {cfg.nodes[node_index].name}: {what}"
        assert all(n.state != 0x05 for n in rig.sim.nodes)  # nobody operational
    finally:
        rig.close()


def test_optional_nodes_missing_from_the_aircraft_are_reported():
    cfg = load_config(overrides={"heartbeat": {"boot_timeout_s": 0.3}})
    rig = MasterRig(cfg, nodes_present=())
    try:
        rig.start()
        out = samples(rig.sync(40))
        nodes = rig.reader.health().to_dict()["nodes"]
        assert nodes["rotor_speed"]["state"] == nodes["balance"]["state"] == "missing"
        assert all(s.complete and s.omega is None and s.known_H is None for s in out)
    finally:
        rig.close()


def test_a_node_that_reboots_mid_run_is_back_within_a_second(cfg):
    rig = MasterRig(cfg, faults="reboot:cell_C@0.5")
    try:
        rig.start()
        out = samples(rig.sync(300))  # 1.5 s
        gone = [s.t for s in out if "cell_C" in s.missing]
        assert gone, "the reboot was not seen"
        assert gone[-1] - gone[0] < 1.0  # back within a second of acquisition time
        assert all(s.complete for s in out if s.t > gone[-1])
        h = rig.reader.health().to_dict()["nodes"]["cell_C"]
        assert h["boots"] == 3 and h["state"] == "operational"  # power-on, reset, reboot
        assert rig.reader.master.reconfigured == 1
    finally:
        rig.close()


def test_heartbeat_loss_is_detected_within_two_and_a_half_periods(cfg):
    rig = LockstepRig(cfg, faults="silent:accel_1@0.6-1.1")
    events = []
    sup = rig.reader.supervisor
    base = sup.on_event
    sup.on_event = lambda kind, node: (events.append((kind, node, rig.reader.now)),
                                       base(kind, node))
    try:
        out = samples(rig.step(300))
        period = cfg.heartbeat.producer_ms / 1000
        lost = [(n, t) for k, n, t in events if k == "lost"]
        assert [n for n, _ in lost] == ["accel_1"]
        t_silent = T0 + 0.6
        # heartbeats at ≤ t_silent; declared lost at the first frame after 2.5 periods
        assert lost[0][1] - t_silent <= cfg.heartbeat.timeout_factor * period + cfg.sample_period_s
        back = [t for k, n, t in events if k == "alive" and n == "accel_1"]
        assert back and back[0] >= T0 + 1.1
        flagged = [s for s in out if "missing:accel_1" in s.flags]
        assert flagged and all(T0 + 0.6 - 0.005 <= s.t < T0 + 1.1 + 0.005 for s in flagged)
    finally:
        rig.close()


def test_every_channel_matches_truth_within_the_encoding_resolution(cfg):
    rig = LockstepRig(cfg)
    try:
        out = samples(rig.step(400))
        truth = rig.sim.samples
        assert [s.seq for s in out] == list(range(400))
        n_rotor = 0
        for s in out:
            tr = truth[s.seq]
            # stamped when the SYNC frame went out: its nominal time, or after the frames
            # still occupying the bus (heartbeats)
            assert 0.0 <= s.t - rig.sim.sync_info[s.seq][2] < 1e-3
            # REAL32: half an ulp of float32
            np.testing.assert_allclose(s.T, tr.T, rtol=2.0**-24, atol=0)
            # INTEGER16 mg counts: half a count (none saturate within ±7 g)
            assert np.abs(s.accel - tr.accel).max() <= 0.5e-3 * G0 * (1 + 1e-9)
            assert s.cell_status == {c.name: int(tr.cell_status[i])
                                     for i, c in enumerate(cfg.cells)}
            if s.omega is not None:
                n_rotor += 1
                assert s.omega == pytest.approx(tr.omega, rel=2.0**-24)
                d = (s.azimuth - tr.azimuth + math.pi) % (2 * math.pi) - math.pi
                assert abs(d) <= math.pi / 65536 * (1 + 1e-9)
                np.testing.assert_allclose(s.known_H, tr.H_balance, rtol=2.0**-24, atol=0)
        assert n_rotor == 400  # from the first sample on (it waits for every node: issue 29)
    finally:
        rig.close()


def test_each_injected_fault_is_counted_and_flagged(cfg):
    faults = ("drop:cell_B:0.03;malformed:cell_E:0.03;unknown:0.03;lostsync:0.03;"
              "errorframe:0.03")
    rig = LockstepRig(cfg, faults=faults, seed=11)
    try:
        out = samples(rig.step(600))
        log = rig.sim.fault_log
        kinds = Counter(f["kind"] for f in log)
        assert all(kinds[k] >= 5 for k in ("drop", "malformed", "unknown", "lostsync",
                                            "errorframe")), kinds
        h = rig.reader.health().to_dict()
        assert h["bus"]["unknown"] == kinds["unknown"]
        assert h["bus"]["errors"] == kinds["errorframe"]
        assert h["bus"]["malformed"] == kinds["malformed"]
        assert h["samples"]["lost"] == kinds["lostsync"]
        by_seq = {s.seq: s for s in out}
        lost = {f["sample"] for f in log if f["kind"] == "lostsync"}
        assert set(range(600)) - set(by_seq) == lost  # lost samples keep their numbers
        for k in lost:
            nxt = min(j for j in by_seq if j > k) if any(j > k for j in by_seq) else None
            if nxt is not None:
                assert "lost_before" in by_seq[nxt].flags and by_seq[nxt].lost_before >= 1
        for kind, node in (("drop", "cell_B"), ("malformed", "cell_E")):
            hit = {f["sample"] for f in log if f["kind"] == kind} - lost
            flagged = {s.seq for s in out if f"missing:{node}" in s.flags}
            assert flagged == hit
        assert h["samples"]["incomplete"] == len({f["sample"] for f in log
                                                  if f["kind"] in ("drop", "malformed")} - lost)
    finally:
        rig.close()


def test_an_optional_node_that_appears_later_is_configured_and_started():
    cfg = load_config(overrides={"heartbeat": {"boot_timeout_s": 0.2}})
    ch = channel_name("late")
    slaves = LocalSlaves(cfg, ch, absent=("rotor_speed",))
    r = _reader(cfg, ch)
    late = None
    try:
        r.start()
        assert r.health().to_dict()["nodes"]["rotor_speed"]["state"] == "missing"
        late = LocalSlaves(cfg, ch, absent=tuple(n.name for n in cfg.nodes
                                                 if n.name != "rotor_speed"))
        late.net.send_message(0x731, b"\x00")  # power-on: boot-up
        wait_until(lambda: ("rotor_speed", 0x01) in late.nmt_log, what="the late node's start")
        assert late.heartbeat_ms("rotor_speed") == cfg.heartbeat.producer_ms
        assert r.master.reconfigured == 1
        assert r.health().to_dict()["nodes"]["rotor_speed"]["identity"]["product code"] == 0xB01
    finally:
        r.close()
        slaves.close()
        if late is not None:
            late.close()


def test_a_rebooted_node_that_fails_verification_is_reported_not_retried():
    cfg = load_config()
    ch = channel_name("reverify")
    slaves = LocalSlaves(cfg, ch)
    r = _reader(cfg, ch)
    try:
        r.start()
        wait_until(lambda: sum(c == 0x01 for _, c in slaves.nmt_log) == len(cfg.nodes),
                   what="NMT start")
        # the unit is swapped for another product and powers up
        slaves.nodes["cell_E"].set_data(0x1018, 2, struct.pack("<I", 0x999),
                                        check_writable=False)
        slaves.net.send_message(0x715, b"\x00")
        wait_until(lambda: r.health().to_dict()["nodes"]["cell_E"].get("error"), what="the verification")
        err = r.health().to_dict()["nodes"]["cell_E"]["error"]
        assert err == ("node cell_E: 0x1018:2 (product code) reads 0x00000999, "
                       "the EDS says 0x00000404")
        for _ in range(5):  # pre-operational heartbeats do not trigger retries
            slaves.net.send_message(0x715, b"\x7f")
        slaves.net.send_message(0x95, b"\x00\x10\x01")  # EMCY as a marker: all seen after it
        wait_until(lambda: r.health().to_dict()["nodes"]["cell_E"]["emcy_count"] == 1, what="the frames")
        wait_until(r.nodes.idle, what="the master")
        assert r.health().to_dict()["nodes"]["cell_E"]["state"] == "error"
        assert sum(1 for n, c in slaves.nmt_log if n == "cell_E" and c == 0x01) == 1
        assert r.master.reconfigured == 0
    finally:
        r.close()
        slaves.close()
