"""A posterior pooled across recordings, from their likelihood information (docs/identification.md,
"Pooling recordings"; model.md §7 known-load mode).

The known-load likelihood depends on the data only through the second moments
``G = Σ x xᵀ`` of the stacked, content-filtered channels ``x = [z, T, H, q]`` over the scored
samples (W(θ) is the same for every sample and there is no log-det term): the moments of a
recording are the sufficient statistics of its known-load windows. Pooling K recordings is
therefore exact — V of their union is V of their summed moments — and is re-solved from those
moments with Levenberg–Marquardt (the Gauss–Newton normal equations summed over every window,
re-linearised at every iteration), with the prior counted **once**. Posteriors are never
multiplied: K posteriors of one prior would count it K times.

Where the rig allows the angles to move (``identification.drift_rate_rad2_s``, a random walk),
the recordings in time order are the measurements of a random-walk state: each recording's
likelihood is linearised (its Gauss–Newton information and score from its moments) at that
state's smoothed estimate, a Kalman filter and Rauch–Tung–Striebel smoother in information form
run over the recordings, and the linearisation is repeated at the smoothed estimates until the
steps are below 0.01 σ (an iterated smoother: the exact MAP of the linear-Gaussian pieces). With
no allowance (rate 0) this is the constant-angle pooled fit above.

Homogeneity (do the recordings agree?): each recording's own estimate, linearised at the pooled
one, ``θ̂_k = θ̂ − M_k⁺ g_k`` (M_k, g_k its information and score), in the directions it
determines (eigenvalues of P_p^½ M_k P_p^½ ≥ 1). The global statistic is the sum of the
sequential innovations of the filter above over the recordings after the first — each
recording's estimate against the prediction from those before it, covariance
``Uᵀ P_pred U + Λ⁻¹`` — χ² with Σ r_k degrees of freedom under the hypothesis (for constant
angles it is the classical Σ (θ̂_k − θ̄)ᵀ M_k (θ̂_k − θ̄) decomposed into recursive residuals).
Each recording is also set against the pool of the others (leave one out: χ²_{r_k}), which names
the recordings that disagree, and the drift trend over time (a weighted straight line through
the recordings' estimates, its slope tested against 0 by χ²_p) is stated beside it.

Pure numerics: numpy arrays in and out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.stats import chi2

from .identification import (
    AccumulatedKnownLoadProblem,
    IdentificationResult,
    KnownLoadProblem,
    Parameterisation,
    levenberg_marquardt,
)

FALSE_ALARM = 1e-3  # the homogeneity test's size (the whole test; Bonferroni for the naming)
MIN_INFORMATION = 1.0  # a recording determines a direction whose information ≥ the prior's
SMOOTHER_ITERATIONS = 5  # re-linearisations of the iterated smoother (drift allowance only)
STEP_TOL = 0.01  # of a σ: the smoother's re-linearisation has converged


# ------------------------------------------------------------------------------------------
# Sufficient statistics
# ------------------------------------------------------------------------------------------
def window_statistics(x: np.ndarray, scored: np.ndarray, window: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``window`` samples on the grid from sample 0 (the service's periodic
    windows): (first sample index (W,), scored count n (W,), first moments Σ x (W, c),
    second moments Σ x xᵀ (W, c, c)) over the scored samples; windows with none are left out.
    Their sums are the moments of the whole recording."""
    x = np.asarray(x, float)
    ok = np.asarray(scored, bool)
    if window < 1:
        raise ValueError(f"window must be at least 1 sample, got {window}")
    firsts, ns, s1, s2 = [], [], [], []
    for k in range(0, len(x), window):
        xk = x[k:k + window][ok[k:k + window]]
        if not len(xk):
            continue
        firsts.append(k)
        ns.append(len(xk))
        s1.append(xk.sum(axis=0))
        s2.append(xk.T @ xk)
    c = x.shape[1]
    if not ns:
        return (np.zeros(0, int), np.zeros(0, int), np.zeros((0, c)), np.zeros((0, c, c)))
    return np.array(firsts), np.array(ns), np.array(s1), np.array(s2)


