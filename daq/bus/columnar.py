"""The columnar replay: recordings read in blocks of arrays, the clean samples assembled per
block, everything else through the streaming reader (docs/bus.md §5, docs/cli.md §6).

::

    candump text ─▶ CandumpBlocks ─┬▶ FrameBlock (numpy: t, COB-ID, DLC, data[n, 8])
    .blf/.asc/… ─▶ python-can ─────┘  └▶ can.Message (a line not of the plain form)
                                           │
    ColumnarReplay: per block, each SYNC period that is *clean* — nothing pending in the
    assembler, the SYNC's counter the next one and its time one period on (not late, no gap),
    exactly the TPDOs the assembler waits for, each once with its length, times never going
    back or far ahead, no timed task due — is assembled here (the same SampleLayout decode);
    every other frame (heartbeats, EMCY, NMT, unknown, garbage, lost or duplicate PDOs, a
    counter jump, time going back, a reboot, a line python-can parses differently) goes one
    by one through the streaming reader (:class:`~rsra.daq.bus.reader.OfflineReader`), whose
    rules therefore apply on both paths, written once. The hand-over carries the state
    across (``SampleAssembler.steady_bits``/``advance``, the tap's frame count and clock).

The samples and health reports are those of :func:`rsra.daq.bus.replay.replay` on the
streaming path, bit for bit (tests/test_columnar.py).
"""
from __future__ import annotations

import io
import itertools
import logging
import math
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from rsra.daq.bus.assembler import Sample
from rsra.daq.bus.logfiles import MAX_LINE_CHARS, ReplayError
from rsra.daq.bus.reader import HealthReport, ReaderBase
from rsra.daq.bus.reorder import FrameReorder, reordered

log = logging.getLogger(__name__)

# candump text read per block (512 KiB ≈ 12 500 frames): a 2 MiB block took the same time and
# 14 MiB more peak memory (the parse's arrays, a few per byte or line of the block)
BLOCK_BYTES = 1 << 19
BLOCK_FRAMES = 12_500  # frames per block from python-can's readers (other formats)

_HEX = np.full(256, -1, np.int16)
for _i, _c in enumerate(b"0123456789ABCDEF"):
    _HEX[_c] = _i
for _i, _c in enumerate(b"abcdef", start=10):
    _HEX[_c] = _i
_DIGIT = np.full(256, -1, np.int16)
for _i in range(10):
    _DIGIT[48 + _i] = _i
_POW10 = 10 ** np.arange(9, -1, -1, dtype=np.int64)  # 10 integer digits of a UNIX time
_EXACT = 2**53  # microsecond counts below this convert to float exactly


@dataclass
class FrameBlock:
    """Plain frames (11-bit data frames, no error, remote or FD frame) as arrays."""

    t: np.ndarray  # float64, the recorded time stamps
    cid: np.ndarray  # int64 COB-IDs
    dlc: np.ndarray  # int64 data lengths
    data: np.ndarray  # uint8 [n, 8], zero beyond dlc

    def __len__(self) -> int:
        return len(self.t)

    def message(self, i: int) -> can.Message:
        n = int(self.dlc[i])
        return can.Message(timestamp=float(self.t[i]), arbitration_id=int(self.cid[i]),
                           is_extended_id=False, dlc=n, data=bytearray(self.data[i, :n]))


Piece = FrameBlock | can.Message


