"""`rsra calibrate`: off-line known-load calibration from recordings (docs/cli.md §9; model.md §7
known-load mode; report Phase I and Appendix C). The work is in :mod:`daq.calibrate`."""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

from rsra.daq.runtime.persistence import write_text_atomic
from rsra.estimator.content import KINDS


OUTPUTS = {"out": "file", "posterior": "file"}  # checked against the inputs before any work (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="off-line calibration of the load-cell angles (or other parameters) from "
        "recordings with known loads",
        description="Reads recordings made with the reference balance on the bus (bench, shake "
        "or static calibration: the report's Phase I and Appendix C) through the same reader as "
        "the service, keeps the samples whose load cells, accelerometers and balance are present "
        "and unflagged, applies the content filter to the inertial loads, load cells and known "
        "loads alike (its settling is not scored), and identifies the parameters in one batch "
        "with the effective-variance likelihood of model.md §7 and a weak prior. Prints each "
        "parameter's start value, estimate, Cramér-Rao bound (conventional and corrected for "
        "coloured residuals) and change in σ; the residual RMS per axis against what the sensor "
        "noise explains; the information (determined and undetermined directions, condition "
        "number); convergence; and a plausibility check (angles beyond ±10°, masses and "
        "inertias not positive or beyond ±50 % of the config, attach points beyond ±0.2 m: "
        "flagged, not refused). With a recording folder and no --config, the folder's own "
        "configuration is used.")
    common_options(p)
    p.add_argument("logs", nargs="+", metavar="LOG|DIR",
                   help="recording files (candump .log, .blf, .asc, …) or recording folders, "
                   "each a continuous stretch; all are used together")
    p.add_argument("--params", default="angles", metavar="angles|NAME,…",
                   help='what to identify: "angles" (the 14 deformation angles, the default) or '
                   "a comma list of parameter names: the angles (delta_A, theta_A, …, psi_G), "
                   "cell attach points (x_A … z_G), hub centre (hub_x, hub_y, hub_z), effective "
                   'masses (m_x, m_y, m_z), inertias (I_xx, I_yy, I_zz); "angles" may be part '
                   "of the list")
    p.add_argument("--content", choices=KINDS, default=None,
                   help="what part of the data to identify from (model.md §7): static (low-pass "
                   "below 1/rev; the default from identification.content_known_loads), harmonics "
                   "(the modelled rotor harmonics), broadband (everything; only for rigs that "
                   "measure angular acceleration)")
    p.add_argument("--out", metavar="FILE", default=None,
                   help="write a TOML config fragment to adopt ([identification] "
                   "initial_angles_deg for angles; [geometry], [mass] or [[cells]] keys for the "
                   "others; [identification.structure] when the structure test selected one), "
                   "with the σ and the source recordings in comments")
    p.add_argument("--posterior", metavar="P.json", default=None,
                   help="also write the angles' posterior in the state-file format (rsra angles "
                   "show reads it; run and replay use it with --angles): pooled across the "
                   "recordings from each one's known-load information with the prior counted "
                   "once, with its covariance and reference load; beside it a homogeneity test "
                   "of the recordings (docs/identification.md, \"Pooling recordings\"): when "
                   "they disagree at 1e-3, no posterior is written and the exit status is 1. "
                   "Only with --params angles; replaces only a posterior file")
    p.add_argument("--json", action="store_true",
                   help='print the result as JSON instead of the tables: {"parameters": [{"name", '
                   '"unit", "start", "estimate", "sigma_cr", "sigma_cr_corrected", "prior_sigma", '
                   '"change_sigma", "determined"}], "names", "covariance", '
                   '"covariance_corrected", "alpha_all_deg", "residuals", "information", '
                   '"convergence", "plausibility", "data", "notes", "fragment", "next_conditions": '
                   '[{"H", "information_gain", "by_structure"}], "structure": {"structure", '
                   '"candidates", "structure_fit", "looks", "conditions"} or null, "posterior": '
                   "the pooled posterior and its homogeneity test with --posterior, else null} "
                   "(angles in degrees, loads in SI whatever --units)")
    p.add_argument("--angles", metavar="STATE", default=None,
                   help="start from the angles of a saved posterior (rsra angles show) instead of "
                   "identification.initial_angles_deg")
    from rsra.daq.cli.options import add_accept_option

    add_accept_option(p)
    p.add_argument("--prior-sigma-deg", type=float, default=None, metavar="DEG",
                   help="σ of the weak prior on the angles (default identification.prior_sigma_deg);"
                   " positions get 0.1 m, masses and inertias 25 %% of their configured value")
    p.add_argument("--max-iterations", type=int, default=None, metavar="N",
                   help="Levenberg-Marquardt iterations per stage (default "
                   "identification.max_iterations)")
    return p


