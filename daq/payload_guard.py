"""Every telemetry payload received over Zenoh is untrusted (docs/telemetry.md §1): the one
guard a viewer (`rsra listen`, `rsra web`) and the service put between a received payload and
anything that uses it.

:meth:`PayloadGuard.check` takes the bytes as received and returns the payload as a ``dict``
or raises :class:`BadPayload` with one line saying why:

1. **bounded size** (:data:`MAX_BYTES`) and **nesting depth** (:data:`MAX_DEPTH`), both
   checked on the bytes before any parser sees them (a ``[`` × 200 000 is refused by a
   count, never by a recursion);
2. **strict decoding**: UTF-8 and JSON (orjson: no lone surrogates, no number beyond a
   double). A non-finite number (``NaN``, ``Infinity``, ``1e400``), which no rsra service
   sends, becomes ``null`` as the service would write it (daq/jsonout.py) and the check says
   so (:attr:`Checked.non_finite`): the payload is kept, the message still counted;
3. **the key's schema**: the JSON Schema the exports declare for it (the caller passes
   ``daq.runtime.schema.json_schema`` of each key: one schema, never a second), compiled once
   (fastjsonschema). A key without a schema must still be a JSON object.

:meth:`PayloadGuard.receive` does the same and counts what it refused per key (a bounded
number of keys), for the one line a viewer shows (:meth:`PayloadGuard.lines`). Nothing
here raises anything but :class:`BadPayload`, whatever the bytes.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import fastjsonschema
import numpy as np
import orjson

# The largest payload rsra publishes is an `angles` record with its posterior, candidates and
# advice (tens of kB) or a `health` record of a large rig: 1 MiB is far above both.
MAX_BYTES = 1 << 20
# The deepest path of the declared schemas is 4 containers below the record
# (advice.accelerometers[].position_m); 32 leaves room for keys a newer service adds.
MAX_DEPTH = 32
# Keys whose refusals are counted one by one; a peer that sprays more keys than this has
# the rest counted together (the counters stay bounded).
MAX_COUNTED_KEYS = 64
OTHER_KEYS = "<other keys>"

# A JSON string (quotes and escapes), or an unterminated one up to the end: possessive, and
# never failing once it starts at a quote, so stripping strings is linear in the size.
_STRING = re.compile(rb'"(?:[^"\\]|\\.)*+(?:"|\\?\Z)', re.S)
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")
_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_OPEN[[ord("]"), ord("}")]] = -1


# control characters (C0, DEL, C1) and the invisible format characters that reorder or hide
# text: a peer's string must not move the cursor, retitle the terminal or disguise a value
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069]")


def printable(text: str) -> str:
    """``text`` from a peer with every control or invisible format character replaced by
    '?': safe to print on a terminal."""
    return _UNSAFE.sub("?", text)


class ZenohBytes(Protocol):
    """A payload as Zenoh hands it over (``zenoh.ZBytes``): its size known before a copy."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


Received = bytes | bytearray | memoryview | ZenohBytes


class BadPayload(ValueError):
    """A received payload refused: the message says why in a few words."""


@dataclass(frozen=True, slots=True)
class Checked:
    """A payload the guard let through."""

    #: the decoded payload (a JSON object; non-finite numbers replaced by None)
    payload: dict[str, Any]
    #: it held non-finite numbers (now null): not what a service sends
    non_finite: bool = False


def nesting_depth(data: bytes) -> int:
    """The deepest nesting of arrays and objects in a JSON text (brackets inside strings not
    counted), without parsing it; linear in ``len(data)``."""
    brackets = _STRING.sub(b'""', data).translate(None, _NOT_BRACKETS)
    if not brackets:
        return 0
    steps = _OPEN[np.frombuffer(brackets, np.uint8)].astype(np.int64)
    return int(np.cumsum(steps).max())


def _lenient(text: str) -> tuple[Any, bool]:
    """The stdlib's parse with every non-finite number as None; (value, any non-finite)."""
    seen = []

    def constant(_: str) -> None:
        seen.append(True)
        return None

    def number(s: str) -> float | None:
        v = float(s)
        if math.isfinite(v):
            return v
        seen.append(True)
        return None

    return json.loads(text, parse_constant=constant, parse_float=number), bool(seen)


_COMPILED: dict[str, Callable[[Any], Any]] = {}  # one per distinct schema (a handful)


def _compiled(schema: dict) -> Callable[[Any], Any]:
    """The schema's validator, compiled once per process (~30 ms a schema)."""
    text = json.dumps(schema, sort_keys=True)
    v = _COMPILED.get(text)
    if v is None:
        v = _COMPILED[text] = fastjsonschema.compile(schema)
    return v


