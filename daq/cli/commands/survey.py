"""`rsra survey`: the loads survey of a recording or a results JSONL (docs/cli.md, docs/
user-guide.md "Loads survey"; daq/analysis/survey.py, estimator/survey.py)."""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from rsra.daq.analysis.survey import SURVEY_FILES
from rsra.daq.analysis.survey_run import POINT_SOURCES
from rsra.daq.cli.options import positive_float

OUTPUTS = {"out": SURVEY_FILES}  # checked against the inputs before any work (daq.cli.outputs)
INPUTS = ("test_points_file",)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(
        name, help="loads survey: per test point, steady/alternating loads, harmonics, peaks, "
        "fatigue cycles, each with 1σ",
        description="Per test point and hub-load axis (X Y Z L M N): mean, std, min, max, "
        "alternating (mean over whole revolutions of half the peak-to-peak, on the measured "
        "azimuth) and alternating_max, harmonic amplitude and phase 1/rev … N_b/rev by least "
        "squares on the measured azimuth, rainflow cycle counts and damage-equivalent loads, "
        "each with its 1σ from the published σ of the hub loads and the angles' covariance. "
        "Writes DIR/survey.parquet, survey.csv (columns test_point, t_start, t_end, axis, "
        "quantity, value, sigma, unit, estimate, note), survey.md and two PNG charts.")
    common_options(p)
    p.add_argument("logs", nargs="+", metavar="RECORDING|RESULTS.jsonl|DATASET",
                   help="a recording folder (or recording files), replayed with its recorded "
                   "angle schedule; the JSONL written by `rsra replay --out`; or a Parquet "
                   "dataset (a campaign's <key>/recording=<id>/, or `rsra export --parquet`)")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="folder for survey.parquet, survey.csv, survey.md and the PNG charts "
                   "(created if missing)")
    p.add_argument("--test-points", metavar="FILE|SOURCE", default="auto",
                   help="a TOML of [[test_point]] name/start/end (s, the samples' own time; "
                   "time = \"from_start\" counts from the first sample), or where to find them "
                   "in the recording: marks (the operator's, marks.jsonl), scenario (the "
                   "simulator's conditions and manoeuvres, from truth.npz), transient (the "
                   "held stretches between the transient flag's edges); default auto: marks, "
                   "else scenario, else transient")
    p.add_argument("--sn-slopes", metavar="M[,M…]", default="4,10", type=_slopes,
                   help="S-N curve slopes for the damage-equivalent loads del_m<M> (default 4,10)")
    p.add_argument("--del-cycles", metavar="N", type=positive_float, default=None,
                   help="reference cycle count of the DELs (default: one per second of the "
                   "test point, the 1 Hz equivalent load)")
    p.add_argument("--limit", metavar="AXIS=VALUE", action="append", default=[], type=_limit,
                   help="the limit of an axis (X Y Z L M N), in the --units, repeatable, instead of "
                   "the rig file's [limits]: peak_fraction_of_limit, the largest |load| over "
                   "the limit, with its σ")
    p.add_argument("--draws", metavar="N", type=_draws, default=50,
                   help="Monte Carlo draws for the σ of the rainflow counts and DELs (default 50)")
    return p


def _slopes(text: str) -> tuple[float, ...]:
    try:
        out = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of numbers (e.g. 4,10)") \
            from None
    if not out or not all(0 < m < 100 for m in out):
        raise argparse.ArgumentTypeError("each slope must be > 0 and < 100")
    return out


def _limit(text: str) -> tuple[str, float]:
    axis, _, value = text.partition("=")
    if axis not in ("X", "Y", "Z", "L", "M", "N"):
        raise argparse.ArgumentTypeError(f"'{text}': give AXIS=VALUE with AXIS one of X Y Z L "
                                         "M N, e.g. M=20000")
    return axis, positive_float(value)


def _limits(given: list[tuple[str, float]], units: str,
            rig: tuple[float, ...] = (math.nan,) * 6) -> tuple[float, ...]:
    """Per axis the limit in SI (NaN: none): the rig's ``[limits]``, an axis given with
    ``--limit`` (in the ``--units``) instead."""
    from rsra.config.units import to_units

    raw = np.full(6, np.nan)
    for axis, value in given:
        raw["XYZLMN".index(axis)] = value
    si = raw / to_units(np.ones(6), units)
    return tuple(float(v) if math.isfinite(v) else float(r) for v, r in zip(si, rig))


