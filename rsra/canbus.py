"""python-can glue shared by the service (``rsra.daq``) and the simulator (``rsra.sim_bus``).

Imports nothing of ours, so both sides may use it without importing each other.
:func:`shutdown_bus` closes any python-can bus once: python-can-remote's client raises from
``shutdown`` when the server already closed the connection, and then again from ``__del__``
(``ValueError: file descriptor cannot be a negative integer``).
:class:`EchoFirstVirtualBus` is python-can's in-process ``virtual`` bus with the sender's own
copy delivered first (see there); :func:`open_bus` opens it wherever ``virtual`` is asked for.
"""
from __future__ import annotations

import logging
import re
import time

from copy import deepcopy
from queue import Full
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

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


def bus_failure(exc: BaseException) -> bool:
    """The bus itself failed or went away (an interface down, python-can-remote's server
    closed: ``WebsocketClosed``), as opposed to a bug in a frame's handler."""
    if isinstance(exc, (can.CanError, OSError)):
        return True
    try:
        from can_remote.websocket import WebsocketClosed
    except ImportError:  # python-can-remote not installed: no such failure
        return False
    return isinstance(exc, WebsocketClosed)


class EndOnBusFailure(can.Listener):
    """A Notifier listener that ends the Notifier's thread when its bus fails (python-can
    otherwise either re-raises from the thread, printing a traceback, or — with an
    ``on_error`` that returns — retries a bus that is gone at once, in a loop). The failure
    stays in ``notifier.exception`` for the owner to report; the thread ends by SystemExit,
    which ``threading`` ends a thread with silently. Any other error is left unhandled (a bug:
    its traceback is printed, as before)."""

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        if not bus_failure(exc):
            raise NotImplementedError  # not handled here: python-can raises it
        raise SystemExit


class EchoFirstVirtualBus(VirtualBus):
    """python-can's ``virtual`` bus, with one ordering guarantee added: a frame sent with
    ``receive_own_messages`` reaches the sender's own queue before any other user's.

    python-can puts the copies in the channel's queues in the order the buses were opened. A
    responder opened first (the simulator) can then receive the master's SYNC, answer it and
    have its answer queued to the master before the master's own copy of the SYNC: the master
    sees a sample's frames before the SYNC that opened it (under load, about once in a few
    thousand samples; found by a lock-step test with ``sys.setswitchinterval(2e-5)``). On a real
    bus, SocketCAN's loopback echoes a frame before any answer to it can be sent. Only
    :meth:`send` differs; the queues, channels and timestamps are python-can's."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        own = [self.queue] if self.receive_own_messages else []
        all_sent = True
        for bus_queue in own + [q for q in self.channel if q is not self.queue]:
            copy = deepcopy(msg)
            copy.timestamp = timestamp
            copy.channel = self.channel_id
            copy.is_rx = bus_queue is not self.queue
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")


_IFNAME = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")  # a Linux interface name (IFNAMSIZ 16)


def recording_channel(interface: str | None, channel: Any, *, sim: bool = False) -> str:
    """The channel name written on every frame of a recording (docs/bus.md §5): stable,
    short and true — ``sim`` for the simulator's own bus, else the interface's channel when
    it is a name candump and canplayer can take (at most 15 characters, no ``/`` or ``:``),
    else the interface's name (``remote`` for python-can-remote, whose channel is a URL)."""
    if sim:
        return "sim"
    name = "" if channel is None else str(channel)
    if _IFNAME.match(name):
        return name
    if interface and _IFNAME.match(str(interface)):
        return str(interface)
    return "can"


def open_bus(**args: Any) -> can.BusABC:
    """``can.Bus(**args)``, except that ``interface='virtual'`` opens
    :class:`EchoFirstVirtualBus` (same channels: it talks to plain virtual buses)."""
    if args.get("interface") == "virtual":
        rest = {k: v for k, v in args.items() if k != "interface"}
        return EchoFirstVirtualBus(**rest)
    return can.Bus(**args)
