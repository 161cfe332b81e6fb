"""`rsra campaign status DIR`: the manifest of a dataset, one line per recording."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="the recordings of a dataset and their status",
                       description=__doc__)
    p.add_argument("dataset", metavar="DIR", help="a dataset `rsra campaign run` wrote")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.campaign.dataset import MANIFEST, CampaignError, read_manifest

    d = Path(args.dataset)
    if not (d / MANIFEST).is_file():
        raise CampaignError(f"{d}: no {MANIFEST}; fix: give a dataset `rsra campaign run` wrote")
    rows = read_manifest(d)
    from rsra.daq.campaign.progress import console as campaign_console
    from rsra.daq.campaign.progress import table

    t = table(f"campaign {d}", ("recording", "rig", "status", "samples", "lost",
                                "accepted runs", "wall s", "rsra", "reason"))
    for r in sorted(rows.values(), key=lambda r: (r.get("t_start") or 0.0, r["recording"])):
        t.add_row(r["recording"], str(r.get("rig_name") or "-"), str(r["status"]),
                  *(str(r.get(k)) if r.get(k) is not None else "-"
                    for k in ("samples", "lost_samples", "accepted_runs")),
                  f"{r['wall_s']:.1f}" if r.get("wall_s") is not None else "-",
                  str(r.get("rsra_version") or "-"), str(r.get("reason") or ""))
    console = campaign_console()
    console.print(t)
    failed = sum(1 for r in rows.values() if r["status"] != "ok")
    console.print(f"campaign status: {len(rows)} recordings, {len(rows) - failed} ok, "
                  f"{failed} failed", markup=False)
    return 1 if failed else 0
