"""The loads survey of one recording (docs/user-guide.md "Loads survey", docs/cli.md `rsra
survey`): test points, and per point and axis the quantities of estimator/survey.py as a long
table (``test_point, t_start, t_end, axis, quantity, value, sigma, unit, estimate, note``)
with a Markdown + PNG report.

Which estimate each quantity uses: ``mean``, ``std``, ``min``, ``max``, ``alternating``,
``alternating_max``, the harmonics the load filter models (``[filter] harmonics``) and the
rainflow counts and DELs come from the filtered ``H`` with ``sigma_filter`` (coloured over the
filter's time constant) and the angles' covariance; the harmonics the filter does not model
from ``H_static`` with the static noise bound (white) and the same angle error. The survey is
a function of arrays (:class:`SurveyData`, :func:`survey`) so that a campaign can call it per
recording.
"""
from __future__ import annotations

import csv
import io
import math
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rsra.config.units import axis_units, to_units
from rsra.daq.runtime.persistence import AtomicOutput, save_figure, write_text_atomic
from rsra.estimator import survey as num
from rsra.estimator.noise_budget import AXES

SURVEY_FILES = ("survey.parquet", "survey.csv", "survey.md", "survey_harmonics.png",
                "survey_loads.png")
COLUMNS = ("recording", "test_point", "t_start", "t_end", "axis", "quantity", "value", "sigma", "unit",
           "estimate", "note")
MARK_NAME_MAX = 200  # characters of a test point's name (marks, TOML)
TEST_POINTS_MAX = 10_000
MIN_POINT_S = 1.0  # a test point found in the recording is at least this long
NO_AZIMUTH = ("no measured azimuth in this test point (no rotor-speed node sending it, or "
              "fewer than one whole revolution measured): never computed from a nominal Ω")


class SurveyError(ValueError):
    """An input the survey cannot use (one line naming it and the fix)."""


@dataclass(frozen=True)
class TestPoint:
    """A stretch of a recording surveyed as one condition, in the samples' own time (``t``)."""

    name: str
    start: float
    end: float
    source: str  # "marks", "file", "scenario", "transient"


@dataclass(frozen=True)
class AngleState:
    """The angles in force from sample ``from_seq`` on, and their covariance (model order)."""

    from_seq: int
    alpha: np.ndarray
    P: np.ndarray


@dataclass
class SurveyData:
    """One recording's hub-load samples and what their errors need (arrays of N samples)."""

    t: np.ndarray
    seq: np.ndarray
    H: np.ndarray  # (N, 6) SI, in ``frame``
    H_static: np.ndarray
    sigma_angles: np.ndarray
    sigma_filter: np.ndarray
    transient: np.ndarray  # bool (N,)
    azimuth: np.ndarray  # rad (NaN: none)
    T: np.ndarray  # (N, 7) cell loads (NaN: none)
    angles: list[AngleState] = field(default_factory=list)
    frame: str = "body"


class RecordCollector:
    """Builds :class:`SurveyData` from published records (``key, payload``): a results JSONL
    or a replay's sink. Keeps only the numbers the survey needs."""

    def __init__(self, angle_names: Sequence[str]) -> None:
        #: the model's angle names: an angles record over others is not used
        self.angle_names = list(angle_names)
        self.hub: dict[str, list] = {k: [] for k in ("t", "seq", "H", "H_static", "sa", "sf",
                                                       "tr")}
        #: seq -> (azimuth, T) from the channels records
        self.channels: dict[int, tuple[float, list[float]]] = {}
        self.angles: list[AngleState] = []
        self.frames: set[str] = set()

    def add(self, key: str, rec: dict) -> None:
        if key == "hub_loads":
            h = self.hub
            h["t"].append(_num(rec.get("t")))
            h["seq"].append(int(rec["seq"]))
            h["H"].append(_vec(rec.get("H"), 6))
            h["H_static"].append(_vec(rec.get("H_static"), 6))
            h["sa"].append(_vec(rec.get("sigma_angles"), 6))
            h["sf"].append(_vec(rec.get("sigma_filter"), 6))
            h["tr"].append("transient" in (rec.get("flags") or ()))
            self.frames.add(str(rec.get("frame") or "body"))
        elif key == "channels":
            self.channels[int(rec["seq"])] = (_num(rec.get("azimuth")), _vec(rec.get("T"), 7))
        elif key == "angles":
            self._angles(rec)

    def _angles(self, rec: dict) -> None:
        if list(rec.get("names") or ()) != self.angle_names or rec.get("P") is None:
            return
        start = rec.get("applies_from_seq")
        alpha = rec.get("alpha_all") if rec.get("initial") else rec.get("alpha")
        self.angles.append(AngleState(-1 if start is None else int(start),
                                      np.asarray(_vec(alpha, len(self.angle_names))),
                                      np.asarray(rec["P"], float)))

    def finish(self) -> SurveyData:
        h = self.hub
        if not h["seq"]:
            raise SurveyError("no hub_loads records; fix: give a recording, or the JSONL "
                              "written by `rsra replay --out` / `rsra run --out`")
        if len(self.frames) > 1:
            raise SurveyError(f"hub_loads records in more than one frame ({sorted(self.frames)})")
        seq = np.asarray(h["seq"], np.int64)
        ch = [self.channels.get(int(s), (math.nan, [math.nan] * 7)) for s in seq]
        return SurveyData(
            t=np.asarray(h["t"], float), seq=seq,
            H=np.asarray(h["H"], float).reshape(-1, 6),
            H_static=np.asarray(h["H_static"], float).reshape(-1, 6),
            sigma_angles=np.asarray(h["sa"], float).reshape(-1, 6),
            sigma_filter=np.asarray(h["sf"], float).reshape(-1, 6),
            transient=np.asarray(h["tr"], bool),
            azimuth=np.asarray([c[0] for c in ch], float),
            T=np.asarray([c[1] for c in ch], float).reshape(-1, 7),
            angles=sorted(self.angles, key=lambda a: a.from_seq),
            frame=self.frames.pop() if self.frames else "body")