# -- reading -----------------------------------------------------------------------------------
class CandumpBlocks:
    """The frames of a candump ``.log`` in blocks: every line of the plain form
    ``(SECONDS.MICROS) CHANNEL III#HEX [R|T]`` parsed with numpy (the time as its exact
    microsecond count, which gives the very float python-can's ``float()`` gives); any other
    line — error, remote, extended or FD frames, odd spacing, bytes that are not UTF-8, a
    line python-can would refuse — handed to python-can's own parser in its place, so that
    what the streaming path does with it (a frame, or the error naming file and line) is done
    here too. A last line without its newline is dropped (a cut write), as on the streaming
    path."""

    def __init__(self, path: Path, block_bytes: int = BLOCK_BYTES):
        self.path = path
        self.block_bytes = block_bytes
        self.lineno = 0  # lines handed over so far (text lines, as Python counts them)

    def __iter__(self) -> Iterator[Piece]:
        tail = b""
        skipping = False  # inside a line longer than any frame: its start kept in tail
        with open(self.path, "rb") as f:
            while True:
                chunk = f.read(self.block_bytes)
                if not chunk:
                    break
                if skipping:  # the rest of an over-long line dropped unread into memory
                    nl = chunk.find(b"\n")
                    if nl < 0:
                        continue
                    chunk, skipping = chunk[nl:], False
                buf = tail + chunk
                end = buf.rfind(b"\n") + 1
                tail = buf[end:]
                if end:
                    yield from self._lines(buf[:end])
                if len(tail) > MAX_LINE_CHARS:  # as the streaming path: its start stands for it
                    tail, skipping = tail[:MAX_LINE_CHARS], True
        if tail and skipping:  # the file ended inside an over-long line: a cut line
            from rsra.daq.bus.logfiles import cut_line_dropped

            cut_line_dropped(self.path, tail[:80].decode("utf-8", "replace"))
        elif tail:  # no newline at its end: a cut write (or lines that end in '\r' alone)
            yield from self._odd(tail)

    def _lines(self, chunk: bytes) -> Iterator[Piece]:
        blk, ok = _parse_plain(chunk)
        nl = np.flatnonzero(np.frombuffer(chunk, np.uint8) == 10)
        starts = np.r_[0, nl[:-1] + 1]
        bad = np.flatnonzero(~ok)
        if not len(bad):
            self.lineno += len(ok)
            yield blk
            return
        # runs of plain lines between the odd ones, in order
        first = 0  # first line of the current run
        k = 0
        while k < len(bad):
            lo = bad[k]
            hi = lo + 1
            while k + 1 < len(bad) and bad[k + 1] == hi:  # consecutive odd lines: one run
                k += 1
                hi += 1
            k += 1
            if lo > first:
                self.lineno += lo - first
                yield _take(blk, ok, first, lo)
            stop = int(starts[hi]) if hi < len(starts) else len(chunk)
            yield from self._odd(chunk[int(starts[lo]):stop])
            first = hi
        if first < len(ok):
            self.lineno += len(ok) - first
            yield _take(blk, ok, first, len(ok))

    def _odd(self, text: bytes) -> Iterator[can.Message]:
        """Lines python-can parses (the streaming path's own reading, error and all)."""
        from rsra.daq.bus.logfiles import candump_frames

        lines = _NumberedLines(io.TextIOWrapper(io.BytesIO(text), encoding="utf-8",
                                                errors="replace"), self.lineno, self.path)
        yield from candump_frames(self.path, lines)
        self.lineno = lines.lineno


class _NumberedLines:
    """Text lines with the file's line numbers (what replay.candump_frames reports); a
    last line without its newline dropped (replay._CompleteLines)."""

    def __init__(self, lines: io.TextIOWrapper, lineno: int, path: Path):
        self.file, self.lineno, self.line, self.path = lines, lineno, "", path

    def __iter__(self) -> Iterator[str]:
        from rsra.daq.bus.logfiles import cut_line_dropped

        for line in self.file:
            if not line.endswith("\n"):
                cut_line_dropped(self.path, line)
                continue
            self.lineno += 1
            self.line = line
            yield line

    def close(self) -> None:
        self.file.close()


def _take(blk: FrameBlock, ok: np.ndarray, lo: int, hi: int) -> FrameBlock:
    """The parsed frames of lines ``lo``..``hi`` (all plain) of a chunk."""
    a = int(np.count_nonzero(ok[:lo]))
    b = a + hi - lo
    return FrameBlock(blk.t[a:b], blk.cid[a:b], blk.dlc[a:b], blk.data[a:b])


