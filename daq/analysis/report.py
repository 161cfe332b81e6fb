"""Plots and a summary from published records (JSONL) and, where it exists, the simulator's
truth (docs/cli.md §7 `rsra report`; docs/telemetry.md §2 payloads; model.md §4, §6, §7).

* load: one JSON object per line, ``{"key": "<key>", …payload}`` (``rsra replay --out``, the
  service's JSONL sink); keys ``hub_loads``, ``channels``, ``angles``, ``innovations``,
  ``health``; others are counted and ignored;
* align: truth samples to records by time (the truth's SYNC time, else its simulated time;
  nearest within half a sample: in lock-step runs the records' ``t`` is simulated time), and
  by sample number (``seq``, with the SYNC counter fixing an offset) when times do not match;
* compute: hub-load errors against the static bound of model §4 (the noise budget σ), the
  final angles against their Cramér–Rao σ (and jointly, χ² with the posterior covariance),
  the normalised innovations against χ²₆, counts of flags;
* plot (matplotlib, Agg): hub loads vs truth, their errors, angles with ±σ_CR bands and
  accepted/rejected runs (the report's Figures 20–23, with honest bounds), NIS, spectra.
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from scipy import signal, stats

from rsra.config.rig import RigConfig
from rsra.daq.jsonlines import json_lines
from rsra.daq.jsonout import dumps
from rsra.daq.runtime.persistence import save_figure, write_text_atomic
from rsra.config.units import axis_units, to_units
from rsra.estimator.geometry import shaft_rotation
from rsra.estimator.noise_budget import AXES, noise_budget

FALSE_ALARM = 1e-3  # two-sided bands and consistency thresholds (team standard)
MIN_UNIFORM_FRACTION = 0.8  # spectra need at least this share of the samples present
FIG_SIZE = (12, 8)  # inches at 100 dpi: 1200 x 800 px
DPI = 100
ZOOM_REVOLUTIONS = 8  # hub_loads.png shows the last few rotor revolutions, readable waveforms


class ReportError(ValueError):
    """An input that cannot be reported on (missing file, not JSON lines, bad truth)."""


# ---------------------------------------------------------------------------------------------
# records


@dataclass
class Records:
    path: Path
    counts: dict[str, int]
    channels: dict[str, np.ndarray] | None = None  # seq, t, T (N,7), omega
    hub: dict | None = None  # seq, sync, t, H (N,6), H_static (N,6), omega, flags, frame
    angles: list[dict] = field(default_factory=list)
    innovations: dict[str, np.ndarray] | None = None  # seq, t, e (N,6), nis
    health: list[dict] = field(default_factory=list)
    initial_angles: dict | None = None  # the run's starting state, where the results carry it


def _vec(x, n: int) -> list[float]:
    """A payload vector (null or with nulls) as n floats, nan for missing."""
    if x is None:
        return [math.nan] * n
    return [math.nan if v is None else float(v) for v in x]


def _num(x) -> float:
    return math.nan if x is None else float(x)


def load_records(path: str | Path) -> Records:
    """Parse a JSONL of published records; ReportError names the line of a broken one."""
    p = Path(path)
    if not p.is_file():
        raise ReportError(f"{p}: no such file; give the JSONL written by `rsra replay --out` "
                          "or `rsra run`")
    counts: dict[str, int] = {}
    ch: dict[str, list] = {"seq": [], "t": [], "T": [], "omega": []}
    hub: dict[str, list] = {"seq": [], "sync": [], "t": [], "H": [], "H_static": [],
                            "omega": [], "flags": [], "sigma_angles": [], "sigma_filter": []}
    inn: dict[str, list] = {"seq": [], "t": [], "e": [], "nis": []}
    frames: set[str] = set()
    angles: list[dict] = []
    health: list[dict] = []
    initial: dict | None = None

    def bad(n: int, why: str) -> NoReturn:
        raise ReportError(f"{p} line {n}: not a JSON record with a \"key\" field ({why}); "
                          "give the JSONL written by `rsra replay --out`")

    try:
        for n, rec in json_lines(p, bad):
            if not isinstance(rec, dict) or not isinstance(rec.get("key"), str):
                bad(n, "no \"key\" naming it")
            key = rec["key"]
            counts[key] = counts.get(key, 0) + 1
            try:
                if key == "channels":
                    ch["seq"].append(int(rec["seq"]))
                    ch["t"].append(_num(rec["t"]))
                    ch["T"].append(_vec(rec["T"], 7))
                    ch["omega"].append(_num(rec.get("omega")))
                elif key == "hub_loads":
                    hub["seq"].append(int(rec["seq"]))
                    hub["sync"].append(int(rec.get("sync") or 0))
                    hub["t"].append(_num(rec["t"]))
                    hub["H"].append(_vec(rec.get("H"), 6))
                    hub["H_static"].append(_vec(rec.get("H_static"), 6))
                    hub["omega"].append(_num(rec.get("omega")))
                    hub["flags"].append(tuple(rec.get("flags") or ()))
                    # the σ the record publishes (NaN: absent, an older recording)
                    hub["sigma_angles"].append(_vec(rec.get("sigma_angles"), 6))
                    hub["sigma_filter"].append(_vec(rec.get("sigma_filter"), 6))
                    frames.add(rec.get("frame") or "body")
                elif key == "innovations":
                    inn["seq"].append(int(rec["seq"]))
                    inn["t"].append(_num(rec["t"]))
                    inn["e"].append(_vec(rec.get("e"), 6))
                    inn["nis"].append(_num(rec.get("nis")))
                elif key == "angles":
                    if not rec.get("initial"):
                        angles.append(rec)
                    elif initial is None:
                        initial = rec
                elif key == "health":
                    health.append(rec)
            except (KeyError, TypeError, ValueError) as e:
                raise ReportError(f"{p} line {n}: a {key!r} record without a valid {e} field "
                                  "(docs/telemetry.md §2 payload)") from None
    except OSError as e:
        raise ReportError(f"{p}: cannot read ({e.strerror})") from None
    if not counts:
        raise ReportError(f"{p}: no records (empty file)")
    if len(frames) > 1:
        raise ReportError(f"{p}: hub_loads records in more than one frame ({sorted(frames)})")
    out = Records(path=p, counts=counts, angles=angles, health=health, initial_angles=initial)
    if ch["seq"]:
        out.channels = {"seq": np.array(ch["seq"], np.int64), "t": np.array(ch["t"]),
                        "T": np.array(ch["T"], float).reshape(-1, 7),
                        "omega": np.array(ch["omega"])}
    if hub["seq"]:
        out.hub = {"seq": np.array(hub["seq"], np.int64), "sync": np.array(hub["sync"], np.int64),
                   "t": np.array(hub["t"]), "H": np.array(hub["H"], float).reshape(-1, 6),
                   "H_static": np.array(hub["H_static"], float).reshape(-1, 6),
                   "omega": np.array(hub["omega"]), "flags": hub["flags"],
                   "sigma_angles": np.array(hub["sigma_angles"], float).reshape(-1, 6),
                   "sigma_filter": np.array(hub["sigma_filter"], float).reshape(-1, 6),
                   "frame": frames.pop() if frames else "body"}
    if inn["seq"]:
        out.innovations = {"seq": np.array(inn["seq"], np.int64), "t": np.array(inn["t"]),
                           "e": np.array(inn["e"], float).reshape(-1, 6),
                           "nis": np.array(inn["nis"])}
    return out


# ---------------------------------------------------------------------------------------------
# truth and alignment


def load_truth(path: str | Path, read_truth: Callable[[Path], dict]) -> dict:
    """The simulator's truth file, read by ``read_truth`` (``rsra.sim_bus.truth.read_truth``,
    given by the command line: the report does not import the simulator), checked."""
    p = Path(path)
    if not p.is_file():
        raise ReportError(f"--truth {p}: no such file; give the .npz written by `rsra sim "
                          "--truth`")
    try:
        tr = read_truth(p)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the user's input problem
        raise ReportError(f"--truth {p}: not a truth file ({e})") from None
    for k in ("t", "H_true", "alpha_true"):
        if k not in tr:
            raise ReportError(f"--truth {p}: the truth file has no {k!r} array")
    return tr


@dataclass
class Alignment:
    """For every record of a set: the truth sample index (−1: none)."""

    method: str  # "sync_time", "t", "seq" or "none"
    idx: np.ndarray
    matched: float  # fraction of records matched

    def valid(self) -> np.ndarray:
        return self.idx >= 0


def _nearest(tt: np.ndarray, t: np.ndarray, tol: float) -> np.ndarray:
    order = np.argsort(tt, kind="stable")
    ts = tt[order]
    j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1) if len(ts) > 1 else np.zeros(len(t), int)
    if len(ts) > 1:
        left = np.abs(t - ts[j - 1]) <= np.abs(ts[j] - t)
        j = np.where(left, j - 1, j)
    idx = order[j]
    ok = np.abs(tt[idx] - t) <= tol
    return np.where(ok & np.isfinite(t), idx, -1)


def _align_by_time(truth: dict, t: np.ndarray, dt: float, method: str | None
                   ) -> Alignment | None:
    """By the truth's SYNC time, else its simulated time (nearest within half a sample),
    when at least 90 % of the records match (or ``method`` forces it); else None."""
    if method in ("sync_time", "t"):
        cands = [method]
    elif method is None:
        cands = [m for m in ("sync_time", "t") if m in truth]
    else:
        cands = []
    for m in cands:
        tt = np.asarray(truth[m], float)
        if len(tt) == 0 or not np.isfinite(tt).any():
            continue
        idx = _nearest(tt, t, 0.5 * dt)
        frac = float(np.mean(idx >= 0)) if len(idx) else 0.0
        if frac >= 0.9 or method is not None:
            return Alignment(m, idx, frac)
    return None


def _sync_offset(truth: dict, seq: np.ndarray, sync: np.ndarray | None) -> int:
    """The shift of ``seq`` that makes the most SYNC counters agree with the truth's (0
    without counters)."""
    sc = truth.get("sync_counter")
    if sync is None or sc is None or not len(sc) or not np.any(np.asarray(sync) > 0):
        return 0
    n = len(truth["t"])
    sync = np.asarray(sync, np.int64)
    sc = np.asarray(sc, np.int64)
    period = int(sc.max()) if sc.max() > 0 else 1
    best, offset = -1, 0
    for k in range(-int(seq.min()), -int(seq.min()) + period):
        j = seq + k
        ok = (j >= 0) & (j < n)
        score = int(np.sum(sc[j[ok]] == sync[ok]))
        if score > best:
            best, offset = score, k
    return offset


def align_truth(truth: dict, t: np.ndarray, seq: np.ndarray, dt: float,
                sync: np.ndarray | None = None, method: str | None = None) -> Alignment:
    """Truth sample of each record: by time (the truth's SYNC time, else its simulated time;
    nearest within half a sample) when at least 90 % of the records match; otherwise by
    ``seq`` (lost samples keep their number), shifted so that the SYNC counters agree when the
    records carry them. ``method`` forces one."""
    t = np.asarray(t, float)
    seq = np.asarray(seq, np.int64)
    by_time = _align_by_time(truth, t, dt, method)
    if by_time is not None:
        return by_time
    n = len(truth["t"])
    j = seq + _sync_offset(truth, seq, sync)
    idx = np.where((j >= 0) & (j < n), j, -1)
    return Alignment("seq", idx, float(np.mean(idx >= 0)) if len(idx) else 0.0)


def truth_in_frame(H_body: np.ndarray, geometry, frame: str) -> np.ndarray:
    """Truth hub loads (body axes) expressed in the records' frame: C_sᵀ on force and moment
    (the hub centre is the same point in both)."""
    C = shaft_rotation(geometry, frame)
    H = np.asarray(H_body, float)
    return np.hstack([H[:, :3] @ C, H[:, 3:] @ C])  # rows: (Cᵀ h)ᵀ = hᵀ C


# ---------------------------------------------------------------------------------------------
# computations


def _uniform(seq: np.ndarray, values: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Values on the complete seq grid with gaps and non-finite entries interpolated, and the
    fraction of grid samples that were present; None when a column has no finite value."""
    seq = np.asarray(seq, np.int64)
    order = np.argsort(seq, kind="stable")
    seq, values = seq[order], np.asarray(values, float)[order]
    keep = np.r_[True, np.diff(seq) > 0]
    seq, values = seq[keep], values[keep]
    n = int(seq[-1] - seq[0] + 1)
    grid = np.full((n, values.shape[1]), np.nan)
    grid[seq - seq[0]] = values
    present = np.isfinite(grid).all(axis=1)
    x = np.arange(n)
    for j in range(grid.shape[1]):
        ok = np.isfinite(grid[:, j])
        if not ok.any():
            return None, 0.0
        grid[:, j] = np.interp(x, x[ok], grid[ok, j])
    return grid, float(present.mean())