def _draws(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if not 2 <= v <= 10_000:
        raise argparse.ArgumentTypeError("must be between 2 and 10000")
    return v


def run(args: argparse.Namespace) -> int:
    from rsra.daq.analysis import survey as sv
    from rsra.daq.cli.options import UsageError

    try:
        return _run(args, sv)
    except sv.SurveyError as e:
        raise UsageError(str(e)) from None


def _run(args: argparse.Namespace, sv) -> int:
    from rsra.daq.analysis import survey_run as sr
    from rsra.daq.bus.replay import config_for

    inputs = [Path(p) for p in args.logs]
    for p in inputs:
        if not p.exists():
            raise sv.SurveyError(f"{p}: no such file or folder; fix: give a recording folder "
                                 "or a results JSONL")
    if args.test_points not in POINT_SOURCES:  # a bad file refused before any work
        sv.points_from_toml(Path(args.test_points), 0.0)
    opts = sv.SurveyOptions(slopes=args.sn_slopes, reference_cycles=args.del_cycles,
                            draws=args.draws, units=args.units,
                            limits=_limits(args.limit, args.units))
    if len(inputs) == 1 and sv.is_dataset(inputs[0]):
        cfg = config_for([], args.config)
        rig = sr.survey_rig(cfg)
        opts = dataclasses.replace(opts, limits=_limits(args.limit, args.units,
                                                        cfg.limits.per_axis()))
        rows, points = _survey_dataset(args, sv, inputs[0], rig, opts)
    else:
        results = len(inputs) == 1 and inputs[0].is_file() and inputs[0].suffix == ".jsonl"
        cfg = config_for([] if results else args.logs, args.config)
        rig = sr.survey_rig(cfg)
        opts = dataclasses.replace(opts, limits=_limits(args.limit, args.units,
                                                        cfg.limits.per_axis()))
        data = (sv.load_results(inputs[0], rig.angle_names) if results
                else sr.replay_data(cfg, args.logs, rig))
        folder = sr.folder_of(inputs[0])
        points = sr.recording_points(args.test_points, data, folder, _scenario_points)
        if not points:
            raise sv.SurveyError(f"{args.logs[0]}: no test point found ({args.test_points}); "
                                 "fix: give --test-points FILE.toml with [[test_point]] tables")
        rows = sv.survey(data, points, rig, opts, recording=folder.name if not results
                         else inputs[0].stem)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)  # only now: a refused input leaves no folder
    sv.write_outputs(rows, points, rig, opts, out, str(args.logs[0]))
    print(f"survey: {len(points)} test points, {len(rows)} rows -> {out}/survey.parquet, "
          "survey.csv, survey.md, survey_harmonics.png, survey_loads.png")
    if len(inputs) == 1 and sv.is_dataset(inputs[0]):
        subs = sv.write_recording_reports(rows, points, rig, opts, out)
        print(f"survey: a report per recording in {out}/recordings/ ({len(subs)})")
    return 0


def _survey_dataset(args, sv, path: Path, rig, opts):
    """Every recording of a Parquet dataset (a campaign's, or one `rsra export --parquet`),
    its test points named ``<recording>: <name>``; a campaign's manifest names each
    recording's folder, where its marks and the simulator's truth are."""
    from dataclasses import replace

    from rsra.daq.analysis import survey_run as sr

    sources = sv.dataset_sources(path)
    rows, points = [], []
    for rid, data in sv.load_dataset(path, rig.angle_names).items():
        src = sources.get(rid)
        if src is None and args.test_points in ("marks", "scenario"):
            raise sv.SurveyError(f"{path}: recording {rid} has no source folder in a campaign "
                                 f"manifest, so no {args.test_points}; fix: --test-points "
                                 "FILE.toml or transient")
        pts = sr.recording_points(args.test_points, data,
                                  None if src is None else sr.folder_of(src), _scenario_points)
        pts = [replace(tp, name=f"{rid}: {tp.name}") for tp in pts]
        rows += sv.survey(data, pts, rig, opts, recording=rid)
        points += pts
    if not points:
        raise sv.SurveyError(f"{path}: no test point in any recording ({args.test_points}); "
                             "fix: give --test-points FILE.toml with [[test_point]] tables")
    return rows, points


def _scenario_points(truth_path: Path):
    """The simulator's conditions and manoeuvres (daq.analysis.survey.points_from_schedule)
    on the samples' time base (the truth's SYNC times); [] without a usable scenario."""
    from rsra.daq.analysis.survey import points_from_schedule
    from rsra.sim_bus.scenarios import load_scenario
    from rsra.sim_bus.truth import read_truth

    try:
        tr = read_truth(truth_path)
        meta = tr["meta"]
        sc = load_scenario(meta["scenario"], **(meta.get("variants") or {}))
    except Exception:  # noqa: BLE001 - no usable scenario: the next source is tried
        return []
    ts = np.asarray(tr["t"], float)
    return points_from_schedule(sc, ts, np.asarray(tr.get("sync_time", ts), float))