def _parse_plain(chunk: bytes) -> tuple[FrameBlock, np.ndarray]:
    """Parse every line of ``chunk`` (whole lines) of the plain form; ``ok`` per line says
    which; the block holds the frames of the ``ok`` lines, in order."""
    buf = np.frombuffer(chunk, np.uint8)
    nl = np.flatnonzero(buf == 10)
    n = len(nl)
    starts = np.r_[0, nl[:-1] + 1].astype(np.int64)
    ends = nl.astype(np.int64)  # the newline
    size = len(buf)

    def at(pos: np.ndarray) -> np.ndarray:
        return buf[np.clip(pos, 0, size - 1)]

    ok = (ends - starts >= 24) & (at(starts) == 40)  # '('
    pc = _next_of(buf, 41, starts, ends)  # ')'
    ok &= (pc < ends) & (at(pc + 1) == 32)
    ps = _next_of(buf, 32, pc + 2, ends)  # the space after the channel
    ok &= (ps > pc + 2) & (ps + 5 <= ends) & (at(ps + 4) == 35)  # '#'
    # an " R"/" T" direction after the data (python-can's writer)
    suffix = (at(ends - 2) == 32) & np.isin(at(ends - 1), np.frombuffer(b"RTrt", np.uint8))
    dend = np.where(suffix, ends - 2, ends)
    nhex = dend - (ps + 5)
    ok &= (nhex >= 0) & (nhex <= 16) & (nhex % 2 == 0)
    # no byte outside printable ASCII but the two (three) separating spaces: counted per
    # line from the positions of such bytes (a few a line), not a running count of every
    # byte (a quarter of the parse's time, and 8 bytes of memory a byte of text)
    odd = np.flatnonzero((buf < 0x21) | (buf > 0x7E))
    n_odd = np.searchsorted(odd, ends) - np.searchsorted(odd, starts)
    ok &= n_odd == 2 + suffix
    # the time: up to 10 digits, '.', 6 digits
    dot = pc - 7
    ok &= (at(dot) == 46) & (dot - starts >= 2) & (dot - starts <= 11)
    ip = np.zeros(n, np.int64)
    width = dot - starts - 1
    for k in range(10):
        pos = dot - 10 + k
        use = 10 - k <= width
        d = _DIGIT[at(pos)]
        ok &= ~use | (d >= 0)
        ip += np.where(use, np.maximum(d, 0), 0).astype(np.int64) * _POW10[k]
    frac = np.zeros(n, np.int64)
    for k in range(6):
        d = _DIGIT[at(dot + 1 + k)]
        ok &= d >= 0
        frac = frac * 10 + np.maximum(d, 0)
    us = ip * 1_000_000 + frac
    ok &= us < _EXACT
    cid = np.zeros(n, np.int64)
    for k in range(3):
        h = _HEX[at(ps + 1 + k)]
        ok &= h >= 0
        cid = cid * 16 + np.maximum(h, 0)
    data = np.zeros((n, 8), np.uint8)
    for k in range(8):
        use = 2 * k < nhex
        hi = _HEX[at(ps + 5 + 2 * k)]
        lo = _HEX[at(ps + 6 + 2 * k)]
        ok &= ~use | ((hi >= 0) & (lo >= 0))
        data[:, k] = np.where(use, np.maximum(hi, 0) * 16 + np.maximum(lo, 0), 0)
    blk = FrameBlock(us[ok] / 1e6, cid[ok], (nhex[ok] // 2).astype(np.int64), data[ok])
    return blk, ok


def _next_of(buf: np.ndarray, byte: int, frm: np.ndarray, default: np.ndarray) -> np.ndarray:
    """The position of the first ``byte`` at or after each of ``frm`` (``default`` where
    there is none)."""
    pos = np.flatnonzero(buf == byte)
    if not len(pos):
        return default
    j = np.searchsorted(pos, frm)
    return np.where(j < len(pos), pos[np.minimum(j, len(pos) - 1)], default)


def _python_can_blocks(path: Path) -> Iterator[Piece]:
    """Another format through python-can's reader (replay.read_file), the plain frames
    gathered into blocks, any other frame passed on as it is, in order."""
    from rsra.daq.bus.logfiles import read_file

    t: list[float] = []
    cid: list[int] = []
    dlc: list[int] = []
    data: list[bytes] = []

    def block() -> FrameBlock:
        d = np.zeros((len(t), 8), np.uint8)
        if t:
            raw = np.frombuffer(b"".join(x.ljust(8, b"\0") for x in data), np.uint8)
            d[:] = raw.reshape(-1, 8)
        b = FrameBlock(np.array(t, float), np.array(cid, np.int64), np.array(dlc, np.int64), d)
        t.clear()
        cid.clear()
        dlc.clear()
        data.clear()
        return b

    for msg in read_file(path):
        if (msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or msg.is_fd
                or len(msg.data) > 8 or msg.dlc != len(msg.data)):
            if t:
                yield block()
            yield msg
            continue
        t.append(msg.timestamp)
        cid.append(msg.arbitration_id)
        dlc.append(msg.dlc)
        data.append(bytes(msg.data))
        if len(t) >= BLOCK_FRAMES:
            yield block()
    if t:
        yield block()


def read_pieces(files: Sequence[Path], block_bytes: int = BLOCK_BYTES,
                names: Sequence[str | Path] | None = None) -> Iterator[Piece]:
    """Every frame of the recording ``files`` (replay.expand's) in order, as blocks of plain
    frames and single messages, with the errors of replay.read_frames (``names``: the
    recordings as the user gave them, for the error of an empty one); candump text read
    ``block_bytes`` at a time."""
    n = 0
    for f in files:
        pieces = CandumpBlocks(f, block_bytes) if f.suffix.lower() == ".log" \
            else _python_can_blocks(f)
        for p in pieces:
            n += len(p) if isinstance(p, FrameBlock) else 1
            yield p
    if n == 0:
        shown = names if names is not None else files
        raise ReplayError(f"{', '.join(map(str, shown))}: no CAN frames in it (an empty "
                          "recording); fix: give a recording that holds frames")


# -- assembling --------------------------------------------------------------------------------
class ColumnarReplay:
    """Samples and health reports of blocks of frames, through ``reader`` (an offline
    reader: its assembler, tap and health monitor are the streaming path's), the clean SYNC
    periods assembled per block here."""

    def __init__(self, reader: ReaderBase):
        self.reader = reader
        asm = reader.assembler
        self.asm = asm
        self.tap = reader.tap
        self.layout = asm.layout
        self.sync_cob = asm.sync_cob_id
        table = reader.table
        self.layouts = table.layouts
        width = sum(lay.length for lay in table.layouts)
        self.width = width
        # per COB-ID: (bit, length, byte offset in the joined sample); a lookup array
        top = max([self.sync_cob, *table.tpdos]) + 1
        self.bit_of = np.zeros(top, np.int64)
        self.len_of = np.full(top, -1, np.int64)
        self.off_of = np.zeros(top, np.int64)
        off = 0
        for lay in table.layouts:
            self.bit_of[lay.cob_id] = lay.bit
            self.len_of[lay.cob_id] = lay.length
            self.off_of[lay.cob_id] = off
            off += lay.length
        self._orders: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}
        #: SYNC periods taken here, and frames fed one by one (the bench's statistic)
        self.fast_samples = 0
        self.slow_frames = 0

    def run(self, pieces: Iterator[Piece], finish: bool = False
            ) -> Iterator[Sample | HealthReport]:
        r = self.reader
        pending = r.items.queue.queue
        for p in pieces:
            if isinstance(p, FrameBlock):
                yield from self._block(p)
            else:
                self.slow_frames += 1
                r.feed(p)
                if pending:
                    yield from r.poll()
        if finish:
            self.asm.finish()
        yield from r.poll()

    def _feed(self, blk: FrameBlock, lo: int, hi: int) -> Iterator[Sample | HealthReport]:
        r = self.reader
        pending = r.items.queue.queue
        self.slow_frames += hi - lo
        for i in range(lo, hi):
            r.feed(blk.message(i))
            if pending:
                yield from r.poll()

    def _block(self, blk: FrameBlock) -> Iterator[Sample | HealthReport]:
        n = len(blk)
        if n == 0:
            return
        from rsra.daq import stagetiming

        if stagetiming.TIMER is not None:  # a benchmark timing every sample: one by one
            yield from self._feed(blk, 0, n)
            return
        tq = np.floor(blk.t * 1e6 + 0.5) / 1e6  # the tap's 1 µs time (the same arithmetic)
        syncs = np.flatnonzero((blk.cid == self.sync_cob) & (blk.dlc == 1))
        # a SYNC period: from a SYNC up to the next one (or the block's end)
        seg_end = np.r_[syncs[1:], n]
        periods: dict[int, _Periods] = {}  # by the TPDO bits awaited (steady_bits)
        i = 0
        k = 0  # the next SYNC period (index into syncs)
        while i < n:
            if k < len(syncs) and syncs[k] == i:
                bits = self.asm.steady_bits()
                took = None
                if bits is not None:
                    if bits not in periods:
                        periods[bits] = _Periods(self, blk, tq, syncs, seg_end, bits)
                    took = self._clean_run(blk, periods[bits], k)
                if took:
                    samples, stop = took
                    yield from samples
                    k += len(samples)
                    # the frames after the last clean sample's TPDOs, up to the next SYNC
                    end = int(seg_end[k - 1])
                    if stop < end:
                        yield from self._feed(blk, stop, end)
                    i = end
                    continue
                end = int(seg_end[k])
                k += 1
            else:
                end = int(syncs[k]) if k < len(syncs) else n
            yield from self._feed(blk, i, end)
            i = end

    def _clean_run(self, blk: FrameBlock, p: _Periods, k: int
                   ) -> tuple[list[Sample], int] | None:
        """The clean SYNC periods from the block's ``k``-th SYNC on, assembled: (samples,
        index of the first frame not taken), or None when the first one is not clean."""
        if not p.first_ok[k]:
            return None
        asm, tap = self.asm, self.tap
        clock = asm.clock
        # the first period against the state the streaming path left (SyncClock.stamp_sync)
        ts = float(p.ts[k])
        assert clock.base_t is not None  # steady_bits: a SYNC was taken
        dt = clock.period
        x = (ts - clock.base_t) / dt
        if not (int(p.counter[k]) == clock.base_c % clock.overflow + 1
                and abs(x - 1) <= clock.tol and not ts - clock.base_t > 1.5 * dt
                and ts >= tap.frame_time and float(p.tlast[k]) < tap.deadlines.next):
            return None
        end = p.run_end(k)
        # no timed task due within the run (the frame times rise through it)
        end = k + int(np.searchsorted(p.tlast[k:end], tap.deadlines.next, side="left"))
        nrun = end - k
        samples = self._samples(blk, p.tq, p.idx[k:end], p.bits, p.counter[k:end])
        last = int(p.cand[end - 1])
        asm.advance(samples, int(p.counter[end - 1]), float(p.tq[last]))
        tap.frames += nrun * (p.m + 1)
        tap.frame_time = max(tap.frame_time, float(p.tlast[end - 1]))
        items = self.reader.items
        items.max_depth = max(items.max_depth, 1)  # each one queued and taken at once
        self.fast_samples += nrun
        return samples, int(p.idx[end - 1, -1]) + 1

    def _gather(self, order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """For periods whose TPDOs come in ``order`` (COB-IDs): each byte of the joined
        sample as (the period's TPDO q, its byte j), and the bytes of TPDOs not in it
        (zeros); one gather then joins a whole run of periods."""
        key = order.tobytes()
        got = self._orders.get(key)
        if got is None:
            q = np.zeros(self.width, np.int64)
            j = np.zeros(self.width, np.int64)
            have = np.zeros(self.width, bool)
            for k, cob in enumerate(order.tolist()):
                o, n = int(self.off_of[cob]), int(self.len_of[cob])
                q[o:o + n], j[o:o + n], have[o:o + n] = k, np.arange(n), True
            got = (q, j, None if have.all() else np.flatnonzero(~have))
            if len(self._orders) >= 64:  # bounded (a recording shows one or two orders)
                self._orders.clear()
            self._orders[key] = got
        return got

    def _samples(self, blk: FrameBlock, tq: np.ndarray, idx: np.ndarray, bits: int,
                 counter: np.ndarray) -> list[Sample]:
        """The Samples of clean periods: their frames joined in TPDO order (an unreported
        TPDO as zeros), decoded by the streaming path's SampleLayout."""
        n, m1 = idx.shape
        rows = idx[:, 1:]
        c = blk.cid[rows]
        if (c == c[0]).all():  # the TPDOs in the same order in every period (the rule)
            q, byte, zero = self._gather(c[0])
            joined = blk.data.reshape(-1)[rows[:, q] * 8 + byte]
            if zero is not None:
                joined[:, zero] = 0
        else:
            joined = np.zeros((n, self.width), np.uint8)
            off = self.off_of[c]
            ln = self.len_of[c]
            for j in range(8):
                use = j < ln
                r, qq = np.nonzero(use)
                joined[r, off[r, qq] + j] = blk.data[rows[r, qq], j]
        raw = joined.tobytes()
        w = self.width
        t_sync = np.floor(tq[idx[:, 0]] * 1e6 + 0.5) / 1e6  # the assembler's own rounding
        seq0 = self.asm._next_seq
        sample = self.layout.sample
        out = []
        for i, (ti, ci) in enumerate(zip(t_sync.tolist(), counter.tolist())):
            out.append(sample([raw[i * w:(i + 1) * w]], bits, bits, seq0 + i, ci, ti, 0))
        return out


class _Periods:
    """What can be told of a block's SYNC periods before the replay reaches them, for
    periods awaiting the TPDO bits ``bits``: whose head (the SYNC and the next ``m``
    frames) is clean by itself (``first_ok``), and also against the period before it in the
    block (``inner``: the next counter, one period on, times never back, no frames
    between)."""

    def __init__(self, cr: ColumnarReplay, blk: FrameBlock, tq: np.ndarray,
                 syncs: np.ndarray, seg_end: np.ndarray, bits: int):
        clock, tap = cr.asm.clock, cr.tap
        n = len(blk)
        self.bits, self.tq, self.cand = bits, tq, syncs
        self.m = m = bin(bits).count("1")  # TPDOs per period
        room = (seg_end - syncs) >= m + 1
        self.idx = idx = np.minimum(syncs[:, None] + np.arange(m + 1), n - 1)
        c = blk.cid[idx[:, 1:]]
        known = c < len(cr.bit_of)
        cc = np.where(known, c, 0)
        b = np.where(known, cr.bit_of[cc], 0)
        ok = room & known.all(axis=1) & (np.bitwise_or.reduce(b, axis=1) == bits) \
            & (b.sum(axis=1) == bits) & (blk.dlc[idx[:, 1:]] == cr.len_of[cc]).all(axis=1)
        ov = clock.overflow
        self.counter = counter = blk.data[syncs, 0].astype(np.int64)
        ok &= (counter >= 1) & (counter <= ov)
        tt = tq[idx]
        self.ts, self.tlast = tt[:, 0], tt[:, -1]
        # within the head: times never back, a TPDO never far ahead of the clock
        ok &= (np.diff(tt, axis=1) >= 0).all(axis=1)
        ok &= (tt[:, 1:] <= tt[:, :-1] + tap._ahead_s).all(axis=1)
        self.first_ok = ok
        # against the period before it (the clock's base then is its SYNC)
        inner = ok.copy()
        if len(syncs) > 1:
            dt = clock.period
            gap = self.ts[1:] - self.ts[:-1]
            x = gap / dt
            inner[1:] &= (counter[1:] == counter[:-1] % ov + 1) & (np.abs(x - 1) <= clock.tol) \
                & ~(gap > 1.5 * dt) & (syncs[1:] == syncs[:-1] + m + 1) \
                & (self.ts[1:] >= self.tlast[:-1])
        inner[0] = False
        self._bad = np.flatnonzero(~inner)

    def run_end(self, k: int) -> int:
        """The end (exclusive) of the run of periods that follow period ``k`` cleanly."""
        j = int(np.searchsorted(self._bad, k + 1))
        return int(self._bad[j]) if j < len(self._bad) else len(self.cand)


def _t_range(p: Piece) -> tuple[float, float, bool]:
    """A piece's first and last time stamp, and whether it is non-decreasing inside."""
    if isinstance(p, FrameBlock):
        t = p.t
        return float(t[0]), float(t[-1]), bool(len(t) < 2 or np.all(t[1:] >= t[:-1]))
    return float(p.timestamp), float(p.timestamp), True


def _messages(p: Piece) -> Iterator[can.Message]:
    if isinstance(p, FrameBlock):
        for i in range(len(p)):
            yield p.message(i)
    else:
        yield p


def in_time_order(pieces: Iterator[Piece], reorder: FrameReorder, sync_id: int
                  ) -> Iterator[Piece]:
    """The pieces as the streaming path's reorder stage (daq.bus.reorder) would pass their
    frames on, the rule written once: while the stream is non-decreasing in time the stage
    changes nothing, so a piece is passed on whole once the :attr:`FrameReorder.window`
    frames after it are seen to keep the order; at the first frame out of order every piece
    not yet passed on goes frame by frame through ``reorder`` itself, its state as the
    stage's would be there (everything before released in order, the last at its time):
    the same frames, in the same order, with the same late and discontinuities."""
    held: deque[Piece] = deque()
    ahead = 0  # frames in held after the first piece
    last = -math.inf  # the latest time stamp seen (all seen so far in order)
    released = -math.inf  # the last time stamp passed on
    it = iter(pieces)
    while True:
        try:
            p = next(it)
        except StopIteration:
            break
        except Exception:  # a damaged recording: what came before it is replayed first
            yield from held
            raise
        t0, t1, inside = _t_range(p)
        if t0 < last or not inside:  # out of order: the stage's rule from here on
            reorder.last_out = reorder._last_in = released
            rest = (m for q in (*held, p) for m in _messages(q))
            yield from reordered(itertools.chain(rest, (m for q in it for m in _messages(q))),
                                 reorder=reorder, sync_id=sync_id)
            return
        last = t1
        held.append(p)
        if len(held) > 1:
            ahead += len(p) if isinstance(p, FrameBlock) else 1
        while len(held) > 1 and ahead >= reorder.window:
            first = held.popleft()
            released = _t_range(first)[1]
            nxt = held[0]
            ahead -= len(nxt) if isinstance(nxt, FrameBlock) else 1
            yield first
    yield from held


def replay_columnar(reader: ReaderBase, files: Sequence[Path], finish: bool = False,
                    names: Sequence[str | Path] | None = None,
                    block_bytes: int = BLOCK_BYTES) -> Iterator[Sample | HealthReport]:
    """The items of :func:`rsra.daq.bus.replay.replay` of the recording ``files``
    (replay.expand's), by the columnar path (frames out of order: the streaming path's
    reorder stage, :func:`in_time_order`)."""
    reorder = reader.monitor.reorder = FrameReorder()
    pieces = in_time_order(read_pieces(files, block_bytes, names=names), reorder,
                           reader.assembler.sync_cob_id)
    return ColumnarReplay(reader).run(pieces, finish=finish)