def _chi2_band(dof: int) -> tuple[float, float]:
    return (float(stats.chi2.ppf(FALSE_ALARM / 2, dof)),
            float(stats.chi2.ppf(1 - FALSE_ALARM / 2, dof)))


@dataclass
class ReportData:
    """Everything the plots and the summary need, computed once."""

    cfg: RigConfig
    rec: Records
    truth: dict | None
    units: str
    t0: float
    frame: str
    sigma_static: np.ndarray  # (6,) SI, in the records' frame
    angle_names: tuple[str, ...]
    alpha_config: np.ndarray
    hub_align: Alignment | None = None
    H_truth: np.ndarray | None = None  # (N_hub, 6) truth at the hub records, frame, nan if none
    ch_align: Alignment | None = None
    alpha_truth_hub: np.ndarray | None = None  # (N_hub or N_ch, 14) truth angles at records
    alpha_truth_t: np.ndarray | None = None  # their times (relative)
    omega: float | None = None
    settle_s: float = 0.0  # load-filter settling: not scored (model §7: 5 τ)
    skipped: dict[str, str] = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def _truth_hub(d: ReportData, truth: dict, geometry) -> Alignment | None:
    """The truth's hub loads at each hub_loads record, in the records' frame."""
    rec = d.rec
    if rec.hub is None:
        return None
    d.hub_align = al = align_truth(truth, rec.hub["t"], rec.hub["seq"], d.cfg.sample_period_s,
                                   rec.hub["sync"])
    ok = al.valid()
    H = np.full((len(ok), 6), np.nan)
    H[ok] = truth_in_frame(np.asarray(truth["H_true"])[al.idx[ok]], geometry, d.frame)
    d.H_truth = H
    return al


def _truth_angles(d: ReportData, truth: dict, hub_al: Alignment | None) -> None:
    """The truth's angles at each hub_loads record (else each channels record)."""
    rec = d.rec
    base = rec.hub if rec.hub is not None else rec.channels
    if base is None:
        return
    al = hub_al if hub_al is not None else align_truth(
        truth, base["t"], base["seq"], d.cfg.sample_period_s)
    d.ch_align = al
    ok = al.valid()
    A = np.full((len(ok), np.asarray(truth["alpha_true"]).shape[1]), np.nan)
    A[ok] = np.asarray(truth["alpha_true"])[al.idx[ok]]
    d.alpha_truth_hub = A
    d.alpha_truth_t = base["t"] - d.t0


def prepare(cfg: RigConfig, rec: Records, truth: dict | None, units: str = "si") -> ReportData:
    model = cfg.rig_model()
    frame = rec.hub["frame"] if rec.hub else cfg.hub_frame
    alpha_cfg = np.asarray(cfg.identification.initial_angles_rad, float)
    nb = noise_budget(model, alpha_cfg, frame)
    starts = [s["t"][np.isfinite(s["t"])].min() for s in (rec.hub, rec.channels, rec.innovations)
              if s is not None and np.isfinite(s["t"]).any()]
    t0 = min(starts) if starts else 0.0
    d = ReportData(cfg=cfg, rec=rec, truth=truth, units=units, t0=t0, frame=frame,
                   sigma_static=nb.total, angle_names=tuple(model.geometry.angle_names),
                   alpha_config=alpha_cfg,
                   settle_s=cfg.identification.settle_time_constants * cfg.filter.time_constant_s)
    om = [float(np.nanmedian(s["omega"])) for s in (rec.hub, rec.channels)
          if s is not None and np.isfinite(s["omega"]).any()]
    d.omega = om[0] if om else (None if cfg.rotor.stopped else cfg.rotor.omega_nominal_rad_s)
    if truth is not None:
        _truth_angles(d, truth, _truth_hub(d, truth, model.geometry))
    return d


def _hub_summary(d: ReportData) -> dict:
    rec = d.rec
    if rec.hub is None:
        return {"skipped": "no hub_loads records"}
    H, Hs = rec.hub["H"], rec.hub["H_static"]
    out: dict = {"frame": d.frame, "axes": list(AXES), "records": int(len(H)),
                 "sigma_static": to_units(d.sigma_static, d.units).tolist(),
                 "H_null": int(np.sum(~np.isfinite(H).all(axis=1))),
                 "H_static_null": int(np.sum(~np.isfinite(Hs).all(axis=1)))}
    if d.H_truth is None:
        out["truth"] = None
        return out
    settle = d.settle_s
    t = rec.hub["t"] - d.t0
    scored = np.isfinite(d.H_truth).all(axis=1)
    res: dict[str, dict[str, Any] | None] = {}
    for name, est, mask in (("H", H, scored & (t >= settle)), ("H_static", Hs, scored)):
        good = mask & np.isfinite(est).all(axis=1)
        if not good.any():
            res[name] = None
            continue
        err = est[good] - d.H_truth[good]
        rms = np.sqrt(np.mean(err**2, axis=0))
        res[name] = {"samples": int(good.sum()),
                     "rms_error": to_units(rms, d.units).tolist(),
                     "bias": to_units(err.mean(axis=0), d.units).tolist(),
                     "rms_over_sigma_static": (rms / d.sigma_static).tolist()}
    assert d.hub_align is not None  # prepare() made it with H_truth
    out.update(truth={"alignment": d.hub_align.method, "matched": d.hub_align.matched},
               settle_s=settle, errors=res)
    out["by_phase"] = _hub_by_phase(d)
    return out