class _Progress:
    """Recorded seconds read, on the terminal only (rich, on stderr)."""

    def __init__(self, enabled: bool):
        self.live = None
        if enabled:
            from rich.console import Console
            from rich.progress import Progress, TextColumn, TimeElapsedColumn

            self.live = Progress(TextColumn("calibrate: {task.description}"), TimeElapsedColumn(),
                                 transient=True, console=Console(stderr=True))
            self.task = self.live.add_task("reading", total=None)
            self.live.start()

    def update(self, seconds: float, samples: int) -> None:
        if self.live is not None:
            self.live.update(self.task, description=f"read {seconds:.0f} s of recording, "
                             f"{samples} samples")

    def say(self, text: str) -> None:
        if self.live is not None:
            self.live.update(self.task, description=text)

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()


def run(args: argparse.Namespace) -> int:
    from rsra.daq.analysis.calibrate import CalibrationError, parse_params
    from rsra.daq.bus.replay import config_for
    from rsra.daq.cli.options import UsageError

    _check_arguments(args)
    out = Path(args.out) if args.out else None
    cfg = config_for(args.logs, args.config)  # ConfigError → exit 2 in daq.cli
    try:
        names = parse_params(args.params, cfg)
    except CalibrationError as e:
        raise UsageError(str(e)) from None
    if args.posterior:
        _check_posterior_output(args.posterior, names, cfg)
    alpha_start = _starting_angles(args, cfg)
    parts, result = _identify(args, cfg, names, alpha_start)
    return _report(args, cfg, result, out, parts, alpha_start)


def _check_arguments(args: argparse.Namespace) -> None:
    """The options checked before anything is read (one line, exit 2)."""
    from rsra.daq.bus.replay import ReplayError, expand
    from rsra.daq.cli.options import UsageError

    if args.prior_sigma_deg is not None and not (math.isfinite(args.prior_sigma_deg)
                                                 and args.prior_sigma_deg > 0):
        raise UsageError(f"--prior-sigma-deg {args.prior_sigma_deg}: must be a positive number "
                         "of degrees")
    if args.max_iterations is not None and args.max_iterations < 1:
        raise UsageError(f"--max-iterations {args.max_iterations}: must be at least 1")
    try:
        expand(args.logs)
    except ReplayError as e:
        raise UsageError(str(e)) from None
    out = Path(args.out) if args.out else None
    if out is not None and not os.access(out.resolve().parent, os.W_OK):
        raise UsageError(f"--out {args.out}: folder {out.resolve().parent} is not writable")


def _starting_angles(args: argparse.Namespace, cfg) -> np.ndarray | None:
    """--angles: the saved posterior's angles over the configured ones (None without it)."""
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.posterior_file import load_checked
    from rsra.estimator.posterior import PosteriorFileError

    if not args.angles:
        return None
    try:
        state, warning = load_checked(cfg, args.angles,
                                      accept_rig_mismatch=args.accept_rig_mismatch)
    except PosteriorFileError as e:
        raise UsageError(str(e)) from None
    if warning:
        print(f"rsra calibrate: warning: {warning}", file=sys.stderr)
    angle_names = cfg.rig_model().geometry.angle_names
    alpha_start = np.asarray(cfg.identification.initial_angles_rad, float).copy()
    for n, v in zip(state.names, state.theta):
        if n in angle_names:
            alpha_start[angle_names.index(n)] = v
    return alpha_start


