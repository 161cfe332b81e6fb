"""`rsra campaign plan`: what `campaign run` would do with the same arguments (dry run): what
runs, what is skipped, and why. Writes nothing."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.campaign.run import recording_options

    p = sub.add_parser(name, help="what `campaign run` would run or skip, and why (dry run)",
                       description=__doc__)
    recording_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.campaign.keys import HashCache
    from rsra.daq.campaign.run import options_of
    from rsra.daq.campaign.runner import make_plan

    plan = make_plan(args.inputs, Path(args.dataset), args.config, options_of(args),
                     args.retry_failed)
    plan.cache = HashCache(None)  # (a dry run: the cache is not written either)
    from rsra.daq.campaign.progress import console as campaign_console
    from rsra.daq.campaign.progress import table

    t = table(f"campaign plan for {args.dataset}", ("recording", "source", "action", "why"))
    for i in plan.items:
        t.add_row(i.recording, str(i.source), i.action, i.why)
    console = campaign_console()
    console.print(t)
    console.print(f"campaign plan: {len(plan.of('run'))} to run, {len(plan.of('skip'))} "
                  f"skipped, {len(plan.of('fail'))} cannot be read", markup=False)
    return 0
