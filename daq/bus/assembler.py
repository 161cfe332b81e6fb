"""Sample assembly by frame order alone (docs/bus.md §2 "SYNC and samples").

A sample is every TPDO that follows SYNC k and precedes SYNC k+1, stamped with SYNC k's
receive time rounded to 1 µs (the resolution of the recordings) and its counter. It is
complete when every required node, and every optional node seen alive, has reported; it is
then passed on at once (latency), otherwise at the next SYNC with the missing nodes flagged.
No wall-clock timer decides anything here, so a replay of the same frames assembles exactly
the same samples.

Hot path: one closure per COB-ID (subscribed with canopen's raw ``Network.subscribe``) does
the ``len`` and duplicate checks and keeps the frame; one ``struct`` unpack of the whole
sample, the calibration (one numpy multiply-add) and the Sample object are built once per
sample, with everything that depends only on which nodes reported cached per pattern.
"""
from __future__ import annotations

import logging
import math
import operator
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq import stagetiming
from rsra.daq.bus.decoder import STATUS_FAULT, STATUS_OVERRANGE, DecodeTable
from rsra.daq.bus.reorder import DISCONTINUITY_S
from rsra.daq.jsonout import sanitise

log = logging.getLogger(__name__)

FrameCallback = Callable[[int, Any, float], None]
_CACHE_MAX = 256  # distinct (reported, expected) patterns remembered (bounded)
# a SYNC stamped DISCONTINUITY_S before the last one, with a counter that does not follow it
# (or followed by frames at its time), is a discontinuity (time went back: recordings joined,
# a clock stepped back), not a bad stamp: far above any delay of a frame, far below the gap of
# a recording replayed after itself (one constant with the replay's reorder stage)
# SYNCs further apart than this are a gap (the SYNC producer — the service itself, or the
# bus — stalled or paused): counted with its length, whatever else the counter says
GAP_S = 1.0
GAP_LOG_MAX = 10  # gaps logged per run (all are counted)
TIME_TOLERANCE_PERIODS = 4  # "a few periods": a frame time further than this from where the
#                             SYNC counter puts it is a bad timestamp (docs/reliability.md)


def _unpack_kernel() -> Callable[..., Any] | None:
    """The compiled decode (rsra.daq._hubkernel.unpack_cal), or None: not built, or
    ``RSRA_HUB_KERNEL=off`` (the pure-Python path, as for the hub path)."""
    if os.environ.get("RSRA_HUB_KERNEL", "").lower() == "off":
        return None
    try:
        from rsra.daq import _hubkernel
    except ImportError:
        return None
    f: Callable[..., Any] | None = getattr(_hubkernel, "unpack_cal", None)
    return f


