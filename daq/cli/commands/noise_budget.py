"""`rsra noise-budget`: the static-estimate noise budget of the configured rig (model §4)."""
from __future__ import annotations

import argparse
import json

from rsra.daq.rigmodel import load_rig
from rsra.config.units import axis_units, to_units
from rsra.estimator.noise_budget import AXES, noise_budget


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(name, help="per-axis noise budget of the static hub-load estimate",
                       description="The lower bound on static accuracy without statistical "
                       "processing (report Appendix B): per axis the total sigma and its "
                       "load-cell and accelerometer parts.")
    common_options(p)
    p.add_argument("--json", action="store_true",
                   help='print {"units", "axes", "total", "load_cells", "accelerometers"}')
    return p


def run(args: argparse.Namespace) -> int:
    cfg = load_rig(args.config)
    nb = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad)
    units = axis_units(args.units)
    total, cells, acc = (to_units(v, args.units) for v in (nb.total, nb.load_cells, nb.accelerometers))
    if args.json:
        print(json.dumps({"units": units, "axes": list(AXES), "total": total.tolist(),
                          "load_cells": cells.tolist(), "accelerometers": acc.tolist()},
                         allow_nan=False))
        return 0
    from rich.table import Table

    from rsra.daq.cli.console import make_console

    t = Table(title=f"Static-estimate noise budget, rig {cfg.rig_name!r}, {cfg.hub_frame} axes")
    for col in ("axis", "unit", "total σ", "load cells", "accelerometers"):
        t.add_column(col, justify="right" if col not in ("axis", "unit") else "left")
    for i, ax in enumerate(AXES):
        t.add_row(ax, units[i], f"{total[i]:.1f}", f"{cells[i]:.1f}", f"{acc[i]:.1f}")
    make_console().print(t)
    return 0
