"""The filtered hub loads' own error σ: what the load filter can and cannot follow.

The fixed-gain filter (``estimator.filters``, model §6) publishes Ĥ = C x⁺. With the static
estimate H_s = R⁻¹ (z − S T) and the innovation e = z − S T − J x⁻ (J = R C),

    Ĥ = H_s − G e,        G = R⁻¹ − C K        (exact, any gain K of this form)

so the error Ĥ − H = (H_s − H) − G e. Three parts (derivation: docs/model.md §6.2):

* the sensors' noise W_s (the config's cell and accelerometer accuracy; the design's W unless
  ``noise`` is given) through the fixed gain for a **held** load: ``C P⁺₀ Cᵀ`` with P⁻₀ the
  fixed-gain error loop driven by the noise alone (no process noise: with the report's
  time-constant gain the design's Q_d only shapes the gain; a real load does not wander as that
  random walk — what it does do is in the innovations), B₀ = J P⁻₀ Jᵀ + W_s its innovation
  covariance (:func:`held_load_covariance`);
* hub-load content the held model does not describe (broadband loads, a ramp's lag): H_s
  carries it without error, so its error is exactly −G e_l: ``G (M − B₀) Gᵀ``, M an on-line
  estimate of E[e eᵀ] (not centred: a ramp's biased innovations count). Two exponential
  averages of u uᵀ, u = R⁻¹ e (hub axes: the same quantity whatever the design): a fast one
  (time constant ``FAST_FRACTION`` × the filter's τ) that widens σ within a few samples of a
  ramp's start, and a slow one (``SLOW_FRACTION`` × τ) that holds σ through the quiet spells of
  broadband loads; per axis the larger excess is used, never below 0 (a quieter load than the
  model's is not credited). Both start at B₀; the slow one takes samples only from
  ``SETTLE_FRACTION`` × τ after the start on (the filter's own start from a zero state — 80 kN
  of thrust to reach — is not a load the model misses; the fast average covers those
  samples). Bounded: two 6 × 6 matrices of state, no history;
* load the balance carries that is no hub load — an unmodelled load path at a modelled
  harmonic: H_s and Ĥ share it and no innovation shows it. A reference balance on the bus
  does (:class:`ReferenceSigma`, applied by the pipeline after this class's σ).

The σ of this class is per axis ``sqrt(diag Σ)`` (``sigma_filter`` of the `hub_loads` record
before the reference's widening, docs/telemetry.md): the error σ of the filtered H is
``sqrt(sigma_angles² + sigma_filter²)`` (docs/identification.md). ``floor`` (optional, not
used by the service: the former rule, kept for comparisons) bounds it from below. The class
takes the design's matrices (Φ, K, J, C, W, R) and nothing else of the filter's formulation, so
another state layout with the same measurement form keeps it valid. Pure numerics.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .filters import FilterDesign

FAST_FRACTION = 1.0  # fast average: this × the filter's time constant
SLOW_FRACTION = 20.0  # slow average: this × the filter's time constant
SETTLE_FRACTION = 5.0  # the slow average takes samples from this × τ after the start on
MAX_DESIGNS = 64  # cached constants (bounded, as the design cache)


def held_load_covariance(design: FilterDesign,
                         W: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P⁻₀, B₀): the fixed gain's error covariance before the update and its innovation
    covariance J P⁻₀ Jᵀ + W when the load is held (the harmonics' and the random walks'
    amplitudes constant): the measurement noise ``W`` (the design's unless given) through the
    gain alone, P⁻₀ = A P⁻₀ Aᵀ + Φ K W Kᵀ Φᵀ, A = Φ (I − K J) — no process noise."""
    from scipy.linalg import solve_discrete_lyapunov

    W = design.W if W is None else np.asarray(W, float)
    A = design.Phi @ (np.eye(design.n_states) - design.K @ design.J)
    P = solve_discrete_lyapunov(A, design.Phi @ design.K @ W @ design.K.T @ design.Phi.T)
    P = 0.5 * (P + P.T)
    B = design.J @ P @ design.J.T + W
    return P, 0.5 * (B + B.T)


def modelled_covariance(design: FilterDesign, W: np.ndarray | None = None) -> np.ndarray:
    """C P⁺₀ Cᵀ (6, 6): the steady-state covariance of Ĥ − H for a held load — the
    measurement noise ``W`` (the design's unless given) through the fixed gain."""
    n = design.n_states
    W = design.W if W is None else np.asarray(W, float)
    P0, _ = held_load_covariance(design, W)
    IKJ = np.eye(n) - design.K @ design.J
    P = IKJ @ P0 @ IKJ.T + design.K @ W @ design.K.T
    S = design.C @ P @ design.C.T
    out: np.ndarray = 0.5 * (S + S.T)
    return out


