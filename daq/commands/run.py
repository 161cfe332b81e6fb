"""`rsra run`: the service — on a real bus, or with the simulator attached in-process."""
from __future__ import annotations

import argparse
import json
import logging
import logging.handlers
import math
import os
import sys
from pathlib import Path

LOG_FILE_BYTES = 10 * 1024 * 1024
LOG_FILE_BACKUPS = 5


def parse_speed(text: str) -> float | None:
    if text == "max":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number or 'max'") from None
    if not v > 0:
        raise argparse.ArgumentTypeError("the speed must be > 0 (or 'max')")
    return v


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not 0 < v < math.inf:
        raise argparse.ArgumentTypeError("must be a finite number > 0")
    return v


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if v <= 0:
        raise argparse.ArgumentTypeError("must be a whole number > 0")
    return v


def seed(text: str) -> int:
    """A simulator seed: a whole number >= 0 (numpy's SeedSequence refuses negatives)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if v < 0:
        raise argparse.ArgumentTypeError("must be a whole number >= 0")
    return v


def add_sim_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=seed, default=None, help="simulator seed (default: the scenario's)")
    p.add_argument("--faults", default=None, metavar="SPEC",
                   help="simulator faults, e.g. 'drop:cell_A:0.1;reboot:cell_C@12.5' "
                   "(see docs/simulator.md)")
    p.add_argument("--speed", type=parse_speed, default=1.0, metavar="X|max",
                   help="simulated time per wall-clock second: 1 (default) is real time; "
                   "'max' runs simulator and service in lock-step as fast as possible (the "
                   "same samples as real time)")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop after S seconds of acquisition time (exit 0)")


def add_no_identification(p: argparse.ArgumentParser, help: str | None = None) -> None:
    p.add_argument("--no-identification", dest="identification", action="store_false",
                   help=help or "no on-line identification: the angles stay at the starting "
                   "ones (--angles, else the configured initial angles) for the whole run")


def add_service_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--record", metavar="DIR", default=None,
                   help="record every frame, the angle schedule and the effective config here")
    p.add_argument("--angles", metavar="STATE", default=None,
                   help="start from a saved posterior (see identification.state_file)")
    from daq.posterior_file import add_accept_option

    add_accept_option(p)
    add_no_identification(p)
    p.add_argument("--zenoh-config", metavar="FILE", default=None,
                   help="a Zenoh config file (TLS, user/password, access control)")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint (router) to connect to (repeatable)")
    from daq.foxglove_out import add_options as add_foxglove_options

    add_foxglove_options(p)
    p.add_argument("--log-file", metavar="FILE", default=None,
                   help="log to this size-rotated file instead of stderr")
    p.add_argument("--log-level", default="info",
                   choices=("debug", "info", "warning", "error"), help="default info")


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from daq.cli import common_options

    p = sub.add_parser(name, help="run the service (real bus, or the simulator in-process)",
                       description="The DAQ service: CANopen master, real-time hub-load "
                       "estimation, periodic identification of the load-cell angles in its own "
                       "process, Zenoh telemetry. On a real bus (--interface socketcan --channel "
                       "vcan0) or with the simulated aircraft attached in-process (--sim).")
    common_options(p, units=False)
    p.add_argument("--interface", default=None, help="python-can interface, e.g. socketcan")
    p.add_argument("--channel", default=None, help="python-can channel, e.g. vcan0 or can0")
    p.add_argument("--sim", metavar="SCENARIO", default=None,
                   help="attach the simulator in-process: ground-test, flight, paper, sweep "
                   "(or a scenario file)")
    add_sim_options(p)
    add_service_options(p)
    p.add_argument("--truth", metavar="FILE", default=None,
                   help="with --sim: write the simulator's truth here (default: beside the "
                   "recording)")
    return p


def setup_logging(level: str, log_file: str | None) -> None:
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    if log_file:
        try:
            h: logging.Handler = logging.handlers.RotatingFileHandler(
                log_file, maxBytes=LOG_FILE_BYTES, backupCount=LOG_FILE_BACKUPS)
        except OSError as e:
            from daq.cli import UsageError

            raise UsageError(f"--log-file {log_file}: cannot be written ({e.strerror or e}); "
                             "fix: give a file in an existing, writable folder") from None
    else:
        h = logging.StreamHandler(sys.stderr)
    h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(h)
    root.setLevel(level.upper())
    # canopen logs every SDO step of a boot at INFO: keep that for --log-level debug
    if level != "debug":
        logging.getLogger("canopen").setLevel(logging.WARNING)


def options_from_args(args: argparse.Namespace):
    from daq.cli import UsageError
    from daq.service import ServiceOptions

    if args.sim is None and args.interface is None:
        raise UsageError("give --interface and --channel for a bus, or --sim SCENARIO")
    if args.sim is not None and args.interface not in (None, "virtual"):
        raise UsageError("--sim runs the simulator in-process on python-can's virtual bus; "
                         "for a bench rig run `rsra sim` on that bus instead")
    if args.sim is None and (args.faults or args.seed is not None):
        raise UsageError("--faults and --seed need --sim")
    if args.sim is None and args.speed != 1.0:
        raise UsageError("--speed needs --sim (a real bus runs in real time)")
    return ServiceOptions(
        interface=args.interface, channel=args.channel, sim=args.sim, seed=args.seed,
        faults=args.faults, speed=args.speed, record=args.record, duration=args.duration,
        angles=args.angles, accept_rig_mismatch=args.accept_rig_mismatch,
        zenoh_config=args.zenoh_config, zenoh_listen=args.zenoh_listen,
        zenoh_connect=args.zenoh_connect, truth=getattr(args, "truth", None),
        identification=args.identification, foxglove=args.foxglove,
        foxglove_origins=args.foxglove_allow_origin)


def run_service(cfg, opts, quiet: bool = False) -> int:
    """Run the service to its end; every failure reaches the one error path in daq.cli."""
    from daq.service import Service

    service = Service(cfg, opts)
    service.install_signal_handlers()
    summary = service.run()
    if not quiet:
        print(json.dumps({"summary": summary}, allow_nan=False, default=str))
    return 0


def check_sim_faults(cfg, scenario: str | None, faults: str | None, speed: float | None) -> None:
    """A --faults SPEC checked against the simulated bus before anything starts (FaultSpecError:
    one line, exit 2): the same parse and check as the simulator's."""
    if not faults or scenario is None:
        return
    from sim_bus.bus_sim import check_faults
    from sim_bus.scenarios import load_scenario

    # the service's simulator produces SYNC itself (autostart) in lock-step only
    check_faults(cfg, faults, load_scenario(scenario).nodes_present, autostart=speed != 1.0)


