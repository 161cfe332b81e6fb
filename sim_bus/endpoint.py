"""The simulator's end of the CAN bus: it opens (or borrows) the python-can bus and the
recording, stamps every frame with the simulator's clock, sends it, logs it, captures it for
the driver that asked, and hands the frames of the other bus users to the canopen network.

It knows nothing of nodes, physics or faults: :class:`sim_bus.bus_sim.Simulator` says what to
send and when; this sends it (docs/bus.md §4 for the frame times).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import can
import canopen

from rsra.canbus import recording_channel, send_batch, shutdown_bus
from rsra.sim_bus.nodes import COB_SDO_TX, Frame, SimNode

if TYPE_CHECKING:
    import threading

    from rsra.sim_bus.clocks import Clock

log = logging.getLogger("rsra.sim_bus.bus_sim")  # the simulator's log, as before the split

FRAME_OVERHEAD_BITS = 47  # 11-bit identifier frame without data, before stuffing (docs/bus.md §4)


class RecordError(OSError):
    """The recording file cannot be written."""


def _open_logger(path: Path) -> can.Listener:
    """python-can's writer for the file's suffix; candump .log when the suffix names none."""
    from can.io.logger import MESSAGE_WRITERS

    suffixes = [s.lower() for s in path.suffixes]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffixes and (suffixes[-1] in MESSAGE_WRITERS or (
                suffixes[-1] == ".gz" and len(suffixes) > 1 and suffixes[-2] in MESSAGE_WRITERS)):
            return can.Logger(str(path))
        return can.CanutilsLogWriter(str(path))
    except (OSError, ValueError, ImportError) as e:
        raise RecordError(f"cannot record to {path}: {e}") from e


class _TxMessage(can.Message):
    """A frame the simulator sends. python-can's virtual bus deep-copies every sent frame for
    every receiver (can/interfaces/virtual.py); copying this one builds the receiver's plain
    ``can.Message`` directly — the payload is immutable bytes and the channel a str, there is
    nothing deeper to copy — instead of ``copy.deepcopy`` recursing into both (a third of the
    send time). Receivers get what they got before: a ``can.Message`` with a bytearray."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any] | None) -> can.Message:
        data: bytes | bytearray = self.data  # bytes as built (build()), python-can types bytearray
        return can.Message(timestamp=self.timestamp, arbitration_id=self.arbitration_id,
                           is_extended_id=self.is_extended_id,
                           is_remote_frame=self.is_remote_frame,
                           is_error_frame=self.is_error_frame, channel=self.channel,
                           dlc=self.dlc, data=data if type(data) is bytes else bytes(data),
                           is_fd=self.is_fd, is_rx=self.is_rx,
                           bitrate_switch=self.bitrate_switch,
                           error_state_indicator=self.error_state_indicator)


class _SimNetwork(canopen.Network):
    """canopen's Network whose sends (LocalNode's SDO server, among others) go through the
    simulator's endpoint, so they are stamped, recorded and captured like every other frame."""

    def __init__(self, bus: can.BusABC, endpoint: BusEndpoint):
        super().__init__(bus)
        self._endpoint = endpoint

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._endpoint.transmit("sdo" if COB_SDO_TX < can_id <= COB_SDO_TX + 0x7F else "other",
                                can_id, bytes(data), None, remote=remote)


class _Logged:
    """A sent frame as the simulator's log writes it: the frame's fields with the
    recording's channel name (the frame itself, sent and perhaps captured, is unchanged)."""

    __slots__ = ("_msg", "channel")

    def __init__(self, msg: can.Message, channel: str):
        self._msg, self.channel = msg, channel

    def __getattr__(self, name: str) -> Any:
        return getattr(self._msg, name)


class _Recorder(can.Listener):
    """Frames received from the other bus users go to the endpoint's log."""

    def __init__(self, endpoint: BusEndpoint):
        self._endpoint = endpoint

    def on_message_received(self, msg: can.Message) -> None:
        self._endpoint.on_received(msg)

    def stop(self) -> None:  # the logger itself is closed by the endpoint
        pass


