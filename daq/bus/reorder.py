"""Frames back into recorded-time order before the sample assembler (docs/reliability.md
"SYNC counter and frame times").

A recording whose frames were written, copied or merged slightly out of order (a log
shuffled within a few thousand lines) must give the same samples as the ordered one: the
assembler works by frame order. :class:`FrameReorder` is a stable sort by recorded time
within a sliding window of :data:`REORDER_WINDOW` frames: a frame is held until the window
is full, then the earliest held frame (the first received of equal times) is released. Any
frame displaced by at most ``window`` places from where a stable sort of the whole stream
puts it comes out exactly there. A frame that arrives after a later-stamped frame was
already released (displaced further than the window) is **late**: it is released at once,
marked, and the replay counts and drops it (health ``bus.late``) — it is never turned into
lost samples.

Two interfaces, one rule (a test shows they agree on random inputs):

* streaming, one frame at a time: :meth:`FrameReorder.push` / :meth:`FrameReorder.flush`
  return the (index, late) pairs released, the index counting the frames pushed (from 0);
  :func:`reordered` wraps an iterable of ``can.Message`` with it;
* block: :meth:`FrameReorder.push_block` takes a numpy array of time stamps and returns the
  indices released and their late mask (numpy arrays); :func:`order` is a whole array at once:
  a permutation of ``range(n)`` and the late mask over the input.

The common case — times already non-decreasing — costs one comparison per frame (streaming:
an append and a pop of a deque) and one ``np.diff`` per block. Light on imports (numpy,
the standard library): the columnar replay reuses it.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Iterable, Iterator
from typing import Any, Protocol

import numpy as np

#: frames held back to put the stream into time order (≈ 0.8 s of the ground rig's traffic at
#: 200 samples/s): a log shuffled within this many lines replays as the ordered log
REORDER_WINDOW = 2048
#: a frame stamped this far before the latest one is not out of order but a discontinuity
#: (time went back: recordings joined, a clock stepped back): the held frames are released
#: and the window starts afresh from it (the assembler counts the discontinuity)
DISCONTINUITY_S = 1.0


class _Stamped(Protocol):
    timestamp: float


def _key(item: tuple[float, Any]) -> float:
    return item[0]


class FrameReorder:
    """The sliding-window stable sort by time stamp (see the module's text)."""

    def __init__(self, window: int = REORDER_WINDOW):
        if window < 0:
            raise ValueError(f"window {window}: must be >= 0")
        self.window = int(window)
        self._held: deque[tuple[float, Any]] = deque()  # (t, index or item), sorted, stable
        self._last_in = -math.inf  # the latest time held (the in-order test)
        self.last_out = -math.inf  # the time of the last frame released in order
        self.n = 0  # frames pushed
        self.late = 0  # frames released late
        self.late_syncs = 0  # of them SYNCs (a caller's count: see :func:`reordered`)
        self.discontinuities = 0  # times the stream went back (DISCONTINUITY_S): flushed
        self.reordered = 0  # frames that arrived before an earlier-stamped one (held, sorted)

    def push(self, t: float, item: Any = None) -> list[tuple[Any, bool]]:
        """One frame's time stamp (and what to hand back for it: by default its index, the
        frames pushed before it); the (item, late) pairs released by it, in order."""
        i = self.n if item is None else item
        self.n += 1
        held = self._held
        if t < max(self._last_in, self.last_out) - DISCONTINUITY_S:  # time went back
            out = [(j, False) for _, j in held]
            held.clear()
            held.append((t, i))
            self._last_in = t
            self.last_out = -math.inf
            self.discontinuities += 1
            return out
        if t < self.last_out:  # beyond the window: too late to be put in its place
            self.late += 1
            return [(i, True)]
        if t >= self._last_in:
            held.append((t, i))
            self._last_in = t
        else:  # out of order: into its place (after the held frames of equal time)
            self.reordered += 1
            held.insert(bisect.bisect_right(held, t, key=_key), (t, i))
        if len(held) > self.window:
            t0, i0 = held.popleft()
            self.last_out = t0
            return [(i0, False)]
        return []

    def flush(self) -> list[tuple[int, bool]]:
        """The end of the stream: every held frame, in order."""
        out = [(i, False) for _, i in self._held]
        if self._held:
            self.last_out = self._held[-1][0]
        self._held.clear()
        return out

    def push_block(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A block of time stamps (the next ``len(ts)`` frames): the indices released (int64,
        counting every frame pushed so far) and their late mask — exactly what :meth:`push`
        per frame gives. An already ordered block that continues the held frames is one
        ``np.diff`` and a slice."""
        ts = np.asarray(ts, dtype=np.float64)
        n = len(ts)
        if n and self._ordered(ts):
            base = self.n
            self.n += n
            held = [i for _, i in self._held]
            total = len(held) + n
            k = max(0, total - self.window)  # released now: the first k of held + block
            rel = np.concatenate([np.asarray(held[:k], dtype=np.int64),
                                  base + np.arange(max(0, k - len(held)), dtype=np.int64)])
            keep = list(self._held)[k:] if k < len(held) else []
            start = max(0, k - len(held))
            keep += zip(ts[start:].tolist(), range(base + start, base + n))
            if k:
                self.last_out = float(ts[k - len(held) - 1]) if k > len(held) else \
                    self._held[k - 1][0]
            self._held = deque(keep)
            self._last_in = float(ts[-1])
            return rel, np.zeros(len(rel), dtype=bool)
        idx: list[int] = []
        late: list[bool] = []
        for t in ts.tolist():
            for i, lt in self.push(t):
                idx.append(i)
                late.append(lt)
        return np.asarray(idx, dtype=np.int64), np.asarray(late, dtype=bool)

    def _ordered(self, ts: np.ndarray) -> bool:
        return bool(ts[0] >= self._last_in and ts[0] >= self.last_out
                    and (len(ts) < 2 or bool(np.all(ts[1:] >= ts[:-1]))))

    def flush_block(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`flush` as numpy arrays."""
        rel = self.flush()
        return (np.asarray([i for i, _ in rel], dtype=np.int64),
                np.zeros(len(rel), dtype=bool))


def order(ts: np.ndarray, window: int = REORDER_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """A whole stream of time stamps at once: the release order (a permutation of
    ``range(len(ts))``) and the late mask over the input (``late[i]``: frame ``i`` came
    more than ``window`` places late)."""
    r = FrameReorder(window)
    a, la = r.push_block(ts)
    b, _ = r.flush_block()
    perm = np.concatenate([a, b])
    late = np.zeros(len(ts), dtype=bool)
    late[a[la]] = True
    return perm, late


def reordered(frames: Iterable[Any], window: int = REORDER_WINDOW,
              reorder: FrameReorder | None = None, sync_id: int | None = None
              ) -> Iterator[Any]:
    """The frames (``can.Message``: ``timestamp``, ``arbitration_id``) in time order within
    ``window``; late frames are counted in ``reorder.late`` (SYNCs, COB-ID ``sync_id``, also
    in ``reorder.late_syncs``: the sample a late SYNC opened is late, not lost) and left out.
    The frames themselves are what the window holds; a frame in order (the common case) takes
    :meth:`FrameReorder.push`'s in-order branch inline, on the same state."""
    r = reorder if reorder is not None else FrameReorder(window)
    held = r._held
    push, append, popleft = r.push, held.append, held.popleft
    window = r.window
    src = iter(frames)
    while True:
        try:
            msg = next(src)
        except StopIteration:
            break
        except Exception:  # a damaged recording: the frames before it are replayed first
            for m, _ in r.flush():
                yield m
            raise
        t = msg.timestamp
        if t >= r._last_in and t >= r.last_out:  # in order (push's common branch, inline)
            r.n += 1
            append((t, msg))
            r._last_in = t
            if len(held) > window:
                t0, m0 = popleft()
                r.last_out = t0
                yield m0
            continue
        for m, late in push(t, msg):
            if not late:
                yield m
            elif m.arbitration_id == sync_id:
                r.late_syncs += 1
    for m, _ in r.flush():
        yield m
