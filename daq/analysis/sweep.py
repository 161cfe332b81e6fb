"""The report's frequency-domain evaluation of a shake-test sweep (Phase I; report Eq 1.3–1.5,
Table I, Figures 4–5, 6–18; model.md §3, §4, §8 `sweep`).

With known applied loads H (the reference balance, body axes) the static estimate's error is
(report Eq 1.3)

    e_H = Ĥ − H = R₀⁻¹ (I_m − S(α) T_m − D q_m) − H = R₀⁻¹ W_u

where ``W_u = I_m − S T_m − D q_m − R₀ H`` is whatever the rigid-body balance (Eq 1.1) leaves
unexplained, at the CG: an unmodelled external load, sensor noise, neglected angular inertia.
In the frequency domain, for an excitation along one axis only (Eq 1.4, 1.5), every term is a
transfer function to that excitation: ``e_H(ω)/H_a(ω) = R₀⁻¹ (G_I(ω) − S G_T(ω)) − 1_a``.

The report had transfer functions from a harmonic analyser; here they are computed from the
recording by the H1 estimator (scipy.signal.csd / welch: ``G = P_xy / P_xx`` with the balance
channel of the excited axis as x). Complex values are written with their real and imaginary
parts stacked end to end (the report's organisation of frequency-domain data), never complex.

Segments of excitation (axis, level) are found in the balance data alone: the envelope of its
high-passed signal, in units of the balance's own noise σ, above a threshold.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from rsra.config.rig import RigConfig
from rsra.config.units import axis_units, to_units
from rsra.daq.runtime.persistence import save_figure
from rsra.estimator.balance import inertial_load_matrix
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix
from rsra.estimator.noise_budget import AXES, NoiseBudget, noise_budget
from rsra.estimator.params import Geometry

# A coherent error (or unmodelled-load gain) is "significant" when its magnitude exceeds its
# random error (σ per real/imaginary part) by the Rayleigh quantile of a 1e-3 false-alarm rate:
# P(|c| > zσ | c = 0) = exp(−z²/2).
Z_SIGNIFICANT = math.sqrt(-2.0 * math.log(1e-3))
ENVELOPE_S = 0.5  # moving-RMS window of the excitation detector
HIGHPASS_HZ = 2.0  # removes the static load (and slow ramps) before the detector
MIN_SEGMENT_S = 1.0
SNR_THRESHOLD = 8.0  # envelope / balance noise sigma: excitation present
LEVEL_GROUP_TOL = 0.1  # segments on the same axis within 10 % of amplitude are one level
BAND_FRACTION = 0.1  # excited band: bins with P_xx within 10 dB of the segment's peak
MAX_FINDING_ROWS = 4  # rows of the Figure-18 plot (the largest findings)
HANN_ENBW_BINS = 1.5  # equivalent noise bandwidth of the Hann window, in bins


class SweepError(ValueError):
    """A recording that cannot be evaluated as a sweep (no balance, no excitation, …)."""


@dataclass
class SweepData:
    """Uniformly sampled channels of a recording (grid by the samples' ``seq``)."""

    fs: float
    t: np.ndarray  # (N,) s, acquisition time
    T: np.ndarray  # (N, 7) N
    I: np.ndarray  # (N, 6) inertial loads [m f; I ω̇] at the CG
    known_H: np.ndarray  # (N, 6) reference balance, body axes, at the hub
    q: np.ndarray | None = None  # (N, Q) measured external loads (drive), if any
    filled: int = 0  # grid samples interpolated (lost, missing or not finite)
    sources: list[str] = field(default_factory=list)


def _grid(seq: np.ndarray, rows: np.ndarray, names: Sequence[str] = ()
          ) -> tuple[np.ndarray, int]:
    """Rows on the complete seq grid; missing or non-finite entries linearly interpolated
    per column. Returns (grid rows, number of grid samples that needed filling)."""
    seq = np.asarray(seq, dtype=np.int64)
    n = int(seq[-1] - seq[0] + 1)
    out = np.full((n,) + rows.shape[1:], np.nan)
    out[seq - seq[0]] = rows
    flat = out.reshape(n, -1)
    bad_rows = ~np.isfinite(flat).all(axis=1)
    x = np.arange(n)
    for j in range(flat.shape[1]):
        ok = np.isfinite(flat[:, j])
        if not ok.any():
            name = names[j] if j < len(names) else f"column {j}"
            raise SweepError(f"the recording has no valid value of {name} at all")
        if not ok.all():
            flat[:, j] = np.interp(x, x[ok], flat[ok, j])
    return flat.reshape(out.shape), int(bad_rows.sum())


def sweep_data_from_samples(cfg: RigConfig, samples: Sequence, sources: Sequence[str] = ()
                            ) -> SweepData:
    """SweepData from reader samples (daq.assembler.Sample or anything with seq, t, T, accel,
    known_H, drive)."""
    if not samples:
        raise SweepError("the recording holds no samples")
    model = cfg.rig_model()
    nq = model.external.wrenches.shape[1]
    seq = np.array([s.seq for s in samples], dtype=np.int64)
    order = np.argsort(seq, kind="stable")
    seq = seq[order]
    keep = np.r_[True, np.diff(seq) > 0]  # a repeated seq (a second file from 0) is dropped
    idx = order[keep]
    seq = seq[keep]
    nan6 = np.full(6, np.nan)
    K = len(cfg.accelerometers)
    rows = np.empty((len(idx), 1 + 7 + 3 * K + 6 + nq))
    n_known = 0
    cells = [c.name for c in cfg.cells]
    for r, i in enumerate(idx):
        s = samples[i]
        kh = s.known_H
        if kh is not None:
            n_known += 1
        q = np.full(nq, np.nan) if (s.drive is None or nq == 0) else np.asarray(s.drive, float)[:nq]
        T = np.array(s.T, float)
        for fl in getattr(s, "flags", ()):  # an over-range or faulted cell is not a measurement
            kind, _, cell = fl.partition(":")
            if kind in ("overrange", "fault") and cell in cells:
                T[cells.index(cell)] = np.nan
        rows[r] = np.concatenate([[s.t], T, np.asarray(s.accel, float).ravel(),
                                  nan6 if kh is None else np.asarray(kh, float), q])
    if n_known == 0:
        raise SweepError("no reference-balance data in the recording: a sweep evaluation needs "
                         "the known applied loads (the balance node)")
    names = (["time"] + [f"load cell {c}" for c in cells]
             + [f"{a.name} {x}" for a in cfg.accelerometers for x in "xyz"]
             + [f"balance {ax}" for ax in AXES] + [e.name for e in cfg.external_loads])
    g, filled = _grid(seq, rows, names)
    fs = cfg.sample_rate_hz
    t = g[:, 0]
    T = g[:, 1:8]
    accel = g[:, 8:8 + 3 * K]
    known_H = g[:, 8 + 3 * K:14 + 3 * K]
    drive = g[:, 14 + 3 * K:] if nq else None
    I = accel @ inertial_load_matrix(model).T  # model §3: I = M_f f_m
    return SweepData(fs=fs, t=t, T=T, I=I, known_H=known_H, q=drive, filled=filled,
                     sources=[str(s) for s in sources])


def load_sweep_data(cfg: RigConfig, paths: Sequence[str | Path]) -> SweepData:
    """Replay recordings (files or recording folders) through the reader; see daq.replay."""
    from rsra.daq.bus.reader import HealthReport
    from rsra.daq.bus.replay import expand, replay

    files = expand(paths)
    samples = [s for s in replay(cfg, paths) if not isinstance(s, HealthReport)]
    return sweep_data_from_samples(cfg, samples, [str(f) for f in files])


# ---------------------------------------------------------------------------------------------
# segments


@dataclass(frozen=True)
class Segment:
    """One stretch of excitation along one axis (indices into the SweepData grid)."""

    axis: int  # 0..5: X Y Z L M N
    start: int
    stop: int
    amplitude: float  # sine amplitude of the excitation (√2 × RMS of the high-passed balance)
    # largest RMS, in balance-noise σ, of the oscillation on another axis that the excited
    # axis does not explain (least squares, zero lag): ~1 for a shaker on one axis (noise),
    # far above SNR_THRESHOLD when several axes oscillate independently (rotor harmonics)
    other_axes_snr: float = 0.0

    @property
    def single_axis(self) -> bool:
        """A shaker excitation along one axis, the case Eq 1.4/1.5 evaluate."""
        return self.other_axes_snr <= SNR_THRESHOLD


def detect_segments(known_H: np.ndarray, fs: float, sigma_balance: np.ndarray,
                    min_duration_s: float = MIN_SEGMENT_S) -> list[Segment]:
    """Stretches where the high-passed balance signal's moving RMS exceeds SNR_THRESHOLD × its
    noise σ on some axis; the axis is the one with the largest RMS in noise units."""
    H = np.asarray(known_H, float)
    sos = signal.butter(4, HIGHPASS_HZ, "highpass", fs=fs, output="sos")
    hp = signal.sosfiltfilt(sos, H - H[0], axis=0)
    w = max(1, int(round(ENVELOPE_S * fs)))
    env = np.sqrt(np.maximum(signal.fftconvolve(hp**2, np.ones((w, 1)) / w, mode="same", axes=0),
                             0.0))
    snr = env / np.asarray(sigma_balance, float)[None, :]
    active = snr.max(axis=1) > SNR_THRESHOLD
    edges = np.diff(np.r_[0, active.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = []
    for a, b in zip(starts, stops):
        if (b - a) < min_duration_s * fs:
            continue
        axis = int(np.bincount(np.argmax(snr[a:b], axis=1), minlength=6).argmax())
        m = (b - a) // 10  # the middle 80 % (the ramps at both ends are lower)
        mid = hp[a + m:b - m]
        x = mid[:, axis]
        amp = math.sqrt(2.0) * float(np.sqrt(np.mean(x**2)))
        resid = mid - np.outer(x, mid.T @ x / max(float(x @ x), 1e-300))
        other = np.sqrt(np.mean(resid**2, axis=0)) / np.asarray(sigma_balance, float)
        other[axis] = 0.0
        out.append(Segment(axis=axis, start=int(a), stop=int(b), amplitude=amp,
                           other_axes_snr=float(other.max())))
    return out


# ---------------------------------------------------------------------------------------------
# spectra


@dataclass
class LevelResult:
    """The frequency-domain evaluation of one excitation axis at one level (all its segments
    pooled). Complex arrays here; stacked real/imaginary in the JSON."""

    axis: int
    amplitude: float  # mean excitation amplitude, N or N·m
    segments: list[Segment]
    n_averages: int  # Welch segments pooled
    freq: np.ndarray  # (F,) Hz, the excited band
    G_T: np.ndarray  # (F, 7) load cells per unit excitation
    G_I: np.ndarray  # (F, 6) inertial loads per unit excitation
    G_e: np.ndarray  # (F, 6) static-estimate error e_H per unit excitation (Eq 1.5)
    G_u: np.ndarray  # (F, 6) reconstructed unmodelled load at the CG per unit excitation
    sigma_G_e: np.ndarray  # (F, 6) random error of G_e (coherence-based)
    sigma_G_u: np.ndarray  # (F, 6)
    error_amplitude: np.ndarray  # (6,) mean over the band of |G_e| × amplitude (Table I)
    error_rms_time: np.ndarray  # (6,) time-domain RMS of Ĥ − H over the segments
    gain_u: np.ndarray  # (6,) complex: band fit of G_u (real/imag stacked least squares)
    sigma_gain_u: np.ndarray  # (6,)
    gain_e: np.ndarray  # (6,) complex: band fit of G_e
    sigma_gain_e: np.ndarray  # (6,)

    @property
    def label(self) -> str:
        return AXES[self.axis]


def _nperseg(fs: float, n: int) -> int:
    """About 2.5 s per Welch segment (0.4 Hz resolution at 200 samples/s: ~9 bins over the
    report's 15–18.5 Hz), fewer when the segment is short (at least three averages)."""
    target = 2 ** int(round(math.log2(2.56 * fs)))
    while target > 32 and 3 * target // 2 + target // 2 > n:
        target //= 2
    return target


def _band_fit(G: np.ndarray, sigma: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One complex gain per column over the band: the weighted least-squares fit of a constant
    to the transfer function with real and imaginary parts stacked end to end (the report's
    frequency-domain least squares), weights P_xx. Its σ from the per-bin random errors."""
    ws = w / w.sum()
    # minimise sum_k w_k [(Re G_k - Re c)^2 + (Im G_k - Im c)^2]: the stacked real/imaginary
    # equations decouple, and the solution is the weighted mean of each part
    c = np.sum(ws[:, None] * G.real, axis=0) + 1j * np.sum(ws[:, None] * G.imag, axis=0)
    # neighbouring bins of a Hann-windowed spectrum are correlated: the band holds about
    # n_bins / 1.5 independent values (the window's equivalent noise bandwidth is 1.5 bins);
    # checked by Monte Carlo over 40 seeds on the default rig (x-force phase error spread)
    s = np.sqrt(HANN_ENBW_BINS * np.sum((ws[:, None] * sigma) ** 2, axis=0))
    return c, s


def analyse_level(data: SweepData, segments: list[Segment], S: np.ndarray, R0: np.ndarray,
                  D: np.ndarray | None) -> LevelResult:
    """Pooled H1 transfer functions of every channel to the excitation over the segments."""
    fs = data.fs
    axis = segments[0].axis
    R0inv = np.linalg.inv(R0)
    acc: dict[str, np.ndarray] = {}
    n_avg = 0
    err_sq = np.zeros(6)
    n_err = 0
    nper = min(_nperseg(fs, s.stop - s.start) for s in segments)  # one frequency grid
    for seg in segments:
        sl = slice(seg.start, seg.stop)
        x = data.known_H[sl, axis]
        Wu = data.I[sl] - data.T[sl] @ S.T - data.known_H[sl] @ R0.T  # balance residual, Eq 1.1
        if D is not None and data.q is not None:
            Wu = Wu - data.q[sl] @ D.T
        e = Wu @ R0inv.T  # e_H = Ĥ − H (Eq 1.3)
        Y = np.hstack([data.T[sl], data.I[sl], e, Wu])  # 7 + 6 + 6 + 6 columns
        kw: dict[str, Any] = dict(fs=fs, window="hann", nperseg=nper, noverlap=nper // 2,
                                  detrend="constant")
        f, Pxx = signal.welch(x, **kw)
        _, Pxy = signal.csd(x[:, None], Y, axis=0, **kw)
        _, Pyy = signal.welch(Y, axis=0, **kw)
        m = 1 + (len(x) - nper) // (nper // 2)
        for k, v in (("Pxx", Pxx * m), ("Pxy", Pxy * m), ("Pyy", Pyy * m)):
            acc[k] = acc[k] + v if k in acc else v
        acc.setdefault("f", f)
        n_avg += m
        e_d = e - e.mean(axis=0)
        err_sq += np.sum(e_d**2, axis=0)
        n_err += len(e_d)
    Pxx, Pxy, Pyy = acc["Pxx"] / n_avg, acc["Pxy"] / n_avg, acc["Pyy"] / n_avg
    f = acc["f"]
    band = Pxx >= BAND_FRACTION * Pxx.max()
    band[0] = False  # never the DC bin
    Pxx_b, Pxy_b, Pyy_b = Pxx[band], Pxy[band], Pyy[band]
    G = Pxy_b / Pxx_b[:, None]
    coh = np.clip(np.abs(Pxy_b) ** 2 / (Pxx_b[:, None] * np.maximum(Pyy_b, 1e-300)), 0.0, 1.0)
    # random error of the H1 estimate (Bendat & Piersol): var(G) = (1 − γ²) P_yy / (n P_xx),
    # split evenly between the real and imaginary parts; 50 % overlap counted as ~1/1.2 as many
    # independent averages (Welch, Hann window).
    n_eff = max(n_avg / 1.2, 1.0)
    sigma = np.sqrt((1.0 - coh) * Pyy_b / (2.0 * n_eff * Pxx_b[:, None]))
    G_T, G_I, G_e, G_u = G[:, :7], G[:, 7:13], G[:, 13:19], G[:, 19:25]
    s_e, s_u = sigma[:, 13:19], sigma[:, 19:25]
    amp = float(np.mean([s.amplitude for s in segments]))
    gain_u, sg_u = _band_fit(G_u, s_u, Pxx_b)
    gain_e, sg_e = _band_fit(G_e, s_e, Pxx_b)
    return LevelResult(
        axis=axis, amplitude=amp, segments=list(segments), n_averages=n_avg, freq=f[band],
        G_T=G_T, G_I=G_I, G_e=G_e, G_u=G_u, sigma_G_e=s_e, sigma_G_u=s_u,
        error_amplitude=np.mean(np.abs(G_e), axis=0) * amp,
        error_rms_time=np.sqrt(err_sq / max(n_err, 1)),
        gain_u=gain_u, sigma_gain_u=sg_u, gain_e=gain_e, sigma_gain_e=sg_e)


@dataclass
class SweepResult:
    fs: float
    frame: str  # always "body": the balance measures in body axes
    alpha: np.ndarray
    budget: NoiseBudget
    sigma_balance: np.ndarray
    levels: list[LevelResult]  # sorted by axis, then amplitude
    segments: list[Segment]
    n_samples: int
    filled: int
    sources: list[str]
    model_geometry: Geometry | None = None  # (for R₀)
    # stretches of oscillating load on several axes at once (not a shaker): left out
    excluded: list[Segment] = field(default_factory=list)

    def by_axis(self) -> dict[int, list[LevelResult]]:
        out: dict[int, list[LevelResult]] = {}
        for lv in self.levels:
            out.setdefault(lv.axis, []).append(lv)
        return out


def _group_levels(segments: list[Segment]) -> list[list[Segment]]:
    groups: list[list[Segment]] = []
    for seg in sorted(segments, key=lambda s: (s.axis, s.amplitude)):
        if groups and groups[-1][0].axis == seg.axis:
            ref = np.mean([s.amplitude for s in groups[-1]])
            if abs(seg.amplitude - ref) <= LEVEL_GROUP_TOL * ref:
                groups[-1].append(seg)
                continue
        groups.append([seg])
    return groups


def analyse_sweep(cfg: RigConfig, data: SweepData, alpha: np.ndarray | None = None
                  ) -> SweepResult:
    """Segments, per (axis, level) transfer functions, the static model's error and the
    reconstructed unmodelled load, and the noise budget (Table I) — all in body axes with the
    configured (nominal) angles unless ``alpha`` is given."""
    model = cfg.rig_model()
    alpha = cfg.identification.initial_angles_rad if alpha is None else np.asarray(alpha, float)
    S = wrench_matrix(model.geometry, alpha)
    R0 = hub_transfer_matrix(model.geometry, "body")  # the balance measures in body axes
    D = model.external.wrenches if model.external.wrenches.shape[1] else None
    sigma_bal = cfg.balance.sigma
    found = detect_segments(data.known_H, data.fs, sigma_bal)
    if not found:
        raise SweepError("no shaker excitation found in the balance data (no stretch of at "
                         f"least {MIN_SEGMENT_S:g} s where the oscillating load exceeds "
                         f"{SNR_THRESHOLD:g}× the balance noise)")
    segments = [s for s in found if s.single_axis]
    excluded = [s for s in found if not s.single_axis]
    if not segments:
        worst = max(excluded, key=lambda s: s.other_axes_snr)
        total = sum(s.stop - s.start for s in excluded) / data.fs
        raise SweepError(
            "the recording holds no shake-test sweep: the oscillating load found "
            f"({len(excluded)} stretch{'es' if len(excluded) > 1 else ''}, {total:.1f} s) is on "
            f"several axes at once (up to {worst.other_axes_snr:.0f}× the balance noise on an axis the "
            f"{AXES[worst.axis]} load does not explain), as rotor harmonics are; a sweep "
            "excites one axis at a time")
    levels = [analyse_level(data, g, S, R0, D) for g in _group_levels(segments)]
    return SweepResult(fs=data.fs, frame="body", alpha=alpha,
                       budget=noise_budget(model, alpha, "body"), sigma_balance=sigma_bal,
                       levels=levels, segments=segments, n_samples=len(data.t),
                       filled=data.filled, sources=list(data.sources),
                       model_geometry=model.geometry, excluded=excluded)


# ---------------------------------------------------------------------------------------------
# presentation


def phase_deg(z: complex | np.ndarray) -> np.ndarray:
    """Phase in [0, 360) degrees (so that 180°, elastic, sits mid-range)."""
    return np.mod(np.degrees(np.angle(z)), 360.0)


def gain_units(component: int, excitation: int, units: str) -> str:
    u = axis_units(units)
    return f"{u[component]}/{u[excitation]}"


def _gain_scale(component: int, excitation: int, units: str) -> float:
    """Display scale of a gain component/excitation."""
    num = float(to_units(np.eye(6)[component], units)[component])
    den = float(to_units(np.eye(6)[excitation], units)[excitation])
    return num / den


def level_label(lv: LevelResult, units: str) -> str:
    a = float(to_units(np.eye(6)[lv.axis] * lv.amplitude, units)[lv.axis])
    return f"{AXES[lv.axis]} {a:.0f} {axis_units(units)[lv.axis]}"


def classify_phase(ph: float) -> str:
    """Figure 18: a phase near 180° means an elastic load (against the excitation), near ±90°
    a damping-like one, near 0° one in phase with the excitation."""
    d = min(abs(ph - 180.0), 360.0 - abs(ph - 180.0))
    if d <= 30.0:
        return "elastic"
    if min(abs(ph - 90.0), abs(ph - 270.0)) <= 30.0:
        return "damping"
    if min(ph, 360.0 - ph) <= 30.0:
        return "in phase"
    return "mixed"


COMPONENT_NAMES = ("x-force", "y-force", "z-force", "roll torque", "pitch moment", "yaw moment")


def cg_noise_sigma(result: SweepResult) -> np.ndarray:
    """Instrumentation-noise σ of the balance residual at the CG (R₀ Q_H R₀ᵀ, model §4)."""
    assert result.model_geometry is not None  # analyse_sweep sets it
    R0 = hub_transfer_matrix(result.model_geometry, "body")
    return np.sqrt(np.diag(R0 @ result.budget.covariance @ R0.T))


def findings(result: SweepResult) -> list[dict]:
    """Components of the reconstructed unmodelled load (at the CG) that are significantly
    different from zero for an excitation axis: the gain pooled over the levels (inverse-
    variance weights) exceeds Z_SIGNIFICANT × its random error. Ranked by the size of the load
    at the highest level relative to the instrumentation noise at the CG (the report's
    criterion for an error "too great to be explained" by sensor noise)."""
    out = []
    sig_cg = cg_noise_sigma(result)
    for axis, lvls in result.by_axis().items():
        for c in range(6):
            g = np.array([lv.gain_u[c] for lv in lvls])
            s = np.array([lv.sigma_gain_u[c] for lv in lvls])
            w = 1.0 / np.maximum(s, 1e-300) ** 2
            pooled = np.sum(w * g) / np.sum(w)
            sp = 1.0 / math.sqrt(np.sum(w))
            z = abs(pooled) / sp
            if z > Z_SIGNIFICANT:
                ph = float(phase_deg(pooled))
                top = max(lv.amplitude for lv in lvls)
                out.append({"excitation": AXES[axis], "component": AXES[c],
                            "name": COMPONENT_NAMES[c], "gain": abs(pooled), "sigma": sp,
                            "z": z, "phase_deg": ph,
                            "phase_sigma_deg": math.degrees(sp / abs(pooled)),
                            "kind": classify_phase(ph),
                            "load_over_noise": abs(pooled) * top / sig_cg[c]})
    return sorted(out, key=lambda d: -d["load_over_noise"])


def _stack(z: np.ndarray) -> list:
    """Real parts then imaginary parts, end to end (per column when 2-D)."""
    z = np.asarray(z)
    return np.concatenate([z.real, z.imag], axis=0).tolist()


def sweep_json(result: SweepResult, units: str = "si") -> dict:
    """Machine-readable table (strict-JSON-able, display units)."""
    b = result.budget
    tot, cells, acc = (to_units(v, units) for v in (b.total, b.load_cells, b.accelerometers))
    lv_out = []
    for lv in result.levels:
        scale_e = to_units(np.ones(6), units)  # per estimated axis
        exc = float(to_units(np.eye(6)[lv.axis], units)[lv.axis])
        gs = np.array([_gain_scale(c, lv.axis, units) for c in range(6)])
        lv_out.append({
            "excitation": AXES[lv.axis], "amplitude": lv.amplitude * exc,
            "segments": [{"start_s": s.start / result.fs, "stop_s": s.stop / result.fs,
                          "amplitude": s.amplitude * exc} for s in lv.segments],
            "n_averages": lv.n_averages,
            "band_hz": [float(lv.freq[0]), float(lv.freq[-1])],
            "error_amplitude": (lv.error_amplitude * scale_e).tolist(),
            "error_rms_time": (lv.error_rms_time * scale_e).tolist(),
            "error_gain": {"magnitude": (np.abs(lv.gain_e) * scale_e / exc).tolist(),
                           "sigma": (lv.sigma_gain_e * scale_e / exc).tolist(),
                           "phase_deg": phase_deg(lv.gain_e).tolist()},
            "unmodelled_gain": {"magnitude": (np.abs(lv.gain_u) * gs).tolist(),
                                "sigma": (lv.sigma_gain_u * gs).tolist(),
                                "phase_deg": phase_deg(lv.gain_u).tolist(),
                                "units": [gain_units(c, lv.axis, units) for c in range(6)]},
            "transfer_functions": {
                "stacking": "per column: the real parts at every frequency, then the imaginary "
                            "parts (report: real and imaginary parts stacked end to end)",
                "frequency_hz": lv.freq.tolist(),
                "load_cells": _stack(lv.G_T * _gain_scale(0, lv.axis, units)),
                "inertial_loads": _stack(lv.G_I * gs[None, :]),
                "estimation_error": _stack(lv.G_e * gs[None, :]),
                "unmodelled_load": _stack(lv.G_u * gs[None, :]),
            },
        })
    return {
        "units": axis_units(units), "axes": list(AXES), "frame": result.frame,
        "sources": result.sources, "samples": result.n_samples, "filled_samples": result.filled,
        "excluded_segments": [{"start_s": s.start / result.fs, "stop_s": s.stop / result.fs,
                               "largest_axis": AXES[s.axis],
                               "other_axes_snr": s.other_axes_snr} for s in result.excluded],
        "angles_rad": result.alpha.tolist(),
        "noise_budget": {"total": tot.tolist(), "load_cells": cells.tolist(),
                         "accelerometers": acc.tolist(),
                         "balance": to_units(result.sigma_balance, units).tolist()},
        "levels": lv_out,
        "findings": [{**f, "gain": f["gain"] * _gain_scale(AXES.index(f["component"]),
                                                          AXES.index(f["excitation"]), units),
                      "sigma": f["sigma"] * _gain_scale(AXES.index(f["component"]),
                                                        AXES.index(f["excitation"]), units),
                      "units": gain_units(AXES.index(f["component"]),
                                          AXES.index(f["excitation"]), units)}
                     for f in findings(result)],
    }


def sweep_table(result: SweepResult, units: str = "si") -> str:
    """Table I per excitation axis: the mean coherent error amplitude over the band at each
    level beside the instrumentation-noise σ (total, load cells, accelerometers); '>' marks an
    error above the total σ (the report's criterion), '*' one that is statistically significant
    (|error| > 3.72 × its random error, 1e-3 false alarm)."""
    b = result.budget
    tot, cells, acc = (to_units(v, units) for v in (b.total, b.load_cells, b.accelerometers))
    u = axis_units(units)
    lines = [f"Estimation error of the static model (report Eq 1.3-1.5, Table I), {result.frame} "
             f"axes, nominal angles; mean |e_H| over the excited band per level"]
    for axis, lvls in result.by_axis().items():
        lines.append("")
        lines.append(f"Excitation along {AXES[axis]} "
                     f"(band {lvls[0].freq[0]:.2f}-{lvls[0].freq[-1]:.2f} Hz)")
        heads = [level_label(lv, units).split(" ", 1)[1] for lv in lvls]
        w = max(11, *(len(h) + 2 for h in heads))
        hdr = f"{'axis':<5}{'unit':<7}" + "".join(f"{h:>{w}}" for h in heads)
        hdr += f"{'noise σ':>10}{'cells':>9}{'accel':>9}"
        lines.append(hdr)
        for i, ax in enumerate(AXES):
            row = f"{ax:<5}{u[i]:<7}"
            for lv in lvls:
                v = float(to_units(lv.error_amplitude, units)[i])
                z = abs(lv.gain_e[i]) / max(lv.sigma_gain_e[i], 1e-300)
                mark = (">" if lv.error_amplitude[i] > b.total[i] else " ") + \
                       ("*" if z > Z_SIGNIFICANT else " ")
                row += f"{v:>{w - 2}.1f}{mark}"
            row += f"{tot[i]:>10.1f}{cells[i]:>9.1f}{acc[i]:>9.1f}"
            lines.append(row)
    lines.append("")
    lines.append("> above the instrumentation-noise sigma (report's criterion); * significant "
                 "(> 3.72 x its random error, 1e-3 false alarm)")
    fl = findings(result)
    lines.append("")
    lines.append("Reconstructed unmodelled load (at the CG) relative to the excitation "
                 "(report Figure 18: near 180 deg = elastic; with angular = \"neglect\" a moment "
                 "here can also be the neglected angular inertia I*omega_dot, model 3):")
    if not fl:
        lines.append("  none significant")
    for f in fl:
        c, e = AXES.index(f["component"]), AXES.index(f["excitation"])
        sc = _gain_scale(c, e, units)
        lines.append(f"  {f['name']} ({f['component']}) from {f['excitation']} excitation: "
                     f"{f['gain'] * sc:.4g} ± {f['sigma'] * sc:.2g} {gain_units(c, e, units)}, "
                     f"phase {f['phase_deg']:.1f} ± {f['phase_sigma_deg']:.1f} deg ({f['kind']}); "
                     f"{f['load_over_noise']:.2f} x the noise sigma at the highest level")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# plots


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_sweep(result: SweepResult, out_dir: str | Path, units: str = "si") -> list[Path]:
    """The report's figures, made from the recording: transfer functions (Figs 4-5), the
    estimation error against frequency per excitation axis (Figs 6-17) and the phase of the
    reconstructed unmodelled load (Fig 18)."""
    plt = _mpl()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    u = axis_units(units)
    by_axis = result.by_axis()
    cmap = plt.get_cmap("viridis")

    # transfer functions at the highest level of each axis (report Figs 4-5)
    fig, axs = plt.subplots(len(by_axis), 2, figsize=(12, 3.2 * len(by_axis) + 1.2),
                            squeeze=False, layout="constrained")
    cell_names = ["A", "B", "C", "D", "E", "F", "G"]
    for r, (axis, lvls) in enumerate(by_axis.items()):
        lv = lvls[-1]
        for i in range(7):
            axs[r, 0].plot(lv.freq, np.abs(lv.G_T[:, i]), marker="o", ms=3,
                           label=f"cell {cell_names[i]}")
        for j in range(3):
            axs[r, 1].plot(lv.freq, np.abs(lv.G_I[:, j]), marker="o", ms=3,
                           label=f"inertial {AXES[j]}")
        axs[r, 0].set_title(f"Load cells per unit {level_label(lv, units)} excitation")
        axs[r, 1].set_title(f"Inertial forces (accelerometers × mass), {level_label(lv, units)}")
        for a in axs[r]:
            a.set_xlabel("frequency [Hz]")
            a.set_ylabel(f"|transfer function| [{u[0]}/{u[axis]}]" if axis < 3
                         else "|transfer function|")
            a.grid(True, alpha=0.3)
            a.legend(fontsize=8, ncol=2, loc="best")
    fig.suptitle("Transfer functions to the shaker excitation (H1 estimate, report Figs 4-5)")
    p = out / "sweep_transfer_functions.png"
    save_figure(fig, p, dpi=100)
    plt.close(fig)
    paths.append(p)

    # estimation error against frequency, one figure per excitation axis (report Figs 6-17)
    for axis, lvls in by_axis.items():
        fig, axs = plt.subplots(2, 3, figsize=(12, 8), layout="constrained")
        for i in range(6):
            a = axs.flat[i]
            sc = float(to_units(np.eye(6)[i], units)[i])
            for k, lv in enumerate(lvls):
                col = cmap(0.15 + 0.7 * k / max(1, len(lvls) - 1))
                amp = np.abs(lv.G_e[:, i]) * lv.amplitude * sc
                err = lv.sigma_G_e[:, i] * lv.amplitude * sc
                a.errorbar(lv.freq, amp, yerr=err, marker="o", ms=3, capsize=2, color=col,
                           label=level_label(lv, units))
            a.axhline(result.budget.total[i] * sc, color="crimson", ls="--",
                      label="instrumentation noise σ")
            a.set_yscale("log")
            a.set_title(f"error in {AXES[i]} [{u[i]}]")
            a.set_xlabel("frequency [Hz]")
            a.set_ylabel(f"|Ĥ − H| amplitude [{u[i]}]")
            a.grid(True, which="both", alpha=0.3)
        fig.legend(*axs.flat[0].get_legend_handles_labels(), loc="outside lower center",
                   ncol=len(lvls) + 1, fontsize=9)
        fig.suptitle(f"Static-model estimation error for {AXES[axis]} excitation "
                     f"(report Eq 1.5, Figs 6-17; nominal angles, {result.frame} axes)")
        p = out / f"sweep_error_{AXES[axis]}.png"
        save_figure(fig, p, dpi=100)
        plt.close(fig)
        paths.append(p)

    # the reconstructed unmodelled load: gain and phase vs frequency (report Fig 18)
    shown = [(AXES.index(f["excitation"]), AXES.index(f["component"]))
             for f in findings(result)][:MAX_FINDING_ROWS]
    if shown:
        fig, axs = plt.subplots(len(shown), 2, figsize=(12, 3.4 * len(shown) + 1.2),
                                squeeze=False, layout="constrained")
        for r, (e, c) in enumerate(shown):
            gs = _gain_scale(c, e, units)
            for k, lv in enumerate(by_axis[e]):
                col = cmap(0.15 + 0.7 * k / max(1, len(by_axis[e]) - 1))
                g = lv.G_u[:, c]
                s = lv.sigma_G_u[:, c]
                axs[r, 0].errorbar(lv.freq, np.abs(g) * gs, yerr=s * gs, marker="o", ms=3,
                                   capsize=2, color=col, label=level_label(lv, units))
                ph_err = np.degrees(np.minimum(s / np.maximum(np.abs(g), 1e-300), math.pi))
                axs[r, 1].errorbar(lv.freq, phase_deg(g), yerr=ph_err, marker="o", ms=3,
                                   capsize=2, color=col, label=level_label(lv, units))
            axs[r, 1].axhline(180.0, color="k", ls=":", label="180° (elastic)")
            axs[r, 1].set_ylim(0, 360)
            axs[r, 1].set_yticks(range(0, 361, 45))
            name = COMPONENT_NAMES[c]
            axs[r, 0].set_title(f"Unmodelled {name} per unit {AXES[e]} excitation")
            axs[r, 1].set_title(f"Phase of the unmodelled {name} relative to {AXES[e]}")
            axs[r, 0].set_ylabel(f"|gain| [{gain_units(c, e, units)}]")
            axs[r, 1].set_ylabel("phase [deg]")
            for a in axs[r]:
                a.set_xlabel("frequency [Hz]")
                a.grid(True, alpha=0.3)
                a.legend(fontsize=8, loc="best")
        fig.suptitle("Reconstructed unmodelled load at the CG, I − S T − R H (report Fig 18)")
        p = out / "sweep_unmodelled_phase.png"
        save_figure(fig, p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths
