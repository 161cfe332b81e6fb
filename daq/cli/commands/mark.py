"""`rsra mark`: name a test point of the running service (docs/cli.md, daq/runtime/marks.py).

Puts ``{"name": NAME}`` (or ``{"end": true}`` with ``--end``) on ``<prefix>/mark``; a
recording service writes it to ``marks.jsonl`` in its recording folder, stamped with its
latest sample's time, and `rsra survey` makes a test point of it that lasts until the next mark
or the end mark.
"""
from __future__ import annotations

import argparse
import sys


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="mark a test point in the running service's recording (rsra survey)",
        description="Names the test point that starts now in the running service's recording "
        "(marks.jsonl in its --record folder): it lasts until the next mark or `rsra mark "
        "--end`. `rsra survey` surveys each marked test point.")
    common_options(p, units=False)
    p.add_argument("name", nargs="?", default=None,
                   help="the test point's name, e.g. \"hover 40 kt\" (1-200 printable characters)")
    p.add_argument("--end", action="store_true", help="end the current test point")
    p.add_argument("--prefix", default=None, help="key prefix (default: the config's)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="endpoint of the service (default: the config's listen endpoints)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh config file (TLS, user/password) instead of --zenoh-connect")
    return p


def run(args: argparse.Namespace) -> int:
    import zenoh

    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.runtime.marks import MarkError, mark_payload
    from rsra.daq.runtime.telemetry import viewer_config, zenoh_config

    if args.end == (args.name is not None):
        raise UsageError("give a test point's name or --end (one of them); e.g. rsra mark "
                         "\"hover 40 kt\"")
    try:
        data = mark_payload(None if args.end else args.name)
    except MarkError as e:
        raise UsageError(f"the name {args.name!r}: {e}; fix: a shorter, printable "
                         "name") from None
    cfg = load_rig(args.config)
    prefix = args.prefix or cfg.telemetry.prefix
    conf = (zenoh_config(cfg.telemetry, config_file=args.zenoh_config) if args.zenoh_config
            else viewer_config(args.zenoh_connect or list(cfg.telemetry.listen)))
    with zenoh.open(conf) as session:
        # the service's liveliness token: it is there and the session reaches it
        alive = list(session.liveliness().get(f"{prefix}/alive", timeout=3.0))
        if not any(getattr(r, "ok", None) is not None for r in alive):
            print(f"rsra mark: no service with prefix {prefix} reached (no {prefix}/alive "
                  "token); fix: start `rsra run --record DIR`, or give the service's --config "
                  "(its prefix is rsra/<rig name>) or --prefix, and --zenoh-connect",
                  file=sys.stderr)
            return 1
        session.put(f"{prefix}/mark", data)
    print(f"mark: {'end' if args.end else args.name!r} sent to {prefix}/mark")
    return 0
