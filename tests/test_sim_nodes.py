"""The simulated CANopen slaves (sim_bus.nodes) — the LocalNode wrapper — seen from the outside
by a master built only from canopen's RemoteNode and the EDS, and unit by unit.

Lock-step throughout: simulated time comes from the SYNC timestamps the test master sends, so
heartbeat periods are measured exactly, without sleeping. SDO needs the simulator's bus
thread (sim_bus.drivers.FollowSim); an SDO upload doubles as a barrier: the simulator handles frames in
order, so when the answer is back every earlier SYNC/NMT has been handled.
"""
from __future__ import annotations

import itertools
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import can
import canopen
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from rsra.sim_bus.bus_sim import Simulator
from rsra.sim_bus.drivers import FollowSim, RealtimeSim
from rsra.sim_bus.nodes import (
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMM,
    NMT_RESET_NODE,
    NMT_START,
    NMT_STOP,
    OPERATIONAL,
    PRE_OPERATIONAL,
    STOPPED,
    SimNode,
    decode_channel,
    encode_channel,
)

_chan = itertools.count()


def channel_name(tag: str) -> str:
    return f"test-sim-{tag}-{next(_chan)}"


# ------------------------------------------------------------------------------------------
# a small stand-in sample source (the physics engineer's AircraftPhysics when it exists)

@dataclass
class StandInSample:
    index: int
    t: float
    T: np.ndarray
    cell_status: np.ndarray
    accel: np.ndarray
    omega: float
    azimuth: float
    H_balance: np.ndarray
    drive: np.ndarray
    truth: Any = None


class StandInPhysics:
    """Deterministic, seeded, plausible channel values: enough to exercise the bus."""

    def __init__(self, cfg, seed: int = 0):
        self.dt = cfg.sample_period_s
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        self._k = 0
        self._K = len(cfg.accelerometers)
        self._Q = len(cfg.external_loads)
        self._omega = cfg.rotor.omega_nominal_rad_s

    def next_sample(self) -> StandInSample:
        k, r = self._k, self._rng
        self._k += 1
        t = k * self.dt
        psi = self._omega * t
        return StandInSample(
            index=k, t=t,
            T=-11500.0 + 3000.0 * np.sin(psi + np.arange(7)) + 50.0 * r.standard_normal(7),
            cell_status=np.zeros(7, np.uint8),
            accel=np.array([[0.0, 0.0, -9.80665]] * self._K) + 0.3 * r.standard_normal((self._K, 3)),
            omega=self._omega * (1 + 1e-3 * r.standard_normal()),
            azimuth=psi % (2 * math.pi),
            H_balance=np.array([1e3, -2e3, -80e3, 5e3, 2e3, -1e3]) + 10 * r.standard_normal(6),
            drive=r.standard_normal(self._Q))


def make_physics(cfg, seed: int = 7):
    """AircraftPhysics on ground-test when sim_bus.physics exists, else the stand-in."""
    try:
        from rsra.sim_bus.physics import AircraftPhysics
        from rsra.sim_bus.scenarios import load_scenario
    except ImportError:
        return StandInPhysics(cfg, seed)
    return AircraftPhysics(cfg, load_scenario("ground-test"), seed=seed)


# ------------------------------------------------------------------------------------------
# an outside master: canopen RemoteNodes from the EDS on its own virtual bus

class Collector(can.Listener):
    def __init__(self):
        self.frames: deque[can.Message] = deque(maxlen=200_000)

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)

    def take(self) -> list[can.Message]:
        out = list(self.frames)
        self.frames.clear()
        return out


