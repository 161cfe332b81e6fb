"""Strict JSON for every payload (telemetry.md): non-finite numbers become null, never NaN."""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def sanitise(obj: Any) -> Any:
    """numpy → lists, non-finite floats → None, recursively."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            if np.isfinite(obj).all():
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


def dumps(obj: Any) -> str:
    return json.dumps(sanitise(obj), allow_nan=False, separators=(",", ":"))
