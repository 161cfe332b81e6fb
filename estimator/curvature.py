"""Does a run's Gaussian (Laplace) summary hold? The curvature of the likelihood's valley.

A known-load run from a cold start determines a few directions sharply (σ ≈ 0.01°) while the
others stay near the prior (σ ≈ 5°). The constraints the window puts on the angles are not
linear over 5°: the valley of the cost J(θ) bends, and at the truth's offset in the soft
directions its bottom lies many σ of the sharp directions away from the flat slab the Gaussian
at the mode describes. Measured (ground-test, seed 10, windows 2 and 3 from the 4° start):
J(truth) − J(mode) = 3.7 and 6.5 — the truth is well inside the exact posterior — while the
Gaussian summary puts it at χ²₁₄ = 304 and 436.

:func:`nonlinearity` measures the bend where the summary is used: for pairs of points ±u drawn
from the Gaussian in the soft directions (σ above ``soft_ratio`` × the prior σ), the sharp
directions' conditional optimum (Gauss–Newton steps on J with the soft coordinates held) is
found; for a quadratic J it is zero. Its mean m and covariance C over the draws, whitened by the
sharp directions' σ, give the index ν = mᵀ Λ⁻¹ m + tr(Λ⁻¹ C): how far, in χ² units, the
summary's sharp directions are from where the valley puts them. A run whose index exceeds the
limit is not accepted (its window's information is held for the next run, which re-solves the
exact likelihood). Deterministic: the draws come from a fixed seed, so a replay gives the same
verdicts. No soft direction (a converged posterior): ν = 0 at no cost.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np


class _Evaluated(Protocol):
    gradient: np.ndarray | None
    information: np.ndarray | None


class _Problem(Protocol):
    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> _Evaluated: ...


def nonlinearity(
    problem: _Problem,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    sigma0: float,
    *,
    soft_ratio: float = 0.2,
    pairs: int = 16,
    iterations: int = 2,
    seed: int = 0,
) -> float:
    """The curvature index ν of the run (θ, P) of ``problem`` under the prior N(prior_mean,
    prior_cov): 0 when no direction of P has σ above ``soft_ratio`` · ``sigma0`` (or every
    direction has); ``inf`` when the valley cannot be followed (a failed evaluation)."""
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    lam = np.clip(lam, 0.0, None)
    soft = np.sqrt(lam) > soft_ratio * sigma0
    if not soft.any() or soft.all():
        return 0.0
    S, U = V[:, ~soft], V[:, soft]
    lam_s, sig_u = lam[~soft], np.sqrt(lam[soft])
    Pinv = np.linalg.inv(prior_cov)
    xi = np.random.default_rng(seed).standard_normal((pairs, int(soft.sum())))
    shifts = []
    try:
        for x in xi:
            for sign in (-1.0, 1.0):
                th0 = theta + U @ (sign * sig_u * x)
                c = np.zeros(S.shape[1])
                for _ in range(iterations):
                    th = th0 + S @ c
                    ev = problem.evaluate(th)
                    if ev.gradient is None or ev.information is None:
                        return float("inf")
                    g = ev.gradient + Pinv @ (th - prior_mean)
                    H = ev.information + Pinv
                    c = c - np.linalg.solve(S.T @ H @ S, S.T @ g)
                shifts.append(c)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return float("inf")
    b = np.asarray(shifts)
    if not np.all(np.isfinite(b)):
        return float("inf")
    m = b.mean(axis=0)
    C = (b - m).T @ (b - m) / len(b)
    return float(m @ (m / lam_s) + np.trace(C / lam_s[:, None]))