def _vec(x, n: int) -> list[float]:
    if x is None or isinstance(x, (str, bytes, dict)):
        return [math.nan] * n
    out = [math.nan if v is None else float(v) for v in list(x)[:n]]
    return out + [math.nan] * (n - len(out))


def _num(x) -> float:
    return math.nan if x is None else float(x)


def load_results(path: Path, angle_names: Sequence[str]) -> SurveyData:
    from rsra.daq.analysis.export import ExportError, read_records

    col = RecordCollector(angle_names)
    try:
        for key, rec in read_records(path):
            col.add(key, rec)
    except ExportError as e:
        raise SurveyError(str(e)) from None
    except (KeyError, TypeError, ValueError) as e:
        raise SurveyError(f"{path}: a record without a valid {e} field (docs/telemetry.md §2); "
                          "fix: give the JSONL written by `rsra replay --out`") from None
    return col.finish()


def is_dataset(path: Path) -> bool:
    """A Parquet dataset: a campaign's ``<key>/recording=<id>/*.parquet`` folders, or one
    recording's ``rsra export --parquet`` folder (``hub_loads.parquet``, …)."""
    return path.is_dir() and ((path / "hub_loads").is_dir() or (path / "hub_loads.parquet")
                              .is_file())


def dataset_sources(path: Path) -> dict[str, Path]:
    """A campaign dataset's recordings whose tables are valid (the ``ok`` rows of its
    manifest.parquet) and the folder or file each was read from; {} without a manifest."""
    import pyarrow.parquet as pq

    m = path / "manifest.parquet"
    if not m.is_file():
        return {}
    try:
        rows = pq.read_table(m, columns=["recording", "source", "status"]).to_pylist()
    except Exception as e:  # noqa: BLE001 - any unreadable manifest is the user's input
        raise SurveyError(f"{m}: not a campaign manifest ({' '.join(str(e).split())}); fix: "
                          "give the dataset `rsra campaign run` wrote") from None
    return {str(r["recording"]): Path(str(r["source"])) for r in rows
            if r["status"] == "ok" and r["recording"] and r["source"]}


def load_dataset(path: Path, angle_names: Sequence[str]) -> dict[str, SurveyData]:
    """Per recording, its :class:`SurveyData` from the Parquet tables of `rsra export
    --parquet` (columns ``H.X``, ``T.A``, …; docs/user-guide.md): ``hub_loads`` (required),
    ``channels`` (the azimuth, the cell loads) and ``angles`` (the covariance in force)."""
    import pyarrow.parquet as pq

    def tables(key: str) -> dict[str, object]:
        if (path / f"{key}.parquet").is_file():
            return {path.name: pq.read_table(path / f"{key}.parquet")}
        out: dict[str, object] = {}
        for part in sorted((path / key).glob("recording=*")) if (path / key).is_dir() else []:
            out[part.name.split("=", 1)[1]] = pq.read_table(part)
        return out

    try:
        hub, ch, ang = tables("hub_loads"), tables("channels"), tables("angles")
    except Exception as e:  # noqa: BLE001 - any unreadable file is the user's input problem
        raise SurveyError(f"{path}: not a readable Parquet dataset ({e}); fix: give the folder "
                          "written by `rsra export --parquet` or a campaign") from None
    ok = dataset_sources(path) if (path / "manifest.parquet").is_file() else None
    if ok is not None:  # a campaign's: a recording's tables are those of its ok row
        hub = {rid: table for rid, table in hub.items() if rid in ok}
    if not hub:
        raise SurveyError(f"{path}: no hub_loads table; fix: give the folder written by "
                          "`rsra export --parquet` or a campaign")
    return {rid: _from_tables(table, ch.get(rid), ang.get(rid), angle_names, path)
            for rid, table in hub.items()}


