"""How the simulated aircraft's time moves: the drivers of a :class:`sim_bus.bus_sim.Simulator`.

The Simulator is the aircraft (bus, nodes, physics, faults, truth) and has no mode; a driver
owns one, chooses its clock and decides which thread handles the bus and when time moves::

    driver        clock           frames from the bus      time moves                threads
    LockstepSim   SimulatedTime   pump(), caller's thread  step() / on_sync() /      none
                                                           advance()
    FollowSim     SimulatedTime   a Notifier thread        the master's SYNC frames  Notifier
                                  (NMT, SDO, SYNC)         (their timestamps),
                                                           advance()
    RealtimeSim   WallClock       a Notifier thread        the wall clock: run()     Notifier,
                                                           (autostart: its SYNC at   heartbeat
                                                           the sample rate)          ticker

Construct the driver with the Simulator's arguments (``LockstepSim(cfg, physics=…,
autostart=True)``); it reads like its Simulator (every other attribute is the aircraft's:
``sync_info``, ``fault_log``, ``write_truth`` …, as :class:`HandoffBus` reads like its bus).
A test or tool that wants another arrangement drives a bare Simulator by hand (``pump``,
``answer_sync``, ``produce_sync``, ``advance``, ``prepare_next``).

Lock-step with a peer (the service's reader) on the same virtual bus:

::

    LockstepDriver.step():  sim.step()  ─▶ peer.pump()  ─▶ settle()
                                                           │ while a peer is busy (its
                                                           │ master restarting a node):
                            HandoffBus ◀── peer's thread ──┤   a transmission handed over
                            (send waits) ──▶ driver:       │   sim.pump(), peer.pump(),
                                                           └   then the sender goes on

Simulated time moves only in :meth:`LockstepDriver.step` (one sample period: the simulator's
SYNC and every answer). A peer that must hold a conversation between two steps — the
reader's CANopen master reconfiguring a node over SDO, whose client blocks until the answer is
in its queue — does so in its own thread on a :class:`HandoffBus`: each transmission waits
until the driver has let every bus user process it (the simulator answers, the peer reads
the answer), so the client finds its answer already queued and the frames follow one
deterministic order, as on a bus where time stands still. Nothing is processed inside a
``send`` call (no re-entrant pump): the driver's thread does all processing, in order.

A peer is anything with ``pump() -> int`` (process the frames queued for it now, in order,
in the caller's thread) and ``busy() -> bool`` (an exchange is in progress in another
thread; time must not move). rsra.daq.bus.reader.LockstepReader is one.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import can

from rsra.canbus import BatchNotifier, EndOnBusFailure, bus_failure
from rsra.sim_bus.bus_sim import SimulatedTime, Simulator, WallClock

log = logging.getLogger(__name__)

HANDOFF_POLL_S = 0.01  # the driver's wait for a handed-over frame before it re-checks busy()


class Peer(Protocol):
    """A bus user driven in lock-step."""

    def pump(self) -> int: ...

    def busy(self) -> bool: ...


class HandoffBus:
    """A python-can bus whose transmissions from threads other than the driver's wait for
    the driver (:meth:`LockstepDriver.settle`) to have every bus user process them.

    Everything but ``send`` is the wrapped bus's (``recv``, ``shutdown``, attributes)."""

    def __init__(self, bus: can.BusABC):
        self.bus = bus
        self._cond = threading.Condition()
        self._handed = 0  # transmissions waiting for the driver
        self._done = 0  # transmissions the driver has let everyone process
        self._closed = False
        self.driver_thread: int | None = None  # sends from this thread never wait

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.bus.send(msg, timeout)
        if threading.get_ident() == self.driver_thread:
            return  # the driver processes its own thread's frames in its own order
        with self._cond:
            if self._closed:
                return
            self._handed += 1
            ticket = self._handed
            self._cond.notify_all()
            while self._done < ticket and not self._closed:
                self._cond.wait()

    def take(self, timeout: float) -> bool:
        """Driver: wait up to ``timeout`` s for a handed-over transmission. True: one (or
        more) is on the bus; process it, then :meth:`release`."""
        with self._cond:
            if self._done == self._handed:
                self._cond.wait(timeout)
            return self._done < self._handed

    def release(self) -> None:
        """Driver: every handed-over transmission has been processed by every bus user."""
        with self._cond:
            self._done = self._handed
            self._cond.notify_all()

    def close(self) -> None:
        """Release every waiting sender for good (before the peer's threads are joined)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class LockstepDriver:
    """Steps a lock-step simulator (``LockstepSim(cfg, …, autostart=True)``) and one peer on the same virtual bus; ``handoff`` is the peer's bus
    when the peer transmits from a thread of its own (module docstring)."""

    def __init__(self, sim: Any, peer: Peer, handoff: HandoffBus | None = None):
        self.sim = sim
        self.peer = peer
        self.handoff = handoff
        self.steps = 0

    def start(self) -> None:
        """The simulator boots (and starts) its nodes; the peer sees the boot-ups."""
        if self.handoff is not None:
            self.handoff.driver_thread = threading.get_ident()
        self.sim.start()
        self.peer.pump()

    def step(self) -> None:
        """Simulated time moves one sample period; the peer has processed every frame and
        finished every exchange it started before this returns."""
        self.sim.step()
        self.peer.pump()
        self.settle()
        self.steps += 1

    def settle(self) -> None:
        """Hold simulated time while the peer is busy, serving its transmissions in order."""
        peer, sim, handoff = self.peer, self.sim, self.handoff
        while peer.busy():
            if handoff is None:
                raise RuntimeError("a busy lock-step peer needs a HandoffBus")
            if handoff.take(HANDOFF_POLL_S):
                sim.pump()
                peer.pump()
                handoff.release()

    def close(self) -> None:
        if self.handoff is not None:
            self.handoff.close()


# ----------------------------------------------------------------------------------------------
# the simulator's own drivers

class _Driven:
    """What every driver shares: its aircraft (``sim``), started and closed with it; every
    attribute the driver does not have is the aircraft's."""

    def __init__(self, sim: Simulator):
        self.sim = sim

    def __getattr__(self, name: str) -> Any:
        if name == "sim":  # not set yet (a failed __init__): no recursion
            raise AttributeError(name)
        return getattr(self.sim, name)

    def start(self) -> _Driven:
        self.sim.start()
        return self

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> Any:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


