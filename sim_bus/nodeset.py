"""The simulator's set of CANopen nodes: which configured nodes are on the bus, what each is
fed from a physics sample (the process image, through the codec shared with the off-line API),
and the frames the whole set sends for one NMT command, SYNC or moment in time, in bus order.

It sends nothing itself: the frames go back to :class:`sim_bus.bus_sim.Simulator`, which
applies the faults and hands them to its :class:`sim_bus.endpoint.BusEndpoint`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from canopen.objectdictionary import datatypes as od_types

from rsra.config.devices import device_profile
from rsra.sim_bus.nodes import (
    COB_EMCY_BASE,
    COB_HEARTBEAT,
    COB_NMT,
    COB_SDO_RX,
    COB_SDO_TX,
    NMT_START,
    Frame,
    SimNode,
)
from rsra.sim_bus.offline import ChannelCodec

if TYPE_CHECKING:
    import threading

    from rsra.config.rig import RigConfig

DEFAULT_BITRATE = 1_000_000  # docs/bus.md: 1 Mbit/s on the aircraft, when no EDS says otherwise
COB_TIME, COB_LSS_MASTER, COB_LSS_SLAVE = 0x100, 0x7E5, 0x7E4
_ENCODED = ("force", "status", "accel_counts", "omega", "azimuth_counts", "balance", "drive")


def codec_type(role: str, channel: str) -> int:
    """The CANopen data type a channel is encoded to (the device profile's, config.devices:
    what sim_bus.offline.ChannelCodec encodes a fed channel to); the EDS must agree."""
    code: int = getattr(od_types, device_profile(role).channel(channel).data_type)
    return code


@dataclass
class NodeFeed:
    """What one node is fed from each sample."""

    node: SimNode
    raws: Callable[[dict[str, Any]], Any]  # encoded sample (lists) -> raw values, the profile's channel order
    full_scale: float | None  # load cell: the force an over-range reads (config)


def _by_cob(pairs: list[tuple[SimNode, Frame]]) -> list[tuple[SimNode, Frame]]:
    """Bus arbitration: lowest identifier first (stable among equal identifiers)."""
    return sorted(pairs, key=lambda p: p[1].cob_id)


class NodeSet:
    """The nodes of ``cfg`` on the bus: required ones always, optional ones when their role is
    in ``nodes_present`` (None: all of them). Each node's object dictionary comes from its EDS;
    ``clock`` and ``lock`` are the simulator's."""

    def __init__(self, cfg: RigConfig, nodes_present: tuple[str, ...] | None,
                 clock: Callable[[], float], lock: threading.RLock):
        #: the nodes in the config's order
        self.nodes: list[SimNode] = [
            SimNode(n.name, n.role, n.node_id, n.eds, clock=clock, lock=lock)
            for n in cfg.nodes if n.required or nodes_present is None or n.role in nodes_present]
        #: the nodes by name
        self.by_name = {n.name: n for n in self.nodes}
        #: the names, in order (what the fault plan is asked about)
        self.names = [n.name for n in self.nodes]
        #: the sample → bus values codec shared with the off-line API
        self.codec = ChannelCodec(cfg)
        #: per fed node, how a sample feeds it (bus order)
        self.feeds = self._build_feeds(cfg)
        rates = [max(n.od.device_information.allowed_baudrates or {0}) for n in self.nodes]
        #: bit/s: the EDS's (the highest a node allows), else the aircraft's default
        self.bitrate = max(rates) if rates and max(rates) > 0 else DEFAULT_BITRATE
        self._configured_ids = {n.node_id for n in cfg.nodes}
        #: a TPDO1 COB-ID of a node id nobody configured (the ``unknown`` fault's default)
        self.unknown_cob = self._pick_unknown_cob()

    def __iter__(self):
        return iter(self.nodes)

    def _build_feeds(self, cfg: RigConfig) -> list[NodeFeed]:
        feeds: dict[str, NodeFeed] = {}

        def add(name: str, fn: Callable[[dict[str, Any]], Any], fs: float | None = None) -> None:
            if name and name in self.by_name:
                feeds[name] = NodeFeed(self.by_name[name], fn, fs)

        # each feed picks its node's values out of the encoded sample (element i, k, q)
        def cell(i: int) -> Callable[[dict[str, Any]], Any]:
            return lambda e: (e["force"][i], e["status"][i])

        def accelerometer(k: int) -> Callable[[dict[str, Any]], Any]:
            return lambda e: e["accel_counts"][k]

        def drive(q: int) -> Callable[[dict[str, Any]], Any]:
            return lambda e: (e["drive"][q],)

        for i, c in enumerate(cfg.cells):
            add(c.node, cell(i), c.full_scale_N)
        for k, a in enumerate(cfg.accelerometers):
            add(a.node, accelerometer(k))
        add(cfg.rotor.node, lambda e: (e["omega"], e["azimuth_counts"]))
        add(cfg.balance.node, lambda e: e["balance"])
        for q, x in enumerate(cfg.external_loads):
            add(x.node, drive(q))
        for f in feeds.values():
            for ch, var in f.node.channels:
                want = codec_type(f.node.role, ch)
                if var.data_type != want:
                    raise ValueError(
                        f"node {f.node.name!r} ({f.node.eds.name}): channel {ch!r} is mapped to "
                        f"0x{var.index:04X}:{var.subindex} of data type 0x{var.data_type:04X}, "
                        f"the bus contract (docs/bus.md §1) says 0x{want:04X}; fix the EDS")
        # bus order: feed in the config's node order
        return [feeds[n.name] for n in self.nodes if n.name in feeds]

    def _pick_unknown_cob(self) -> int:
        """A TPDO1 COB-ID of a node id nobody configured (highest first)."""
        for nid in range(0x7F, 0, -1):
            if nid not in self._configured_ids:
                return 0x180 + nid
        return 0x7FF

    def known_cob_ids(self, sync_cob: int) -> set[int]:
        """Every COB-ID the configured nodes and the master use (CiA 301 pre-defined set)."""
        known = {COB_NMT, sync_cob, COB_TIME, COB_LSS_MASTER, COB_LSS_SLAVE}
        for nid in self._configured_ids:
            for base in (COB_EMCY_BASE, 0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480,
                         0x500, COB_SDO_TX, COB_SDO_RX, COB_HEARTBEAT):
                known.add(base + nid)
        for n in self.nodes:
            known.update(c.cob_id for c in n.tpdo_configs())
            known.add(n.emcy_cob_id)
        return known

    # ------------------------------------------------------------------------------------------
    # the frames of the whole set, in bus order
    def boot(self, t: float) -> list[Frame]:
        """Every node boots: the boot-up frames, lowest COB-ID first."""
        frames: list[Frame] = []
        for n in self.nodes:
            frames.extend(n.boot(t))
        return sorted(frames, key=lambda f: f.cob_id)

    def self_start(self, t: float) -> None:
        """CiA 301 self-starting nodes: each starts itself (no frame)."""
        for n in self.nodes:
            n.nmt(NMT_START, n.node_id, t)

    def nmt(self, command: int, target: int, t: float) -> list[tuple[SimNode, Frame]]:
        """An NMT command from the master: each node's answer, in bus order."""
        frames: list[tuple[SimNode, Frame]] = []
        for n in self.nodes:
            frames.extend((n, f) for f in n.nmt(command, target, t))
        return _by_cob(frames)

    def heartbeats(self, t: float) -> list[tuple[float, SimNode, Frame]]:
        """The heartbeats due by ``t``: (due time, node, frame), by due time then COB-ID."""
        due: list[tuple[float, int, SimNode, Frame]] = []
        for n in self.nodes:
            due.extend((d, f.cob_id, n, f) for d, f in n.heartbeats(t))
        return [(d, n, f) for d, _, n, f in sorted(due, key=lambda x: (x[0], x[1]))]

    def next_heartbeat(self) -> float | None:
        """When the next heartbeat is due (None: no node produces one)."""
        due = [n.next_heartbeat for n in self.nodes if n.next_heartbeat is not None]
        return min(due) if due else None

    def sync(self, counter: int | None,
             carried: list[tuple[SimNode, list]] | None = None) -> list[tuple[SimNode, Frame]]:
        """A SYNC: the TPDOs due, in bus order. ``carried`` (an answer built ahead) collects
        per node the values its TPDOs carried, for :meth:`SimNode.carry` at the SYNC."""
        frames: list[tuple[SimNode, Frame]] = []
        for n in self.nodes:
            if carried is None:
                frames.extend((n, fr) for fr in n.sync(counter))
            else:
                mine: list = []
                frames.extend((n, fr) for fr in n.sync(counter, mine))
                if mine:
                    carried.append((n, mine))
        return _by_cob(frames)

    def process_image(self, sample: Any) -> dict[str, list]:
        """The sample encoded as the bus carries it (the one codec shared with the off-line
        API), as exact python ints/floats per encoded field."""
        enc = self.codec.encode(T=sample.T, cell_status=sample.cell_status, accel=sample.accel,
                                omega=sample.omega, azimuth=sample.azimuth,
                                H_balance=sample.H_balance, drive=sample.drive)
        return {k: getattr(enc, k).tolist() for k in _ENCODED}

    def snapshot(self) -> list[tuple[SimNode, tuple]]:
        return [(n, n.snapshot()) for n in self.nodes]

    def detach(self) -> None:
        for n in self.nodes:
            n.detach()
