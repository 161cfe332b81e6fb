"""`rsra run`: the service — on a real bus, or with the simulator attached in-process."""
from __future__ import annotations

import argparse
import json
import sys

from rsra.daq.cli.options import (
    UsageError,
    add_service_options,
    add_sim_options,
    check_output_file,
    check_sim_faults,
    common_options,
    config_for_run,
    setup_logging,
)


OUTPUTS = {"truth": "file", "record": "folder"}  # checked against the inputs (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
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
    p.add_argument("--state-file", metavar="PATH", default=None,
                   help="save the posterior of the angles here after every accepted "
                   "identification run (the TOML key identification.state_file; `rsra angles "
                   "show PATH` reads it, `--angles PATH` starts the next run from it)")
    return p


# the source options that contradict each other: (when refused, the one line saying why)
_SOURCE_CONFLICTS = (
    (lambda a: a.sim is None and a.interface is None,
     "give --interface and --channel for a bus, or --sim SCENARIO"),
    (lambda a: a.sim is not None and a.interface not in (None, "virtual"),
     "--sim runs the simulator in-process on python-can's virtual bus; for a bench rig run "
     "`rsra sim` on that bus instead"),
    (lambda a: a.sim is None and (a.faults or a.seed is not None or a.variant),
     "--faults, --seed and --variant need --sim"),
    (lambda a: a.sim is None and a.speed != 1.0,
     "--speed needs --sim (a real bus runs in real time)"),
)


def options_from_args(args: argparse.Namespace):
    from rsra.daq.runtime.service import ServiceOptions

    for refused, message in _SOURCE_CONFLICTS:
        if refused(args):
            raise UsageError(message)
    return ServiceOptions(
        interface=args.interface, channel=args.channel, sim=args.sim, seed=args.seed,
        faults=args.faults, speed=args.speed, record=args.record, duration=args.duration,
        angles=args.angles, accept_rig_mismatch=args.accept_rig_mismatch,
        zenoh_config=args.zenoh_config, zenoh_listen=args.zenoh_listen,
        zenoh_connect=args.zenoh_connect, truth=getattr(args, "truth", None),
        identification=args.identification, foxglove=args.foxglove,
        foxglove_origins=args.foxglove_allow_origin,
        realtime_priority=args.realtime_priority, scenario_variants=dict(args.variant))


def run_service(cfg, opts, quiet: bool = False) -> int:
    """Run the service to its end; every failure reaches the one error path in daq.cli."""
    from rsra.daq.runtime.service import Service

    service = Service(cfg, opts)
    service.install_signal_handlers()
    summary = service.run()
    failed = recording_outcome(service, summary)
    if not quiet:
        print(json.dumps({"summary": summary}, allow_nan=False, default=str))
    for line in failed:  # the service ran on; what it was asked to keep is not all kept
        print(f"rsra run: error: {line}", file=sys.stderr)
    return 1 if failed else 0


def recording_outcome(service, summary: dict) -> list[str]:
    """The summary's ``recording`` entry (frames kept, frames not, why it stopped) and the
    lines saying what was not kept: a recording stopped early (a full disk: the service ran
    on without it) or a truth file not written. Empty: everything asked for was kept."""
    failed = []
    rec = service.recorder
    if rec is not None:
        entry = {"folder": str(rec.folder), "frames": rec.frames, "dropped": rec.dropped,
                 "complete": rec.error is None}
        if rec.error is not None:
            entry["error"] = rec.error
            failed.append(f"{rec.error.removeprefix('recording stopped: ')}: the recording "
                          f"stopped early, {rec.frames} frames kept in {rec.folder} (the "
                          f"service ran on; {rec.dropped} frames not recorded); fix: free "
                          "space or record elsewhere")
        summary["recording"] = entry
    truth_error = getattr(service.source, "truth_error", None)
    if truth_error:
        summary["truth"] = {"error": truth_error}
        failed.append(f"{truth_error}; no partial file is left")
    return failed


def run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level, args.log_file)
    if args.truth:  # found out now, not after the run
        if not args.sim:
            raise UsageError("--truth needs --sim (the truth is the simulator's); fix: add "
                             "--sim SCENARIO or leave --truth out")
        check_output_file("--truth", args.truth, suffix=".npz")
    if args.state_file is not None:
        if not args.state_file:
            raise UsageError("--state-file: give a file name")
        check_output_file("--state-file", args.state_file)
    opts = options_from_args(args)
    cfg = config_for_run(args.config, args.sim, opts.scenario_variants)
    if args.state_file is not None:  # the option over the TOML key (the same checks follow)
        import dataclasses

        cfg = dataclasses.replace(cfg, identification=dataclasses.replace(
            cfg.identification, state_file=args.state_file))
    check_sim_faults(cfg, args.sim, args.faults, args.speed, opts.scenario_variants)
    from rsra.daq.runtime.foxglove_out import check_option

    check_option(args)  # a taken port: refused before anything starts
    return run_service(cfg, opts)