@dataclass
class Master:
    net: canopen.Network
    collector: Collector
    remotes: dict[str, Any]
    sim: FollowSim
    t: float = 0.0
    k: int = 0
    counter: int = 0
    ids: dict[str, int] = field(default_factory=dict)

    def sync(self, n: int = 1, dt: float = 0.005) -> None:
        """n SYNC frames, simulated time advancing dt each (the master's acquisition clock)."""
        for _ in range(n):
            self.k += 1
            self.t = round(self.k * dt, 9)
            self.counter = self.counter % 240 + 1
            self.net.bus.send(can.Message(arbitration_id=0x80, data=[self.counter], timestamp=self.t,
                                          is_extended_id=False))

    def nmt(self, command: int, node_id: int = 0) -> None:
        self.net.bus.send(can.Message(arbitration_id=0x000, data=[command, node_id],
                                      timestamp=self.t, is_extended_id=False))

    def barrier(self) -> list[can.Message]:
        """Everything the simulator sent in answer to what the master sent so far."""
        self.remotes[next(iter(self.remotes))].sdo.upload(0x1000, 0)
        return [m for m in self.collector.take() if not 0x580 <= m.arbitration_id < 0x600]


@pytest.fixture
def master(cfg):
    chan = channel_name("outside")
    collector = Collector()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05  # quick shutdown
    net.listeners.append(collector)
    net.connect(interface="virtual", channel=chan, receive_own_messages=False,
                preserve_timestamps=True)
    remotes = {n.name: net.add_node(n.node_id, str(n.eds)) for n in cfg.nodes}
    for r in remotes.values():
        r.sdo.RESPONSE_TIMEOUT = 1.0
    sim = FollowSim(cfg, physics=make_physics(cfg), channel=chan)
    sim.start()
    try:
        yield Master(net, collector, remotes, sim, ids={n.name: n.node_id for n in cfg.nodes})
    finally:
        sim.close()
        net.disconnect()


def tpdo_cobs(sim: Simulator) -> dict[int, str]:
    return {c.cob_id: n.name for n in sim.nodes for c in n.tpdo_configs() if c.valid}


def heartbeat_states(frames: list[can.Message], node_id: int) -> list[int]:
    return [m.data[0] for m in frames if m.arbitration_id == 0x700 + node_id]


# ------------------------------------------------------------------------------------------

def test_outside_master_reads_identity_heartbeat_and_tpdo_maps_as_the_eds_says(master, cfg):
    boot = master.barrier()
    for n in cfg.nodes:  # every node sent its boot-up frame on start
        assert heartbeat_states(boot, n.node_id)[:1] == [0]
    for n in cfg.nodes:
        r = master.remotes[n.name]
        od = r.object_dictionary
        assert r.sdo[0x1000].raw == od[0x1000].default, n.name
        for sub in (1, 2, 3, 4):
            assert r.sdo[0x1018][sub].raw == od[0x1018][sub].default, (n.name, sub)
        assert r.sdo[0x1017].raw == od[0x1017].default == cfg.heartbeat.producer_ms
        assert r.sdo[0x1001].raw == 0
        r.tpdo.read()
        n_maps = 0
        for num, pdo in r.tpdo.map.items():
            com, mp = od[0x1800 + num - 1], od[0x1A00 + num - 1]
            assert pdo.cob_id == com[1].default & 0x7FF, (n.name, num)
            assert pdo.enabled
            assert pdo.trans_type == com[2].default == 1
            expected = [(w >> 16, (w >> 8) & 0xFF, w & 0xFF)
                        for w in (mp[s].default for s in range(1, mp[0].default + 1))]
            assert [(v.index, v.subindex, v.length) for v in pdo.map] == expected, (n.name, num)
            n_maps += 1
        assert n_maps == od.device_information.nr_of_TXPDO


def test_tpdos_only_when_operational_one_per_sync(master, cfg):
    cobs = tpdo_cobs(master.sim)
    master.barrier()
    master.sync(7)  # pre-operational: nothing
    assert [m for m in master.barrier() if m.arbitration_id in cobs] == []
    master.nmt(NMT_START)
    master.sync(11)
    got = [m for m in master.barrier() if m.arbitration_id in cobs]
    assert len(got) == 11 * len(cobs)
    assert {m.arbitration_id for m in got} == set(cobs)
    # each TPDO's length is what its mapping says (load cell REAL32 + UNSIGNED8 = 5 bytes …)
    lengths = {c.cob_id: c.length for n in master.sim.nodes for c in n.tpdo_configs()}
    assert all(len(m.data) == lengths[m.arbitration_id] for m in got)
    master.nmt(NMT_STOP, master.ids["cell_C"])  # one node stopped, the others go on
    master.sync(5)
    got = [m for m in master.barrier() if m.arbitration_id in cobs]
    assert len(got) == 5 * (len(cobs) - 1)
    assert all(cobs[m.arbitration_id] != "cell_C" for m in got)
    master.nmt(NMT_PRE_OPERATIONAL)
    master.sync(5)
    assert [m for m in master.barrier() if m.arbitration_id in cobs] == []