def config_for_run(config: str | None, scenario: str | None):
    """The rig config, with a simulated scenario's own overrides (e.g. `paper` starts the
    service at 4°) when the simulator is attached."""
    from daq.cli import UsageError
    from daq.config import ConfigError, load_config

    if scenario is None:
        return load_config(config)
    from sim_bus.scenarios import load_scenario

    try:
        sc = load_scenario(scenario)
    except ConfigError:
        raise
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    return load_config(config, overrides=sc.rig_overrides or None)


def check_output_file(option: str, path: str) -> None:
    """An output file named on the command line, checked before any work: not a folder, in an
    existing folder we may write (no folder is created for it: nothing the user did not name)."""
    from daq.cli import UsageError

    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{option} {path}: is a folder; fix: give a file name")
    parent = p.resolve().parent
    if not parent.is_dir():
        raise UsageError(f"{option} {path}: no folder {parent}; fix: create it or write elsewhere")
    if not os.access(parent, os.W_OK):
        raise UsageError(f"{option} {path}: folder {parent} is not writable; fix: write "
                         "elsewhere")


def run(args: argparse.Namespace) -> int:
    from daq.cli import UsageError

    setup_logging(args.log_level, args.log_file)
    if args.truth:  # found out now, not after the run
        if not args.sim:
            raise UsageError("--truth needs --sim (the truth is the simulator's); fix: add "
                             "--sim SCENARIO or leave --truth out")
        check_output_file("--truth", args.truth)
    opts = options_from_args(args)
    cfg = config_for_run(args.config, args.sim)
    check_sim_faults(cfg, args.sim, args.faults, args.speed)
    from daq.foxglove_out import check_option

    check_option(args)  # a taken port: refused before anything starts
    return run_service(cfg, opts)
