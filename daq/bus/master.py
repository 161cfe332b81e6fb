"""The CANopen master: boot, verification, supervision (docs/bus.md §3 "Boot and supervision").

Two parts:

* :class:`Supervisor` — passive, runs on the bus thread in frame order and is driven by the
  acquisition clock only: heartbeat consumer with its own watchdog (canopen has none),
  NMT state per node, boot-up detection, EMCY decoding tolerant of short frames with a
  bounded history (canopen's drops them and keeps an unbounded log). Replay runs it too, so
  node health replays exactly.
* :class:`CanopenMaster` — active: NMT reset-communication, wait for boot-up or
  heartbeat, SDO verification of 0x1000 / 0x1018 / TPDO parameters against the EDS, 0x1017,
  NMT start, the SYNC producer (python-can ``send_periodic``), and a worker thread that
  reconfigures and restarts a node that rebooted or appeared late — SDO must never run on
  the bus thread, which delivers the SDO responses. In lock-step (the simulator boots its
  nodes and produces SYNC) only the restart part runs (:meth:`CanopenMaster.supervise`), in
  the same worker thread; the lock-step driver (sim_bus.drivers) holds simulated time and
  serves its transmissions while it works.
"""
from __future__ import annotations

import logging
import queue
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can
import canopen

from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import COB_MASK_11BIT, DecodeTable, NodeLayout
from rsra.daq.bus.health import OMIT, Emcy, NodeHealth, frozen_map
from rsra.daq.bus.nodecheck import fmt_value, verify_node

log = logging.getLogger(__name__)

# CiA 301 function codes and NMT.
COB_NMT = 0x000
COB_EMCY = 0x080
COB_SDO_TX = 0x580
COB_SDO_RX = 0x600
COB_HEARTBEAT = 0x700
NMT_START = 0x01
NMT_RESET_COMMUNICATION = 0x82
HB_BOOTUP, HB_STOPPED, HB_OPERATIONAL, HB_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
NMT_STATE_NAMES = {HB_BOOTUP: "booting", HB_STOPPED: "stopped", HB_OPERATIONAL: "operational",
                   HB_PRE_OPERATIONAL: "pre-operational"}
EMCY_FRAME = struct.Struct("<HB5s")
EMCY_HISTORY = 16  # per node (bounded)
EVENT_QUEUE = 64  # reconfiguration requests (bounded)



class BootError(RuntimeError):
    """The start cannot go on: names the node, the object and both values."""

    def __init__(self, node: str, obj: str, expected: Any = None, actual: Any = None,
                 problem: str = ""):
        self.node, self.obj, self.expected, self.actual = node, obj, expected, actual
        if not problem:
            problem = f"reads {fmt_value(actual)}, the EDS says {fmt_value(expected)}"
        super().__init__(f"node {node}: {obj} {problem}")



@dataclass
class NodeStatus:
    """What the supervisor knows of one node (all times on the acquisition clock)."""

    name: str
    node_id: int
    required: bool
    # missing, booting, pre-operational, operational, stopped, lost, error
    state: str = "missing"
    last_heartbeat: float | None = None
    operational: bool = False  # by its last heartbeat, and not lost since
    boots: int = 0
    losses: int = 0
    emcy_count: int = 0
    emcy: deque = field(default_factory=lambda: deque(maxlen=EMCY_HISTORY))
    identity: dict[str, int] | None = None
    error: str | None = None
    heard: threading.Event = field(default_factory=threading.Event, repr=False)


