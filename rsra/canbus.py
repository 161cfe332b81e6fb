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


    # -- batches (one wake-up per sample: docs/performance.md "One wake-up per sample") -------
    def recv_pending(self, limit: int) -> list[can.Message]:
        """Every frame already queued for this bus (at most ``limit``), in order, taken under
        the queue's lock once instead of one ``recv(0)`` each; ``[]`` when none. A bus with
        software filters gets them applied per frame, as ``recv`` does."""
        self._check_if_open()
        q = self.queue
        with q.mutex:
            items = q.queue
            n = min(len(items), limit)
            if not n:
                return []
            out = [items.popleft() for _ in range(n)]
            q.not_full.notify(n)
        if self._filters is None:
            return out
        return [m for m in out if self._matches_filters(m)]

    def send_many(self, msgs: list[can.Message]) -> None:
        """Send ``msgs`` in order as :meth:`send` would, each receiver getting all of them in
        one put (one wake-up of a waiting reader instead of one per frame). A bounded
        receiver queue (``rx_queue_size``) falls back to :meth:`send` frame by frame."""
        self._check_if_open()
        preserve = self.preserve_timestamps
        now = time.time()
        own = [self.queue] if self.receive_own_messages else []
        queues = own + [q for q in self.channel if q is not self.queue]
        if any(q.maxsize > 0 for q in queues):
            for m in msgs:
                self.send(m)
            return
        for bus_queue in queues:
            is_rx = bus_queue is not self.queue
            copies = []
            for msg in msgs:
                copy = deepcopy(msg)
                copy.timestamp = msg.timestamp if preserve else now
                copy.channel = self.channel_id
                copy.is_rx = is_rx
                copies.append(copy)
            with bus_queue.mutex:
                bus_queue.queue.extend(copies)
                bus_queue.unfinished_tasks += len(copies)
                bus_queue.not_empty.notify()


def recv_batch(bus: can.BusABC, limit: int) -> list[can.Message]:
    """The frames ``bus`` has already received (at most ``limit``; ``[]``: none), without
    waiting: the interface's own batch read where it has one (:class:`EchoFirstVirtualBus`),
    else python-can's ``recv`` with a zero timeout until it returns nothing."""
    # (the class, not an attribute lookup: a wrapper that forwards attributes, such as the
    # lock-step HandoffBus, must not have its own recv/send bypassed)
    if isinstance(bus, EchoFirstVirtualBus):
        return bus.recv_pending(limit)
    out: list[can.Message] = []
    recv = bus.recv
    while len(out) < limit and (m := recv(0.0)) is not None:
        out.append(m)
    return out


def send_batch(bus: can.BusABC, msgs: list[can.Message]) -> None:
    """Send ``msgs`` in order: in one call where the interface allows
    (:meth:`EchoFirstVirtualBus.send_many`), else one ``send`` each."""
    if isinstance(bus, EchoFirstVirtualBus):
        bus.send_many(msgs)
        return
    for m in msgs:
        bus.send(m)


BATCH_MAX = 1024  # frames taken per batch read (a burst is taken in several, in order)


class BatchNotifier(can.Notifier):
    """python-can's Notifier, reading in batches: when its thread wakes for a frame it also
    takes every frame the bus has received meanwhile (:func:`recv_batch`) and hands them all
    to the listeners, in order, before it waits again — one wake-up per burst (a sample's
    SYNC answer) instead of one per frame. Listeners, errors, ``stop`` and the registry are
    python-can's; only the receive loop differs. ``wakeups`` counts the waits that returned
    a frame, ``frames`` the frames handed on."""

    def __init__(self, bus: can.BusABC, listeners: Any, timeout: float = 1.0) -> None:
        self.wakeups = 0
        self.frames = 0
        super().__init__(bus, listeners, timeout)

    def _rx_thread(self, bus: can.BusABC) -> None:
        if self._loop is not None:  # (an asyncio loop: python-can's own loop)
            super()._rx_thread(bus)
            return
        listeners = self.listeners  # (python-can changes this list in place)
        lock = self._lock
        timeout = self.timeout
        while not self._stopped:
            try:
                msg = bus.recv(timeout)
            except Exception as exc:  # a read failed
                self._failed(exc)
                continue
            if msg is None:
                continue
            self.wakeups += 1
            with lock:
                batch = [msg]
                while batch:
                    for m in batch:
                        try:
                            for cb in listeners:
                                cb(m)
                        except Exception as exc:  # the rest of the batch still goes on
                            self._failed(exc)
                    self.frames += len(batch)
                    try:
                        batch = recv_batch(bus, BATCH_MAX)  # what came meanwhile
                    except Exception as exc:
                        self._failed(exc)
                        batch = []

    def _failed(self, exc: Exception) -> None:
        """As python-can's loop: kept in ``exception``; raised unless a listener handled it."""
        self.exception = exc
        if not self._on_error(exc):
            raise exc
        log.debug("suppressed exception: %s", exc)


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
