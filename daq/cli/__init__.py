"""The `rsra` command line: a thin table of commands over the library (docs/cli.md).

Exit status: 0 success, 2 usage or configuration error, 1 anything else.
"""
from __future__ import annotations

import argparse
import errno
import importlib
import os
import re
import sys
from typing import NoReturn

from rsra.daq.cli.options import UsageError

# name -> module under daq.commands; each module has add_parser(sub) and run(args).
COMMANDS = {
    "noise-budget": "noise_budget",
    "listen": "listen",
    "run": "run",
    "demo": "demo",
    "sim": "sim",
    "bus": "bus",
    "replay": "replay",
    "nodes": "nodes",
    "zero": "zero",
    "angles": "angles",
    "report": "report",
    "sweep": "sweep",
    "calibrate": "calibrate",
    "export": "export",
    "web": "web",
    "config": "config",
    "campaign": "campaign",
    "survey": "survey",
    "mark": "mark",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _version() -> str:
    """The installed distribution's version (pyproject.toml), or 'unknown' outside one."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rsra")
    except PackageNotFoundError:
        return "unknown"


class _VersionAction(argparse.Action):
    """``--version``: the version looked up only when asked (importlib.metadata's look-up
    costs every start-up tens of ms otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"rsra {_version()}")
        parser.exit()


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or (``only``) of that one command alone: the others are
    left out, and with them their imports (``rsra replay --help`` imports no scipy)."""
    parser = _Parser(prog="rsra", description=(
        "Rotor hub loads from the load cells of an isolated transmission: CANopen DAQ, "
        "fixed-gain Kalman filter, on-line calibration of the load-cell angles, Zenoh telemetry."))
    parser.add_argument("--version", action=_VersionAction,
                        help="print the version of rsra and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, module in COMMANDS.items():
        if only is not None and name != only:
            continue
        mod = importlib.import_module(f"rsra.daq.cli.commands.{module}")
        p = mod.add_parser(sub, name)
        p.set_defaults(_run=mod.run, _outputs={"log_file": "file", **getattr(mod, "OUTPUTS", {})},
                       _inputs=getattr(mod, "INPUTS", ()))
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C at any moment, the start-up's imports included
        return 130


def _command(argv: list[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def _main(argv: list[str] | None) -> int:
    parser = build_parser(_command(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        from rsra.daq.cli.outputs import check_outputs

        check_outputs(args, args._outputs, args._inputs)  # an output never replaces an input: before any work
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
    except Exception as e:  # the one error path: every failure is one line (docs/cli.md §17)
        if os.environ.get("RSRA_DEBUG"):
            raise
        status, line = describe_error(e)
        print(f"rsra {args.command}: {line}", file=sys.stderr)
        return status


_RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def zenoh_error_line(e: BaseException) -> str:
    """A Zenoh error in one line, without the Rust source paths it carries."""
    text = " ".join(_RUST_SOURCE.sub("", str(e)).split())
    m = re.search(r"bound to (\S+?):? \[.*Address already in use", text)
    if m:
        return (f"cannot listen on {m.group(1)}: the address is in use (another rsra or Zenoh "
                "router?); fix: stop that process or give a free port with --zenoh-listen "
                "tcp/127.0.0.1:PORT")
    return (f"cannot open the Zenoh session: {text}; fix: check --zenoh-config, "
            "--zenoh-listen and --zenoh-connect, certificates and credentials")


def describe_error(e: BaseException) -> tuple[int, str]:
    """(exit status, one line) for any exception that ends a command: 2 for a usage,
    configuration or bad-input error, 1 for anything else (docs/cli.md §17)."""
    from rsra.daq.bus.master import BootError
    from rsra.daq.bus.recorder import RecordingError
    from rsra.daq.bus.replay import ReplayError
    from rsra.daq.runtime.service import BusOpenError
    from rsra.config.readfile import UnreadableFile
    from rsra.daq.runtime.foxglove_out import FoxgloveAddressError
    from rsra.config.rig import ConfigError
    from rsra.daq.runtime.persistence import OutputRefused
    from rsra.estimator.posterior import PosteriorFileError
    from rsra.sim_bus.faults import FaultSpecError

    if isinstance(e, ConfigError):
        return 2, f"configuration error: {_one_line(e)}"
    if isinstance(e, (UsageError, PosteriorFileError, FaultSpecError, RecordingError,
                      ReplayError, BusOpenError, FoxgloveAddressError, OutputRefused,
                      UnreadableFile)):
        return 2, f"error: {_one_line(e)}"
    if isinstance(e, BootError):
        return 1, f"the nodes could not be started: {_one_line(e)}"
    try:
        import zenoh

        if isinstance(e, zenoh.ZError):
            return 1, zenoh_error_line(e)
    except ImportError:  # pragma: no cover - zenoh is a dependency
        pass
    if isinstance(e, OSError):
        where = e.filename if e.filename is not None else ""
        what = e.strerror or str(e)
        return 1, (f"{where}: {what}" if where else what) + (
            "; fix: free some space or write elsewhere" if e.errno == errno.ENOSPC else "")
    return 1, (f"internal error: {type(e).__name__}: {_one_line(e)} (please report it; "
               "RSRA_DEBUG=1 shows the traceback)")


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


if __name__ == "__main__":
    raise SystemExit(main())