class Supervisor:
    """Heartbeat consumer + watchdog, boot-up detection, EMCY history (bus thread).

    ``on_event(kind, node)`` is called (bus thread, must not block) with kind "bootup",
    "heartbeat" (a non-operational node: needs starting), "lost" or "alive".
    ``set_alive(node, alive)`` tells the assembler which optional nodes to wait for.
    """

    def __init__(self, cfg: RigConfig, table: DecodeTable,
                 set_alive: Callable[[str, bool], None] | None = None,
                 on_event: Callable[[str, str], None] | None = None,
                 wake: Callable[[float], None] | None = None):
        self.cfg = cfg
        self.timeout_s = cfg.heartbeat.timeout_factor * cfg.heartbeat.producer_ms / 1000.0
        self.nodes: dict[str, NodeStatus] = {
            nl.name: NodeStatus(nl.name, nl.node_id, nl.required) for nl in table.nodes}
        self._by_hb = {COB_HEARTBEAT + nl.node_id: self.nodes[nl.name] for nl in table.nodes}
        self._by_emcy = {COB_EMCY + nl.node_id: self.nodes[nl.name] for nl in table.nodes}
        self.set_alive = set_alive or (lambda node, alive: None)
        self.on_event = on_event or (lambda kind, node: None)
        self.wake = wake or (lambda t: None)  # the clock must call check() by this time
        self.malformed = 0
        self.next_deadline = float("inf")

    def callbacks(self) -> dict[int, Callable]:
        cbs: dict[int, Callable] = {cob: self.on_heartbeat for cob in self._by_hb}
        cbs.update({cob: self.on_emcy for cob in self._by_emcy})
        return cbs

    def on_heartbeat(self, can_id: int, data: Any, timestamp: float) -> None:
        ns = self._by_hb[can_id]
        if len(data) != 1:
            self.malformed += 1
            return
        code = data[0] & 0x7F  # bit 7 is the node-guarding toggle
        ns.last_heartbeat = timestamp
        was = ns.state
        if code == HB_BOOTUP:
            ns.boots += 1
            ns.state = "booting"
            ns.error = None  # a new boot: the master verifies it afresh
        elif ns.error:
            ns.state = "error"  # failed verification: stays visible until the next boot-up
        else:
            ns.state = NMT_STATE_NAMES.get(code, f"0x{code:02X}")
        ns.heard.set()
        deadline = timestamp + self.timeout_s
        if deadline < self.next_deadline:
            self.next_deadline = deadline
            self.wake(deadline)
        alive = code == HB_OPERATIONAL
        if alive != ns.operational:
            ns.operational = alive
            self.set_alive(ns.name, alive)
        if code == HB_BOOTUP:
            self.on_event("bootup", ns.name)
        elif not alive:
            self.on_event("heartbeat", ns.name)
        elif was in ("missing", "lost"):
            self.on_event("alive", ns.name)

    def on_emcy(self, can_id: int, data: Any, timestamp: float) -> None:
        ns = self._by_emcy[can_id]
        # CiA 301 EMCY is 8 bytes; tolerate short frames (pad) rather than drop them
        code, register, info = EMCY_FRAME.unpack(bytes(data[:8]).ljust(8, b"\x00"))
        ns.emcy_count += 1
        ns.emcy.append(Emcy(t=timestamp, code=code, register=register, info=info.hex(),
                            length=len(data)))

    def check(self, now: float) -> None:
        """Heartbeat watchdog at acquisition time ``now`` (called when the clock passes
        ``next_deadline``): a node silent for timeout_factor × period is lost."""
        nxt = float("inf")
        for ns in self.nodes.values():
            if ns.last_heartbeat is None or ns.state in ("lost", "missing"):
                continue
            deadline = ns.last_heartbeat + self.timeout_s
            if now > deadline:
                ns.state = "lost"
                ns.losses += 1
                if ns.operational:
                    ns.operational = False
                    self.set_alive(ns.name, False)
                self.on_event("lost", ns.name)
            elif deadline < nxt:
                nxt = deadline
        self.next_deadline = nxt

    def rebase(self, now: float) -> None:
        """Time went back to ``now`` (a discontinuity): every node heard is taken as heard
        then, so its watchdog runs from there (no loss invented, none missed for ever)."""
        for ns in self.nodes.values():
            if ns.last_heartbeat is not None and ns.last_heartbeat > now:
                ns.last_heartbeat = now
        self.next_deadline = min((ns.last_heartbeat + self.timeout_s
                                  for ns in self.nodes.values()
                                  if ns.last_heartbeat is not None
                                  and ns.state not in ("lost", "missing")), default=float("inf"))

    def snapshot(self, now: float) -> Mapping[str, NodeHealth]:
        """Every node's part of the health record (read-only)."""
        out = {}
        for ns in self.nodes.values():
            age = None if ns.last_heartbeat is None else round(max(0.0, now - ns.last_heartbeat), 6)
            out[ns.name] = NodeHealth(
                state=ns.state, heartbeat_age=age, emcy=tuple(ns.emcy), required=ns.required,
                boots=ns.boots, losses=ns.losses, emcy_count=ns.emcy_count,
                identity=OMIT if ns.identity is None else frozen_map(ns.identity),
                error=ns.error or OMIT)
        return frozen_map(out)


