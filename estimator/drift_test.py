"""The drift test: angles on a trend, the time-varying candidate beside the load structures
(estimator.structure's docstring; docs/identification.md, "Angles that drift"): its own
bounded history of window means, its alpha spending, the trend's prediction, and the bound on
the drift the windows cannot exclude. Pure numerics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import brentq, minimize_scalar
from scipy.stats import chi2, norm

from .params import RigModel
from .structure_fits import (
    DRIFT_BOUND_LEVEL,
    FALSE_ALARM,
    MAX_DRIFT_WINDOWS,
    MAX_HELD_LOOKS,
    RANK_TOLERANCE,
    TIME_LEVEL,
    _range_basis,
    _stack,
    _unit_columns,
    _whitener,
    fit_constant_converged,
    spend,
)


@dataclass
class DriftVerdict:
    """The drift test at one look (the ``drift`` object of the ``angles`` record)."""

    rate: np.ndarray  # (14,) rad/s, the trend of each angle (0 where not determined)
    rate_sigma: np.ndarray  # (14,) rad/s, NaN where not determined
    rate_P: np.ndarray  # (14, 14) rad²/s², covariance of the rates
    statistic: float
    dof: int
    limit: float
    rejects_constant: bool  # at this look or earlier since the last restart
    explains: bool
    misfit: float
    misfit_dof: int
    windows: int
    span_s: float
    restarted: bool
    selected: bool  # the posterior may track with this trend

    def to_dict(self) -> dict[str, Any]:
        return {"rate": self.rate, "rate_sigma": self.rate_sigma, "statistic": self.statistic,
                "dof": self.dof, "limit": self.limit, "rejects_constant": self.rejects_constant,
                "explains": self.explains, "misfit": self.misfit, "misfit_dof": self.misfit_dof,
                "windows": self.windows, "span_s": self.span_s, "restarted": self.restarted,
                "selected": self.selected}


def rate_scale_bound(s: np.ndarray, b: np.ndarray, level: float = DRIFT_BOUND_LEVEL
                     ) -> tuple[float, float] | None:
    """The rates' prior variance s² of ρ ~ N(0, s² I) that the windows cannot exclude: from
    the rates' information S (r, r) after the constant angles are eliminated (Schur
    complement) and its score b, the marginal likelihood ρ̂ ~ N(0, S⁻¹ + s² I) on the
    determined directions; returns (ML estimate, the one-sided upper likelihood-ratio bound
    at ``level``), rad²/s², or None when no rate direction is determined."""
    lam, U = np.linalg.eigh(0.5 * (s + s.T))
    keep = lam > RANK_TOLERANCE**2 * lam[-1] if len(lam) and lam[-1] > 0 else lam > np.inf
    if not keep.any():
        return None
    v = 1.0 / lam[keep]
    y = (U[:, keep].T @ b) / lam[keep]

    def nll(ls: float) -> float:
        c = v + math.exp(ls)
        return 0.5 * float(np.sum(np.log(c) + y**2 / c))

    lo = math.log(1e-6 * float(v.min()))
    hi = math.log(10.0 * max(float(np.max(y**2)), float(v.max())))
    r = minimize_scalar(nll, bounds=(lo, hi), method="bounded")
    ls_ml, f_ml = float(r.x), float(r.fun)
    if nll(lo) <= f_ml:  # the maximum at the boundary s² = 0
        ls_ml, f_ml = lo, nll(lo)
    z = float(norm.isf(1.0 - level)) if level > 0.5 else 0.0
    if z <= 0.0:
        return math.exp(ls_ml), math.exp(ls_ml)
    target = f_ml + 0.5 * z * z
    top = ls_ml + 1.0
    while nll(top) < target:
        top += 2.0
    ls_u = brentq(lambda ls: nll(ls) - target, ls_ml, top, xtol=1e-6)
    return (0.0 if ls_ml == lo else math.exp(ls_ml)), math.exp(ls_u)


def _trend_prediction(a0: np.ndarray, th: np.ndarray, Pth: np.ndarray, tbar: float, t: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The angles α0 + δα0 + ρ (t − t̄) of a joint fit θ = [δα0, ρ] (covariance Pθ) at time t,
    with their covariance L Pθ Lᵀ, L = [I, (t − t̄) I]."""
    na = len(a0)
    L = np.hstack([np.eye(na), (t - tbar) * np.eye(na)])
    P = L @ Pth @ L.T
    return a0 + L @ th, 0.5 * (P + P.T)


