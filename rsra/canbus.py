"""python-can glue shared by the service (``rsra.daq``) and the simulator (``rsra.sim_bus``).

Imports nothing of ours, so both sides may use it without importing each other.
:func:`shutdown_bus` closes any python-can bus once: python-can-remote's client raises from
``shutdown`` when the server already closed the connection, and then again from ``__del__``
(``ValueError: file descriptor cannot be a negative integer``).
"""
from __future__ import annotations

import logging

import can

log = logging.getLogger(__name__)


def shutdown_bus(bus: can.BusABC) -> None:
    """``bus.shutdown()`` once: an interface whose own shutdown fails (its connection already
    gone) is logged and marked shut down by python-can's base class, so ``__del__`` does not
    try again."""
    try:
        bus.shutdown()
    except Exception as e:  # noqa: BLE001 - any interface's failure to close
        log.debug("bus shutdown: %s: %s", type(e).__name__, e)
        can.BusABC.shutdown(bus)  # the base class's part: periodic tasks stopped, flag set