class LockstepSim(_Driven):
    """Lock-step: simulated time from ``t0``, no thread. :meth:`step` (autostart: the
    simulator is the master) moves time one sample period; behind a master, :meth:`pump`
    handles its frames (NMT, SYNC, SDO) in order and :meth:`on_sync`/:meth:`advance` move
    time. Every call first handles the frames already queued, in the caller's thread. A
    blocking SDO client needs a thread that answers: a :class:`LockstepDriver` with a
    :class:`HandoffBus`, or :class:`FollowSim`."""

    def __init__(self, cfg: Any, scenario: Any = None, *, t0: float = 0.0, **kw: Any):
        self.clock = SimulatedTime(t0)
        super().__init__(Simulator(cfg, scenario, clock=self.clock, **kw))
        self.t0 = self.clock.t0

    def advance(self, t: float) -> list[can.Message]:
        """Simulated time moves to ``t`` without a SYNC: the heartbeats due go out."""
        sim = self.sim
        with sim.lock:
            sim.pump()
            return sim.advance(t)

    def on_sync(self, counter: int | None, t: float) -> list[can.Message]:
        """A SYNC someone else put on the bus at ``t`` (without its frame): the answer."""
        sim = self.sim
        with sim.lock:
            sim.pump()
            return sim.answer_sync(counter, t)

    def step(self) -> list[can.Message]:
        """As our own master (autostart): simulated time moves one sample period, the SYNC
        (counter, jitter, loss per the faults) and every answer go out. Returns the frames."""
        sim = self.sim
        with sim.lock:
            sim.pump()
            jitter = sim.sync_jitter()
            return sim.produce_sync(self.t0 + sim.syncs_produced * sim.dt + jitter, jitter)

    def run(self, duration: float | None = None, *, stop: threading.Event | None = None,
            progress: Callable[[int, float], None] | None = None,
            progress_every: float = 1.0) -> int:
        """Autostart: :meth:`step` as fast as possible for ``duration`` simulated seconds
        (None: until ``stop`` is set). Returns the SYNC cycles."""
        if not self.sim.autostart:
            raise RuntimeError("lock-step follow mode is driven by the master: use on_sync()/pump()")
        self.start()
        stop = stop or threading.Event()
        n_total = None if duration is None else int(round(duration / self.sim.dt))
        every = max(1, int(progress_every / self.sim.dt))
        k = 0
        while (n_total is None or k < n_total) and not stop.is_set():
            self.step()
            k += 1
            if progress and k % every == 0:
                progress(k, k * self.sim.dt)
        return k


