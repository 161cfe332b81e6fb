"""Lock-step driving of the simulated bus: one loop steps the simulator and its peers.

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
thread; time must not move). :class:`daq.reader.Reader` is one.
"""
from __future__ import annotations

import threading
from typing import Any, Protocol

import can

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
    """Steps a lock-step simulator (``Simulator(lockstep=True, threaded=False,
    autostart=True)``) and one peer on the same virtual bus; ``handoff`` is the peer's bus
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
