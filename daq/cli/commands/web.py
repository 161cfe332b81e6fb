"""`rsra web`: NASA Open MCT in the browser against a running rig (the gateway: daq.web)."""
from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(name, help="Open MCT in the browser: live hub loads, limits, history",
                       description="A gateway that subscribes to the rig's telemetry over Zenoh "
                       "and serves NASA Open MCT with an rsra plugin; prints the address to "
                       "open. Files given (`rsra replay --out` JSONL, MCAP from `rsra export "
                       "--mcap`) add their telemetry to the history.")
    common_options(p, units=False)
    from rsra.daq.cli.options import positive_float

    p.add_argument("files", nargs="*", metavar="FILE",
                   help="telemetry files for history (JSONL of `rsra replay --out` or MCAP)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_port, default=8080, help="TCP port (default 8080; 0: any)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow --host to be an address other machines reach (no login, no "
                   "TLS: anyone who reaches the port reads the telemetry)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="another name the browser may use for this server in its address "
                   "(the Host header), e.g. the machine's DNS name (repeatable)")
    p.add_argument("--prefix", default=None,
                   help="key prefix (default: the rig publishing, else the config's)")
    p.add_argument("--rig", default=None, metavar="NAME",
                   help="show the rig of this name (rig.name) among those publishing")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="endpoint to connect to (default: the config's listen endpoints)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh config file (TLS, user/password) instead of --zenoh-connect")
    p.add_argument("--history-s", type=positive_float, default=300.0, metavar="S",
                   help="seconds of telemetry kept in memory for history (default 300)")
    return p


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"port {v} is not in 0…65535")
    return v


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.runtime.telemetry import payload_guard, viewer_config, zenoh_config
    from rsra.daq.web.dictionary import build_dictionary
    from rsra.daq.web.history import History, HistoryFileError, TelemetryFile, key_rates
    from rsra.daq.netaddr import is_loopback
    from rsra.daq.web.server import Gateway, allowed_hosts, openmct_dir, serve

    omct = openmct_dir()
    if omct is None:
        print("rsra web: error: the Open MCT files are not installed; fix: run `make web` in "
              "the rsra source folder (needs npm), or install an rsra wheel built after it",
              file=sys.stderr)
        return 2
    if not is_loopback(args.host) and not args.allow_remote:
        raise UsageError(f"--host {args.host} is not a loopback address: anyone who reaches "
                         "it reads the rig's telemetry (no login, no TLS); fix: add "
                         "--allow-remote if that is what you want, or keep 127.0.0.1")
    cfg = load_rig(args.config)
    if args.zenoh_config:
        conf = zenoh_config(cfg.telemetry, config_file=args.zenoh_config)
    else:
        conf = viewer_config(args.zenoh_connect or list(cfg.telemetry.listen))
    cfg, prefix, source = _whose(args, cfg, conf)
    files = []
    for f in args.files:
        try:
            files.append(TelemetryFile(f, prefix))
        except HistoryFileError as e:
            raise UsageError(str(e)) from None
    dic = build_dictionary(cfg, prefix, source)
    history = History(args.history_s, key_rates(cfg))

    async def main() -> dict:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        gw: Gateway | None = None

        def ready(port: int) -> None:
            assert gw is not None  # made before serve() calls this
            gw.hosts = allowed_hosts(args.host, port, args.allow_host)
            shown = f"[{args.host}]" if ":" in args.host else args.host
            if not is_loopback(args.host):
                print(f"rsra web: WARNING: listening on {args.host}:{port}: anyone who reaches "
                      "this port reads the rig's telemetry (no login, no TLS; docs/deployment.md)",
                      file=sys.stderr)
                if args.host in ("0.0.0.0", "::") and not args.allow_host:
                    print("rsra web: browsers must use an address given with --allow-host "
                          "(the Host check refuses others)", file=sys.stderr)
            print(f"rsra web: open http://{shown}:{port}/ (Ctrl-C stops)", flush=True)
            print(f"rsra web: showing {source}", file=sys.stderr, flush=True)

        gw = Gateway(dic, history, files, set(), guard=payload_guard(), openmct=omct)
        await serve(gw, args.host, args.port, conf, prefix, on_ready=ready, stop=stop)
        return gw.status()

    st = asyncio.run(main())
    summary = {"received": sum(st["received"].values()), "missed": st["missed"],
               "points_sent": st["points_sent"], "points_dropped": st["points_dropped"],
               "refused": st["refused"], "history_bytes": st["history"]["bytes"],
               "bad_messages": st["bad_messages"], "shed": st["shed"]}
    for line in st["guard_lines"]:
        print(f"rsra web: {line}", file=sys.stderr)
    print(json.dumps({"summary": summary}), flush=True)
    return 0


def _whose(args: argparse.Namespace, cfg, conf):
    """The rig the page shows (daq.cli.whose, as `rsra listen`): ``--prefix``, ``--rig NAME``
    or the only rig publishing, and its config — the configured one, or without --config the
    packaged rig of the name it publishes under (its cells, angles and nodes make the page).
    Returns (config, prefix, whose it is in words)."""
    import time

    import zenoh

    from rsra.config.rig import packaged_rigs
    from rsra.daq.cli.options import UsageError
    from rsra.daq.cli.whose import Whose
    from rsra.daq.rigmodel import load_rig

    with zenoh.open(conf) as session:
        whose = Whose(session, cfg.telemetry.prefix, args.prefix, args.rig)
        try:
            whose.discover(time.monotonic())
        finally:
            whose.close()
    inst = whose.instance
    if inst is None:
        if args.rig is not None:
            raise UsageError(f"--rig {args.rig}: {whose.why}; fix: start that rig's service "
                             "first, or leave out --rig")
        return cfg, whose.prefix or cfg.telemetry.prefix, whose.title()
    if inst.rig != cfg.rig_name:
        if args.config is None and inst.rig in packaged_rigs():
            cfg = load_rig(inst.rig)  # its cells, angles and nodes
        else:
            raise UsageError(f"{inst.describe()}, but --config describes rig {cfg.rig_name}: "
                             f"its page would show the wrong cells and angles; fix: give rig "
                             f"{inst.rig}'s file with --config, or --rig {cfg.rig_name}")
    return cfg, inst.prefix, whose.title()