class _Served(_Driven):
    """A python-can Notifier thread hands the other bus users' frames to the simulator as they
    arrive (canopen's Network notifier): NMT, SDO (a blocking client gets its answer), SYNC."""

    def __init__(self, sim: Simulator):
        super().__init__(sim)
        self._started = False

    def start(self) -> _Served:
        sim = self.sim
        with sim.lock:  # the notifier's callbacks wait for the nodes' boot
            if not self._started:
                self._started = True
                # a bus that fails ends the thread quietly; check() raises the failure
                sim.network.notifier = BatchNotifier(
                    sim.bus, [*sim.network.listeners, EndOnBusFailure()], 0.1)
                sim.start()
        return self

    def pump(self) -> int:
        """Nothing to do: the Notifier thread handles the frames."""
        return 0

    def check(self) -> None:
        """Raise the first exception the simulator's callbacks or the Notifier hit."""
        self.sim.check()
        notifier = self.sim.network.notifier
        if notifier is not None and notifier.exception is not None:
            raise notifier.exception

    def close(self) -> None:
        net = self.sim.network
        if net.notifier is not None:
            net.notifier.stop(timeout=5.0)
            net.notifier = None
        self.sim.close()


class FollowSim(_Served):
    """Behind a master in simulated time: a Notifier thread serves NMT, SDO and SYNC; the
    time is what the master's SYNC frames carry, and :meth:`advance` moves it between SYNCs
    (nothing else does: no ticker, no wall clock)."""

    def __init__(self, cfg: Any, scenario: Any = None, *, t0: float = 0.0, **kw: Any):
        self.clock = SimulatedTime(t0)
        super().__init__(Simulator(cfg, scenario, clock=self.clock, **kw))
        self.t0 = self.clock.t0