def error_gain(design: FilterDesign) -> np.ndarray:
    """G' (6, 6) with Ĥ − H = (H_s − H) − G' u, u = R⁻¹ e: G' = (R⁻¹ − C K) R = I − C K R."""
    G: np.ndarray = np.eye(6) - design.C @ design.K @ design.R
    return G


class _Consts:
    __slots__ = ("B_u", "G", "Rinv", "design", "diag", "g2", "modelled")

    def __init__(self, design: FilterDesign, W: np.ndarray | None = None) -> None:
        assert design.R is not None  # design_filter sets it
        Rinv = np.linalg.inv(design.R)
        self.design = design
        self.Rinv = Rinv
        self.modelled = np.diag(modelled_covariance(design, W)).copy()
        Bu = Rinv @ held_load_covariance(design, W)[1] @ Rinv.T
        self.B_u = 0.5 * (Bu + Bu.T)
        G = error_gain(design)
        off = G - np.diag(np.diag(G))
        # the report's time-constant gain: G' diagonal (each hub axis its own filter)
        self.diag = bool(np.max(np.abs(off)) <= 1e-12 * max(1.0, float(np.max(np.abs(G)))))
        self.G = G
        self.g2 = np.diag(G) ** 2


class FilterSigma:
    """Per-sample σ of the filtered hub loads (module doc). ``update(design, e)`` once per
    sample with the load filter's design and innovation (None on a predict-only sample: σ
    stays, the averages are not fed); ``sigma`` the (6,) σ, N and N·m, hub axes."""

    def __init__(self, dt: float, time_constant_s: float,
                 floor: np.ndarray | None = None, noise: np.ndarray | None = None) -> None:
        if not (dt > 0 and time_constant_s > 0):
            raise ValueError("FilterSigma needs a positive dt and time constant")
        # σ never below this (6,) if given: the former rule (comparisons, module doc)
        self.floor = None if floor is None else np.asarray(floor, float).copy()
        self.noise = None if noise is None else np.asarray(noise, float).copy()
        self.beta_fast = min(1.0, dt / (FAST_FRACTION * time_constant_s))
        self.beta_slow = min(1.0, dt / (SLOW_FRACTION * time_constant_s))
        self._Mf = np.zeros((6, 6))
        self._Ms = np.zeros((6, 6))
        self._started = False
        self.settle = int(np.ceil(SETTLE_FRACTION * time_constant_s / dt))
        self._n = 0  # samples taken since the start
        self._consts: dict[int, _Consts] = {}
        self.sigma: np.ndarray | None = None

    def _for(self, design: FilterDesign) -> _Consts:
        c = self._consts.get(id(design))
        if c is None or c.design is not design:
            if len(self._consts) >= MAX_DESIGNS:
                self._consts.clear()
            c = _Consts(design, self.noise)
            self._consts[id(design)] = c
        return c

    def reset(self) -> None:
        self._Mf[:] = 0.0
        self._Ms[:] = 0.0
        self._started = False
        self._n = 0
        self.sigma = None

    def modelled_sigma(self, design: FilterDesign) -> np.ndarray:
        """The held load's term alone: sqrt(diag C P⁺₀ Cᵀ) (the sensors' noise through the gain)."""
        return np.sqrt(self._for(design).modelled)

    def update(self, design: FilterDesign, e: np.ndarray | None) -> np.ndarray | None:
        c = self._for(design)
        if e is None:
            return self.sigma
        u = c.Rinv.dot(e)
        uu = np.multiply.outer(u, u)
        if not self._started:  # start at the design's own innovation covariance
            self._Mf[:] = c.B_u
            self._Ms[:] = c.B_u
            self._started = True
        self._Mf += self.beta_fast * (uu - self._Mf)
        if self._n >= self.settle:
            self._Ms += self.beta_slow * (uu - self._Ms)
        self._n += 1
        if c.diag:
            ex = np.maximum(np.diagonal(self._Mf), np.diagonal(self._Ms)) - np.diagonal(c.B_u)
            var = c.modelled + c.g2 * np.maximum(ex, 0.0)
        else:
            Df, Ds = self._Mf - c.B_u, self._Ms - c.B_u
            ef = np.einsum("ij,jk,ik->i", c.G, Df, c.G)
            es = np.einsum("ij,jk,ik->i", c.G, Ds, c.G)
            var = c.modelled + np.maximum(np.maximum(ef, es), 0.0)
        self.sigma = np.sqrt(var)
        if self.floor is not None:
            np.maximum(self.sigma, self.floor, out=self.sigma)
        return self.sigma