def _schema_error(e: fastjsonschema.JsonSchemaValueException) -> str:
    where = (e.name or "data").replace("data.", "", 1).replace("data", "the record", 1)
    msg = e.message.replace(e.name or "data", "", 1).strip() if e.message else "invalid"
    return f"{where}: {msg}"[:200]


class PayloadGuard:
    """Checks received payloads against the declared schemas and counts the bad ones."""

    def __init__(self, schemas: Mapping[str, dict], *, max_bytes: int = MAX_BYTES,
                 max_depth: int = MAX_DEPTH) -> None:
        #: per key (the last part of the Zenoh key): the compiled validator of its schema
        self.validators: dict[str, Callable[[Any], Any]] = {
            k: _compiled(s) for k, s in schemas.items()}
        #: the size limit (bytes)
        self.max_bytes = max_bytes
        #: the nesting limit (arrays and objects)
        self.max_depth = max_depth
        #: refused messages per key (at most MAX_COUNTED_KEYS keys, then OTHER_KEYS)
        self.bad: dict[str, int] = {}
        #: the last reason a message of that key was refused
        self.last_reason: dict[str, str] = {}
        #: messages let through with non-finite numbers replaced by null, per key (bounded so)
        self.non_finite: dict[str, int] = {}

    def check(self, key: str, data: Received) -> Checked:
        """The payload of one message on ``key`` (the part after the prefix, or the whole
        key: its last part picks the schema); :class:`BadPayload` when refused. A Zenoh
        payload is sized before it is copied out."""
        if len(data) > self.max_bytes:
            raise BadPayload(f"{len(data)} bytes, more than {self.max_bytes}")
        raw = data.to_bytes() if hasattr(data, "to_bytes") else bytes(data)
        # the depth is at most the number of opening brackets: counted first (cheap), the
        # exact depth (strings skipped) only when that is over the limit
        brackets = raw.translate(None, _NOT_BRACKETS)
        if brackets.count(b"[") + brackets.count(b"{") > self.max_depth:
            depth = nesting_depth(raw)
            if depth > self.max_depth:
                raise BadPayload(f"nested {depth} deep, more than {self.max_depth}")
        non_finite = False
        try:
            value = orjson.loads(raw)
        except orjson.JSONDecodeError as e:
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise BadPayload("not UTF-8") from None
            try:  # a non-finite number is the one thing kept from what orjson refuses
                value, non_finite = _lenient(text)
                if non_finite:
                    orjson.dumps(value)  # and nothing else orjson refuses (a lone surrogate)
            except (ValueError, TypeError, RecursionError):
                non_finite = False
            if not non_finite:
                raise BadPayload(f"not JSON ({str(e).split(':', 1)[0]})") from None
        if not isinstance(value, dict):
            raise BadPayload(f"a JSON {type(value).__name__}, not an object")
        validate = self.validators.get(key.rsplit("/", 1)[-1])
        if validate is not None:
            try:
                validate(value)
            except fastjsonschema.JsonSchemaValueException as e:
                raise BadPayload(_schema_error(e)) from None
            except (ValueError, TypeError, RecursionError) as e:  # not expected: still refused
                raise BadPayload(f"cannot be validated ({type(e).__name__})") from None
        return Checked(value, non_finite)

    def receive(self, key: str, data: Received) -> Checked | None:
        """:meth:`check`, counting a refusal (None) and a non-finite payload."""
        try:
            got = self.check(key, data)
        except BadPayload as e:
            k = self._counted(self.bad, key)
            self.bad[k] = self.bad.get(k, 0) + 1
            self.last_reason[k] = str(e)
            return None
        if got.non_finite:
            k = self._counted(self.non_finite, key)
            self.non_finite[k] = self.non_finite.get(k, 0) + 1
        return got

    @staticmethod
    def _counted(counts: dict[str, int], key: str) -> str:
        return key if key in counts or len(counts) < MAX_COUNTED_KEYS else OTHER_KEYS

    @property
    def bad_total(self) -> int:
        return sum(self.bad.values())

    def lines(self) -> list[str]:
        """One line per key with refused or non-finite messages, for a viewer to show."""
        out = [f"{n} bad message{'s' if n != 1 else ''} from {k} (last: {self.last_reason[k]})"
               for k, n in sorted(self.bad.items())]
        out += [f"{n} message{'s' if n != 1 else ''} from {k} with non-finite numbers "
                "(shown as null)" for k, n in sorted(self.non_finite.items())]
        return [printable(line) for line in out]  # keys and field names come from the peer

    def as_json(self) -> dict[str, Any]:
        """The counters for a status endpoint or a summary (strict JSON)."""
        return {"bad_messages": self.bad_total, "bad_by_key": dict(self.bad),
                "last_reason": dict(self.last_reason), "non_finite": dict(self.non_finite)}