class RealtimeSim(_Served):
    """Real time: the wall clock; a Notifier thread serves NMT, SDO and SYNC; a ticker thread
    sends the heartbeats when due and, half a period after each SYNC, has the simulator
    compute the next physics block (``prefetch``) and build the next SYNC's answer
    (``prepare_next``), so the SYNC only sends pre-built frames.
    :meth:`run` produces SYNC at the sample rate (autostart) or lets time pass while a
    master's SYNCs are answered.

    At periods of ``INLINE_PLAN_PERIOD_S`` or less the next answer is built in the SYNC's own
    wake-up, right after this SYNC's answer went out: a ticker woken half a period later is
    often late at such periods, and the SYNC then finds no plan (measured at 5 ms periods
    on a 2-core machine). The frames are the same either way (pure functions of seed,
    sample and slot)."""

    INLINE_PLAN_PERIOD_S = 0.002  # 500 samples/s and above
    AHEAD_SLACK = 0.25  # periods a planned wake-up may come after the work-ahead's time

    def __init__(self, cfg: Any, scenario: Any = None, **kw: Any):
        self.clock = WallClock()
        super().__init__(Simulator(cfg, scenario, clock=self.clock, **kw))
        self._stop = threading.Event()
        self._wake = threading.Event()  # the ticker re-plans its next wake-up
        self._ticker: threading.Thread | None = None
        self._prefetch_at: float | None = None  # when the ticker works ahead (wall clock)
        self._ticker_wake_at: float | None = None  # when it plans to wake (None: planning)
        self._error: BaseException | None = None
        # the physics computes its next block ahead (AircraftPhysics), else None
        self._compute_ahead = getattr(self.sim.physics, "compute_ahead", None)
        # a master's SYNC: after the simulator's answer (subscribed after it), plan ahead
        self.sim.network.subscribe(self.sim.cfg.sync.cob_id, self._on_sync_frame)

    def start(self) -> RealtimeSim:
        super().start()
        if self._ticker is None:
            self._ticker = threading.Thread(target=self._tick_loop, name="rsra-sim-heartbeat",
                                            daemon=True)
            self._ticker.start()
        return self

    def close(self) -> None:
        """Stop the ticker and the Notifier, then close the simulator. Idempotent."""
        self._stop.set()
        self._wake.set()
        if self._ticker is not None:
            self._ticker.join(timeout=5.0)
        super().close()

    def check(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise err
        super().check()

    def _on_sync_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.sim.dt <= self.INLINE_PLAN_PERIOD_S:
            # a short period: build the next answer in this wake-up, right after this one;
            # a ticker woken half a period later is often late at short periods
            self.sim.prefetch()
            self.sim.prepare_next()
        self._schedule_ahead()

    def _schedule_ahead(self) -> None:
        """Half a period after this SYNC the ticker works ahead, off the SYNC → TPDO path."""
        if self._ticker is not None:
            dt = self.sim.dt
            self._prefetch_at = at = time.time() + 0.5 * dt
            wake = self._ticker_wake_at
            # the ticker already plans to wake about then (it expects the SYNCs' rhythm; a
            # quarter of a period later still works ahead in time): not woken now, when this
            # SYNC's answer is being received and its hub loads computed (the latency
            # path); it waits on to ``at`` if it wakes before
            if wake is None or wake > at + self.AHEAD_SLACK * dt:
                self._wake.set()

    def _tick_loop(self) -> None:
        """Live heartbeats between SYNCs (wall clock): wake at the next due heartbeat, and
        half a period after a SYNC to compute the next physics block and build the next
        answer then (between SYNCs) rather than on the next SYNC's path to its TPDOs."""
        sim = self.sim
        expected: float | None = None  # the next SYNC's work-ahead, if the SYNCs keep time
        while not self._stop.is_set():
            self._wake.clear()  # a set() from here on ends the wait below at once
            self._ticker_wake_at = None  # planning: a SYNC meanwhile wakes it (_schedule_ahead)
            with sim.lock:
                ahead_at = self._prefetch_at if self._prefetch_at is not None else expected
                nxt = [t for t in (sim.next_heartbeat(), ahead_at) if t is not None]
                now = time.time()
                wait = min(max(min(nxt) - now if nxt else 0.5, 0.0), 0.5)
                self._ticker_wake_at = now + wait
            self._wake.wait(wait)
            if self._stop.is_set():
                return
            try:
                ahead = False
                with sim.lock:
                    now = time.time()
                    sim.advance(now)  # the heartbeats due; the recording flushed each second
                    if expected is not None and now >= expected:
                        expected = None  # (once: no SYNC came, the ticker waits for one)
                    at = self._prefetch_at
                    if at is not None and now >= at:
                        self._prefetch_at = None
                        expected = at + sim.dt  # half a period after the next SYNC
                        sim.prefetch()  # still ahead of the next SYNC
                        sim.prepare_next()
                        ahead = True
                if ahead and self._compute_ahead is not None:
                    # the physics' next block (1-2 ms for 100 samples), outside the
                    # simulator's lock: the next SYNCs are answered meanwhile, and the block
                    # is ready long before its boundary
                    self._compute_ahead()
            except Exception as e:  # noqa: BLE001 - re-raised by check()
                if bus_failure(e):  # the bus went away: the owner reports it, once
                    log.debug("heartbeat ticker: the bus failed: %s", e)
                else:
                    log.exception("heartbeat ticker failed")
                self._error = self._error or e
                return

    def run(self, duration: float | None = None, *, stop: threading.Event | None = None,
            progress: Callable[[int, float], None] | None = None,
            progress_every: float = 1.0) -> int:
        """Run until ``duration`` seconds (None: until ``stop`` is set). Autostart: produce
        SYNC at the sample rate. Follow mode: answer the master's SYNCs while the time passes.
        Returns SYNC cycles."""
        self.start()
        sim = self.sim
        stop = stop or threading.Event()
        start = time.monotonic()
        if not sim.autostart:
            next_report = progress_every
            while not stop.is_set():
                el = time.monotonic() - start
                if duration is not None and el >= duration:
                    break
                stop.wait(min(0.1, progress_every, (duration - el) if duration else 0.1))
                self.check()
                if progress and time.monotonic() - start >= next_report:
                    next_report += progress_every
                    progress(len(sim.sync_info), time.monotonic() - start)
            return len(sim.sync_info)
        n_total = None if duration is None else int(round(duration / sim.dt))
        k = 0
        every = max(1, int(round(progress_every / sim.dt)))
        while (n_total is None or k < n_total) and not stop.is_set():
            jitter = sim.sync_jitter()
            deadline = start + k * sim.dt + jitter
            delay = deadline - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
            with sim.lock:  # the ticker is woken before the lock is free, as the SYNC's
                sim.produce_sync(None, jitter)  # answer ends: it does not take the GIL from
                self._schedule_ahead()  # this loop (measured: +50 µs CPU a SYNC otherwise)
            self.check()
            k += 1
            if progress and k % every == 0:
                progress(k, k * sim.dt)
        return k
