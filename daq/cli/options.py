"""What the commands share: the usage error, the common options and their checks.

Each command module (``rsra.daq.cli.commands.<name>``) imports from here and from the library,
never from another command; ``rsra.daq.cli`` is the table that imports the commands.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path

LOG_FILE_BYTES = 10 * 1024 * 1024
LOG_FILE_BACKUPS = 5


class UsageError(Exception):
    """A user mistake on the command line: one line, exit 2."""


def common_options(p: argparse.ArgumentParser, units: bool = True) -> None:
    p.add_argument("--config", metavar="PATH", default=None, action="append",
                   help="rig TOML holding what differs from the packaged default rig (or from "
                   "the rig it names in extends = \"...\"); repeat to apply several in order, "
                   "the last one's value winning (docs/configuration.md)")
    if units:
        p.add_argument("--units", choices=("si", "us"), default="si",
                       help="display units: si (N, N·m) or us (lbf, ft·lbf); default si")


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


def variant(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--variant``: the value as a TOML value (``7``, ``false``, ``[1.0, 2]``,
    ``"linear"``), else the text itself (``angles=linear``)."""
    key, eq, value = text.partition("=")
    if not eq or not key.strip():
        raise argparse.ArgumentTypeError(f"'{text}' is not KEY=VALUE (e.g. angles=linear)")
    import tomllib

    try:
        parsed: object = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return key.strip(), parsed


def add_variant_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--variant", type=variant, action="append", default=[], metavar="KEY=VALUE",
                   help="a variant of the scenario (repeatable), e.g. angles=linear (the "
                   "ground test's angles follow the thrust), turbulence=true, noise=false, "
                   "angles.step_at_s=[30.0] (docs/simulator.md)")


def add_sim_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=seed, default=None, help="simulator seed (default: the scenario's)")
    add_variant_option(p)
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


def add_realtime_priority(p: argparse.ArgumentParser) -> None:
    p.add_argument("--realtime-priority", type=positive_int, default=None, metavar="N",
                   help="run the service's threads under SCHED_FIFO at priority N (1-99, e.g. "
                   "10; Linux, root or CAP_SYS_NICE): no other process can delay a sample "
                   "(docs/deployment.md)")


def add_service_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--record", metavar="DIR", default=None,
                   help="record every frame, the angle schedule and the effective config here")
    p.add_argument("--angles", metavar="STATE", default=None,
                   help="start from a saved posterior (see identification.state_file)")
    add_accept_option(p)
    add_no_identification(p)
    p.add_argument("--zenoh-config", metavar="FILE", default=None,
                   help="a Zenoh config file (TLS, user/password, access control)")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP",
                   help="Zenoh endpoint (router) to connect to (repeatable)")
    from rsra.daq.runtime.foxglove_out import add_options as add_foxglove_options

    add_foxglove_options(p)
    add_realtime_priority(p)
    p.add_argument("--log-file", metavar="FILE", default=None,
                   help="log to this size-rotated file instead of stderr")
    p.add_argument("--log-level", default="info",
                   choices=("debug", "info", "warning", "error"), help="default info")


def setup_logging(level: str, log_file: str | None) -> None:
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    if log_file:
        try:
            # (only with --log-file: not imported on every start-up)
            from logging.handlers import RotatingFileHandler

            h: logging.Handler = RotatingFileHandler(
                log_file, maxBytes=LOG_FILE_BYTES, backupCount=LOG_FILE_BACKUPS)
        except OSError as e:
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


def check_sim_faults(cfg, scenario: str | None, faults: str | None, speed: float | None,
                     variants: dict | None = None) -> None:
    """A --faults SPEC checked against the simulated bus before anything starts (FaultSpecError:
    one line, exit 2): the same parse and check as the simulator's."""
    if not faults or scenario is None:
        return
    from rsra.sim_bus.bus_sim import check_faults
    from rsra.sim_bus.scenarios import load_scenario

    # the service's simulator produces SYNC itself (autostart) in lock-step only
    check_faults(cfg, faults, load_scenario(scenario, **(variants or {})).nodes_present,
                 autostart=speed != 1.0)


def config_for_run(config: str | None, scenario: str | None, variants: dict | None = None):
    """The rig config, with a simulated scenario's own overrides (e.g. `paper` starts the
    service at 4°) when the simulator is attached."""
    from rsra.config.rig import ConfigError
    from rsra.daq.rigmodel import load_rig

    if scenario is None:
        return load_rig(config)
    from rsra.sim_bus.scenarios import load_scenario

    try:
        sc = load_scenario(scenario, **(variants or {}))
    except ConfigError:
        raise
    except (FileNotFoundError, ValueError) as e:
        raise UsageError(str(e)) from None
    cfg = load_rig(config, overrides=sc.rig_overrides or None)
    from rsra.sim_bus.scenarios import check_against_rig

    # content the rig cannot sample, refused before anything starts (the physics checks it too)
    check_against_rig(sc, cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s, cfg.rotor.blades)
    return cfg


def check_output_file(option: str, path: str, suffix: str | None = None) -> None:
    """An output file named on the command line, checked before any work: not a folder, in an
    existing folder we may write (no folder is created for it: nothing the user did not name);
    with ``suffix``, a name ending in it (the file written is the file named: numpy would add
    ``.npz`` to a truth file's name, and write a file nobody checked)."""

    p = Path(path)
    if suffix is not None and not p.name.endswith(suffix):
        raise UsageError(f"{option} {path}: the file written would be {path}{suffix}; fix: "
                         f"give a name ending in {suffix} ({p.name}{suffix})")
    if p.is_dir():
        raise UsageError(f"{option} {path}: is a folder; fix: give a file name")
    parent = p.resolve().parent
    if not parent.is_dir():
        raise UsageError(f"{option} {path}: no folder {parent}; fix: create it or write elsewhere")
    if not os.access(parent, os.W_OK):
        raise UsageError(f"{option} {path}: folder {parent} is not writable; fix: write "
                         "elsewhere")


ACCEPT_HELP = ("use a posterior saved on a rig of another geometry (its fingerprint: cell names, "
               "positions, nominal axes, hub position, angle names) instead of refusing it; the "
               "angles' physical range is still enforced")


def add_accept_option(p) -> None:
    """``--accept-rig-mismatch`` on every command that loads a posterior (docs/cli.md)."""
    p.add_argument("--accept-rig-mismatch", action="store_true", help=ACCEPT_HELP)
