"""The simulator's time bases (model §8.3 "Time"): what time it is, and how a frame sent now
is stamped (:class:`SimulatedTime` in lock-step, :class:`WallClock` in real time); and what
the simulator needs from its physics (:class:`SampleSource`)."""
from __future__ import annotations

import time
from typing import Any, ClassVar, Protocol


class SampleSource(Protocol):
    """What the simulator needs from the physics (sim_bus.physics.AircraftPhysics)."""

    dt: float

    def next_sample(self) -> Any: ...


def _round_us(t: float) -> float:
    return round(t * 1e6) / 1e6


class Clock(Protocol):
    """The simulator's time base: what time it is, and how a frame sent now is stamped."""

    simulated: ClassVar[bool]  # frames carry simulated time (the truth file's ``lockstep``)

    def now(self) -> float: ...

    def advance_to(self, t: float) -> None: ...

    def stamp(self, t: float | None, duration: float) -> float: ...

    def occupy(self, t: float, duration: float) -> None: ...

    def sync_time(self, timestamp: float) -> float: ...


class SimulatedTime:
    """Simulated time (lock-step; model §8.3 "Time"): it moves only when the driver says (a
    SYNC's time, ``advance_to``). The bus is serialised: a frame starts when the previous one
    has finished (``duration``: its transmission time at the bit rate); timestamps are rounded
    to 1 µs. Nothing reads the wall clock."""

    simulated: ClassVar[bool] = True

    def __init__(self, t0: float = 0.0):
        self.t0 = float(t0)
        self.t = self.t0
        self._bus_free = self.t0  # when the frame on the bus has finished

    def now(self) -> float:
        return self.t

    def advance_to(self, t: float) -> None:
        self.t = max(self.t, t)

    def stamp(self, t: float | None, duration: float) -> float:
        """A frame sent at ``t`` (None: now) starts when the bus is free."""
        ts = _round_us(max(self.t if t is None else t, self._bus_free))
        self._bus_free = ts + duration
        return ts

    def occupy(self, t: float, duration: float) -> None:
        """Another user's frame (the master's SYNC) held the bus from ``t``."""
        self._bus_free = max(self._bus_free, t + duration)

    def sync_time(self, timestamp: float) -> float:
        """The time of a SYNC frame received: the time it carries."""
        return timestamp


class WallClock:
    """Real time: the wall clock; frames are stamped when sent, the bus is the interface's."""

    simulated: ClassVar[bool] = False

    def now(self) -> float:
        return time.time()

    def advance_to(self, t: float) -> None:
        pass

    def stamp(self, t: float | None, duration: float) -> float:
        return time.time()

    def occupy(self, t: float, duration: float) -> None:
        pass

    def sync_time(self, timestamp: float) -> float:
        return time.time()
