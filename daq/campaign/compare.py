"""`rsra campaign compare BASE NEW`: per recording, what changed beyond a stated tolerance
between two datasets of the same recordings (the automated bus-replay test a rig team runs
in CI: docs/user-guide.md "Campaigns").

Checked per recording (matched by recording id), each against its tolerance:

* **hub loads**: every sample (matched by ``seq``), ``|H_new − H_base| / σ`` on each axis,
  σ the base's published ``√(sigma_angles² + sigma_filter²)``: worst over the recording
  ≤ ``--hub-tol`` (default 0.1 σ); the number of samples must be equal;
* **flags**: the samples whose flags differ ≤ ``--flags-tol`` (default 0);
* **health counts**: the integer counters of the last health record (frames, losses,
  boots, …) equal;
* **accepted runs**: the manifest's count equal;
* **angles**: the last accepted posterior of each angle, ``|Δα| / σ`` (the base's
  ``sigma_deg``) ≤ ``--angle-tol`` (default 0.1 σ);
* a recording ``ok`` in BASE that is missing or ``failed`` in NEW is a regression.

Exit 1 on any regression, 0 when none (a recording new in NEW is listed, not a regression).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rsra.daq.campaign.dataset import MANIFEST, CampaignError, read_manifest

AXES = ("X", "Y", "Z", "L", "M", "N")


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="what changed between two datasets, per recording; exit 1 "
                       "on a regression (CI)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base", metavar="BASE_DIR", help="the reference dataset")
    p.add_argument("new", metavar="NEW_DIR", help="the dataset to check against it")
    p.add_argument("--hub-tol", type=float, default=0.1, metavar="SIGMAS",
                   help="largest hub-load change per sample, in the base's σ (default 0.1)")
    p.add_argument("--angle-tol", type=float, default=0.1, metavar="SIGMAS",
                   help="largest change of an angle's last posterior, in its σ (default 0.1)")
    p.add_argument("--flags-tol", type=int, default=0, metavar="N",
                   help="samples whose flags may differ (default 0)")
    return p


def _glob(d: Path, table: str) -> str:
    return str(d / table / "*" / "*.parquet").replace("'", "''")


def hub_changes(con, base: Path, new: Path) -> dict[str, dict[str, Any]]:
    sig = {a: f'sqrt(coalesce(b."sigma_angles.{a}", 0)^2 + coalesce(b."sigma_filter.{a}", 0)^2)'
           for a in AXES}
    worst = ", ".join(f'coalesce(abs(n."H.{a}" - b."H.{a}") / nullif({sig[a]}, 0), 0)'
                      for a in AXES)
    q = f"""
        SELECT coalesce(b.recording, n.recording) AS recording,
               count(b.seq) AS base_samples, count(n.seq) AS new_samples,
               max(greatest({worst})) AS worst_sigma,
               sum(CASE WHEN b.seq IS NOT NULL AND n.seq IS NOT NULL AND
                        ((b."H.X" IS NULL) <> (n."H.X" IS NULL)) THEN 1 ELSE 0 END)
                   AS null_changed,
               sum(CASE WHEN b.flags IS DISTINCT FROM n.flags THEN 1 ELSE 0 END)
                   AS flags_changed
        FROM read_parquet('{_glob(base, "hub_loads")}', hive_partitioning = true) b
        FULL OUTER JOIN read_parquet('{_glob(new, "hub_loads")}', hive_partitioning = true) n
          ON b.recording = n.recording AND b.seq = n.seq
        GROUP BY 1"""
    cols = ("base_samples", "new_samples", "worst_sigma", "null_changed", "flags_changed")
    return {r[0]: dict(zip(cols, r[1:])) for r in con.execute(q).fetchall()}


def last_angles(con, d: Path) -> dict[str, dict[str, tuple[float, float | None]]]:
    """recording -> angle -> (alpha rad, sigma rad) of its last accepted record."""
    q = f"""
        SELECT recording, names, alpha, P FROM (
          SELECT recording, names, alpha, P,
                 row_number() OVER (PARTITION BY recording ORDER BY seq DESC, t DESC) AS k
          FROM read_parquet('{_glob(d, "angles")}', hive_partitioning = true)
          WHERE accepted) WHERE k = 1"""
    out: dict[str, dict[str, tuple[float, float | None]]] = {}
    for rec, names, alpha, P in con.execute(q).fetchall():
        if not names or not alpha:
            continue
        out[rec] = {n: (a, (P[i][i] ** 0.5 if P and P[i][i] is not None and P[i][i] >= 0
                            else None)) for i, (n, a) in enumerate(zip(names, alpha))}
    return out


def health_counts(d: Path, recording: str) -> dict[str, int]:
    """The integer counters of the recording's last health record."""
    import pyarrow.parquet as pq

    folder = d / "health" / f"recording={recording}"
    files = sorted(folder.glob("*.parquet")) if folder.is_dir() else []
    if not files:
        return {}
    t = pq.read_table(files[0])
    if not t.num_rows:
        return {}
    last = t.slice(t.num_rows - 1).to_pylist()[0]
    return {k: v for k, v in last.items() if isinstance(v, int) and not isinstance(v, bool)
            and "age" not in k and k != "t"}


