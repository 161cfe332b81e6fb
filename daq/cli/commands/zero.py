"""`rsra zero`: the command line of the tare (the work is in :mod:`rsra.daq.analysis.tare`;
docs/cli.md §11)."""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.bus.decoder import DecodeTable
from rsra.config.units import FT_LBF_NM, LBF_N
from rsra.daq.runtime.persistence import write_text_atomic

from rsra.daq.analysis.tare import (
    acquire,
    channel_specs,
    DEFAULT_MAX_OFFSET_FS,
    DEFAULT_MIN_SAMPLES,
    DEFAULT_SECONDS,
    extractor,
    fragment,
    FT_M,
    tare,
    TareResult,
)

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID


OUTPUTS = {"out": "file"}  # checked against the inputs before any work (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="tare: zero offsets with the rotor stopped and no applied load",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Tare with the rotor stopped and no applied load: boots the nodes (as the service does),
averages every channel for --seconds of acquisition time, prints per channel the mean, σ
and number of samples, and writes the zero offsets as a [calibration] TOML fragment to
adopt ("<node>.<channel>" = { gain = …, offset = … }; gains kept from the config).

Targets (what each channel reads at rest after the tare):
  accelerometers   the gravity vector in body axes: f = a − g = (0, 0, −g), z down
                   (−1000 mg on z; assumes a level rig). Gravity stays in the readings:
                   the balance I = S T + R H (model §3) carries it on both sides.
  load cells       their dead-weight reactions, not 0 — at rest they carry the weight.
                   The smallest σ-weighted correction that makes S(α) T = I, i.e. the
                   static hub-load estimate Ĥ = R⁻¹(I − S T) reads 0 at rest; α = the
                   configured initial angles (or --angles STATE). Zeroing the cells
                   would show the weight (≈ m_z g) as a hub load.
  rotor speed, reference balance, drive loads   0.
  not tared        azimuth (its zero is the blade reference), status bytes, absent nodes.