def _column(table, name: str, n: int) -> np.ndarray:
    if name not in table.column_names:
        return np.full(n, np.nan)
    return np.asarray(table.column(name).to_numpy(zero_copy_only=False), float)


def _from_tables(hub, ch, ang, angle_names: Sequence[str], path: Path) -> SurveyData:
    n = hub.num_rows
    if "seq" not in hub.column_names or "t" not in hub.column_names:
        raise SurveyError(f"{path}: hub_loads without seq and t columns; fix: give the folder "
                          "written by `rsra export --parquet`")

    def six(prefix: str) -> np.ndarray:
        return np.column_stack([_column(hub, f"{prefix}.{a}", n) for a in AXES])

    seq = np.asarray(hub.column("seq").to_numpy(zero_copy_only=False), np.int64)
    flags = hub.column("flags").to_pylist() if "flags" in hub.column_names else [None] * n
    azimuth, T = np.full(n, np.nan), np.full((n, 7), np.nan)
    if ch is not None and "seq" in ch.column_names:
        cseq = np.asarray(ch.column("seq").to_numpy(zero_copy_only=False), np.int64)
        where = {int(q): i for i, q in enumerate(cseq)}
        idx = np.array([where.get(int(q), -1) for q in seq])
        ok = idx >= 0
        az = _column(ch, "azimuth", ch.num_rows)
        cells = [c for c in ch.column_names if c.startswith("T.")][:7]
        Tc = np.column_stack([_column(ch, c, ch.num_rows) for c in cells]) if len(cells) == 7 \
            else np.full((ch.num_rows, 7), np.nan)
        azimuth[ok], T[ok] = az[idx[ok]], Tc[idx[ok]]
    col = RecordCollector(angle_names)
    for rec in ang.to_pylist() if ang is not None else []:
        col.add("angles", rec)
    frames = set(hub.column("frame").to_pylist()) if "frame" in hub.column_names else {"body"}
    return SurveyData(t=_column(hub, "t", n), seq=seq, H=six("H"), H_static=six("H_static"),
                      sigma_angles=six("sigma_angles"), sigma_filter=six("sigma_filter"),
                      transient=np.array(["transient" in (f or ()) for f in flags], bool),
                      azimuth=azimuth, T=T, angles=sorted(col.angles, key=lambda a: a.from_seq),
                      frame=str(frames.pop() or "body") if len(frames) == 1 else "body")


# ---------------------------------------------------------------------------------------------
# test points


