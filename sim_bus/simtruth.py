"""What the simulated bus carried, kept for the truth file and the live views: every sample's
fields (:class:`TruthBuffer`), per SYNC cycle the sample, counter, time and loss
(:class:`SyncLog`), and :class:`SimTruth`, which keeps both for one simulator and turns them
into the sim_bus.truth arrays.
"""
from __future__ import annotations

import dataclasses
import logging
from collections import deque
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from rsra.sim_bus.offline import ChannelCodec

log = logging.getLogger("rsra.sim_bus.bus_sim")  # the simulator's log, as before the split

RECENT_SAMPLES = 512  # the last samples' truth, whatever keep_samples says (live views)
MAX_TRUTH_SAMPLES = 720_000  # one hour at 200 samples/s: the truth history is bounded


class TruthBuffer:
    """The samples the bus carried, stored compactly: one growing array per sample field (in
    chunks, so appending is cheap and memory is ~8 bytes per number, not a Python object per
    sample). Bounded: past ``max_samples`` further samples are counted, not kept.

    ``spill=True``: every full chunk goes to an anonymous temporary file (``TMPDIR``; it has
    no name on disk and disappears with the process, even after ``kill -9``), so resident
    memory stays flat over a long run; :meth:`arrays` reads them back (at the end, to write
    the truth file)."""

    def __init__(self, max_samples: int = MAX_TRUTH_SAMPLES, chunk: int = 4096,
                 spill: bool = False):
        self.max_samples, self.chunk = int(max_samples), int(chunk)
        self.spill = spill
        self._fields: list[str] | None = None
        self._chunks: dict[str, list[np.ndarray | tuple[int, np.dtype, tuple]]] = {}
        self._n = 0
        self._file: Any = None
        self.dropped = 0

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes held in memory (chunks not spilled)."""
        return sum(c.nbytes for v in self._chunks.values() for c in v if isinstance(c, np.ndarray))

    def append(self, sample: Any) -> None:
        if self._n >= self.max_samples:
            self.dropped += 1
            return
        if self._fields is None:
            if dataclasses.is_dataclass(sample):
                self._fields = [f.name for f in dataclasses.fields(sample)]
            else:
                self._fields = list(vars(sample))
        row = self._n % self.chunk
        for name in self._fields:
            v = getattr(sample, name)
            if row == 0:
                a = np.asarray(v)
                self._chunks.setdefault(name, []).append(np.zeros((self.chunk,) + a.shape, a.dtype))
            self._chunks[name][-1][row] = v  # type: ignore[index]  # the chunk being filled: an array (spilled ones are (offset, dtype, shape))
        self._n += 1
        if self.spill and row == self.chunk - 1:
            self._spill_last()

    def _spill_last(self) -> None:
        import tempfile

        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="rsra-truth-")  # noqa: SIM115 (lives with the buffer)
        f = self._file
        f.seek(0, 2)
        for chunks in self._chunks.values():
            a = chunks[-1]
            assert isinstance(a, np.ndarray)  # the chunk just filled, in memory
            chunks[-1] = (f.tell(), a.dtype, a.shape)
            f.write(a.tobytes())

    def _load(self, c) -> np.ndarray:
        if isinstance(c, np.ndarray):
            return c
        off, dtype, shape = c
        self._file.seek(off)
        return np.fromfile(self._file, dtype=dtype, count=int(np.prod(shape))).reshape(shape)

    def arrays(self) -> dict[str, np.ndarray]:
        """Every field stacked over the kept samples (first axis = sample)."""
        return {k: np.concatenate([self._load(c) for c in v])[: self._n]
                for k, v in self._chunks.items()}

    def __getitem__(self, k: int) -> SimpleNamespace:
        """Sample k's fields (a view into the buffer)."""
        if not -self._n <= k < self._n:
            raise IndexError(k)
        k %= self._n
        c, r = divmod(k, self.chunk)
        return SimpleNamespace(**{f: self._load(self._chunks[f][c])[r]
                                  for f in (self._fields or [])})