def _identify(args: argparse.Namespace, cfg, names, alpha_start):
    """The recordings' known-load windows (each on its own with --posterior) and the
    identification over all of them: (the parts or None, the result)."""
    from rsra.daq.analysis.calibrate import CalibrationError, calibrate, load_known_load_data
    from rsra.daq.cli.options import UsageError

    progress = _Progress(enabled=sys.stderr.isatty())
    try:
        parts = None
        try:
            if args.posterior:  # each recording's information on its own, then together
                from rsra.daq.analysis.information import load_each

                parts, data = load_each(cfg, args.logs, content=args.content,
                                        progress=progress.update)
            else:
                data = load_known_load_data(cfg, args.logs, content=args.content,
                                            progress=progress.update)
        except CalibrationError as e:
            raise UsageError(str(e)) from None
        progress.say(f"identifying {len(names)} parameters from {data.n_scored} samples")
        try:
            result = calibrate(cfg, data, names, alpha_start=alpha_start,
                               prior_sigma_rad=None if args.prior_sigma_deg is None
                               else math.radians(args.prior_sigma_deg),
                               max_iterations=args.max_iterations)
        except CalibrationError as e:
            raise UsageError(str(e)) from None
    finally:
        progress.close()
    return parts, result


def _report(args: argparse.Namespace, cfg, result, out: Path | None, parts,
            alpha_start) -> int:
    """The tables (or --json), the fragment (--out) and the pooled posterior (--posterior);
    the exit status."""
    from rsra.daq.analysis.calibrate import fragment_toml, structure_of
    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.next_conditions import for_calibration

    ok = result.status != "diverged"
    nxt = for_calibration(cfg, result) if ok else None
    struct = structure_of(cfg, result) if ok else None
    notes = _notes(cfg, result)
    pooled = _pool(cfg, args, parts, alpha_start) if parts is not None and ok else None
    wrote = None
    if out is not None and ok:
        write_text_atomic(out, fragment_toml(cfg, result, struct))
        wrote = str(out)
    if args.json:
        d = result.to_dict(cfg)
        d.update(notes=notes, fragment=wrote, next_conditions=nxt, structure=struct,
                 posterior=None if pooled is None else pooled.report())
        print(dumps(d))
    else:
        _print_text(cfg, result, args.units, notes, wrote, nxt, struct, pooled)
    if not ok:
        print("rsra calibrate: the identification diverged; no fragment written (check the "
              "recordings and the starting values)", file=sys.stderr)
        return 1
    if pooled is not None:
        return _save_posterior(args, pooled)
    return 0


def _print_text(cfg, result, units: str, notes: list[str], wrote: str | None,
                nxt: list[dict] | None, struct, pooled) -> None:
    """The readable report: the tables, the structure found and the pooled posterior."""
    _print_tables(cfg, result, units, notes, wrote, nxt)
    if struct is not None:
        _print_structure(struct)
    if pooled is not None:
        from rsra.daq.analysis.information import summary_lines

        print("\n".join(summary_lines(pooled.report())))


def _check_posterior_output(path: str, names, cfg) -> None:
    """--posterior: the 14 angles only, into a writable folder, replacing nothing but a
    posterior file (never an input, a device, a FIFO or another file)."""
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.posterior_file import classify

    if tuple(names) != tuple(cfg.rig_model().geometry.angle_names):
        raise UsageError("--posterior: only with --params angles (the posterior the service "
                         "uses holds the 14 angles)")
    target = Path(path)
    if not os.access(target.resolve().parent, os.W_OK):
        raise UsageError(f"--posterior {path}: folder {target.resolve().parent} is not writable")
    kind, _, problem = classify(target)
    if kind not in ("absent", "posterior"):
        raise UsageError(f"--posterior {path}: {problem or 'a damaged posterior'}; it replaces only "
                         "a posterior file — name a new file")


