"""The simulated aircraft on a CAN bus: every configured CANopen node fed by the physics, one
sample per SYNC (docs/bus.md §2; model.md §8.3 "Time").

The aircraft and how its time moves are separate::

    Simulator  (this module)          the aircraft: bus, nodes, physics, faults, SDO server,
       │                              truth; answers a SYNC at time t, sends the heartbeats
       │ clock: SimulatedTime         due by t; no thread, no mode
       │        | WallClock           how frames are stamped (and the bus serialised)
       ▼
    sim_bus.drivers                   who moves time, and in which thread:
       LockstepSim   simulated time, no thread: step() / on_sync() / pump() in the caller's
       FollowSim     simulated time the master's SYNC frames carry; a Notifier thread serves
                     NMT, SDO and SYNC (a blocking SDO client gets its answers)
       RealtimeSim   the wall clock; Notifier + heartbeat ticker threads; each SYNC's answer
                     built ahead of it; run()

Construct the driver (``LockstepSim(cfg, …)``, ``RealtimeSim(cfg, …)``: it builds its
Simulator with the right clock and reads like one); the Simulator alone is driven by hand
(``pump``, ``answer_sync``, ``produce_sync``, ``advance``, ``prepare_next``).

Masters
-------
* **follow** (default): the nodes boot, send their boot-up frames and wait for an external
  master's NMT start; every SYNC seen on the bus produces one physics sample and the TPDOs.
* **autostart**: the nodes start themselves and the simulator is its own master, producing
  SYNC (with the CiA 301 counter) at the sample rate (``produce_sync``: ``RealtimeSim.run()``
  in real time, ``LockstepSim.step()`` in lock-step).

Clocks
------
* :class:`SimulatedTime` (lock-step): simulated time is the one acquisition clock. It moves
  only with the SYNCs (their time, or SYNC frames' timestamps) and ``advance(t)``, and drives
  the heartbeats and the fault timeline; nothing reads the wall clock. Frame timestamps are
  simulated time, spaced by each frame's transmission time at the EDS bit rate, rounded to
  1 µs. The same seed gives the same frames bit for bit, and the same sample values as real
  time (one physics sample per SYNC in both).
* :class:`WallClock` (real time): frames are stamped when sent.

Frames from the other bus users: ``pump()`` handles the frames queued on the bus in the
caller's thread, in order, so a master that sends NMT start then SYNC and calls ``pump()``
gets a deterministic answer without any sleep; or a driver's Notifier thread hands them over
as they arrive (SDO needs that when the client blocks).

Answers built ahead (``prepare_next``; only ``RealtimeSim`` asks, so that a SYNC in real
time is answered within the latency the service's telemetry is measured against):
half a period after each SYNC the driver's ticker computes the next physics sample
(``prefetch``) and has the whole answer to the next SYNC built (process image, TPDOs due, the
drop/malformed/unknown/errorframe draws, the frames as python-can messages, the fault-log
entries in order), so the SYNC only sends pre-built frames. A sample where a fault window
opens or closes, a node reboots, an EMCY goes out or the SYNC is lost is built at its SYNC,
as in lock-step; an NMT command or SDO request in between, or a SYNC counter other than the
one predicted, undoes the plan (node snapshots) and the SYNC builds its answer itself.
"""
from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, cast

import can
import numpy as np

from rsra.config.devices import device_profile
from rsra.config.rig import RigConfig
from rsra.sim_bus.clocks import Clock, SampleSource, SimulatedTime, WallClock
from rsra.sim_bus.cycle import SyncCycle
from rsra.sim_bus.endpoint import FRAME_OVERHEAD_BITS, BusEndpoint, RecordError
from rsra.sim_bus.fault_apply import FaultApplier
from rsra.sim_bus.faults import Fault, FaultInjector, FaultLog, parse_faults, validate_faults
from rsra.sim_bus.nodes import COB_NMT, SimNode
from rsra.sim_bus.nodeset import DEFAULT_BITRATE, NodeSet
from rsra.sim_bus.simtruth import MAX_TRUTH_SAMPLES, RECENT_SAMPLES, SimTruth, SyncLog, TruthBuffer

if TYPE_CHECKING:
    from rsra.sim_bus.physics import AircraftPhysics