class SyncClock:
    """Where each SYNC is in time, from its counter and its frame time (docs/reliability.md
    "SYNC counter and frame times"). Frame order only, no wall clock.

    * A SYNC whose counter repeats the last accepted one is a **duplicate** (no new sample),
      unless its time says a whole number of counter cycles went by (then it is a gap).
    * Otherwise the counter gives the number lost modulo the counter cycle (``overflow``) and
      the frame time resolves the wraps: ``k`` periods after the last SYNC means ``k − 1``
      lost, i.e. the counter's count plus the whole cycles that fit.
    * A SYNC whose time is more than ``tol`` periods from where its counter puts it, or any
      other frame more than ``tol`` periods ahead of the running SYNC schedule, is a **bad
      timestamp**: it is re-stamped (a SYNC where its counter puts it, another frame at the
      current clock) and never moves the acquisition clock. Unless the next frame confirms
      a time ahead: then the SYNC was **late** (a stalled producer, a paused bus, a clock
      step): the bad-timestamp count is withdrawn, the SYNC counted ``late``, its sample
      takes the SYNC's own time after all (``on_late``) and the clock follows from there.
    * A SYNC more than half a period after where its counter puts it (within ``tol``) is
      taken at its own time and counted ``late`` too: lateness is counted, never corrected.

    ``stamp_sync``/``stamp_frame`` take the raw (1 µs) time and the current acquisition
    clock and return the time the frame is to carry now (a suspect frame: held at the
    clock). What the recording keeps is the frame's own time (the reader's tap), so a
    replay takes every one of these decisions again on the same times.
    """

    def __init__(self, period: float, overflow: int, tol: float = TIME_TOLERANCE_PERIODS):
        self.period = float(period)
        self.overflow = int(overflow)
        # wraps are resolvable only within half a counter cycle
        self.tol = min(float(tol), (self.overflow - 1) / 2) if self.overflow else float(tol)
        self.base_t: float | None = None  # time of the last accepted SYNC
        self.base_c = 0  # its counter
        self._suspect: tuple[float, int | None] | None = None  # (raw time, SYNC counter)
        #: a SYNC stamped far back with the counter following (raw time, counter): the next
        #: frame at its time makes it a discontinuity, any other leaves it a bad timestamp
        self._back: tuple[float, int] | None = None
        self.bad_timestamp = 0
        #: SYNCs later than their counter puts them (> half a period), taken at their own time
        self.late = 0
        #: called with a late SYNC's own time once the next frame confirmed it (the
        #: assembler: the open sample takes that time)
        self.on_late: Callable[[float], None] = lambda t: None
        # the result for the SYNC just stamped (read by the assembler): lost, duplicate
        self.lost = 0
        self.duplicate = False
        self.jumped = False  # the SYNC just stamped started afresh: time went back
        #: SYNC gaps longer than GAP_S (frame times): how many, the longest and the total, s
        self.gaps = 0
        self.gap_longest_s = 0.0
        self.gap_total_s = 0.0
        self.on_gap: Callable[[float, float], None] = lambda t, gap: None
        self._last_sync_t: float | None = None

    def _gap(self, x: float, lost_c: int, same: bool) -> int | None:
        """Samples lost for a SYNC ``x`` periods after the base whose counter says ``lost_c``
        (mod overflow); None when no whole number of counter cycles fits within ``tol``."""
        ov = self.overflow
        if same:  # the counter repeats: a gap of a whole number of cycles, or a duplicate
            m = max(1, round(x / ov))
            return m * ov - 1 if abs(x - m * ov) <= self.tol else None
        m = max(0, round((x - lost_c - 1) / ov))
        return lost_c + m * ov if abs(x - (lost_c + 1 + m * ov)) <= self.tol else None

    def _confirm(self, t: float, decisive: bool = True) -> None:
        """A pending suspect frame: confirmed (the clock stepped) if ``t`` is not back
        before it; then its bad-timestamp count is withdrawn, and a SYNC was late: it
        becomes the base and its sample takes its own time. A suspect SYNC is refuted only
        by a SYNC (``decisive``) or its sample's end (:meth:`settle`): a data frame stamped
        before it is a straggler sent before it (a node's thread held up), not evidence."""
        assert self._suspect is not None  # called with a suspect frame pending
        st, sc = self._suspect
        if t >= st - self.tol * self.period:
            self._suspect = None
            self.bad_timestamp -= 1
            if sc is not None:
                self._late_confirmed(st, sc)
        elif decisive or sc is None:
            self._suspect = None

    def settle(self) -> None:
        """The open sample is passed on: a suspect SYNC not confirmed by then stays a bad
        timestamp (its sample keeps the time its counter put it at)."""
        if self._suspect is not None and self._suspect[1] is not None:
            self._suspect = None

    def _late_confirmed(self, st: float, sc: int) -> None:
        self.base_t, self.base_c = st, sc
        self.late += 1
        self.on_late(st)

    def stamp_sync(self, counter: int, t: float, clock: float) -> float:
        """A SYNC with a valid counter (1…overflow) at raw time ``t``."""
        self.lost, self.duplicate, self.jumped = 0, False, False
        last, self._last_sync_t = self._last_sync_t, t
        if last is not None and t - last > GAP_S:
            gap = t - last
            self.gaps += 1
            self.gap_longest_s = max(self.gap_longest_s, gap)
            self.gap_total_s += gap
            self.on_gap(t, gap)
        if self.base_t is None:
            self.base_t, self.base_c = t, counter
            return t
        ov, dt = self.overflow, self.period
        same = counter == self.base_c
        lost_c = (counter - (self.base_c % ov + 1)) % ov
        back = self._back
        if back is not None:  # the SYNC after one stamped far back with the next counter
            self._back = None
            if back[0] <= t <= back[0] + DISCONTINUITY_S:
                self._jump_confirmed(*back)  # its time continues that one's: time went back
                self.jumped = True
                lost_c = (counter - (self.base_c % ov + 1)) % ov
                same = counter == self.base_c
        if t < self.base_t - DISCONTINUITY_S and not same:
            if lost_c:
                # time went back and the counter does not follow: a discontinuity — counted
                # by the tap, no sample lost for it, the SYNC taken at its own time as the
                # new base
                self._suspect = None
                self.base_t, self.base_c = t, counter
                self.jumped = True
                return t
            # time went back with the counter following (a recording joined to itself at a
            # whole counter cycle) — or one SYNC stamped far back: a bad timestamp (below)
            # until the next frame shows which (``_back``)
            self._back = (t, counter)
        lost = self._gap((t - self.base_t) / dt, lost_c, same)
        if lost is None and self._suspect is not None:
            st, sc = self._suspect
            if sc is not None:  # consistent with the suspect SYNC: the clock stepped there
                same2 = counter == sc
                lost2 = self._gap((t - st) / dt, (counter - (sc % ov + 1)) % ov, same2)
                if lost2 is not None:
                    self._suspect = None
                    self.bad_timestamp -= 1
                    self._late_confirmed(st, sc)
                    self._count_late(t, lost2)
                    self.base_t, self.base_c = t, counter
                    self.lost = lost2
                    return t
        if self._suspect is not None:
            self._confirm(t)
        if lost is not None:
            self._count_late(t, lost)
            self.base_t, self.base_c = t, counter
            self.lost = lost
            return t
        if same:  # a repeat whose time fits no whole cycle: the same SYNC again
            self.duplicate = True
            return t
        # the time fits no count the counter allows: a bad timestamp. The gap is the
        # counter's; the SYNC is re-stamped where the counter puts it, unless that is far
        # from the clock too (the counter jumped: a restarted producer): then at its own
        # time if that is plausible, else at the clock — never moving the clock by a
        # disputed amount
        self.bad_timestamp += 1
        near = (1 + self.tol) * dt
        predicted = self.base_t + (lost_c + 1) * dt
        if abs(predicted - clock) <= near:
            stamp = max(predicted, clock)
        elif abs(t - clock) <= near:
            stamp = max(t, clock)
        else:
            stamp = clock
        self.base_t, self.base_c = stamp, counter
        if t > stamp + self.tol * dt:  # ahead: the next frame may show the clock stepped
            self._suspect = (t, counter)
        self.lost = lost_c
        return stamp

    def _jump_confirmed(self, t: float, counter: int) -> None:
        """The SYNC held as stamped far back (``_back``) is followed by frames at its time: a
        discontinuity after all — its bad-timestamp count withdrawn, the SYNC the new base at
        its own time, its sample retimed to it (``on_late``: its time, never a rewritten one)."""
        self._suspect = None
        self.bad_timestamp -= 1
        self.base_t, self.base_c = t, counter
        self.on_late(t)

    def _count_late(self, t: float, lost: int) -> None:
        """A SYNC taken at its own time ``t``, ``lost`` after the base: late if more than
        half a period after where its counter puts it."""
        assert self.base_t is not None  # called once a SYNC set the base
        if t - self.base_t > (lost + 1.5) * self.period:
            self.late += 1

    # -- the columnar replay's hand-over (daq/bus/columnar.py) ------------------------------
    def steady(self) -> bool:
        """Nothing pending: the last SYNC was taken at its own time (the columnar replay may
        take over the clean SYNCs that follow, :meth:`advance`)."""
        return (self._suspect is None and self.base_t is not None and self.overflow > 1
                and self.base_t == self._last_sync_t)

    def advance(self, t: float, counter: int) -> None:
        """Clean SYNCs, each one period after the last with the next counter, up to the
        one at ``t`` with ``counter``, were taken by the columnar replay: the state
        :meth:`stamp_sync` would have left (nothing lost, late, duplicated or a gap)."""
        self.base_t = self._last_sync_t = t
        self.base_c = counter
        self.lost, self.duplicate, self.jumped = 0, False, False

    def stamp_frame(self, t: float, clock: float, sync: bool = False) -> float:
        """Any other frame (a SYNC without counter: ``sync=True``): far ahead of a running
        SYNC schedule, it is held at the clock until the next frame confirms it."""
        back = self._back
        if back is not None:  # a SYNC stamped far back: the frame after it decides
            self._back = None
            if back[0] <= t <= back[0] + (1 + self.tol) * self.period:
                self._jump_confirmed(*back)
                self.jumped = True  # (the tap: a discontinuity at the SYNC's time)
                return t
        if self._suspect is not None:
            self._confirm(t, decisive=sync)
        base = self.base_t
        if base is None or clock == -math.inf:
            if sync:
                self.base_t = t
            return t
        dt, tol = self.period, self.tol
        clock = max(clock, base)  # a late SYNC just confirmed: the clock follows it
        running = clock <= base + (1 + tol) * dt  # SYNCs are coming
        if running and t > clock + tol * dt:
            if self._suspect is None:  # (with a SYNC's time undecided: held, not counted)
                self.bad_timestamp += 1
                self._suspect = (t, None)
            return clock
        # far behind: re-stamped at the clock by the tap (never backwards), not counted —
        # our own transmissions come back stamped at send time, or not at all (canopen's
        # SDO requests in lock-step: 0.0)
        if sync:
            self.base_t = max(t, clock)
        return t


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
        """The telemetry ``channels`` payload, strict JSON (non-finite -> None)."""
        return sanitise(channels_payload(self))

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