def _pool(cfg, args, parts, alpha_start):
    """The pooled posterior of the recordings and its homogeneity test
    (daq.analysis.information)."""
    import pyarrow as pa

    from rsra.daq.analysis.information import (
        PoolingError,
        information_table,
        pooled_posterior,
        x_columns,
    )
    from rsra.daq.cli.options import UsageError

    table = pa.concat_tables([information_table(cfg, d, str(p))
                              for d, p in zip(parts, args.logs)])
    try:
        return pooled_posterior(cfg, table, x_columns(cfg), alpha_start=alpha_start,
                                prior_sigma_rad=None if args.prior_sigma_deg is None
                                else math.radians(args.prior_sigma_deg),
                                max_iterations=args.max_iterations)
    except PoolingError as e:
        raise UsageError(str(e)) from None


def _save_posterior(args, pooled) -> int:
    """Saved unless the recordings disagree (exit 1, nothing written)."""
    from rsra.daq.runtime.persistence import save_posterior

    if not pooled.homogeneous:
        print("rsra calibrate: the recordings disagree (homogeneity test at 1e-3): "
              f"{', '.join(pooled.disagree())}; no posterior written", file=sys.stderr)
        return 1
    save_posterior(args.posterior, pooled.state)
    if not args.json:
        print(f"wrote {args.posterior}: the posterior of the 14 angles (rsra angles show; "
              "--angles of run and replay)")
    return 0


def _print_structure(struct: dict) -> None:
    """The structure test's verdict: constant angles, or what explains the data."""
    print(f"structure: {struct['structure']} ({struct['conditions']} load conditions, "
          f"{struct['looks']} windows)")
    for c in struct["candidates"][:4]:
        print(f"  candidate {c['structure']}: statistic {c['statistic']:.1f} on {c['dof']} dof"
              f"{', explains the data' if c['explains'] else ''}")
    fit = struct["structure_fit"]
    if fit is not None:
        print(f"  selected {fit['structure']}: its fit is in the fragment "
              "([identification.structure]); the hub loads use it")


def _notes(cfg, result) -> list[str]:
    """What the user should know beyond the numbers (model §7's warnings)."""
    from rsra.daq.analysis.calibrate import RESIDUAL_RATIO_FLAG

    notes = []
    if result.data.content != "static" and cfg.angular == "neglect":
        notes.append(f"content {result.data.content!r} on a rig that neglects the angular "
                     "inertial loads (inertial.angular = \"neglect\"): at the rotor harmonics "
                     "they bias the angles (model.md §7); prefer --content static")
    if result.status == "not_converged":
        notes.append(f"not converged in {result.ident.iterations} iterations: rerun with a larger "
                     "--max-iterations before adopting the fragment")
    bad = [a for a, r in zip(("X", "Y", "Z", "L", "M", "N"), result.residual_ratio)
           if r > RESIDUAL_RATIO_FLAG]
    if bad:
        notes.append(f"residuals on {', '.join(bad)} exceed {RESIDUAL_RATIO_FLAG:g}× what the sensor "
                     "noise explains: model error (balance, geometry, masses, an unmodelled load)")
    for f in result.flags:
        notes.append(f"plausibility: {f.name} {f.problem}")
    undet = len(result.names) - result.determined
    if undet:
        notes.append(f"{undet} direction(s) undetermined (σ above identification.sigma_max): the "
                     "data cannot tell them; more load conditions would")
    return notes


def _fmt(v: float, unit: str) -> str:
    if not math.isfinite(v):
        return "—"
    if unit == "deg":
        return f"{v:+.4f}"
    if unit == "m":
        return f"{v:+.5f}"
    return f"{v:.2f}"


def _print_tables(cfg, result, units: str, notes: list[str], wrote: str | None,
                  nxt: list[dict] | None = None) -> None:
    from rsra.daq.cli.console import make_console

    # a pipe gets the full table (rich assumes 80 columns there and would cut the numbers)
    con = make_console()
    d = result.data
    con.print(f"calibrate: {', '.join(d.files)} — {d.samples_read} samples read "
              f"({d.duration_s:.1f} s), {d.n_valid} with known loads, {d.n_scored} scored "
              f"(content {d.content}, {d.segments} stretch(es))"
              + ("; rejected: " + ", ".join(f"{k} {v}" for k, v in sorted(d.rejected.items()))
                 if d.rejected else ""))
    con.print(_estimates_table(cfg, result))
    con.print(_residuals_table(result, units))
    _print_closing(con, result, notes, wrote, nxt)


