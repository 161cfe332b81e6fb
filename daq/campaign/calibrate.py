"""`rsra campaign calibrate --dataset DIR [--recordings ID…] --out P.json`: the posterior of the
angles pooled across a campaign's recordings (docs/cli.md; docs/identification.md, "Pooling
recordings").

Reads ``DIR/manifest.parquet`` (the recordings, their ``status``, ``rig_fingerprint`` and
``t_start``) and each recording's ``information`` product
(``DIR/information/recording=<id>/*.parquet``, :mod:`rsra.daq.analysis.information`),
re-solves the pooled posterior with the prior counted once, writes the homogeneity test to
``DIR/calibration/homogeneity.parquet`` and shows it, and writes the posterior to ``--out``
unless the recordings disagree (exit 1, naming them). Recordings of two rigs, a missing
product, an unknown id: one line, exit 2.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

MANIFEST = "manifest.parquet"
RESULT_DIR = "calibration"
HOMOGENEITY_FILE = "homogeneity.parquet"


class CampaignCalibrationError(ValueError):
    """Bad input of `campaign calibrate`: one line, exit 2."""


def add_parser(subparsers: Any, name: str) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        name, help="the angles' posterior pooled across a campaign's recordings",
        description="Re-solves the known-load identification of the 14 angles from the "
        "recordings' likelihood information in a campaign dataset (the information product of "
        "`rsra campaign run`), with the prior counted once, the rig's drift allowance between "
        "recordings in time order, the reference load and the load spread; tests whether the "
        "recordings agree (χ² homogeneity at 1e-3 and the drift trend in time order), writes "
        "that test to DIR/calibration/homogeneity.parquet and shows it; writes the posterior in "
        "the state-file format (rsra angles show; --angles of run and replay) unless the "
        "recordings disagree: then exit 1, naming them. Recordings of different rigs are "
        "refused (exit 2).")
    p.add_argument("--config", metavar="PATH", default=None, action="append",
                   help="the rig the campaign ran with (as for `rsra campaign run`; default the "
                   "packaged rig); its fingerprint must be the recordings'")
    p.add_argument("--dataset", metavar="DIR", required=True,
                   help="a campaign dataset (DIR/manifest.parquet)")
    p.add_argument("--recordings", nargs="+", metavar="ID", default=None,
                   help="pool only these recordings (ids of the manifest; default every "
                   "recording whose status is ok)")
    p.add_argument("--out", metavar="P.json", required=True,
                   help="the posterior file to write (a new file, or a posterior it replaces)")
    p.add_argument("--json", action="store_true",
                   help='print the result as JSON ({"posterior", "homogeneity", "trend", '
                   '"recordings", …}; docs/cli.md)')
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except CampaignCalibrationError as e:
        print(f"rsra campaign calibrate: error: {e}", file=sys.stderr)
        return 2


def _fail(text: str) -> CampaignCalibrationError:
    return CampaignCalibrationError(" ".join(str(text).split()))


def _run(args: argparse.Namespace) -> int:
    from rsra.config.rig import ConfigError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.analysis.information import (
        PoolingError,
        pooled_posterior,
        read_information,
        summary_lines,
    )
    from rsra.daq.runtime.persistence import save_posterior
    from rsra.daq.runtime.posterior_file import classify

    dataset = Path(args.dataset)
    out = Path(args.out)
    kind, _, problem = classify(out)
    if kind not in ("absent", "posterior"):
        raise _fail(f"--out {args.out}: {problem or 'a damaged posterior'}; it replaces only a "
                    "posterior file — name a new file")
    if not os.access(out.resolve().parent, os.W_OK):
        raise _fail(f"--out {args.out}: folder {out.resolve().parent} is not writable")
    try:
        cfg = load_rig(args.config)
    except ConfigError as e:
        raise _fail(f"configuration error: {e}") from None
    rows = _manifest(dataset)
    chosen = _choose(rows, args.recordings)
    files = {}
    for r in chosen:
        folder = dataset / "information" / f"recording={r['recording']}"
        parts = sorted(folder.glob("*.parquet")) if folder.is_dir() else []
        if not parts:
            raise _fail(f"recording {r['recording']}: no information product ({folder}); rerun "
                        "`rsra campaign run` with this rsra (it writes it)")
        files[str(r["recording"])] = parts
    try:
        table, columns = read_information(files)
        times = {str(r["recording"]): _seconds(r.get("t_start")) for r in chosen}
        empty = [rid for rid in files if rid not in set(table.column("recording").to_pylist())]
        if empty and args.recordings:
            raise PoolingError(f"recording {empty[0]}: no known-load information (no samples "
                               "with the reference balance)")
        pooled = pooled_posterior(cfg, table, columns, times=times)
    except PoolingError as e:
        raise _fail(str(e)) from None
    rep = pooled.report()
    rep["skipped"] = empty
    _write_homogeneity(dataset / RESULT_DIR / HOMOGENEITY_FILE, rep)
    if args.json:
        print(json.dumps(_strict(rep), allow_nan=False))
    else:
        print("\n".join(summary_lines(rep)))
    if not pooled.homogeneous:
        print("rsra campaign calibrate: the recordings disagree (homogeneity test at 1e-3): "
              f"{', '.join(pooled.disagree())}; no posterior written", file=sys.stderr)
        return 1
    save_posterior(out, pooled.state)
    if not args.json:
        print(f"wrote {out}: the posterior of the 14 angles from {len(pooled.recordings)} "
              "recording(s) (rsra angles show; --angles of run and replay)")
    return 0


def _manifest(dataset: Path) -> list[dict]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = dataset / MANIFEST
    if not path.is_file():
        raise _fail(f"--dataset {dataset}: no {MANIFEST} (not a campaign dataset; make one with "
                    "`rsra campaign run --dataset DIR`)")
    try:
        rows = pq.read_table(path).to_pylist()
    except (OSError, pa.ArrowException) as e:
        raise _fail(f"{path}: not a readable manifest ({e})") from None
    if rows and not {"recording", "rig_fingerprint", "status"} <= set(rows[0]):
        raise _fail(f"{path}: a manifest needs the columns recording, rig_fingerprint, status")
    return rows


def _choose(rows: list[dict], wanted: list[str] | None) -> list[dict]:
    """The recordings to pool: the named ones (each must be in the manifest and ok), or every
    ok one; all of one rig fingerprint."""
    by_id = {str(r["recording"]): r for r in rows}
    if wanted:
        for rid in wanted:
            if rid not in by_id:
                raise _fail(f"--recordings {rid}: not in the manifest (its recordings: "
                            f"{', '.join(list(by_id)[:5])}{' …' if len(by_id) > 5 else ''})")
            if by_id[rid]["status"] != "ok":
                raise _fail(f"--recordings {rid}: its status is {by_id[rid]['status']!r} "
                            f"({by_id[rid].get('reason') or 'no reason given'}), not ok")
        chosen = [by_id[r] for r in dict.fromkeys(wanted)]
    else:
        chosen = [r for r in rows if r["status"] == "ok"]
    if not chosen:
        raise _fail("no recording with status ok in the manifest: nothing to pool")
    first: dict[str, str] = {}
    for r in chosen:
        first.setdefault(str(r["rig_fingerprint"]), str(r["recording"]))
    if len(first) > 1:
        a, b = list(first.values())[:2]
        raise _fail(f"recordings of {len(first)} rigs (different rig fingerprints: {a} and {b}); "
                    "pool the recordings of one rig (--recordings)")
    return chosen


def _seconds(v: Any) -> float:
    """A manifest time (seconds, or a datetime) as seconds; NaN when unknown."""
    if v is None:
        return math.nan
    if hasattr(v, "timestamp"):
        return float(v.timestamp())
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _strict(x: Any) -> Any:
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    return x


def _write_homogeneity(path: Path, rep: dict) -> None:
    """One row per recording with the test's figures; the whole test in the metadata
    (``rsra.homogeneity``, JSON). Atomic (temporary file, rename)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from rsra.daq.runtime.persistence import AtomicOutput

    rows = rep["recordings"]
    table = pa.table({
        "recording": [r["recording"] for r in rows],
        "t_start": pa.array([r["t_start"] for r in rows], pa.float64()),
        "windows": pa.array([r["windows"] for r in rows], pa.int64()),
        "scored": pa.array([r["scored"] for r in rows], pa.int64()),
        "determined": pa.array([r["determined"] for r in rows], pa.int32()),
        "sequential_chi2": pa.array([r["sequential_chi2"] for r in rows], pa.float64()),
        "sequential_dof": pa.array([r["sequential_dof"] for r in rows], pa.int32()),
        "leave_one_out_chi2": pa.array([r["leave_one_out_chi2"] for r in rows], pa.float64()),
        "leave_one_out_p": pa.array([r["leave_one_out_p"] for r in rows], pa.float64()),
        "disagrees": pa.array([r["disagrees"] for r in rows], pa.bool_()),
        "estimate_deg": pa.array([r["estimate_deg"] for r in rows], pa.list_(pa.float64())),
    })
    whole = {k: v for k, v in rep.items() if k != "recordings"}
    table = table.replace_schema_metadata(
        {b"rsra.homogeneity": json.dumps(_strict(whole), allow_nan=False).encode()})
    path.parent.mkdir(exist_ok=True)
    f = AtomicOutput(path, "wb")
    try:
        pq.write_table(table, f.open())
        f.commit()
    finally:
        f.discard()