def points_from_transient(t: np.ndarray, transient: np.ndarray,
                          min_s: float = MIN_POINT_S) -> list[TestPoint]:
    """The held stretches between the edges of the ``transient`` flag (each at least
    ``min_s`` long), named ``held 1``, ``held 2``, …"""
    out: list[TestPoint] = []
    held = ~np.asarray(transient, bool)
    n = len(held)
    i = 0
    while i < n:
        if not held[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and held[j + 1]:
            j += 1
        if t[j] - t[i] >= min_s:
            out.append(TestPoint(f"held {len(out) + 1}", float(t[i]), float(t[j]), "transient"))
        i = j + 1
    return out


def points_from_marks(marks: Sequence[dict], t_end: float) -> list[TestPoint]:
    """Operator marks (marks.jsonl: ``{"t": …, "name": …}`` or ``{"t": …, "end": true}``): a
    mark opens a test point that lasts until the next mark, an end mark or the recording's
    end."""
    out: list[TestPoint] = []
    ms = sorted((m for m in marks if math.isfinite(float(m.get("t", math.nan)))),
                key=lambda m: float(m["t"]))
    for i, m in enumerate(ms):
        if m.get("end"):
            continue
        stop = float(ms[i + 1]["t"]) if i + 1 < len(ms) else float(t_end)
        if stop > float(m["t"]):
            out.append(TestPoint(str(m.get("name") or f"mark {i + 1}"), float(m["t"]), stop,
                                 "marks"))
    return out


def read_marks(path: Path) -> list[dict]:
    """marks.jsonl of a recording folder; a line that is not a valid mark is named."""
    import json

    out = []
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SurveyError(f"{path}: cannot read ({e}); fix: check the file") from None
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            m = json.loads(line)
            float(m["t"])
        except (ValueError, KeyError, TypeError):
            raise SurveyError(f"{path} line {n}: not a mark ({{\"t\": …, \"name\": …}}); "
                              "fix: remove or correct the line") from None
        out.append(m)
    return out


SETTLE_S = 0.5  # after a ramp or a manoeuvre, before a held condition's test point starts
START_S = 2.0  # the filter's start from a zero state: the first test point starts after it


def points_from_schedule(sc, t_sim: np.ndarray, t_samples: np.ndarray) -> list[TestPoint]:
    """The simulator's held conditions (``sc.loads``: from ``SETTLE_S`` after the ramp into
    one to the start of the ramp out of it; manoeuvres cut out) and its manoeuvres as test
    points, each cycle of the schedule on its own. ``t_sim``: the truth's simulated time of
    every sample, ``t_samples`` the samples' own time (the truth's SYNC time). ``sc`` is a
    scenario of the simulator (sim_bus.scenarios.Scenario: duck-typed here)."""
    ts = np.asarray(t_sim, float)
    if not len(ts):
        return []

    def at(x: float) -> float:
        return float(np.interp(x, ts, t_samples))

    L = sc.loads
    ramp = L.ramp_s if len(L.conditions) > 1 else 0.0
    cycles = int(math.ceil((ts[-1] + 1e-9) / sc.duration_s))
    out = []
    for c in range(cycles):
        c0 = c * sc.duration_s
        tag = f" #{c + 1}" if cycles > 1 else ""
        cuts = sorted((c0 + m.start_s, c0 + m.start_s + m.duration_s) for m in sc.manoeuvres)
        for i in range(len(L.conditions)):
            lo = max(c0 + i * L.hold_s + (SETTLE_S if i or c else 0.0), START_S)
            pieces = [(lo, c0 + (i + 1) * L.hold_s - ramp)]
            for a, b in cuts:
                pieces = [q for p in pieces for q in ((p[0], min(p[1], a)),
                                                     (max(p[0], b + SETTLE_S), p[1]))]
            pieces = [q for q in pieces if q[1] - q[0] >= MIN_POINT_S]
            for j, (a, b) in enumerate(pieces):
                name = f"condition {i + 1}{tag}" + (f".{j + 1}" if len(pieces) > 1 else "")
                out.append(TestPoint(name, at(a), at(b), "scenario"))
        for j, m in enumerate(sc.manoeuvres):
            a, b = c0 + m.start_s, c0 + m.start_s + m.duration_s
            out.append(TestPoint(f"manoeuvre {j + 1}{tag}", at(a), at(b), "scenario"))
    end = float(np.nanmax(t_samples))
    return sorted((tp for tp in out if tp.start < end), key=lambda tp: tp.start)


def points_from_toml(path: Path, t0: float) -> list[TestPoint]:
    """``[[test_point]]`` tables with ``name``, ``start``, ``end`` (s); with top-level
    ``time = "from_start"`` the times count from the recording's first sample (``t0``),
    else they are the samples' own time (``t``)."""
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise SurveyError(f"--test-points {path}: cannot read ({e}); fix: give a TOML "
                          "file") from None
    except tomllib.TOMLDecodeError as e:
        raise SurveyError(f"--test-points {path}: not TOML ({e}); fix: correct the "
                          "file") from None
    base = raw.get("time", "absolute")
    if base not in ("absolute", "from_start"):
        raise SurveyError(f"--test-points {path}: time = {base!r}; fix: \"absolute\" or "
                          "\"from_start\"")
    tps = raw.get("test_point")
    if not isinstance(tps, list) or not tps or len(tps) > TEST_POINTS_MAX:
        raise SurveyError(f"--test-points {path}: no [[test_point]] tables (or more than "
                          f"{TEST_POINTS_MAX}); fix: write [[test_point]] name = \"hover\" "
                          "start = 10.0 end = 20.0")
    off = t0 if base == "from_start" else 0.0
    out = []
    for i, tp in enumerate(tps, 1):
        try:
            name = str(tp["name"])[:MARK_NAME_MAX]
            start, end = float(tp["start"]), float(tp["end"])
        except (KeyError, TypeError, ValueError):
            raise SurveyError(f"--test-points {path}: test_point {i} needs name, start and "
                              "end (numbers, s); fix: complete it") from None
        if not (math.isfinite(start) and math.isfinite(end) and end > start):
            raise SurveyError(f"--test-points {path}: test_point {i} ({name!r}) start "
                              f"{start} end {end}; fix: finite times with end > start")
        out.append(TestPoint(name, start + off, end + off, "file"))
    return out


# ---------------------------------------------------------------------------------------------
# the survey


@dataclass(frozen=True)
class SurveyRig:
    """What the survey takes from the rig configuration."""

    blades: int
    modelled: tuple[int, ...]  # harmonic orders the load filter models
    dt: float
    time_constant_s: float
    bound: np.ndarray  # (6,) the static noise bound (SI, the records' frame)
    angle_names: tuple[str, ...]
    #: alpha -> A = R⁻¹ ∂S/∂α (6, 7, 14) in the records' frame
    sensitivity: object = None
    #: (6,) a coherent model error of the rotor-frequency content per axis: the unmeasured
    #: angular inertial loads (``identification.moment_floor_Nm`` on L, M, N; 0 on X, Y, Z)
    model_sigma: np.ndarray = field(default_factory=lambda: np.zeros(6))


@dataclass(frozen=True)
class SurveyOptions:
    slopes: tuple[float, ...] = (4.0, 10.0)
    reference_cycles: float | None = None  # None: 1 per second of the test point
    draws: int = 50
    units: str = "si"
    seed: int = 0
    #: per axis the rig's limit (SI; NaN: none): ``peak_fraction_of_limit``
    limits: tuple[float, ...] = (math.nan,) * 6


def moment_model_sigma(moment_floor: float) -> np.ndarray:
    """SurveyRig.model_sigma from the configured model error of the moment rows
    (``identification.moment_floor_Nm``: the angular inertial loads one accelerometer does
    not measure); the forces have none."""
    return np.array([0.0, 0.0, 0.0, moment_floor, moment_floor, moment_floor])


def _angle_state(data: SurveyData, seq0: int, seq1: int) -> AngleState | None:
    """The angles in force over [seq0, seq1]: of those in force at some sample, the one
    with the largest covariance (trace)."""
    cands = []
    before = [a for a in data.angles if a.from_seq <= seq0]
    if before:
        cands.append(before[-1])
    cands += [a for a in data.angles if seq0 < a.from_seq <= seq1]
    if not cands:
        return None
    return max(cands, key=lambda a: float(np.trace(a.P)))


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    result: np.ndarray = V * np.sqrt(np.clip(lam, 0.0, None))[None, :]
    return result


def _models(data: SurveyData, rig: SurveyRig, idx: np.ndarray, k: int,
            angle_sens: np.ndarray | None) -> tuple[num.ErrorModel, num.ErrorModel]:
    """(the error model of H, of H_static) on axis k over the samples ``idx``."""
    sa = np.nan_to_num(data.sigma_angles[idx, k], nan=0.0)
    sf = data.sigma_filter[idx, k]
    sf = np.where(np.isfinite(sf), sf, rig.bound[k])
    rho = math.exp(-rig.dt / rig.time_constant_s)
    T = data.T[idx]
    measured = num.unwrap_azimuth(data.azimuth[idx])
    fin = np.isfinite(measured)
    if fin.any() and not fin.all():  # the error's phase across a missing azimuth: interpolated
        i = np.arange(len(fin))
        measured = np.interp(i, i[fin], measured[fin])
    bands = (0,) + rig.modelled if fin.any() else (0,)
    psi = measured if fin.any() else None
    white = np.full(len(idx), rig.bound[k])
    if angle_sens is not None and np.isfinite(T).all(axis=1).any():
        sens = angle_sens[k]  # (σ_angles bounds the samples without cell loads)
        return (num.ErrorModel(sf, rho, T, sens, sigma_angles=sa, bands=bands, psi=psi),
                num.ErrorModel(white, 0.0, T, sens, sigma_angles=sa))
    return (num.ErrorModel(sf, rho, sigma_angles=sa, bands=bands, psi=psi),
            num.ErrorModel(white, 0.0, sigma_angles=sa))


def survey(data: SurveyData, points: Sequence[TestPoint], rig: SurveyRig,
           opts: SurveyOptions, recording: str = "") -> list[dict]:
    """The long table's rows (SI or US units per ``opts.units``) for every test point of one
    recording (named in the ``recording`` column: a campaign surveys each of its own)."""
    rows: list[dict] = []
    rng = np.random.default_rng(opts.seed)
    for tp in points:
        rows += survey_point(data, tp, rig, opts, rng)
    for r in rows:
        r["recording"] = recording
    return rows


def survey_point(data: SurveyData, tp: TestPoint, rig: SurveyRig, opts: SurveyOptions,
                 rng: np.random.Generator) -> list[dict]:
    sel = np.flatnonzero((data.t >= tp.start) & (data.t <= tp.end)
                         & np.isfinite(data.H).all(axis=1))
    if len(sel) < 3:
        return [_row(tp, "-", "samples", float(len(sel)), math.nan, "", "H",
                     "fewer than 3 samples with H in the test point: nothing surveyed")]
    st = _angle_state(data, int(data.seq[sel[0]]), int(data.seq[sel[-1]]))
    angle_sens = None
    if st is not None and rig.sensitivity is not None:
        A = rig.sensitivity(st.alpha)  # type: ignore[operator]
        L = _sqrt_psd(st.P)
        angle_sens = np.einsum("kij,jl->kil", A, L)
    psi = num.unwrap_azimuth(data.azimuth[sel])
    revs = num.whole_revolutions(psi)  # (a sample without azimuth: its turn left out)
    orders = list(range(1, rig.blades + 1))
    duration = float(data.t[sel[-1]] - data.t[sel[0]]) + rig.dt
    n_ref = opts.reference_cycles or duration
    units = axis_units(opts.units)
    rows: list[dict] = []
    for k, ax in enumerate(AXES):
        scale = float(to_units(np.eye(6)[k], opts.units)[k])
        unit = units[k]
        mH, mS = _models(data, rig, sel, k, angle_sens)
        y = data.H[sel, k]

        def add(q: str, v: num.Value | None, est: str = "H", note: str = "",
                u: str = unit, s: float = scale) -> None:
            rows.append(_row(tp, ax, q, math.nan if v is None else v.value * s,
                             math.nan if v is None else v.sigma * s, u, est, note))
        ms = float(rig.model_sigma[k])
        mean, std = num.mean_std(y, mH)
        add("mean", mean)
        add("std", _widen(std, ms))
        lo, hi = _widen(num.peak(y, mH, "min"), ms), _widen(num.peak(y, mH, "max"), ms)
        add("min", lo)
        add("max", hi)
        limit = opts.limits[k]
        if math.isfinite(limit):
            top = hi if abs(hi.value) >= abs(lo.value) else lo
            add("peak_fraction_of_limit", num.Value(abs(top.value) / limit, top.sigma / limit),
                u="fraction", s=1.0, note=f"limit {limit * scale:g} {unit}")
        hrows, present = _harmonic_rows(data, tp, rig, sel, k, psi, revs, orders, mH, mS, scale,
                                        unit)
        # the alternating load from the fit of the harmonics present over the point (> 3σ;
        # 1/rev at least): a fit of absent ones would add their noise to every peak-to-peak
        alt = (num.alternating(data.H_static[sel, k], psi, revs, present or [1], mS, ms,
                               opts.draws, rng) if revs else None)
        est = (f"H_static, per-revolution fit of the harmonics present, bias from {opts.draws} "
               "Monte Carlo draws taken off")
        add("alternating", alt[0] if alt else None, est, "" if alt else NO_AZIMUTH)
        add("alternating_max", alt[1] if alt else None, est, "" if alt else NO_AZIMUTH)
        rows += hrows
        count, dels = num.fatigue(y, opts.slopes, n_ref)
        s_count, s_dels = num.fatigue_sigma(y, mH, opts.slopes, n_ref, opts.draws, rng)
        est = "H"
        est += f", σ from {opts.draws} Monte Carlo draws"
        add("rainflow_cycles", num.Value(count, s_count), est, u="cycles", s=1.0)
        for m, d, sd in zip(opts.slopes, dels, s_dels):  # (a range: twice the model error)
            add(f"del_m{m:g}", num.Value(d, math.hypot(sd, 2.0 * ms)), est,
                note=f"reference {n_ref:.6g} cycles, S-N slope {m:g}")
    return rows


def _widen(v: num.Value, model_sigma: float) -> num.Value:
    return num.Value(v.value, math.hypot(v.sigma, model_sigma))


def _harmonic_rows(data: SurveyData, tp: TestPoint, rig: SurveyRig, sel: np.ndarray, k: int,
                   psi: np.ndarray, revs: list, orders: list[int],
                   mH: num.ErrorModel, mS: num.ErrorModel, scale: float, unit: str
                   ) -> tuple[list[dict], list[int]]:
    """The harmonic rows of one axis, and the orders whose amplitude exceeds 3σ."""
    ax = AXES[k]
    rows: list[dict] = []
    if not revs:
        for o in orders:
            rows.append(_row(tp, ax, f"h{o}_amplitude", math.nan, math.nan, unit, "", NO_AZIMUTH))
            rows.append(_row(tp, ax, f"h{o}_phase_deg", math.nan, math.nan, "deg", "",
                             NO_AZIMUTH))
        return rows, []
    modelled = [o for o in orders if o in rig.modelled]
    other = [o for o in orders if o not in rig.modelled]
    found: dict[int, tuple[num.Harmonic, str]] = {}
    measured = np.isfinite(psi)  # the least squares on the samples with an azimuth
    if modelled:
        for h in num.harmonics(data.H[sel, k][measured], psi[measured], modelled,
                               mH.subset(measured), float(rig.model_sigma[k])):
            found[h.order] = (h, "H")
    ys = data.H_static[sel, k]
    ok = np.isfinite(ys) & measured
    if other and ok.sum() > 2 * len(orders) + 1:
        mS_ok = mS.subset(ok)
        # H_static's error near an order it does not model, as the revolutions show it
        scatter = num.revolution_scatter(ys, psi, revs, orders, other)
        # fitted with every order (a large 1/rev or N_b/rev left out of the fit would leak
        # into the others over a point of few revolutions); the modelled ones come from H
        for h in num.harmonics(ys[ok], psi[ok], orders, mS_ok, float(rig.model_sigma[k]),
                               scatter):
            if h.order in other:
                found[h.order] = (h, "H_static")
    for o in orders:
        if o not in found:
            note = "no H_static samples in the test point"
            rows.append(_row(tp, ax, f"h{o}_amplitude", math.nan, math.nan, unit, "", note))
            rows.append(_row(tp, ax, f"h{o}_phase_deg", math.nan, math.nan, "deg", "", note))
            continue
        h, est = found[o]
        note = "" if est == "H" else "not modelled by the load filter: from H_static"
        rows.append(_row(tp, ax, f"h{o}_amplitude", h.amplitude * scale,
                         h.amplitude_sigma * scale, unit, est, note))
        rows.append(_row(tp, ax, f"h{o}_phase_deg", h.phase_deg, h.phase_sigma_deg, "deg", est,
                         note))
    present = [o for o, (h, _e) in sorted(found.items()) if h.amplitude > 3 * h.amplitude_sigma]
    return rows, present


def _row(tp: TestPoint, axis: str, q: str, v: float, s: float, unit: str, est: str,
         note: str) -> dict:
    return {"test_point": tp.name, "t_start": tp.start, "t_end": tp.end, "axis": axis,
            "quantity": q, "value": v, "sigma": s, "unit": unit, "estimate": est, "note": note}


# ---------------------------------------------------------------------------------------------
# outputs


def write_table(rows: Sequence[dict], out: Path) -> None:
    """DIR/survey.parquet and DIR/survey.csv, each written atomically."""
    import pyarrow.parquet as pq

    table = table_of(rows, COLUMNS)
    dst = AtomicOutput(out / "survey.parquet", "wb")
    try:
        pq.write_table(table, dst.open())
        dst.commit()
    finally:
        dst.discard()
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow(["" if _cell(r[c]) is None else r[c] for c in COLUMNS])
    write_text_atomic(out / "survey.csv", buf.getvalue())


def table_of(rows: Sequence[dict], columns: Sequence[str]):
    """The rows as a pyarrow Table of ``columns`` (times, values and σ float64, NaN as
    null; the rest strings): the same schema whether or not a column has a value."""
    import pyarrow as pa

    types = {"t_start": pa.float64(), "t_end": pa.float64(), "value": pa.float64(),
             "sigma": pa.float64()}
    return pa.table({c: pa.array([_cell(r.get(c)) for r in rows],
                                 type=types.get(c, pa.string())) for c in columns})


def _cell(v):
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _fmt(v: float, s: float) -> str:
    if not math.isfinite(v):
        return "—"
    return f"{v:.4g} ± {s:.2g}" if math.isfinite(s) else f"{v:.4g}"


def markdown(rows: Sequence[dict], points: Sequence[TestPoint], rig: SurveyRig,
             opts: SurveyOptions, source: str) -> str:
    by = {(r["test_point"], r["axis"], r["quantity"]): r for r in rows}
    units = axis_units(opts.units)
    lines = [f"# Loads survey of {source}", "",
             f"{len(points)} test points; values ± 1 σ ({opts.units.upper()} units). Mean, "
             "std, min, max, alternating and the harmonics the load filter models "
             f"({', '.join(f'{o}/rev' for o in rig.modelled)}) from the filtered H; the other "
             "harmonics from H_static; rainflow counts and DELs from H with σ from "
             f"{opts.draws} Monte Carlo draws. Phases: degrees from the measured azimuth's "
             "zero, h(ψ) = A cos(kψ − φ).", "",
             "| test point | source | t_start | t_end |", "|---|---|---|---|"]
    lines += [f"| {tp.name} | {tp.source} | {tp.start:.3f} | {tp.end:.3f} |" for tp in points]
    orders = range(1, rig.blades + 1)
    for k, ax in enumerate(AXES):
        lines += ["", f"## {ax} [{units[k]}]", "",
                  "| test point | mean | alternating | alternating_max | min | max | "
                  + " | ".join(f"h{o} amplitude (phase °)" for o in orders) + " |",
                  "|---" * (6 + len(orders)) + "|"]
        for tp in points:
            def g(q: str) -> str:
                r = by.get((tp.name, ax, q))
                return "—" if r is None else _fmt(r["value"], r["sigma"])
            cells = [g(q) for q in ("mean", "alternating", "alternating_max", "min", "max")]
            cells += [f"{g(f'h{o}_amplitude')} ({g(f'h{o}_phase_deg')})" for o in orders]
            lines.append(f"| {tp.name} | " + " | ".join(cells) + " |")
    notes = sorted({r["note"] for r in rows if r["note"] and "S-N" not in r["note"]})
    if notes:
        lines += ["", "Notes:", ""] + [f"* {n}" for n in notes]
    return "\n".join(lines) + "\n"


def plot(rows: Sequence[dict], points: Sequence[TestPoint], rig: SurveyRig,
         opts: SurveyOptions, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {(r["test_point"], r["axis"], r["quantity"]): r for r in rows}
    units = axis_units(opts.units)
    names = [tp.name for tp in points]
    x = np.arange(len(names))

    def get(name: str, ax: str, q: str) -> tuple[float, float]:
        r = by.get((name, ax, q))
        return (math.nan, math.nan) if r is None else (r["value"], r["sigma"])

    orders = list(range(1, rig.blades + 1))
    fig, axs = plt.subplots(3, 2, figsize=(12, 10), squeeze=False)
    width = 0.8 / max(len(orders), 1)
    for k, ax in enumerate(AXES):
        a = axs[k // 2][k % 2]
        for j, o in enumerate(orders):
            v = np.array([get(n, ax, f"h{o}_amplitude") for n in names]).reshape(-1, 2)
            a.bar(x + (j - (len(orders) - 1) / 2) * width, v[:, 0], width, yerr=v[:, 1],
                  capsize=2, label=f"{o}/rev")
        a.set_title(f"{ax}: harmonic amplitudes ± 1σ")
        a.set_ylabel(units[k])
        a.set_xticks(x, names, rotation=30, ha="right", fontsize=7)
    axs[0][0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "survey_harmonics.png", dpi=90)
    plt.close(fig)
    # per axis a row: the steady load on the left, the alternating on the right, each on
    # its own scale (a thrust's mean would flatten its alternating load's bars)
    fig, axs = plt.subplots(6, 2, figsize=(12, 18), squeeze=False)
    for k, ax in enumerate(AXES):
        for col, (q, label, colour) in enumerate(
                (("mean", "steady (mean)", "C0"),
                 ("alternating", "alternating (mean half peak-to-peak per rev)", "C1"))):
            a = axs[k][col]
            v = np.array([get(n, ax, q) for n in names]).reshape(-1, 2)
            a.errorbar(x, v[:, 0], yerr=v[:, 1], fmt="o", capsize=3, color=colour)
            if q == "alternating" and not np.isfinite(v[:, 0]).any():
                a.text(0.5, 0.5, "no measured azimuth: absent", transform=a.transAxes,
                       ha="center", va="center", color="0.4")
            if q == "alternating":  # (a zero line would flatten a thrust's mean and its bars)
                a.axhline(0.0, color="0.7", lw=0.5)
            a.set_title(f"{ax}: {label} ± 1σ", fontsize=9)
            a.set_ylabel(units[k])
            a.set_xticks(x, names, rotation=30, ha="right", fontsize=7)
            a.set_xlim(-0.5, len(names) - 0.5)
    fig.tight_layout()
    save_figure(fig, out / "survey_loads.png", dpi=90)
    plt.close(fig)


def write_outputs(rows: Sequence[dict], points: Sequence[TestPoint], rig: SurveyRig,
                  opts: SurveyOptions, out: Path, source: str) -> None:
    write_table(rows, out)
    write_report(rows, points, rig, opts, out, source)


def write_report(rows: Sequence[dict], points: Sequence[TestPoint], rig: SurveyRig,
                 opts: SurveyOptions, out: Path, source: str) -> None:
    """survey.md and the two PNG charts in ``out``."""
    write_text_atomic(out / "survey.md", markdown(rows, points, rig, opts, source))
    plot(rows, points, rig, opts, out)


def report_folder(recording: str) -> str:
    """A recording id as a folder name of its own report (a dataset's ids are untrusted: no
    separators, no leading dot)."""
    import re

    return "r_" + re.sub(r"[^A-Za-z0-9_.-]", "_", recording)[:120]


def write_recording_reports(rows: Sequence[dict], points: Sequence[TestPoint],
                            rig: SurveyRig, opts: SurveyOptions, out: Path) -> list[Path]:
    """Per recording of a dataset survey, its own report (survey.md and the PNG charts) in
    ``out/recordings/<id>/``; its test points are named ``<recording>: <name>``."""
    folders = []
    for rid in sorted({str(r["recording"]) for r in rows}):
        mine = [tp for tp in points if tp.name.startswith(f"{rid}: ")]
        sub = out / "recordings" / report_folder(rid)
        sub.mkdir(parents=True, exist_ok=True)
        write_report([r for r in rows if r["recording"] == rid], mine, rig, opts, sub,
                     f"recording {rid}")
        folders.append(sub)
    return folders


def filter_points(points: Iterable[TestPoint], t: np.ndarray) -> list[TestPoint]:
    """The test points that overlap the samples (the others name nothing to survey)."""
    if not len(t):
        return []
    lo, hi = float(np.nanmin(t)), float(np.nanmax(t))
    return [tp for tp in points if tp.end >= lo and tp.start <= hi]