def channels_payload(s: Sample, I: np.ndarray | None = None,
                     status: dict | None = None) -> dict:
    """The one builder of the telemetry ``channels`` payload (docs/telemetry.md §2.2) of sample
    ``s``: ``I`` (the inertial loads) when the estimator computed them, ``status`` when the
    cells' status is not already a dict by name. Values as they are (numpy arrays, NaN): the
    encoder (:func:`rsra.daq.jsonout.dumps`) makes it strict JSON."""
    out = {"seq": s.seq, "t": float(s.t), "T": s.T,
           "accel": np.asarray(s.accel, float).reshape(-1, 3)}
    if I is not None:
        out["I"] = I
    out.update({"omega": s.omega, "azimuth": s.azimuth, "known_H": s.known_H, "drive": s.drive,
                "status": dict(s.cell_status) if status is None else status})
    return out


class SampleLayout:
    """How a SYNC period's TPDO frames become a :class:`Sample` (the per-sample decode).

    Built once from the rig and its decode table: the output layout ``[T | accel | balance |
    drive | omega, azimuth]`` (one gather of struct's tuple), the calibration in that layout
    (one multiply-add), and what depends only on which nodes reported (cached per pattern,
    bounded). :meth:`sample` is the one call per sample; no state changes but the cache.
    """

    def __init__(self, cfg: RigConfig, table: DecodeTable):
        self.table = table
        n = table.n_channels
        self._unpack = table.sample_struct.unpack
        self._pattern_cache: dict[tuple[int, int], tuple] = {}

        # output layout (config order): T | accel | balance | drive | omega, azimuth; one
        # gather ``raw[perm]`` per sample, the Sample's arrays are views of its sections
        idx = table.index
        T_idx = [idx(f"{c.node}.force") for c in cfg.cells]
        self._status_idx = [idx(f"{c.node}.status") for c in cfg.cells]
        self._cell_names = [c.name for c in cfg.cells]
        self._cell_nodes = [c.node for c in cfg.cells]
        self._status_flags = [(f"overrange:{c.name}", f"fault:{c.name}") for c in cfg.cells]
        codes = {i: lay.codes[i - lay.start] for lay in table.layouts
                 for i in range(lay.start, lay.stop)}
        # integer status bytes come out of struct as int already (bool/float ones need int())
        self._status_is_int = all(codes[i] in "bBhHiIqQ" for i in self._status_idx)
        acc_idx = [idx(f"{a.node}.{ax}") for a in cfg.accelerometers for ax in "xyz"]
        perm = T_idx + acc_idx
        self._sl_T = slice(0, len(T_idx))
        self._sl_acc = slice(len(T_idx), len(perm))
        self._n_acc = len(cfg.accelerometers)
        rn = cfg.rotor.node
        self._rotor = None
        if rn:
            self._rotor = (rn, len(perm), len(perm) + 1, table.channels[idx(f"{rn}.azimuth")].wrap)
            perm += [idx(f"{rn}.omega"), idx(f"{rn}.azimuth")]
        bn = cfg.balance.node
        self._balance = None
        if bn:
            self._balance = (bn, slice(len(perm), len(perm) + 6))
            perm += [idx(f"{bn}.{k}") for k in "XYZLMN"]
        drive = []
        for e in cfg.external_loads:
            nl = table.node(e.node)
            values = [i for i in range(nl.start, nl.stop) if not table.channels[i].is_status]
            if len(values) != 1:
                from rsra.config.rig import ConfigError
                raise ConfigError(f"external_loads[{e.name}].node", e.node,
                                  f"the node maps {len(values)} values; an external load needs one",
                                  "map exactly one value in the drive-load node's TPDOs")
            drive.append((e.node, values[0]))
        self._drive = None
        if drive:
            self._drive = (frozenset(n for n, _ in drive),
                           slice(len(perm), len(perm) + len(drive)))
            perm += [i for _, i in drive]
        self._perm = np.array(perm, dtype=np.intp)
        # the output channels picked from struct's tuple in Python, then one float array:
        # a third of np.array(raw)[perm]'s cost (dtype discovery over the mixed tuple)
        self._gather: Callable[[tuple[Any, ...]], tuple[Any, ...]]
        if len(perm) > 1:
            self._gather = operator.itemgetter(*perm)
        else:
            self._gather = lambda raw: tuple(raw[i] for i in perm)
        self._gain_out = table.gain[self._perm]  # calibration in the output layout
        self._offset_out = table.offset[self._perm]
        self._node_of_channel = np.array(
            [next(k for k, nl in enumerate(table.nodes) if nl.start <= i < nl.stop)
             for i in range(n)], dtype=int)
        self._node_names = [nl.name for nl in table.nodes]
        self._node_slices = [(nl.start, nl.stop, nl.mask) for nl in table.nodes]
        # the compiled decode (daq/_hubkernel.c unpack_cal): a sample with every value
        # finite unpacked and calibrated in one call, the same bits; every other sample,
        # and all of them without it, the Python of sample() (the reference)
        self._unpack_cal = _unpack_kernel() if self._status_is_int else None
        self._codes = "".join(lay.codes for lay in table.layouts).encode("ascii")
        if self._unpack_cal is not None and (
                len(self._codes) != n or table.sample_struct.format[0] != "<"
                or struct.calcsize(table.sample_struct.format) != table.sample_struct.size):
            self._unpack_cal = None
        self._n_out = len(perm)

    def _pattern(self, have: int, expect: int) -> tuple:
        """What depends only on which TPDOs came and which were expected (cached, bounded)."""
        key = (have, expect)
        p = self._pattern_cache.get(key)
        if p is None:
            unreported: list[str] = []
            missing: list[str] = []
            nan_idx: list[int] = []
            for name, (lo, hi, mask) in zip(self._node_names, self._node_slices):
                if have & mask != mask:
                    unreported.append(name)
                    nan_idx.extend(range(lo, hi))
                    if expect & mask:
                        missing.append(name)
            cells = [(name, si, fl) for name, node, si, fl in zip(
                self._cell_names, self._cell_nodes, self._status_idx, self._status_flags)
                if node not in unreported]
            names = tuple(c[0] for c in cells)
            sis = tuple(c[1] for c in cells)
            flags = tuple(c[2] for c in cells)
            nan_set = set(nan_idx)
            nan_out = np.array([k for k, i in enumerate(self._perm.tolist()) if i in nan_set],
                               dtype=np.intp)
            un = frozenset(unreported)
            p = (un, tuple(missing), tuple(f"missing:{m}" for m in missing),
                 np.array(nan_idx, dtype=int), nan_out if len(nan_out) else None,
                 names, sis, flags,
                 self._rotor is not None and self._rotor[0] not in un,
                 self._balance is not None and self._balance[0] not in un,
                 self._drive is not None and not un.intersection(self._drive[0]))
            if len(self._pattern_cache) >= _CACHE_MAX:
                self._pattern_cache.clear()
            self._pattern_cache[key] = p
        return p

    def sample(self, frames: list[Any], have: int, expect: int, seq: int, counter: int,
               t: float, lost: int) -> Sample:
        """The Sample of one SYNC period: ``frames`` one per TPDO (bit order; an unreported
        one decodes as zeros), ``have`` the TPDO bits reported, ``expect`` those that
        complete it; ``seq``, ``counter``, ``t`` its SYNC's, ``lost`` samples lost before."""
        (unreported, missing, missing_flags, nan_idx, nan_out, cell_names, status_idx,
         status_flags, rotor_ok, balance_ok, drive_ok) = self._pattern(have, expect)
        data = b"".join(frames)
        sts = None
        if self._unpack_cal is not None:  # (None back: a non-finite value, the Python below)
            out = np.empty(self._n_out)
            sts = self._unpack_cal(data, self._codes, self._perm, self._gain_out,
                                   self._offset_out, out, status_idx)
            if sts is not None and nan_out is not None:
                out[nan_out] = np.nan
        if sts is None:
            raw = self._unpack(data)  # every channel, channel order
            total = sum(raw)
            if total - total == 0.0:  # all finite (x - x is 0 for finite x, nan for inf/nan)
                out = np.array(self._gather(raw), float)
                out *= self._gain_out
                out += self._offset_out
                if nan_out is not None:
                    out[nan_out] = np.nan
            else:
                cal = np.array(raw)
                cal *= self.table.gain
                cal += self.table.offset
                bad = ~np.isfinite(cal)
                bad[nan_idx] = False
                bad_nodes = {self._node_names[k] for k in np.unique(self._node_of_channel[bad])}
                bad_nodes -= unreported
                if bad_nodes:
                    # non-finite values mark the channel missing (and its node flagged)
                    cal[bad] = np.nan
                    missing = tuple(sorted(set(missing) | bad_nodes, key=self._node_names.index))
                    missing_flags = tuple(f"missing:{m}" for m in missing)
                    unreported = unreported | bad_nodes
                    # (each _ok is False where its node is not configured)
                    rotor_ok = rotor_ok and self._rotor is not None and \
                        self._rotor[0] not in unreported
                    balance_ok = balance_ok and self._balance is not None and \
                        self._balance[0] not in unreported
                    drive_ok = drive_ok and self._drive is not None and \
                        not unreported.intersection(self._drive[0])
                if len(nan_idx):
                    cal[nan_idx] = np.nan
                out = cal[self._perm]
            sts = [raw[i] for i in status_idx]
            if not self._status_is_int:
                sts = [int(x) for x in sts]
        status = dict(zip(cell_names, sts))
        flags: tuple[str, ...]
        if lost or any(sts):
            fl = list(missing_flags)
            if lost:
                fl.append("lost_before")
            for st, (f_or, f_fault) in zip(sts, status_flags):
                if st:
                    if st & STATUS_OVERRANGE:
                        fl.append(f_or)
                    if st & STATUS_FAULT:
                        fl.append(f_fault)
            flags = tuple(fl)
        else:
            flags = missing_flags
        omega = azimuth = None
        if rotor_ok:
            assert self._rotor is not None  # rotor_ok: a rotor node is configured
            _, oi, ai, wrap = self._rotor
            omega = out.item(oi)
            azimuth = out.item(ai) % wrap if wrap else out.item(ai)
        return Sample(
            seq, counter, t, out[self._sl_T], status,
            out[self._sl_acc].reshape(self._n_acc, 3), omega, azimuth,
            out[self._balance[1]] if balance_ok and self._balance is not None else None,
            out[self._drive[1]] if drive_ok and self._drive is not None else None,
            missing, lost, flags, not missing)


