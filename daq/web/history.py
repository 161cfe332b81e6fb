"""History for Open MCT's late joiners and time conductor: a bounded in-memory history of the
telemetry the gateway received, plus telemetry files on disk.

* :class:`History` keeps, per Zenoh key, the latest messages as their JSON text (compact:
  parsed only when asked) in a ring bounded by count (``history_s`` × the key's rate × 1.25)
  and by age (``history_s`` of acquisition time behind the newest message). Its memory is
  the bytes of the texts it holds (:attr:`History.bytes`), bounded by those counts.
* :class:`TelemetryFile` is a `rsra replay --out` JSONL file or an MCAP file from
  `rsra export --mcap`: its time span and keys are read once at start; a request scans the
  file again (nothing of it stays in memory). History never re-runs the estimator.

A request for one series between two times parses at most ``max_points`` messages per
source (evenly strided) so a long window stays cheap for the gateway and the browser.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path

import orjson

from rsra.daq.web.dictionary import Dictionary, points

MAX_POINTS = 4000  # per series and source in one history answer
LOW_RATE_CAP = 2000  # angles and health messages kept at most (besides the time bound)
# bytes of text kept per key at most: its count bound × 4 KiB (a sample's records are under
# 1 kB), at least 64 MiB (angles records with their posterior are tens of kB): a peer that
# publishes large valid records cannot grow the history beyond this
BYTES_PER_MESSAGE = 4096
MIN_KEY_BYTES = 64 << 20


class HistoryFileError(ValueError):
    """A telemetry file that cannot be read (one line naming the file and the fix)."""


def key_rates(cfg) -> dict[str, float]:
    """Messages per second of each key (telemetry.md), for the count bounds."""
    return {"hub_loads": cfg.sample_rate_hz, "channels": cfg.sample_rate_hz,
            "innovations": float(cfg.telemetry.innovations_hz), "health": 1.0}


class History:
    """Bounded history of the messages received, per key (thread-unsafe: one event loop)."""

    def __init__(self, history_s: float, rates: dict[str, float]):
        self.history_s = float(history_s)
        self.caps = {k: max(16, math.ceil(self.history_s * r * 1.25)) for k, r in rates.items()}
        self._t: dict[str, deque[float]] = {}
        self._text: dict[str, deque[str]] = {}
        self._key_bytes: dict[str, int] = {}
        self.bytes = 0
        self.evicted = 0

    def cap(self, key: str) -> int:
        return self.caps.get(key, LOW_RATE_CAP)

    def byte_cap(self, key: str) -> int:
        return max(MIN_KEY_BYTES, self.cap(key) * BYTES_PER_MESSAGE)

    def add(self, key: str, t: float, text: str) -> None:
        ts = self._t.setdefault(key, deque())
        tx = self._text.setdefault(key, deque())
        kb = self._key_bytes.get(key, 0)
        if ts and t < ts[-1]:  # out of order (a restarted service): start the key afresh
            self.bytes -= kb
            kb = 0
            self.evicted += len(tx)
            ts.clear()
            tx.clear()
        ts.append(t)
        tx.append(text)
        self.bytes += len(text)
        kb += len(text)
        cap, oldest, byte_cap = self.cap(key), t - self.history_s, self.byte_cap(key)
        while ts and (len(ts) > cap or ts[0] < oldest or kb > byte_cap):
            ts.popleft()
            n = len(tx.popleft())
            self.bytes -= n
            kb -= n
            self.evicted += 1
        self._key_bytes[key] = kb

    def count(self, key: str | None = None) -> int:
        if key is not None:
            return len(self._t.get(key, ()))
        return sum(len(v) for v in self._t.values())

    def span(self) -> tuple[float, float] | None:
        spans = [(v[0], v[-1]) for v in self._t.values() if v]
        if not spans:
            return None
        return min(s[0] for s in spans), max(s[1] for s in spans)

    def query(self, dic: Dictionary, mid: str, start_s: float, end_s: float,
              max_points: int = MAX_POINTS) -> list[dict]:
        return points_of(dic, mid, self.texts(dic, mid, start_s, end_s, max_points))

    def texts(self, dic: Dictionary, mid: str, start_s: float, end_s: float,
              max_points: int = MAX_POINTS) -> list[str]:
        """The texts a query parses (cheap: taken on the event loop, then parsed by
        :func:`points_of` anywhere — the history may change meanwhile)."""
        m = dic.by_id.get(mid)
        if m is None:
            return []
        ts, tx = self._t.get(m.source), self._text.get(m.source)
        if not ts or tx is None:  # (the two are made together)
            return []
        lo = bisect.bisect_left(ts, start_s)
        hi = bisect.bisect_right(ts, end_s)
        return [tx[i] for i in _strided(lo, hi, max_points)]


def _strided(lo: int, hi: int, max_points: int) -> range:
    n = hi - lo
    if n <= max_points:
        return range(lo, hi)
    step = math.ceil(n / max_points)
    return range(hi - 1 - ((hi - 1 - lo) // step) * step, hi, step)  # the newest included


def points_of(dic: Dictionary, mid: str, texts) -> list[dict]:
    """The points of series ``mid`` in the messages ``texts`` (of its key)."""
    m = dic.by_id.get(mid)
    if m is None:
        return []
    key = m.source
    out = []
    for text in texts:
        try:
            payload = orjson.loads(text) if isinstance(text, str) else text
        except ValueError:  # (orjson.JSONDecodeError is one)
            continue
        for pid, datum in points(dic, key, payload):
            if pid == mid:
                out.append(datum)
    return out


class TelemetryFile:
    """A telemetry file on disk (JSONL of `rsra replay --out`, or MCAP of `rsra export`)."""

    def __init__(self, path: str | Path, prefix: str):
        self.path = Path(path)
        self.prefix = prefix
        if not self.path.is_file():
            raise HistoryFileError(f"{self.path}: no such file; fix: give a `rsra replay --out` "
                                   "JSONL file or an MCAP file from `rsra export --mcap`")
        with open(self.path, "rb") as f:
            self.mcap = f.read(8) == b"\x89MCAP0\r\n"
        self.counts: dict[str, int] = {}
        self.t0 = math.inf
        self.t1 = -math.inf
        for key, t, _ in self._scan():
            self.counts[key] = self.counts.get(key, 0) + 1
            self.t0 = min(self.t0, t)
            self.t1 = max(self.t1, t)
        if not self.counts:
            raise HistoryFileError(f"{self.path}: no telemetry records with a time; fix: give "
                                   "a `rsra replay --out` JSONL file or an MCAP file from "
                                   "`rsra export --mcap`")

    def _scan(self, keys: set[str] | None = None) -> Iterator[tuple[str, float, dict]]:
        """(key, t, payload) of every record with a time."""
        try:
            if self.mcap:
                yield from self._scan_mcap(keys)
            else:
                yield from self._scan_jsonl(keys)
        except OSError as e:
            raise HistoryFileError(f"{self.path}: cannot read ({e.strerror}); fix: check the "
                                   "path and its permissions") from None

    def _scan_jsonl(self, keys):
        with open(self.path, encoding="utf-8", errors="replace") as f:
            for n, line in enumerate(f, start=1):
                if not line.strip():
                    continue
                try:
                    rec = orjson.loads(line)  # strict, and bounded nesting (no recursion)
                except ValueError:
                    raise HistoryFileError(
                        f"{self.path}:{n}: not a JSON line; fix: give a file written by "
                        "`rsra replay --out` or an MCAP file from `rsra export --mcap`") from None
                if not isinstance(rec, dict) or not isinstance(rec.get("key"), str):
                    raise HistoryFileError(f"{self.path}:{n}: a record without a \"key\"; fix: "
                                           "give a file written by `rsra replay --out`")
                key = rec.pop("key")
                t = rec.get("t")
                if (keys is None or key in keys) and isinstance(t, (int, float)):
                    yield key, float(t), rec

    def _scan_mcap(self, keys):
        from mcap.exceptions import McapError
        from mcap.reader import make_reader

        try:
            with open(self.path, "rb") as f:
                for _, channel, message in make_reader(f).iter_messages():
                    topic = channel.topic
                    if not topic.startswith(self.prefix + "/"):
                        continue
                    key = topic[len(self.prefix) + 1:]
                    if keys is not None and key not in keys:
                        continue
                    try:
                        payload = orjson.loads(message.data)
                    except ValueError:
                        continue
                    t = payload.get("t") if isinstance(payload, dict) else None
                    if isinstance(t, (int, float)):
                        yield key, float(t), payload
        except McapError as e:
            raise HistoryFileError(f"{self.path}: not a readable MCAP file ({e}); fix: give "
                                   "an MCAP file from `rsra export --mcap`") from None

    def query(self, dic: Dictionary, mid: str, start_s: float, end_s: float,
              max_points: int = MAX_POINTS) -> list[dict]:
        m = dic.by_id.get(mid)
        if m is None or m.source not in self.counts or end_s < self.t0 or start_s > self.t1:
            return []
        step = max(1, math.ceil(self.counts[m.source] * _overlap(self, start_s, end_s)
                                / max_points))
        out: list[dict] = []
        i = 0
        for _, t, payload in self._scan({m.source}):
            if start_s <= t <= end_s:
                if i % step == 0:
                    out.extend(d for pid, d in points(dic, m.source, payload) if pid == mid)
                i += 1
        return out


def _overlap(f: TelemetryFile, start: float, end: float) -> float:
    span = f.t1 - f.t0
    if span <= 0:
        return 1.0
    return max(0.0, min(end, f.t1) - max(start, f.t0)) / span


def merged_query(sources: list[Callable[[], list[dict]]]) -> list[dict]:
    """The answers of several sources, in time order (duplicates of one time kept once)."""
    seen, out = set(), []
    for src in sources:
        for d in src():
            if d["utc"] not in seen:
                seen.add(d["utc"])
                out.append(d)
    out.sort(key=lambda d: d["utc"])
    return out
