"""The filtered hub loads' own error σ: what the load filter can and cannot follow .

The fixed-gain filter (``estimator.filters``, model §6) publishes Ĥ = C x⁺. With the static
estimate H_s = R⁻¹ (z − S T) and the innovation e = z − S T − J x⁻ (J = R C),

    Ĥ = H_s − G e,        G = R⁻¹ − C K        (exact, any gain K of this form)

so the error Ĥ − H = (H_s − H) − G e. Split the innovations into the part the design's model
predicts (held load with the design's process noise Q_d, white noise W: covariance B) and the
part it does not describe, e_u (load content outside the model: broadband loads, a ramp's
lag). The error's part from e_u is exactly −G e_u, so the error covariance is

    Σ = C P⁺ Cᵀ + G Cov(e_u) Gᵀ,     Cov(e_u) = E[e eᵀ] − B

* ``C P⁺ Cᵀ`` — the design's steady-state covariance of Ĥ for the modelled content
  (P⁺ = (I − K J) P⁻ (I − K J)ᵀ + K W Kᵀ, P⁻ the design's fixed-gain error covariance): noise
  through the filter and the design's own process noise;
* ``G (M − B) Gᵀ`` — what the innovations show the model does not describe: M an on-line
  estimate of E[e eᵀ] (not centred: a ramp's biased innovations count). Two exponential
  averages of u uᵀ, u = R⁻¹ e (hub axes: the same quantity whatever the design): a fast one
  (time constant ``FAST_FRACTION`` × the filter's τ) that widens σ within a few samples of a
  ramp's start, and a slow one (``SLOW_FRACTION`` × τ) that holds σ through the quiet spells of
  broadband loads; per axis the larger excess is used, never below 0 (a quieter load than the
  design's is not credited). Both start at the design's B; the slow one takes samples only
  from ``SETTLE_FRACTION`` × τ after the start on (the filter's own start from a zero state —
  80 kN of thrust to reach — is not a load the model misses; the fast average covers those
  samples). Bounded: two 6 × 6 matrices of state, no history.

**The floor:** the published σ is never below the static bound (``floor``): the filter averages
the noise, but what H_s and Ĥ share at the frequencies the filter follows — an unmodelled load
path at a modelled harmonic (``sweep``'s external load, measured 2.5 % of L beyond 3 ×
sqrt(diag Σ) without it) — is in no innovation; the static bound is the accuracy the noise
budget states for both.

The published σ is per axis ``sqrt(diag Σ)``, floored (``sigma_filter`` of the `hub_loads` record,
docs/telemetry.md): the error σ of the filtered H is ``sqrt(sigma_angles² + sigma_filter²)``
(docs/identification.md). The class takes the design's matrices (Φ, K, J, C, W, R, P⁻, B) and
nothing else of the filter's formulation, so another state layout with the same measurement
form keeps it valid. Pure numerics.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .filters import FilterDesign

FAST_FRACTION = 1.0  # fast average: this × the filter's time constant
SLOW_FRACTION = 20.0  # slow average: this × the filter's time constant
SETTLE_FRACTION = 5.0  # the slow average takes samples from this × τ after the start on
MAX_DESIGNS = 64  # cached constants (bounded, as the design cache)


def modelled_covariance(design: FilterDesign) -> np.ndarray:
    """C P⁺ Cᵀ (6, 6): the design's steady-state covariance of Ĥ − H for its own model."""
    n = design.n_states
    IKJ = np.eye(n) - design.K @ design.J
    P = IKJ @ design.P_minus @ IKJ.T + design.K @ design.W @ design.K.T
    S = design.C @ P @ design.C.T
    out: np.ndarray = 0.5 * (S + S.T)
    return out


def error_gain(design: FilterDesign) -> np.ndarray:
    """G' (6, 6) with Ĥ − H = (H_s − H) − G' u, u = R⁻¹ e: G' = (R⁻¹ − C K) R = I − C K R."""
    G: np.ndarray = np.eye(6) - design.C @ design.K @ design.R
    return G


class _Consts:
    __slots__ = ("B_u", "G", "Rinv", "design", "diag", "g2", "modelled")

    def __init__(self, design: FilterDesign) -> None:
        assert design.R is not None  # design_filter sets it
        Rinv = np.linalg.inv(design.R)
        self.design = design
        self.Rinv = Rinv
        self.modelled = np.diag(modelled_covariance(design)).copy()
        Bu = Rinv @ design.B @ Rinv.T
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
                 floor: np.ndarray | None = None) -> None:
        if not (dt > 0 and time_constant_s > 0):
            raise ValueError("FilterSigma needs a positive dt and time constant")
        # σ never below this (6,): the static bound — the filter averages the noise, not what
        # H_static and H share (an unmodelled load path at a modelled frequency, module doc)
        self.floor = None if floor is None else np.asarray(floor, float).copy()
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
            c = _Consts(design)
            self._consts[id(design)] = c
        return c

    def reset(self) -> None:
        self._Mf[:] = 0.0
        self._Ms[:] = 0.0
        self._started = False
        self._n = 0
        self.sigma = None

    def modelled_sigma(self, design: FilterDesign) -> np.ndarray:
        """The design's term alone: sqrt(diag C P⁺ Cᵀ)."""
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
                       floor: np.ndarray | None = None) -> np.ndarray:
    """The σ of :class:`FilterSigma` for a whole array of innovations (N, 6) of one design,
    every sample measured (off-line: bench, tests). Equal to the per-sample path to rounding."""
    from scipy.signal import lfilter

    c = _Consts(design)
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
