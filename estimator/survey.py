"""The loads survey's numerics: per test point and hub-load axis, the steady and alternating
load, the harmonics on the measured azimuth, the peaks and the fatigue cycles, each with its
1 σ (docs/user-guide.md, "Loads survey"). Pure: numpy arrays in, numbers out, no I/O.

**The error model of a test point.** The estimate of one axis over the N samples of a point is
``y = y_true + e`` with ``e = e_angles + e_noise``:

* ``e_angles``, the error of the angles in force, is *common to the whole point*: an error δα
  of the angles moves sample i by ``−A T_i δα`` (``A = R⁻¹ ∂S/∂α``, one row of it per axis,
  estimator/angle_uncertainty.py) with ``δα ~ N(0, P)``, the same δα for every sample. So a
  linear functional ``w·y`` (a mean, a harmonic coefficient) has the angle error
  ``−(Σ w_i T_i) A δα``, of variance ``(Σ w_i T_i) A P Aᵀ (Σ w_i T_i)ᵀ``: it never shrinks
  with N. Without the cell loads and the covariance, the published per-sample ``σ_angles``
  bounds it: ``|Σ w_i σ_i|`` taken fully correlated (the σ of a sample is a seminorm of its
  cell loads, so this is an upper bound).
* ``e_noise``: for the filtered ``H`` the filter's own error, published as ``sigma_filter``,
  *coloured over the filter's time constant* τ: an AR(1) process of correlation
  ``ρ = exp(−Δt/τ)`` between neighbouring samples; for ``H_static`` the noise bound, white
  (ρ = 0). The variance of ``w·e`` is ``Σ_ij w_i σ_i w_j σ_j ρ^|i−j|``, summed exactly (two
  passes of a first-order recursion), so a mean over a point of duration T has about
  ``σ² 2τ/T``, never ``σ²/N``.

Nonlinear quantities (amplitude and phase, std, alternating, peaks) take their σ from the
linearisation about the estimate (the functional is the gradient); the rainflow counts and the
damage-equivalent loads from Monte Carlo draws of ``e`` (:func:`draw_errors`).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

TWO_PI = 2.0 * math.pi


# ---------------------------------------------------------------------------------------------
# the error model


@dataclass(frozen=True)
class ErrorModel:
    """The error of one axis's estimate over a test point (module docstring).

    ``sigma_noise`` (N,) per-sample σ of the non-angle error, correlated with ``rho`` between
    neighbouring samples. The angle error: ``T`` (N, 7) the cell loads with ``sens`` (7, n)
    the axis's row of ``A`` times a square root of the angles' covariance (``A_k L``, with
    ``P = L Lᵀ``), so that sample i's error is ``−T_i sens z`` for one ``z ~ N(0, I)`` per
    point; or, without them (or on the samples whose cell loads are missing),
    ``sigma_angles`` (N,) per sample, taken fully correlated."""

    sigma_noise: np.ndarray
    rho: float
    T: np.ndarray | None = None
    sens: np.ndarray | None = None
    sigma_angles: np.ndarray | None = None
    #: where the coloured error's power may sit: 0 the low frequencies, k a band around k/rev
    #: on the measured azimuth ``psi`` (a filter with harmonic states errs there too). A
    #: functional's variance is taken in the band where it is largest (conservative).
    bands: tuple[int, ...] = (0,)
    psi: np.ndarray | None = None

    def subset(self, idx: np.ndarray | slice) -> ErrorModel:
        return ErrorModel(self.sigma_noise[idx], self.rho,
                          None if self.T is None else self.T[idx], self.sens,
                          None if self.sigma_angles is None else self.sigma_angles[idx],
                          self.bands, None if self.psi is None else self.psi[idx])

    @property
    def has_angle_covariance(self) -> bool:
        return self.T is not None and self.sens is not None


def _two_sided(u: np.ndarray, rho: float) -> np.ndarray:
    """``g_i = Σ_j ρ^|i−j| u_j`` along the last axis (forward and backward recursions)."""
    if rho <= 0.0:
        return u.copy()
    fwd = lfilter([1.0], [1.0, -rho], u, axis=-1)
    bwd = lfilter([1.0], [1.0, -rho], u[..., ::-1], axis=-1)[..., ::-1]
    result: np.ndarray = fwd + bwd - u
    return result


def _band_cov(U: np.ndarray, rho: float, k: int, psi: np.ndarray | None) -> np.ndarray:
    """``Σ_ij u_i u_j ρ^|i−j| cos k(ψ_i − ψ_j)``: an AR(1) envelope around k/rev."""
    if k == 0 or psi is None or rho <= 0.0:
        result: np.ndarray = U @ _two_sided(U, rho).T
        return result
    ph = np.exp(1j * k * psi)[None, :]
    G = _two_sided(U * ph.conj(), rho)
    return np.real((U * ph) @ G.T)


def functional_cov(W: np.ndarray, model: ErrorModel,
                   groups: Sequence[Sequence[int]] | None = None) -> np.ndarray:
    """Covariance (m, m) of the errors of the linear functionals ``W @ y`` (W: (m, N)). The
    coloured part per group of rows (default each row) in the band where its trace is
    largest."""
    W = np.atleast_2d(np.asarray(W, float))
    U = W * model.sigma_noise[None, :]
    bands = [_band_cov(U, model.rho, k, model.psi) for k in model.bands]
    C: np.ndarray = bands[0].copy()
    for g in groups if groups is not None else [[i] for i in range(W.shape[0])]:
        ix = np.ix_(list(g), list(g))
        best = max(bands, key=lambda B: float(np.trace(B[ix])))
        C[ix] = best[ix]
    rest = np.ones(W.shape[1], bool)  # the samples whose angle error is only bounded
    if model.has_angle_covariance:
        assert model.T is not None and model.sens is not None
        good = np.isfinite(model.T).all(axis=1)
        B = (W[:, good] @ model.T[good]) @ model.sens  # (m, n)
        C = C + B @ B.T
        rest = ~good
    if model.sigma_angles is not None and rest.any():
        s = np.abs(W[:, rest]) @ model.sigma_angles[rest]
        C = C + np.outer(s, s)
    result: np.ndarray = 0.5 * (C + C.T)
    return result


def functional_sigma(W: np.ndarray, model: ErrorModel) -> np.ndarray:
    return np.sqrt(np.maximum(np.diag(functional_cov(W, model)), 0.0))


def draw_errors(model: ErrorModel, draws: int, rng: np.random.Generator) -> np.ndarray:
    """``draws`` error series (draws, N) from the model: one angle error per draw, common to
    the point, and the coloured noise (AR(1) of unit variance scaled per sample)."""
    n = len(model.sigma_noise)
    white = rng.standard_normal((draws, n))
    if model.rho > 0.0:
        white[:, 1:] *= math.sqrt(1.0 - model.rho ** 2)
        white = lfilter([1.0], [1.0, -model.rho], white, axis=-1)
    e = white * model.sigma_noise[None, :]
    rest = np.ones(n, bool)
    if model.has_angle_covariance:
        assert model.T is not None and model.sens is not None
        good = np.isfinite(model.T).all(axis=1)
        z = rng.standard_normal((draws, model.sens.shape[1]))
        e[:, good] -= z @ (model.T[good] @ model.sens).T
        rest = ~good
    if model.sigma_angles is not None and rest.any():
        e[:, rest] += rng.standard_normal((draws, 1)) * model.sigma_angles[None, rest]
    result: np.ndarray = e
    return result


# ---------------------------------------------------------------------------------------------
# azimuth, revolutions, harmonics


def unwrap_azimuth(psi: np.ndarray) -> np.ndarray:
    """The measured azimuth (0 … 2π per turn, NaN where missing) made continuous: it counts
    turns from its zero, so ``floor(ψ/2π)`` numbers the revolutions."""
    psi = np.asarray(psi, float)
    out = np.full(len(psi), np.nan)
    ok = np.isfinite(psi)
    if ok.any():
        out[ok] = np.unwrap(psi[ok])
    return out


def whole_revolutions(psi_u: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [i0, i1) of the whole revolutions in a continuous azimuth: the samples of
    one turn number ``floor(ψ/2π)``, where the turn is seen from its start to its end (the
    first and last, partial turns are left out; a turn with a missing azimuth too)."""
    psi_u = np.asarray(psi_u, float)
    n = len(psi_u)
    if n < 3:
        return []
    ok = np.isfinite(psi_u)
    turn = np.where(ok, np.floor(np.where(ok, psi_u, 0.0) / TWO_PI), np.nan)
    revs = []
    i = 0
    while i < n:
        if not ok[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and ok[j + 1] and turn[j + 1] == turn[i]:
            j += 1
        # whole: bounded on both sides by a finite sample of the previous and next turn
        if i > 0 and j + 1 < n and ok[i - 1] and ok[j + 1] and turn[i - 1] == turn[i] - 1 \
                and turn[j + 1] == turn[i] + 1:
            revs.append((i, j + 1))
        i = j + 1
    return revs


def harmonic_design(psi_u: np.ndarray, orders: Sequence[int]) -> np.ndarray:
    """Columns ``[1, cos kψ, sin kψ …]`` for each order k (N, 1 + 2K)."""
    cols = [np.ones(len(psi_u))]
    for k in orders:
        cols += [np.cos(k * psi_u), np.sin(k * psi_u)]
    return np.column_stack(cols)


def harmonic_weights(psi_u: np.ndarray, orders: Sequence[int]) -> np.ndarray:
    """The least-squares weights W (1 + 2K, N): ``W @ y`` are the coefficients
    ``[c0, a1, b1, …]`` of ``y ≈ c0 + Σ a_k cos kψ + b_k sin kψ`` on the measured azimuth —
    whatever the rotor speed does between samples."""
    X = harmonic_design(psi_u, orders)
    W: np.ndarray = np.linalg.pinv(X)
    return W


@dataclass(frozen=True)
class Harmonic:
    """``A cos(kψ − φ)``: amplitude, phase (degrees from the azimuth's zero) and their σ."""

    order: int
    amplitude: float
    amplitude_sigma: float
    phase_deg: float
    phase_sigma_deg: float


def amplitude_phase(a: float, b: float, cov: np.ndarray, order: int) -> Harmonic:
    """Amplitude and phase of ``a cos kψ + b sin kψ = A cos(kψ − φ)`` with σ linearised from
    the 2 × 2 covariance of (a, b); the phase σ is capped at 180°."""
    amp = math.hypot(a, b)
    phi = math.atan2(b, a)
    g = np.array([math.cos(phi), math.sin(phi)])
    h = np.array([-math.sin(phi), math.cos(phi)])
    s_amp = math.sqrt(max(float(g @ cov @ g), 0.0))
    s_phi = math.sqrt(max(float(h @ cov @ h), 0.0)) / amp if amp > 0 else math.inf
    return Harmonic(order, amp, s_amp, math.degrees(phi), min(math.degrees(s_phi), 180.0))


def harmonics(y: np.ndarray, psi_u: np.ndarray, orders: Sequence[int], model: ErrorModel,
              model_sigma: float = 0.0, scatter: dict[int, np.ndarray] | None = None
              ) -> list[Harmonic]:
    """Amplitude and phase of each order by least squares on the measured azimuth, σ from the
    error model plus ``model_sigma`` on each of the coefficients (a coherent model error at
    the harmonic, which no averaging removes). ``scatter``: per order a 2 × 2 covariance
    measured from the data (:func:`revolution_scatter`), used where it is the larger."""
    W = harmonic_weights(psi_u, orders)
    coef = W @ y
    groups = [[0]] + [[1 + 2 * n, 2 + 2 * n] for n in range(len(orders))]
    C = functional_cov(W, model, groups)
    out = []
    for n, k in enumerate(orders):
        i = 1 + 2 * n
        c = C[i:i + 2, i:i + 2]
        if scatter is not None and k in scatter and np.trace(scatter[k]) > np.trace(c):
            c = scatter[k]
        c = c + model_sigma ** 2 * np.eye(2)
        out.append(amplitude_phase(float(coef[i]), float(coef[i + 1]), c, k))
    return out


MIN_REVOLUTIONS = 8  # for a scatter of per-revolution coefficients to mean anything


def revolution_scatter(y: np.ndarray, psi_u: np.ndarray, revs: Iterable[tuple[int, int]],
                       fitted: Sequence[int], wanted: Sequence[int]
                       ) -> dict[int, np.ndarray]:
    """Per order in ``wanted``, the covariance (2 × 2) of the mean over R whole revolutions of
    its per-revolution coefficients (a, b) — each revolution fitted with every order of
    ``fitted``, its mean and a linear drift — from their scatter: ``cov / R``. It measures the
    error near that order as it is (the model's white noise misses coloured errors such as a
    vibration the inertial correction leaves); a true harmonic whose amplitude or phase
    varies widens it too (conservative). {} with fewer than ``MIN_REVOLUTIONS``."""
    fitted = list(fitted)
    coefs = []
    for i0, i1 in revs:
        p, seg = psi_u[i0:i1], y[i0:i1]
        if i1 - i0 <= 2 * len(fitted) + 2 or not np.isfinite(seg).all():
            continue
        drift = (p - TWO_PI * math.floor(p[0] / TWO_PI) - math.pi) / TWO_PI
        coefs.append(np.linalg.pinv(np.column_stack([harmonic_design(p, fitted), drift]))
                     @ seg)
    if len(coefs) < MIN_REVOLUTIONS:
        return {}
    c = np.asarray(coefs)
    out = {}
    for k in wanted:
        j = 1 + 2 * fitted.index(k)
        out[k] = np.cov(c[:, j:j + 2], rowvar=False) / len(c)
    return out


# ---------------------------------------------------------------------------------------------
# statistics of one axis over a point


@dataclass(frozen=True)
class Value:
    value: float
    sigma: float


def mean_std(y: np.ndarray, model: ErrorModel) -> tuple[Value, Value]:
    n = len(y)
    m = float(np.mean(y))
    s = float(np.std(y))
    W = np.vstack([np.full(n, 1.0 / n), (y - m) / (n * s) if s > 0 else np.zeros(n)])
    sig = functional_sigma(W, model)
    return Value(m, float(sig[0])), Value(s, float(sig[1]))


def peak(y: np.ndarray, model: ErrorModel, which: str) -> Value:
    i = int(np.argmax(y) if which == "max" else np.argmin(y))
    w = np.zeros(len(y))
    w[i] = 1.0
    return Value(float(y[i]), float(functional_sigma(w, model)[0]))


@dataclass(frozen=True)
class Revolutions:
    """Per whole revolution, the fit of the harmonics 1 … N_b/rev on the measured azimuth,
    with the revolution's mean and a linear drift across it: the half peak-to-peak of its
    periodic part (``halves``), the linear functional of the samples that gives each
    (``rows``, (R, N)), and the periodic part with the mean at the revolution's samples
    (``fit``, NaN outside whole revolutions). The fit takes the harmonics out of the noise,
    so the half peak-to-peak is not inflated by it (the raw peak-to-peak of a noisy series
    is); the drift term keeps a manoeuvre's quasi-static change within one revolution out of
    the alternating load (a fit of harmonics alone would fold it into them)."""

    halves: np.ndarray
    rows: np.ndarray
    fit: np.ndarray


def _revolution_fits(y: np.ndarray, psi_u: np.ndarray, revs: Iterable[tuple[int, int]],
                     orders: Sequence[int], grid: int
                     ) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(i0, i1, W, Xg) per usable revolution: its least-squares weights and the design on a
    fine grid of its azimuth (the continuous turn)."""
    out = []
    for i0, i1 in revs:
        p = psi_u[i0:i1]
        if i1 - i0 <= 2 * len(orders) + 2 or not np.isfinite(y[i0:i1]).all():
            continue
        base = TWO_PI * math.floor(p[0] / TWO_PI)
        g = base + np.linspace(0.0, TWO_PI, grid, endpoint=False)
        drift = (p - base - math.pi) / TWO_PI  # −½ … ½ across the turn
        W = np.linalg.pinv(np.column_stack([harmonic_design(p, orders), drift]))
        # evaluated without the drift: the periodic part (and the mean, which no
        # peak-to-peak sees)
        out.append((i0, i1, W, np.column_stack([harmonic_design(g, orders),
                                                np.zeros(grid)])))
    return out


def per_revolution(y: np.ndarray, psi_u: np.ndarray, revs: Iterable[tuple[int, int]],
                   orders: Sequence[int], grid: int = 360) -> Revolutions:
    n = len(y)
    halves, rows = [], []
    fit = np.full(n, np.nan)
    for i0, i1, W, Xg in _revolution_fits(y, psi_u, revs, orders, grid):
        c = W @ y[i0:i1]
        f = Xg @ c
        hi, lo = int(np.argmax(f)), int(np.argmin(f))
        w = np.zeros(n)
        w[i0:i1] = 0.5 * (Xg[hi] - Xg[lo]) @ W
        rows.append(w)
        halves.append(0.5 * (f[hi] - f[lo]))
        fit[i0:i1] = harmonic_design(psi_u[i0:i1], orders) @ c[:-1]
    return Revolutions(np.asarray(halves, float),
                       np.vstack(rows) if rows else np.zeros((0, n)), fit)


def _halves_of_draws(Y: np.ndarray, fits: list[tuple[int, int, np.ndarray, np.ndarray]]
                     ) -> np.ndarray:
    """Half peak-to-peak per revolution (R, D) of each series of Y (D, N)."""
    out = []
    for i0, i1, W, Xg in fits:
        F = Xg @ (W @ Y[:, i0:i1].T)  # (grid, D)
        out.append(0.5 * (F.max(axis=0) - F.min(axis=0)))
    return np.asarray(out)


def alternating(y: np.ndarray, psi_u: np.ndarray, revs: Sequence[tuple[int, int]],
                orders: Sequence[int], model: ErrorModel, model_sigma: float = 0.0,
                draws: int = 0, rng: np.random.Generator | None = None
                ) -> tuple[Value, Value] | None:
    """(the mean over whole revolutions of half the peak-to-peak of the per-revolution fit,
    the largest one), each with its σ (linearised; ``model_sigma``, a coherent model error,
    in quadrature); None without a whole revolution.

    A peak-to-peak is a convex function of the noisy coefficients, so noise inflates it (and
    the largest of R halves more, by the selection): with ``draws`` the bias is estimated from
    Monte Carlo draws of the error model and taken off (a parametric bootstrap correction)."""
    rv = per_revolution(y, psi_u, revs, orders)
    if not len(rv.halves):
        return None
    k = int(np.argmax(rv.halves))
    sig = np.hypot(functional_sigma(np.vstack([rv.rows.mean(axis=0), rv.rows[k]]), model),
                   model_sigma)
    mean, top = float(np.mean(rv.halves)), float(rv.halves[k])
    if draws and rng is not None:
        sims = _halves_of_draws(y[None, :] + draw_errors(model, draws, rng),
                                _revolution_fits(y, psi_u, revs, orders, 360))  # (R, D)
        mean -= float(np.mean(sims)) - mean
        top -= float(np.mean(sims.max(axis=0))) - top
        # the largest half is the noisiest statistic: which revolution wins varies with the
        # noise; the spread of its excess over that revolution's own half joins its σ
        excess = sims.max(axis=0) - sims[k]
        if len(excess) > 1:
            sig[1] = math.hypot(sig[1], float(np.std(excess, ddof=1)))
    return Value(mean, float(sig[0])), Value(top, float(sig[1]))


# ---------------------------------------------------------------------------------------------
# fatigue: rainflow (ASTM E1049-85, the `rainflow` package) and damage-equivalent loads


def turning_points(y: np.ndarray) -> np.ndarray:
    """The reversals of a series (its ends included): all that rainflow counting sees."""
    y = np.asarray(y, float)
    if len(y) < 3:
        return y
    d = np.diff(y)
    keep = d != 0
    y2 = np.concatenate([y[:1], y[1:][keep]])
    if len(y2) < 3:
        return y2
    d = np.diff(y2)
    rev = np.flatnonzero(d[:-1] * d[1:] < 0) + 1
    result: np.ndarray = y2[np.concatenate([[0], rev, [len(y2) - 1]])]
    return result


def rainflow_ranges(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ranges, counts): the rainflow cycles of ``y`` — a half cycle counts 0.5 (ASTM
    E1049-85 through the `rainflow` package; exact ranges, no binning)."""
    import rainflow  # type: ignore[import-untyped]  # (no annotations published)

    cyc = rainflow.count_cycles(turning_points(y))
    if not cyc:
        return np.zeros(0), np.zeros(0)
    arr = np.asarray(cyc, float)
    return arr[:, 0], arr[:, 1]


def damage_equivalent(ranges: np.ndarray, counts: np.ndarray, slope: float,
                      reference_cycles: float) -> float:
    """The constant range that does, in ``reference_cycles`` cycles, the damage (Miner's sum
    on an S-N curve of slope m) of the counted cycles: ``(Σ n_i S_i^m / N_ref)^(1/m)``."""
    if len(ranges) == 0:
        return 0.0
    return float((np.sum(counts * ranges ** slope) / reference_cycles) ** (1.0 / slope))


def fatigue(y: np.ndarray, slopes: Sequence[float], reference_cycles: float
            ) -> tuple[float, list[float]]:
    """(rainflow cycle count, [DEL per slope]) of the finite samples of ``y``."""
    r, c = rainflow_ranges(y[np.isfinite(y)])
    return float(np.sum(c)), [damage_equivalent(r, c, m, reference_cycles) for m in slopes]


def fatigue_sigma(y: np.ndarray, model: ErrorModel, slopes: Sequence[float],
                  reference_cycles: float, draws: int, rng: np.random.Generator
                  ) -> tuple[float, list[float]]:
    """σ of the cycle count and of each DEL from ``draws`` Monte Carlo draws of the error: the
    spread of the counting on ``y + e``, and the shift the draws show (noise adds small cycles
    and widens ranges: a bias of the counting on a noisy estimate, not a spread, which the
    model's error — larger than the filter's actual one — bounds from above) in quadrature."""
    e = draw_errors(model, draws, rng)
    out = np.array([[n, *d] for n, d in (fatigue(y + ei, slopes, reference_cycles)
                                         for ei in e)])
    if draws < 2:
        return math.nan, [math.nan] * len(slopes)
    n0, d0 = fatigue(y, slopes, reference_cycles)
    shift = out.mean(axis=0) - np.array([n0, *d0])
    sd = np.hypot(out.std(axis=0, ddof=1), shift)
    return float(sd[0]), [float(s) for s in sd[1:]]