def compare(base: Path, new: Path, hub_tol: float, angle_tol: float, flags_tol: int
            ) -> list[dict[str, Any]]:
    import duckdb

    mb, mn = read_manifest(base), read_manifest(new)
    con = duckdb.connect()
    try:
        hub = hub_changes(con, base, new) if _has(base, new, "hub_loads") else {}
        ang_b = last_angles(con, base) if _has(base, new, "angles") else {}
        ang_n = last_angles(con, new) if _has(base, new, "angles") else {}
    finally:
        con.close()
    rows = []
    for rec in sorted(set(mb) | set(mn)):
        b, n = mb.get(rec), mn.get(rec)
        changes: list[str] = []
        regression = False
        if b is None:
            changes.append("new in NEW")
        elif n is None or (b["status"] == "ok" and n["status"] != "ok"):
            changes.append("missing in NEW" if n is None else f"failed in NEW: {n['reason']}")
            regression = b["status"] == "ok"
        elif b["status"] == "ok":
            changes += _hub_text(hub.get(rec), hub_tol, flags_tol)
            if b.get("accepted_runs") != n.get("accepted_runs"):
                changes.append(f"accepted runs {b.get('accepted_runs')} -> "
                               f"{n.get('accepted_runs')}")
            hb, hn = health_counts(base, rec), health_counts(new, rec)
            diff = sorted(k for k in set(hb) | set(hn) if hb.get(k) != hn.get(k))
            if diff:
                changes.append(f"health counts differ: {', '.join(diff[:4])}"
                               f"{' …' if len(diff) > 4 else ''}")
            changes += _angles_text(ang_b.get(rec, {}), ang_n.get(rec, {}), angle_tol)
            regression = bool(changes)
        rows.append({"recording": rec, "regression": regression,
                     "changes": "; ".join(changes) or "none beyond tolerance"})
    return rows


def _has(base: Path, new: Path, table: str) -> bool:
    return any((base / table).glob("*/*.parquet")) and any((new / table).glob("*/*.parquet"))


def _hub_text(h: dict[str, Any] | None, tol: float, flags_tol: int) -> list[str]:
    if h is None:
        return []
    out = []
    if h["base_samples"] != h["new_samples"]:
        out.append(f"samples {h['base_samples']} -> {h['new_samples']}")
    if (h["worst_sigma"] or 0.0) > tol:
        out.append(f"hub loads moved {h['worst_sigma']:.3g} σ (tolerance {tol:g} σ)")
    if h["null_changed"]:
        out.append(f"{h['null_changed']} samples with/without hub loads")
    if (h["flags_changed"] or 0) > flags_tol:
        out.append(f"flags differ on {h['flags_changed']} samples")
    return out


def _angles_text(b: dict, n: dict, tol: float) -> list[str]:
    import math

    if set(b) != set(n):
        return [f"accepted angles: {len(b)} -> {len(n)} angles"] if b or n else []
    worst, name = 0.0, ""
    for k, (a, s) in b.items():
        d = abs(n[k][0] - a)
        z = d / s if s else (math.inf if d else 0.0)
        if z > worst:
            worst, name = z, k
    return [f"angle {name} moved {worst:.3g} σ (tolerance {tol:g} σ)"] if worst > tol else []


def run(args: argparse.Namespace) -> int:
    from rsra.daq.campaign.progress import console as campaign_console
    from rsra.daq.campaign.progress import table

    base, new = Path(args.base), Path(args.new)
    for d, what in ((base, "BASE_DIR"), (new, "NEW_DIR")):
        if not (d / MANIFEST).is_file():
            raise CampaignError(f"{what} {d}: no {MANIFEST}; fix: give a dataset `rsra "
                                "campaign run` wrote")
    for name in ("hub_tol", "angle_tol"):
        if not getattr(args, name) >= 0:
            raise CampaignError(f"--{name.replace('_', '-')}: must be a number >= 0")
    rows = compare(base, new, args.hub_tol, args.angle_tol, args.flags_tol)
    t = table(f"campaign compare {base} -> {new}", ("recording", "verdict", "changes"))
    for r in rows:
        t.add_row(r["recording"], "REGRESSION" if r["regression"] else "ok", r["changes"])
    console = campaign_console()
    console.print(t)
    bad = sum(r["regression"] for r in rows)
    console.print(f"campaign compare: {len(rows)} recordings, {bad} regressions "
                  f"(tolerances: hub loads {args.hub_tol:g} σ, angles {args.angle_tol:g} σ, "
                  f"flags {args.flags_tol} samples)", markup=False)
    return 1 if bad else 0