def calibrated_from_seq(angles: list[dict]) -> int | None:
    """The sample the first accepted calibration applies from (None: none accepted)."""
    seqs = [int(a["applies_from_seq"]) for a in angles
            if a.get("accepted") and isinstance(a.get("applies_from_seq"), int)]
    return min(seqs) if seqs else None


def calibrated_from(d: ReportData) -> int | None:
    """The first sample of the calibrated state: the first accepted calibration's, or the
    run's first sample when it started from calibrated angles (daq.analysis.accuracy)."""
    from rsra.daq.analysis.accuracy import starts_calibrated

    hub = d.rec.hub
    if hub is not None and len(hub["seq"]) and starts_calibrated(
            hub["flags"][int(np.argmin(hub["seq"]))]):
        return int(np.min(hub["seq"]))  # a saved posterior: no start phase
    return calibrated_from_seq(d.rec.angles)


def record_phases(d: ReportData, seq: np.ndarray) -> np.ndarray:
    """The phase (daq.analysis.accuracy) of each record by its sample number: ``start``
    before the first accepted calibration, then ``transient`` where the hub_loads record at
    that sample is flagged, else ``steady``."""
    from rsra.daq.analysis.accuracy import TRANSIENT_FLAG

    hub = d.rec.hub
    cal = calibrated_from(d)
    moving = ({int(q) for q, f in zip(hub["seq"], hub["flags"]) if TRANSIENT_FLAG in f}
              if hub is not None else set())
    seq = np.asarray(seq, np.int64)
    tr = np.fromiter((int(q) in moving for q in seq), bool, len(seq))
    started = np.zeros(len(seq), bool) if cal is None else seq >= cal
    return np.where(~started, "start", np.where(tr, "transient", "steady"))


def _hub_by_phase(d: ReportData) -> dict:
    """H and H_static against truth per phase, each sample against the σ its record published
    (daq.analysis.accuracy)."""
    from rsra.daq.analysis.accuracy import MEANING, PhaseAccuracy

    hub = d.rec.hub
    assert hub is not None  # _hub_summary: with hub_loads records only
    phases = record_phases(d, hub["seq"])
    sa2 = np.nan_to_num(hub["sigma_angles"], nan=0.0) ** 2
    sf = hub["sigma_filter"]
    bound = d.sigma_static[None, :]
    sig = {"H": np.sqrt(sa2 + np.where(np.isfinite(sf), sf, bound) ** 2),
           "H_static": np.sqrt(sa2 + bound ** 2)}
    scale = to_units(np.ones(6), d.units)
    out: dict = {"meaning": dict(MEANING),
                 "calibrated_from_seq": calibrated_from(d),
                 "sigma": ("published: sqrt(sigma_angles² + sigma_filter²) for H"
                           if np.isfinite(sf).any() else
                           "published: sqrt(sigma_angles² + static bound²) for H")
                 + "; sqrt(sigma_angles² + static bound²) for H_static"}
    settling = hub["t"] - d.t0 < d.settle_s  # the filter's own start (from a zero state)
    out["settle_s"] = d.settle_s
    for name in ("H", "H_static"):
        acc = PhaseAccuracy()
        err = hub[name] - d.H_truth
        if name == "H":  # H scored after the filter has settled, as above
            err = np.where(settling[:, None], np.nan, err)
        acc.add_many(phases, err, sig[name])
        out[name] = acc.summary(scale)
    return out


def _angle_records(d: ReportData) -> list[dict]:
    """Angle records as arrays over the 14 angles (nan for angles a record does not carry)."""
    return [_angle_record(d, r) for r in d.rec.angles]


def _angle_record(d: ReportData, r: dict) -> dict:
    """One angles record as arrays over the rig's angles: ``alpha``, ``sigma`` (the run's
    σ_CR, else the posterior's), ``sigma_post`` (sqrt diag P), and the record's own fields."""
    names = r.get("names") or list(d.angle_names)
    a = _vec(r.get("alpha"), len(names))
    s = r.get("sigma_cr")
    P = r.get("P")
    Pm = None if P is None else np.array([_vec(row, len(names)) for row in P], float)
    if s is None and Pm is not None:
        s = np.sqrt(np.clip(np.diag(Pm), 0, None)).tolist()
    s = _vec(s, len(names)) if s is not None else [math.nan] * len(names)
    post = (np.sqrt(np.clip(np.diag(Pm), 0, None)) if Pm is not None and Pm.shape ==
            (len(names), len(names)) else np.full(len(names), np.nan))
    alpha, sig, sig_post = _on_rig_angles(d, names, a, s, post)
    return {"t": _num(r.get("t")), "accepted": bool(r.get("accepted")),
            "reason": r.get("reason"), "alpha": alpha, "sigma": sig,
            "sigma_post": sig_post, "names": names,
            "P": Pm, "alpha_sub": np.array(a), "determined": r.get("determined"),
            "window": r.get("window")}


def _on_rig_angles(d: ReportData, names: list[str], *values: Any) -> list[np.ndarray]:
    """Each of ``values`` (one number per name) placed on the rig's angles (nan for the
    angles the names leave out; names that are not the rig's angles dropped)."""
    out = [np.full(len(d.angle_names), np.nan) for _ in values]
    for k, nm in enumerate(names):
        if nm in d.angle_names:
            i = d.angle_names.index(nm)
            for o, v in zip(out, values):
                o[i] = v[k]
    return out


def _truth_alpha_at(d: ReportData, t_abs: float) -> np.ndarray | None:
    """Truth angles at an absolute record time (nearest record's truth)."""
    if d.alpha_truth_hub is None or d.alpha_truth_t is None or not math.isfinite(t_abs):
        return None
    rel = d.alpha_truth_t
    j = int(np.argmin(np.abs(rel - (t_abs - d.t0))))
    if abs(rel[j] - (t_abs - d.t0)) > 1.0 or not np.isfinite(d.alpha_truth_hub[j]).all():
        return None
    return d.alpha_truth_hub[j]


def _joint_chi2(d: ReportData, last: dict, tr: np.ndarray) -> dict | None:
    """The final angles' joint consistency with the whole posterior covariance over the
    identified names; None when P is singular."""
    e = last["alpha_sub"] - tr[[d.angle_names.index(n) for n in last["names"]]]
    try:
        chi2 = float(e @ np.linalg.solve(last["P"], e))
    except np.linalg.LinAlgError:
        return None
    dof = len(e)
    thr = float(stats.chi2.ppf(1 - FALSE_ALARM, dof))
    return {"value": chi2, "dof": dof, "threshold": thr, "false_alarm": FALSE_ALARM,
            "consistent": chi2 <= thr}


def _last_advice(d: ReportData) -> dict | None:
    """Filter-error windows: what would determine the rest, the latest."""
    advised = [r for r in d.rec.angles if isinstance(r.get("advice"), dict)]
    if not advised:
        return None
    from rsra.estimator.flight_advice import advice_summary

    r = advised[-1]
    return {"t": _num(r.get("t")) - d.t0, "sentence": advice_summary(
        r["advice"], len(r.get("names") or []) or None), "advice": r["advice"]}


def _angles_summary(d: ReportData) -> dict:
    runs = _angle_records(d)
    if not runs:
        return {"skipped": "no angles records"}
    reasons: dict[str, int] = {}
    for r in runs:
        if not r["accepted"]:
            reasons[str(r["reason"])] = reasons.get(str(r["reason"]), 0) + 1
    last = runs[-1]
    out: dict = {"runs": len(runs), "accepted": sum(r["accepted"] for r in runs),
                 "rejected": reasons,
                 "final_t": last["t"] - d.t0 if math.isfinite(last["t"]) else None}
    final = {"names": list(d.angle_names), "estimate_deg": np.degrees(last["alpha"]).tolist(),
             "sigma_cr_deg": np.degrees(last["sigma"]).tolist(),
             "determined": last["determined"]}
    tr = _truth_alpha_at(d, last["t"])
    if tr is not None:
        err = last["alpha"] - tr
        final.update(truth_deg=np.degrees(tr).tolist(), error_deg=np.degrees(err).tolist(),
                     error_over_sigma=(err / last["sigma"]).tolist())
        if last["P"] is not None and all(n in d.angle_names for n in last["names"]):
            out["joint_chi2"] = _joint_chi2(d, last, tr)
    out["final"] = final
    advice = _last_advice(d)
    if advice is not None:
        out["advice"] = advice
    return out


