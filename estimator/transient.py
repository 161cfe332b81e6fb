"""Honest transients: the load filter's lag behind a moving static load (model.md
§6.1 "Transients").

The fixed-gain load filter (model §6, τ = 0.1 s) models the static hub load as a random
walk whose process noise is set for the held load. When the static load moves — a 0.5 s
ramp between ground-test conditions, a manoeuvre — the filter lags by about rate × τ, its
innovations are biased, and neither Ĥ nor the NIS is within the σ it was designed with
(measured on `ground-test`: 35 % of the NIS outside the χ²₆ band while the load moves, the
N error 3.8× its bound). The filter is not changed (the gain stays fixed, as model §6 says); the
samples are **flagged** `transient` instead, and the σ that holds there is the static bound
of `H_static` (model §3), which has no lag.

The detector: the whitened innovations ``w = L⁻¹ e`` (B = L Lᵀ, the filter's innovation
covariance) pass through a first-order smoother ``s' = (1 − β) s + β w`` with time constant
``time_constant_s`` (β = Δt / τ_d). As the filter's own model predicts them (a held load,
:func:`estimator.identification.innovation_model`), s is Gaussian with a stationary covariance
Σ_s, computed exactly from the fixed-gain loop by one discrete Lyapunov equation (the
innovations of a fixed gain are coloured; Σ_s is not β/(2 − β) I). A sample is `transient`
when ``q = sᵀ Σ_s⁻¹ s`` exceeds the χ²₆ point of ``false_alarm`` (10⁻³): a lag of about one σ
sustained over τ_d is found within a few samples, white noise is flagged in 10⁻³ of the
samples. Pure numerics; one design's constants are cached per design.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
from scipy.stats import chi2

from .identification import innovation_model

if TYPE_CHECKING:
    from .filters import FilterDesign

TRANSIENT = "transient"  # the hub_loads flag (docs/telemetry.md)
FALSE_ALARM = 1e-3
TIME_CONSTANT_FRACTION = 0.25  # τ_d = this × the filter's time constant
MAX_DESIGNS = 64  # cached constants (bounded, as the design cache)


def smoothed_innovation_covariance(design: FilterDesign, beta: float) -> np.ndarray:
    """Σ_s (6, 6): the stationary covariance of s' = (1 − β) s + β L⁻¹ e under the filter's
    own model (held load, white measurement noise W, process noise Q_d, fixed gain K)."""
    A, G, C, D, U = innovation_model(design.Phi, design.K, design.J, design.Qd, design.W, None)
    Linv = np.linalg.inv(np.linalg.cholesky(design.B))
    n = A.shape[0]
    Aa = np.zeros((n + 6, n + 6))
    Aa[:n, :n] = A
    Aa[n:, :n] = beta * Linv @ C
    Aa[n:, n:] = (1.0 - beta) * np.eye(6)
    Ga = np.vstack([G, beta * Linv @ D])
    Sig = scipy.linalg.solve_discrete_lyapunov(Aa, Ga @ U @ Ga.T)
    S = Sig[n:, n:]
    out: np.ndarray = 0.5 * (S + S.T)
    return out


class TransientDetector:
    """Per-sample `transient` decision from the load filter's innovations (module doc).

    The smoother is kept as v = Σ_s^-½ L⁻¹ s_e with s_e' = (1 − β) s_e + β e (the raw
    innovations; a redesign converts v through s_e), so q = |v|²: one 6×6 product and two
    small in-place updates per sample."""

    def __init__(self, dt: float, time_constant_s: float, false_alarm: float = FALSE_ALARM):
        if not (time_constant_s > 0 and dt > 0):
            raise ValueError("the transient detector needs a positive time constant and dt")
        self.beta = min(1.0, float(dt) / float(time_constant_s))
        self.threshold = float(chi2.isf(false_alarm, 6))
        self._s = np.zeros(6)
        self._consts: dict[int, tuple[object, np.ndarray]] = {}
        self._design: FilterDesign | None = None
        self._M = self._Mb = np.zeros((6, 6))
        self.q = 0.0

    def _matrix(self, design: FilterDesign) -> np.ndarray:
        c = self._consts.get(id(design))
        if c is None or c[0] is not design:
            if len(self._consts) >= MAX_DESIGNS:
                self._consts.clear()
            Linv = np.linalg.inv(np.linalg.cholesky(design.B))
            S = smoothed_innovation_covariance(design, self.beta)
            c = (design, np.linalg.inv(np.linalg.cholesky(S)) @ Linv)
            self._consts[id(design)] = c
        return c[1]

    def reset(self) -> None:
        self._s[:] = 0.0
        self.q = 0.0

    def update(self, design: FilterDesign, e: np.ndarray | None) -> bool:
        """One sample's innovation ``e`` (None: predict-only — the state is kept, no flag)."""
        if e is None:
            return False
        if design is not self._design:
            M = self._matrix(design)
            if self._design is not None:  # carry the smoothed innovation over: v = M s_e
                self._s[:] = M.dot(np.linalg.solve(self._M, self._s))
            self._M, self._Mb, self._design = M, self.beta * M, design
        v = self._s  # = Σ_s^-½ L⁻¹ s_e
        v *= 1.0 - self.beta
        v += self._Mb.dot(e)
        self.q = q = float(v.dot(v))
        return q > self.threshold