# python-can bus classes whose own send_periodic sends a sequence of messages in turn
PERIODIC_SEQUENCE_BUSES = frozenset({"SocketcanBus"})


SYNC_RETRY_MIN_S = 0.01  # the SYNC producer's pause after a failed send ...
SYNC_RETRY_MAX_S = 1.0  # ... doubling up to this while the sends keep failing


class SyncProducer:
    """Periodic SYNC from a thread, for interfaces without periodic sending of their own.

    python-can's thread-based fallback catches up a late SYNC by sending the missed ones back
    to back: two SYNCs with no time between them for the nodes to answer, i.e. a sample with
    no TPDO at all (docs/bus.md §2: samples are assembled by frame order). Here a late SYNC goes out
    at once and the next one keeps at least half a period from it; the counter still counts
    every SYNC sent (CiA 301), so no sample is lost — but the sample slots skipped are never
    taken: ``periods_not_taken`` counts them (health ``sync.periods_not_taken``)."""

    def __init__(self, bus: can.BusABC, msgs: list[can.Message], period: float,
                 lock: threading.Lock, *, clock: Callable[[], float] = time.perf_counter,
                 start: bool = True):
        self.bus, self.msgs, self.period, self.lock = bus, msgs, period, lock
        self.clock = clock
        self.late = 0  # SYNCs sent later than planned (re-phased, not caught up)
        self.sent = 0
        self.failed = 0  # sends that failed (the bus gone): retried after a growing pause
        self.last_error: str | None = None
        # the schedule's total shift from re-phasing, and the whole periods it cost: the
        # sample slots never taken (health sync.periods_not_taken)
        self.shift_s = 0.0
        self.periods_not_taken = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rsra-sync", daemon=True)
        if start:
            self._thread.start()

    def _wait(self, s: float) -> bool:
        return self._stop.wait(s)

    def _run(self) -> None:
        k, period = 0, self.period
        due = self.clock()
        pause = 0.0
        while not self._stop.is_set():
            try:
                with self.lock:
                    self.bus.send(self.msgs[k])
            except Exception as e:  # the bus went away (or is failing): retried, supervised
                self.failed += 1
                text = f"{type(e).__name__}: {e}"
                if text != self.last_error:
                    log.error("SYNC not sent (%s); retrying with a growing pause", text)
                    self.last_error = text
                pause = min(SYNC_RETRY_MAX_S, max(SYNC_RETRY_MIN_S, 2 * pause))
                if self._wait(pause):
                    return
                due = self.clock()  # the schedule starts afresh when the bus is back
                continue
            if pause:
                pause = 0.0
                self.last_error = None
                log.warning("SYNC sent again after %d failed sends", self.failed)
            self.sent += 1
            k = (k + 1) % len(self.msgs)
            now = self.clock()
            due += period
            if due < now + 0.5 * period:
                # more than half a period late: re-phase (no catching up); every later slot
                # moves by the same amount, so the shift adds up to the periods not taken
                self.late += 1
                self.shift_s += now + 0.5 * period - due
                self.periods_not_taken = int(self.shift_s / period + 1e-9)
                due = now + 0.5 * period
            self._wait(due - now)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


