"""How the fault plan acts on one SYNC cycle of the simulated aircraft (docs/simulator.md
"Faults"): the windows that open or close and the reboots at a sample, the node-level faults
on each node's process image (stuck, over-range, sensor) and the EMCY they cause, the SYNC's
jitter and loss, and the bus-level draws on the frames of the answer (drop, malformed,
unknown, error frame).

:class:`sim_bus.faults.FaultInjector` decides (pure functions of seed, sample and slot) and
keeps the log; this applies its decisions to the nodes and frames. The bus-level draws come
out as a list of actions, so the same sequence serves an answer sent at its SYNC and one built
ahead of it (``Simulator.prepare_next``).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Literal, Union

from rsra.sim_bus.faults import (
    EMCY_OVER_RANGE,
    EMCY_SENSOR_FAULT,
    STATUS_OVER_RANGE,
    STATUS_SENSOR_FAULT,
    WINDOW_KINDS,
    Fault,
    FaultInjector,
)
from rsra.sim_bus.nodes import OPERATIONAL, PRE_OPERATIONAL, Frame, SimNode

if TYPE_CHECKING:
    from rsra.sim_bus.nodeset import NodeFeed, NodeSet

# (status bit, EMCY code) pairs the load-cell status drives
_STATUS_EMCY = ((STATUS_OVER_RANGE, EMCY_OVER_RANGE), (STATUS_SENSOR_FAULT, EMCY_SENSOR_FAULT))

#: one step of a SYNC's answer, in order: ("rec", args, kwargs) a fault-log entry
#: (FaultInjector.record), ("send", node or None, cob_id, data, error) a frame
Action = Union[tuple[Literal["rec"], tuple[Any, ...], dict[str, Any]],
               tuple[Literal["send"], Union[SimNode, None], int, bytes, bool]]


class FaultApplier:
    """The fault plan ``faults`` applied to the nodes of ``nodes`` (module docstring).
    ``unknown_cob`` is the COB-ID an ``unknown`` fault without one uses."""

    def __init__(self, faults: FaultInjector, nodes: NodeSet, unknown_cob: int):
        #: the plan: decisions and the log
        self.faults = faults
        self._nodes = nodes
        self._unknown_cob = unknown_cob
        #: a stuck channel's value, held from when its fault began: (fault, node, channel)
        self._frozen: dict[tuple[int, str, str], int | float | None] = {}

    def __bool__(self) -> bool:
        return bool(self.faults)

    # ------------------------------------------------------------------------------------------
    # the SYNC itself
    def sync_plan(self, k: int, dt: float) -> tuple[float, bool]:
        """The SYNC jitter and loss of cycle k: a function of (seed, k) only, so real time and
        lock-step agree."""
        t = k * dt
        fi = self.faults
        jitter = fi.jitter(k, t, 0.45 * dt) if fi.of("jitter") else 0.0
        lost = fi.chance("lostsync", k, t) is not None
        return jitter, lost

    # ------------------------------------------------------------------------------------------
    # the timeline at a sample
    def timeline(self, k: int, st: float, t: float) -> tuple[list[tuple[Fault, SimNode]],
                                                           list[tuple[SimNode, Frame]]]:
        """The windows that open or close at sample ``k`` (time ``st``) and the reboots since
        the previous one, logged and applied (silenced nodes, reset nodes): the faults started
        (for :meth:`node_faults`) and the reset nodes' frames to send at ``t``."""
        fi, by_name, names = self.faults, self._nodes.by_name, self._nodes.names
        started = []
        for f, name, on in fi.window_changes(k, st, names):
            node = by_name[name]
            if f.kind in ("overrange", "sensor") and "status" not in node.channel_names:
                continue
            fi.record(k, st, f.kind, name, event="start" if on else "end",
                      channel=f.channel, spec=f.token)
            if f.kind == "silent":
                node.silent = on
            if on:
                started.append((f, node))
        pre: list[tuple[SimNode, Frame]] = []
        for f, name in fi.reboots(st, names):
            node = by_name[name]
            fi.record(k, st, "reboot", name, event="inject", spec=f.token)
            pre.extend((node, fr) for fr in node.reset(False, t))
        return started, pre

    def changes_at(self, st: float) -> bool:
        """A window fault begins or ends, or a node reboots, at sample time ``st``
        (:meth:`timeline` would act), without changing the injector."""
        fi, nodes = self.faults, self._nodes.nodes
        for kind in WINDOW_KINDS:
            for f in fi.of(kind):
                now = f.active(st)
                for n in nodes:
                    if f.applies_to(n.name) and now != ((f.index, n.name) in fi._active):
                        return True
        return bool(fi.reboots(st, self._nodes.names))

    # ------------------------------------------------------------------------------------------
    # the process image
    def node_faults(self, feed: NodeFeed, started: list[tuple[Fault, SimNode]]) -> None:
        """The node-level faults on ``feed``'s node's process image: stuck channels hold
        their value, an over-range reads full scale, status bits set."""
        node = feed.node
        for f, n in started:  # a stuck channel holds the value it had when the fault began
            if n is node and f.kind == "stuck":
                for ch in self._stuck_channels(f, node):
                    self._frozen[(f.index, node.name, ch)] = node.raw(ch)
        self._hold_stuck(node)
        if "status" in node.channel_names:
            self._status_faults(feed)

    @staticmethod
    def _stuck_channels(f: Fault, node: SimNode) -> list[str]:
        """The channels a stuck fault holds: its own, or every value channel of the node."""
        return [f.channel] if f.channel else [c for c in node.channel_names if c != "status"]

    def _hold_stuck(self, node: SimNode) -> None:
        """Each active stuck fault's channels back to the values they were frozen at."""
        fi = self.faults
        for f in fi.of("stuck"):
            if (f.index, node.name) not in fi._active:
                continue
            for ch in self._stuck_channels(f, node):
                v = self._frozen.get((f.index, node.name, ch))
                if v is not None:
                    node.set_raw(ch, v)

    def _status_faults(self, feed: NodeFeed) -> None:
        """An over-range reads full scale with its status bit; a sensor fault sets its bit."""
        fi, node = self.faults, feed.node
        status = int(node.raw("status") or 0)
        if fi.active("overrange", node.name) is not None:
            status |= STATUS_OVER_RANGE
            force = node.raw("force") or 0.0
            node.set_raw("force", math.copysign(feed.full_scale or abs(force), force))
        if fi.active("sensor", node.name) is not None:
            status |= STATUS_SENSOR_FAULT
        node.set_raw("status", status)

    @staticmethod
    def status_emcy(feed: NodeFeed) -> list[Frame]:
        """EMCY when a status bit appears or clears (CiA 301: only in pre-op or operational)."""
        node = feed.node
        if "status" not in node.channel_names or node.state not in (PRE_OPERATIONAL, OPERATIONAL):
            return []
        status = int(node.raw("status") or 0)
        out = [_status_change(node, status, bit, code) for bit, code in _STATUS_EMCY]
        return [fr for fr in out if fr is not None]

    # ------------------------------------------------------------------------------------------
    # the answer's frames
    def on_frames(self, frames: list[tuple[SimNode, Frame]], k: int, st: float) -> list[Action]:
        """The answer to SYNC ``k`` (time ``st``): ``frames`` (in bus order) through the
        bus-level draws — a TPDO dropped or sent one byte off, then an unknown frame and an
        error frame — as the log entries and frames to send, in order. Silent nodes send
        nothing."""
        acts: list[Action] = []
        for node, fr in frames:
            if node.silent:
                continue
            data: bytes | None = fr.data
            if fr.kind == "tpdo" and self.faults:
                data = self._tpdo_draws(node, fr, k, st, acts)
            if data is not None:
                acts.append(("send", node, fr.cob_id, data, False))
        if self.faults:
            acts += self._bus_draws(k, st)
        return acts

    def _tpdo_draws(self, node: SimNode, fr: Frame, k: int, st: float,
                    acts: list[Action]) -> bytes | None:
        """A TPDO's data after its draws (None: dropped), their log entries onto ``acts``."""
        fi = self.faults
        if fi.chance("drop", k, st, node.name, slot=fr.cob_id) is not None:
            acts.append(("rec", (k, st, "drop", node.name), {"cob_id": fr.cob_id, "tpdo": fr.tpdo}))
            return None
        data = fr.data
        if fi.chance("malformed", k, st, node.name, slot=0x1000 | fr.cob_id) is not None:
            data = data[:-1] if len(data) > 1 else data + b"\x00"
            acts.append(("rec", (k, st, "malformed", node.name),
                         {"cob_id": fr.cob_id, "tpdo": fr.tpdo, "length": len(data),
                          "expected": len(fr.data)}))
        return data

    def _bus_draws(self, k: int, st: float) -> list[Action]:
        """After the nodes' frames: an unknown frame, then an error frame, each when drawn."""
        fi = self.faults
        acts: list[Action] = []
        f = fi.chance("unknown", k, st, slot=0x2000)
        if f is not None:
            cob = f.cob_id if f.cob_id is not None else self._unknown_cob
            acts.append(("rec", (k, st, "unknown", None), {"cob_id": cob}))
            acts.append(("send", None, cob, fi.payload(k, 0x2000), False))
        if fi.chance("errorframe", k, st, slot=0x3000) is not None:
            acts.append(("rec", (k, st, "errorframe", None), {}))
            acts.append(("send", None, 0, b"", True))
        return acts


def _status_change(node: SimNode, status: int, bit: int, code: int) -> Frame | None:
    """The EMCY of one status bit: raised when it appears, cleared when it goes (None when
    neither)."""
    if status & bit and not node.has_error(code):
        return node.raise_error(code, info=bytes([status]))
    if not status & bit and node.has_error(code):
        return node.clear_error(code)
    return None
