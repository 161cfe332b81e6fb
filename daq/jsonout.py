"""Strict JSON for every payload (docs/telemetry.md): non-finite numbers become null, never NaN."""
from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np
import orjson


def sanitise(obj: Any) -> Any:
    """numpy → lists, non-finite floats → None, recursively."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            if np.count_nonzero(np.isfinite(obj)) == obj.size:  # (cheaper than .all())
                return obj.tolist()
            return np.where(np.isfinite(obj), obj, None).tolist()  # type: ignore[call-overload]  # numpy's stubs take no None (an object array)
        return obj.tolist()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (np.floating,)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, dict):
        return {str(k): sanitise(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [sanitise(v) for v in obj]
    return obj


def _default(obj: Any) -> Any:
    """The fast path's numpy conversions (the same as ``sanitise``'s) for what the C encoder
    cannot take itself; anything else is refused, and ``dumps`` takes the slow path."""
    if isinstance(obj, np.ndarray):
        return sanitise(obj)
    if isinstance(obj, np.floating):  # not a float subclass (float32, float16)
        v = float(obj)
        if not math.isfinite(v):
            raise ValueError("non-finite")  # → slow path, which publishes null
        return v
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise TypeError(type(obj).__name__)


# The stdlib path's encoders, built once: json.dumps with non-default arguments builds a new
# JSONEncoder on every call. Its fast path is the usual payload (string keys, no non-finite
# Python float) encoded directly, numpy arrays converted as met — the same text as
# ``sanitise`` first; a non-finite float (the encoder refuses it) or anything else unusual
# goes through ``sanitise``.
_FAST = json.JSONEncoder(allow_nan=False, separators=(",", ":"), default=_default)
_STRICT = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def _stdlib(obj: Any) -> str:
    """The reference path: the C encoder with numpy conversions, else ``sanitise`` first."""
    try:
        return _FAST.encode(obj)
    except (ValueError, TypeError):
        return _STRICT.encode(sanitise(obj))


def _orjson_default(obj: Any) -> Any:
    """orjson's hook for what it does not take itself: numpy, as ``sanitise`` converts it
    (orjson writes a non-finite float as null, so a float array needs no check); anything
    else — and an object array, whose contents the stdlib path judges — is refused, and
    ``dumpb`` takes the stdlib path."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fiub":
            return obj.tolist()
        raise TypeError("object array")
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise TypeError(type(obj).__name__)


# Subclasses (IntEnum, str subclasses), dataclasses and datetimes go to the hook (refused →
# stdlib path), so they are encoded, or refused, exactly as before.
_ORJSON_OPTIONS = (orjson.OPT_PASSTHROUGH_SUBCLASS | orjson.OPT_PASSTHROUGH_DATACLASS
                   | orjson.OPT_PASSTHROUGH_DATETIME)
# Where orjson's text differs from the stdlib's: a float with a one-digit negative exponent
# (orjson "1.5e-7", Python "1.5e-07") or in [1e-5, 1e-4) (orjson "0.00001", Python "1e-05").
# Both write the same shortest round-trip digits and the same text everywhere else (checked
# on 4·10⁶ doubles of every magnitude, tests/test_jsonout.py). A match in a string is only a
# needless fallback. The regular expression runs only when a substring test finds a candidate
# (a search with a look-behind costs ~10× the encoding).
_DIFFERS = re.compile(rb"e-\d(?!\d)|(?<!\d)0\.0000")


def _differs(out: bytes) -> bool:
    return (b"e-" in out or b"0.0000" in out) and _DIFFERS.search(out) is not None


def dumpb(obj: Any) -> bytes:
    """``dumps(obj)`` as UTF-8 bytes (what Zenoh sends), byte for byte.

    Encoded by orjson (≈ 15× faster than the stdlib encoder: float formatting is most of a
    record's cost, docs/performance.md), and its text kept only where it is the stdlib's:
    pure ASCII without DEL (the stdlib escapes both as ``\\uXXXX``) and no float written in
    one of the two forms the stdlib writes otherwise (``_DIFFERS``). Anything else — such a
    float, a non-ASCII string, a non-string key, an integer beyond 64 bits, a type orjson
    refuses — takes the stdlib path. orjson also encodes an Enum or a UUID, which the
    stdlib refuses; no payload holds one."""
    try:
        out = orjson.dumps(obj, default=_orjson_default, option=_ORJSON_OPTIONS)
    except TypeError:  # orjson.JSONEncodeError
        return _stdlib(obj).encode()
    if out.isascii() and b"\x7f" not in out and not _differs(out):
        return out
    return _stdlib(obj).encode()


def dumps(obj: Any) -> str:
    """``json.dumps(sanitise(obj))``, strict and compact: non-finite numbers become null,
    numpy values their Python equivalents. Text for text the stdlib's (``_stdlib``), through
    orjson where that gives the same text (``dumpb``)."""
    return dumpb(obj).decode()
