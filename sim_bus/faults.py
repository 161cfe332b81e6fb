"""Fault injection for the simulated aircraft bus (task: bus faults; docs/simulator.md "Faults").

A fault SPEC is a ``;``-separated list of items ``KIND[:ARG…][@WHEN]``::

    drop:cell_A:0.1;reboot:cell_C@12.5;silent:accel_1@20-22;jitter:0.5ms

WHEN is simulated (sample) time in seconds: ``@T`` (an instant for ``reboot``; "from T on"
for the window kinds), ``@T1-T2`` (the window [T1, T2)); without it a fault lasts the whole
run. Probabilities are per opportunity (``0.1`` or ``10%``); durations take ``s``, ``ms`` or
``us``. NODE is a configured node name, or ``*`` for every node where that makes sense.

=============================  ===============================================================
``drop:NODE:P``                each TPDO of NODE is lost with probability P
``malformed:NODE:P``           a TPDO of NODE goes out one byte short (wrong length), prob. P
``stuck:NODE[.CHANNEL]``       the channel(s) hold the value they had when the fault began
``overrange:NODE``             load cell: status bit 0 set, force at ±full scale, EMCY
``sensor:NODE``                load cell: status bit 1 (sensor fault), EMCY
``silent:NODE``                the node sends nothing and hears nothing (unplugged)
``reboot:NODE@T``              power cycle at T: boot-up, pre-operational, waits for NMT start
``unknown[:COBID]:P``          per SYNC, a frame on a COB-ID no configured node uses, prob. P
``lostsync:P``                 (--autostart) the SYNC of a cycle is lost, prob. P
``jitter:SIGMA``               (--autostart) SYNC time jitter, Gaussian σ (clipped to ±3σ)
``errorframe:P``               per SYNC, a CAN error frame (python-can is_error_frame), prob. P
=============================  ===============================================================

Random decisions are a pure function of (seed, fault item, sample index, slot) — a counter-
based hash, not a shared generator — so they do not depend on the order in which they are
asked, and lock-step and real-time runs inject exactly the same faults. Every injected fault
is logged (``FaultInjector.log``: dicts with sample index, time, kind, node, …) for the truth.
"""
from __future__ import annotations

import difflib
import math
import re
from collections import deque
from dataclasses import dataclass, field
from typing import IO

# EMCY error codes (CiA 301 table 21 classes) the simulated nodes raise.
EMCY_OVER_RANGE = 0xFF01  # device specific: input over range (status bit 0)
EMCY_SENSOR_FAULT = 0x5000  # device hardware: sensor fault (status bit 1)
STATUS_OVER_RANGE = 0x01  # load-cell status bits (docs/bus.md §1: 0x6150:1)
STATUS_SENSOR_FAULT = 0x02

NODE_KINDS = ("drop", "malformed", "stuck", "overrange", "sensor", "silent", "reboot")
BUS_KINDS = ("unknown", "lostsync", "jitter", "errorframe")
KINDS = NODE_KINDS + BUS_KINDS
WINDOW_KINDS = ("stuck", "overrange", "sensor", "silent")
PROBABILITY_KINDS = ("drop", "malformed", "unknown", "lostsync", "errorframe")
AUTOSTART_KINDS = ("lostsync", "jitter")
STATUS_KINDS = ("overrange", "sensor")
MAX_LOG = 1_000_000  # bounded truth log; further entries are only counted
RECENT_LOG = 1024  # without a truth file: the last entries only

_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"


class FaultSpecError(ValueError):
    """A bad fault SPEC: names the item and what is wrong with it."""

    def __init__(self, token: str, problem: str, fix: str = ""):
        self.token, self.problem = token, problem
        msg = f"fault {token!r}: {problem}"
        super().__init__(msg + (f"; {fix}" if fix else ""))


@dataclass(frozen=True)
class Fault:
    kind: str
    token: str  # the item as written, for messages and the truth
    node: str | None = None  # None: bus-level; "*": every node
    channel: str | None = None
    value: float | None = None  # probability, or jitter sigma (s)
    cob_id: int | None = None
    start: float = 0.0
    end: float = math.inf
    index: int = 0  # position in the SPEC (part of the random key)

    def active(self, t: float) -> bool:
        return self.start <= t < self.end

    def applies_to(self, node: str) -> bool:
        return self.node == "*" or self.node == node