def _estimates_table(cfg, result):
    """Each parameter's start, estimate, σ's, change and flag, in its unit."""
    from rich.table import Table

    from rsra.daq.analysis.calibrate import parameter_unit

    t = Table(title="Estimates: σ_CR the Cramér–Rao bound, σ_MK corrected for coloured residuals "
              "(Morelli–Klein), change/σ = (estimate − start)/σ_CR")
    for col in ("parameter", "unit", "start", "estimate", "σ_CR", "σ_MK", "change/σ",
                "flag"):
        t.add_column(col, justify="left" if col in ("parameter", "unit", "flag") else "right")
    flagged = {f.name: f.problem for f in result.flags}
    for k, n in enumerate(result.names):
        unit = parameter_unit(n, cfg)
        s = math.degrees(1.0) if unit == "deg" else 1.0
        det = result.sigma[k] <= result.sigma_max[k]
        t.add_row(n, unit, _fmt(result.start[k] * s, unit), _fmt(result.estimate[k] * s, unit),
                  f"{result.sigma[k] * s:.4g}", f"{result.sigma_corrected[k] * s:.4g}",
                  f"{result.change_in_sigma[k]:+.1f}",
                  flagged.get(n, "" if det else "undetermined"))
    return t


def _residuals_table(result, units: str):
    """The residual RMS per axis against the sensor noise through the same filter."""
    from rich.table import Table

    from rsra.config.units import axis_units, to_units

    ax_units = axis_units(units)
    rms, exp = to_units(result.residual_rms, units), to_units(result.residual_expected, units)
    r = Table(title="Residuals at the estimate (rows of I = S T + R₀ H at the CG, content-filtered)"
              " against the sensor noise through the same filter")
    for col in ("axis", "unit", "RMS", "noise", "ratio"):
        r.add_column(col, justify="left" if col in ("axis", "unit") else "right")
    for i, ax in enumerate(("X", "Y", "Z", "L", "M", "N")):
        r.add_row(ax, ax_units[i], f"{rms[i]:.1f}", f"{exp[i]:.1f}",
                  f"{result.residual_ratio[i]:.2f}")
    return r


def _print_closing(con, result, notes: list[str], wrote: str | None,
                   nxt: list[dict] | None) -> None:
    """After the tables: information, convergence, plausibility, notes, the next load
    conditions and the fragment written."""
    lo, hi = result.information_ratio
    con.print(f"information: {result.determined} of {len(result.names)} directions determined "
              f"(σ ≤ sigma_max), condition number {result.condition:.3g}, data/prior "
              f"information {lo:.3g} … {hi:.3g}")
    for dct in result.undetermined:
        comps = ", ".join(f"{k} {v:+.2f}" for k, v in dct["components"].items())
        con.print(f"  undetermined: σ {dct['sigma']:.3g} along {comps}")
    con.print(f"convergence: {result.status} after {result.ident.iterations} iterations "
              f"(J {result.ident.cost_start:.6g} → {result.ident.cost:.6g}; coloured-residual "
              f"lags {result.ident.lags})")
    con.print("plausibility: " + ("ok" if not result.flags else
                                  "; ".join(f"{f.name} {f.problem}" for f in result.flags)))
    for n in notes:
        if not n.startswith("plausibility:"):
            con.print(f"note: {n}")
    if nxt:
        from rsra.daq.runtime.next_conditions import describe

        con.print("next load conditions to apply (D-optimal for the constant angles and per-cell "
                  "load gains, docs/identification.md):")
        for k, c in enumerate(nxt, 1):
            con.print(f"  {k}. {describe(c['H'], c['information_gain'])}")
    if wrote:
        con.print(f"wrote {wrote}: a rig layer — use it as --config {wrote} (after the rig's own "
                  "--config, if any); `rsra config show` names each value's file")
