"""Truth files: what the simulator really did, written beside the bus output (model.md §8).

One compressed `.npz` per run (format documented in docs/simulator.md):

* per-sample arrays (first axis = sample): `index`, `sync_counter`, `t`, the truth
  (`H_true`, `alpha_true`, `T_true`, `accel_true`, `unmodelled`, `I_true`, `drive_true`,
  `base_accel`) and the channels as sent on the bus (`T`, `cell_status`, `accel`,
  `accel_counts`, `omega`, `azimuth`, `azimuth_counts`, `H_balance`, `drive`);
* `faults_json`: a JSON list of the injected faults (dicts, written by whoever injects them);
* `meta_json`: a JSON object (scenario, seed, rig, names, units, …);
* `format_version`.

Nothing is pickled: `read_truth` loads with allow_pickle=False.
"""
from __future__ import annotations

import io
import json
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .offline import SimRun

TRUTH_FORMAT_VERSION = 1
PER_SAMPLE_KEYS = (
    "index", "sync_counter", "t",
    "H_true", "alpha_true", "T_true", "accel_true", "unmodelled", "I_true", "drive_true",
    "base_accel",
    "T", "cell_status", "accel", "accel_counts", "omega", "azimuth", "azimuth_counts",
    "H_balance", "drive",
)
REQUIRED_KEYS = ("index", "t", "H_true", "alpha_true", "T_true")


def sync_counters(index: np.ndarray, counter_overflow: int = 240) -> np.ndarray:
    """CiA 301 SYNC counter of each sample when the first SYNC carries 1 (0: no counter)."""
    index = np.asarray(index, dtype=np.int64)
    if counter_overflow == 0:
        return np.zeros(index.shape, np.uint8)
    return (index % counter_overflow + 1).astype(np.uint8)


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def write_truth(path: str | Path, run_or_arrays: SimRun | Mapping[str, np.ndarray],
                faults: Iterable[Mapping[str, Any]] = (), meta: Mapping[str, Any] | None = None,
                sync_counter: np.ndarray | None = None, counter_overflow: int = 240,
                write: Callable[[Path, bytes], None] | None = None) -> Path:
    """Write a truth file; returns its path (".npz" appended if missing). ``write(path,
    data)`` writes the file's bytes (the command line passes its atomic write: temporary
    file, fsync, rename); by default the file is written in place."""
    if isinstance(run_or_arrays, SimRun):
        arrays = run_or_arrays.arrays()
        meta = {**run_or_arrays.meta, **(meta or {})}
    else:
        arrays = dict(run_or_arrays)
        meta = dict(meta or {})
    missing = [k for k in REQUIRED_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"truth needs the arrays {missing}")
    n = len(arrays["index"])
    if sync_counter is None and "sync_counter" not in arrays:
        arrays["sync_counter"] = sync_counters(arrays["index"], counter_overflow)
    elif sync_counter is not None:
        arrays["sync_counter"] = np.asarray(sync_counter)
    out = {}
    for k, v in arrays.items():
        v = np.asarray(v)
        if v.dtype == object:
            raise ValueError(f"truth array {k!r} has dtype object; give numbers")
        if k in PER_SAMPLE_KEYS and len(v) != n:
            raise ValueError(f"truth array {k!r} has {len(v)} samples, index has {n}")
        out[k] = v
    out["faults_json"] = np.array(json.dumps(_jsonable(list(faults)), allow_nan=False))
    out["meta_json"] = np.array(json.dumps(_jsonable(meta), allow_nan=False))
    out["format_version"] = np.array(TRUTH_FORMAT_VERSION)
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    if write is None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **out)  # type: ignore[arg-type]  # numpy types **kwds against its allow_pickle keyword
        return path
    buf = io.BytesIO()
    np.savez_compressed(buf, **out)  # type: ignore[arg-type]  # numpy types **kwds against its allow_pickle keyword
    write(path, buf.getvalue())
    return path


def read_truth(path: str | Path) -> dict[str, Any]:
    """The arrays of a truth file, with `faults` (list of dicts) and `meta` (dict) decoded."""
    with np.load(Path(path), allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    version = int(d.pop("format_version", 0))
    if version != TRUTH_FORMAT_VERSION:
        raise ValueError(f"{path}: truth format {version}, this code reads {TRUTH_FORMAT_VERSION}")
    d["faults"] = json.loads(str(d.pop("faults_json")))
    d["meta"] = json.loads(str(d.pop("meta_json")))
    return d
