"""One SYNC cycle of the simulated aircraft, and its schedule: the SYNC counter, the heartbeats
due as time moves, the physics sample drawn for each SYNC, and the answer to the next SYNC
built ahead of it in real time (so the SYNC's answer costs no computation; the module docstring of
sim_bus.bus_sim).

Every SYNC does the same steps in the same order (:meth:`SyncCycle.answer`): heartbeats due,
the fault timeline at this sample, the physics sample into the nodes (the process image, then
the node-level faults), EMCY on status changes, TPDOs in COB-ID order (bus arbitration), the
bus-level faults, the truth bookkeeping. :meth:`SyncCycle.prepare_next` runs the part of that
sequence that does not depend on the SYNC's own time ahead of it and keeps the result in a
:class:`Plan`; the SYNC then only sends it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rsra.sim_bus.clocks import Clock, SampleSource
    from rsra.sim_bus.endpoint import BusEndpoint
    from rsra.sim_bus.fault_apply import FaultApplier
    from rsra.sim_bus.nodes import SimNode
    from rsra.sim_bus.nodeset import NodeSet
    from rsra.sim_bus.simtruth import SimTruth


@dataclass
class Plan:
    """The answer to the next SYNC, built ahead of it (real time): the node state is already
    advanced (``snap`` undoes that), the frames are built; the SYNC only sends them."""

    sample: Any
    k: int
    st: float
    counter: int | None
    n_sync: int
    snap: list[tuple[SimNode, tuple]]
    carried: list[tuple[SimNode, list]]
    # in order: ("rec", args, kwargs) a fault-log entry, ("send", message) a frame
    actions: list[tuple]


class SyncCycle:
    """The SYNC cycles of one simulator: its ``nodes`` fed from ``physics`` (one sample per
    SYNC), the faults applied by ``applier``, the frames sent through ``endpoint`` (stamped by
    ``clock``), the truth kept in ``truth``. ``sync_cob`` and ``counter_overflow`` are the
    rig's SYNC; ``dt`` the sample period. The caller holds the simulator's lock."""

    def __init__(self, *, nodes: NodeSet, applier: FaultApplier, endpoint: BusEndpoint,
                 truth: SimTruth, physics: SampleSource, clock: Clock, dt: float,
                 sync_cob: int, counter_overflow: int, autostart: bool):
        self.nodes, self.applier, self.endpoint = nodes, applier, endpoint
        self.truth, self.physics, self.clock = truth, physics, clock
        self.dt, self.sync_cob, self.autostart = dt, sync_cob, autostart
        self._counter_overflow = counter_overflow
        #: SYNC cycles produced as our own master (autostart), lost ones too
        self.n_sync = 0
        self._counter = 0  # the last SYNC counter produced
        self._last_counter: int | None = None  # the counter of the last SYNC answered
        #: real time: the physics block that the next SYNC would compute (~1 ms for 100
        #: samples) is computed half a period after the current SYNC instead (prefetch), off
        #: the SYNC → TPDO path
        self.ahead: Any = None
        #: physics samples computed ahead (real time)
        self.prefetched = 0
        #: real time: the whole answer to the next SYNC, built half a period ahead
        self.plan: Plan | None = None
        #: SYNC answers built ahead and sent as built
        self.prepared = 0
        #: built ahead but undone (NMT/SDO in between, another counter)
        self.plans_discarded = 0

    # ------------------------------------------------------------------------------------------
    # the schedule
    def next_counter(self) -> int | None:
        """The counter of the next SYNC we produce (CiA 301: 1…overflow; None: no counter)."""
        if self._counter_overflow == 0:
            return None
        self._counter = self._counter % self._counter_overflow + 1
        return self._counter

    def advance(self, t: float) -> None:
        """Time passes to ``t``: due heartbeats go out, each stamped with its due time."""
        self.clock.advance_to(t)
        for d, n, f in self.nodes.heartbeats(t):
            self.endpoint.send_frame(f, d, n)
        self.endpoint.flush_if_due(t)

    def _next_sample(self) -> Any:
        s, self.ahead = self.ahead, None
        if s is None:
            s = self.physics.next_sample()
        self.truth.take(s)
        return s

    def _where(self, sample: Any) -> tuple[int, float]:
        """(index, sample time) of a sample."""
        k = int(getattr(sample, "index", len(self.truth.sync_info)))
        return k, float(getattr(sample, "t", k * self.dt))

    def _sync_payload(self, counter: int | None) -> bytes:
        return bytes([counter]) if counter is not None else b""

    # ------------------------------------------------------------------------------------------
    # one SYNC, answered at its time
    def answer(self, counter: int | None, t: float, send_sync: bool, jitter: float = 0.0,
               received_sync: int | None = None) -> None:
        """Everything one SYNC does (module docstring); ``send_sync``: we are the master and
        send it (perhaps lost, with ``jitter`` in ``t``); ``received_sync``: the length of the
        master's SYNC frame, which occupied the bus."""
        plan, self.plan = self.plan, None
        if plan is not None:  # real time: the answer was built ahead of this SYNC
            if plan.counter == counter and plan.n_sync == self.n_sync and self.ahead is plan.sample:
                self._commit(plan, counter, t, send_sync, jitter)
                return
            self._undo(plan)  # not the SYNC it was built for: build it now, as below
        self._last_counter = counter
        self.advance(t)
        ep = self.endpoint
        if received_sync is not None:  # the master's SYNC occupied the bus
            self.clock.occupy(t, ep.frame_time(received_sync))
        sample = self._next_sample()
        k, st = self._where(sample)
        ap = self.applier
        fi = ap.faults
        lost = False
        if send_sync:
            _, lost = ap.sync_plan(self.n_sync, self.dt)
            self.n_sync += 1
            if jitter:
                fi.record(k, st, "jitter", None, offset_s=jitter)
            if lost:
                fi.record(k, st, "lostsync", None, counter=counter)
            else:
                ep.transmit("sync", self.sync_cob, self._sync_payload(counter), t)
        self.truth.sync_info.append((k, -1 if counter is None else counter, t, lost))
        started: list = []
        if fi:
            started, pre = ap.timeline(k, st, t)
            for node, fr in pre:
                ep.send_frame(fr, t, node)
        # process image: the sample encoded as the bus carries it, then the node-level
        # faults on top
        raw = self.nodes.process_image(sample)
        emcy: list[tuple[SimNode, Any]] = []
        for feed in self.nodes.feeds:
            node = feed.node
            node.set_raws(feed.raws(raw))
            if fi:
                ap.node_faults(feed, started)
            emcy.extend((node, fr) for fr in ap.status_emcy(feed))
        if lost:
            fi.end_sample(st)
            return
        frames = sorted(emcy + self.nodes.sync(counter), key=lambda p: p[1].cob_id)
        sends = []
        for a in ap.on_frames(frames, k, st):
            if a[0] == "rec":
                fi.record(*a[1], **a[2])
            else:
                sends.append((a[2], a[3], a[4]))
        ep.transmit_many(sends, t)  # the whole answer in one send where the bus allows
        if fi:
            fi.end_sample(st)

    # ------------------------------------------------------------------------------------------
    # the next SYNC's answer built ahead of it (a real-time driver asks, between two SYNCs)
    def prefetch(self) -> None:
        """Compute the next physics sample now when the physics computes a whole block at it
        (AircraftPhysics: every ``block_size`` samples) and it is not computed yet: off the
        next SYNC's path to its TPDOs."""
        bs = getattr(self.physics, "block_size", None)
        k = getattr(self.physics, "index", None)
        if bool(bs) and k is not None and self.ahead is None and k % bs == 0:
            self.ahead = self.physics.next_sample()
            self.prefetched += 1

    def prepare_next(self) -> None:
        """Build the answer to the next SYNC now: the steps of :meth:`answer` in the same
        order — process image, node faults, TPDOs due, the bus-level draws (pure functions of
        seed, sample and slot) — with the fault-log entries and the frames kept in order for
        the SYNC to emit and send. Not built ahead (left to the SYNC): a sample where a fault
        window opens or closes, a node reboots, an EMCY goes out or the SYNC is lost; anything
        that then changes a node (NMT, SDO) undoes the plan first (:meth:`discard_plan`)."""
        if self.plan is not None or not self.nodes.feeds:
            return
        ovf = self._counter_overflow
        if self.autostart:
            counter = self._counter % ovf + 1 if ovf else None
            if self.applier.sync_plan(self.n_sync, self.dt)[1]:
                return  # this SYNC is lost
        elif not self.truth.sync_info:
            return  # follow mode: the master's counter is predicted from its last SYNC
        else:
            last = self._last_counter
            counter = None if last is None or not ovf else last % ovf + 1
        if self.ahead is None:
            self.ahead = self.physics.next_sample()
        sample = self.ahead
        k, st = self._where(sample)
        ap = self.applier
        if ap and ap.changes_at(st):
            return
        plan = Plan(sample, k, st, counter, self.n_sync, self.nodes.snapshot(), [], [])
        raw = self.nodes.process_image(sample)
        for feed in self.nodes.feeds:
            feed.node.set_raws(feed.raws(raw))
            if ap:
                ap.node_faults(feed, [])
            if ap.status_emcy(feed):  # a status bit changes: left to the SYNC
                for node, snap in plan.snap:
                    node.restore(snap)
                return
        frames = self.nodes.sync(counter, plan.carried)
        build = self.endpoint.build
        plan.actions = [a if a[0] == "rec" else ("send", build(a[2], a[3], a[4]))
                        for a in ap.on_frames(frames, k, st)]
        self.plan = plan

    def _undo(self, plan: Plan) -> None:
        """The nodes back to before ``plan`` was built (its sample stays the next one)."""
        for node, snap in plan.snap:
            node.restore(snap)
        self.plans_discarded += 1

    def discard_plan(self) -> None:
        """Something outside a SYNC cycle is about to change a node: undo the plan first."""
        plan, self.plan = self.plan, None
        if plan is not None:
            self._undo(plan)

    def _commit(self, plan: Plan, counter: int | None, t: float, send_sync: bool,
                jitter: float) -> None:
        """The SYNC a plan was built for: what :meth:`answer` does at the SYNC, in its order,
        with the frames sent as built."""
        self._last_counter = counter
        self.advance(t)
        self._next_sample()  # plan.sample: the truth bookkeeping
        k, st, fi = plan.k, plan.st, self.applier.faults
        if send_sync:  # not lost: prepare_next does not build a lost SYNC's answer
            self.n_sync += 1
            if jitter:
                fi.record(k, st, "jitter", None, offset_s=jitter)
            self.endpoint.transmit("sync", self.sync_cob, self._sync_payload(counter), t)
        self.truth.sync_info.append((k, -1 if counter is None else counter, t, False))
        for node, carried in plan.carried:
            node.carry(carried)
        sends = []
        for a in plan.actions:
            if a[0] == "send":
                sends.append(a[1])
            else:
                fi.record(*a[1], **a[2])
        if sends:  # the whole answer in one send where the bus allows (one wake-up)
            self.endpoint.send_built_many(sends)
        self.prepared += 1
        if fi:
            fi.end_sample(st)
