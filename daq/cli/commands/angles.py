"""`rsra angles show|reset STATE`: inspect a saved posterior, or reset it to the configured
prior (docs/cli.md §12; model.md §7.4 "sequential posterior").

The state file is what the service saves after every accepted identification run
(``identification.state_file``, daq.persistence.save_posterior) and what ``--angles``
starts from. ``show`` prints the angles in degrees, their σ, how many directions are
determined (posterior σ ≤ ``identification.sigma_max_deg``) and the condition number;
``reset`` rewrites it atomically with the configured prior (initial angles, prior σ), asking
nothing (scripts).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.estimator.posterior import PosteriorFileError, PosteriorState, determined_directions

DIRECTION_COMPONENT_MIN = 0.1  # components of an undetermined direction worth naming
SHOW_DIRECTIONS = 5
RANGE_Z = 1.959964  # the 95 % two-sided range of a Gaussian: ± 1.96 σ  # undetermined directions listed in the table view (largest σ first)


def _configured_names(cfg: RigConfig) -> tuple[tuple[str, ...], tuple[str, ...]]:
    angle_names = cfg.rig_model().geometry.angle_names
    p = cfg.identification.parameters
    return (angle_names if p == "angles" else tuple(p)), angle_names


def describe(state: PosteriorState, cfg: RigConfig) -> dict:
    """Everything `show` prints, as JSON-ready values (degrees)."""
    from rsra.daq.cli.options import UsageError

    configured, angle_names = _configured_names(cfg)
    others = [n for n in state.names if n not in angle_names]
    if others:
        raise UsageError(f"the posterior holds parameters that are not deformation angles of "
                         f"this rig ({', '.join(others)}); check --config")
    smax = cfg.identification.sigma_max_rad
    s = np.full(len(state.names), smax)
    sigma = np.sqrt(np.diag(state.P))
    det, U, cond = determined_directions(state.P, s)
    directions: list[dict[str, Any]] = []
    for j in range(U.shape[1]):
        d = U[:, j] / np.linalg.norm(U[:, j])
        d = d if d[np.argmax(np.abs(d))] > 0 else -d  # sign: largest component positive
        directions.append({
            "sigma_deg": math.degrees(math.sqrt(float(d @ state.P @ d))),
            "components": {n: round(float(w), 3) for n, w in zip(state.names, d)
                           if abs(w) >= DIRECTION_COMPONENT_MIN}})
    directions.sort(key=lambda x: -x["sigma_deg"])
    return {
        "names": list(state.names),
        "angles_deg": np.degrees(state.theta).tolist(),
        "sigma_deg": np.degrees(sigma).tolist(),
        "sigma_max_deg": math.degrees(smax),
        # each angle's 95 % range (± RANGE_Z σ, the Gaussian posterior) and the physical
        # range every angle is held to (identification.angle_limit_deg)
        "range_deg": [[math.degrees(a - RANGE_Z * sg), math.degrees(a + RANGE_Z * sg)]
                      for a, sg in zip(state.theta, sigma)],
        "angle_limit_deg": math.degrees(cfg.identification.angle_limit_rad),
        "determined": det,
        "parameters": len(state.names),
        "determined_parameters": (sigma <= smax).tolist(),
        "undetermined_directions": directions,
        "condition": cond if math.isfinite(cond) else None,
        "applies_from_seq": state.applies_from_seq,
        "t": state.t,
        "reference_load": (None if state.reference_load is None
                           else [float(x) for x in state.reference_load]),
        "matches_config": tuple(state.names) == tuple(configured),
        "version": state.version,
        "rig_difference": _rig_difference(state, cfg),
    }


def _rig_difference(state: PosteriorState, cfg: RigConfig) -> str | None:
    """The first item in which the file's rig fingerprint differs from the configured rig
    (None: the same rig, or a version-1 file without a fingerprint)."""
    from rsra.estimator.posterior import rig_difference, rig_fingerprint

    if state.rig is None:
        return None
    return rig_difference(state.rig, rig_fingerprint(cfg.rig_model().geometry))


def prior_state(cfg: RigConfig) -> PosteriorState:
    """The configured prior: initial angles, covariance diag(prior σ²)."""
    from rsra.daq.cli.options import UsageError
    from rsra.estimator.posterior import SequentialPosterior

    names, angle_names = _configured_names(cfg)
    from rsra.estimator.posterior import rig_fingerprint

    try:
        post = SequentialPosterior.from_config(cfg.identification, names, angle_names,
                                               rig=rig_fingerprint(cfg.rig_model().geometry))
    except ValueError as e:
        raise UsageError(f"identification.parameters: {e}; only angles have a configured "
                         "prior") from None
    return post.state()


# ---------------------------------------------------------------------------------------------
# command line

def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="inspect a saved posterior (show) or reset it to the configured prior",
        description="The saved posterior of the angle identification (the service writes it "
        "after every accepted run to identification.state_file; run --angles STATE starts "
        "from it). 'show STATE' prints it, 'reset STATE' rewrites it with the configured prior.")
    acts = p.add_subparsers(dest="action", metavar="ACTION", required=True,
                            help="show: print a posterior; reset: rewrite it with the prior")
    show = acts.add_parser(
        "show", help="angles, σ, determined directions and condition number of a posterior",
        description="Print a saved posterior: every angle and its posterior σ in degrees "
        "(in both unit systems), which are determined (σ ≤ identification.sigma_max_deg), how "
        "many eigen-directions of the covariance are determined, the undetermined directions "
        "(the angle combinations the data have not fixed, with their σ) and the condition "
        "number of the covariance scaled by sigma_max. A corrupt or unreadable file: one-line "
        "error, exit 2.")
    common_options(show)
    show.add_argument("state", metavar="STATE",
                      help="the posterior file (JSON), or a recording's angles.jsonl (or its "
                      "folder): its last applied record, else its starting posterior")
    show.add_argument("--json", action="store_true",
                      help='print {"file", "names", "angles_deg", "sigma_deg", "sigma_max_deg", '
                      '"determined", "parameters", "determined_parameters", '
                      '"undetermined_directions": [{"sigma_deg", "components"}], "condition", '
                      '"applies_from_seq", "t", "matches_config", "version", "rig_difference"}')
    reset = acts.add_parser(
        "reset", help="rewrite a posterior with the configured prior (no questions)",
        description="Rewrite STATE atomically with the configured prior: the angles of "
        "identification.initial_angles_deg and the covariance diag(prior_sigma_deg²), applying "
        "from the start. Asks nothing (for scripts) and prints what it did. Creates STATE when "
        "it does not exist and replaces a damaged posterior; a file that is not a posterior at "
        "all is left alone (exit 2), in case the path is wrong.")
    common_options(reset, units=False)
    reset.add_argument("state", metavar="STATE", help="the posterior file (JSON) to rewrite")
    return p


def run(args: argparse.Namespace) -> int:
    from rsra.daq.rigmodel import load_rig

    cfg = load_rig(args.config)
    if args.action == "show":
        return _show(cfg, args)
    return _reset(cfg, args)


def _load(path: str) -> PosteriorState:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.persistence import load_posterior

    try:
        return load_posterior(path)
    except PosteriorFileError as e:
        raise UsageError(str(e)) from None


def _is_recording(path: Path) -> bool:
    """A recording's angles schedule (a folder holding angles.jsonl, or a JSON-lines file whose
    first line is an angles record), not a saved posterior."""
    if path.is_dir():
        return (path / "angles.jsonl").is_file()
    if path.suffix == ".jsonl":
        return True
    try:
        with open(path, encoding="utf-8") as f:
            first = f.readline()
        rec = json.loads(first)
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(rec, dict) and ("initial" in rec or "accepted" in rec)


def _from_recording(path: Path) -> tuple[PosteriorState, dict]:
    """The posterior of a recording's last applied ``angles`` record (accepted; else its
    starting posterior) and what to say about where it came from."""
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.sources import read_angles_schedule

    from rsra.config.readfile import UnreadableFile, check_utf8

    file = path / "angles.jsonl" if path.is_dir() else path
    try:  # a bad byte: one line naming the file and its line, not a decoding error
        check_utf8(file)
    except UnreadableFile as e:
        raise UsageError(str(e)) from None
    initial, records = read_angles_schedule(file.parent, file)
    applied = [(i, r) for i, r in enumerate(records) if r.get("accepted")]
    if applied:
        i, rec = applied[-1]
        source = {"record": "last_applied", "index": i + 1, "records": len(records),
                  "after": len(records) - i - 1,
                  "reset_after": any(r.get("reason") == "reset" for r in records[i + 1:])}
    elif initial is not None:
        rec = initial
        source = {"record": "initial", "index": 0, "records": len(records),
                  "after": len(records), "reset_after": False}
    else:
        raise UsageError(f"{file}: holds no angles record (an empty schedule); fix: give a "
                         "recording made with identification on, or a posterior file")
    source["advice"] = _latest_advice(records)
    names, alpha, P = rec.get("names"), rec.get("alpha"), rec.get("P")
    try:
        theta = np.asarray(alpha, float).reshape(-1)
        Pm = np.asarray(P, float)
        if (not isinstance(names, list) or len(names) != theta.size
                or Pm.shape != (theta.size, theta.size) or not np.all(np.isfinite(Pm))):
            raise ValueError
    except (TypeError, ValueError):
        raise UsageError(f"{file}: its {'starting' if rec is initial else 'last applied'} "
                         "record has no usable names, alpha and P; fix: give a posterior "
                         "file") from None
    seq = rec.get("applies_from_seq")
    state = PosteriorState(names=tuple(names), theta=theta, P=Pm,
                           applies_from_seq=seq if isinstance(seq, int) else None, t=rec.get("t"),
                           structure=rec.get("structure_fit"))
    return state, source


def _latest_advice(records: list[dict]) -> dict | None:
    """The advice of the latest filter-error window that has one (applied or not): its time,
    record number and sentence (estimator.flight_advice.advice_summary, as the log and the
    report say it); None when no record carries advice."""
    from rsra.estimator.flight_advice import advice_summary

    for i in range(len(records) - 1, -1, -1):
        r = records[i]
        if isinstance(r.get("advice"), dict):
            t = r.get("t")
            return {"index": i + 1, "t": t if isinstance(t, (int, float)) else None,
                    "sentence": advice_summary(r["advice"], len(r.get("names") or []) or None)}
    return None


def _show(cfg: RigConfig, args: argparse.Namespace) -> int:
    from rsra.config.readfile import regular_file_problem
    from rsra.daq.cli.options import UsageError

    path = Path(args.state)
    problem = None if path.is_dir() or not path.exists() else regular_file_problem(path)
    if problem is not None:  # a FIFO would block the read, a device never end
        raise UsageError(f"{path}: {problem}; fix: give a posterior file or a recording")
    source = None
    if _is_recording(path):
        state, source = _from_recording(path)
    else:
        state = _load(args.state)
    d = describe(state, cfg)
    if source is not None:
        d["source"] = source
        d["version"] = None  # a recording's record: no file format, no rig fingerprint
    if args.json:
        print(json.dumps({"file": str(args.state), **d}, allow_nan=False))
        return 0
    from rich.table import Table

    from rsra.daq.cli.console import make_console

    console = make_console()
    smax = d["sigma_max_deg"]
    saved_rig = state.rig.get("name") if isinstance(state.rig, dict) else None
    title = f"Posterior {args.state} (rig {saved_rig or cfg.rig_name!r})"
    if source is not None:
        title = (f"Recording {args.state}: "
                 + (f"the last applied angles record ({source['index']} of {source['records']})"
                    if source["record"] == "last_applied" else
                    "no record applied: the starting posterior")
                 + f" (rig {cfg.rig_name!r})")
    t = Table(title=title)
    for col in ("parameter", "angle (deg)", "σ (deg)", "95 % range (deg)", f"σ ≤ {smax:g}°"):
        t.add_column(col, justify="left" if col == "parameter" else "right")
    for n, a, s, (lo, hi), ok in zip(d["names"], d["angles_deg"], d["sigma_deg"],
                                     d["range_deg"], d["determined_parameters"]):
        t.add_row(n, f"{a:+.4f}", f"{s:.4f}", f"{lo:+.3f} … {hi:+.3f}",
                  "[green]yes[/green]" if ok else "[yellow]no[/yellow]")
    console.print(t)
    console.print(f"range: angle ± 1.96 σ, where the true angle lies with 95 % probability (the "
                  f"posterior is Gaussian); every angle is held within ±{d['angle_limit_deg']:g}° "
                  "(identification.angle_limit_deg)", highlight=False)
    cond = "inf" if d["condition"] is None else f"{d['condition']:.3g}"
    applies = ("from the start" if d["applies_from_seq"] is None
               else f"from sample {d['applies_from_seq']}")
    console.print(f"determined directions: {d['determined']} of {d['parameters']} (posterior σ ≤ "
                  f"{smax:g}°); condition number {cond}; applies {applies}"
                  + ("" if d["t"] is None else f" (t = {d['t']:.6f} s)"), highlight=False)
    if d["reference_load"] is not None:
        ref = "  ".join(f"{a} {v / 1e3:.1f}" for a, v in zip("XYZLMN", d["reference_load"]))
        console.print(f"reference load (the known-load windows' mean; kN, kN·m): {ref}; a flight "
                      "at another load widens the posterior by "
                      "identification.angle_load_sensitivity_deg_per_unit", highlight=False)
    undet = d["undetermined_directions"]
    for k, u in enumerate(undet[:SHOW_DIRECTIONS], start=1):
        comb = " ".join(f"{w:+.2f}·{n}" for n, w in u["components"].items())
        console.print(f"  undetermined {k}: σ {u['sigma_deg']:.3f}° along {comb}",
                      highlight=False)
    if len(undet) > SHOW_DIRECTIONS:
        console.print(f"  … and {len(undet) - SHOW_DIRECTIONS} more (--json lists them all)",
                      highlight=False)
    _notes(console, d, source)
    return 0


def _notes(console: Any, d: dict, source: dict | None) -> None:
    """The lines under `show`'s table: a recording's latest advice, the records after the one
    shown, and what the service would say of the file."""
    adv = source.get("advice") if source is not None else None
    if adv is not None and adv["sentence"]:
        console.print(f"advice (record {adv['index']}, the latest filter-error window with "
                      f"advice): {adv['sentence']}", highlight=False)
    if source is not None and source["after"]:
        console.print(f"note: {source['after']} later record(s) not applied"
                      + ("; a later reset reopened the σ (the last record's P is the current "
                         "posterior)" if source["reset_after"] else ""), highlight=False)
    if d["rig_difference"] is not None:
        console.print(f"note: saved on another rig ({d['rig_difference']}): --angles refuses "
                      "it without --accept-rig-mismatch", highlight=False)
    elif d["version"] == 1 and source is None:
        console.print("note: format version 1, without a rig fingerprint", highlight=False)
    if not d["matches_config"]:
        console.print("note: the config identifies other parameters: the service would refuse "
                      "this file (reset it or check --config)", highlight=False)


def _reset(cfg: RigConfig, args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.runtime.persistence import save_posterior
    from rsra.daq.runtime.posterior_file import classify

    path = Path(args.state)
    state = prior_state(cfg)
    # the same rule as the service's identification.state_file: only a posterior of ours
    kind, old, problem = classify(path)
    if kind == "foreign" and path.is_dir():
        raise UsageError(f"{path} is a folder; give the posterior file")
    if kind == "foreign":
        raise UsageError(f"{path} {problem}; refusing to overwrite it: check the path, or "
                         "delete the file first")
    if kind == "posterior":
        assert old is not None  # classify: the posterior read
        was = (f"replaced a posterior of {len(old.names)} parameters with "
               f"{describe(old, cfg)['determined']} determined directions"
               if set(old.names) <= set(_configured_names(cfg)[1])
               else f"replaced a posterior of {len(old.names)} parameters")
    elif kind == "damaged":
        was = f"replaced a damaged posterior ({problem})"
    else:
        was = "created it"
    try:
        save_posterior(path, state)
    except OSError as e:
        raise UsageError(f"{path}: cannot write ({e.strerror or e})") from None
    init = np.degrees(state.theta)
    sig = np.degrees(np.sqrt(np.diag(state.P)))
    init_s, sig_s = (f"{v[0]:g}°" if np.all(v == v[0])
                     else "[" + ", ".join(f"{a:g}" for a in v) + "]°" for v in (init, sig))
    print(f"rsra angles reset: {path}: {len(state.names)} angles set to the configured prior "
          f"(initial {init_s}, σ {sig_s}, applying from the start); {was}")
    return 0
