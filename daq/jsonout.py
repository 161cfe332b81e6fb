"""Strict JSON for every payload (docs/telemetry.md): non-finite numbers become null, never NaN."""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def sanitise(obj: Any) -> Any:
    """numpy → lists, non-finite floats → None, recursively."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            if np.count_nonzero(np.isfinite(obj)) == obj.size:  # (cheaper than .all())
                return obj.tolist()
            return np.where(np.isfinite(obj), obj, None).tolist()
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


# One encoder built once: json.dumps with non-default arguments builds a new JSONEncoder on
# every call, a third of the cost of a hub_loads record (docs/performance.md P5).
_FAST = json.JSONEncoder(allow_nan=False, separators=(",", ":"), default=_default)
_STRICT = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def dumps(obj: Any) -> str:
    """``json.dumps(sanitise(obj))``, strict and compact. The usual payload (string keys, no
    non-finite Python float) is encoded directly, numpy arrays converted as met — the same
    text without first copying the whole tree; a non-finite float (the encoder refuses it)
    or anything else unusual goes through ``sanitise`` as before."""
    try:
        return _FAST.encode(obj)
    except (ValueError, TypeError):
        return _STRICT.encode(sanitise(obj))