class SampleAssembler:
    """Assembles samples from SYNC and TPDO frames; ``emit`` receives every Sample.

    ``callbacks()`` gives the per-COB-ID frame callbacks (``cb(can_id, data, timestamp)``),
    the SYNC one included, for canopen's ``Network.subscribe``.

    Per frame only the length and the duplicate check run and the frame is kept (one list
    store; the bytes are read when the sample is passed on, within the same SYNC period, so
    the caller must not reuse a frame's buffer before the next SYNC — python-can and canopen
    hand over a new one per frame). Per sample: one ``struct`` unpack of every TPDO joined
    in bit order (DecodeTable.sample_struct), one gather into the output layout
    ``[T | accel | balance | drive | omega, azimuth]`` and one multiply-add (calibration) —
    :class:`SampleLayout`'s; this class frames the periods (SYNC, TPDOs, which nodes to wait
    for) and counts them.
    """

    def __init__(self, cfg: RigConfig, table: DecodeTable, emit: Callable[[Sample], None]):
        self.cfg, self.table, self.emit = cfg, table, emit
        self.sync_cob_id = cfg.sync.cob_id
        self.overflow = cfg.sync.counter_overflow
        #: the decode of a period's frames into a Sample
        self.layout = SampleLayout(cfg, table)
        self._layout_sample = self.layout.sample
        self._zero_frames = list(table.zero_frames)  # an unreported TPDO decodes as zeros
        self._frames: list[Any] = list(self._zero_frames)  # one per TPDO, bit order
        self._have = table.all_bits  # TPDO bits reported since the last SYNC (all: none yet)
        self._expect = 0  # TPDO bits that complete the current sample
        self._wait = -1  # = _expect while the sample is open, -1 (matches nothing) otherwise
        self._open = False  # the current sample is not passed on yet
        self._in_sample = False  # a SYNC has been seen
        self._sync_t = 0.0
        self._sync_counter = 0
        self._lost = 0
        self._seq = 0  # seq of the current sample
        self._next_seq = 0
        self._prev_have = 0
        self.clock = SyncClock(1.0 / cfg.sample_rate_hz, self.overflow)
        self.clock.on_late = self._late_sync
        self.clock.on_gap = self._gap_seen
        self._stamped: tuple[Any, float] | None = None  # (data, t) the tap stamped last
        # counters (health)
        self.complete = 0
        self.incomplete = 0
        self.lost = 0
        self.malformed = 0
        self.duplicate = 0
        self.orphan = 0  # TPDOs before the first SYNC
        self.duplicate_sync = 0  # SYNCs repeating the last counter (no sample)
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
        for slot, lay in enumerate(self.table.layouts):
            cbs[lay.cob_id] = self._make_tpdo_callback(lay.length, slot, lay.bit)
        return cbs

    def _make_tpdo_callback(self, length: int, slot: int, bit: int) -> FrameCallback:
        frames = self._frames  # the same list object for the whole run (item stores only)

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
            frames[slot] = data  # decoded with the whole sample (_pass_on)
            have |= bit
            self._have = have
            wait = self._wait
            if have & wait == wait:  # every expected TPDO is in (never while not open)
                self.clock.settle()  # its SYNC's time is decided by now
                self._pass_on(True)

        return on_tpdo

    def sync_counter(self, data: Any) -> int | None:
        """The counter of a well-formed SYNC (0 when none is configured); None: malformed."""
        n = len(data)
        if self.overflow:
            return data[0] if n == 1 and 1 <= data[0] <= self.overflow else None
        return 0 if n <= 1 else None

    def stamp_sync(self, data: Any, t: float, clock: float) -> float:
        """The time a SYNC frame is to carry (called by the reader's frame tap before the
        frame is dispatched; ``clock`` is the acquisition clock so far)."""
        counter = self.sync_counter(data)
        if counter is None:  # malformed: an ordinary frame for the clock
            return self.clock.stamp_frame(t, clock)
        if counter and self.overflow:
            t = self.clock.stamp_sync(counter, t, clock)
        else:
            t = self.clock.stamp_frame(t, clock, sync=True)
        self._stamped = (data, t)
        return t

    def _gap_seen(self, t: float, gap: float) -> None:
        """A SYNC gap (SyncClock.GAP_S): logged as it happens, live and in replay alike (the
        first GAP_LOG_MAX of a run; every one is counted in health sync.gaps)."""
        n = self.clock.gaps
        if n <= GAP_LOG_MAX:
            log.warning("no SYNC for %.1f s before the SYNC at %.6f (the SYNC producer — this "
                        "service, or the one on the bus — stalled or the bus paused)%s", gap, t,
                        "; further gaps only counted (health sync.gaps)" if n == GAP_LOG_MAX
                        else "")

    def _late_sync(self, t: float) -> None:
        """The next frame confirmed the open sample's SYNC late: the sample takes the SYNC's
        own time (it was held at where the counter put it until then)."""
        if self._open:
            self._sync_t = math.floor(t * 1e6 + 0.5) / 1e6

    def on_sync(self, can_id: int, data: Any, timestamp: float) -> None:
        counter = self.sync_counter(data)
        if counter is None:
            self.malformed += 1
            return
        ov = self.overflow
        stamped, self._stamped = self._stamped, None
        if stamped is None or stamped[0] is not data:  # not through the tap (direct use)
            timestamp = self.stamp_sync(data, timestamp, timestamp)
            self._stamped = None
        clk = self.clock
        if ov and clk.duplicate:
            self.duplicate_sync += 1  # the same SYNC again: no new sample, no seq
            return
        if self._open:
            self._pass_on(False)  # incomplete: passed on at the next SYNC, missing flagged
        lost = clk.lost if ov else 0
        self.lost += lost
        self._seq = self._next_seq + lost
        self._next_seq = self._seq + 1
        self._lost = lost
        self._sync_t = math.floor(timestamp * 1e6 + 0.5) / 1e6  # 1 µs, = round(t, 6)
        self._sync_counter = counter
        first = not self._in_sample
        have = 0 if first else self._have
        # optional nodes that reported in the last period count as alive (by frame order)
        self._expect = expect = self._required_bits | self._alive_bits | (have & self._optional_bits)
        self._prev_have = have
        self._frames[:] = self._zero_frames
        self._have = 0
        self._in_sample = True
        self._open = True
        # the first sample has no period before it to say which optional nodes report: it
        # waits for every node (or the next SYNC), so that nothing its frames hold is left
        # out of it; `missing` is still judged against `expect`
        self._wait = wait = expect | self._optional_bits if first else expect
        if wait == 0:
            self._pass_on(True)

    # -- the sample, passed on (once per SYNC; decoded by SampleLayout) ---------------------
    def _pass_on(self, complete_trigger: bool) -> None:
        if stagetiming.TIMER is not None:  # off unless a benchmark asked for the stage timing
            stagetiming.TIMER.frame_done(self._seq, self._sync_t)
        self._open = False
        self._wait = -1
        s = self._layout_sample(self._frames, self._have, self._expect, self._seq,
                                self._sync_counter, self._sync_t, self._lost)
        if s.complete:
            self.complete += 1
        else:
            self.incomplete += 1
        self.emitted += 1
        self.emit(s)

    def finish(self) -> None:
        """Pass on a pending incomplete sample (end of a replay; no further SYNC will come)."""
        if self._open:
            self.clock.settle()
            self._pass_on(False)

    def counters(self) -> dict[str, int]:
        return {"complete": self.complete, "incomplete": self.incomplete, "lost": self.lost}

    # -- the columnar replay's hand-over (daq/bus/columnar.py) ------------------------------
    def steady_bits(self) -> int | None:
        """The TPDO bits the next sample waits for when the assembler is between samples
        with nothing pending (the last sample passed on complete, the next one expecting
        exactly what the last one had); None otherwise. The columnar replay takes over a
        SYNC followed by exactly these TPDOs only then."""
        if self._open or not self._in_sample or self._stamped is not None \
                or not self.clock.steady():
            return None
        have = self._have
        expect = self._required_bits | self._alive_bits | (have & self._optional_bits)
        return have if have == self._expect == expect and have else None

    def advance(self, samples: list[Sample], counter: int, sync_t: float) -> None:
        """``samples`` (consecutive, nothing lost before them, each a SYNC followed by the
        :meth:`steady_bits` TPDOs) were assembled by the columnar replay: counted, and the
        state left as the frame callbacks would have left it. ``sync_t`` is the last SYNC's
        stamp."""
        last = samples[-1]
        n_complete = sum(1 for s in samples if s.complete)
        self.complete += n_complete
        self.incomplete += len(samples) - n_complete
        self.emitted += len(samples)
        self._seq, self._next_seq, self._lost = last.seq, last.seq + 1, 0
        self._sync_t, self._sync_counter = last.t, counter
        self._prev_have = self._have
        self.clock.advance(sync_t, counter)