def test_nmt_stop_and_reset_seen_in_heartbeats_and_bootup(master, cfg):
    nid = master.ids["cell_A"]
    node = master.sim.by_name["cell_A"]
    master.barrier()
    master.nmt(NMT_START)
    master.sync(25)  # 125 ms: at least one heartbeat
    assert set(heartbeat_states(master.barrier(), nid)) == {OPERATIONAL}
    master.nmt(NMT_STOP, nid)
    master.sync(25)
    assert set(heartbeat_states(master.barrier(), nid)) == {STOPPED}
    # reset node: boot-up frame, then PRE-OPERATIONAL — not stuck in INITIALISING as LocalNode
    master.remotes["cell_A"].sdo[0x1017].raw = 40
    master.nmt(NMT_RESET_NODE, nid)
    master.sync(25)
    states = heartbeat_states(master.barrier(), nid)
    assert states[0] == 0 and set(states[1:]) == {PRE_OPERATIONAL}
    assert node.local.nmt.state == "PRE-OPERATIONAL"
    assert master.remotes["cell_A"].sdo[0x1017].raw == 100  # back to the EDS default
    # reset communication also restores the communication objects, then waits for start
    master.remotes["cell_A"].sdo[0x1800][2].raw = 3
    master.nmt(NMT_RESET_COMM, nid)
    assert master.remotes["cell_A"].sdo[0x1800][2].raw == 1
    master.nmt(NMT_START, nid)
    master.sync(4)
    cob = master.remotes["cell_A"].object_dictionary[0x1800][1].default
    assert sum(m.arbitration_id == cob for m in master.barrier()) == 4


def assert_periodic(ts: np.ndarray, period: float) -> None:
    """Due times are first + n·period exactly; a frame may only be late by bus arbitration
    (the frames due at the same instant ahead of it: well under 1 ms at 1 Mbit/s)."""
    late = ts - (ts[0] + period * np.arange(len(ts)))
    assert np.all(late > -2e-6) and np.all(late < 1e-3), late
    assert np.median(np.diff(ts)) == pytest.approx(period, abs=1e-6)


def test_heartbeat_period_follows_0x1017(master, cfg):
    master.barrier()
    master.sync(400)  # 2 s of simulated time
    frames = master.barrier()
    for n in cfg.nodes:
        ts = np.array([m.timestamp for m in frames if m.arbitration_id == 0x700 + n.node_id])
        assert len(ts) == 20, n.name
        assert_periodic(ts, cfg.heartbeat.producer_ms / 1000.0)
    master.remotes["accel_1"].sdo[0x1017].raw = 35
    master.sync(200)
    ts = np.array([m.timestamp for m in master.barrier() if m.arbitration_id == 0x721])
    assert len(ts) >= 28
    assert_periodic(ts, 0.035)
    master.remotes["accel_1"].sdo[0x1017].raw = 0  # 0 disables the producer
    master.sync(100)
    assert not [m for m in master.barrier() if m.arbitration_id == 0x721]


def test_sdo_read_of_a_process_object_returns_what_the_last_tpdo_carried(master, cfg):
    master.barrier()
    master.nmt(NMT_START)
    master.sync(3)
    frames = master.barrier()
    r = master.remotes["cell_B"]
    cob = r.object_dictionary[0x1800][1].default
    last = [m for m in frames if m.arbitration_id == cob][-1]
    force, status = struct.unpack("<fB", last.data)
    assert r.sdo[0x6130][1].raw == force
    assert r.sdo[0x6150][1].raw == status
    acc = master.remotes["accel_1"]
    last = [m for m in frames if m.arbitration_id == acc.object_dictionary[0x1800][1].default][-1]
    assert tuple(acc.sdo[0x6401][s].raw for s in (1, 2, 3)) == struct.unpack("<hhh", last.data)


