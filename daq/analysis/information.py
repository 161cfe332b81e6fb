"""A recording's likelihood information and the posterior pooled across recordings
(docs/identification.md, "Pooling recordings"; docs/cli.md, ``rsra calibrate --posterior`` and
``rsra campaign calibrate``).

**The information product.** One recording's sufficient statistics of its known-load windows,
as a table (one row per identification window of ``identification.window_s`` on the sample grid
of the content-filtered data, :func:`rsra.daq.analysis.calibrate.load_known_load_data`):

==================  ==================  ==================================================
column              type                meaning
==================  ==================  ==================================================
``recording``       string              the recording's id (in a campaign dataset: the partition's,
                                        ``recording=<id>``; not a column of the file)
``rig_fingerprint`` string              the rig fingerprint (canonical JSON; posterior files)
``content``         string              the content filter (``static`` …)
``t_start``         float64             the recording's first sample, its own clock (s)
``window``          int32               the window's index in the recording
``first_sample``    int64               its first sample (index in the usable data)
``n_scored``        int64               scored samples in it
``sum``             list<float64>       Σ x over them (c values)
``moments``         list<float64>       Σ x xᵀ over them (c × c, row-major)
==================  ==================  ==================================================

with ``x = [z (6), T (cells), H (6), q (external loads)]`` — the column names in the schema
metadata ``rsra.information.columns`` (``rsra.information.version`` = 1). A recording without
usable known loads gives no rows (the reason in ``rsra.information.reason``).

**The pooled posterior** (:func:`pooled_posterior`): the windows' moments summed per recording,
re-solved by :func:`rsra.estimator.pooling.pool` with the configured prior counted once, the
rig's drift allowance between recordings, the reference load (the mean of the windows' static
loads) and, for a rig with a load-sensitivity bound, the load spread (``LoadSpread``) added to
the stated covariance — the same posterior the service would state, in the state-file format.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.analysis.calibrate import (
    CalibrationData,
    CalibrationError,
    KnownLoadCollector,
    load_known_load_data,
    prior_sigmas,
)
from rsra.daq.runtime.posterior_file import rig_of
from rsra.estimator.balance import static_estimate
from rsra.estimator.identification import Parameterisation
from rsra.estimator.load_spread import LoadSpread
from rsra.estimator.pooling import PooledResult, Recording, pool, window_statistics
from rsra.estimator.posterior import PosteriorState, ReferenceLoad

PRODUCT = "information"  # the campaign's product name: DIR/information/recording=<id>/
VERSION = 1  # of the table's schema
META_VERSION = b"rsra.information.version"
META_COLUMNS = b"rsra.information.columns"
META_REASON = b"rsra.information.reason"
SECONDS_PER_DAY = 86400.0


class PoolingError(ValueError):
    """Information that cannot be pooled (two rigs, another layout, nothing usable): one line."""


# ------------------------------------------------------------------------------------------
# The information product
# ------------------------------------------------------------------------------------------
def x_columns(cfg: RigConfig) -> list[str]:
    """Names of the stacked channels x of the moments (module doc)."""
    model = cfg.rig_model()
    axes = ("X", "Y", "Z", "L", "M", "N")
    return ([f"z_{a}" for a in axes] + [f"T_{c}" for c in model.geometry.cell_names]
            + [f"H_{a}" for a in axes] + [f"q_{n}" for n in model.external.names])


def fingerprint_text(cfg: RigConfig) -> str:
    """The rig fingerprint as canonical JSON (equal text ⇔ equal fingerprint, as written)."""
    return json.dumps(rig_of(cfg), sort_keys=True, separators=(",", ":"))


def schema(columns: Sequence[str] = (), reason: str | None = None):
    import pyarrow as pa

    meta = {META_VERSION: str(VERSION).encode(), META_COLUMNS: json.dumps(list(columns)).encode()}
    if reason:
        meta[META_REASON] = reason.encode()
    return pa.schema([
        ("recording", pa.string()), ("rig_fingerprint", pa.string()), ("content", pa.string()),
        ("t_start", pa.float64()), ("window", pa.int32()), ("first_sample", pa.int64()),
        ("n_scored", pa.int64()), ("sum", pa.list_(pa.float64())),
        ("moments", pa.list_(pa.float64())),
    ], metadata=meta)


def information_table(cfg: RigConfig, data: CalibrationData | None, recording: str,
                      reason: str | None = None):
    """The information rows of one recording's known-load data (module doc); ``data`` None:
    no rows, ``reason`` says why."""
    import pyarrow as pa

    cols = x_columns(cfg)
    if data is None:
        return schema(cols, reason).empty_table()
    x = np.hstack([data.z, data.T, data.H] + ([data.q] if data.q is not None else []))
    window = max(1, round(cfg.identification.window_s * data.fs))
    first, n, s1, s2 = window_statistics(x, data.scored, window)
    W = len(n)
    fp = fingerprint_text(cfg)
    return pa.table({
        "recording": [recording] * W, "rig_fingerprint": [fp] * W,
        "content": [data.content] * W, "t_start": [float(data.t_first)] * W,
        "window": np.arange(W, dtype=np.int32), "first_sample": first.astype(np.int64),
        "n_scored": n.astype(np.int64), "sum": [r.tolist() for r in s1],
        "moments": [r.reshape(-1).tolist() for r in s2],
    }, schema=schema(cols))


def recording_information(cfg: RigConfig, source: str | Path, recording: str | None = None,
                          content: str | None = None):
    """Read one recording (a log file or a recording folder) and return its information table;
    a recording without usable known loads gives no rows and the reason."""
    rid = recording or Path(source).name
    try:
        data = load_known_load_data(cfg, [source], content=content)
    except CalibrationError as e:
        return information_table(cfg, None, rid, str(e))
    return information_table(cfg, data, rid)


class InformationCollector:
    """One recording's information table built from the samples of a replay run for another
    product (a campaign task's telemetry replay): :meth:`observe` each sample in order, then
    :meth:`table`. The same table as :func:`recording_information` of the recording, which
    reads it on its own."""

    def __init__(self, cfg: RigConfig, recording: str, content: str | None = None):
        self.cfg, self.recording = cfg, recording
        self.reason: str | None = None
        self.collector: KnownLoadCollector | None = None
        try:
            self.collector = KnownLoadCollector(cfg, content)
        except CalibrationError as e:  # no balance on the rig: no rows, and why
            self.reason = str(e)
        else:
            self.collector.begin()

    def observe(self, sample: Any) -> None:
        if self.collector is not None:
            self.collector.add(sample)

    def table(self, source: str | Path):
        """The information table once the replay of ``source`` has ended (module doc)."""
        if self.collector is None:
            return information_table(self.cfg, None, self.recording, self.reason)
        self.collector.end()
        try:
            data = self.collector.data([source])
        except CalibrationError as e:
            return information_table(self.cfg, None, self.recording, str(e))
        return information_table(self.cfg, data, self.recording)


def information_product(source: str | Path, cfg: RigConfig, options: Mapping[str, Any],
                        staging_dir: str | Path) -> dict[str, Any]:
    """The campaign's ``information`` product of one recording: writes
    ``staging_dir/part.parquet`` (the campaign renames the folder into
    ``DIR/information/recording=<id>/``) and returns a small summary. ``options``:
    ``recording`` (the id; default the source's name), ``content`` (default the rig's
    ``identification.content_known_loads``)."""
    import pyarrow.parquet as pq

    table = recording_information(cfg, source, options.get("recording"), options.get("content"))
    out = Path(staging_dir) / "part.parquet"
    # in the dataset the recording id is the partition's (recording=<id>), not a column
    pq.write_table(table.drop_columns(["recording"]), out)
    meta = table.schema.metadata or {}
    return {"product": PRODUCT, "windows": table.num_rows,
            "scored": int(sum(table.column("n_scored").to_pylist())),
            "reason": meta.get(META_REASON, b"").decode() or None}


def read_information(files: Mapping[str, Sequence[str | Path]]):
    """The information tables of each recording (id → its Parquet files; in the dataset the
    id is the partition's), concatenated with the ``recording`` column; refuses a file of
    another layout version or other columns (one line). Returns (table, x columns)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    tables, columns = [], None
    for rid, p in ((r, p) for r, ps in files.items() for p in ps):
        try:
            t = pq.read_table(p)
        except (OSError, pa.ArrowException) as e:
            raise PoolingError(f"{p}: not a readable information table ({e})") from None
        if "recording" not in t.column_names:
            t = t.append_column("recording", pa.array([rid] * t.num_rows, pa.string()))
        meta = t.schema.metadata or {}
        if meta.get(META_VERSION) != str(VERSION).encode():
            raise PoolingError(f"{p}: information table version "
                               f"{meta.get(META_VERSION, b'?').decode()}, this rsra reads "
                               f"{VERSION}; rerun the campaign to rewrite it")
        cols = json.loads(meta.get(META_COLUMNS, b"[]"))
        if columns is not None and cols != columns and t.num_rows:
            raise PoolingError(f"{p}: its channels {cols} differ from {columns}: recordings "
                               "of two rigs cannot be pooled")
        if t.num_rows:
            columns = cols
        try:
            tables.append(t.select(schema().names).cast(schema()))
        except (KeyError, pa.ArrowException) as e:
            raise PoolingError(f"{p}: not an information table of version {VERSION} ({e})") from None
    if not tables:
        return schema(columns or []).empty_table(), columns or []
    return pa.concat_tables(tables), columns or []


# ------------------------------------------------------------------------------------------
# The pooled posterior
# ------------------------------------------------------------------------------------------
@dataclass
class PooledCalibration:
    """What :func:`pooled_posterior` found: the posterior to save, the pooling's result, the
    recordings (in the table's order) and their windows' static loads."""

    state: PosteriorState
    result: PooledResult
    recordings: list[Recording]
    windows: list[int]
    content: str

    @property
    def homogeneous(self) -> bool:
        return not self.result.homogeneity.reject

    def disagree(self) -> list[str]:
        order = self.result.order
        return [self.recordings[order[k]].name for k in self.result.homogeneity.disagree]

    def report(self) -> dict[str, Any]:
        """JSON-ready: the posterior, the homogeneity test, the trend (docs/cli.md)."""
        res, h = self.result, self.result.homogeneity
        names = list(self.state.names)
        deg = math.degrees(1.0)
        rows = []
        for j, k in enumerate(res.order):
            r = self.recordings[k]
            rows.append({
                "recording": r.name, "t_start": r.t if math.isfinite(r.t) else None,
                "windows": self.windows[k], "scored": r.n, "determined": h.determined[j],
                "sequential_chi2": None if j == 0 else h.sequential[j],
                "sequential_dof": h.sequential_dof[j],
                "leave_one_out_chi2": h.leave_one_out[j], "leave_one_out_p": h.leave_one_out_p[j],
                "disagrees": j in h.disagree,
                "estimate_deg": (h.estimates[j] * deg).tolist()})
        trend = None
        if h.trend is not None and h.trend_sigma is not None:
            trend = {"deg_per_day": (h.trend * deg * SECONDS_PER_DAY).tolist(),
                     "sigma_deg_per_day": (h.trend_sigma * deg * SECONDS_PER_DAY).tolist(),
                     "statistic": h.trend_statistic, "p_value": h.trend_p_value}
        sigma = np.sqrt(np.diag(self.state.P))
        return {
            "names": names, "content": self.content,
            "theta_deg": (self.state.theta * deg).tolist(), "sigma_deg": (sigma * deg).tolist(),
            "reference_load": None if self.state.reference_load is None
            else self.state.reference_load.tolist(),
            "status": res.ident.status, "iterations": res.ident.iterations,
            "drift_rate_rad2_s": res.drift_rate,
            "sigma_floor_deg": None if res.sigma_floor is None
            else (res.sigma_floor * deg).tolist(),
            "homogeneity": {"statistic": h.statistic, "dof": h.dof, "limit": h.limit,
                            "p_value": h.p_value, "false_alarm": 1e-3, "reject": h.reject,
                            "disagree": self.disagree()},
            "trend": trend, "recordings": rows,
        }


def summary_lines(rep: dict[str, Any]) -> list[str]:
    """The pooled posterior's report (:meth:`PooledCalibration.report`) in lines: the
    homogeneity test, each recording, the trend, the drift allowance and the σ."""
    h = rep["homogeneity"]
    skipped = rep.get("skipped") or []
    test = (f"homogeneity χ² {h['statistic']:.1f} on {h['dof']} dof (limit {h['limit']:.1f} at "
            f"1e-3, p {h['p_value']:.3g}): "
            + ("the recordings DISAGREE: " + ", ".join(h["disagree"]) if h["reject"]
               else "they agree") if h["dof"] else "no homogeneity test (one recording)")
    lines = [f"pooled over {len(rep['recordings'])} recording(s)"
             + (f" ({len(skipped)} without known loads skipped)" if skipped else "")
             + f": {test}"]
    for r in rep["recordings"]:
        seq = "—" if r["sequential_chi2"] is None else f"{r['sequential_chi2']:.1f}"
        lines.append(f"  {r['recording']}: {r['windows']} windows, {r['scored']} samples, "
                     f"{r['determined']} directions; χ² against the ones before {seq} on "
                     f"{r['sequential_dof']}, against the others {r['leave_one_out_chi2']:.1f} "
                     f"(p {r['leave_one_out_p']:.3g})" + ("  DISAGREES" if r["disagrees"] else ""))
    t = rep["trend"]
    if t is not None:
        ratio = [abs(v) / max(s, 1e-300) for v, s in zip(t["deg_per_day"], t["sigma_deg_per_day"])]
        k = int(np.argmax(ratio))
        lines.append(f"  drift trend in time order: χ² {t['statistic']:.1f} (p {t['p_value']:.3g});"
                     f" largest {rep['names'][k]} {t['deg_per_day'][k]:+.3g} ± "
                     f"{t['sigma_deg_per_day'][k]:.2g} °/day")
    if rep["sigma_floor_deg"] is not None:
        lines.append(f"  drift allowance {rep['drift_rate_rad2_s']:g} rad²/s between recordings: "
                     f"σ floor {min(rep['sigma_floor_deg']):.3g}–{max(rep['sigma_floor_deg']):.3g}°")
    else:
        lines.append("  angles taken as constant across the recordings (no drift allowance: "
                     + ("the rig states none)" if not rep["drift_rate_rad2_s"]
                        else "their start times do not differ)"))
    lines.append("  σ of the pooled angles: " + ", ".join(
        f"{n} {s:.3f}°" for n, s in zip(rep["names"], rep["sigma_deg"])))
    return lines


def recordings_of(table, columns: Sequence[str], cfg: RigConfig,
                  times: Mapping[str, float] | None = None) -> tuple[list[Recording], list[list[tuple[np.ndarray, int, np.ndarray]]], str]:
    """The recordings of an information table, each with its windows (G, n, Σx), and the
    content; refuses two rig fingerprints, another rig than ``cfg``'s, mixed content.
    ``times``: start times (s) that replace the tables' (a campaign manifest's ``t_start``)."""
    if not table.num_rows:
        raise PoolingError("no known-load information in the recordings (no rows): record with "
                           "the reference balance on the bus")
    fps = sorted(set(table.column("rig_fingerprint").to_pylist()))
    if len(fps) > 1:
        by: dict[str, str] = {}
        for rid, fp in zip(table.column("recording").to_pylist(),
                           table.column("rig_fingerprint").to_pylist()):
            by.setdefault(fp, rid)
        first = list(by.values())
        raise PoolingError(f"recordings of {len(fps)} rigs (different rig fingerprints, e.g. "
                           f"{first[0]} and {first[1]}); pool the recordings of one rig")
    if fps[0] != fingerprint_text(cfg) or list(columns) != x_columns(cfg):
        raise PoolingError("the recordings' rig fingerprint differs from the configured rig's; "
                           "give the rig they were recorded with (--config)")
    contents = sorted(set(table.column("content").to_pylist()))
    if len(contents) > 1:
        raise PoolingError(f"recordings of different content filters {contents}; rerun them "
                           "with one")
    c = len(columns)
    recs: dict[str, Recording] = {}
    wins: dict[str, list[tuple[np.ndarray, int, np.ndarray]]] = {}
    d = table.to_pydict()
    for rid, t0, n, s1, s2 in zip(d["recording"], d["t_start"], d["n_scored"], d["sum"],
                                 d["moments"]):
        G = np.asarray(s2, float).reshape(c, c)
        s = np.asarray(s1, float)
        if G.shape != (c, c) or s.shape != (c,) or not (np.all(np.isfinite(G))
                                                         and np.all(np.isfinite(s))):
            raise PoolingError(f"recording {rid}: malformed information row (shape or "
                               "non-finite numbers)")
        r = recs.setdefault(rid, Recording(rid, np.zeros((c, c)), 0,
                                           math.nan if t0 is None else float(t0)))
        r.G = r.G + G
        r.n += int(n)
        wins.setdefault(rid, []).append((G, int(n), s))
    names = list(recs)
    for k, v in (times or {}).items():
        if k in recs and v is not None and math.isfinite(v):
            recs[k].t = float(v)
    return [recs[k] for k in names], [wins[k] for k in names], contents[0]


def pooled_posterior(cfg: RigConfig, table, columns: Sequence[str], *,
                     alpha_start: np.ndarray | None = None,
                     prior_sigma_rad: float | None = None,
                     max_iterations: int | None = None,
                     times: Mapping[str, float] | None = None) -> PooledCalibration:
    """The pooled posterior of the 14 angles from an information table (module doc)."""
    recs, wins, content = recordings_of(table, columns, cfg, times)
    model = cfg.rig_model()
    idc = cfg.identification
    names = model.geometry.angle_names
    alpha0 = np.asarray(idc.initial_angles_rad if alpha_start is None else alpha_start, float)
    par = Parameterisation(model, names, alpha0, moment_floor=idc.moment_floor_Nm,
                           known_loads=True)
    start = par.initial()
    sig = idc.prior_sigma_rad if prior_sigma_rad is None else float(prior_sigma_rad)
    P_p = np.diag(prior_sigmas(names, start, cfg, sig) ** 2)
    res = pool(par, recs, start, P_p, drift_rate=float(idc.drift_rate_rad2_s),
               max_iterations=max_iterations or idc.max_iterations)
    if res.ident.status == "diverged" or not np.all(np.isfinite(res.P)):
        raise PoolingError("the pooled identification diverged; check the recordings and the "
                           "starting values (--angles)")
    # the reference load: the mean of the windows' static loads at the estimate (the service:
    # of its accepted known-load windows); the load spread about it where the rig bounds it
    nc = model.geometry.n_cells
    alpha = par.alpha(res.theta)
    loads = []
    for ws in wins:
        for G, n, s in ws:
            m = s / max(n, 1)
            q = m[12 + nc:][None, :] if len(m) > 12 + nc else None
            loads.append((G, n, static_estimate(model, alpha, m[6:6 + nc][None, :],
                                                m[:6][None, :], q)[0]))
    ref = ReferenceLoad()
    for _, _, L in loads:
        ref.note(L)
    sens = np.asarray(idc.angle_load_sensitivity_rad_per_unit, float)
    theta, P = res.theta.copy(), res.P.copy()
    if np.any(sens > 0):
        post = SimpleNamespace(theta=res.theta, P=res.P, P0=P_p, reference=ref)
        spread = LoadSpread(post, par, sens)
        spread.windows.extend(loads)
        spread.refresh()
        theta, P = ref.reported_theta(res.theta), ref.reported(res.P)
    state = PosteriorState(tuple(names), theta, 0.5 * (P + P.T), None, None,
                           rig_of(cfg), None, ref.load)
    return PooledCalibration(state, res, recs, [len(w) for w in wins], content)


def load_each(cfg: RigConfig, paths: Sequence[str | Path], *, content: str | None = None,
              progress=None) -> tuple[list[CalibrationData], CalibrationData]:
    """Each recording's known-load data read on its own (a recording is its own stretch, as in
    :func:`load_known_load_data` over them all), and their concatenation (the batch
    calibration of them together). CalibrationError names a recording without usable data."""
    parts = [load_known_load_data(cfg, [p], content=content, progress=progress) for p in paths]
    q = [d.q for d in parts]
    rejected: dict[str, int] = {}
    for d in parts:
        for k, v in d.rejected.items():
            rejected[k] = rejected.get(k, 0) + v
    whole = CalibrationData(
        z=np.vstack([d.z for d in parts]), T=np.vstack([d.T for d in parts]),
        H=np.vstack([d.H for d in parts]),
        q=None if any(x is None for x in q) else np.vstack(q),  # type: ignore[arg-type]
        valid=np.concatenate([d.valid for d in parts]),
        scored=np.concatenate([d.scored for d in parts]), content=parts[0].content,
        fs=parts[0].fs, files=tuple(f for d in parts for f in d.files),
        segments=sum(d.segments for d in parts),
        samples_read=sum(d.samples_read for d in parts), rejected=rejected,
        duration_s=sum(d.duration_s for d in parts), t_first=parts[0].t_first)
    return parts, whole