Refuses (exit 1, nothing written) when the rotor turns (Ω above rotor.omega_min_fraction ×
omega_nominal_rad_s), when a load shows (a channel's σ above its configured sensor σ at a
10⁻³ false-alarm rate over all channels, or a shift beyond --max-offset-fs of full scale),
when a load cell reports over-range or a fault, or with fewer than --min-samples samples.
Exit 0 when the fragment is written, 2 for a usage or configuration error.""")
    common_options(p)
    p.add_argument("--interface", default=None, metavar="I",
                   help="python-can interface, e.g. socketcan (required)")
    p.add_argument("--channel", default=None, metavar="C",
                   help="python-can channel, e.g. vcan0 or can0")
    p.add_argument("--seconds", type=float, default=DEFAULT_SECONDS, metavar="S",
                   help=f"seconds of acquisition time to average (default {DEFAULT_SECONDS:g})")
    p.add_argument("--out", default=None, metavar="FILE",
                   help="write the fragment to FILE (atomically; the report goes to stdout); "
                   "default: the fragment on stdout, the report on stderr")
    p.add_argument("--min-samples", type=int, default=DEFAULT_MIN_SAMPLES, metavar="N",
                   help=f"refuse with fewer samples per channel (default {DEFAULT_MIN_SAMPLES}: "
                   "the tare's own error σ/√N stays below 10 %% of the sensor σ)")
    p.add_argument("--max-offset-fs", type=float, default=DEFAULT_MAX_OFFSET_FS, metavar="F",
                   help="refuse a shift larger than F × full scale (load cells, accelerometers, "
                   f"balance; default {DEFAULT_MAX_OFFSET_FS:g}: a healthy load cell's zero "
                   "balance is within ±1 %% of rated output, more is a load or a tilt)")
    p.add_argument("--angles", default=None, metavar="STATE",
                   help="take α for S(α) from a saved posterior (default: the configured "
                   "initial angles)")
    from rsra.daq.cli.options import add_accept_option

    add_accept_option(p)
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.rigmodel import load_rig
    from rsra.daq.cli.console import make_console

    out = _check_arguments(args)
    cfg = load_rig(args.config)
    table = DecodeTable(cfg)
    specs = channel_specs(cfg, table, args.max_offset_fs)
    alpha, angles_from = _angles(cfg, args.angles, args.accept_rig_mismatch)

    report = make_console(stderr=out is None)
    if not report.is_terminal:
        report.width = max(report.width, 120)
    bus = f"{args.interface}:{args.channel}" if args.channel else args.interface
    acquired = _acquire(args, cfg, table, specs)
    if acquired is None:
        return 1
    values, span, flags = acquired
    result = tare(cfg, specs, values, alpha=alpha, min_samples=args.min_samples,
                  status_counts=dict(flags), span_s=span)
    _print_report(report, cfg, result, args.units, bus)
    if not result.ok:
        for p in result.problems:
            print(f"rsra zero: refused: {p}", file=sys.stderr)
        return 1
    text = fragment(cfg, result, angles_from=angles_from, bus=bus)
    if out is None:
        sys.stdout.write(text)
    else:
        write_text_atomic(out, text)
        report.print(f"rsra zero: wrote {out} ({sum(c.n > 0 for c in result.channels)} channels)",
                     highlight=False)
    return 0


def _check_arguments(args: argparse.Namespace) -> Path | None:
    """The options checked before the bus is touched (one line, exit 2); the --out path."""
    from rsra.daq.cli.options import UsageError

    if args.interface is None:
        raise UsageError("give the bus: --interface I [--channel C], e.g. --interface socketcan "
                         "--channel vcan0")
    if not (args.seconds > 0 and math.isfinite(args.seconds)):
        raise UsageError(f"--seconds {args.seconds}: must be a positive number of seconds")
    if args.min_samples < 2:
        raise UsageError(f"--min-samples {args.min_samples}: must be at least 2")
    if not 0 < args.max_offset_fs <= 1:
        raise UsageError(f"--max-offset-fs {args.max_offset_fs}: must be in (0, 1]")
    out = Path(args.out) if args.out else None
    if out is not None and not os.access(out.resolve().parent, os.W_OK):
        raise UsageError(f"--out {args.out}: folder {out.resolve().parent} is not writable")
    return out


def _acquire(args: argparse.Namespace, cfg: RigConfig, table: DecodeTable, specs):
    """--seconds of the channels from the bus: (values, span, status flags), or None when
    the nodes could not be started (said on stderr); a bus that does not open: exit 2."""
    import can

    from rsra.daq.bus.master import BootError
    from rsra.daq.bus.reader import Reader
    from rsra.daq.cli.options import UsageError

    reader = Reader(cfg, interface=args.interface, channel=args.channel, table=table)
    try:
        try:
            reader.start()
        except BootError as e:
            print(f"rsra zero: the nodes could not be started: {e}", file=sys.stderr)
            return None
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise UsageError(f"cannot open the bus --interface {args.interface} --channel "
                             f"{args.channel}: {e}; check the interface and channel") from None
        with _Progress(args.seconds) as progress:
            return acquire(reader, args.seconds, extractor(cfg, specs), len(specs),
                           progress.update)
    finally:
        reader.close()


def _angles(cfg: RigConfig, state: str | None,
            accept_rig_mismatch: bool = False) -> tuple[np.ndarray, str]:
    if state is None:
        deg = np.degrees(cfg.identification.initial_angles_rad)
        return cfg.identification.initial_angles_rad, (
            "the configured initial angles" + (f" ({deg[0]:g} deg)" if np.all(deg == deg[0])
                                               else ""))
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.posterior_file import load_checked
    from rsra.estimator.posterior import PosteriorFileError

    names = cfg.rig_model().geometry.angle_names
    try:
        st, warning = load_checked(cfg, state, accept_rig_mismatch=accept_rig_mismatch)
    except PosteriorFileError as e:
        raise UsageError(f"--angles: {e}") from None
    if warning:
        print(f"rsra zero: warning: {warning}", file=sys.stderr)
    alpha = np.array(cfg.identification.initial_angles_rad, float)
    for name, value in zip(st.names, st.theta):
        if name in names:
            alpha[names.index(name)] = value
    return alpha, f"the saved posterior {state}"


_UNIT = {"si": {"force": ("N", 1.0), "moment": ("N·m", 1.0), "accel": ("m/s²", 1.0),
                "rate": ("rad/s", 1.0)},
         "us": {"force": ("lbf", 1 / LBF_N), "moment": ("ft·lbf", 1 / FT_LBF_NM),
                "accel": ("ft/s²", 1 / FT_M), "rate": ("rad/s", 1.0)}}


def _print_report(console: Any, cfg: RigConfig, result: TareResult, units: str, bus: str) -> None:
    from rich.table import Table

    t = Table(title=f"Tare of rig {cfg.rig_name!r} on {bus}: {result.samples} samples, "
              f"{result.span_s:.2f} s")
    for col in ("channel", "unit", "n", "mean", "σ", "target", "offset now", "new offset"):
        t.add_column(col, justify="left" if col in ("channel", "unit") else "right")
    for c in result.channels:
        unit, k = _UNIT[units][c.spec.quantity]
        if c.n == 0:
            t.add_row(c.spec.key, unit, "0", "—", "—", "—", f"{c.spec.offset * k:.5g}",
                      "(absent: kept)")
            continue
        t.add_row(c.spec.key, unit, str(c.n), f"{c.mean * k:.6g}", f"{c.std * k:.4g}",
                  f"{c.target * k:.6g}", f"{c.spec.offset * k:.5g}", f"{c.new_offset * k:.5g}")
    console.print(t)
    if result.hub_loads_now is not None:
        ax = ("X", "Y", "Z", "L", "M", "N")
        kinds = ["force"] * 3 + ["moment"] * 3
        parts = [f"{a} {v * _UNIT[units][q][1]:.4g} {_UNIT[units][q][0]}"
                 for a, v, q in zip(ax, result.hub_loads_now, kinds)]
        console.print("hub loads read before the tare (zero after it): " + ", ".join(parts),
                      highlight=False)
    for note in result.notes:
        console.print(f"note: {note}", highlight=False)


class _Progress:
    """Acquisition progress on a terminal (rich), one line otherwise."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.live: Progress | None = None
        self.task: TaskID | None = None
        self._last = 0.0

    def __enter__(self) -> "_Progress":
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self.live = Progress(TextColumn("averaging"), BarColumn(),
                                 TextColumn("{task.completed:.1f}/{task.total:g} s"),
                                 TimeRemainingColumn(), console=Console(stderr=True),
                                 transient=True)
            self.live.start()
            self.task = self.live.add_task("tare", total=self.seconds)
        else:
            print(f"rsra zero: averaging {self.seconds:g} s of samples…", file=sys.stderr)
        return self

    def update(self, t: float) -> None:
        if self.live is not None and self.task is not None and t - self._last >= 0.1:
            self._last = t  # (live and task: made together)
            self.live.update(self.task, completed=t)

    def __exit__(self, *exc: object) -> None:
        if self.live is not None:
            self.live.stop()
