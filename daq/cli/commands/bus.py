"""`rsra bus`: a CAN bus shared between processes on this machine (docs/deployment.md "A
shared bus between processes"; python-can-remote's server, wrapped by daq.sharedbus)."""
from __future__ import annotations

import argparse
import signal
import sys
import threading


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.bus.sharedbus import DEFAULT_PORT

    p = sub.add_parser(
        name, help="share a CAN bus between processes (loopback WebSocket)",
        description="Hosts one python-can bus (default: virtual) and shares it with other "
        "processes through python-can-remote: give them --interface remote --channel "
        "ws://127.0.0.1:PORT/. Binds 127.0.0.1 only and refuses WebSocket upgrades from web "
        "pages (an Origin header): the server has no authentication. Runs until Ctrl-C or "
        "SIGTERM.")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, metavar="P",
                   help=f"TCP port (default {DEFAULT_PORT}; 0: a free one, printed)")
    p.add_argument("--interface", default="virtual", metavar="I",
                   help="python-can interface of the bus shared (default virtual)")
    p.add_argument("--channel", default="rig", metavar="C",
                   help="its channel (default rig)")
    p.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                   help="address to listen on (default 127.0.0.1). RISK: anything else lets "
                   "every host that reaches ADDR send any frame, NMT and SDO writes included, to "
                   "the rig — there is no authentication; only on an isolated network")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.bus.sharedbus import BusServer
    from rsra.daq.netaddr import is_loopback

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port {args.port}: give a TCP port 0–65535")
    import can

    try:  # the bus shared is opened per client: find a wrong interface or channel now
        can.Bus(interface=args.interface, channel=args.channel).shutdown()
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise UsageError(f"cannot open the bus --interface {args.interface} --channel "
                         f"{args.channel}: {e}; check the interface and channel") from None
    try:
        server = BusServer(args.bind, args.port, interface=args.interface, channel=args.channel)
    except OSError as e:
        print(f"rsra bus: cannot listen on {args.bind}:{args.port}: {e.strerror or e}; fix: "
              "stop the other server or give a free port with --port", file=sys.stderr)
        return 1
    stop = threading.Event()

    def on_signal(signum, frame):  # noqa: ARG001
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        server.start()
        if not is_loopback(args.bind):
            print(f"rsra bus: WARNING: listening on {args.bind}, not loopback: any host that "
                  "reaches it can send frames to the rig (no authentication)", file=sys.stderr)
        print(f"rsra bus: sharing {args.interface}:{args.channel} on {server.url} — clients: "
              f"--interface remote --channel {server.url} (Ctrl-C stops)",
              file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        server.close()
        for s, h in old.items():
            signal.signal(s, h)
    print(f"rsra bus: stopped; {server.refused} browser connection(s) refused",
          file=sys.stderr, flush=True)
    return 0