def _duration(tok: str, text: str, what: str) -> float:
    m = re.fullmatch(rf"({_NUM})\s*(s|ms|us)?", text.strip())
    if not m:
        raise FaultSpecError(tok, f"{what} {text!r} is not a time",
                             "write seconds, e.g. 12.5, 0.5ms or 200us")
    scale = {"s": 1.0, None: 1.0, "ms": 1e-3, "us": 1e-6}[m.group(2)]
    return float(m.group(1)) * scale


def _probability(tok: str, text: str) -> float:
    m = re.fullmatch(rf"({_NUM})\s*(%)?", text.strip())
    if not m:
        raise FaultSpecError(tok, f"probability {text!r} is not a number", "write e.g. 0.1 or 10%")
    p = float(m.group(1)) / (100.0 if m.group(2) else 1.0)
    if not 0.0 <= p <= 1.0:
        raise FaultSpecError(tok, f"probability {text!r} is outside 0…1", "write e.g. 0.1 or 10%")
    return p


def _kind(tok: str, written: str) -> str:
    kind = written.lower()
    if kind not in KINDS:
        near = difflib.get_close_matches(kind, KINDS, n=1)
        raise FaultSpecError(tok, f"unknown fault kind {written!r}"
                             + (f" (did you mean {near[0]!r}?)" if near else ""),
                             "use one of " + ", ".join(KINDS))
    return kind


def _window(tok: str, kind: str, when: str) -> tuple[float, float]:
    """``@T``, ``@T1-T2`` or ``@T1-`` as (start, end); none: the whole run (a reboot needs an
    instant)."""
    if not when:
        if kind == "reboot":
            raise FaultSpecError(tok, "a reboot needs a time", "write e.g. reboot:cell_C@12.5")
        return 0.0, math.inf
    if "-" not in when:
        return _duration(tok, when, "time"), math.inf
    a, _, b = when.partition("-")
    start = _duration(tok, a, "start time")
    end = _duration(tok, b, "end time") if b.strip() else math.inf
    if end <= start:
        raise FaultSpecError(tok, f"window {when!r} ends before it starts",
                             "write @T1-T2 with T1 < T2")
    if kind == "reboot":
        raise FaultSpecError(tok, "a reboot happens at an instant", "write reboot:NODE@T")
    return start, end


def _node(tok: str, kind: str, args: list[str]) -> tuple[str, str | None]:
    """A node kind's NODE[.CHANNEL] (taken from ``args``)."""
    if not args or not args[0]:
        raise FaultSpecError(tok, "needs a node", f"write e.g. {kind}:cell_A…")
    node, dot, channel = args.pop(0).partition(".")
    if not dot:
        return node, None
    if kind != "stuck":
        raise FaultSpecError(tok, "only stuck takes a channel", f"write {kind}:{node}")
    return node, channel


def _cob_id(tok: str, args: list[str]) -> int:
    """``unknown:COBID:P``'s COB-ID (taken from ``args``)."""
    try:
        cob = int(args.pop(0), 0)
    except ValueError:
        raise FaultSpecError(tok, "COB-ID is not a number", "write e.g. unknown:0x1FF:0.05") from None
    if not 0 < cob <= 0x7FF:
        raise FaultSpecError(tok, f"COB-ID 0x{cob:X} is not an 11-bit identifier",
                             "use 0x001…0x7FF")
    return cob


_VALUE_EXAMPLES = {"jitter": "jitter:0.5ms", "drop": "drop:cell_A:0.1",
                   "malformed": "malformed:cell_A:0.01", "unknown": "unknown:0.05"}


def _value(tok: str, kind: str, args: list[str]) -> float | None:
    """The probability (or jitter's σ) the kind takes as its last argument; no other
    argument is left."""
    if kind not in PROBABILITY_KINDS and kind != "jitter":
        if args:
            raise FaultSpecError(tok, f"unexpected argument(s) {':'.join(args)!r}",
                                 f"write {kind}:NODE[@WHEN]")
        return None
    if len(args) != 1:
        what = "a standard deviation" if kind == "jitter" else "a probability"
        raise FaultSpecError(tok, f"needs {what}",
                             f"write e.g. {_VALUE_EXAMPLES.get(kind, f'{kind}:0.01')}")
    if kind == "jitter":
        return _duration(tok, args[0], "standard deviation")
    return _probability(tok, args[0])


