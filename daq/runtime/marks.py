"""Operator marks: test points named during a run (`rsra mark "hover 40 kt"`, `rsra mark
--end`; docs/telemetry.md "<prefix>/mark", docs/user-guide.md "Loads survey").

The service subscribes to ``<prefix>/mark`` (the one key it listens to) and, when it records,
appends each valid mark to ``marks.jsonl`` in the recording folder, stamped with the time
``t`` of the latest sample it published (the samples' own time base, which `rsra survey`
uses). A mark arrives from outside and is untrusted: at most ``MARK_BYTES_MAX`` bytes, strict
UTF-8, one JSON object ``{"name": "<1…200 printable characters>"}`` or ``{"end": true}`` and
nothing else; anything else is counted and dropped (logged once per kind), never written.
At most ``MARKS_MAX`` marks are recorded per run.
"""
from __future__ import annotations

import json
import logging
import math
import os
import threading
from pathlib import Path
from typing import Any

log = logging.getLogger("rsra.marks")

MARK_KEY = "mark"
MARKS_FILE = "marks.jsonl"
MARK_BYTES_MAX = 1024
MARK_NAME_MAX = 200
MARKS_MAX = 10_000


class MarkError(ValueError):
    """A payload that is not a mark."""


def parse_mark(data: bytes) -> dict[str, Any]:
    """The mark a payload carries (``{"name": …}`` or ``{"end": True}``), else MarkError."""
    if len(data) > MARK_BYTES_MAX:
        raise MarkError(f"larger than {MARK_BYTES_MAX} bytes")
    try:
        obj = json.loads(data.decode("utf-8", errors="strict"))
    except (UnicodeDecodeError, ValueError):
        raise MarkError("not UTF-8 JSON") from None
    if not isinstance(obj, dict):
        raise MarkError("not a JSON object")
    if obj == {"end": True}:
        return {"end": True}
    name = obj.get("name")
    if set(obj) != {"name"} or not isinstance(name, str):
        raise MarkError('not {"name": "…"} or {"end": true}')
    if not 0 < len(name) <= MARK_NAME_MAX or not name.isprintable() or not name.strip():
        raise MarkError(f"a name must be 1 … {MARK_NAME_MAX} printable characters")
    return {"name": name}


def mark_payload(name: str | None) -> bytes:
    """What `rsra mark` puts: a name, or the end mark (None)."""
    obj: dict[str, Any] = {"end": True} if name is None else {"name": name}
    data = json.dumps(obj, ensure_ascii=False).encode("utf-8")
    parse_mark(data)  # the sender's own check: the same rules as the service's
    return data


class MarkRecorder:
    """Receives marks on ``<prefix>/mark`` and appends them to ``<folder>/marks.jsonl``.
    ``observe`` is a service sink: it keeps the time of the latest published sample."""

    def __init__(self, session, prefix: str, folder: str | os.PathLike[str]) -> None:
        #: where marks.jsonl goes (the recording folder)
        self.path = Path(folder) / MARKS_FILE
        #: the time of the latest hub_loads record (NaN before the first)
        self.t = math.nan
        #: marks written, and payloads refused
        self.written = 0
        self.refused = 0
        self._lock = threading.Lock()
        self._reasons: set[str] = set()
        self._closed = False
        self._sub = session.declare_subscriber(f"{prefix}/{MARK_KEY}", self._on_sample)

    def observe(self, key: str, payload: dict) -> None:
        if key == "hub_loads":
            t = payload.get("t")
            if isinstance(t, (int, float)):
                self.t = float(t)

    def _on_sample(self, sample) -> None:
        try:
            mark = parse_mark(bytes(sample.payload.to_bytes()))
        except MarkError as e:
            self._refuse(str(e))
            return
        self.receive(mark)

    def receive(self, mark: dict[str, Any]) -> None:
        with self._lock:
            if self._closed:
                return
            if self.written >= MARKS_MAX:
                self._refuse(f"more than {MARKS_MAX} marks in this run")
                return
            if not math.isfinite(self.t):
                self._refuse("before the first sample")
                return
            t = self.t
            line = json.dumps({"t": t, **mark}, ensure_ascii=False, allow_nan=False)
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(line + "\n")
                f.flush()
                os.fsync(f.fileno())
            self.written += 1
        log.info("mark at t=%.3f: %s", t, mark.get("name", "end"))

    def _refuse(self, reason: str) -> None:
        self.refused += 1
        if reason not in self._reasons and len(self._reasons) < 16:
            self._reasons.add(reason)
            log.warning("a payload on %s refused: %s (counted, not written)", MARK_KEY, reason)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - a session already closed
            pass