def moments_problem(par: Parameterisation, G: np.ndarray, n: int) -> AccumulatedKnownLoadProblem:
    """The exact known-load likelihood of data given only by their moments ``G`` and scored
    count ``n`` (a :class:`KnownLoadProblem` of no samples, accumulated with them)."""
    nc = par.n_cells
    Q = par.model.external.wrenches.shape[1]
    empty = KnownLoadProblem(par, np.zeros((0, 6)), np.zeros((0, nc)), np.zeros((0, 6)),
                             np.zeros((0, Q)) if Q else None)
    return empty.with_moments(np.asarray(G, float), int(n))


# ------------------------------------------------------------------------------------------
# The pooled fit
# ------------------------------------------------------------------------------------------
@dataclass
class Recording:
    """One recording's sufficient statistics: its moments, scored count and start time (s;
    NaN when unknown — then no drift allowance applies before it)."""

    name: str
    G: np.ndarray
    n: int
    t: float = math.nan


@dataclass
class Homogeneity:
    """Whether the recordings agree (module doc)."""

    statistic: float  # Σ of the sequential innovations after the first recording
    dof: int
    p_value: float
    limit: float  # χ²_dof at 1 − FALSE_ALARM
    reject: bool
    sequential: list[float]  # each recording's innovation against those before it (first: nan)
    sequential_dof: list[int]
    leave_one_out: list[float]  # each recording against the pool of the others
    leave_one_out_p: list[float]
    determined: list[int]  # directions each recording determines (r_k)
    disagree: list[int]  # indices of the recordings named (empty unless reject)
    trend: np.ndarray | None  # (p,) slope per second of time (None: fewer than 3 times known)
    trend_sigma: np.ndarray | None
    trend_statistic: float | None
    trend_p_value: float | None
    estimates: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (K, p) θ̂_k


@dataclass
class PooledResult:
    """The pooled posterior (θ, P) about the angles at the last recording, how it was found,
    and the homogeneity test."""

    theta: np.ndarray
    P: np.ndarray
    ident: IdentificationResult  # the constant-angle pooled fit (exact, from the moments)
    information: list[np.ndarray]  # M_k at the pooled estimate (linearisation point)
    homogeneity: Homogeneity
    drift_rate: float  # rad²/s applied between recordings (0: constant angles)
    sigma_floor: np.ndarray | None  # (p,) the floor the allowance sets on σ (module doc)
    smoother_iterations: int = 0
    order: list[int] = field(default_factory=list)  # recordings in time order (indices)


def _time_order(recs: Sequence[Recording]) -> list[int]:
    """Time order (unknown times keep their given place at the end, stable)."""
    return sorted(range(len(recs)), key=lambda k: (not math.isfinite(recs[k].t),
                                                   recs[k].t if math.isfinite(recs[k].t) else 0,
                                                   k))