@dataclass(frozen=True)
class _Refit:
    """The drift bound's joint fit re-linearised at ``at`` (:meth:`DriftTest._refit_at`):
    [α, ρ] and its covariance, the windows' mean time and linearised design [A, B]."""

    at: np.ndarray
    theta: np.ndarray
    P: np.ndarray
    tbar: float
    A: np.ndarray
    B: np.ndarray
    means: np.ndarray
    counts: np.ndarray


class DriftTest:
    """Constant angles against angles on a linear trend in time, α(t) = α0 + ρ (t − t̄)
    (docs/identification.md, "Angles that drift"). Unlike the load structures it cannot pool
    windows by load — a trend predicts different residuals at the same load — so it keeps
    every window's mean and time (bounded: ``max_windows``).

    At each look: the constant fit α̂ of every window's mean (Gauss–Newton, as the load
    test), the whitened, √n-weighted residuals ê and angle Jacobians A (6W × 14), and the
    trend's columns B = A_w τ_w (τ_w the window's time from the count-weighted mean time).
    B is projected off the span of A (columns to unit length first); r = its rank (singular
    values ≥ ``RANK_TOLERANCE`` of the largest) is the number of testable rate directions and
    ``q = ‖U_Bᵀ ê‖²`` the likelihood-ratio statistic of the linearised model, χ²_r under
    constant angles. Alpha spending of its own (``spend``, Σ = ``false_alarm``): the
    probability that a run of constant angles is ever called drifting is at most that. The
    rates and their covariance come from the joint least squares of [α0, ρ]; the misfit left
    must pass at the look's level (``explains``) and every rate be determined (r = 14) for the
    trend to be *selected*. A step is not a trend: a new window the trend (fitted before it)
    mispredicts by more than χ²₆(1 − ``time_level``) restarts the history.

    Before a trend is selected, :attr:`bounded_prediction` is the angles at the next window
    under the drift the windows cannot exclude: the same joint fit with the rates' prior
    ρ ~ N(0, s² I), s² at the upper bound of :func:`rate_scale_bound` (``bound_level``),
    from the look at which the windows determine all 14 angles and all 14 rates (before,
    with few rate directions tested, the bound is unbounded in the others)."""

    def __init__(self, model: RigModel, moment_floor: float, *, false_alarm: float = FALSE_ALARM,
                 time_level: float = TIME_LEVEL, max_windows: int = MAX_DRIFT_WINDOWS,
                 bound_level: float | None = DRIFT_BOUND_LEVEL) -> None:
        self.model, self.moment_floor = model, float(moment_floor)
        self.false_alarm, self.time_level = float(false_alarm), float(time_level)
        # None: no bounded prediction (the constant-angle posterior as it is)
        self.bound_level = bound_level
        self.max_windows = int(max_windows)
        self.n_a = 2 * model.geometry.n_cells
        self.look = 0
        self.restarts = 0
        self.rejected = False
        self.windows: list[tuple[float, np.ndarray, int]] = []  # (t, x̄, n)
        self._fit: tuple[np.ndarray, np.ndarray, np.ndarray, float, bool] | None = None  # (α̂, θ̂ = [δα0, ρ], Pθ, t̄, determined)
        self.last: DriftVerdict | None = None
        # the angles the fit of the windows before the last one predicts at the last one's
        # time, with the prediction's covariance (α (14,), P (14, 14)); None: not determined
        self.prediction: tuple[np.ndarray, np.ndarray] | None = None
        # the same under the drift the windows cannot exclude (rate prior at its bound);
        # (α̂, θ̃, Pθ̃, t̄) of the last look and its prediction at the last window
        self._bounded: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None
        self.bounded_prediction: tuple[np.ndarray, np.ndarray] | None = None
        self.bounded_look: int | None = None  # the look whose fit made bounded_prediction
        # the fits of the last looks (bounded), for a prior that leaves out held windows
        self._bounded_by_look: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}
        # the windows each of those fits used (times, means, counts), to re-linearise it
        self._windows_by_look: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._scale_by_look: dict[int, float] = {}  # the rates' prior s² of each look's fit
        self.rate_scale: tuple[float, float] | None = None  # (ML, bound) of s², rad²/s²

    def restart(self) -> None:
        self.windows = []
        self.rejected = False
        self._fit = None
        self._bounded = None
        self._bounded_by_look = {}
        self._windows_by_look = {}
        self._scale_by_look = {}
        self.restarts += 1

    def _predict(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        if self._fit is None or not self._fit[4]:
            return None
        a_hat, th, Pth, tbar, _ = self._fit
        return _trend_prediction(a_hat, th, Pth, tbar, t)

    def predict_bounded(self, t: float, look: int | None = None
                        ) -> tuple[np.ndarray, np.ndarray] | None:
        """The bounded prediction at time t from the fit of ``look`` (default the last one;
        None when that look made none or is no longer kept)."""
        fit = self._bounded if look is None else self._bounded_by_look.get(look)
        if fit is None:
            return None
        a_hat, th, Pth, tbar = fit
        return _trend_prediction(a_hat, th, Pth, tbar, t)

    def bounded_angles(self, look: int | None = None) -> np.ndarray | None:
        """The constant fit α̂ the bounded prediction of ``look`` is linearised at (None as
        :meth:`predict_bounded`)."""
        fit = self._bounded if look is None else self._bounded_by_look.get(look)
        return None if fit is None else fit[0]

    def predict_bounded_at(self, t: float, look: int | None, at: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray] | None:
        """:meth:`predict_bounded` with the joint fit linearised at the angles ``at`` instead
        of the constant fit α̂ of the window means: where the means alone leave α̂ far off
        (a direction only the full moments determine), the Jacobians at α̂ bend the directions
        the means do determine (the drift benchmark's constant arm, seed 79: α̂ 8.7° off, the prediction at
        χ²₁₄ 85 from the truth). The rates' prior s² stays the look's; None as
        :meth:`predict_bounded`."""
        refit = self._refit_at(look, at)
        if refit is None:
            return None
        return _trend_prediction(refit.at, refit.theta, refit.P, refit.tbar, t)

    def _refit_at(self, look: int | None, at: np.ndarray) -> "_Refit | None":
        """The bound's joint fit of a kept look (:meth:`_joint`, the rates' prior s² the
        look's) re-linearised at the angles ``at``; None when that look is not kept or the
        fit fails."""
        key = self.look if look is None else look
        fit, wins = self._bounded_by_look.get(key), self._windows_by_look.get(key)
        if fit is None or wins is None or key not in self._scale_by_look:
            return None
        ts, means, counts = wins
        tbar = fit[3]
        a0 = np.asarray(at, float)
        Li = _whitener(self.model, a0, self.moment_floor)
        e, A, _ = _stack(self.model, a0, means, counts, Li, ())
        B = A * np.repeat(ts - tbar, 6)[:, None]
        th_P = self._joint(A, B, e, self._scale_by_look[key])
        if th_P is None:
            return None
        return _Refit(a0, th_P[0], th_P[1], tbar, A, B, means, counts)

    def bounded_load_spread(self, t: float, look: int | None, at: np.ndarray,
                            sensitivity: np.ndarray, reference: np.ndarray | None
                            ) -> np.ndarray | None:
        """The covariance the angles' load dependence adds to the bounded prediction at time
        t (estimator.load_spread for the posterior): each window mean is of the
        angles at its own static load L_j (its mean known hub loads), α_ref + g (L_j − L_ref),
        g_k of 1-σ ``sensitivity[k]`` on axis k and unknown sign, so the prediction carries
        ``Σ_k D_k g_k``, D_k = [I, (t − t̄) I] Pθ Jᵀ diag(L_jk − L_ref,k) A with J = [A, B] the
        fit's linearised windows at ``at`` (the angles its prediction was linearised at).
        ``reference``: L_ref (None: the windows' count-weighted mean load). Returns
        Σ_k s_k² D_k D_kᵀ; None when that look is not kept or nothing is configured."""
        s = np.asarray(sensitivity, float)
        refit = self._refit_at(look, at) if np.any(s) else None
        if refit is None:
            return None
        A = refit.A
        nc = self.model.geometry.n_cells
        loads = np.atleast_2d(np.asarray(refit.means, float))[:, 6 + nc:12 + nc]
        w = np.asarray(refit.counts, float)
        ref = (np.asarray(reference, float) if reference is not None
               else (w[:, None] * loads).sum(0) / max(float(w.sum()), 1.0))
        na = self.n_a
        Lt = np.hstack([np.eye(na), (float(t) - refit.tbar) * np.eye(na)])
        LPJ = Lt @ refit.P @ np.hstack([A, refit.B]).T  # (14, 6W)
        C = np.zeros((na, na))
        for k in np.flatnonzero(s):
            D = LPJ @ (np.repeat(loads[:, k] - ref[k], 6)[:, None] * A)
            C += s[k] ** 2 * (D @ D.T)
        return 0.5 * (C + C.T)

    def bounded_shift(self, t: float, look: int | None = None, since: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """The bound's drift alone from ``since`` (default its fit's mean time t̄) to t:
        (ρ̂ Δt, Δt² P_ρρ); None as :meth:`predict_bounded`. Added to a posterior of constant
        angles (the same windows, more of their information) it moves that posterior along
        the drift the windows cannot exclude without replacing what it knows of the angles."""
        fit = self._bounded if look is None else self._bounded_by_look.get(look)
        if fit is None:
            return None
        _, th, Pth, tbar = fit
        na = self.n_a
        dt = float(t) - (tbar if since is None else float(since))
        P = dt * dt * Pth[na:, na:]
        return dt * th[na:], 0.5 * (P + P.T)

    def _bound(self, A: np.ndarray, B: np.ndarray, e: np.ndarray, a_hat: np.ndarray,
               tbar: float, windows: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """The joint fit of [δα0, ρ] under the rates' prior N(0, s² I), s² at its bound;
        ``windows`` (times, means, counts) and s² kept with the look for
        :meth:`predict_bounded_at`."""
        self._bounded, self.rate_scale = None, None
        if self.bound_level is None:
            return
        Laa, Lab, Lbb = A.T @ A, A.T @ B, B.T @ B
        ga, gb = A.T @ e, B.T @ e
        try:
            ca = np.linalg.cholesky(Laa)
        except np.linalg.LinAlgError:
            return
        X = np.linalg.solve(ca, Lab)
        xa = np.linalg.solve(ca, ga)
        S = Lbb - X.T @ X  # the rates' information, the constant angles eliminated
        bound = rate_scale_bound(S, gb - X.T @ xa, self.bound_level)
        if bound is None:
            return
        self.rate_scale = bound
        th_P = self._joint(A, B, e, bound[1])
        if th_P is None:
            return
        self._bounded = (a_hat, th_P[0], th_P[1], tbar)
        self._scale_by_look[self.look] = bound[1]
        self._windows_by_look[self.look] = windows

    def _joint(self, A: np.ndarray, B: np.ndarray, e: np.ndarray, s2: float
               ) -> tuple[np.ndarray, np.ndarray] | None:
        """[δα0, ρ] and their covariance from the linearised windows under ρ ~ N(0, s² I)."""
        na = self.n_a
        Lam = np.block([[A.T @ A, A.T @ B], [B.T @ A, B.T @ B + np.eye(na) / s2]])
        d = np.sqrt(np.diag(Lam))
        try:
            Pn = np.linalg.inv(Lam / np.outer(d, d)) / np.outer(d, d)
        except np.linalg.LinAlgError:
            return None
        th = Pn @ np.concatenate([A.T @ e, B.T @ e])
        return th, 0.5 * (Pn + Pn.T)

    def _mispredicts(self, xbar: np.ndarray, n: int, t: float) -> bool:
        assert self._fit is not None  # called after a fit
        a_hat, th, Pth, tbar, determined = self._fit
        if not determined:
            return False
        Li = _whitener(self.model, a_hat, self.moment_floor)
        r, A, _ = _stack(self.model, a_hat, xbar[None, :], np.array([n], float), Li, ())
        M = np.hstack([A, A * (t - tbar)])
        d = r - M @ th
        C = np.eye(6) + M @ Pth @ M.T
        return float(d @ np.linalg.solve(C, d)) > float(chi2.isf(self.time_level, 6))

    def add_window(self, x: np.ndarray, alpha: np.ndarray, t: float) -> DriftVerdict | None:
        """One known-load window: x (n, ncol) its scored rows ``[z, T, H, q]``, α the angles
        in force, t its time (s, the window's middle)."""
        x = np.asarray(x, float)
        xbar, n = x.mean(axis=0), len(x)
        self.look += 1
        restarted = False
        self.prediction = self._predict(float(t))
        self.bounded_prediction = self.predict_bounded(float(t))
        self.bounded_look = self.look - 1 if self.bounded_prediction is not None else None
        if self._fit is not None and self._mispredicts(xbar, n, float(t)):
            self.restart()
            self.prediction = self.bounded_prediction = None
            restarted = True
        self.windows.append((float(t), xbar, n))
        if len(self.windows) > self.max_windows:
            self.windows.pop(0)
        self.last = self._verdict(np.asarray(alpha, float), restarted)
        if self._bounded is not None:
            self._bounded_by_look[self.look] = self._bounded
        for k in [k for k in self._bounded_by_look if k < self.look - MAX_HELD_LOOKS]:
            del self._bounded_by_look[k]
            self._windows_by_look.pop(k, None)
            self._scale_by_look.pop(k, None)
        return self.last

    def _verdict(self, alpha: np.ndarray, restarted: bool) -> DriftVerdict | None:
        if len(self.windows) < 2:
            self._fit = self._bounded = None
            return None
        ts = np.array([w[0] for w in self.windows])
        means = np.array([w[1] for w in self.windows])
        counts = np.array([w[2] for w in self.windows], float)
        a_hat, converged = fit_constant_converged(self.model, alpha, means, counts,
                                                  self.moment_floor)
        if not converged:
            self._fit = self._bounded = None
            return None
        tbar = float(np.average(ts, weights=counts))
        tau = ts - tbar
        Li = _whitener(self.model, a_hat, self.moment_floor)
        e, A, _ = _stack(self.model, a_hat, means, counts, Li, ())
        na = self.n_a
        B = A * np.repeat(tau, 6)[:, None]
        UA = _range_basis(A)
        Bu, _ = _unit_columns(B)
        Bp = Bu - UA @ (UA.T @ Bu)
        UB = _range_basis(Bp) if np.any(Bp) else np.zeros((len(e), 0))
        r = UB.shape[1]
        level = spend(self.look, self.false_alarm)
        M = np.hstack([A, B])
        Mu, scale = _unit_columns(M)
        th_u, *_ = np.linalg.lstsq(Mu, e, rcond=RANK_TOLERANCE)
        th = th_u / scale
        res = e - M @ th
        rank_all = UA.shape[1] + r
        misfit = float(res @ res)
        misfit_dof = len(e) - rank_all
        Pu = np.linalg.pinv(Mu.T @ Mu, rcond=RANK_TOLERANCE ** 2)
        Pth = Pu / np.outer(scale, scale)
        determined = r == na
        self._fit = (a_hat, th, Pth, tbar, determined)
        if determined and UA.shape[1] == na:
            self._bound(A, B, e, a_hat, tbar, (ts, means, counts))
        else:
            self._bounded = None
        if r == 0:
            return DriftVerdict(np.zeros(na), np.full(na, np.nan), np.zeros((na, na)), 0.0, 0,
                                0.0, self.rejected, False, misfit, misfit_dof, len(ts),
                                float(ts[-1] - ts[0]), restarted, False)
        q = float(np.sum((UB.T @ e) ** 2))
        limit = float(chi2.isf(level, r))
        if q > limit:
            self.rejected = True
        explains = misfit_dof > 0 and misfit <= float(chi2.isf(level, misfit_dof))
        P_rate = Pth[na:, na:]
        rate = th[na:] if determined else np.zeros(na)
        sig = np.sqrt(np.maximum(np.diag(P_rate), 0.0)) if determined else np.full(na, np.nan)
        selected = bool(self.rejected and explains and determined
                        and np.all(np.isfinite(sig)))
        return DriftVerdict(rate.copy(), sig, 0.5 * (P_rate + P_rate.T), q, r, limit,
                            self.rejected, explains, misfit, misfit_dof, len(ts),
                            float(ts[-1] - ts[0]), restarted, selected)
