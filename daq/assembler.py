"""Sample assembly by frame order alone (spec bus.md "SYNC and samples").

A sample is every TPDO that follows SYNC k and precedes SYNC k+1, stamped with SYNC k's
receive time rounded to 1 µs (the resolution of the recordings) and its counter. It is
complete when every required node, and every optional node seen alive, has reported; it is
then passed on at once (latency), otherwise at the next SYNC with the missing nodes flagged.
No wall-clock timer decides anything here, so a replay of the same frames assembles exactly
the same samples.

Hot path: one closure per COB-ID (subscribed with canopen's raw ``Network.subscribe``) does
``len`` check, ``Struct.unpack`` and a slice store into a list; calibration (one numpy
multiply-add over the whole sample) and the Sample object are built once per sample.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from daq.config import RigConfig
from daq.decoder import STATUS_FAULT, STATUS_OVERRANGE, DecodeTable

FrameCallback = Callable[[int, Any, float], None]
_CACHE_MAX = 256  # distinct (reported, expected) patterns remembered (bounded)


@dataclass(slots=True)
class Sample:
    """One SYNC period of calibrated channels (what the estimator consumes).

    ``seq`` counts from the first SYNC (lost samples keep their number); ``t`` is the SYNC's
    receive time in acquisition-clock seconds rounded to 1 µs; ``T`` the seven load-cell forces
    in cfg.cells order (N, nan when missing); ``accel`` the specific force of each configured
    accelerometer (K, 3) m/s²; ``flags`` from the telemetry vocabulary ("missing:<node>",
    "lost_before", "overrange:<cell>", "fault:<cell>").
    """

    seq: int
    sync: int
    t: float
    T: np.ndarray
    cell_status: dict[str, int]
    accel: np.ndarray
    omega: float | None
    azimuth: float | None
    known_H: np.ndarray | None
    drive: np.ndarray | None
    missing: tuple[str, ...]
    lost_before: int
    flags: tuple[str, ...]
    complete: bool = field(default=True)

    def channels_payload(self) -> dict:
        """The telemetry ``channels`` payload (strict JSON: non-finite -> None)."""
        return {
            "seq": self.seq, "t": self.t, "T": _json_list(self.T),
            "accel": [_json_list(a) for a in self.accel],
            "omega": _json_num(self.omega), "azimuth": _json_num(self.azimuth),
            "known_H": None if self.known_H is None else _json_list(self.known_H),
            "drive": None if self.drive is None else _json_list(self.drive),
            "status": dict(self.cell_status),
        }

    def same_as(self, other: Sample) -> bool:
        """Bit-for-bit equality of every field (nan equal to nan): replay == live."""
        for name in self.__slots__:
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                    return False
                if a.shape != b.shape or not np.array_equal(a, b, equal_nan=True):
                    return False
            elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
                continue
            elif a != b:
                return False
        return True


def _json_num(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def _json_list(a: np.ndarray) -> list:
    return [float(v) if math.isfinite(v) else None for v in a.tolist()]


class SampleAssembler:
    """Assembles samples from SYNC and TPDO frames; ``emit`` receives every Sample.

    ``callbacks()`` gives the per-COB-ID frame callbacks (``cb(can_id, data, timestamp)``),
    the SYNC one included, for canopen's ``Network.subscribe``.
    """

    def __init__(self, cfg: RigConfig, table: DecodeTable, emit: Callable[[Sample], None]):
        self.cfg, self.table, self.emit = cfg, table, emit
        self.sync_cob_id = cfg.sync.cob_id
        self.overflow = cfg.sync.counter_overflow
        n = table.n_channels
        self._template = [0.0] * n
        self._raw: list[float] = list(self._template)
        self._have = table.all_bits  # TPDO bits reported since the last SYNC (all: none yet)
        self._expect = 0  # TPDO bits that complete the current sample
        self._open = False  # the current sample is not passed on yet
        self._in_sample = False  # a SYNC has been seen
        self._sync_t = 0.0
        self._sync_counter = 0
        self._lost = 0
        self._seq = 0  # seq of the current sample
        self._next_seq = 0
        self._prev_counter: int | None = None
        self._prev_have = 0
        # counters (health)
        self.complete = 0
        self.incomplete = 0
        self.lost = 0
        self.malformed = 0
        self.duplicate = 0
        self.orphan = 0  # TPDOs before the first SYNC
        self.emitted = 0

        self._required_bits = 0
        self._optional_bits = 0
        self._node_bits: dict[str, int] = {}
        for nl in table.nodes:
            self._node_bits[nl.name] = nl.mask
            if nl.required:
                self._required_bits |= nl.mask
            else:
                self._optional_bits |= nl.mask
        self._alive_bits = 0  # optional nodes whose heartbeat says operational
        self._pattern_cache: dict[tuple[int, int], tuple] = {}

        # output index arrays (config order)
        idx = table.index
        self._T_idx = np.array([idx(f"{c.node}.force") for c in cfg.cells])
        self._status_idx = [idx(f"{c.node}.status") for c in cfg.cells]
        self._cell_names = [c.name for c in cfg.cells]
        self._cell_nodes = [c.node for c in cfg.cells]
        self._status_flags = [(f"overrange:{c.name}", f"fault:{c.name}") for c in cfg.cells]
        self._acc_idx = np.array([[idx(f"{a.node}.{ax}") for ax in "xyz"]
                                  for a in cfg.accelerometers])
        rn = cfg.rotor.node
        self._rotor = (rn, idx(f"{rn}.omega"), idx(f"{rn}.azimuth"),
                       table.channels[idx(f"{rn}.azimuth")].wrap) if rn else None
        bn = cfg.balance.node
        self._balance = (bn, np.array([idx(f"{bn}.{k}") for k in "XYZLMN"])) if bn else None
        drive = []
        for e in cfg.external_loads:
            nl = table.node(e.node)
            values = [i for i in range(nl.start, nl.stop) if not table.channels[i].is_status]
            if len(values) != 1:
                from daq.config import ConfigError
                raise ConfigError(f"external_loads[{e.name}].node", e.node,
                                  f"the node maps {len(values)} values; an external load needs one",
                                  "map exactly one value in the drive-load node's TPDOs")
            drive.append((e.node, values[0]))
        self._drive = ((tuple(n for n, _ in drive), np.array([i for _, i in drive]))
                       if drive else None)
        self._node_of_channel = np.array(
            [next(k for k, nl in enumerate(table.nodes) if nl.start <= i < nl.stop)
             for i in range(n)], dtype=int)
        self._node_names = [nl.name for nl in table.nodes]
        self._node_slices = [(nl.start, nl.stop, nl.mask) for nl in table.nodes]

    # -- liveness (from the supervisor, same thread, frame order) --------------------------
    def set_alive(self, node: str, alive: bool) -> None:
        """An optional node became operational / was lost; applies from the next SYNC."""
        bits = self._node_bits[node] & self._optional_bits
        if alive:
            self._alive_bits |= bits
        else:
            self._alive_bits &= ~bits

    # -- frame callbacks -------------------------------------------------------------------
    def callbacks(self) -> dict[int, FrameCallback]:
        cbs: dict[int, FrameCallback] = {self.sync_cob_id: self.on_sync}
        for cob, lay in self.table.tpdos.items():
            cbs[cob] = self._make_tpdo_callback(lay.length, lay.struct.unpack, lay.start,
                                                lay.stop, lay.bit)
        return cbs

    def _make_tpdo_callback(self, length: int, unpack: Callable, lo: int, hi: int,
                            bit: int) -> FrameCallback:
        raw = self._raw  # the same list object for the whole run (slice stores only)

        def on_tpdo(can_id: int, data: Any, timestamp: float) -> None:
            if len(data) != length:
                self.malformed += 1  # wrong length: counted, never passed on
                return
            have = self._have
            if have & bit:
                if self._in_sample:
                    self.duplicate += 1
                else:
                    self.orphan += 1
                return
            raw[lo:hi] = unpack(data)
            have |= bit
            self._have = have
            expect = self._expect
            if have & expect == expect and self._open:
                self._pass_on(True)

        return on_tpdo

    def on_sync(self, can_id: int, data: Any, timestamp: float) -> None:
        n = len(data)
        ov = self.overflow
        if ov:
            if n != 1 or not 1 <= data[0] <= ov:
                self.malformed += 1
                return
            counter = data[0]
        else:
            if n > 1:
                self.malformed += 1
                return
            counter = 0
        if self._open:
            self._pass_on(False)  # incomplete: passed on at the next SYNC, missing flagged
        lost = 0
        if ov and self._prev_counter is not None:
            # CiA 301 counter runs 1…overflow then restarts at 1: a skip is a lost sample
            lost = (counter - (self._prev_counter % ov + 1)) % ov
        self._prev_counter = counter
        self.lost += lost
        self._seq = self._next_seq + lost
        self._next_seq = self._seq + 1
        self._lost = lost
        self._sync_t = math.floor(timestamp * 1e6 + 0.5) / 1e6  # 1 µs, = round(t, 6)
        self._sync_counter = counter
        have = self._have if self._in_sample else 0
        # optional nodes that reported in the last period count as alive (by frame order)
        self._expect = self._required_bits | self._alive_bits | (have & self._optional_bits)
        self._prev_have = have
        self._raw[:] = self._template
        self._have = 0
        self._in_sample = True
        self._open = True
        if self._expect == 0:
            self._pass_on(True)

    # -- sample construction (once per SYNC) -----------------------------------------------
    def _pattern(self, have: int, expect: int) -> tuple:
        key = (have, expect)
        p = self._pattern_cache.get(key)
        if p is None:
            unreported = []
            missing = []
            nan_idx = []
            for name, (lo, hi, mask) in zip(self._node_names, self._node_slices):
                if have & mask != mask:
                    unreported.append(name)
                    nan_idx.extend(range(lo, hi))
                    if expect & mask:
                        missing.append(name)
            cells = tuple((name, si, fl) for name, node, si, fl in zip(
                self._cell_names, self._cell_nodes, self._status_idx, self._status_flags)
                if node not in unreported)
            p = (frozenset(unreported), tuple(missing), np.array(nan_idx, dtype=int), cells)
            if len(self._pattern_cache) >= _CACHE_MAX:
                self._pattern_cache.clear()
            self._pattern_cache[key] = p
        return p

    def _pass_on(self, complete_trigger: bool) -> None:
        self._open = False
        raw = self._raw
        unreported, missing, nan_idx, reported_cells = self._pattern(self._have, self._expect)
        cal = np.array(raw)
        cal *= self.table.gain
        cal += self.table.offset
        total = sum(raw)
        if total - total != 0.0:  # some value is inf or nan (x - x is 0 for finite x)
            bad = ~np.isfinite(cal)
            bad[nan_idx] = False
            bad_nodes = {self._node_names[k] for k in np.unique(self._node_of_channel[bad])}
            bad_nodes -= unreported
            if bad_nodes:
                # non-finite values mark the channel missing (and its node flagged)
                cal[bad] = np.nan
                missing = tuple(sorted(set(missing) | bad_nodes, key=self._node_names.index))
                unreported = unreported | bad_nodes
        if len(nan_idx):
            cal[nan_idx] = np.nan
        flags: list[str] = [f"missing:{m}" for m in missing]
        if self._lost:
            flags.append("lost_before")
        status: dict[str, int] = {}
        for name, si, (f_or, f_fault) in reported_cells:
            st = int(raw[si])
            status[name] = st
            if st:
                if st & STATUS_OVERRANGE:
                    flags.append(f_or)
                if st & STATUS_FAULT:
                    flags.append(f_fault)
        omega = azimuth = None
        if self._rotor is not None:
            rn, oi, ai, wrap = self._rotor
            if rn not in unreported:
                omega = float(cal[oi])
                azimuth = float(cal[ai]) % wrap if wrap else float(cal[ai])
        known_H = None
        if self._balance is not None and self._balance[0] not in unreported:
            known_H = cal[self._balance[1]]
        drive = None
        if self._drive is not None and not unreported.intersection(self._drive[0]):
            drive = cal[self._drive[1]]
        complete = not missing
        if complete:
            self.complete += 1
        else:
            self.incomplete += 1
        self.emitted += 1
        self.emit(Sample(
            seq=self._seq, sync=self._sync_counter, t=self._sync_t, T=cal[self._T_idx],
            cell_status=status, accel=cal[self._acc_idx], omega=omega, azimuth=azimuth,
            known_H=known_H, drive=drive, missing=missing, lost_before=self._lost,
            flags=tuple(flags), complete=complete))

    def finish(self) -> None:
        """Pass on a pending incomplete sample (end of a replay; no further SYNC will come)."""
        if self._open:
            self._pass_on(False)

    def counters(self) -> dict[str, int]:
        return {"complete": self.complete, "incomplete": self.incomplete, "lost": self.lost}