def _evaluate(par: Parameterisation, rec: Recording, theta: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    ev = moments_problem(par, rec.G, rec.n).evaluate(theta)
    assert ev.gradient is not None and ev.information is not None
    M = 0.5 * (ev.information + ev.information.T)
    return ev.gradient, M


def _determined(M: np.ndarray, prior_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The directions (p × r) a recording determines (information ratio against the prior ≥
    MIN_INFORMATION) as eigenvectors U of M with their eigenvalues λ (in θ units): M ≈ U Λ Uᵀ
    there. Found in the prior's scaled coordinates, then mapped back (orthonormalised)."""
    L = np.linalg.cholesky(prior_cov)
    lam, V = np.linalg.eigh(L.T @ M @ L)
    keep = lam >= MIN_INFORMATION
    if not keep.any():
        return np.zeros((len(M), 0)), np.zeros(0)
    # the subspace L V_keep (θ units), orthonormal basis; M restricted to it
    Q, _ = np.linalg.qr(L @ V[:, keep])
    lam_t, W = np.linalg.eigh(Q.T @ M @ Q)
    return Q @ W, np.clip(lam_t, 1e-300, None)


def _drift_cov(par: Parameterisation, rate: float, dt: float) -> np.ndarray:
    Q = np.zeros((par.n, par.n))
    if rate > 0 and math.isfinite(dt) and dt > 0:
        Q[par.angle_pos, par.angle_pos] = rate * dt
    return Q


def _smooth(theta_p: np.ndarray, P_p: np.ndarray, lin: list[tuple[np.ndarray, np.ndarray,
            np.ndarray]], Qs: list[np.ndarray]
            ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Information-form Kalman filter and RTS smoother of a random walk over the recordings.
    ``lin[k] = (θ_L, g, M)``: recording k's likelihood linearised at θ_L; ``Qs[k]`` the walk's
    covariance between recording k−1 and k (Qs[0] unused). Returns the filtered means and
    covariances, then the smoothed ones."""
    K = len(lin)
    mf, Pf, mp, Pp = [], [], [], []
    m, P = theta_p.copy(), P_p.copy()
    for k, (thL, g, M) in enumerate(lin):
        if k:
            P = P + Qs[k]
        mp.append(m.copy())
        Pp.append(P.copy())
        info = np.linalg.inv(P) + M
        Pn = np.linalg.inv(info)
        Pn = 0.5 * (Pn + Pn.T)
        m = Pn @ (np.linalg.solve(P, m) + M @ thL - g)
        P = Pn
        mf.append(m.copy())
        Pf.append(P.copy())
    ms: list[np.ndarray] = [np.zeros(0)] * K
    Ps: list[np.ndarray] = [np.zeros(0)] * K
    ms[-1], Ps[-1] = mf[-1], Pf[-1]
    for k in range(K - 2, -1, -1):
        C = Pf[k] @ np.linalg.inv(Pp[k + 1])
        ms[k] = mf[k] + C @ (ms[k + 1] - mp[k + 1])
        Pk = Pf[k] + C @ (Ps[k + 1] - Pp[k + 1]) @ C.T
        Ps[k] = 0.5 * (Pk + Pk.T)
    return mf, Pf, ms, Ps


def pool(par: Parameterisation, recs: Sequence[Recording], prior_mean: np.ndarray,
         prior_cov: np.ndarray, *, drift_rate: float = 0.0, max_iterations: int = 10,
         false_alarm: float = FALSE_ALARM) -> PooledResult:
    """The pooled posterior of ``recs`` (module doc) with the prior (``prior_mean``,
    ``prior_cov``) counted once, at the first recording in time order; ``drift_rate``
    (rad²/s) the rig's allowance for the angles to move between recordings."""
    if not recs:
        raise ValueError("no recordings to pool")
    order = _time_order(recs)
    recs = [recs[k] for k in order]
    theta_p = np.asarray(prior_mean, float)
    P_p = np.asarray(prior_cov, float)
    G = sum((r.G for r in recs), np.zeros_like(recs[0].G))
    n = sum(r.n for r in recs)
    ident = levenberg_marquardt(moments_problem(par, G, n), theta_p, P_p,
                                max_iterations=max_iterations)
    theta, P = ident.theta.copy(), ident.P.copy()
    lin = [(theta.copy(), *_evaluate(par, r, theta)) for r in recs]
    Qs = [np.zeros_like(P_p)] + [_drift_cov(par, drift_rate, recs[k].t - recs[k - 1].t)
                                 for k in range(1, len(recs))]
    iterations = 0
    if drift_rate > 0 and len(recs) > 1 and ident.status != "diverged":
        lin, iterations = _relinearise(par, recs, lin, theta_p, P_p, Qs)
        _, Pf, ms, _ = _smooth(theta_p, P_p, lin, Qs)
        theta, P = ms[-1].copy(), Pf[-1].copy()
    hom = homogeneity(par, recs, lin, theta_p, P_p, Qs, false_alarm=false_alarm)
    floor = sigma_floor(par, recs, [M for _, _, M in lin], drift_rate) if drift_rate > 0 else None
    return PooledResult(theta=theta, P=P, ident=ident, information=[M for _, _, M in lin],
                        homogeneity=hom, drift_rate=float(drift_rate), sigma_floor=floor,
                        smoother_iterations=iterations, order=order)


def _relinearise(par: Parameterisation, recs: Sequence[Recording],
                 lin: list[tuple[np.ndarray, np.ndarray, np.ndarray]], theta_p: np.ndarray,
                 P_p: np.ndarray, Qs: list[np.ndarray]
                 ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], int]:
    """Each recording linearised again at the smoother's estimate for its time, until no
    estimate moves by STEP_TOL of its σ (at most SMOOTHER_ITERATIONS): the linearisations
    and the iterations taken."""
    iterations = 0
    for iterations in range(1, SMOOTHER_ITERATIONS + 1):
        _, _, ms, Ps = _smooth(theta_p, P_p, lin, Qs)
        moved = max(float(np.max(np.abs(m - thL) / np.sqrt(np.diag(Pk))))
                    for m, Pk, (thL, _, _) in zip(ms, Ps, lin))
        lin = [(m.copy(), *_evaluate(par, r, m)) for m, r in zip(ms, recs)]
        if moved < STEP_TOL:
            break
    return lin, iterations


def sigma_floor(par: Parameterisation, recs: Sequence[Recording], Ms: Sequence[np.ndarray],
                drift_rate: float) -> np.ndarray | None:
    """The σ below which no number of such recordings brings an angle under the random walk:
    the steady state of P = ((P + qΔt)⁻¹ + m)⁻¹, P∞ = (−qΔt + √((qΔt)² + 4 qΔt/m))/2, with Δt
    the median spacing of the recordings and m each parameter's mean information per recording
    (1/[M_k⁻¹]_jj over the recordings that determine it). None without a spacing."""
    t = np.array([r.t for r in recs], float)
    t = np.sort(t[np.isfinite(t)])
    if len(t) < 2 or drift_rate <= 0:
        return None
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return None
    out = np.zeros(par.n)
    for j in par.angle_pos:
        infos = _informations(Ms, j)
        if not infos:
            out[j] = np.inf
            continue
        m = float(np.mean(infos))
        qd = drift_rate * dt
        out[j] = math.sqrt(max((-qd + math.sqrt(qd * qd + 4 * qd / m)) / 2, 0.0))
    return out


def _informations(Ms: Sequence[np.ndarray], j: int) -> list[float]:
    """Parameter j's information 1/[M⁻¹]_jj from each recording that determines it."""
    infos = []
    for M in Ms:
        try:
            v = np.linalg.inv(M)[j, j]
        except np.linalg.LinAlgError:
            continue
        if np.isfinite(v) and v > 0:
            infos.append(1.0 / v)
    return infos


# ------------------------------------------------------------------------------------------
# Homogeneity
# ------------------------------------------------------------------------------------------
def homogeneity(par: Parameterisation, recs: Sequence[Recording],
                lin: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], theta_p: np.ndarray,
                P_p: np.ndarray, Qs: Sequence[np.ndarray], *,
                false_alarm: float = FALSE_ALARM) -> Homogeneity:
    """The homogeneity test of the recordings ``recs`` (in time order), each linearised as
    ``lin[k] = (θ_L, g, M)`` (module doc)."""
    K, p = len(recs), len(theta_p)
    bases = [_determined(M, P_p) for _, _, M in lin]
    # each recording's own estimate in the directions it determines: θ_L − M⁺ g
    est = np.zeros((K, p))
    for k, ((thL, g, _), (U, lam)) in enumerate(zip(lin, bases)):
        est[k] = thL - U @ ((U.T @ g) / lam)
    seq, seq_dof = _sequential(lin, bases, est, theta_p, P_p, Qs)
    stat = float(np.nansum(seq[1:])) if K > 1 else 0.0
    dof = int(sum(seq_dof[1:]))
    limit = float(chi2.isf(false_alarm, dof)) if dof else math.inf
    pval = float(chi2.sf(stat, dof)) if dof else 1.0
    reject = bool(dof and stat > limit)
    loo, loo_p = _leave_one_out(lin, bases, est, theta_p, P_p)
    disagree = _disagreeing(loo_p, seq, false_alarm) if reject else []
    trend = trend_sig = tstat = tp = None
    t = np.array([r.t for r in recs], float)
    if K >= 3 and np.all(np.isfinite(t)) and np.ptp(t) > 0:
        trend, trend_sig, tstat, tp = _trend(t, est, bases)
    return Homogeneity(statistic=stat, dof=dof, p_value=pval, limit=limit, reject=reject,
                       sequential=seq, sequential_dof=seq_dof, leave_one_out=loo,
                       leave_one_out_p=loo_p, determined=[len(lam) for _, lam in bases],
                       disagree=disagree, trend=trend, trend_sigma=trend_sig,
                       trend_statistic=tstat, trend_p_value=tp, estimates=est)


def _disagreeing(loo_p: Sequence[float], seq: Sequence[float], false_alarm: float
                 ) -> list[int]:
    """The recordings that disagree with the rest (the test rejected): each whose
    leave-one-out p-value is under the Bonferroni level over the recordings, or when none
    alone, the recording where the sequence changes most."""
    each = false_alarm / len(loo_p)
    disagree = [k for k in range(len(loo_p)) if loo_p[k] < each]
    return disagree or [int(np.nanargmax(np.array(seq, float)))]


def _sequential(lin: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                bases: Sequence[tuple[np.ndarray, np.ndarray]], est: np.ndarray,
                theta_p: np.ndarray, P_p: np.ndarray, Qs: Sequence[np.ndarray]
                ) -> tuple[list[float], list[int]]:
    """Sequential innovations (the filter of the pooled fit, on the projected estimates):
    each recording's statistic against the ones before it and its dof (the first: nan, 0)."""
    seq, seq_dof = [math.nan], [0]
    m, P = theta_p.copy(), P_p.copy()
    for k, ((thL, g, M), (U, lam)) in enumerate(zip(lin, bases)):
        if k:
            P = P + Qs[k]
            r = U.T @ (est[k] - m)
            S = U.T @ P @ U + np.diag(1.0 / lam)
            seq.append(float(r @ np.linalg.solve(S, r)) if len(r) else 0.0)
            seq_dof.append(len(lam))
        Pn = np.linalg.inv(np.linalg.inv(P) + M)
        m = Pn @ (np.linalg.solve(P, m) + M @ thL - g)
        P = 0.5 * (Pn + Pn.T)
    return seq, seq_dof


def _leave_one_out(lin: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                   bases: Sequence[tuple[np.ndarray, np.ndarray]], est: np.ndarray,
                   theta_p: np.ndarray, P_p: np.ndarray) -> tuple[list[float], list[float]]:
    """Leave one out, constant angles: d_k = θ̂_k − θ̂_(−k) in recording k's directions, its
    statistic and p-value (0 and 1 for a recording that determines nothing, or alone)."""
    K, p = len(lin), len(theta_p)
    Minfo = [M for _, _, M in lin]
    total = np.linalg.inv(P_p) + sum(Minfo, np.zeros((p, p)))
    total_b = np.linalg.solve(P_p, theta_p) + sum(
        (M @ thL - g for thL, g, M in lin), np.zeros(p))
    loo, loo_p = [], []
    for k, ((thL, g, M), (U, lam)) in enumerate(zip(lin, bases)):
        if not len(lam) or K < 2:
            loo.append(0.0)
            loo_p.append(1.0)
            continue
        rest = total - M
        m_rest = np.linalg.solve(rest, total_b - (M @ thL - g))
        d = U.T @ (est[k] - m_rest)
        S = U.T @ np.linalg.inv(rest) @ U + np.diag(1.0 / lam)
        v = float(d @ np.linalg.solve(S, d))
        loo.append(v)
        loo_p.append(float(chi2.sf(v, len(lam))))
    return loo, loo_p


def _trend(t: np.ndarray, est: np.ndarray, bases: Sequence[tuple[np.ndarray, np.ndarray]]
           ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """θ̂_k = a + b (t_k − t̄) weighted by each recording's information in the directions it
    determines: the slope b (per second), its σ, and bᵀ Cov(b)⁻¹ b against χ² of b's rank."""
    p = est.shape[1]
    tc = t - t.mean()
    A = np.zeros((2 * p, 2 * p))
    b = np.zeros(2 * p)
    for tk, e, (U, lam) in zip(tc, est, bases):
        W = (U * lam) @ U.T
        X = np.hstack([np.eye(p), tk * np.eye(p)])
        A += X.T @ W @ X
        b += X.T @ W @ e
    C = np.linalg.pinv(A, hermitian=True)
    sol = C @ b
    slope, Cb = sol[p:], C[p:, p:]
    lam, V = np.linalg.eigh(Cb)
    keep = lam > 1e-12 * max(lam.max(), 1e-300)
    z = V[:, keep].T @ slope
    stat = float(np.sum(z * z / lam[keep]))
    r = int(keep.sum())
    return slope, np.sqrt(np.clip(np.diag(Cb), 0.0, None)), stat, float(chi2.sf(stat, r))
