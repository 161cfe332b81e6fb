"""One node verifier for boot and ``rsra nodes`` (docs/bus.md §3, boot step 2, without writes).

Over SDO: 0x1000 (device type), 0x1018 (vendor, product, revision compared; the serial number
identifies one physical unit and is reported, never compared) and every TPDO's COB-ID,
transmission type and mapping against the node's EDS defaults. The master's boot stops at the
first :class:`Mismatch` (``first_only=True``, raised as a ``BootError``); ``rsra nodes`` lists
them all.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import canopen
from canopen.objectdictionary import ODVariable

from rsra.daq.bus.decoder import TPDO_COMM, TPDO_MAP, NodeLayout, od_variable

COB_RTR_NOT_ALLOWED = 1 << 30  # a device may report it in 0x18xx:1; not part of the contract
IDENTITY_NAMES = {1: "vendor-ID", 2: "product code", 3: "revision number", 4: "serial number"}
# The serial number identifies one physical unit: reported, never compared with the EDS.
IDENTITY_COMPARED = (1, 2, 3)


def fmt_value(v: Any) -> str:
    return f"0x{v:08X}" if isinstance(v, int) else repr(v)


@dataclass(frozen=True)
class Mismatch:
    """One object that does not agree with the EDS (or cannot be read: ``problem``;
    ``timeout`` when the node did not answer at all)."""

    object: str
    expected: Any = None
    actual: Any = None
    problem: str = ""
    timeout: bool = False

    def text(self) -> str:
        if self.problem:
            return f"{self.object} {self.problem}"
        return (f"{self.object} reads {fmt_value(self.actual)}, the EDS says "
                f"{fmt_value(self.expected)}")

    def to_dict(self) -> dict:
        return {"object": self.object, "expected": self.expected, "actual": self.actual,
                "problem": self.problem or None, "text": self.text()}


@dataclass
class NodeFacts:
    """What the verification read: whether the node answered SDO, its device type and
    identity (by name), and every mismatch found (at most one with ``first_only``)."""

    sdo: bool = False
    device_type: int | None = None
    identity: dict[str, int] = field(default_factory=dict)
    mismatches: list[Mismatch] = field(default_factory=list)


class _Stop(Exception):
    """The first mismatch, when only the first is wanted."""


def verify_node(nl: NodeLayout, node: canopen.RemoteNode, *,
                first_only: bool = False) -> NodeFacts:
    """Verify one node against its EDS (see the module docstring). A node silent over SDO
    (timeout on 0x1000) ends the check with that one timeout mismatch."""
    facts = NodeFacts()
    v = _Verifier(nl, node, facts, first_only)
    try:
        v.run()
    except _Stop:
        pass
    return facts


class _Verifier:
    def __init__(self, nl: NodeLayout, node: canopen.RemoteNode, facts: NodeFacts,
                 first_only: bool):
        self.nl, self.node, self.facts, self.first_only = nl, node, facts, first_only

    def _add(self, m: Mismatch) -> None:
        self.facts.mismatches.append(m)
        if self.first_only:
            raise _Stop

    def _read(self, index: int, sub: int, name: str) -> int | None:
        """One SDO upload decoded with the EDS data type; None (and a mismatch) when it
        cannot be read."""
        try:
            data = self.node.sdo.upload(index, sub)
        except canopen.SdoAbortedError as e:
            self._add(Mismatch(name, problem=f"cannot be read: SDO abort {e}"))
            return None
        except canopen.SdoCommunicationError as e:
            self._add(Mismatch(name, problem=f"cannot be read: {e}", timeout=True))
            return None
        return int(od_variable(self.nl.od, index, sub).decode_raw(data))

    def _compare(self, index: int, sub: int, name: str, expected: int | None,
                 mask: int = ~0) -> int | None:
        """Read and compare with the EDS default ``expected`` (None: the EDS gives none,
        nothing to compare)."""
        value = self._read(index, sub, name)
        if value is not None and expected is not None and value & mask != expected & mask:
            self._add(Mismatch(name, expected, value))
        return value

    def run(self) -> None:
        nl, facts = self.nl, self.facts
        try:
            dev = self.node.sdo.upload(0x1000, 0)
        except canopen.SdoCommunicationError as e:  # silent: nothing else will answer either
            self._add(Mismatch("0x1000 (device type)", problem=f"cannot be read: {e}",
                               timeout=True))
            return
        except canopen.SdoAbortedError as e:
            facts.sdo = True
            self._add(Mismatch("0x1000 (device type)",
                               problem=f"cannot be read: SDO abort {e}"))
            dev = None
        else:
            facts.sdo = True
            dev = int(od_variable(nl.od, 0x1000, 0).decode_raw(dev))
        facts.device_type = dev
        if dev is not None and dev != nl.device_type:
            self._add(Mismatch("0x1000 (device type)", nl.device_type, dev))
        for sub, expected in nl.identity.items():
            label = IDENTITY_NAMES.get(sub, str(sub))
            name = f"0x1018:{sub} ({label})"
            if sub in IDENTITY_COMPARED:
                value = self._compare(0x1018, sub, name, expected)
            else:
                value = self._read(0x1018, sub, name)
            if value is not None:
                facts.identity[label] = value
        for index in sorted(i for i in nl.od.indices if TPDO_COMM <= i < TPDO_COMM + 512):
            self._tpdo(index - TPDO_COMM)

    def _tpdo(self, k: int) -> None:
        nl = self.nl
        comm = nl.od[TPDO_COMM + k]
        if isinstance(comm, ODVariable):
            return  # not a communication record (a damaged EDS): no TPDO in the decode table
        n = k + 1
        for sub, what in ((1, "COB-ID"), (2, "transmission type")):
            if sub in comm:
                mask = ~COB_RTR_NOT_ALLOWED if sub == 1 else ~0  # bit 30: the device's business
                self._compare(TPDO_COMM + k, sub,
                              f"0x{TPDO_COMM + k:04X}:{sub} (TPDO{n} {what})",
                              comm[sub].default, mask)
        if TPDO_MAP + k not in nl.od:
            return
        mapping = nl.od[TPDO_MAP + k]
        if isinstance(mapping, ODVariable):
            return  # not a mapping record (a damaged EDS): no entries to compare
        count = self._compare(TPDO_MAP + k, 0,
                              f"0x{TPDO_MAP + k:04X}:0 (TPDO{n} number of mapped objects)",
                              mapping[0].default)
        if count is None or count != mapping[0].default:
            return  # entries of a different mapping cannot be compared one by one
        for s in range(1, count + 1):
            self._compare(TPDO_MAP + k, s,
                          f"0x{TPDO_MAP + k:04X}:{s} (TPDO{n} mapped object {s})",
                          mapping[s].default)
