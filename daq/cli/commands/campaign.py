"""`rsra campaign run|plan|status|compare|calibrate`: many recordings into one dataset (docs/cli.md).

A table of subcommands, each a module of daq/campaign with add_parser(sub, name) and
run(args), as the command table of daq/cli does."""
from __future__ import annotations

import argparse
import importlib

SUBCOMMANDS = {
    "run": "run",
    "plan": "plan",
    "status": "status",
    "compare": "compare",
    "calibrate": "calibrate",
}

OUTPUTS = {"dataset": "folder"}  # against the inputs (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="reprocess many recordings into one dataset (Dask; "
                       "incremental), query and compare datasets",
                       description="Recordings reprocessed on every core or a Dask cluster "
                       "into one Parquet dataset (DIR/<table>/recording=<id>/part.parquet and "
                       "DIR/manifest.parquet), incrementally; a dry run; the status of a "
                       "dataset; the comparison of two (docs/user-guide.md, Campaigns).")
    inner = p.add_subparsers(dest="campaign_command", metavar="SUBCOMMAND",
                             parser_class=type(p))
    inner.required = True
    for sub_name, module in SUBCOMMANDS.items():
        mod = importlib.import_module(f"rsra.daq.campaign.{module}")
        q = mod.add_parser(inner, sub_name)
        q.set_defaults(_campaign_run=mod.run)
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.campaign.dataset import CampaignError
    from rsra.daq.cli.options import UsageError

    try:
        return int(args._campaign_run(args) or 0)
    except CampaignError as e:
        raise UsageError(str(e)) from None