class BusEndpoint:
    """One python-can bus as the simulator uses it: the bus (opened here with
    ``interface``/``channel`` unless one is given, then not closed here), the canopen network
    on it, the recording (``record``: a python-can Logger by suffix, candump ``.log`` when the
    suffix is not a log format), the frame counters, and the frames captured for the caller
    of :meth:`captured`. Every send stamps the frame with ``clock`` (its transmission time at
    ``bitrate``) under ``lock``."""

    def __init__(self, clock: Clock, lock: threading.RLock, bitrate: int, *,
                 bus: can.BusABC | None = None, interface: str = "virtual",
                 channel: str = "rsra", record: str | Path | None = None):
        #: the simulator's time base: stamps every frame
        self.clock = clock
        #: shared with the simulator (the drivers' threads and the caller's take turns)
        self.lock = lock
        #: bit/s: a frame's transmission time (docs/bus.md §4)
        self.bitrate = bitrate
        #: the recording's writer (None: no recording)
        self.logger: can.Listener | None = None
        if record is not None:  # before the bus: a bad path must not leak an open bus
            self.logger = _open_logger(Path(record))
        #: the bus was opened here (and is closed here)
        self.own_bus = bus is None
        if bus is None:
            kw: dict[str, Any] = {"interface": interface, "channel": channel}
            if interface == "virtual":
                kw.update(preserve_timestamps=True, receive_own_messages=False)
            try:
                bus = can.Bus(**kw)
            except BaseException:
                if self.logger is not None:
                    self.logger.stop()
                raise
        self.bus: can.BusABC = bus
        #: the channel name the sent frames carry
        self.channel = str(getattr(bus, "channel_id", None) or getattr(bus, "channel", None)
                           or channel)
        #: the name its recording writes on every frame: the interface's channel when it is a
        #: real interface's name (vcan0), else "sim" (a virtual bus's generated name, a URL)
        self.log_channel = recording_channel(
            interface, self.channel, sim=interface in ("virtual", "remote")
            or recording_channel(interface, self.channel) != self.channel)
        #: canopen's network on the bus (nodes attach to it; its sends come back here)
        self.network = _SimNetwork(bus, self)
        self.network.listeners.append(_Recorder(self))  # type: ignore[arg-type]  # canopen's list takes any can.Listener (its type is inferred from its first, a MessageListener)
        #: when the recording was last flushed (the clock's time)
        self.last_flush = self.clock.now()
        #: the frames sent while a :meth:`captured` call runs (None: not capturing)
        self.capture: list[can.Message] | None = None
        #: frames sent, received from the other users, and error frames among those
        self.frames_sent = 0
        self.frames_received = 0
        self.error_frames_received = 0
        #: the first exception a bus callback hit (re-raised by :meth:`check`)
        self.error: BaseException | None = None

    def close(self) -> None:
        """Close the recording and (if opened here) the bus."""
        if self.logger is not None:
            self.logger.stop()
            self.logger = None
        if self.own_bus:
            shutdown_bus(self.bus)

    # ------------------------------------------------------------------------------------------
    # callbacks: canopen only logs exceptions in them (docs/bus.md §6 "Library pitfalls")
    def guard(self, fn: Callable) -> Callable:
        """``fn`` as a bus callback: keep its first exception and re-raise it in the caller's
        thread at the next :meth:`check`."""
        def wrapped(*a, **kw):
            try:
                return fn(*a, **kw)
            except Exception as e:  # noqa: BLE001 - re-raised by check()
                log.exception("simulator callback failed")
                if self.error is None:
                    self.error = e
        return wrapped

    def check(self) -> None:
        """Raise the first exception a bus callback hit."""
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    # ------------------------------------------------------------------------------------------
    # transmission
    def frame_time(self, nbytes: int) -> float:
        return (FRAME_OVERHEAD_BITS + 8 * nbytes) / self.bitrate

    def transmit(self, kind: str, cob_id: int, data: bytes, t: float | None, *,
                 remote: bool = False, error: bool = False) -> can.Message:
        """Build, stamp (at ``t``; None: now) and send one frame."""
        with self.lock:
            ts = self.clock.stamp(t, self.frame_time(len(data)))
            msg = self.build(cob_id, data, error, remote=remote)
            msg.timestamp = ts
            self.emit(msg)
            return msg

    def transmit_many(self, frames: list[tuple[int, bytes, bool]], t: float | None) -> None:
        """Build, stamp (each at ``t`` as :meth:`transmit` stamps, in order) and send
        ``frames`` ((cob_id, data, error) each) in one call where the bus allows
        (rsra.canbus.send_batch: a receiver waiting on the in-process virtual bus wakes once
        for all of them). The frames, their stamps and the recording are :meth:`transmit`'s
        one at a time."""
        if not frames:
            return
        with self.lock:
            stamp, frame_time, build = self.clock.stamp, self.frame_time, self.build
            msgs: list[can.Message] = []
            for cob_id, data, error in frames:
                msg = build(cob_id, data, error)
                msg.timestamp = stamp(t, frame_time(len(data)))
                msgs.append(msg)
            self._sent(msgs)

    def build(self, cob_id: int, data: bytes, error: bool = False, *,
              remote: bool = False) -> _TxMessage:
        """The message to send (built at the SYNC by :meth:`transmit`, or ahead of it)."""
        msg = _TxMessage(timestamp=0.0, arbitration_id=cob_id, data=data, is_extended_id=False,
                         is_remote_frame=remote, is_error_frame=error, channel=self.channel,
                         is_rx=False, check=False)
        if not remote:
            # an immutable payload: python-can's virtual bus deep-copies every frame for
            # every receiver, and bytes copy as themselves where a bytearray goes through
            # copyreg (half the send time); receivers still get a bytearray
            msg.data = bytes(msg.data)  # type: ignore[assignment]  # python-can types the payload bytearray; it takes any bytes-like
        return msg

    def send_built_many(self, msgs: list[can.Message]) -> None:
        """Send messages built ahead, in order, each stamped now as :meth:`transmit` stamps,
        in one call where the bus allows (rsra.canbus.send_batch: a receiver waiting on the
        in-process virtual bus wakes once for all of them)."""
        stamp, frame_time = self.clock.stamp, self.frame_time
        for msg in msgs:
            msg.timestamp = stamp(None, frame_time(len(msg.data)))
        self._sent(msgs)

    def _sent(self, msgs: list[can.Message]) -> None:
        """Send stamped messages in one call where the bus allows; count, record, capture."""
        send_batch(self.bus, msgs)
        self.frames_sent += len(msgs)
        if self.logger is not None:  # under the recording's one channel name, as emit()
            for msg in msgs:
                self.logger.on_message_received(_Logged(msg, self.log_channel))  # type: ignore[arg-type]  # a stand-in: the frame with the recording's channel
        if self.capture is not None:
            self.capture.extend(msgs)

    def emit(self, msg: _TxMessage) -> None:
        self.bus.send(msg)
        self.frames_sent += 1
        if self.logger is not None:
            self.logger.on_message_received(_Logged(msg, self.log_channel))  # type: ignore[arg-type]  # a stand-in: the frame with the recording's channel
        if self.capture is not None:
            self.capture.append(msg)

    def send_frame(self, fr: Frame, t: float | None, node: SimNode | None) -> can.Message | None:
        """A node's frame (nothing when the node is silenced)."""
        if node is not None and node.silent:
            return None
        return self.transmit(fr.kind, fr.cob_id, fr.data, t)

    def captured(self, fn: Callable[..., None], *args: Any, **kw: Any) -> list[can.Message]:
        """Run ``fn`` and return the frames sent meanwhile."""
        with self.lock:
            out: list[can.Message] = []
            self.capture = out
            try:
                fn(*args, **kw)
            finally:
                self.capture = None
        return out

    def flush_if_due(self, t: float) -> None:
        """Flush the recording once a second of clock time."""
        if self.logger is not None and t - self.last_flush >= 1.0:
            self.last_flush = t
            f = getattr(self.logger, "file", None)
            if f is not None and hasattr(f, "flush"):
                f.flush()

    # ------------------------------------------------------------------------------------------
    # reception
    def on_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames_received += 1
            if msg.is_error_frame:
                self.error_frames_received += 1
            if self.logger is not None:
                msg.channel = self.log_channel  # one name for the whole recording
                self.logger.on_message_received(msg)

    def pump(self) -> int:
        """Handle every frame already queued on the bus, in order, in this thread (a driver
        without a Notifier reading the bus). Returns the number handled."""
        n = 0
        while True:
            msg = self.bus.recv(0.0)
            if msg is None:
                return n
            n += 1
            for listener in self.network.listeners:
                listener.on_message_received(msg)
            self.check()