def parse_fault(tok: str, index: int) -> Fault:
    """One item ``KIND[:ARG…][@WHEN]`` of a SPEC, at ``index`` in it."""
    body, _, when = tok.partition("@")
    parts = [p.strip() for p in body.split(":")]
    kind = _kind(tok, parts[0])
    start, end = _window(tok, kind, when)
    args = parts[1:]
    node = channel = None
    cob = None
    if kind in NODE_KINDS:
        node, channel = _node(tok, kind, args)
    elif kind == "unknown" and len(args) == 2:
        cob = _cob_id(tok, args)
    return Fault(kind=kind, token=tok, node=node, channel=channel,
                 value=_value(tok, kind, args), cob_id=cob, start=start, end=end, index=index)


def parse_faults(spec: str | None) -> tuple[Fault, ...]:
    """Parse a SPEC (syntax in the module docstring). Raises FaultSpecError naming the item."""
    if not spec or not spec.strip():
        return ()
    items = ((i, raw.strip()) for i, raw in enumerate(spec.split(";")))
    return tuple(parse_fault(tok, i) for i, tok in items if tok)


def _check_node(f: Fault, node_roles: dict[str, str]) -> None:
    if f.node is not None and f.node != "*" and f.node not in node_roles:
        near = difflib.get_close_matches(f.node, list(node_roles), n=1)
        raise FaultSpecError(f.token, f"no node {f.node!r} on the simulated bus"
                             + (f" (did you mean {near[0]!r}?)" if near else ""),
                             "nodes: " + ", ".join(node_roles))


def _check_channel(f: Fault, channels: dict[str, tuple[str, ...]]) -> None:
    if f.channel is None:
        return
    if f.node is None or f.node == "*":
        raise FaultSpecError(f.token, "a channel needs a named node", "write e.g. stuck:accel_1.z")
    if f.channel not in channels[f.node]:
        raise FaultSpecError(f.token, f"node {f.node!r} has no channel {f.channel!r}",
                             "channels: " + ", ".join(channels[f.node]))


def _check_status(f: Fault, node_roles: dict[str, str],
                  channels: dict[str, tuple[str, ...]]) -> None:
    # "*" applies a status fault to the nodes that have a status channel only
    if f.kind in STATUS_KINDS and f.node is not None and f.node != "*" \
            and "status" not in channels[f.node]:
        raise FaultSpecError(f.token, f"node {f.node!r} ({node_roles[f.node]}) has no "
                             "status channel", "use it on a load cell")


def validate_faults(faults: tuple[Fault, ...], node_roles: dict[str, str],
                    channels: dict[str, tuple[str, ...]], autostart: bool) -> None:
    """Check node and channel names against the configured nodes and the mode."""
    for f in faults:
        _check_node(f, node_roles)
        _check_channel(f, channels)
        _check_status(f, node_roles, channels)
        if f.kind in AUTOSTART_KINDS and not autostart:
            raise FaultSpecError(f.token, "the simulator produces SYNC only with --autostart",
                                 "add --autostart or drop this fault")


def _mix(x: int) -> int:
    """splitmix64 finaliser: a fast, well-mixed 64-bit hash."""
    x = (x + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return x ^ (x >> 31)


class FaultLog:
    """The injected faults' entries, bounded. ``keep`` (a truth file will be written): every
    entry up to ``max_n``, full chunks spilled (pickled) to an anonymous temporary file so
    resident memory stays flat; otherwise only the last ``recent`` (live views). ``len()`` is
    the number of entries held."""

    def __init__(self, keep: bool = True, max_n: int = MAX_LOG, recent: int = RECENT_LOG,
                 chunk: int = 1024):
        self.keep = keep
        self.maxlen = int(max_n) if keep else int(recent)
        self.chunk = int(chunk)
        self._mem: deque = deque(maxlen=None if keep else self.maxlen)
        self._spilled = 0
        self._file: IO[bytes] | None = None

    def __len__(self) -> int:
        return self._spilled + len(self._mem)

    def append(self, entry: dict) -> bool:
        """Keep ``entry``; False when the log is full (keep) and it was not kept."""
        if self.keep:
            if len(self) >= self.maxlen:
                return False
            self._mem.append(entry)
            if len(self._mem) >= self.chunk:
                self._spill()
            return True
        full = len(self._mem) == self.maxlen
        self._mem.append(entry)  # a ring: the oldest goes
        return not full

    def _spill(self) -> None:
        import pickle
        import tempfile

        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="rsra-faults-")  # noqa: SIM115 (lives with the log)
        self._file.seek(0, 2)
        pickle.dump(list(self._mem), self._file, protocol=pickle.HIGHEST_PROTOCOL)
        self._spilled += len(self._mem)
        self._mem.clear()

    def __iter__(self):
        if self._file is not None:
            import pickle

            self._file.seek(0)
            n = 0
            while n < self._spilled:
                part = pickle.load(self._file)
                n += len(part)
                yield from part
        yield from list(self._mem)