__all__ = [  # the names other modules and the tests import from here
    "DEFAULT_BITRATE", "FRAME_OVERHEAD_BITS", "MAX_TRUTH_SAMPLES", "RECENT_SAMPLES", "Clock",
    "RecordError", "SampleSource", "SimulatedTime", "Simulator", "SyncLog", "TruthBuffer",
    "WallClock", "check_faults",
]

log = logging.getLogger(__name__)






def _validate(parsed: tuple[Fault, ...], nodes: list[tuple[str, str]], autostart: bool) -> None:
    validate_faults(parsed, dict(nodes), {name: device_profile(role).names for name, role in nodes},
                    autostart)


def check_faults(cfg: RigConfig, spec: str, nodes_present: tuple[str, ...] | None,
                 autostart: bool) -> tuple[Fault, ...]:
    """Parse and check a fault SPEC against the nodes a simulator of ``cfg`` would put on the
    bus (the same selection and check as :class:`Simulator`), before building one: raises
    FaultSpecError."""
    parsed = parse_faults(spec)
    _validate(parsed, [(n.name, n.role) for n in cfg.nodes
                       if n.required or nodes_present is None or n.role in nodes_present],
              autostart)
    return parsed




class Simulator:
    """The aircraft: every configured node on one python-can bus, fed by the physics one
    sample per SYNC. It runs no thread and has no mode: ``clock`` stamps its frames, and a
    driver (sim_bus.drivers: LockstepSim, FollowSim, RealtimeSim) moves time (module
    docstring).

    It assembles the pieces, each with one job, and is what the drivers call: the node set
    (sim_bus.nodeset.NodeSet: which nodes, fed how), the bus endpoint
    (sim_bus.endpoint.BusEndpoint: send, stamp, record, receive), the fault application
    (sim_bus.fault_apply.FaultApplier), the SYNC cycles and their schedule
    (sim_bus.cycle.SyncCycle) and the truth kept (sim_bus.simtruth.SimTruth).

    Parameters: ``cfg`` the rig; ``scenario`` a scenario name/object for AircraftPhysics, or
    ``physics`` any object with ``dt`` and ``next_sample()``; ``nodes_present`` the optional
    node roles on the bus (default: the scenario's, else all); ``bus`` an open python-can bus
    to use (not closed here), else one is opened with ``interface``/``channel`` (virtual:
    ``preserve_timestamps=True``); ``faults`` a SPEC string or parsed faults; ``record`` a log
    file (python-can Logger by suffix; candump ``.log`` when the suffix is not a log format);
    ``clock`` a :class:`SimulatedTime` (default: from 0 s) or a :class:`WallClock`.
    """

    def __init__(self, cfg: RigConfig, scenario: Any = None, *, physics: SampleSource | None = None,
                 seed: int | None = None, faults: str | tuple[Fault, ...] | None = None,
                 bus: can.BusABC | None = None, interface: str = "virtual",
                 channel: str = "rsra", autostart: bool = False,
                 clock: Clock | None = None, record: str | Path | None = None,
                 keep_samples: bool = True, nodes_present: tuple[str, ...] | None = None):
        self.cfg = cfg
        self.autostart = autostart
        self.clock: Clock = SimulatedTime() if clock is None else clock
        self.keep_samples = keep_samples
        if physics is None:
            from rsra.sim_bus.physics import AircraftPhysics
            if scenario is None or isinstance(scenario, str):
                from rsra.sim_bus.scenarios import load_scenario
                scenario = load_scenario(scenario or "ground-test")
            physics = AircraftPhysics(cfg, scenario, seed=seed)
        self.physics = physics
        self.dt = float(getattr(physics, "dt", cfg.sample_period_s))
        self.seed = seed if seed is not None else int(getattr(physics, "seed", 0) or 0)
        self.lock = threading.RLock()  # the drivers' threads and the caller's take turns
        # ---- nodes from the config; the EDS gives every object and COB-ID ------------------
        # required nodes always; optional ones when the scenario's aircraft has them
        # (Scenario.nodes_present: optional roles), all of them without a scenario
        if nodes_present is None:
            nodes_present = getattr(getattr(physics, "scenario", None), "nodes_present", None)
        self.node_set = NodeSet(cfg, nodes_present, self.now, self.lock)
        self.nodes: list[SimNode] = self.node_set.nodes
        self.by_name = self.node_set.by_name
        self.bitrate = self.node_set.bitrate
        self._sync_cob = cfg.sync.cob_id
        # ---- faults --------------------------------------------------------------------------
        parsed = parse_faults(faults) if isinstance(faults, (str, type(None))) else tuple(faults)
        _validate(parsed, [(n.name, n.role) for n in self.nodes], autostart)
        self.faults = FaultInjector(parsed, seed=self.seed)
        self.faults.log = FaultLog(keep=keep_samples)  # all of it only for a truth file
        self.applier = FaultApplier(self.faults, self.node_set, self.node_set.unknown_cob)
        # ---- bus: the recording first (a bad path must not leak an open bus) -----------------
        self.endpoint = BusEndpoint(self.clock, self.lock, self.bitrate, bus=bus,
                                    interface=interface, channel=channel, record=record)
        self.bus, self.channel = self.endpoint.bus, self.endpoint.channel
        self.log_channel, self.network = self.endpoint.log_channel, self.endpoint.network
        # ---- truth and the cycles ------------------------------------------------------------
        self.truth = SimTruth(keep_samples)
        self.samples, self.sync_info = self.truth.samples, self.truth.sync_info
        self.recent_samples = self.truth.recent_samples
        self.cycles = SyncCycle(nodes=self.node_set, applier=self.applier,
                                endpoint=self.endpoint, truth=self.truth, physics=physics,
                                clock=self.clock, dt=self.dt, sync_cob=self._sync_cob,
                                counter_overflow=cfg.sync.counter_overflow,
                                autostart=autostart)
        for n in self.nodes:
            n.attach(self.network)
            n.before_change = self._discard_plan
        self.network.subscribe(COB_NMT, self.endpoint.guard(self._on_nmt_frame))
        self.network.subscribe(self._sync_cob, self.endpoint.guard(self._on_sync_frame))
        self._started = False
        self._closed = False

    # ------------------------------------------------------------------------------------------
    # what the pieces count and keep, read here (the drivers, the command line, the tests)
    frames_sent = property(lambda self: self.endpoint.frames_sent)
    frames_received = property(lambda self: self.endpoint.frames_received)
    error_frames_received = property(lambda self: self.endpoint.error_frames_received)
    last_sample = property(lambda self: self.truth.last_sample)
    truth_truncated = property(lambda self: self.truth.truth_truncated)
    prefetched = property(lambda self: self.cycles.prefetched)
    prepared = property(lambda self: self.cycles.prepared)
    plans_discarded = property(lambda self: self.cycles.plans_discarded)
    _unknown_cob = property(lambda self: self.node_set.unknown_cob)

    def known_cob_ids(self) -> set[int]:
        """Every COB-ID the configured nodes and the master use (CiA 301 pre-defined set)."""
        return self.node_set.known_cob_ids(self._sync_cob)

    # ------------------------------------------------------------------------------------------
    # lifetime
    def start(self) -> Simulator:
        """Boot every node (boot-up frames); with autostart, start them."""
        with self.lock:
            if self._started:
                return self
            self._started = True
            t = self.now()
            for fr in self.node_set.boot(t):
                self.endpoint.send_frame(fr, t, None)
            if self.autostart:  # CiA 301 self-starting nodes
                self.node_set.self_start(t)
        return self

    def close(self) -> None:
        """Close the recording and (if we opened it) the bus; a driver stops its threads
        first. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self.lock:
            self.node_set.detach()
            self.endpoint.close()

    def __enter__(self) -> Simulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------
    # the acquisition clock, the bus
    def now(self) -> float:
        """The clock's time: simulated in lock-step, the wall clock live (model §8.3 "Time")."""
        return self.clock.now()

    def check(self) -> None:
        """Raise the first exception a bus callback hit."""
        self.endpoint.check()

    def pump(self) -> int:
        """Handle every frame already queued on the bus, in order, in this thread (a driver
        without a Notifier reading the bus). Returns the number handled."""
        return self.endpoint.pump()

    # ------------------------------------------------------------------------------------------
    # NMT and SYNC from the bus
    def _on_nmt_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2:
            return  # malformed NMT: ignored, as a node would
        with self.lock:
            t = self.now()
            for n, f in self.node_set.nmt(data[0], data[1], t):
                self.endpoint.send_frame(f, t, n)

    def _on_sync_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        counter = data[0] if len(data) >= 1 else None
        with self.lock:
            self.cycles.answer(counter, self.clock.sync_time(timestamp), send_sync=False,
                               received_sync=len(data))

    # ------------------------------------------------------------------------------------------
    # what a driver calls to move time (each returns the frames it sent; none pumps the bus)
    def advance(self, t: float) -> list[can.Message]:
        """Time passes to ``t`` without a SYNC: due heartbeats go out (each stamped with its due
        time). With simulated time this is how time moves between SYNCs."""
        return self.endpoint.captured(self.cycles.advance, t)

    def answer_sync(self, counter: int | None, t: float) -> list[can.Message]:
        """A SYNC (counter byte or None) was put on the bus at time ``t`` by someone else: draw
        one physics sample and answer it. Use this *or* SYNC frames on the bus, not both, for
        the same SYNC."""
        out = self.endpoint.captured(self.cycles.answer, counter, t, send_sync=False)
        self.check()
        return out

    @property
    def syncs_produced(self) -> int:
        """SYNC cycles this simulator produced as its own master (autostart), lost ones too."""
        return self.cycles.n_sync

    def sync_jitter(self) -> float:
        """The jitter of the next SYNC :meth:`produce_sync` sends (the faults'; 0 without)."""
        return self.applier.sync_plan(self.cycles.n_sync, self.dt)[0]

    def produce_sync(self, t: float | None = None, jitter: float = 0.0) -> list[can.Message]:
        """As our own master (autostart): the next SYNC (counter; loss per the faults) at time
        ``t`` (None: the clock's now), which includes its ``jitter`` (:meth:`sync_jitter`), and
        every answer."""
        with self.lock:
            out = self.endpoint.captured(self.cycles.answer, self.cycles.next_counter(),
                                         self.clock.now() if t is None else t, send_sync=True,
                                         jitter=jitter)
        self.check()
        return out

    def next_heartbeat(self) -> float | None:
        """When the next heartbeat is due (None: no node produces one)."""
        with self.lock:
            return self.node_set.next_heartbeat()

    # ------------------------------------------------------------------------------------------
    # the next SYNC's answer built ahead of it (a real-time driver asks, between two SYNCs)
    def prefetch(self) -> None:
        """Compute the next physics sample now when the physics computes a whole block at it
        (SyncCycle.prefetch)."""
        with self.lock:
            self.cycles.prefetch()

    def prepare_next(self) -> None:
        """Build the answer to the next SYNC now (SyncCycle.prepare_next)."""
        with self.lock:
            if not self._closed:
                self.cycles.prepare_next()

    def _discard_plan(self) -> None:
        """Something outside a SYNC cycle is about to change a node: undo the plan first."""
        with self.lock:
            self.cycles.discard_plan()

    # ------------------------------------------------------------------------------------------
    # truth
    @property
    def fault_log(self) -> list[dict]:
        return list(self.faults.log)

    def sync_arrays(self) -> dict[str, np.ndarray]:
        """Per sample: index, SYNC counter (0: the SYNC carried none), SYNC time, lost flag."""
        return self.truth.sync_arrays()

    def truth_arrays(self) -> dict[str, np.ndarray]:
        """The kept samples as sim_bus.truth arrays (SimTruth.truth_arrays). Needs
        keep_samples=True."""
        return self.truth.truth_arrays(self.node_set.codec)

    def write_truth(self, path: str | Path, meta: dict | None = None,
                    write: Callable[[Path, bytes], None] | None = None) -> Path:
        """Write the truth file (sim_bus.truth format) with the injected faults; ``write``
        as in :func:`sim_bus.truth.write_truth` (an atomic write)."""
        from rsra.sim_bus.offline import run_meta
        from rsra.sim_bus.truth import write_truth

        full: dict[str, Any] = {}
        if hasattr(self.physics, "scenario"):  # AircraftPhysics (or physics that reads like it)
            full.update(run_meta(self.cfg, cast("AircraftPhysics", self.physics)))
        full.update(faults_spec=[f.token for f in self.faults.faults],
                    fault_entries_not_kept=self.faults.dropped_log_entries,
                    samples_not_kept=self.samples.dropped,
                    nodes=[n.name for n in self.nodes], lockstep=self.clock.simulated,
                    autostart=self.autostart, **(meta or {}))
        arrs = self.truth_arrays()
        return write_truth(path, arrs, faults=self.fault_log, meta=full,
                           sync_counter=arrs["sync_counter"], write=write)
