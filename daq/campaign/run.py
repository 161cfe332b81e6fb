"""`rsra campaign run`: recordings reprocessed into one dataset, on every core or a Dask
cluster, incrementally (docs/cli.md, docs/user-guide.md "Campaigns")."""
from __future__ import annotations

import argparse
import functools
from pathlib import Path
from typing import Any

from rsra.daq.campaign.dataset import CampaignError


def recording_options(p: argparse.ArgumentParser) -> None:
    """The options `run` and `plan` share: what to process, and how (part of the key)."""
    p.add_argument("inputs", nargs="+", metavar="RECORDING",
                   help="recording folders, log files (any python-can format), or folders "
                   "holding recordings")
    p.add_argument("--dataset", metavar="DIR", required=True,
                   help="the dataset folder: missing, empty, or one `rsra campaign run` wrote")
    p.add_argument("--config", metavar="RIG", default=None,
                   help="rig TOML for every recording (default: each recording folder's own "
                   "config.json, else the packaged rig)")
    p.add_argument("--recompute", action="store_true",
                   help="recompute the identification instead of following each recording's "
                   "angle schedule (as `rsra replay --recompute`)")
    p.add_argument("--no-identification", action="store_true",
                   help="no identification: the starting angles throughout")
    p.add_argument("--survey", action="store_true",
                   help="also the loads survey of each recording (`rsra survey` at its own test "
                   "points) as the dataset's `survey` table")
    p.add_argument("--retry-failed", action="store_true",
                   help="run recordings that failed before again even when unchanged")


def options_of(args: argparse.Namespace) -> dict[str, Any]:
    out = {"recompute": bool(args.recompute),
           "no_identification": bool(args.no_identification)}
    if args.survey:  # (absent when not asked: the output keys of datasets without it stand)
        out["survey"] = True
    return out


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="reprocess recordings into the dataset (parallel, "
                       "incremental)", description=__doc__)
    recording_options(p)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", metavar="N", type=int, default=None,
                       help="worker processes of the local cluster (default: one per core)")
    where.add_argument("--scheduler", metavar="ADDR", default=None,
                       help="run on an existing Dask cluster (tcp://HOST:PORT of `dask "
                       "scheduler`)")
    where.add_argument("--scheduler-file", metavar="FILE", default=None,
                       help="run on an existing Dask cluster (the file `dask scheduler "
                       "--scheduler-file` wrote)")
    p.add_argument("--pool", action="store_true",
                       help="a plain ProcessPoolExecutor instead of Dask (one machine; a dead "
                       "worker is not retried)")
    p.add_argument("--dashboard", metavar="HOST:PORT", default=None,
                   help="serve the local cluster's Dask dashboard there (default: off)")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.campaign import dataset as ds
    from rsra.daq.campaign.engine import open_engine
    from rsra.daq.campaign.progress import Progress
    from rsra.daq.campaign.runner import Runner, make_plan

    if args.pool and (args.scheduler or args.scheduler_file):
        raise CampaignError("--pool runs on this machine; fix: leave out --pool or "
                            "--scheduler/--scheduler-file")
    if args.workers is not None and args.workers < 1:
        raise CampaignError(f"--workers {args.workers}: must be 1 or more")
    dataset = Path(args.dataset)
    plan = make_plan(args.inputs, dataset, args.config, options_of(args), args.retry_failed)
    progress = Progress()
    if not plan.of("run") and not plan.of("fail"):
        progress.console.print(f"campaign: nothing to do: {len(plan.items)} recordings "
                               f"unchanged in {dataset}")
        return 0 if all(plan.manifest.get(i.recording, {}).get("status") == "ok"
                        for i in plan.items) else 1
    dataset.mkdir(parents=True, exist_ok=True)
    with ds.DatasetLock(dataset):
        runner = Runner(plan, progress)
        engine = functools.partial(open_engine, args.workers, args.scheduler,
                                   args.scheduler_file, args.dashboard, args.pool)
        try:
            status = runner.run(engine)
        finally:
            progress.stop()
        progress.summary(plan, runner.rows)
    return status