def test_master_side_pdo_changes_apply_at_the_next_sync(master, cfg):
    """Remap the load cell to status only, transmission type 2; an invalid entry is refused."""
    r = master.remotes["cell_D"]
    master.barrier()
    r.sdo[0x1800][1].raw = r.object_dictionary[0x1800][1].default | (1 << 31)  # disable
    r.sdo[0x1A00][0].raw = 0
    r.sdo[0x1A00][1].raw = 0x61500108
    with pytest.raises(SdoAbortedError):
        r.sdo[0x1A00][2].raw = 0x70000108  # no such object
    r.sdo[0x1A00][0].raw = 1
    r.sdo[0x1800][2].raw = 2
    r.sdo[0x1800][1].raw = r.object_dictionary[0x1800][1].default
    master.nmt(NMT_START)
    master.sync(6)
    cob = r.object_dictionary[0x1800][1].default
    got = [m for m in master.barrier() if m.arbitration_id == cob]
    assert len(got) == 3 and all(len(m.data) == 1 for m in got)


# ------------------------------------------------------------------------------------------
# the wrapper unit by unit (no bus)

@pytest.fixture
def cell(cfg):
    n = cfg.node("cell_A")
    clock = [0.0]
    node = SimNode(n.name, n.role, n.node_id, n.eds, clock=lambda: clock[0])
    node.clock = clock
    return node


def test_transmission_types_and_sync_start(cell):
    cell.boot(0.0)
    cell.nmt(NMT_START, 0)
    cell.update([1.0, 0])
    assert [f.kind for f in cell.sync(1)] == ["tpdo"]
    cell.local.sdo.download(0x1800, 2, bytes([3]))  # every third SYNC
    sent = [bool(cell.sync(c)) for c in range(1, 10)]
    assert sent == [False, False, True] * 3
    cell.local.sdo.download(0x1800, 2, bytes([0]))  # acyclic: only when the data change
    sent = []
    for c, v in enumerate([1.0, 1.0, 2.0, 2.0, 3.0]):
        cell.update([v, 0])
        sent.append(bool(cell.sync(c)))
    assert sent == [True, False, True, False, True]
    cell.local.sdo.download(0x1800, 1, struct.pack("<I", 0x191 | 1 << 31))  # not valid
    assert cell.sync(1) == []


def test_reset_returns_to_pre_operational_and_restores_defaults(cell):
    frames = cell.boot(0.0)
    assert [(f.kind, f.cob_id, f.data) for f in frames] == [("bootup", 0x711, b"\x00")]
    cell.nmt(NMT_START, 0)
    cell.local.sdo.download(0x1017, 0, struct.pack("<H", 20))
    assert cell.heartbeat_period_s == 0.02
    frames = cell.nmt(NMT_RESET_COMM, 0x11, t=1.0)
    assert [f.kind for f in frames] == ["bootup"]
    assert cell.state == PRE_OPERATIONAL and cell.local.nmt.state == "PRE-OPERATIONAL"
    assert cell.heartbeat_period_s == 0.1
    assert cell.nmt(NMT_START, 0x12) == [] and cell.state == PRE_OPERATIONAL  # not addressed
    hb = cell.heartbeats(1.35)
    assert [round(t, 9) for t, _ in hb] == [1.1, 1.2, 1.3]
    assert {f.data for _, f in hb} == {bytes([PRE_OPERATIONAL])}


def test_emcy_and_error_register(cell):
    cell.boot(0.0)
    f = cell.raise_error(0xFF01, info=b"\x01")
    code, reg, info = struct.unpack("<HB5s", f.data)
    assert f.cob_id == 0x91 and code == 0xFF01 and reg & 1 and info[:1] == b"\x01"
    assert cell.local.sdo.upload(0x1001, 0) == bytes([reg])
    f = cell.clear_error(0xFF01)
    assert struct.unpack("<HB5s", f.data)[:2] == (0, 0)
    assert cell.local.sdo.upload(0x1001, 0) == b"\x00"
    assert cell.clear_error(0xFF01) is None


