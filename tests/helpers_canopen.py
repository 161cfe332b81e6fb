"""Test helpers for the reader: frames built with struct from the EDS mapping, canopen
LocalNode slaves, and lock-step rigs around the bus simulator.

Frames here are built independently of daq.decoder (struct formats written out from the EDS
tables of docs/bus.md §1), so decoder tests can fail.
"""
from __future__ import annotations

import itertools
import os
import struct
import threading
import time
from pathlib import Path

import can
import canopen

from rsra.canbus import EchoFirstVirtualBus
from rsra.sim_bus.nodes import QuietLocalNode

T0 = 1_700_000_000.0  # acquisition time origin of the tests (UNIX-like: BLF needs it)
_chan = itertools.count()

# docs/bus.md §1 "Nodes": TPDO layouts (little-endian, CiA 301)
CELL = struct.Struct("<fB")  # force REAL32 N, status UNSIGNED8
ACCEL = struct.Struct("<hhh")  # x y z INTEGER16, 1 count = 1 mg
ROTOR = struct.Struct("<fH")  # omega REAL32 rad/s, azimuth UNSIGNED16 (0…65535 ↔ 0…2π)
PAIR = struct.Struct("<ff")  # balance TPDO1..3: (X, Y), (Z, L), (M, N)
TORQUE = struct.Struct("<f")


def channel_name(tag: str) -> str:
    return f"test-reader-{tag}-{os.getpid()}-{next(_chan)}"


def msg(cob: int, data: bytes | list[int], t: float, **kw) -> can.Message:
    kw.setdefault("is_extended_id", False)
    return can.Message(arbitration_id=cob, data=bytes(data), timestamp=t, **kw)


def sync(counter: int | None, t: float) -> can.Message:
    return msg(0x80, b"" if counter is None else bytes([counter]), t)


def heartbeat(node_id: int, state: int, t: float) -> can.Message:
    return msg(0x700 + node_id, bytes([state]), t)


def cell(node_id: int, force: float, status: int, t: float) -> can.Message:
    return msg(0x180 + node_id, CELL.pack(force, status), t)


def accel(node_id: int, counts: tuple[int, int, int], t: float) -> can.Message:
    return msg(0x180 + node_id, ACCEL.pack(*counts), t)


def rotor(node_id: int, omega: float, az_counts: int, t: float) -> can.Message:
    return msg(0x180 + node_id, ROTOR.pack(omega, az_counts), t)


def balance(node_id: int, H: tuple[float, ...], t: float) -> list[can.Message]:
    return [msg(base + node_id, PAIR.pack(H[2 * i], H[2 * i + 1]), t)
            for i, base in enumerate((0x180, 0x280, 0x380))]


def period_frames(cfg, k: int, t: float, forces=None, status=None, acc=(0, 0, -1000),
                  omega: float | None = None, az: int = 0, H=None, skip: tuple[str, ...] = (),
                  counter: int | None = None) -> list[can.Message]:
    """SYNC k (counter k % overflow + 1 unless given) and every default-rig TPDO after it."""
    ov = cfg.sync.counter_overflow
    c = counter if counter is not None else (k % ov + 1 if ov else None)
    out = [sync(c, t)]
    forces = forces if forces is not None else [1000.0 * (i + 1) + k for i in range(7)]
    status = status if status is not None else [0] * 7
    dt = 1e-5
    for i, cc in enumerate(cfg.cells):
        if cc.node in skip:
            continue
        out.append(cell(cfg.node(cc.node).node_id, forces[i], status[i], t + dt * (i + 1)))
    for a in cfg.accelerometers:
        if a.node not in skip:
            out.append(accel(cfg.node(a.node).node_id, acc, t + 1e-4))
    if omega is not None and "rotor_speed" not in skip:
        out.append(rotor(cfg.node("rotor_speed").node_id, omega, az, t + 2e-4))
    if H is not None and "balance" not in skip:
        out.extend(balance(cfg.node("balance").node_id, H, t + 3e-4))
    return out


def wait_until(cond, timeout: float = 5.0, what: str = "condition") -> None:
    """Synchronisation with another thread (a poll, not a timing assertion)."""
    end = time.monotonic() + timeout
    ev = threading.Event()
    while not cond():
        if time.monotonic() > end:
            raise TimeoutError(f"timed out waiting for {what}")
        ev.wait(0.0002)


# ------------------------------------------------------------------------------------------
# canopen LocalNode slaves (master tests without the simulator)

class LocalSlaves:
    """The configured nodes as canopen LocalNodes on one canopen Network (their own virtual
    bus instance): LocalNode answers SDO; NMT is done here (LocalNode stays INITIALISING
    after a reset: docs/bus.md §6 "Library pitfalls"): reset → boot-up frame + pre-operational, start →
    operational. ``absent`` nodes are not created; ``overrides`` {(node, index, sub): bytes}
    replace object values (a wrong identity or mapping)."""

    def __init__(self, cfg, channel: str, absent: tuple[str, ...] = (),
                 overrides: dict | None = None):
        self.cfg = cfg
        self.net = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.05  # quick close
        self.net.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.nodes: dict[str, canopen.LocalNode] = {}
        self.state: dict[str, int] = {}
        self.nmt_log: list[tuple[str, int]] = []
        for nc in cfg.nodes:
            if nc.name in absent:
                continue
            # NMT and heartbeat are ours: LocalNode would start a wall-clock heartbeat on 0x1017
            node = QuietLocalNode(nc.node_id, canopen.import_od(str(nc.eds), nc.node_id))
            self.net.add_node(node)
            self.net.unsubscribe(0, node.nmt.on_command)
            self.nodes[nc.name] = node
            self.state[nc.name] = 0
        for (name, index, sub), data in (overrides or {}).items():
            self.nodes[name].set_data(index, sub, data, check_writable=False)
        self.net.subscribe(0, self._on_nmt)

    def _on_nmt(self, can_id, data, timestamp) -> None:
        cmd, target = data[0], data[1]
        for name, node in self.nodes.items():
            if target not in (0, node.id):
                continue
            self.nmt_log.append((name, cmd))
            if cmd in (0x81, 0x82):
                self.state[name] = 0x7F
                self.net.send_message(0x700 + node.id, b"\x00")  # boot-up
            elif cmd == 0x01:
                self.state[name] = 0x05

    def heartbeat_ms(self, name: str) -> int:
        return struct.unpack("<H", self.nodes[name].get_data(0x1017, 0))[0]

    def close(self) -> None:
        self.net.disconnect()