@dataclass
class FaultInjector:
    """Runtime side of a fault plan: windows, instants and random draws by sample, and the log."""

    faults: tuple[Fault, ...]
    seed: int = 0
    log: FaultLog = field(default_factory=FaultLog)
    dropped_log_entries: int = 0
    counts: dict = field(default_factory=dict)  # entries by kind, all of them (bounded: kinds)
    _prev_t: float = -math.inf
    _active: set = field(default_factory=set)

    def __post_init__(self) -> None:
        self._seed = _mix(int(self.seed) & 0xFFFFFFFFFFFFFFFF)
        self.by_kind: dict[str, list[Fault]] = {}
        for f in self.faults:
            self.by_kind.setdefault(f.kind, []).append(f)

    def __bool__(self) -> bool:
        return bool(self.faults)

    def uniform(self, fault: Fault, sample: int, slot: int = 0) -> float:
        """A uniform in [0, 1) that depends only on (seed, fault, sample, slot)."""
        h = _mix(self._seed ^ _mix((fault.index << 40) ^ (sample << 8) ^ slot))
        return (h >> 11) * (1.0 / (1 << 53))

    def record(self, sample: int, t: float, kind: str, node: str | None, **extra) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if not self.log.append({"sample": int(sample), "t": float(t), "kind": kind,
                                "node": node, **extra}):
            self.dropped_log_entries += 1

    @property
    def events(self) -> int:
        """Entries recorded since the start (kept or not)."""
        return sum(self.counts.values())

    def of(self, kind: str) -> list[Fault]:
        return self.by_kind.get(kind, [])

    def window_changes(self, sample: int, t: float, nodes: list[str]) -> list[tuple[Fault, str, bool]]:
        """Window faults that begin or end at this sample: (fault, node, started)."""
        out = []
        for kind in WINDOW_KINDS:
            for f in self.of(kind):
                now = f.active(t)
                for n in nodes:
                    if not f.applies_to(n):
                        continue
                    key = (f.index, n)
                    was = key in self._active
                    if now and not was:
                        self._active.add(key)
                        out.append((f, n, True))
                    elif was and not now:
                        self._active.discard(key)
                        out.append((f, n, False))
        return out

    def active(self, kind: str, node: str, channel: str | None = None) -> Fault | None:
        for f in self.of(kind):
            if (f.index, node) in self._active and (channel is None or f.channel in (None, channel)):
                return f
        return None

    def reboots(self, t: float, nodes: list[str]) -> list[tuple[Fault, str]]:
        """Reboot instants crossed since the previous sample (prev < T <= t)."""
        out: list[tuple[Fault, str]] = []
        for f in self.of("reboot"):
            if self._prev_t < f.start <= t:
                out.extend((f, n) for n in nodes if f.applies_to(n))
        return out

    def end_sample(self, t: float) -> None:
        self._prev_t = t

    def chance(self, kind: str, sample: int, t: float, node: str | None = None,
               slot: int = 0) -> Fault | None:
        """The first fault of ``kind`` (for ``node``) whose draw fires at this opportunity."""
        for f in self.of(kind):
            if not f.active(t) or (node is not None and not f.applies_to(node)):
                continue
            p = f.value
            assert p is not None  # parse_faults gives every probability kind its probability
            if self.uniform(f, sample, slot) < p:
                return f
        return None

    def jitter(self, sample: int, t: float, limit: float) -> float:
        """Sum of the active jitter faults' Gaussian offsets (Box–Muller), clipped to ±3σ and
        to ±limit (so SYNCs never swap order)."""
        total = 0.0
        for f in self.of("jitter"):
            if not f.active(t) or not f.value:
                continue
            u1 = 1.0 - self.uniform(f, sample, 1)  # (0, 1]
            u2 = self.uniform(f, sample, 2)
            z = math.sqrt(-2.0 * math.log(u1)) * math.cos(2 * math.pi * u2)
            total += max(-3.0, min(3.0, z)) * f.value
        return max(-limit, min(limit, total))

    def payload(self, sample: int, slot: int, n: int = 8) -> bytes:
        return _mix(self._seed ^ (sample << 16) ^ slot).to_bytes(8, "little")[:n]