def filter_sigma_batch(design: FilterDesign, e: np.ndarray, dt: float, time_constant_s: float,
                       floor: np.ndarray | None = None,
                       noise: np.ndarray | None = None) -> np.ndarray:
    """The σ of :class:`FilterSigma` for a whole array of innovations (N, 6) of one design,
    every sample measured (off-line: bench, tests). Equal to the per-sample path to rounding."""
    from scipy.signal import lfilter

    c = _Consts(design, noise)
    fs = FilterSigma(dt, time_constant_s)
    u = np.asarray(e, float) @ c.Rinv.T
    N = u.shape[0]
    if N == 0:
        return np.zeros((0, 6))

    def ewma(x: np.ndarray, beta: float, x0: np.ndarray) -> np.ndarray:
        # m(n) = (1 − β) m(n−1) + β x(n), m(−1) = x0
        zi = ((1.0 - beta) * x0)[None, :]
        m: np.ndarray = lfilter([beta], [1.0, -(1.0 - beta)], x, axis=0, zi=zi)[0]
        return m

    k = min(fs.settle, N)  # the slow average's settling: held at its start

    def slow(x: np.ndarray, x0: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        out[:k] = x0
        if k < N:
            out[k:] = ewma(x[k:], fs.beta_slow, x0)
        return out

    if c.diag:
        x = u * u
        b0 = np.diagonal(c.B_u)
        mf = ewma(x, fs.beta_fast, b0)
        ms = slow(x, b0)
        var = c.modelled + c.g2 * np.maximum(np.maximum(mf, ms) - b0, 0.0)
    else:
        x = (u[:, :, None] * u[:, None, :]).reshape(N, 36)
        b0 = c.B_u.reshape(36)
        mf = ewma(x, fs.beta_fast, b0).reshape(N, 6, 6) - c.B_u
        ms = slow(x, b0).reshape(N, 6, 6) - c.B_u
        ef = np.einsum("ij,njk,ik->ni", c.G, mf, c.G)
        es = np.einsum("ij,njk,ik->ni", c.G, ms, c.G)
        var = c.modelled + np.maximum(np.maximum(ef, es), 0.0)
    out: np.ndarray = np.sqrt(var)
    return out if floor is None else np.maximum(out, np.asarray(floor, float))


class ReferenceSigma:
    """What a reference balance on the bus shows of the filtered loads' error (module doc):
    ``update(d)`` once per sample with d = Ĥ − H_ref, the published Ĥ less the reference's
    reading (in the hub loads' frame), ``widen(sigma)`` the σ no smaller than the error the
    reference shows. d = Ĥ − H_ref = (Ĥ − H) − n_ref, so E[d²] − σ_ref² is the
    error's variance, whatever its cause — an unmodelled load path at a modelled harmonic
    included, which neither H_static nor the innovations can show. Two exponential averages
    of d² as :class:`FilterSigma`'s (fast, and slow from the settling on), the larger used.
    No reference reading: the averages hold (and widen nothing before the first). Bounded:
    three (6,) vectors of state."""

    def __init__(self, dt: float, time_constant_s: float, noise_var: np.ndarray) -> None:
        if not (dt > 0 and time_constant_s > 0):
            raise ValueError("ReferenceSigma needs a positive dt and time constant")
        self.noise_var = np.asarray(noise_var, float).copy()  # (6,) the reference's σ²
        self.beta_fast = min(1.0, dt / (FAST_FRACTION * time_constant_s))
        self.beta_slow = min(1.0, dt / (SLOW_FRACTION * time_constant_s))
        self.settle = int(np.ceil(SETTLE_FRACTION * time_constant_s / dt))
        self._mf = np.zeros(6)
        self._ms = np.zeros(6)
        self._w = 0.0  # the slow average's weight so far (its start's bias removed)
        self._n = 0  # reference samples taken
        self.excess: np.ndarray | None = None  # (6,) the error variance shown, ≥ 0

    def reset(self) -> None:
        self._mf[:] = 0.0
        self._ms[:] = 0.0
        self._w = 0.0
        self._n = 0
        self.excess = None

    def update(self, d: np.ndarray) -> None:
        """One sample's d = Ĥ − H_ref (6,); not all finite: not taken."""
        d2 = d * d
        if not math.isfinite(float(d2.sum())):
            return
        mf, ms = self._mf, self._ms
        if self._n == 0:
            mf[:] = d2
        mf += self.beta_fast * (d2 - mf)
        if self._n >= self.settle:  # the slow average: from 0, divided by its weight so far
            ms += self.beta_slow * (d2 - ms)
            self._w += self.beta_slow * (1.0 - self._w)
            np.maximum(mf, ms / self._w, out=d2)
        else:
            d2[:] = mf
        self._n += 1
        d2 -= self.noise_var
        self.excess = np.maximum(d2, 0.0, out=d2)

    def widen(self, sigma: np.ndarray) -> np.ndarray:
        """σ per axis no smaller than the error the reference shows (a new array)."""
        if self.excess is None:
            return sigma
        out: np.ndarray = np.sqrt(np.maximum(np.asarray(sigma, float) ** 2, self.excess))
        return out