class CanopenMaster:
    """Boot, verify, start and keep the nodes running (live only; needs a connected network).

    ``clock()`` returns the acquisition time (for the reconfiguration guard).
    """

    def __init__(self, cfg: RigConfig, table: DecodeTable, network: canopen.Network,
                 supervisor: Supervisor, clock: Callable[[], float]):
        self.cfg, self.table, self.network, self.supervisor = cfg, table, network, supervisor
        self.clock = clock
        # a worker thread restarts nodes (SDO must not run on the thread that delivers the
        # answers: the bus thread live, the lock-step driver's otherwise)
        self._sync_counter = 0
        self.remote: dict[str, canopen.RemoteNode] = {}
        for nl in table.nodes:
            node = canopen.RemoteNode(nl.node_id, nl.od)
            network.add_node(node)
            # canopen's EMCY consumer drops short frames and logs without bound: ours does it
            network.unsubscribe(COB_EMCY + nl.node_id, node.emcy.on_emcy)
            self.remote[nl.name] = node
        self._events: queue.Queue[tuple[str, str]] = queue.Queue(EVENT_QUEUE)
        self.events_dropped = 0
        self._pending: set[str] = set()
        self._last_config: dict[str, float] = {}
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self.running = False
        self.sync_task: can.broadcastmanager.CyclicSendTaskABC | SyncProducer | None = None
        self.reconfigured = 0

    # -- boot ------------------------------------------------------------------------------
    def boot(self) -> None:
        """docs/bus.md §3, steps 1–3 (reset, verify, start); SYNC (:meth:`start_sync`) and
        supervision (:meth:`supervise`) are the caller's next steps (daq.bus.reader's node
        policies). Raises BootError naming node/object/values on any mismatch and when a
        required node does not answer; optional absent nodes are reported missing."""
        sup = self.supervisor
        for nl in self.table.nodes:
            sup.nodes[nl.name].heard.clear()
            self.remote[nl.name].nmt.send_command(NMT_RESET_COMMUNICATION)
        # SDO and the boot wait are real-time protocols (canopen's SDO timeouts are too)
        deadline = time.monotonic() + self.cfg.heartbeat.boot_timeout_s
        present = []
        for nl in self.table.nodes:
            ns = sup.nodes[nl.name]
            if ns.heard.wait(max(0.0, deadline - time.monotonic())):
                present.append(nl)
            elif nl.required:
                raise BootError(nl.name, f"(id 0x{nl.node_id:02X})", problem=(
                    f"is required but sent no boot-up or heartbeat within "
                    f"{self.cfg.heartbeat.boot_timeout_s:g} s of the NMT reset; "
                    "check its power, wiring and node id"))
            else:
                ns.state = "missing"
                log.warning("optional node %s (id 0x%02X) is missing: its channels stay off "
                            "until it appears", nl.name, nl.node_id)
        for nl in present:
            self.configure(nl)
        for nl in present:
            self.remote[nl.name].nmt.send_command(NMT_START)

    def supervise(self) -> None:
        """From now on restart every node that boots (boot-up seen) or reports a state other
        than operational: reconfigure over SDO, then NMT start (docs/bus.md §3 "Boot and
        supervision"). After boot(); alone where another party booted the nodes (the
        simulator in lock-step)."""
        if self.running:
            return
        self.running = True
        self._worker = threading.Thread(target=self._work, name="rsra-canopen-master",
                                        daemon=True)
        self._worker.start()

    def configure(self, nl: NodeLayout) -> None:
        """Step 2 for one node: identity and TPDO parameters against the EDS (the verifier
        ``rsra nodes`` runs, stopping at the first mismatch), then 0x1017."""
        node = self.remote[nl.name]
        ns = self.supervisor.nodes[nl.name]
        try:
            facts = verify_node(nl, node, first_only=True)
            if facts.mismatches:
                m = facts.mismatches[0]
                raise BootError(nl.name, m.object, m.expected, m.actual, problem=m.problem)
            ns.identity = facts.identity
            node.sdo.download(0x1017, 0, struct.pack("<H", self.cfg.heartbeat.producer_ms))
        except BootError as e:
            ns.state = "error"
            ns.error = str(e)
            raise
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as e:
            ns.state = "error"
            ns.error = f"SDO failed: {e}"
            raise BootError(nl.name, "SDO", problem=f"failed: {e}") from None

    # -- SYNC --------------------------------------------------------------------------------
    def start_sync(self) -> None:
        """Produce SYNC at the sample rate (kernel BCM on SocketCAN; a thread of ours where
        the interface has no periodic sending of its own), counter 1…overflow."""
        if self.cfg.sync.producer != "service" or self.sync_task is not None:
            return
        cob = self.cfg.sync.cob_id & COB_MASK_11BIT
        ov = self.cfg.sync.counter_overflow
        if ov:
            msgs = [can.Message(arbitration_id=cob, data=[c], is_extended_id=False)
                    for c in range(1, ov + 1)]
        else:
            msgs = [can.Message(arbitration_id=cob, data=b"", is_extended_id=False)]
        bus = self.network.bus
        assert bus is not None  # the network is connected before the SYNC starts
        period = 1.0 / self.cfg.sample_rate_hz
        native = type(bus)._send_periodic_internal is not can.BusABC._send_periodic_internal
        # the interface's own periodic sending (kernel-timed BCM on SocketCAN) for a sequence
        # of SYNCs (the counter) only where it is known to send sequences: python-can-remote's
        # server keeps one message per COB-ID (the last), so every SYNC would carry the same
        # counter (docs/deployment.md "A shared bus between processes")
        if native and (len(msgs) == 1 or type(bus).__name__ in PERIODIC_SEQUENCE_BUSES):
            self.sync_task = bus.send_periodic(msgs, period)  # the interface's own (BCM)
        else:
            self.sync_task = SyncProducer(bus, msgs, period, self.network.send_lock)

    def send_sync(self, timestamp: float | None = None) -> None:
        """One SYNC now (lock-step drivers: the caller owns the sample clock). ``timestamp``
        is kept on buses that preserve it (python-can virtual with preserve_timestamps)."""
        ov = self.cfg.sync.counter_overflow
        data = b""
        if ov:
            self._sync_counter = self._sync_counter % ov + 1  # CiA 301: 1…overflow
            data = bytes([self._sync_counter])
        msg = can.Message(arbitration_id=self.cfg.sync.cob_id & COB_MASK_11BIT, data=data,
                          is_extended_id=False, timestamp=timestamp or 0.0)
        bus = self.network.bus
        assert bus is not None  # the network is connected before the SYNC starts
        with self.network.send_lock:
            bus.send(msg)

    def idle(self) -> bool:
        """No reconfiguration pending or running (lock-step drivers hold time meanwhile)."""
        return not self._pending and self._events.empty()

    @property
    def events_pending(self) -> int:
        """Restart requests queued for the worker (health ``queues.master_events.depth``)."""
        return self._events.qsize()

    # -- supervision ---------------------------------------------------------------------------
    def on_event(self, kind: str, node: str) -> None:
        """Supervisor events (bus thread: never blocks)."""
        if not self.running or kind not in ("bootup", "heartbeat"):
            return
        ns = self.supervisor.nodes[node]
        if kind == "heartbeat" and ns.error:
            return  # a failed verification waits for the node's next boot-up
        if node in self._pending:
            return
        last = self._last_config.get(node)
        if kind == "heartbeat" and last is not None and \
                self.clock() - last < self.supervisor.timeout_s:
            return  # just started: its next heartbeats may still say pre-operational
        self._pending.add(node)
        try:
            self._events.put_nowait((kind, node))
        except queue.Full:
            self._pending.discard(node)
            self.events_dropped += 1

    def _work(self) -> None:
        # blocks until a request (or stop's wake-up) comes: no polling while the bus is healthy
        while True:
            kind, node = self._events.get()
            if self._stop.is_set():
                return
            self._restart(kind, node)

    def _restart(self, kind: str, node: str) -> None:
        nl = self.table.node(node)
        try:
            self.configure(nl)
            self.remote[node].nmt.send_command(NMT_START)
            self.reconfigured += 1
            log.info("node %s (%s) reconfigured and started", node, kind)
        except BootError as e:
            log.error("%s", e)
        except Exception as e:  # the bus went away: keep the worker alive, report
            self.supervisor.nodes[node].error = f"restart failed: {e}"
            log.error("restart of %s failed: %s", node, e)
        finally:
            self._last_config[node] = self.clock()
            self._pending.discard(node)

    def stop(self) -> None:
        self.running = False
        self._stop.set()
        try:
            self._events.put_nowait(("stop", ""))  # wakes the worker (a full queue: it is awake)
        except queue.Full:
            pass
        if self.sync_task is not None:
            self.sync_task.stop()
            self.sync_task = None
        if self._worker is not None:
            self._worker.join(timeout=2.0)
            self._worker = None