def _innovations_summary(d: ReportData) -> dict:
    inn = d.rec.innovations
    if inn is None:
        return {"skipped": "no innovations records"}
    ok = np.isfinite(inn["nis"])
    if not ok.any():
        return {"skipped": "innovations records carry no nis"}
    nis = inn["nis"][ok & (inn["t"] - d.t0 >= d.settle_s)]
    if not len(nis):
        return {"skipped": f"no innovations after the {d.settle_s:g} s of filter settling"}
    lo, hi = _chi2_band(6)
    total = float(nis.sum())
    dof = 6 * len(nis)
    out = {"records": int(len(nis)), "settle_s": d.settle_s,
           "mean_nis": float(nis.mean()), "dof_per_record": 6,
           "band": [lo, hi], "false_alarm": FALSE_ALARM,
           "fraction_outside": float(np.mean((nis < lo) | (nis > hi))),
           "joint_chi2": {"value": total, "dof": dof,
                          "band": list(_chi2_band(dof)),
                          "p_value_upper": float(stats.chi2.sf(total, dof))}}
    out.update(nis_consistency(nis, lo, hi))
    # per state of the load: held, or `transient` (the hub_loads flag at the record's sample)
    sel = ok & (inn["t"] - d.t0 >= d.settle_s)
    hub = d.rec.hub
    # and per phase, as the hub loads (daq.analysis.accuracy): the start, transients, steady
    from rsra.daq.analysis.accuracy import PHASES

    ph = record_phases(d, inn["seq"][sel])
    out["by_phase"] = {p: _nis_group(nis, ph == p, lo, hi) for p in PHASES}
    if hub is not None:
        moving = {int(q) for q, f in zip(hub["seq"], hub["flags"]) if "transient" in f}
        tr = np.array([int(q) in moving for q in inn["seq"][sel]], bool)
        out["by_state"] = {state: _nis_group(nis, m, lo, hi)
                           for state, m in (("held", ~tr), ("transient", tr))}
    return out


def _nis_group(nis: np.ndarray, m: np.ndarray, lo: float, hi: float) -> dict:
    """The NIS of the records ``m`` selects: how many, their mean and their consistency."""
    return {"records": int(m.sum()), "mean_nis": float(nis[m].mean()) if m.any() else None,
            **nis_consistency(nis[m], lo, hi)}