def test_node_codec_agrees_with_the_shared_channel_codec(cfg):
    """SimNode's generic EDS-typed encoder and sim_bus.offline.ChannelCodec (what the simulator
    feeds its nodes, shared with the off-line API) give the same raw values inside the sensor
    range; the generic one decodes back within half a count."""
    from rsra.sim_bus.offline import ChannelCodec

    rng = np.random.default_rng(3)
    codec = ChannelCodec(cfg)
    n = 2000
    K, Q = len(cfg.accelerometers), len(cfg.external_loads)
    fs_acc = np.array([a.full_scale_g for a in cfg.accelerometers]) * 9.80665
    ch = dict(T=rng.uniform(-2e5, 2e5, (n, 7)), cell_status=rng.integers(0, 4, (n, 7)),
              accel=rng.uniform(-1, 1, (n, K, 3)) * fs_acc[None, :, None],
              omega=rng.uniform(0, 40, n), azimuth=rng.uniform(0, 2 * np.pi, n),
              H_balance=rng.uniform(-2e5, 2e5, (n, 6)), drive=rng.uniform(-1e4, 1e4, (n, Q)))
    enc = codec.encode(**ch)
    raw_of = {
        "load_cell": lambda j, i: (enc.force[j, i], enc.status[j, i]),
        "accelerometer": lambda j, i: enc.accel_counts[j, i],
        "rotor_speed": lambda j, i: (enc.omega[j], enc.azimuth_counts[j]),
        "balance": lambda j, i: enc.balance[j],
    }
    eng_of = {
        "load_cell": lambda j, i: (ch["T"][j, i], ch["cell_status"][j, i]),
        "accelerometer": lambda j, i: ch["accel"][j, i],
        "rotor_speed": lambda j, i: (ch["omega"][j], ch["azimuth"][j]),
        "balance": lambda j, i: ch["H_balance"][j],
    }
    slot = {c.node: i for i, c in enumerate(cfg.cells)} | {a.node: k for k, a in enumerate(cfg.accelerometers)}
    checked = 0
    for nc in cfg.nodes:
        node = SimNode(nc.name, nc.role, nc.node_id, nc.eds, clock=lambda: 0.0)
        i = slot.get(nc.name, 0)
        for j in range(0, n, 7):
            for (name, var), v, r in zip(node.channels, eng_of[nc.role](j, i), raw_of[nc.role](j, i)):
                mine = encode_channel(nc.role, name, v, var)
                assert mine == r.item(), (nc.name, name, v)
                back = decode_channel(nc.role, name, mine, var)
                if nc.role == "accelerometer":
                    assert abs(back - v) <= 0.5 * 9.80665e-3 + 1e-9
                elif name == "azimuth":
                    assert abs(math.remainder(back - v, 2 * math.pi)) <= math.pi / 65536 + 1e-12
                checked += 1
    assert checked > 1000
    # outside the sensor range the generic encoder saturates at the data type (INTEGER16)
    acc = SimNode("a", "accelerometer", 0x21, cfg.node("accel_1").eds, clock=lambda: 0.0)
    var = acc.channels[0][1]
    assert encode_channel("accelerometer", "x", 1e6, var) == 32767
    assert encode_channel("accelerometer", "x", -1e6, var) == -32768


