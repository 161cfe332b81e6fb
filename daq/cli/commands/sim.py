"""`rsra sim`: the simulated aircraft alone on a bus (docs/cli.md §3; docs/bus.md; model.md §8).

CANopen nodes that wait for a master's NMT start and follow its SYNC, or with --autostart
start by themselves while the simulator produces SYNC at the sample rate. --record writes
every frame with python-can's Logger; --truth writes the physics truth and the injected faults.
"""
from __future__ import annotations

import argparse
import signal
import threading
import time
from pathlib import Path

FAULT_HELP = (
    "faults to inject, ';'-separated KIND[:ARG…][@WHEN], e.g. "
    "'drop:cell_A:0.1;reboot:cell_C@12.5;silent:accel_1@20-22;jitter:0.5ms'. Kinds: "
    "drop:NODE:P, malformed:NODE:P, stuck:NODE[.CHANNEL], overrange:NODE, sensor:NODE, "
    "silent:NODE, reboot:NODE@T, unknown[:COBID]:P, lostsync:P, jitter:SIGMA, errorframe:P "
    "(lostsync and jitter need --autostart). WHEN is @T or @T1-T2 in simulated seconds; "
    "NODE may be '*'. See docs/simulator.md, 'Faults'")


OUTPUTS = {"truth": "file", "record": "file"}  # checked against the inputs (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options
    from rsra.daq.cli.options import add_variant_option, positive_float, seed

    p = sub.add_parser(
        name, help="the simulated aircraft alone on a bus",
        description="The simulated aircraft's CANopen nodes on a CAN bus, fed by the physics of a "
        "scenario, one sample per SYNC. By default the nodes boot, wait for a master's NMT start "
        "and answer its SYNC; with --autostart they start by themselves and the simulator "
        "produces SYNC at the sample rate (no master needed). Runs in real time until --duration "
        "or Ctrl-C.")
    common_options(p, units=False)
    p.add_argument("--scenario", required=True, metavar="S",
                   help="scenario name (ground-test, flight, paper, sweep) or a scenario .toml")
    p.add_argument("--interface", default="virtual", metavar="I",
                   help="python-can interface (default virtual: in-process only; socketcan on "
                   "a bench rig)")
    p.add_argument("--channel", default="vcan0", metavar="C",
                   help="bus channel (default vcan0)")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop after S seconds and exit 0 (default: until Ctrl-C)")
    p.add_argument("--seed", type=seed, default=None, metavar="N",
                   help="random seed of the physics and the faults (default: the scenario's)")
    add_variant_option(p)
    p.add_argument("--truth", default=None, metavar="FILE",
                   help="write the truth (hub loads, angles, channels before noise, SYNC "
                   "counters, injected faults) to FILE (.npz) at the end")
    p.add_argument("--faults", default=None, metavar="SPEC", help=FAULT_HELP)
    p.add_argument("--record", default=None, metavar="FILE",
                   help="write every frame on the bus to FILE with python-can's Logger: the "
                   "suffix picks the format (.log candump, .blf, .asc, …); candump otherwise")
    p.add_argument("--autostart", action="store_true",
                   help="nodes start themselves and the simulator produces SYNC (its own master)")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.cli.console import make_console
    from rsra.sim_bus.physics import AircraftPhysics
    from rsra.sim_bus.scenarios import load_scenario

    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration {args.duration}: must be a positive number of seconds")
    if args.truth:  # found out now, not after the run
        from rsra.daq.cli.options import check_output_file

        check_output_file("--truth", args.truth, suffix=".npz")
    cfg = load_rig(args.config)
    from rsra.daq.bus.decoder import DecodeTable

    DecodeTable(cfg)  # an EDS canopen cannot read: a ConfigError naming the node (exit 2)
    scenario = load_scenario(args.scenario, **dict(args.variant))
    physics = AircraftPhysics(cfg, scenario, seed=args.seed)
    sim = _open_sim(args, cfg, physics)
    console = make_console(stderr=True)
    stop = threading.Event()
    t_start = time.monotonic()
    mode = "autostart, producing SYNC" if args.autostart else "waiting for the master's NMT start and SYNC"
    console.print(f"rsra sim: scenario {scenario.name!r}, seed {physics.seed}, "
                  f"{len(sim.nodes)} nodes on {args.interface}:{args.channel} ({mode})")

    def progress(n_samples: int, _t: float) -> None:
        console.print(f"  {time.monotonic() - t_start:7.1f} s  {n_samples:8d} samples  "
                      f"{sim.frames_sent:9d} frames sent  {sim.faults.events:6d} faults",
                      highlight=False)

    stopped_by: list[str] = []

    def on_signal(signum, frame):  # noqa: ARG001 - Ctrl-C and SIGTERM: the same clean stop
        stopped_by.append("Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name)
        stop.set()

    # both handled explicitly: a background `rsra sim … &` of a script starts with SIGINT
    # ignored, and `kill -INT` must still stop it and write the truth
    old_handlers = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        failed = _drive(sim, args.duration, stop, progress, stopped_by)
    finally:
        sim.close()
    try:
        # the truth so far is written whatever ended the run (nothing lost), atomically: a
        # second Ctrl-C or a kill during the write leaves the old file or the new one
        truth = None
        if args.truth and len(sim.samples):
            from rsra.daq.runtime.persistence import write_bytes_atomic

            truth = sim.write_truth(Path(args.truth), write=write_bytes_atomic)
    finally:
        for s, h in old_handlers.items():
            signal.signal(s, h)
    _say_end(console, args, sim, truth, stopped_by, failed)
    return 1 if failed is not None else 0


def _open_sim(args: argparse.Namespace, cfg, physics):
    """The simulator on its bus; a bad --faults, --record or bus: one line (exit 2)."""
    import can

    from rsra.daq.cli.options import UsageError
    from rsra.sim_bus.bus_sim import RecordError
    from rsra.sim_bus.drivers import RealtimeSim
    from rsra.sim_bus.faults import FaultSpecError

    try:
        return RealtimeSim(cfg, physics=physics, faults=args.faults, interface=args.interface,
                           channel=args.channel, autostart=args.autostart, record=args.record,
                           keep_samples=bool(args.truth))
    except FaultSpecError as e:
        raise UsageError(f"--faults: {e}") from None
    except RecordError as e:
        raise UsageError(f"--record: {e}; give a writable file") from None
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise UsageError(f"cannot open the bus --interface {args.interface} --channel "
                         f"{args.channel}: {e}; check the interface and channel") from None


def _drive(sim, duration: float | None, stop: threading.Event, progress,
           stopped_by: list[str]) -> BaseException | None:
    """Run the simulator until ``duration``, ``stop`` or Ctrl-C (named in ``stopped_by``);
    the bus failure that ended it, or None."""
    from rsra.canbus import bus_failure

    with sim:
        try:
            sim.run(duration, stop=stop, progress=progress)
        except KeyboardInterrupt:  # (a handler restored by a library)
            stopped_by.append("Ctrl-C")
            stop.set()
        except Exception as e:  # the bus went away (e.g. `rsra bus` stopped): say so
            if not bus_failure(e):
                raise
            stop.set()
            return e
    return None


def _say_end(console, args: argparse.Namespace, sim, truth, stopped_by: list[str],
             failed: BaseException | None) -> None:
    """How the run ended, what it sent and where its files are; why no truth was written."""
    how = (f"stopped ({stopped_by[0]})" if stopped_by
           else f"the bus failed ({type(failed).__name__}: {failed}; was it closed?)"
           if failed is not None else "done")
    console.print(f"rsra sim: {how}: {len(sim.sync_info)} samples, {sim.frames_sent} frames sent, "
                  f"{sim.faults.events} fault events"
                  + (f", frames in {args.record}" if args.record else "")
                  + (f", truth in {truth}" if truth else ""), highlight=False)
    if args.truth and truth is None:  # said, not silently skipped
        console.print(f"rsra sim: no truth written to {args.truth}: no sample was simulated — "
                      + ("nothing started the nodes (no master's NMT start and SYNC on "
                         f"{args.interface}:{args.channel}); fix: run `rsra run` on the same bus "
                         "or give --autostart" if not args.autostart else
                         "the run ended before the first SYNC"), highlight=False)