def effective_records(x: np.ndarray, max_lag: int = 200) -> float:
    """How many independent records a correlated series is worth: n / (1 + 2 Σ ρ_k), the
    sum of its sample autocorrelations up to the first that is not positive (Geyer's initial
    positive sequence, simplified); n for a white series."""
    n = len(x)
    if n < 8:
        return float(n)
    x = np.asarray(x, float) - float(np.mean(x))
    var = float(x @ x) / n
    if var <= 0.0:
        return float(n)
    acc = 0.0
    for k in range(1, min(n // 4, max_lag)):
        rho = float(x[:-k] @ x[k:]) / (n * var)
        if rho <= 0.0:
            break
        acc += rho
    return max(1.0, n / (1.0 + 2.0 * acc))


def nis_consistency(nis: np.ndarray, lo: float, hi: float,
                    false_alarm: float = FALSE_ALARM) -> dict:
    """The NIS against the χ²₆ band [lo, hi] (each tail ``false_alarm``/2): the share above and
    below, the mean against the band of a mean of ``n_eff`` χ²₆ (``n_eff``: the records'
    worth as independent ones, :func:`effective_records` — they are correlated over a few
    filter time constants), and the verdict — ``inconsistent`` when more lie above hi than a
    consistent filter gives at an overall false-alarm rate of ``false_alarm`` (binomial;
    innovations larger than their stated σ) or the mean lies above its band,
    ``conservative`` when too many lie below lo or the mean lies below its band (smaller than
    stated: the σ is overstated), ``consistent`` otherwise; ``no data`` without records."""
    n = int(len(nis))
    if not n:
        return {"above": None, "below": None, "limit": None, "verdict": "no data",
                "effective_records": None, "mean_band": None}
    k_hi, k_lo = int(np.sum(nis > hi)), int(np.sum(nis < lo))
    n_eff = effective_records(nis)
    # the tail counts of correlated records come in clusters: counted at the records' worth
    w = n_eff / n
    limit = int(stats.binom.isf(false_alarm / 4, max(1, round(n_eff)), false_alarm / 2))
    dof = 6.0 * n_eff
    m_lo, m_hi = (float(stats.chi2.ppf(false_alarm / 4, dof)) / n_eff,
                  float(stats.chi2.isf(false_alarm / 4, dof)) / n_eff)
    mean = float(np.mean(nis))
    verdict = ("inconsistent" if w * k_hi > limit or mean > m_hi else
               "conservative" if w * k_lo > limit or mean < m_lo else "consistent")
    return {"above": k_hi / n, "below": k_lo / n, "limit": limit / max(1, round(n_eff)),
            "verdict": verdict,
            "effective_records": n_eff, "mean_band": [m_lo, m_hi]}


def _flags_summary(d: ReportData) -> dict:
    out: dict = {}
    if d.rec.hub is not None:
        counts: dict[str, int] = {}
        n_any = 0
        for fl in d.rec.hub["flags"]:
            if fl:
                n_any += 1
            for f in fl:
                counts[f] = counts.get(f, 0) + 1
        out["hub_loads"] = dict(sorted(counts.items()))
        out["samples_flagged"] = n_any
    if d.rec.health:
        h = d.rec.health[-1]
        out["health"] = {k: h.get(k) for k in ("samples", "bus") if k in h}
    return out


# ---------------------------------------------------------------------------------------------
# plots


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    save_figure(fig, path, dpi=DPI)
    _plt().close(fig)
    return path


def _fmt(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def _axis_scale(units: str) -> np.ndarray:
    return to_units(np.ones(6), units)


PHASE_SHADE = {"start": ("tab:red", 0.10), "transient": ("gold", 0.22)}  # steady: unshaded


def phase_spans(d: ReportData) -> list[tuple[float, float, str]]:
    """The run's phases (:func:`record_phases`) as time spans ``(t0, t1, phase)`` relative to
    the start, from the hub-load records; empty without them."""
    hub = d.rec.hub
    if hub is None or not len(hub["seq"]):
        return []
    order = np.argsort(hub["t"], kind="stable")
    t = (hub["t"] - d.t0)[order]
    ph = record_phases(d, hub["seq"])[order]
    ok = np.isfinite(t)
    t, ph = t[ok], ph[ok]
    if not len(t):
        return []
    cut = np.flatnonzero(ph[1:] != ph[:-1]) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [len(t)]])
    half = 0.5 * d.cfg.sample_period_s
    return [(float(t[a]) - half, float(t[b - 1]) + half, str(ph[a])) for a, b in zip(starts, ends)]


def shade_phases(ax, spans: list[tuple[float, float, str]]) -> None:
    """Shade the start and transient phases behind a time plot (steady: unshaded), each
    labelled once for the legend."""
    seen: set[str] = set()
    for t0, t1, p in spans:
        if p not in PHASE_SHADE:
            continue
        color, alpha = PHASE_SHADE[p]
        label = None
        if p not in seen:
            seen.add(p)
            label = {"start": "start (uncalibrated)", "transient": "transient"}[p]
        ax.axvspan(t0, t1, color=color, alpha=alpha, lw=0, label=label, zorder=0)


def _steady_title(bp: dict | None, name: str, i: int) -> str:
    """``steady: RMS err …, err/σ …, … % > 3σ`` for axis ``i`` of ``name`` (H or H_static) from
    the by-phase summary; empty without a steady phase."""
    v = ((bp or {}).get(name) or {}).get("steady")
    if not v:
        return ""
    return (f"steady {name}: RMS {_fmt(v['rms_error'][i])}, err/σ "
            f"{v['rms_over_sigma'][i]:.2f}, {100 * v['beyond_3sigma'][i]:.1f} % > 3σ")


def _per_revolution(t: np.ndarray, x: np.ndarray, period: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mean, min and max of ``x`` over consecutive spans of one ``period`` (a revolution, or
    a fixed span without a rotor speed): the whole run readable at a glance."""
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    if not len(t):
        e = np.empty(0)
        return e, e, e, e
    k = np.floor((t - t[0]) / period).astype(np.int64)
    cut = np.flatnonzero(np.diff(k)) + 1
    starts = np.concatenate([[0], cut])
    mean = np.add.reduceat(x, starts) / np.diff(np.concatenate([starts, [len(x)]]))
    return (np.add.reduceat(t, starts) / np.diff(np.concatenate([starts, [len(x)]])), mean,
            np.minimum.reduceat(x, starts), np.maximum.reduceat(x, starts))


def _whole_run_panel(a, d: ReportData, t: np.ndarray, i: int, rev: float) -> None:
    """Hub-load axis ``i`` over the whole run: mean and range per revolution of H and of the
    truth, the phases shaded."""
    sc = _axis_scale(d.units)
    hub = d.rec.hub
    assert hub is not None  # build_report: with hub_loads records only
    shade_phases(a, phase_spans(d))
    if d.H_truth is not None:
        tt, m, lo, hi = _per_revolution(t, d.H_truth[:, i] * sc[i], rev)
        a.fill_between(tt, lo, hi, color="0.8", lw=0, label="truth: range per revolution")
        a.plot(tt, m, color="k", lw=1.4, label="truth: mean per revolution")
    tt, m, lo, hi = _per_revolution(t, hub["H"][:, i] * sc[i], rev)
    if d.H_truth is None:
        a.fill_between(tt, lo, hi, color="tab:blue", alpha=0.2, lw=0,
                       label="H: range per revolution")
    a.plot(tt, m, color="tab:blue", lw=1.0, ls="--" if d.H_truth is not None else "-",
           label="H: mean per revolution")
    a.set_title(f"{AXES[i]}: whole run", fontsize=10)


def _last_revolutions_panel(a, d: ReportData, t: np.ndarray, i: int, win: np.ndarray,
                            span: float) -> None:
    """Hub-load axis ``i`` over the last revolutions: H, H_static and the truth with the
    static noise-budget band."""
    sc = _axis_scale(d.units)
    hub = d.rec.hub
    assert hub is not None  # build_report: with hub_loads records only
    tw = t[win]
    ref = d.H_truth[win, i] if d.H_truth is not None else hub["H"][win, i]
    band = d.sigma_static[i] * sc[i]
    a.fill_between(tw, ref * sc[i] - band, ref * sc[i] + band, color="0.85",
                   label=("truth" if d.H_truth is not None else "H") + " ± static σ")
    if d.H_truth is not None:
        a.plot(tw, d.H_truth[win, i] * sc[i], color="k", lw=1.6, label="truth")
    a.plot(tw, hub["H_static"][win, i] * sc[i], color="tab:orange", lw=0.8, alpha=0.8,
           label="H_static (per sample)")
    a.plot(tw, hub["H"][win, i] * sc[i], color="tab:blue", lw=1.2, label="H (load filter)")
    a.set_title(f"{AXES[i]}: last {span:.1f} s", fontsize=10)


def plot_hub_loads(d: ReportData, out: Path) -> Path:
    """The whole run (per-revolution mean and range of H and of the truth, phases shaded), then
    the estimates (filter H, static H_static) vs truth over the last rotor revolutions with
    the static bound band (truth ± noise-budget σ, model §4)."""
    plt = _plt()
    hub = d.rec.hub
    assert hub is not None  # build_report: with hub_loads records only
    t = hub["t"] - d.t0
    rev = 2 * math.pi / d.omega if d.omega else 0.25
    span = ZOOM_REVOLUTIONS * rev if d.omega else 2.0
    win = t >= (np.nanmax(t) - span)
    u = axis_units(d.units)
    fig, axs = plt.subplots(4, 3, figsize=(14, 14), layout="constrained")
    for i in range(6):
        _whole_run_panel(axs[i // 3, i % 3], d, t, i, rev)
        _last_revolutions_panel(axs[2 + i // 3, i % 3], d, t, i, win, span)
    for i in range(6):  # the forces' row and the moments' (time axis) of both halves
        for a in (axs[i // 3, i % 3], axs[2 + i // 3, i % 3]):
            a.set_ylabel(f"{AXES[i]} [{u[i]}]")
            a.grid(True, alpha=0.3)
            if i >= 3:
                a.set_xlabel("time since start [s]")
    axs[0, 0].legend(fontsize=7, loc="best")
    axs[2, 0].legend(fontsize=7, loc="best")
    what = f"{ZOOM_REVOLUTIONS} rotor revolutions" if d.omega else "no rotor speed"
    fig.suptitle(f"Hub loads ({d.frame} axes). Rows 1–2: the whole run, mean and range per "
                 f"revolution, phases shaded.\nRows 3–4: the last {span:.1f} s ({what}), "
                 "band = static noise-budget σ")
    return _save(fig, out / "hub_loads.png")


def plot_hub_errors(d: ReportData, out: Path, summ: dict) -> Path:
    """Errors over the whole run with the ±σ (and ±3σ) static bound."""
    plt = _plt()
    hub, H_truth = d.rec.hub, d.H_truth
    assert hub is not None and H_truth is not None  # build_report: with both only
    t = hub["t"] - d.t0
    sc = _axis_scale(d.units)
    u = axis_units(d.units)
    errs = summ.get("errors", {})
    spans = phase_spans(d)
    fig, axs = plt.subplots(2, 3, figsize=FIG_SIZE, layout="constrained", sharex=True)
    for i in range(6):
        a = axs.flat[i]
        s = d.sigma_static[i] * sc[i]
        shade_phases(a, spans)
        a.axhspan(-3 * s, 3 * s, color="0.93", label="±3σ static bound")
        a.axhspan(-s, s, color="0.82", label="±σ static bound")
        rs = errs.get("H_static")
        rh = errs.get("H")
        a.plot(t, (hub["H_static"][:, i] - H_truth[:, i]) * sc[i], color="tab:orange",
               lw=0.5, alpha=0.7, label="H_static − truth (static estimate)")
        a.plot(t, (hub["H"][:, i] - H_truth[:, i]) * sc[i], color="tab:blue", lw=0.8,
               label="H − truth (load filter)")
        steady = _steady_title(summ.get("by_phase"), "H", i)
        if not steady:  # no phases (no truth alignment by phase): the whole run, said so
            steady = "whole run: " + ", ".join(f"RMS {k} {_fmt(r['rms_error'][i])}"
                                               for k, r in (("H", rh), ("H_static", rs)) if r)
        a.set_title(f"{AXES[i]} [{u[i]}]: static σ {_fmt(s)}\n{steady}", fontsize=9)
        settled = t >= d.settle_s
        e_all = np.concatenate([(hub[k][settled, i] - H_truth[settled, i]) * sc[i]
                                for k in ("H", "H_static")])
        e_all = e_all[np.isfinite(e_all)]
        lim = max(5 * s, 1.1 * float(np.percentile(np.abs(e_all), 99.9)) if len(e_all) else 0.0)
        a.set_ylim(-lim, lim)  # the start-up transient may leave the frame
        a.grid(True, alpha=0.3)
        if i >= 3:
            a.set_xlabel("time since start [s]")
    fig.legend(*axs.flat[0].get_legend_handles_labels(), loc="outside lower center", ncol=6,
               fontsize=9)
    fig.suptitle(f"Hub-load errors against truth ({d.frame} axes): load filter and static "
                 "estimate vs the static noise budget (model §4)\ntitles: the calibrated "
                 "steady state, err/σ against the σ published with each sample")
    return _save(fig, out / "hub_load_errors.png")


def _starting_state(d: ReportData) -> tuple[np.ndarray, np.ndarray, str]:
    """The angles and their σ in force before the first run, and what they are: the results'
    own starting record, else the configured prior — or, for a run started from a saved
    posterior whose values the results do not carry, nan (drawn as nothing)."""
    names = d.angle_names
    ini = d.rec.initial_angles
    if ini is not None:
        r = _angle_record(d, ini)
        return r["alpha"], r["sigma_post"], "the run's starting posterior"
    hub = d.rec.hub
    if hub is not None and len(hub["seq"]) and calibrated_from(d) == int(np.min(hub["seq"])):
        nan = np.full(len(names), np.nan)
        return nan, nan, "a saved posterior (its values are not in the results)"
    return (d.alpha_config, np.full(len(names), d.cfg.identification.prior_sigma_rad),
            "the configured prior")


def angle_steps(d: ReportData, runs: list[dict]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """The angles in force as steps: times (relative), estimates and posterior σ (rows: the
    starting state, then each run's record, the last held to the end), and what the first
    row is (:func:`_starting_state`)."""
    t_end = max([r["t"] for r in runs if math.isfinite(r["t"])] + [d.t0])
    if d.rec.hub is not None:
        t_end = max(t_end, float(np.nanmax(d.rec.hub["t"])))
    tt = np.array([d.t0] + [r["t"] for r in runs] + [t_end]) - d.t0
    a0, s0, start_what = _starting_state(d)
    A = np.vstack([a0] + [r["alpha"] for r in runs] + [runs[-1]["alpha"]])
    S = np.vstack([s0] + [r["sigma_post"] for r in runs] + [runs[-1]["sigma_post"]])
    return tt, A, S, start_what


def _run_marks(a, d: ReportData, runs: list[dict], i: int) -> None:
    """Each run's estimate of angle ``i``: accepted ± its σ_CR, rejected as a cross."""
    for acc, fmt, color, label in ((True, "o", "tab:green", "accepted run ± σ_CR"),
                                   (False, "x", "tab:red", "rejected run")):
        sel = [r for r in runs if r["accepted"] == acc]
        if not sel:
            continue
        tr_ = np.array([r["t"] - d.t0 for r in sel])
        va = np.degrees(np.array([r["alpha"][i] for r in sel]))
        if acc:
            err = np.degrees(np.array([r["sigma"][i] for r in sel]))
            a.errorbar(tr_, va, yerr=np.where(np.isfinite(err), err, 0.0), fmt=fmt,
                       color=color, ms=4, lw=0.8, capsize=2, label=label)
        else:
            a.plot(tr_, va, fmt, color=color, ms=6, mew=1.5, label=label)


def _readable_range(a, d: ReportData, A: np.ndarray, S: np.ndarray, i: int) -> None:
    """A readable range: every run's estimate ± its posterior σ and the truth (a wide prior
    before the first run may leave the frame), at least 1° tall."""
    vals = np.concatenate([A[1:, i] - S[1:, i], A[1:, i] + S[1:, i]])
    if d.alpha_truth_hub is not None:
        vals = np.concatenate([vals, d.alpha_truth_hub[:, i]])
    vals = np.degrees(vals[np.isfinite(vals)])
    if len(vals):
        lo, hi = float(vals.min()), float(vals.max())
        mid, half = (lo + hi) / 2, max(0.5, 0.55 * (hi - lo))
        a.set_ylim(mid - half, mid + half)


def _angles_legend(axs, n: int) -> None:
    """One legend in the first free panel, with the marker kinds only some panels have."""
    handles, labels = axs.flat[0].get_legend_handles_labels()
    for r_ax in axs.flat[:n]:
        for h, lab in zip(*r_ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    axs.flat[n].legend(handles, labels, loc="center", fontsize=10)


def plot_angles(d: ReportData, out: Path) -> Path:
    """Angles over time: the estimate in force with its posterior ±σ band (sqrt diag P of
    each record), truth, each run's estimate with its own Cramér–Rao σ_CR, accepted or
    rejected, the phases shaded; before the first run the state the run started from."""
    plt = _plt()
    runs = _angle_records(d)
    names = d.angle_names
    tt, A, S, start_what = angle_steps(d, runs)
    spans = phase_spans(d)
    fig, axs = plt.subplots(4, 4, figsize=(14, 10), layout="constrained", sharex=True)
    for i, nm in enumerate(names):
        a = axs.flat[i]
        shade_phases(a, spans)
        a.fill_between(tt, np.degrees(A[:, i] - S[:, i]), np.degrees(A[:, i] + S[:, i]),
                       step="post", color="tab:blue", alpha=0.2, label="±σ posterior")
        a.step(tt, np.degrees(A[:, i]), where="post", color="tab:blue", lw=1.2,
               label="estimate in force")
        if d.alpha_truth_hub is not None:
            a.plot(d.alpha_truth_t, np.degrees(d.alpha_truth_hub[:, i]), color="k", lw=1.0,
                   ls="--", label="truth")
        _run_marks(a, d, runs, i)
        _readable_range(a, d, A, S, i)
        a.set_title(nm, fontsize=10)
        a.set_ylabel("angle [deg]")
        a.grid(True, alpha=0.3)
    for j in range(len(names), 16):
        axs.flat[j].axis("off")
    _angles_legend(axs, len(names))
    for j in range(max(0, len(names) - 4), len(names)):  # each column's lowest used panel
        axs.flat[j].set_xlabel("time since start [s]")
        axs.flat[j].xaxis.set_tick_params(labelbottom=True)
    fig.suptitle("Load-cell deformation angles: the estimate in force with its posterior ±σ, "
                 f"truth, each run with its σ_CR; before the first run: {start_what}")
    return _save(fig, out / "angles.png")


def plot_nis(d: ReportData, out: Path, summ: dict | None = None) -> Path:
    """Normalised innovations squared against the χ²₆ band (two-sided 1e-3), and its running
    mean against the band of a mean of M independent χ²₆, both on a log scale with the
    phases shaded; the calibrated steady state's verdict in the title."""
    plt = _plt()
    inn = d.rec.innovations
    assert inn is not None  # build_report: with innovations records only
    ok = np.isfinite(inn["nis"])
    t = inn["t"][ok] - d.t0
    nis = inn["nis"][ok]
    lo, hi = _chi2_band(6)
    M = max(1, int(round(d.cfg.telemetry.innovations_hz)))  # one second of records
    settled = t >= d.settle_s
    sn = nis[settled]
    spans = phase_spans(d)
    fig, axs = plt.subplots(2, 1, figsize=FIG_SIZE, layout="constrained", sharex=True)
    a = axs[0]
    a.plot(t, nis, ".", ms=2, color="tab:blue", label="NIS per record")
    a.axhspan(lo, hi, color="tab:green", alpha=0.12,
              label=f"χ²₆ band [{lo:.3g}, {hi:.3g}] (false alarm {FALSE_ALARM:g})")
    a.axhline(6.0, color="tab:green", ls="--", lw=1, label="expected mean 6")
    a.set_yscale("log")
    a.set_ylabel("NIS = eᵀ B⁻¹ e")
    _nis_title(a, d, summ, sn, lo, hi)
    a.grid(True, which="both", alpha=0.3)
    b = axs[1]
    if len(sn) >= M:  # windows entirely after the settling
        _running_mean(b, t[settled], sn, M)
    b.set_yscale("log")
    b.axhline(6.0, color="tab:green", ls="--", lw=1)
    b.set_ylabel("running mean NIS")
    b.set_xlabel("time since start [s]")
    b.grid(True, which="both", alpha=0.3)
    for ax in axs:
        shade_phases(ax, spans)
        ax.axvspan(t.min(), d.settle_s, color="0.9", label="filter settling (not scored)")
        ax.legend(fontsize=8, loc="upper right")
    fig.suptitle("Load-filter innovations against χ²₆ (model §6: B normalises the NIS)")
    return _save(fig, out / "innovations.png")


def _nis_title(a, d: ReportData, summ: dict | None, sn: np.ndarray, lo: float, hi: float
               ) -> None:
    """The calibrated steady state's verdict, else the settled records' figures."""
    steady = ((summ or {}).get("by_phase") or {}).get("steady") or {}
    if steady.get("records"):
        a.set_title(f"Calibrated steady state: {steady['records']} records, mean NIS "
                    f"{steady['mean_nis']:.2f} (band of the mean "
                    f"{steady['mean_band'][0]:.2f}–{steady['mean_band'][1]:.2f}), "
                    f"{steady['above'] * 100:.2f} % above / {steady['below'] * 100:.2f} % "
                    f"below the band: {steady['verdict']}", fontsize=10)
    elif len(sn):
        a.set_title(f"Normalised innovations after {d.settle_s:g} s of settling ({len(sn)} "
                    f"records, mean {sn.mean():.2f}, "
                    f"{np.mean((sn < lo) | (sn > hi)) * 100:.2f} % outside the band)")


def _running_mean(b, t: np.ndarray, sn: np.ndarray, M: int) -> None:
    """The running mean of ``M`` settled records against the band of a mean of M
    independent χ²₆."""
    run = np.convolve(sn, np.ones(M) / M, mode="valid")
    lo_m, hi_m = (v / M for v in _chi2_band(6 * M))
    b.plot(t[M - 1:], run, color="tab:blue", lw=1.0, label=f"running mean of {M} records")
    b.axhspan(lo_m, hi_m, color="tab:green", alpha=0.12,
              label=f"band of a mean of {M} independent χ²₆ [{lo_m:.3g}, {hi_m:.3g}]")
    pos = run[run > 0]
    if len(pos):
        b.set_ylim(min(0.5 * lo_m, 0.8 * float(pos.min())),
                   max(2.0 * hi_m, 1.25 * float(pos.max())))


def _spectrum_series(d: ReportData) -> list[tuple[str, np.ndarray]]:
    """The load cells and the hub loads (H, H_static) on a uniform grid, each with enough
    of its samples present."""
    candidates = []
    if d.rec.channels is not None:
        candidates.append(("cells", d.rec.channels["seq"], d.rec.channels["T"]))
    if d.rec.hub is not None:
        candidates += [(name, d.rec.hub["seq"], d.rec.hub[name]) for name in ("H", "H_static")]
    series = []
    for name, seq, values in candidates:
        g, frac = _uniform(seq, values)
        if g is not None and frac >= MIN_UNIFORM_FRACTION:
            series.append((name, g))
    return series


def _plot_asd(d: ReportData, ax_of: dict, name: str, f: np.ndarray, asd: np.ndarray,
              colors) -> None:
    sc = _axis_scale(d.units)
    if name == "cells":
        cells = [c.name for c in d.cfg.cells]
        for j in range(asd.shape[1]):
            ax_of["cells"].semilogy(f, asd[:, j] * sc[0], lw=0.9, color=colors(j),
                                    label=f"cell {cells[j]}")
        return
    style = dict(lw=1.0) if name == "H" else dict(lw=0.7, ls=":", alpha=0.8)
    for j in range(6):
        a = ax_of["forces"] if j < 3 else ax_of["moments"]
        a.semilogy(f, asd[:, j] * sc[j], color=colors(j % 3), label=f"{AXES[j]} ({name})",
                   **style)


def _mark_revolutions(d: ReportData, a) -> None:
    """1/rev and N_b/rev on a spectrum's frequency axis."""
    if not d.omega:
        return
    f1 = d.omega / (2 * math.pi)
    for k, lab in ((1, "1/rev"), (d.cfg.rotor.blades, f"{d.cfg.rotor.blades}/rev")):
        a.axvline(k * f1, color="crimson", ls="--", lw=1)
        a.text(k * f1, 0.97, f" {lab}", color="crimson", transform=a.get_xaxis_transform(),
               va="top", fontsize=9)


def plot_spectra(d: ReportData, out: Path) -> tuple[Path | None, str | None]:
    """Welch amplitude spectral densities of the load cells and the hub loads (filter H and
    static H_static), with 1/rev and N_b/rev marked."""
    plt = _plt()
    fs = d.cfg.sample_rate_hz
    series = _spectrum_series(d)
    if not series:
        return None, "no load-cell or hub-load series with enough samples"
    n = min(len(g) for _, g in series)
    if n < 64:
        return None, f"too few samples for a spectrum ({n})"
    nper = min(n, 2 ** int(math.log2(max(64, min(n // 4, int(8 * fs))))))
    u = axis_units(d.units)
    has_cells = any(name == "cells" for name, _ in series)
    has_hub = any(name != "cells" for name, _ in series)
    kinds = (["cells"] if has_cells else []) + (["forces", "moments"] if has_hub else [])
    fig, axs = plt.subplots(len(kinds), 1, figsize=FIG_SIZE, layout="constrained",
                            sharex=True, squeeze=False)
    ax_of = dict(zip(kinds, axs[:, 0]))
    colors = plt.get_cmap("tab10")
    for name, g in series:
        f, P = signal.welch(g, fs=fs, nperseg=nper, axis=0, detrend="constant")
        _plot_asd(d, ax_of, name, f, np.sqrt(P), colors)
    titles = {"cells": f"Load cells [{u[0]}/√Hz]", "forces": f"Hub forces [{u[0]}/√Hz]",
              "moments": f"Hub moments [{u[3]}/√Hz]"}
    axs = axs[:, 0]
    for kind, a in ax_of.items():
        _mark_revolutions(d, a)
        a.set_title(titles[kind])
        a.set_ylabel("amplitude spectral density")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7, ncol=4, loc="upper right")
    axs[-1].set_xlabel("frequency [Hz]")
    fig.suptitle(f"Spectra (Welch, {nper} samples per segment"
                 + ("; hub loads: solid = load filter, dotted = static estimate)" if has_hub
                    else "; no hub-load records)"))
    return _save(fig, out / "spectra.png"), None


# ---------------------------------------------------------------------------------------------
# the report


@dataclass
class Report:
    out: Path
    plots: list[Path]
    skipped: dict[str, str]
    summary: dict

    def markdown_brief(self) -> str:
        s = self.summary
        lines = [f"report: {len(self.plots)} plots and summary.md/summary.json in {self.out}"]
        hub = s.get("hub_loads", {})
        lines += _brief_hub((hub.get("by_phase") or {}) if isinstance(hub, dict) else {})
        lines += _brief_angles(s.get("angles", {}))
        lines += _brief_innovations(s.get("innovations", {}))
        lines += [f"  skipped {k}: {v}" for k, v in self.skipped.items()]
        return "\n".join(lines)


def _brief_hub(bp: dict) -> list[str]:
    """The hub-load error against truth by phase, for the terminal."""
    if not bp:
        return []
    from rsra.daq.analysis.accuracy import MEANING, phase_lines

    lines = ["  hub-load error against truth, by phase (RMS error/σ and the fraction beyond 3σ "
             "per axis, σ as published for each sample):"]
    for name in ("H", "H_static"):
        lines += [x for x in phase_lines(bp.get(name) or {}, name, "    ")
                  if not x.lstrip().startswith("(")]
    return lines + [f"    {p}: {m}" for p, m in MEANING.items()
                    if (bp.get("H") or {}).get(p) or (bp.get("H_static") or {}).get(p)]


def _brief_angles(ang: dict) -> list[str]:
    lines = []
    j = ang.get("joint_chi2")
    if j:
        lines.append(f"  final angles: joint χ² {j['value']:.1f} on {j['dof']} dof "
                     f"(threshold {j['threshold']:.1f}): "
                     + ("consistent" if j["consistent"] else "INCONSISTENT"))
    if isinstance(ang.get("advice"), dict):
        lines.append(f"  advice (the last filter-error window, {ang['advice']['t']:.1f} s): "
                     f"{ang['advice']['sentence']}")
    return lines


def _loud(verdict: str, consistent: str = "consistent") -> str:
    """A verdict as the terminal says it: an inconsistent one in capitals."""
    return consistent if verdict == "consistent" else verdict.upper()


def _brief_innovations(inn: dict) -> list[str]:
    if "mean_nis" not in inn:
        return []
    lines = [f"  innovations, whole run (the phases below mixed): mean NIS "
             f"{inn['mean_nis']:.2f} (expected 6), "
             f"{inn['fraction_outside'] * 100:.2f} % outside the χ²₆ band: "
             f"{_loud(inn['verdict'])}"]
    for state, v in (inn.get("by_phase") or inn.get("by_state") or {}).items():
        if v["records"]:
            lines.append(f"    {state}: {v['records']} records, mean NIS "
                         f"{v['mean_nis']:.2f}, {v['above'] * 100:.2f} % above / "
                         f"{v['below'] * 100:.2f} % below the band: " + _loud(v["verdict"]))
    return lines


def _bold(verdict: str) -> str:
    """A verdict as the markdown says it: an inconsistent one in bold."""
    return "consistent" if verdict == "consistent" else f"**{verdict}**"


def _md_inputs(inp: dict, units: str) -> list[str]:
    recs = ", ".join(f"{k} {v}" for k, v in inp["records"].items())
    aligned = (f", aligned by {inp['alignment']} ({inp['matched'] * 100:.1f} % of records "
               "matched)" if inp.get("alignment") else "")
    return [f"* results: `{inp['results']}` ({recs})", f"* truth: `{inp['truth']}`{aligned}",
            f"* span: {inp['span_s']:.2f} s; units: {units.upper()}", ""]


def _pair(e: dict | None, i: int) -> str:
    """An estimate's RMS error and RMS error/σ on axis ``i`` as two table cells."""
    if not e:
        return "– | –"
    return f"{e['rms_error'][i]:.1f} | {e['rms_over_sigma_static'][i]:.3f}"


def _md_hub_errors(hub: dict, u: list[str]) -> list[str]:
    errs = hub["errors"]
    L = ["", f"RMS error against truth (H scored after {hub['settle_s']:.2f} s of "
         "filter settling) vs the static noise-budget σ (model §4):", "",
         "| axis | unit | static σ | RMS H | RMS H / σ | RMS H_static | RMS H_static / σ |",
         "|---|---|---|---|---|---|---|"]
    for i, a in enumerate(AXES):
        L.append(f"| {a} | {u[i]} | {hub['sigma_static'][i]:.1f} | "
                 f"{_pair(errs.get('H'), i)} | {_pair(errs.get('H_static'), i)} |")
    return L


def _md_hub_by_phase(bp: dict, u: list[str]) -> list[str]:
    L = ["", "By phase, each sample against the σ its record published "
         f"({bp['sigma']}): RMS error, RMS error/σ and the fraction beyond 3σ "
         "(0.27 % for an error of that σ).", ""]
    L += [f"* **{p}**: {m}" for p, m in bp["meaning"].items()]
    L += ["", "| estimate | phase | samples | axis | RMS error | RMS error / σ | beyond 3σ |",
          "|---|---|---|---|---|---|---|"]
    for name in ("H", "H_static"):
        for p, v in (bp.get(name) or {}).items():
            L += [f"| {name} | {p} | {v['samples']} | {a} [{u[i]}] | "
                  f"{v['rms_error'][i]:.1f} | {v['rms_over_sigma'][i]:.3f} | "
                  f"{100 * v['beyond_3sigma'][i]:.2f} % |" for i, a in enumerate(AXES) if v]
    return L


def _md_hub(hub: dict, units: str) -> list[str]:
    if "skipped" in hub:
        return ["## Hub loads", f"Skipped: {hub['skipped']}."]
    L = ["## Hub loads", f"{hub['records']} records, {hub['frame']} axes; H null in "
         f"{hub['H_null']}, H_static null in {hub['H_static_null']}."]
    if not hub.get("errors"):
        return L + ["No truth: errors not computed."]
    u = axis_units(units)
    L += _md_hub_errors(hub, u)
    if hub.get("by_phase"):
        L += _md_hub_by_phase(hub["by_phase"], u)
    return L


def _md_final_angles(ang: dict) -> list[str]:
    fin = ang["final"]
    L = ["", "Final estimate against truth:", "",
         "| angle | estimate [deg] | truth [deg] | error [deg] | σ_CR [deg] | error / σ |",
         "|---|---|---|---|---|---|"]
    L += [f"| {nm} | {fin['estimate_deg'][k]:.3f} | {fin['truth_deg'][k]:.3f} | "
          f"{fin['error_deg'][k]:+.3f} | {fin['sigma_cr_deg'][k]:.3f} | "
          f"{fin['error_over_sigma'][k]:+.2f} |" for k, nm in enumerate(fin["names"])]
    j = ang.get("joint_chi2")
    if j:
        L += ["", f"Joint χ² with the posterior covariance: {j['value']:.2f} on {j['dof']} "
              f"dof, threshold {j['threshold']:.2f} (false alarm {j['false_alarm']:g}): "
              + ("consistent." if j["consistent"] else "**inconsistent**.")]
    return L


def _md_angles(ang: dict) -> list[str]:
    if "skipped" in ang:
        return ["", "## Angles", f"Skipped: {ang['skipped']}."]
    rej = ", ".join(f"{k} {v}" for k, v in ang["rejected"].items()) or "none"
    L = ["", "## Angles",
         f"{ang['runs']} identification runs: {ang['accepted']} accepted; rejected: {rej}."]
    if "error_deg" in ang["final"]:
        L += _md_final_angles(ang)
    else:
        L.append("No truth: final errors not computed.")
    if isinstance(ang.get("advice"), dict):
        L += ["", f"Advice of the last filter-error window ({ang['advice']['t']:.1f} s): "
              f"{ang['advice']['sentence']}"]
    return L


def _md_state(state: str, v: dict) -> str:
    """The NIS of one load state (steady, transient)."""
    which = "hub_loads flagged `transient`" if state == "transient" else "not flagged"
    lags = state == "transient" and v["verdict"] != "consistent"
    return (f"* {state} load ({which}): {v['records']} records, mean NIS {v['mean_nis']:.3f}, "
            f"{v['above'] * 100:.3f} % above and {v['below'] * 100:.3f} % below the band "
            f"(each tail at most {v['limit'] * 100:.3f} % when consistent): "
            + _bold(v["verdict"])
            + (" — the filter lags the moving load; the σ that holds there is H_static's "
               "static bound (model.md, Transients)." if lags else "."))


def _md_innovations(inn: dict) -> list[str]:
    if "skipped" in inn:
        return ["", "## Innovations", f"Skipped: {inn['skipped']}."]
    j = inn["joint_chi2"]
    L = ["", "## Innovations",
         f"{inn['records']} records; mean NIS {inn['mean_nis']:.3f} (χ²₆: 6); "
         f"{inn['fraction_outside'] * 100:.2f} % outside [{inn['band'][0]:.3g}, "
         f"{inn['band'][1]:.3g}] (expected {FALSE_ALARM * 100:g} %); joint χ² "
         f"{j['value']:.1f} on {j['dof']} dof (band [{j['band'][0]:.1f}, "
         f"{j['band'][1]:.1f}]; records are correlated, so this is indicative): "
         f"{_bold(inn['verdict'])}."]
    L += [f"* phase {state}: {v['records']} records, mean NIS {v['mean_nis']:.3f}, "
          f"{v['above'] * 100:.3f} % above and {v['below'] * 100:.3f} % below the band: "
          f"{_bold(v['verdict'])}." for state, v in (inn.get("by_phase") or {}).items()
          if v["records"]]
    L += [_md_state(state, v) for state, v in (inn.get("by_state") or {}).items()
          if v["records"]]
    return L


def _md_flags(fl: dict) -> list[str]:
    L = ["", "## Flags and health"]
    if fl.get("hub_loads") is not None:
        L.append(f"Samples with a flag: {fl['samples_flagged']}.")
        L += [f"* `{k}`: {v}" for k, v in fl["hub_loads"].items()]
    if fl.get("health"):
        L.append(f"Last health: `{json.dumps(fl['health'])}`")
    if not fl:
        L.append("No hub_loads or health records.")
    return L


def _markdown(s: dict, units: str) -> str:
    L = ["# rsra report", "", *_md_inputs(s["inputs"], units), *_md_hub(s["hub_loads"], units),
         *_md_angles(s["angles"]), *_md_innovations(s["innovations"]), *_md_flags(s["flags"]),
         "", "## Plots", ""]
    L += [f"* ![{p}]({p})" for p in s["plots"]]
    L += [f"* {k}: skipped — {v}" for k, v in s["skipped"].items()]
    return "\n".join(L) + "\n"


def summarise(cfg: RigConfig, rec: Records, truth: dict | None, units: str = "si",
              truth_name: str | None = None) -> tuple[ReportData, dict]:
    """The numbers of the report (no plots): inputs and alignment, hub-load errors against
    the static bound, angles against σ_CR (and jointly), innovations against χ²₆, flags."""
    d = prepare(cfg, rec, truth, units)
    ts = [s["t"] for s in (rec.hub, rec.channels, rec.innovations) if s is not None]
    tmax = max((float(np.nanmax(x)) for x in ts if np.isfinite(x).any()), default=d.t0)
    al = d.hub_align or d.ch_align
    summary: dict = {
        "inputs": {"results": str(rec.path), "truth": truth_name, "records": rec.counts,
                   "span_s": tmax - d.t0,
                   "alignment": al.method if al else None,
                   "matched": al.matched if al else None},
        "units": axis_units(units),
        "hub_loads": _hub_summary(d),
        "angles": _angles_summary(d),
        "innovations": _innovations_summary(d),
        "flags": _flags_summary(d),
    }
    d.summary = summary
    return d, summary


def build_report(cfg: RigConfig, rec: Records, truth: dict | None, out: str | Path,
                 units: str = "si", truth_name: str | None = None) -> Report:
    """Summary and plots into ``out`` (summary.md, summary.json, PNGs)."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ReportError(f"--out {out}: cannot create the folder ({e.strerror})") from None
    d, summary = summarise(cfg, rec, truth, units, truth_name)
    plots: list[Path] = []
    skipped: dict[str, str] = {}
    _hub_plots(d, summary["hub_loads"], out, plots, skipped)
    if rec.angles:
        plots.append(plot_angles(d, out))
    else:
        skipped["angles.png"] = "no angles records (no identification run)"
    if "mean_nis" in summary["innovations"]:
        plots.append(plot_nis(d, out, summary["innovations"]))
    else:
        skipped["innovations.png"] = summary["innovations"].get("skipped", "no innovations")
    p, why = plot_spectra(d, out)
    if p is not None:
        plots.append(p)
    else:
        assert why is not None  # plot_spectra says why it made none
        skipped["spectra.png"] = why
    summary["plots"] = [p.name for p in plots]
    summary["skipped"] = skipped
    write_text_atomic(out / "summary.json", dumps(summary) + "\n")
    write_text_atomic(out / "summary.md", _markdown(summary, units))
    return Report(out=out, plots=plots, skipped=skipped, summary=summary)


def _hub_plots(d: ReportData, hub_s: dict, out: Path, plots: list[Path],
               skipped: dict[str, str]) -> None:
    """The hub loads' plot and, against truth, their errors' (or why not)."""
    hub = d.rec.hub
    if hub is None or not (np.isfinite(hub["H"]).any() or np.isfinite(hub["H_static"]).any()):
        skipped["hub_loads.png"] = "no hub_loads records with estimates"
        skipped["hub_load_errors.png"] = "no hub_loads records with estimates"
        return
    plots.append(plot_hub_loads(d, out))
    if d.H_truth is not None and np.isfinite(d.H_truth).any():
        plots.append(plot_hub_errors(d, out, hub_s))
    else:
        skipped["hub_load_errors.png"] = "no truth (give --truth)" if d.truth is None else \
            "no record matched a truth sample"


def write_report(cfg: RigConfig, results: str | Path, truth: str | Path | None,
                 out: str | Path, units: str = "si",
                 read_truth: Callable[[Path], dict] | None = None) -> Report:
    """`rsra report`: load, align, compute, plot, summarise. ``truth`` needs ``read_truth``."""
    rec = load_records(results)
    if truth and read_truth is None:  # (the report does not import the simulator's reader)
        raise ReportError(f"--truth {truth}: no reader for the truth file given (read_truth)")
    tr = load_truth(truth, read_truth) if truth and read_truth is not None else None
    return build_report(cfg, rec, tr, out, units, truth_name=str(truth) if truth else None)