def test_live_follow_mode_heartbeats_on_the_wall_clock_and_answers_sync(cfg):
    """The default mode: wall clock, bus thread and heartbeat thread; a canopen master starts
    the nodes with NMT and produces SYNC with canopen's own SyncProducer."""
    chan = channel_name("live")
    collector = Collector()
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.listeners.append(collector)
    net.connect(interface="virtual", channel=chan, receive_own_messages=False)
    remotes = {n.name: net.add_node(n.node_id, str(n.eds)) for n in cfg.nodes}
    for r in remotes.values():
        r.sdo.RESPONSE_TIMEOUT = 5.0  # generous: a loaded 2-core CI box
    sim = RealtimeSim(cfg, physics=make_physics(cfg), channel=chan)
    try:
        sim.start()
        net.nmt.send_command(NMT_START)
        # the heartbeat thread reports the new state within one producer period
        # a heartbeat already on its way may still say PRE-OPERATIONAL: wait for the next ones
        state = None
        for _ in range(20):
            state = remotes["accel_1"].nmt.wait_for_heartbeat(timeout=5.0)
            if state == "OPERATIONAL":
                break
        assert state == "OPERATIONAL"
        for c in range(1, 11):
            net.sync.transmit(c)
        remotes["cell_A"].sdo.upload(0x1000, 0)  # barrier: everything before it is answered
        cobs = tpdo_cobs(sim)
        got = [m for m in collector.take() if m.arbitration_id in cobs]
        assert len(got) == 10 * len(cobs)
    finally:
        sim.close()
        net.disconnect()
    assert not sim._ticker.is_alive()


def test_the_heartbeat_schedule_alone():
    """HeartbeatSchedule without a node: due times base + n·period (no accumulated
    rounding), nothing when off, at most one period's backlog after a long stall."""
    from rsra.sim_bus.nodes import HeartbeatSchedule

    hb = HeartbeatSchedule()
    assert hb.next is None and hb.due(100.0) == []
    hb.arm(1.0, 100)
    assert hb.due(1.05) == [] and hb.next == pytest.approx(1.1)
    assert hb.due(1.3) == [pytest.approx(1.1), pytest.approx(1.2), pytest.approx(1.3)]
    due = hb.due(60.0)  # a stall: the backlog is cut to about a period, not 587 beats
    assert 1 <= len(due) <= 2 and due[-1] == pytest.approx(60.0)
    hb.arm(5.0, 0)
    assert hb.next is None and hb.due(10.0) == []


def test_the_error_state_alone():
    """ErrorState without a node: the register is the OR of the active errors' bits (generic
    always set), clearing one sends the EMCY reset with what remains, an unknown code none."""
    from rsra.sim_bus.nodes import EMCY_STRUCT, ERR_GENERIC, ERR_MANUFACTURER, ErrorState

    es = ErrorState()
    f1 = es.raise_error(0x81, 0x5000, ERR_MANUFACTURER, b"\x01")
    assert f1.kind == "emcy" and f1.cob_id == 0x81
    assert EMCY_STRUCT.unpack(f1.data)[:2] == (0x5000, ERR_MANUFACTURER | ERR_GENERIC)
    es.raise_error(0x81, 0x6000, ERR_GENERIC, b"")
    assert es.clear_error(0x81, 0x7777) is None
    f2 = es.clear_error(0x81, 0x5000)
    code, register, info = EMCY_STRUCT.unpack(f2.data)
    assert (code, register, info[:2]) == (0, ERR_GENERIC, struct.pack("<H", 0x5000))
    es.clear()
    assert es.active == {} and es.register == 0


def test_the_node_drives_canopen_only_through_its_public_api(cell):
    """LocalNode's NMT view follows every state through its own command handler, and a write
    to 0x1017 on a network starts no wall-clock heartbeat task (QuietLocalNode declines
    LocalNode's registration of it): the heartbeats are the acquisition clock's alone."""
    net = canopen.Network()  # never connected: nothing to send on, only the calls counted
    periodic: list[tuple] = []
    net.send_periodic = lambda *a, **kw: periodic.append(a)  # type: ignore[method-assign]
    cell.attach(net)
    try:
        cell.boot(0.0)
        seen = [cell.local.nmt.state]
        for cmd in (NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_START):
            cell.nmt(cmd, 0)
            seen.append(cell.local.nmt.state)
        assert seen == ["PRE-OPERATIONAL", "OPERATIONAL", "STOPPED", "PRE-OPERATIONAL",
                        "OPERATIONAL"]
        cell.local.sdo.download(0x1017, 0, struct.pack("<H", 20))
        assert periodic == [] and cell.heartbeat_period_s == 0.02
        assert cell.local.sdo.upload(0x1017, 0) == struct.pack("<H", 20)
    finally:
        cell.detach()
