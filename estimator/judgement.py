"""The accept/reject decision of an identification run, in one place (model §7;
docs/identification.md): :func:`judge` applies the tests in their order to one run and returns
one :class:`Judgement` — the :class:`~estimator.verdict.Verdict` (reason, detail and the limit
the deciding test used), the information ratio, and a filter-error run's update — without
touching the posterior; :meth:`estimator.posterior.SequentialPosterior.update` then applies it.

The tests themselves are plain functions: the physical range (:func:`out_of_range`), the
information ratio, model §7's consistency gate (:func:`consistency_gate`), and the
information rule of filter-error runs (:func:`filter_error_decision`, with its consider update
and gate). Pure numerics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.stats import chi2

from .identification import IdentificationResult, InnovationTest
from .verdict import ACCEPTED, Detail, Reason, Verdict

GATE_PROBABILITY = 0.999  # model §7: accepted when ν ≤ χ²_{d, 0.999}
GATE_RELATIVE_EIGENVALUE = 1e-6  # directions of D kept by the gate, relative to the largest


def gate_limit(probability: float, dof: int) -> float | None:
    """The gate's χ²_{dof, probability} point (None: no direction to test)."""
    return float(chi2.ppf(probability, dof)) if dof > 0 else None


def out_of_range(theta: np.ndarray, limit: np.ndarray) -> bool:
    """A run's estimate outside the physical range |θ_k| ≤ limit_k (rejected ``out_of_range``:
    no real load cell is tilted that far; the data or the model are wrong)."""
    return not bool(np.all(np.abs(np.asarray(theta, float)) <= limit))


def information_ratio(prior_cov: np.ndarray, M: np.ndarray) -> float:
    """Largest eigenvalue of P_p^{1/2} M P_p^{1/2} (data information relative to the prior)."""
    L = np.linalg.cholesky(prior_cov)
    return float(np.linalg.eigvalsh(L.T @ M @ L)[-1])


def consistency_gate(delta: np.ndarray, prior_cov: np.ndarray, post_cov: np.ndarray,
                     probability: float = GATE_PROBABILITY) -> tuple[float, int, bool]:
    """ν = Δθᵀ D⁺ Δθ over the eigen-directions of D = P_p − P_post whose eigenvalue exceeds
    1e-6 of the largest; (ν, d, ν ≤ χ²_{d, probability})."""
    D = prior_cov - post_cov
    lam, V = np.linalg.eigh(0.5 * (D + D.T))
    if lam[-1] <= 0:
        return 0.0, 0, True
    keep = lam > GATE_RELATIVE_EIGENVALUE * lam[-1]
    proj = V[:, keep].T @ delta
    nu = float(np.sum(proj**2 / lam[keep]))
    d = int(keep.sum())
    return nu, d, nu <= float(chi2.ppf(probability, d))


