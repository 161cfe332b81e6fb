"""The `rsra` command line: a thin table of commands over the library (spec: cli.md).

Exit status: 0 success, 2 usage or configuration error, 1 anything else.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from daq.config import ConfigError

# name -> module under daq.commands; each module has add_parser(sub) and run(args).
COMMANDS = {
    "noise-budget": "noise_budget",
    "listen": "listen",
    "run": "run",
    "demo": "demo",
    "sim": "sim",
    "replay": "replay",
    "nodes": "nodes",
    "zero": "zero",
    "angles": "angles",
    "report": "report",
    "sweep": "sweep",
    "calibrate": "calibrate",
    "export": "export",
}


class UsageError(Exception):
    """A user mistake on the command line: one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def common_options(p: argparse.ArgumentParser, units: bool = True) -> None:
    p.add_argument("--config", metavar="PATH", default=None,
                   help="rig TOML (default: the packaged default rig)")
    if units:
        p.add_argument("--units", choices=("si", "us"), default="si",
                       help="display units: si (N, N·m) or us (lbf, ft·lbf); default si")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rsra", description=(
        "Rotor hub loads from the load cells of an isolated transmission: CANopen DAQ, "
        "fixed-gain Kalman filter, on-line calibration of the load-cell angles, Zenoh telemetry."))
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, module in COMMANDS.items():
        mod = importlib.import_module(f"daq.commands.{module}")
        p = mod.add_parser(sub, name)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except ConfigError as e:
        print(f"rsra {args.command}: configuration error: {e}", file=sys.stderr)
        return 2
    except UsageError as e:
        print(f"rsra {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