class SyncLog:
    """Per SYNC cycle: (sample index, counter (-1: none), time, lost), compactly. With
    ``keep`` every cycle up to ``max_n`` (the truth file's sync arrays), in a spilled
    :class:`TruthBuffer` (resident memory flat); without, only the last ``recent`` (live
    views, tests that look back a little) in a ring — what a run without a truth file needs.
    ``len()`` is the number of cycles ever appended."""

    _DTYPE = np.dtype([("k", np.int64), ("counter", np.int16), ("t", np.float64),
                       ("lost", np.bool_)])

    def __init__(self, keep: bool, max_n: int = MAX_TRUTH_SAMPLES, recent: int = RECENT_SAMPLES,
                 chunk: int = 4096):
        self.keep = keep
        self.capacity = int(max_n) if keep else int(recent)
        #: keep: every cycle (None without)
        self._buf = TruthBuffer(self.capacity, chunk, spill=True) if keep else None
        #: without keep: the last ``recent`` cycles (empty with keep)
        self._ring = np.zeros(0 if keep else self.capacity, self._DTYPE)
        self._n = 0  # appended in all

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        return self._buf.nbytes if self._buf is not None else self._ring.nbytes

    def append(self, entry: tuple[int, int, float, bool]) -> None:
        n = self._n
        self._n += 1
        if self._buf is not None:
            k, c, t, lost = entry
            self._buf.append(SimpleNamespace(k=int(k), counter=int(c), t=float(t),
                                             lost=bool(lost)))
        else:
            self._ring[n % self.capacity] = entry

    def _span(self) -> tuple[int, int]:
        """(first, number) of the entries held."""
        if self._buf is not None:
            return 0, len(self._buf)
        held = min(self._n, self.capacity)
        return self._n - held, held

    def __getitem__(self, i: int) -> tuple[int, int, float, bool]:
        """Entry ``i`` (0 = the first SYNC cycle; negative from the latest), if held."""
        if i < 0:
            i += self._n
        first, held = self._span()
        if not first <= i < first + held:
            raise IndexError(f"SYNC cycle {i} is not kept (keep_samples=False keeps the last "
                             f"{self.capacity})")
        if self._buf is not None:
            e = self._buf[i]
            return int(e.k), int(e.counter), float(e.t), bool(e.lost)
        r = self._ring[i % self.capacity]
        return int(r["k"]), int(r["counter"]), float(r["t"]), bool(r["lost"])

    def __iter__(self):
        a = self.arrays()
        for r in a:
            yield int(r["k"]), int(r["counter"]), float(r["t"]), bool(r["lost"])

    def arrays(self) -> np.ndarray:
        """The entries held, in order (a structured array: k, counter, t, lost)."""
        first, held = self._span()
        out = np.zeros(held, self._DTYPE)
        if not held:
            return out
        if self._buf is not None:
            for name, v in self._buf.arrays().items():
                out[name] = v
        else:
            idx = np.arange(first, first + held) % self.capacity
            out[:] = self._ring[idx]
        return out




class SimTruth:
    """One simulator's truth: the samples the bus carried (all of them with ``keep_samples``,
    bounded, spilled to an anonymous temporary file; else only the recent ones for live
    views) and per SYNC cycle its :class:`SyncLog` entry."""

    def __init__(self, keep_samples: bool):
        #: every sample is kept (a truth file will be written)
        self.keep_samples = keep_samples
        #: what every SYNC carried (keep_samples), bounded, spilled chunk by chunk
        self.samples = TruthBuffer(spill=keep_samples)
        #: the latest truth, for live views (kept even without history)
        self.last_sample: Any = None
        #: the last samples, bounded, for live views
        self.recent_samples: deque = deque(maxlen=RECENT_SAMPLES)
        #: (sample, counter, t, lost) per SYNC cycle
        self.sync_info = SyncLog(keep_samples)
        #: the history filled up: later samples were not kept
        self.truth_truncated = False

    def take(self, s: Any) -> None:
        """Sample ``s`` went on the bus."""
        self.last_sample = s
        self.recent_samples.append(s)
        if self.keep_samples:
            self.samples.append(s)
            if self.samples.dropped == 1 and not self.truth_truncated:
                self.truth_truncated = True
                log.warning("truth history full (%d samples): later samples are not kept",
                            self.samples.max_samples)

    def sync_arrays(self) -> dict[str, np.ndarray]:
        """Per sample: index, SYNC counter (0: the SYNC carried none), SYNC time, lost flag."""
        a = self.sync_info.arrays()
        return {"sample_index": a["k"].astype(np.int64),
                "sync_counter": np.maximum(a["counter"], 0).astype(np.uint8),
                "sync_time": a["t"].astype(float), "sync_lost": a["lost"].astype(bool)}

    def truth_arrays(self, codec: ChannelCodec) -> dict[str, np.ndarray]:
        """The kept samples as sim_bus.truth arrays: the physics truth, the channels as the bus
        carried them before faults (quantised by ``codec``, with the raw counts), and per
        sample the SYNC counter, time and loss. Needs keep_samples=True."""
        arrs = self.samples.arrays()
        if not arrs:
            raise ValueError("no samples kept: run with keep_samples=True and at least one SYNC")
        enc = codec.encode(**{k: arrs[k] for k in
                              ("T", "cell_status", "accel", "omega", "azimuth",
                               "H_balance", "drive")})
        arrs.update(codec.decode(enc))
        arrs["accel_counts"], arrs["azimuth_counts"] = enc.accel_counts, enc.azimuth_counts
        n = len(arrs["index"])
        sync = self.sync_arrays()
        arrs["sync_counter"] = sync["sync_counter"][:n]
        arrs["sync_time"] = sync["sync_time"][:n]
        arrs["sync_lost"] = sync["sync_lost"][:n]
        return arrs