# ------------------------------------------------------------------------------------------
# lock-step rigs around the simulator

def make_sim(cfg, channel: str, *, seed: int = 3, scenario: str = "ground-test",
             driver: type | None = None, **kw):
    """The simulator in simulated time from T0: ``driver`` sim_bus.drivers.LockstepSim
    (default: no thread) or FollowSim (a Notifier thread serves NMT/SDO/SYNC)."""
    from rsra.sim_bus.drivers import LockstepSim
    from rsra.sim_bus.physics import AircraftPhysics
    from rsra.sim_bus.scenarios import load_scenario

    return (driver or LockstepSim)(
        cfg, physics=AircraftPhysics(cfg, load_scenario(scenario), seed=seed), seed=seed,
        channel=channel, t0=T0, **kw)


class LockstepRig:
    """Simulator as its own master (autostart, lock-step) + a listening Reader on the same
    virtual bus without a bus thread: ``step(n)`` moves simulated time n samples and returns
    the reader's items. Deterministic: no thread, no wall clock."""

    def __init__(self, cfg, *, faults: str = "", seed: int = 3, record: Path | None = None,
                 record_format: str | None = None, scenario: str = "ground-test", **reader_kw):
        from rsra.daq.bus.reader import DropQueue, LockstepReader

        self.cfg = cfg
        ch = channel_name("lockstep")
        self.sim = make_sim(cfg, ch, seed=seed, faults=faults, autostart=True,
                            scenario=scenario)
        self.bus = can.Bus(interface="virtual", channel=ch, receive_own_messages=True,
                           preserve_timestamps=True)
        reader_kw.setdefault("items", DropQueue())
        self.reader = LockstepReader(cfg, self.bus, record=record, record_format=record_format,
                                     **reader_kw)
        self.reader.start()
        self.sim.start()
        self.items: list = []

    def step(self, n: int = 1) -> list:
        out = []
        for _ in range(n):
            self.sim.step()
            self.reader.pump()
            out.extend(self.reader.poll())
        self.items.extend(out)
        return out

    def close(self) -> None:
        self.sim.close()
        self.reader.close()
        self.bus.shutdown()


class MasterRig:
    """Simulator in follow mode (FollowSim: its Notifier thread serves SDO) + the Reader as
    CANopen master; the sample clock is the test's: ``sync(n)`` sends SYNCs stamped in
    simulated time, one at a time, and holds simulated time while the master reconfigures a
    node (lock-step)."""

    def __init__(self, cfg, *, faults: str = "", seed: int = 3, sim_cfg=None,
                 record: Path | None = None, nodes_present=None, **reader_kw):
        from rsra.daq.bus.reader import BootNodesSyncOnDemand, FrameClock, Reader

        ch = channel_name("master")
        self.cfg = cfg
        from rsra.sim_bus.drivers import FollowSim

        self.sim = make_sim(sim_cfg or cfg, ch, seed=seed, faults=faults, driver=FollowSim,
                            nodes_present=nodes_present)
        # the master's bus: its own SYNC back before any answer (rsra.canbus)
        self.bus = EchoFirstVirtualBus(channel=ch, receive_own_messages=True,
                                       preserve_timestamps=True)
        self.nodes = BootNodesSyncOnDemand()  # the test's sample clock: sync(n)
        self.reader = Reader(cfg, self.bus, nodes=self.nodes, clock=FrameClock(), record=record,
                             **reader_kw)
        self.sim.start()
        self.k = 0
        self.t_start = T0 + 0.01
        self.items: list = []

    def start(self) -> MasterRig:
        self.reader.start()
        self.settle()
        return self

    def settle(self) -> None:
        """Every frame on the bus processed by the reader, and the master idle."""
        sim, r = self.sim, self.reader
        wait_until(lambda: r.tap.frames >= sim.frames_sent + sim.frames_received
                   and r.nodes.idle(), what="the reader to catch up with the simulator")

    def sync(self, n: int = 1) -> list:
        out = []
        for _ in range(n):
            t = self.t_start + self.k * self.cfg.sample_period_s
            seen = len(self.sim.sync_info)
            self.nodes.send_sync(t)
            wait_until(lambda seen=seen: len(self.sim.sync_info) > seen,
                       what="the simulator's answer")
            self.sim.advance(t)  # barrier: the simulator's cycle is complete
            self.settle()
            self.k += 1
            out.extend(self.reader.poll())
        self.items.extend(out)
        return out

    def close(self) -> None:
        self.reader.close()
        self.sim.close()
        self.bus.shutdown()
