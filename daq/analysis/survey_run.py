"""The loads survey of a recording as a whole: its rig's numbers, its replay through the
service, its test points from the recording folder (marks, a TOML, the transient flag's
edges), and the campaign's ``survey`` product. The simulator's schedule (the ``scenario``
source) needs the simulator, which only the command line imports: it comes in as a function
(``scenario_points``)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.analysis import survey as sv

POINT_SOURCES = ("auto", "marks", "scenario", "transient")
#: truth.npz of a simulated recording -> its schedule's test points on the samples' time
ScenarioPoints = Callable[[Path], list[sv.TestPoint]]


def survey_rig(cfg: RigConfig) -> sv.SurveyRig:
    """What the survey takes from the rig: the blade count, the filter's harmonics and time
    constant, the static noise bound, the angles' sensitivity and the moment rows' model
    error (all from the configuration)."""
    from functools import partial

    from rsra.estimator.angle_uncertainty import hub_angle_sensitivity
    from rsra.estimator.noise_budget import noise_budget

    model = cfg.rig_model()
    nb = noise_budget(model, cfg.identification.initial_angles_rad, cfg.hub_frame)
    return sv.SurveyRig(blades=int(cfg.rotor.blades), modelled=tuple(cfg.filter.harmonics),
                        dt=cfg.sample_period_s, time_constant_s=cfg.filter.time_constant_s,
                        bound=nb.total, angle_names=tuple(model.geometry.angle_names),
                        sensitivity=partial(hub_angle_sensitivity, model.geometry,
                                            frame=cfg.hub_frame),
                        model_sigma=sv.moment_model_sigma(cfg.identification.moment_floor_Nm))


def replay_data(cfg: RigConfig, logs: Sequence[str | Path], rig: sv.SurveyRig
                ) -> sv.SurveyData:
    """A recording replayed through the service (its recorded angle schedule), the records
    the survey needs collected."""
    from rsra.daq.bus.replay import ReplayError, check_readable, expand
    from rsra.daq.runtime.service import Service, ServiceOptions

    try:
        check_readable(expand([str(p) for p in logs]))
    except ReplayError as e:
        raise sv.SurveyError(str(e)) from None
    col = sv.RecordCollector(rig.angle_names)
    service = Service(cfg, ServiceOptions(replay=[str(p) for p in logs], zenoh=False))
    service.add_sink(col.add)
    service.run()
    return col.finish()


def recording_points(source: str, data: sv.SurveyData, folder: Path | None,
                     scenario_points: ScenarioPoints | None = None) -> list[sv.TestPoint]:
    """The test points of one recording: ``source`` a TOML file, or ``marks`` (the
    operator's, ``marks.jsonl`` in the folder), ``scenario`` (the simulator's schedule, from
    ``truth.npz``), ``transient`` (the held stretches between the flag's edges), or ``auto``
    (the first of these the recording has)."""
    t = data.t[np.isfinite(data.t)]
    if not len(t):
        return []
    if source not in POINT_SOURCES:
        return sv.filter_points(sv.points_from_toml(Path(source), float(t.min())), t)
    marks = folder / "marks.jsonl" if folder is not None else None
    if source in ("auto", "marks") and marks is not None and marks.is_file():
        return sv.filter_points(sv.points_from_marks(sv.read_marks(marks), float(t.max())), t)
    if source == "marks":
        raise sv.SurveyError(f"{folder}: no marks.jsonl (no `rsra mark` during the run); fix: "
                             "--test-points FILE.toml, scenario or transient")
    truth = folder / "truth.npz" if folder is not None else None
    if source in ("auto", "scenario") and truth is not None and truth.is_file() \
            and scenario_points is not None:
        pts = sv.filter_points(scenario_points(truth), t)
        if pts:
            return pts
    if source == "scenario":
        raise sv.SurveyError(f"{folder}: no simulator truth (truth.npz) with a scenario; fix: "
                             "--test-points FILE.toml, marks or transient")
    return sv.points_from_transient(data.t, data.transient)


def folder_of(source: Path) -> Path:
    return source if source.is_dir() else source.parent


def survey_collector(cfg: RigConfig) -> sv.RecordCollector:
    """What the campaign's ``survey`` product hands the telemetry replay as a record sink."""
    return sv.RecordCollector(survey_rig(cfg).angle_names)


def campaign_survey(cfg: RigConfig, source: Path, options: dict[str, Any],
                    collector: sv.RecordCollector):
    """The campaign's ``survey`` product of one recording: ``data`` (its replay's records,
    :func:`survey_collector`) surveyed at its own test points (marks, else the transient
    flag's edges: a campaign task does not run the simulator), as a table of the long
    table's columns less ``recording`` (the dataset's partition names it); no rows (and the
    reason) for a recording without hub loads or test points. ``options``: ``survey_draws``
    (the Monte Carlo draws, default 50)."""
    columns = [c for c in sv.COLUMNS if c != "recording"]
    rig = survey_rig(cfg)
    try:
        data = collector.finish()
        points = recording_points("auto", data, folder_of(source))
    except sv.SurveyError as e:
        return sv.table_of([], columns), " ".join(str(e).split())
    opts = sv.SurveyOptions(draws=int(options.get("survey_draws") or 50))
    rows = sv.survey(data, points, rig, opts)
    return sv.table_of(rows, columns), None if points else "no test point in the recording"
