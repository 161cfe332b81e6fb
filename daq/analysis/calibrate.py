"""Off-line known-load calibration from recordings (report Phase I and Appendix C; model.md §7
known-load mode; docs/cli.md §9 ``rsra calibrate``).

Recordings made with the reference balance on the bus are read through the same reader as the
live service (:func:`daq.replay.replay`), the samples whose load cells, accelerometers and
balance are present and unflagged are kept, the configured content filter runs alike on
``x = [z, T, H, q]`` (so the balance ``I = S T + R₀ H + D q`` of Eq 1.1 still holds in the
filtered data), its start-up transient is not scored, and one batch identification minimises
the effective-variance likelihood of model §7 with a weak prior from the configured (or a saved)
starting values. The result carries the estimates, their Cramér–Rao bounds (conventional and
coloured-residual corrected), the residuals against what the sensor noise explains, the
information (determined and undetermined directions, condition number), a physical-plausibility
check, and a TOML fragment to adopt into the rig config.

Pure library: no printing; :mod:`daq.commands.calibrate` is the command line.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import sosfilt

from rsra.daq.bus.assembler import Sample
from rsra.config.rig import RigConfig
from rsra.estimator.balance import inertial_load_matrix
from rsra.estimator.content import KINDS, ContentFilter
from rsra.estimator.identification import (
    IdentificationResult,
    KnownLoadProblem,
    Parameterisation,
    levenberg_marquardt,
    parameter_names,
    scored_mask,
)
from rsra.estimator.noise_budget import AXES
from rsra.estimator.posterior import SIGMA_MAX_OTHER_FRACTION, determined_directions

# Weak priors of the non-angle parameters (the angles take identification.prior_sigma_deg):
# half the plausibility windows below, so the prior alone never pulls an estimate back inside
# them and the data decide wherever they carry information.
PRIOR_SIGMA_POSITION_M = 0.1
PRIOR_SIGMA_MASS_FRACTION = 0.25
# Physical plausibility (flagged, never refused): deformation angles are small (the report's
# Eq A2 linearises them; RSRA's fuselage deflections are a few degrees), masses and inertias
# are positive and near the drawings, attach points near the drawings. The angles' range is
# the one physical range of the project, identification.angle_limit_deg (default 10°).
PLAUSIBLE_MASS_FRACTION = 0.5
PLAUSIBLE_POSITION_M = 0.2
# Residual RMS above this multiple of what the sensor noise explains is flagged as model error
# (a wrong balance, geometry or mass, an unmodelled load).
RESIDUAL_RATIO_FLAG = 2.0
DIRECTION_COMPONENT_MIN = 0.1  # components of an undetermined direction worth naming
IMPULSE_TIME_CONSTANTS = 20.0  # length of the impulse response used for the noise gain
CHUNK = 4096  # samples per array block while reading (bounded growth, no per-sample lists)


class CalibrationError(ValueError):
    """Recordings that cannot calibrate (no known loads, too little usable data, bad names)."""


# ------------------------------------------------------------------------------------------
# Parameters
# ------------------------------------------------------------------------------------------
def parse_params(spec: str, cfg: RigConfig) -> tuple[str, ...]:
    """``"angles"`` or a comma list of parameter names (``angles`` inside the list expands to
    the 14 angles), checked against :func:`estimator.identification.parameter_names`."""
    model = cfg.rig_model()
    allowed = parameter_names(model)
    angles = model.geometry.angle_names
    out: list[str] = []
    for raw in spec.split(","):
        name = raw.strip()
        if not name:
            continue
        items = angles if name == "angles" else (name,)
        for n in items:
            if n not in allowed:
                near = difflib.get_close_matches(n, allowed, n=3)
                hint = f" (did you mean {', '.join(near)}?)" if near else ""
                raise CalibrationError(
                    f"--params: unknown parameter {n!r}{hint}; use \"angles\" or names from: "
                    + ", ".join(allowed))
            if n in out:
                raise CalibrationError(f"--params: parameter {n!r} given twice")
            out.append(n)
    if not out:
        raise CalibrationError('--params: no parameter given; use "angles" or a comma list')
    return tuple(out)


def parameter_unit(name: str, cfg: RigConfig) -> str:
    if name in cfg.rig_model().geometry.angle_names:
        return "deg"
    if name.startswith("m_"):
        return "kg"
    if name.startswith("I_"):
        return "kg·m²"
    return "m"


def _display_scale(name: str, cfg: RigConfig) -> float:
    """SI (rad, m, kg) → display (deg, m, kg)."""
    return math.degrees(1.0) if name in cfg.rig_model().geometry.angle_names else 1.0


def prior_sigmas(names: Sequence[str], start: np.ndarray, cfg: RigConfig,
                 angle_sigma_rad: float) -> np.ndarray:
    """The weak prior σ of each parameter (SI)."""
    angles = cfg.rig_model().geometry.angle_names
    out = np.empty(len(names))
    for k, n in enumerate(names):
        if n in angles:
            out[k] = angle_sigma_rad
        elif n.startswith(("m_", "I_")):
            out[k] = PRIOR_SIGMA_MASS_FRACTION * abs(float(start[k]))
        else:
            out[k] = PRIOR_SIGMA_POSITION_M
    return out


# ------------------------------------------------------------------------------------------
# Data
# ------------------------------------------------------------------------------------------
@dataclass
class CalibrationData:
    """The content-filtered channels of the recordings, sample by sample (lost samples
    included as invalid), ready for :class:`KnownLoadProblem`."""

    z: np.ndarray  # (N, 6) inertial loads I (model §3), filtered
    T: np.ndarray  # (N, n_cells) load cells, filtered
    H: np.ndarray  # (N, 6) balance (known hub loads, body axes), filtered
    q: np.ndarray | None  # (N, Q) measured external loads, filtered (None without any)
    valid: np.ndarray  # (N,) cells, accelerometers and balance present and unflagged
    scored: np.ndarray  # (N,) valid and past the content filter's settling
    content: str
    fs: float
    files: tuple[str, ...]
    segments: int  # continuous stretches (a new file argument or a gap > gap_s starts one)
    samples_read: int  # samples the reader assembled
    rejected: dict[str, int] = field(default_factory=dict)  # reason → samples
    duration_s: float = 0.0  # recorded time spanned by the samples read
    t_first: float = math.nan  # the first sample's time on the recording's clock (s)

    @property
    def n_valid(self) -> int:
        return int(self.valid.sum())

    @property
    def n_scored(self) -> int:
        return int(self.scored.sum())


class _Segment:
    """Raw rows of one continuous stretch, grown in fixed blocks (no per-sample objects)."""

    def __init__(self, ncol: int):
        self.blocks: list[np.ndarray] = []
        self.vblocks: list[np.ndarray] = []
        self.ncol, self.n, self.seq0 = ncol, 0, None
        self.last_row: np.ndarray | None = None

    def _room(self) -> None:
        if self.n == len(self.blocks) * CHUNK:
            self.blocks.append(np.zeros((CHUNK, self.ncol)))
            self.vblocks.append(np.zeros(CHUNK, bool))

    def put(self, row: np.ndarray | None) -> None:
        """One sample: ``row`` when valid, else None (the last valid row is held, so the
        content filter sees a sample that balances — the model holds for it — and no step)."""
        self._room()
        b, i = divmod(self.n, CHUNK)
        if row is not None:
            self.last_row = row
            self.blocks[b][i] = row
            self.vblocks[b][i] = True
        elif self.last_row is not None:
            self.blocks[b][i] = self.last_row
        self.n += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.n:
            return np.zeros((0, self.ncol)), np.zeros(0, bool)
        return np.vstack(self.blocks)[: self.n], np.concatenate(self.vblocks)[: self.n]


def _reject_reason(s: Sample, T: np.ndarray, acc: np.ndarray, H: np.ndarray | None,
                   q: np.ndarray | None, need_q: bool) -> str | None:
    if H is None or not np.isfinite(H).all():
        return "no balance"
    if not np.isfinite(T).all():
        return "load cell missing"
    if not np.isfinite(acc).all():
        return "accelerometer missing"
    if need_q and (q is None or not np.isfinite(q).all()):
        return "external load missing"
    if any(f.startswith(("overrange:", "fault:")) for f in s.flags):
        return "load cell flagged"
    return None


class KnownLoadCollector:
    """The known-load data of recordings, built sample by sample as a replay assembles them
    (:func:`load_known_load_data` drives it over its own replay; a campaign task feeds it the
    samples of the service's replay, so a recording is read once for both products).

    :meth:`begin` starts each recording (a new continuous stretch), :meth:`add` takes each
    :class:`Sample` in order, :meth:`end` closes the recording, :meth:`data` returns the
    content-filtered data or raises :class:`CalibrationError`, as ``load_known_load_data``.
    ``progress(recorded_seconds, samples)`` is called every ``progress_every`` samples."""

    def __init__(self, cfg: RigConfig, content: str | None = None,
                 progress: Callable[[float, int], None] | None = None,
                 progress_every: int = 1000):
        self.kind = kind = content or cfg.identification.content_known_loads
        if kind not in KINDS:
            raise CalibrationError(f"--content: unknown content {kind!r}; use one of "
                                   f"{', '.join(KINDS)}")
        if not cfg.balance.node:
            raise CalibrationError("the rig config has no reference balance (balance.node is "
                                   "empty): known-load calibration needs the balance's "
                                   "measured hub loads")
        self.cfg = cfg
        model = cfg.rig_model()
        self.Mf = inertial_load_matrix(model)
        self.nc, self.Q = model.geometry.n_cells, model.external.wrenches.shape[1]
        self.ncol = 6 + self.nc + 6 + self.Q
        self.fs = cfg.sample_rate_hz
        self.gap = max(1, round(cfg.identification.gap_s * self.fs))
        self.settle = ContentFilter(kind, self.fs, cfg.rotor.omega_nominal_rad_s,
                                    tuple(cfg.filter.harmonics), 1,
                                    cfg.identification.settle_time_constants).settle_samples
        self.progress, self.progress_every = progress, progress_every
        # (filtered x, valid, scored) of each continuous stretch
        self.outs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.rejected: dict[str, int] = {}
        self.samples_read = 0
        self.t_first: float | None = None
        self.t_last: float | None = None
        self._seg = _Segment(self.ncol)
        self._last_seq: int | None = None

    def begin(self) -> None:
        """A new recording: a new continuous stretch, its sample numbers its own."""
        self._seg = _Segment(self.ncol)
        self._last_seq = None

    def end(self) -> None:
        """The recording's last stretch content-filtered and kept."""
        self._close_segment(self._seg)
        self._seg = _Segment(self.ncol)

    def _close_segment(self, seg: _Segment) -> None:
        X, valid = seg.arrays()
        if not valid.any():
            return
        first = int(np.argmax(valid))  # a segment starts at its first valid sample
        X, valid = X[first:], valid[first:]
        # one causal filter on every channel alike (model §7): the balance holds filtered too
        cfg = self.cfg
        cf = ContentFilter(self.kind, self.fs, cfg.rotor.omega_nominal_rad_s,
                           tuple(cfg.filter.harmonics), self.ncol,
                           cfg.identification.settle_time_constants)
        Y = cf.process(X)
        scored = valid & scored_mask(valid, self.settle, self.gap, True)
        self.outs.append((Y, valid, scored))

    def add(self, s: Sample) -> None:
        """One assembled sample, in order."""
        self.samples_read += 1
        self.t_first = s.t if self.t_first is None else self.t_first
        self.t_last = s.t
        if self.progress is not None and self.samples_read % self.progress_every == 0:
            self.progress(s.t - self.t_first, self.samples_read)
        seq = int(s.seq)
        if self._last_seq is not None:
            skipped = seq - self._last_seq - 1
            if skipped > self.gap:  # a long hole: a new continuous stretch
                self._close_segment(self._seg)
                self._seg = _Segment(self.ncol)
            else:
                for _ in range(max(skipped, 0)):  # lost samples: invalid, held
                    self._seg.put(None)
        self._last_seq = seq
        T = np.asarray(s.T, float)
        acc = np.asarray(s.accel, float).reshape(-1)
        H = None if s.known_H is None else np.asarray(s.known_H, float)
        q = None if s.drive is None else np.asarray(s.drive, float)
        why = _reject_reason(s, T, acc, H, q, self.Q > 0)
        if why is not None:
            self.rejected[why] = self.rejected.get(why, 0) + 1
            self._seg.put(None)
            return
        z = self.Mf @ acc  # inertial loads (model §3); D q stays in the model's E block
        parts = [z, T, H]
        if self.Q:
            assert q is not None  # _reject_reason: without it the sample is rejected
            parts.append(q[: self.Q])
        self._seg.put(np.concatenate(parts))

    def data(self, paths: Sequence[str | Path]) -> CalibrationData:
        """The known-load data of the recordings read (``paths``: named in errors and kept
        in the result), or :class:`CalibrationError` saying why there is none."""
        named = ", ".join(map(str, paths))
        samples_read, rejected, outs = self.samples_read, self.rejected, self.outs
        if samples_read == 0:
            raise CalibrationError(f"{named}: no samples in the recording(s)")
        if not outs:
            no_bal = rejected.get("no balance", 0)
            if no_bal == samples_read:
                raise CalibrationError(
                    f"{named}: no known loads: none of the {samples_read} samples carries "
                    f"reference-balance data (node {self.cfg.balance.node!r}); record with the "
                    "balance on the bus")
            raise CalibrationError(f"{named}: no usable sample with known loads "
                                   f"({_reasons(rejected)})")
        X = np.vstack([o[0] for o in outs])
        valid = np.concatenate([o[1] for o in outs])
        scored = np.concatenate([o[2] for o in outs])
        if not scored.any():
            raise CalibrationError(
                f"{named}: {int(valid.sum())} usable samples with known loads, all within the "
                f"content filter's settling ({self.settle} samples after each start or gap); "
                "record longer stretches")
        nc, t_first, t_last = self.nc, self.t_first, self.t_last
        return CalibrationData(
            z=X[:, :6], T=X[:, 6:6 + nc], H=X[:, 6 + nc:12 + nc],
            q=X[:, 12 + nc:] if self.Q else None, valid=valid, scored=scored,
            content=self.kind, fs=self.fs, files=tuple(map(str, paths)), segments=len(outs),
            samples_read=samples_read, rejected=rejected,
            duration_s=0.0 if t_first is None or t_last is None
            else float(t_last - t_first) + 1.0 / self.fs,
            t_first=math.nan if t_first is None else float(t_first))


def load_known_load_data(
    cfg: RigConfig,
    paths: Sequence[str | Path],
    *,
    content: str | None = None,
    progress: Callable[[float, int], None] | None = None,
    progress_every: int = 1000,
) -> CalibrationData:
    """Read ``paths`` (each a log file or a recording folder, read in order through the
    reader's code path) and return the content-filtered known-load data
    (:class:`KnownLoadCollector`).

    Raises :class:`CalibrationError` when the config has no balance node, or the recordings
    hold no usable sample with known loads. ``progress(recorded_seconds, samples)`` is called
    every ``progress_every`` samples.
    """
    from rsra.daq.bus.reader import OfflineReader
    from rsra.daq.bus.replay import ReplayError, expand, replay

    collector = KnownLoadCollector(cfg, content, progress, progress_every)
    try:
        expand(paths)
    except ReplayError as e:
        raise CalibrationError(str(e)) from None
    for path in map(str, paths):
        reader = OfflineReader(cfg)
        collector.begin()
        try:
            for item in replay(cfg, [path], reader=reader, finish=True):
                if isinstance(item, Sample):
                    collector.add(item)
        except (ValueError, OSError) as e:  # a corrupt or truncated log file
            if isinstance(e, ReplayError):  # names the file (and line) already
                raise CalibrationError(str(e)) from None
            raise CalibrationError(f"{path}: cannot read the recording ({e})") from None
        finally:
            reader.close()
        collector.end()
    return collector.data(paths)


def _reasons(rejected: dict[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(rejected.items())) or "none"


def content_noise_gain(kind: str, cfg: RigConfig) -> float:
    """Σ h² of the content filter's impulse response: the variance of white noise after the
    filter over its variance before (1 for broadband)."""
    cf = ContentFilter(kind, cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                       tuple(cfg.filter.harmonics), 1)
    if kind == "broadband":
        return 1.0
    n = max(int(IMPULSE_TIME_CONSTANTS / 5.0 * max(cf.settle_samples, 1)), 64)
    x = np.zeros(n)
    x[0] = 1.0
    h = sosfilt(cf.sos, x)
    return float(h @ h)


# ------------------------------------------------------------------------------------------
# Identification
# ------------------------------------------------------------------------------------------
@dataclass
class PlausibilityFlag:
    name: str
    value: float  # SI
    problem: str

    def to_dict(self, cfg: RigConfig) -> dict:
        return {"name": self.name, "value": self.value * _display_scale(self.name, cfg),
                "unit": parameter_unit(self.name, cfg), "problem": self.problem}


@dataclass
class CalibrationResult:
    """One batch calibration: estimates and everything needed to judge and adopt them."""

    names: tuple[str, ...]
    start: np.ndarray  # SI
    prior_sigma: np.ndarray  # SI
    ident: IdentificationResult
    residual_rms: np.ndarray  # (6,) filtered residual at the estimate, rows X Y Z L M N at the CG
    residual_expected: np.ndarray  # (6,) what the sensor noise explains after the content filter
    determined: int
    sigma_max: np.ndarray  # SI, per parameter
    condition: float
    undetermined: list[dict]
    information_ratio: tuple[float, float]  # smallest and largest eigenvalue of P_p½ M P_p½
    flags: list[PlausibilityFlag]
    alpha_all: np.ndarray  # the 14 angles at the estimate (non-identified at their start)
    data: CalibrationData
    content_gain: float

    @property
    def estimate(self) -> np.ndarray:
        return self.ident.theta

    @property
    def sigma(self) -> np.ndarray:
        return self.ident.sigma_cr

    @property
    def sigma_corrected(self) -> np.ndarray:
        s = self.ident.sigma_cr_corrected
        return self.sigma if s is None else s

    @property
    def change_in_sigma(self) -> np.ndarray:
        return (self.estimate - self.start) / self.sigma

    @property
    def residual_ratio(self) -> np.ndarray:
        return self.residual_rms / self.residual_expected

    @property
    def status(self) -> str:
        return self.ident.status

    def to_dict(self, cfg: RigConfig) -> dict:
        """JSON-ready (display units: degrees for angles, m, kg, kg·m²; loads SI)."""
        sc = np.array([_display_scale(n, cfg) for n in self.names])
        P = self.ident.P * np.outer(sc, sc)
        Pc = self.ident.P_corrected
        return {
            "parameters": [
                {"name": n, "unit": parameter_unit(n, cfg), "start": float(self.start[k] * sc[k]),
                 "estimate": float(self.estimate[k] * sc[k]),
                 "sigma_cr": float(self.sigma[k] * sc[k]),
                 "sigma_cr_corrected": float(self.sigma_corrected[k] * sc[k]),
                 "prior_sigma": float(self.prior_sigma[k] * sc[k]),
                 "change_sigma": float(self.change_in_sigma[k]),
                 "determined": bool(self.sigma[k] <= self.sigma_max[k])}
                for k, n in enumerate(self.names)],
            "names": list(self.names),
            "covariance": P,
            "covariance_corrected": None if Pc is None else Pc * np.outer(sc, sc),
            "alpha_all_deg": np.degrees(self.alpha_all),
            "residuals": {"axes": list(AXES), "units": ["N", "N", "N", "N·m", "N·m", "N·m"],
                          "rms": self.residual_rms, "expected": self.residual_expected,
                          "ratio": self.residual_ratio, "content_noise_gain": self.content_gain},
            "information": {"determined": self.determined, "parameters": len(self.names),
                            "condition": self.condition if math.isfinite(self.condition) else None,
                            "information_ratio_min": self.information_ratio[0],
                            "information_ratio_max": self.information_ratio[1],
                            "undetermined_directions": self.undetermined},
            "convergence": {"status": self.ident.status, "iterations": self.ident.iterations,
                            "cost": self.ident.cost, "cost_start": self.ident.cost_start,
                            "coloured_residual_lags": self.ident.lags},
            "plausibility": {"ok": not self.flags, "flags": [f.to_dict(cfg) for f in self.flags]},
            "data": {"files": list(self.data.files), "content": self.data.content,
                     "samples_read": self.data.samples_read, "valid": self.data.n_valid,
                     "scored": self.data.n_scored, "segments": self.data.segments,
                     "duration_s": self.data.duration_s, "rejected": dict(self.data.rejected)},
        }


def start_values(cfg: RigConfig, names: Sequence[str],
                 alpha_start: np.ndarray | None = None) -> tuple[Parameterisation, np.ndarray]:
    """The parameterisation around the configured rig and the starting θ (the configured or
    given angles, the configured geometry and masses)."""
    model = cfg.rig_model()
    alpha = np.asarray(cfg.identification.initial_angles_rad if alpha_start is None
                       else alpha_start, float)
    par = Parameterisation(model, names, alpha, moment_floor=cfg.identification.moment_floor_Nm,
                           known_loads=True)
    return par, par.initial()


def plausibility(cfg: RigConfig, names: Sequence[str], theta: np.ndarray,
                 config_values: np.ndarray) -> list[PlausibilityFlag]:
    """Flags (never refusals): angles beyond ±10°, masses and inertias not positive or beyond
    ±50 % of the configured value, positions beyond ±0.2 m of the configured point."""
    angles = cfg.rig_model().geometry.angle_names
    flags = []
    for n, v, c in zip(names, np.asarray(theta, float), np.asarray(config_values, float)):
        if not math.isfinite(v):
            flags.append(PlausibilityFlag(n, v, "not a finite number"))
        elif n in angles:
            lim = cfg.identification.angle_limit_rad
            if abs(v) > lim:
                flags.append(PlausibilityFlag(n, v, f"|angle| > {math.degrees(lim):g}° "
                                              "(identification.angle_limit_deg)"))
        elif n.startswith(("m_", "I_")):
            if v <= 0:
                flags.append(PlausibilityFlag(n, v, "not positive"))
            elif abs(v - c) > PLAUSIBLE_MASS_FRACTION * abs(c):
                flags.append(PlausibilityFlag(
                    n, v, f"more than {PLAUSIBLE_MASS_FRACTION:.0%} from the configured {c:g}"))
        elif abs(v - c) > PLAUSIBLE_POSITION_M:
            flags.append(PlausibilityFlag(
                n, v, f"more than {PLAUSIBLE_POSITION_M:g} m from the configured {c:g} m"))
    return flags


def calibrate(
    cfg: RigConfig,
    data: CalibrationData,
    names: Sequence[str] | None = None,
    *,
    alpha_start: np.ndarray | None = None,
    prior_sigma_rad: float | None = None,
    max_iterations: int | None = None,
) -> CalibrationResult:
    """Batch known-load identification of ``names`` (default the 14 angles) from ``data``:
    model §7's effective-variance likelihood, Levenberg–Marquardt from the starting values
    with a weak prior (angles: ``prior_sigma_rad``, default the configured prior σ), CR bounds
    with the coloured-residual correction up to 5 τ of lag (as the periodic runs)."""
    model = cfg.rig_model()
    angles = model.geometry.angle_names
    names = tuple(angles if names is None else names)
    idc = cfg.identification
    par, start = start_values(cfg, names, alpha_start)
    _, config_values = start_values(cfg, names, None)
    sig_a = idc.prior_sigma_rad if prior_sigma_rad is None else float(prior_sigma_rad)
    prior_sigma = prior_sigmas(names, start, cfg, sig_a)
    P_p = np.diag(prior_sigma ** 2)
    if par.other_pos:
        worst = par.check_derivatives(start)
        if not worst < 1e-4:  # central differences must agree with half the step
            raise CalibrationError(f"finite-difference derivatives disagree ({worst:.2g}) for "
                                   f"{[names[k] for k in par.other_pos]}")
    prob = KnownLoadProblem(par, data.z, data.T, data.H, data.q, scored=data.scored)
    max_lag = math.ceil(5.0 * cfg.filter.time_constant_s * data.fs)
    res = levenberg_marquardt(prob, start, P_p,
                              max_iterations=max_iterations or idc.max_iterations,
                              max_lag=max_lag)
    # residuals at the estimate against the sensor noise after the content filter
    e, _, W = prob.residual_series(res.theta)
    n = max(prob.n_scored, 1)
    rms = np.sqrt(np.sum(e ** 2, axis=0) / n)
    gain = content_noise_gain(data.content, cfg)
    expected = np.sqrt(np.diag(W) * gain)
    # information: determined directions, condition, data-to-prior ratio
    sigma_max = np.array([idc.sigma_max_rad if nm in angles
                          else SIGMA_MAX_OTHER_FRACTION * prior_sigma[k]
                          for k, nm in enumerate(names)])
    sc = np.array([_display_scale(nm, cfg) for nm in names])
    det, cond, ratio, directions = _information(res, names, prior_sigma, sigma_max, sc)
    flags = plausibility(cfg, names, res.theta, config_values)
    return CalibrationResult(
        names=names, start=start, prior_sigma=prior_sigma, ident=res, residual_rms=rms,
        residual_expected=expected, determined=det, sigma_max=sigma_max, condition=cond,
        undetermined=directions, information_ratio=ratio, flags=flags,
        alpha_all=par.alpha(res.theta), data=data, content_gain=gain)


def _information(res: Any, names: Sequence[str], prior_sigma: np.ndarray,
                 sigma_max: np.ndarray, sc: np.ndarray
                 ) -> tuple[int, float, tuple[float, float], list[dict[str, Any]]]:
    """The information of a run: determined directions, condition, data-to-prior ratio and
    the undetermined directions, largest σ first (none where P is not finite)."""
    if not np.all(np.isfinite(res.P)):
        return 0, math.inf, (math.nan, math.nan), []
    det, U, cond = determined_directions(res.P, sigma_max)
    Lp = np.diag(prior_sigma)  # P_p^½ (the prior is diagonal)
    lam = np.linalg.eigvalsh(Lp @ res.information @ Lp)
    P_disp = res.P * np.outer(sc, sc)
    directions = [_direction(U[:, j], sc, P_disp, names) for j in range(U.shape[1])]
    directions.sort(key=lambda x: -x["sigma"])
    return det, cond, (float(lam[0]), float(lam[-1])), directions


def _direction(u: np.ndarray, sc: np.ndarray, P_disp: np.ndarray, names: Sequence[str]
               ) -> dict[str, Any]:
    """An undetermined direction in display units (degrees for angles), its largest
    component positive: its σ and the components worth naming."""
    d = u * sc
    d = d / np.linalg.norm(d)
    d = d if d[np.argmax(np.abs(d))] > 0 else -d
    return {"sigma": float(math.sqrt(max(float(d @ P_disp @ d), 0.0))),
            "components": {nm: round(float(w), 3) for nm, w in zip(names, d)
                           if abs(w) >= DIRECTION_COMPONENT_MIN}}


def structure_of(cfg: RigConfig, result: CalibrationResult) -> dict | None:
    """The structure test over the recording (docs/identification.md): the scored
    samples of each identification window (as the live windows see them), one look each, from the batch estimate's angles. None unless the content is ``static`` (the
    test compares window means). Returns the verdict, the ranked candidates and the fit of
    the selected structure (``structure_fit``, None when none is selected)."""
    from rsra.estimator.structure import StructureTest, fit_payload

    d = result.data
    if d.content != "static":
        return None
    model = cfg.rig_model()
    st = StructureTest(model, cfg.identification.moment_floor_Nm)
    n = max(int(round(cfg.identification.window_s * d.fs)), 1)
    cols = [d.z, d.T, d.H] + ([d.q] if d.q is not None and d.q.shape[1] else [])
    x = np.hstack(cols)
    v = st.last
    # windows on the sample grid from the first sample read, as the service's periodic
    # windows are (a condition held a multiple of the period fills whole windows)
    starts = range(0, len(x), n)
    for k in starts:
        st.joint_fits = k == starts[-1]  # the verdict of the whole recording: the last look
        v = st.add_window(x[k:k + n][d.scored[k:k + n]], result.alpha_all)
    fit = None if v.selected is None else fit_payload(v.selected, model)
    return {"structure": v.structure, "candidates": v.candidates, "structure_fit": fit,
            "looks": v.look, "conditions": v.conditions}


# ------------------------------------------------------------------------------------------
# The config fragment
# ------------------------------------------------------------------------------------------
def _num(x: float, digits: int) -> str:
    """A TOML float (always with a decimal point or exponent)."""
    v = round(float(x), digits)
    if v == 0:
        v = 0.0  # no "-0.0"
    return repr(v)


def _vec(values: Iterable[float], digits: int) -> str:
    return "[" + ", ".join(_num(v, digits) for v in values) + "]"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


@dataclass(frozen=True)
class _Estimates:
    """The identified parameters by name: estimate, Cramér–Rao σ and σ corrected for
    coloured residuals."""

    est: dict[str, float]
    sig: dict[str, float]
    sig_mk: dict[str, float]

    @classmethod
    def of(cls, result: CalibrationResult) -> "_Estimates":
        names = result.names
        return cls(dict(zip(names, result.estimate)), dict(zip(names, result.sigma)),
                   dict(zip(names, result.sigma_corrected)))


@dataclass(frozen=True)
class _ParameterGroups:
    """The identified parameters by the table of the rig file they go to."""

    angles: list[str]  # [identification] initial_angles_deg
    hub: list[str]  # [geometry] hub_centre_m
    mass: list[str]  # [mass]
    cells: list[str]  # [[cells]] position_m

    @classmethod
    def of(cls, names: Sequence[str], angles: Sequence[str]) -> "_ParameterGroups":
        ang = [n for n in names if n in angles]
        hub = [n for n in names if n.startswith("hub_")]
        mass = [n for n in names if n.startswith(("m_", "I_"))]
        return cls(ang, hub, mass, [n for n in names if n not in ang + hub + mass])


def _frag_head(result: CalibrationResult) -> list[str]:
    when = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    d = result.data
    flags = "" if not result.flags else "; PLAUSIBILITY FLAGS: " + "; ".join(
        f"{f.name} {f.problem}" for f in result.flags)
    return [
        "# rsra calibrate: off-line known-load calibration (model.md §7, report Appendix C)",
        f"# from: {', '.join(d.files)}",
        (f"# {when}; content {d.content}; {d.n_scored} samples scored of {d.samples_read} read; "
         f"status {result.status} after {result.ident.iterations} iterations"),
        "# sigma: Cramér-Rao bound (in brackets: corrected for coloured residuals)" + flags,
        "",
    ]


def _frag_angles(angles: Sequence[str], e: _Estimates, result: CalibrationResult) -> list[str]:
    """``[identification] initial_angles_deg``: all 14, the non-identified at their start."""
    lines = ["[identification]"]
    for a in angles:
        tag = (f"{math.degrees(e.est[a]):+.4f} deg, sigma {math.degrees(e.sig[a]):.4f} deg "
               f"({math.degrees(e.sig_mk[a]):.4f})"
               if a in e.est else "not identified: start value kept")
        lines.append(f"# {a}: {tag}")
    return lines + [f"initial_angles_deg = {_vec(np.degrees(result.alpha_all), 6)}", ""]


def _frag_structure(fit: dict) -> list[str]:
    """``[identification.structure]``: the structure the hub loads use (config.rig)."""
    lines = ["[identification.structure]",
             f"# the structure test selected {fit['structure']!r} (docs/identification.md); "
             "the hub loads use it from the start"]
    lines += [f"# {nm}: {b:.6g}, sigma {'-' if sb is None else f'{sb:.3g}'} (SI)"
              for nm, b, sb in zip(fit["parameters"], fit["beta"], fit["beta_sigma"])]
    return lines + [f'structure = "{fit["structure"]}"',
                    f"alpha0_deg = {_vec(np.degrees(fit['alpha0']), 6)}",
                    f"beta = [{', '.join(repr(float(b)) for b in fit['beta'])}]",
                    f"T_ref_N = {_vec(fit['T_ref'], 2)}", ""]


def _frag_hub(cfg: RigConfig, hub: list[str], e: _Estimates) -> list[str]:
    v = np.asarray(cfg.hub_centre_m, float).copy()
    lines = ["[geometry]"]
    for n in hub:
        v["xyz".index(n[-1])] = e.est[n]
        lines.append(f"# {n}: {e.est[n]:.6f} m, sigma {e.sig[n]:.6f} m ({e.sig_mk[n]:.6f})")
    return lines + [f"hub_centre_m = {_vec(v, 6)}", ""]


def _frag_mass(cfg: RigConfig, mass: list[str], e: _Estimates) -> list[str]:
    m = np.asarray(cfg.effective_mass_kg, float).copy()
    inertia = np.asarray(cfg.inertia_kg_m2, float).copy()
    lines = ["[mass]"]
    for n in mass:
        unit = "kg" if n.startswith("m_") else "kg m^2"
        lines.append(f"# {n}: {e.est[n]:.3f} {unit}, sigma {e.sig[n]:.3f} {unit} "
                     f"({e.sig_mk[n]:.3f})")
        if n.startswith("m_"):
            m["xyz".index(n[-1])] = e.est[n]
        else:
            inertia[("I_xx", "I_yy", "I_zz").index(n)] = e.est[n]
    if any(n.startswith("m_") for n in mass):
        lines.append(f"effective_mass_kg = {_vec(m, 4)}")
    if any(n.startswith("I_") for n in mass):
        lines.append(f"inertia_kg_m2 = {_vec(inertia, 4)}")
    return lines + [""]


def _frag_cell(block: dict, e: _Estimates) -> list[str]:
    """One ``[[cells]]`` block as the rig gives it, its identified position coordinates
    replaced."""
    cell = block["name"]
    p = [float(x) for x in block["position_m"]]
    notes = []
    for i, ax in enumerate("xyz"):
        n = f"{ax}_{cell}"
        if n in e.est:
            p[i] = float(e.est[n])
            notes.append(f"# {n}: {e.est[n]:.6f} m, sigma {e.sig[n]:.6f} m ({e.sig_mk[n]:.6f})")
    return ["[[cells]]", *notes,
            *(f"{k} = {_vec(p, 6) if k == 'position_m' else _toml_value(v)}"
              for k, v in block.items()), ""]


def fragment_toml(cfg: RigConfig, result: CalibrationResult,
                  structure: dict | None = None) -> str:
    """A TOML fragment to merge into the rig config (``load_config(overrides=…)`` accepts it):
    ``[identification] initial_angles_deg`` (all 14; the non-identified at their start values)
    when angles were identified; ``[geometry] hub_centre_m``, ``[mass] effective_mass_kg`` /
    ``inertia_kg_m2`` and the seven ``[[cells]]`` blocks (complete: TOML arrays of tables
    replace, they do not merge) when those parameters were. Comments give each value's σ and
    the source recordings."""
    angles = cfg.rig_model().geometry.angle_names
    g = _ParameterGroups.of(result.names, angles)
    e = _Estimates.of(result)
    lines = _frag_head(result)
    if g.angles:
        lines += _frag_angles(angles, e, result)
    fit = None if structure is None else structure.get("structure_fit")
    if fit is not None:
        lines += _frag_structure(fit)
    if g.hub:
        lines += _frag_hub(cfg, g.hub, e)
    if g.mass:
        lines += _frag_mass(cfg, g.mass, e)
    if g.cells:
        for block in cfg.raw.get("cells", []):
            lines += _frag_cell(block, e)
    return "\n".join(lines).rstrip() + "\n"