def consider_update(P_p: np.ndarray, theta_p: np.ndarray, s: np.ndarray, Vk: np.ndarray,
                    proj: np.ndarray, use: np.ndarray, floor_s: float,
                    extra_R: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The filter-error update restricted to the window's determined directions
    (docs/identification.md "The consider update"), in coordinates scaled by ``s``
    (sigma_max): ``Vk`` (p, k) orthonormal directions, ``proj`` the window's estimate along
    them, ``use`` its information there. A Schmidt (consider) Kalman update: the gain is
    restricted to span(Vk), so the estimate moves only along the directions the window
    determines and every other direction keeps the prior's mean and variance; Joseph form,
    so the covariance is that of this (sub-optimal) estimate. ``floor_s``: the window's
    systematic error σ_b (scaled) — added to its variance (1/use + σ_b²) and a floor on the
    fused variance along Vk (a bias common to the windows does not average out).
    ``extra_R`` (k, k, scaled): more error of the window's estimate as a measurement of the
    posterior's angles — the load excursion's (:func:`window_measurement_cov`).
    Returns (P_new, φ_new) scaled."""
    Ps = P_p / s[:, None] / s[None, :]
    phi_p = theta_p / s
    a_p = Vk.T @ phi_p
    Paa = Vk.T @ Ps @ Vk
    R = window_measurement_cov(use, floor_s, extra_R)
    G = Paa @ np.linalg.inv(Paa + R)
    Kf = Vk @ G
    phi = phi_p + Kf @ (proj - a_p)
    A = np.eye(len(s)) - Kf @ Vk.T
    P_new = A @ Ps @ A.T + Kf @ R @ Kf.T
    if floor_s > 0:
        B = Vk.T @ P_new @ Vk
        mu, U = np.linalg.eigh(0.5 * (B + B.T))
        VU = Vk @ U
        P_new = P_new + (VU * np.maximum(floor_s**2 - mu, 0.0)) @ VU.T
    return 0.5 * (P_new + P_new.T), phi


def window_measurement_cov(use: np.ndarray, floor_s: float,
                           extra_R: np.ndarray | None = None) -> np.ndarray:
    """R (k, k, scaled): the error of a filter-error window's estimate along its kept
    directions as a measurement of the posterior's angles — its noise (1/use), the windows'
    systematic floor σ_b² and ``extra_R`` (the load excursion's)."""
    R = np.diag(1.0 / use + floor_s**2)
    return R if extra_R is None else R + extra_R


def consider_gate(P_p: np.ndarray, theta_p: np.ndarray, s: np.ndarray, Vk: np.ndarray,
                  proj: np.ndarray, R: np.ndarray, probability: float
                  ) -> tuple[float, int, bool]:
    """The consistency gate of the consider update : the window's estimate along
    its kept directions against the prior's prediction there, ν = rᵀ (Vkᵀ P_p Vk + R)⁻¹ r,
    χ²_k under consistency (k = the kept directions). Unlike model §7's Δθᵀ D⁺ Δθ it counts
    the window's systematic floor and load excursion (R), which the fused covariance's
    floor otherwise turns into a D that is not positive (measured: a ground posterior of
    σ 0.005–0.02° along the sharpest directions rejected 9 of 66 consistent flight windows
    and was reset to the prior). Returns (ν, k, passed)."""
    Ps = P_p / s[:, None] / s[None, :]
    r = proj - Vk.T @ (theta_p / s)
    C = Vk.T @ Ps @ Vk + R
    nu = float(r @ np.linalg.solve(0.5 * (C + C.T), r))
    k = int(len(r))
    return nu, k, bool(k == 0 or nu <= float(chi2.ppf(probability, k)))


def _prior_cov(result: IdentificationResult) -> np.ndarray:
    if result.prior_cov is None:
        raise ValueError("a run judged by the posterior carries its prior covariance")
    return result.prior_cov


@dataclass
class FilterErrorDecision:
    """What :func:`filter_error_decision` found: ``theta``/``P`` the update when it passed
    (else None, with the ``reason`` and the ``detail`` of the test that decided)."""

    reason: Reason | None
    detail: Detail
    nu: float | None = None
    d: int = 0
    window_determined: int = 0
    theta: np.ndarray | None = None
    P: np.ndarray | None = None
    limit: float | None = None  # the deciding test's (Verdict.limit)

    @property
    def verdict(self) -> Verdict:
        return Verdict(self.reason, self.detail, self.limit, self.nu, self.d)


def filter_error_decision(result: IdentificationResult, checks: "FilterErrorChecks", *,
                          sigma_max: np.ndarray, limit: np.ndarray, update: str, floor: float,
                          gate_probability: float) -> FilterErrorDecision:
    """The information rule of filter-error runs (docs/identification.md): the window's
    OWN information decides which directions a run may update — whatever the prior knows —
    the innovations must be what the filter model predicts, and the information must
    survive a score covariance that does not trust the model (sandwich). ``update``:
    "consider" (with the systematic floor ``floor`` in units of ``sigma_max``) or "bayes"."""
    P_p, theta_p = _prior_cov(result), result.prior_mean
    s = sigma_max
    Ms = result.information * s[:, None] * s[None, :]
    lam, V = np.linalg.eigh(0.5 * (Ms + Ms.T))
    own = lam >= 1.0  # 1/√λ ≤ sigma_max: the window alone determines this direction
    if not own.any():
        return FilterErrorDecision(Reason.NOT_IDENTIFIABLE, Detail.OWN_INFORMATION, limit=1.0)
    if not checks.innovation.passed:
        # the data are not what the filter model predicts (unmodelled load content):
        # no evidence about the angles either way, so the reset streak is left alone
        return FilterErrorDecision(
            Reason.INCONSISTENT, Detail.INNOVATIONS, window_determined=int(own.sum()),
            limit=checks.innovation.limit / checks.innovation.mean)
    Vk, lk = V[:, own], lam[own]
    # the variance of the score along each direction: the larger of what the window's own
    # score series shows and what the model predicts for its coloured innovations
    var = np.zeros(len(lk))
    for Q in (checks.score_covariance, checks.score_covariance_model):
        if Q is not None:
            Qs = Q * s[:, None] * s[None, :]
            var = np.maximum(var, np.einsum("ai,ab,bi->i", Vk, Qs, Vk))
    robust = lk**2 / np.maximum(var, 1e-300)
    use = np.minimum(lk, robust)  # the smaller of the model's and the sandwich's
    keep = use >= 1.0
    if not keep.any():
        return FilterErrorDecision(Reason.NOT_IDENTIFIABLE, Detail.ROBUST_INFORMATION,
                                   limit=1.0)
    Vk, lk, use = Vk[:, keep], lk[keep], use[keep]
    # the window's estimate in its determined directions (linearised at the run's
    # result: M θ̂_w = P_run⁻¹ θ_run − P_p⁻¹ θ_p), weighted by the information used
    Pp_inv = np.linalg.inv(P_p)
    b = np.linalg.solve(result.P, result.theta) - Pp_inv @ theta_p
    proj = (Vk.T @ (s * b)) / lk  # window estimate along each kept direction (scaled)
    # the load excursion : the window's angles are the reference (trim) load's
    # moved by up to the configured sensitivity × the window's static load away from it
    lv = float(checks.load_variance)
    extra_R = None if lv <= 0 else lv * (Vk.T / s**2) @ Vk
    if update == "consider":
        P_new_s, phi = consider_update(P_p, theta_p, s, Vk, proj, use, floor, extra_R)
    else:  # "bayes": the window's information in full (moves undetermined directions)
        Mk = (Vk * use) @ Vk.T  # scaled coordinates
        hk = Vk @ (use * proj)
        Pinv_s = Pp_inv * s[:, None] * s[None, :]  # prior information in scaled coordinates
        P_new_s = np.linalg.inv(Pinv_s + Mk)
        P_new_s = 0.5 * (P_new_s + P_new_s.T)
        phi = P_new_s @ (Pinv_s @ (theta_p / s) + hk)
    theta_new = s * phi
    P_new = P_new_s * s[:, None] * s[None, :]
    wd = int(keep.sum())
    if out_of_range(theta_new, limit):  # the physical range (docs/identification.md)
        return FilterErrorDecision(Reason.OUT_OF_RANGE, Detail.RANGE, window_determined=wd,
                                   limit=float(np.max(limit)))
    if update == "consider":
        nu, d, ok = consider_gate(P_p, theta_p, s, Vk, proj,
                                  window_measurement_cov(use, floor, extra_R), gate_probability)
    else:
        nu, d, ok = consistency_gate(theta_new - theta_p, P_p, P_new, gate_probability)
    if not ok:
        return FilterErrorDecision(Reason.INCONSISTENT, Detail.GATE, nu=nu, d=d,
                                   window_determined=wd,
                                   limit=gate_limit(gate_probability, d))
    return FilterErrorDecision(ACCEPTED, Detail.PASSED, nu=nu, d=d, window_determined=wd,
                               theta=theta_new, P=P_new, limit=gate_limit(gate_probability, d))


@dataclass
class FilterErrorChecks:
    """What a filter-error run is judged on beyond model §7's gate: the innovation test
    against the model-predicted autocovariance and the robust (sandwich) score covariance."""

    innovation: InnovationTest
    score_covariance: np.ndarray  # (p, p) from the window's own score series (Newey–West)
    score_covariance_model: np.ndarray | None = None  # (p, p) from the predicted Γ(k)
    # the window's static load away from the reference (trim) load (6,; None: not known) and
    # the variance (rad², each angle) of the angles' move that far (load_excursion_variance)
    load_delta: np.ndarray | None = None
    load_variance: float = 0.0


@dataclass(frozen=True)
class Judgement:
    """What :func:`judge` decided about one run: the verdict, the run's largest information
    ratio (None where the run was rejected before it was computed) and, in filter-error
    mode, the information rule's decision (its update when accepted)."""

    verdict: Verdict
    information: float | None = None
    decision: FilterErrorDecision | None = None


def input_verdict(missing_fraction: float, stale_fraction: float,
                  scattered: Callable[[], float] | None = None,
                  scattered_limit: float = math.inf) -> Verdict | None:
    """``stale_input`` when too much of the window lacks an input — more than
    ``stale_fraction`` of it (``missing_samples``), or, in filter-error mode, more than
    ``scattered_limit`` in short gaps (``scattered_samples``: each held sample perturbs the
    content after it, which the calibration filter's model does not hold; ``scattered``
    gives that fraction, asked only of a window otherwise complete enough); None: run it."""
    if missing_fraction > stale_fraction:
        return Verdict(Reason.STALE_INPUT, Detail.MISSING_SAMPLES, stale_fraction)
    if scattered is not None and scattered() > scattered_limit:
        return Verdict(Reason.STALE_INPUT, Detail.SCATTERED_SAMPLES, scattered_limit)
    return None


def _streak(post: Any, verdict: Verdict) -> Verdict:
    """A gate failure is a ``reset`` when it is the posterior's ``reset_after``-th in a row."""
    if post.inconsistent_in_a_row + 1 >= post.reset_after:
        return Verdict(Reason.RESET, verdict.detail, verdict.limit, verdict.nu, verdict.dof)
    return verdict


def judge(post: Any, result: IdentificationResult | None, *, missing_fraction: float = 0.0,
          stale: Verdict | None = None, gate: tuple[float, int] | None = None,
          checks: FilterErrorChecks | None = None, structure: Any = None,
          nonlinear: bool = False, nonlinearity_limit: float | None = None) -> Judgement:
    """Judge one run against the posterior ``post`` (a SequentialPosterior, read, not changed)
    in model §7's order (estimator.posterior's docstring): the input, convergence, (filter
    error: the information rule), the range, the structure test, the curvature, the
    information ratio and the consistency gate. ``stale``: the input's verdict when the run
    was not made (:func:`input_verdict`); ``gate``: (ν, d) computed by the caller (the
    likelihood-ratio form of a re-linearised run) instead of the linearised Δθᵀ D⁺ Δθ."""
    if stale is not None:
        return Judgement(stale)
    if result is None or missing_fraction > post.stale_fraction:
        return Judgement(Verdict(Reason.STALE_INPUT, Detail.MISSING_SAMPLES, post.stale_fraction))
    if tuple(result.names) != post.names:
        raise ValueError("the run identified other parameters than this posterior holds")
    if not result.sound:
        reason = Reason.NOT_CONVERGED if result.status == "not_converged" else Reason.DIVERGED
        return Judgement(Verdict(reason, Detail.CONVERGENCE))
    P_p = _prior_cov(result)
    info = information_ratio(P_p, result.information)
    if checks is not None:  # range-checked on what it would apply (its own directions)
        dec = filter_error_decision(result, checks, sigma_max=post.sigma_max, limit=post.limit,
                                    update=post.filter_error_update,
                                    floor=post.filter_error_floor,
                                    gate_probability=post.gate_probability)
        v = dec.verdict
        return Judgement(_streak(post, v) if v.detail == Detail.GATE else v, info, dec)
    if out_of_range(result.theta, post.limit):
        return Judgement(Verdict(Reason.OUT_OF_RANGE, Detail.RANGE, float(np.max(post.limit))))
    if structure is not None and structure.structure == "not_constant":
        # the constant-angle model is rejected (estimator.structure): its runs can only
        # disagree with each other, so none is accepted and none counts towards a reset —
        # no accepted → inconsistent → reset → accepted cycle
        nu, d = (None, 0) if gate is None else (float(gate[0]), int(gate[1]))
        return Judgement(Verdict(Reason.INCONSISTENT, Detail.STRUCTURE, nu=nu, dof=d), info)
    if nonlinear:
        # the Gaussian summary misses the likelihood's curvature (estimator.curvature)
        return Judgement(Verdict(Reason.NOT_IDENTIFIABLE, Detail.NONLINEAR, nonlinearity_limit),
                         info)
    low = info < post.min_information
    if low and not post.gate_low_information:
        return Judgement(Verdict(Reason.NOT_IDENTIFIABLE, Detail.INFORMATION_RATIO,
                                 post.min_information), info)
    if gate is None:
        nu, d, ok = consistency_gate(result.theta - result.prior_mean, P_p, result.P,
                                     post.gate_probability)
    else:
        nu, d = float(gate[0]), int(gate[1])
        ok = d == 0 or nu <= float(chi2.ppf(post.gate_probability, d))
    limit = gate_limit(post.gate_probability, d)
    if not ok:
        return Judgement(_streak(post, Verdict(Reason.INCONSISTENT, Detail.GATE, limit, nu, d)),
                         info)
    if low:
        return Judgement(Verdict(Reason.NOT_IDENTIFIABLE, Detail.INFORMATION_RATIO,
                                 post.min_information, nu, d), info)
    return Judgement(Verdict(ACCEPTED, Detail.PASSED, limit, nu, d), info)
