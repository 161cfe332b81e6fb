"""The simulator's pieces, each alone (sim_bus.nodeset, endpoint, fault_apply): what the
Simulator assembles works without it."""
import threading
import uuid

from rsra.sim_bus.clocks import SimulatedTime
from rsra.sim_bus.endpoint import BusEndpoint
from rsra.sim_bus.fault_apply import FaultApplier
from rsra.sim_bus.faults import FaultInjector, parse_faults
from rsra.sim_bus.nodes import NMT_START
from rsra.sim_bus.nodeset import NodeSet


def _nodes(cfg):
    clock = SimulatedTime()
    return NodeSet(cfg, None, clock.now, threading.RLock())


def test_node_set_frames_come_in_bus_order(cfg):
    ns = _nodes(cfg)
    assert [n.name for n in ns] == [n.name for n in cfg.nodes]
    boot = ns.boot(0.0)
    assert len(boot) == len(ns.nodes)
    assert [f.cob_id for f in boot] == sorted(f.cob_id for f in boot)
    for n in ns:
        n.nmt(NMT_START, n.node_id, 0.0)
    tpdos = ns.sync(1)
    assert tpdos and [f.cob_id for _, f in tpdos] == sorted(f.cob_id for _, f in tpdos)
    assert ns.unknown_cob not in ns.known_cob_ids(cfg.sync.cob_id)


def test_fault_applier_drops_a_nodes_tpdos_and_logs_them(cfg):
    ns = _nodes(cfg)
    ns.boot(0.0)
    for n in ns:
        n.nmt(NMT_START, n.node_id, 0.0)
    frames = ns.sync(1)
    clean = FaultApplier(FaultInjector(()), ns, ns.unknown_cob).on_frames(frames, 0, 0.0)
    assert [a[2] for a in clean] == [f.cob_id for _, f in frames]  # all sent, in order
    victim = frames[0][0].name
    ap = FaultApplier(FaultInjector(parse_faults(f"drop:{victim}:1.0"), seed=1), ns,
                      ns.unknown_cob)
    acts = ap.on_frames(frames, 0, 0.0)
    dropped = [a for a in acts if a[0] == "rec"]
    assert dropped and all(a[1][2] == "drop" and a[1][3] == victim for a in dropped)
    sent = [a[1] for a in acts if a[0] == "send"]
    assert victim not in [n.name for n in sent]
    assert len(sent) + len(dropped) == len(frames)


def test_endpoint_serialises_frames_at_the_bit_rate(cfg):
    clock = SimulatedTime(1.0)
    ep = BusEndpoint(clock, threading.RLock(), 1_000_000, channel=f"pieces-{uuid.uuid4()}")
    try:
        a = ep.transmit("x", 0x181, bytes(8), None)
        b = ep.transmit("x", 0x182, bytes(2), None)
        assert a.timestamp == 1.0
        assert abs(b.timestamp - (1.0 + ep.frame_time(8))) < 1e-6  # waits for the first
        assert ep.frames_sent == 2
        assert ep.captured(ep.transmit, "x", 0x183, b"", None)[0].arbitration_id == 0x183
    finally:
        ep.close()
