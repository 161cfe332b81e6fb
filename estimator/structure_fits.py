"""The structures' shared numerics (estimator.structure's docstring): the per-condition model
and its Jacobians by structure name (the experiment design's interface), the linearised test
on condition means (:func:`test_structures`, :func:`design_ranks`), the joint and constant
fits, the alpha-spending rule, and a selected structure in the forms the records and the
per-sample path take (:func:`fit_payload`, :class:`StructureCorrection`). The structures
themselves are estimator.structures' registry; the sequential tests are
estimator.structure_test and estimator.drift_test. Pure numerics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from .balance import measurement_covariance
from .geometry import (
    hub_transfer_matrix,
    wrench_matrix,
    wrench_matrix_jacobian,
)
from .params import RigModel
from .structures import (  # noqa: F401  (STRUCTURES, AXES: their home was this module)
    AXES as AXES,
    STRUCTURES as STRUCTURES,
    Structure as Structure,
    _cell_columns as _cell_columns,
    constant_hub_loads as constant_hub_loads,
    structure_of as structure_of,
)

VERDICTS = ("constant", "not_constant", "undetermined", "drifting")
DRIFTING = "drifting"  # the time-varying candidate (DriftTest)
MAX_DRIFT_WINDOWS = 96  # the drift test's history: 8 min of 5-s windows (bounded)
# the drift the data cannot exclude (docs/identification.md, "Angles that drift"):
# the rates' prior scale s at this one-sided upper confidence level of its likelihood
DRIFT_BOUND_LEVEL = 0.8413  # Φ(1): one standard error above the ML estimate
MAX_HELD_LOOKS = 16  # bounded fits kept (≥ the posterior's held windows, 12)
# (smaller, larger): the larger structure contains the smaller one whatever the conditions
# (δp × F is an external load U F)
NESTED = frozenset({("hub_position", "external_load")})
FALSE_ALARM = 1e-3  # over the whole run (alpha spending)
TIME_LEVEL = 1e-3  # per window: a change in time restarts the accumulation
RANK_TOLERANCE = 1e-4  # singular values kept, relative to the largest of the structure
CLUSTER_TOLERANCE = (1000.0, 1000.0)  # N, N·m: windows at the same load within this pool
MAX_CLUSTERS = 256  # bounded: a new load beyond this joins the nearest cluster
MAX_PARAMETERS_REPORTED = 6  # per candidate, the most significant first
GN_ITERATIONS = 8
HUB_SIGMA_FRACTION = 1.0 / 3.0  # a structure is used once its parameters add at most this
# fraction of the static bound (σ, per axis) to the hub loads at every condition seen
FIT_TOLERANCE = 1e-8  # the joint fit's relative tolerances (cost, step, gradient)
FIT_MAX_EVALUATIONS = 40  # the right structure converges in 3–37 (measured); a wrong one
# (a large misfit: Gauss–Newton converges slowly) stops here and keeps its linear misfit
CONVERGED_STEP_RAD = 1e-6  # the constant fit's last Gauss–Newton step (rad): converged


# ------------------------------------------------------------------------------------------
# The structures: names, units and Jacobians (pure; the experiment design calls these)
# ------------------------------------------------------------------------------------------
def parameter_names(structure: str, model: RigModel) -> tuple[str, ...]:
    """The parameters β of a structure, in order."""
    return structure_of(structure).parameter_names(model)


def parameter_units(structure: str, model: RigModel) -> tuple[str, ...]:
    """Unit of each parameter per kN of load (the ``per_kN`` of a candidate)."""
    return structure_of(structure).parameter_units(model)


def per_kN(structure: str, beta: np.ndarray) -> np.ndarray:
    """β expressed per kN of load in :func:`parameter_units` (deg/kN for angle gains)."""
    return structure_of(structure).per_kN(np.asarray(beta, float))


def _split(model: RigModel, xbar: np.ndarray) -> tuple[np.ndarray, ...]:
    n = model.geometry.n_cells
    x = np.asarray(xbar, float)
    return x[:6], x[6:6 + n], x[6 + n:12 + n], x[12 + n:]


def residual(model: RigModel, alpha: np.ndarray, xbar: np.ndarray) -> np.ndarray:
    """r = z − S(α) T − R₀ H − E q of one condition's mean ``x̄ = [z, T, H, q]``."""
    z, T, H, q = _split(model, xbar)
    r: np.ndarray = z - wrench_matrix(model.geometry, alpha) @ T - hub_transfer_matrix(model.geometry,
                                                                            "body") @ H
    if q.size:
        r = r - model.external.wrenches @ q
    return r


def structure_residual(structure: str | None, model: RigModel, alpha: np.ndarray,
                       beta: np.ndarray | None, xbar: np.ndarray) -> np.ndarray:
    """r = z − m(α, β; T, H) of one condition's mean under a structure (exact in β; the
    cell-load gains act on the mean cell load)."""
    if structure in (None, "constant"):
        return residual(model, alpha, xbar)
    assert structure is not None and beta is not None
    z, T, H, q = _split(model, xbar)
    m = structure_of(structure).predict(model, np.asarray(alpha, float),
                                        np.asarray(beta, float), T[None], H[None])[0]
    if q.size:
        m = m + model.external.wrenches @ q
    result: np.ndarray = z - m
    return result


def angle_jacobian(model: RigModel, alpha: np.ndarray, xbar: np.ndarray) -> np.ndarray:
    """∂m/∂α (6, 14) of one condition: column k is ∂S/∂α_k T."""
    _, T, _, _ = _split(model, xbar)
    dS = wrench_matrix_jacobian(model.geometry, alpha)  # (14, 6, 7)
    result: np.ndarray = np.einsum("kac,c->ak", dS, T)
    return result


def structure_jacobian(structure: str, model: RigModel, alpha: np.ndarray,
                       xbar: np.ndarray) -> np.ndarray:
    """∂m/∂β (6, p) at β = 0 of one condition (m: the model's prediction of z)."""
    st = structure_of(structure)
    _, T, H, _ = _split(model, xbar)
    dS = wrench_matrix_jacobian(model.geometry, alpha)
    result: np.ndarray = st.jacobian(model, dS, T[None], H[None])[0]
    return result


def structure_matrices(structure: str, beta: np.ndarray, model: RigModel
                       ) -> dict[str, np.ndarray]:
    """The exact (not linearised) model pieces of a structure at β, for hub loads."""
    return structure_of(structure).matrices(np.asarray(beta, float), model)


def hub_loads(structure: str | None, model: RigModel, alpha: np.ndarray, beta: np.ndarray | None,
              z: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The static estimate Ĥ (N, 6, body axes) under a structure: ``R(β)⁻¹ (z − S(α(T)) T)``.
    ``None`` or ``"constant"``: the constant-angle model. A balance error changes only the
    reference, not the estimate (its α0 is what the estimator uses)."""
    z, T = np.atleast_2d(np.asarray(z, float)), np.atleast_2d(np.asarray(T, float))
    alpha = np.asarray(alpha, float)
    if structure in (None, "constant"):
        return constant_hub_loads(model, alpha, z, T)
    assert structure is not None and beta is not None  # a structure has parameters
    return structure_of(structure).hub_loads(model, alpha, np.asarray(beta, float), z, T)


# ------------------------------------------------------------------------------------------
# The linearised test on condition means
# ------------------------------------------------------------------------------------------
def _whitener(model: RigModel, alpha: np.ndarray, moment_floor: float) -> np.ndarray:
    W = measurement_covariance(model, alpha, moment_floor, True)
    return np.linalg.inv(np.linalg.cholesky(W))  # L⁻¹: L⁻¹ r has unit covariance (n = 1)


def _batched(model: RigModel, alpha: np.ndarray, means: np.ndarray, structures: Sequence[str]
             ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """r (C, 6), ∂m/∂α (C, 6, 14) and ∂m/∂β (C, 6, p) of every condition at once (the same
    as :func:`residual`, :func:`angle_jacobian`, :func:`structure_jacobian` per condition)."""
    g = model.geometry
    n = g.n_cells
    X = np.atleast_2d(np.asarray(means, float))
    z, T, H, q = X[:, :6], X[:, 6:6 + n], X[:, 6 + n:12 + n], X[:, 12 + n:]
    S = wrench_matrix(g, alpha)
    dS = wrench_matrix_jacobian(g, alpha)
    R0 = hub_transfer_matrix(g, "body")
    r = z - T @ S.T - H @ R0.T
    if q.shape[1]:
        r = r - q @ model.external.wrenches.T
    Ja = np.einsum("kac,nc->nak", dS, T)
    Js = {st: structure_of(st).jacobian(model, dS, T, H) for st in structures}
    return r, Ja, Js


def _stack(model: RigModel, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
           Li: np.ndarray, structures: Sequence[str]
           ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    sw = np.sqrt(np.asarray(counts, float))[:, None, None]
    r, Ja, Js = _batched(model, alpha, means, structures)

    def white(A: np.ndarray) -> np.ndarray:  # (C, 6, k) → (6C, k), whitened and weighted by √n
        out: np.ndarray = (np.einsum("ab,nbk->nak", Li, A) * sw).reshape(-1, A.shape[2])
        return out

    return (white(r[:, :, None])[:, 0], white(Ja), {st: white(J) for st, J in Js.items()})


def _white_residual(st: str, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                    means: np.ndarray, counts: np.ndarray, Li: np.ndarray) -> np.ndarray:
    """The whitened, √n-weighted residuals (6C,) of every condition under a structure."""
    g = model.geometry
    n = g.n_cells
    X = np.atleast_2d(np.asarray(means, float))
    z, T, H, q = X[:, :6], X[:, 6:6 + n], X[:, 6 + n:12 + n], X[:, 12 + n:]
    m = structure_of(st).predict(model, np.asarray(alpha, float), np.asarray(beta, float), T, H)
    if q.shape[1]:
        m = m + q @ model.external.wrenches.T
    r = (z - m) @ Li.T * np.sqrt(np.asarray(counts, float))[:, None]
    result: np.ndarray = r.reshape(-1)
    return result


def _unit_columns(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A with every column scaled to unit length (ranks do not depend on parameter units)."""
    c = np.linalg.norm(A, axis=0)
    c = np.where(c > 0, c, 1.0)
    return A / c, c


def _range_basis(A: np.ndarray, tol: float = RANK_TOLERANCE) -> np.ndarray:
    if A.size == 0:
        return np.zeros((A.shape[0], 0))
    U, s, _ = np.linalg.svd(_unit_columns(A)[0], full_matrices=False)
    if not len(s) or s[0] <= 0:
        return np.zeros((A.shape[0], 0))
    return U[:, s > tol * s[0]]




def _white_jacobian(st: str, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                    means: np.ndarray, counts: np.ndarray, Li: np.ndarray) -> np.ndarray:
    """∂/∂[α, β] of :func:`_white_residual` (6C, 14 + p), exact at (α, β)."""
    g = model.geometry
    n = g.n_cells
    X = np.atleast_2d(np.asarray(means, float))
    T, H = X[:, 6:6 + n], X[:, 6 + n:12 + n]
    C = len(X)
    Ja, Jb = structure_of(st).exact_jacobians(model, np.asarray(alpha, float),
                                              np.asarray(beta, float), T, H)
    Jm = np.concatenate([Ja, Jb], axis=2)  # ∂m/∂[α, β]; the residual is z − m
    sw = np.sqrt(np.asarray(counts, float))[:, None, None]
    result: np.ndarray = -(np.einsum("ab,nbk->nak", Li, Jm) * sw).reshape(6 * C, -1)
    return result


@dataclass
class StructureEstimate:
    """The joint fit of a structure's [α0, β] (:func:`fit_structure`)."""

    structure: str
    alpha: np.ndarray  # α0 (14)
    beta: np.ndarray  # β (p); undetermined directions held at the start (the prior, 0)
    P: np.ndarray  # covariance of [α0, β] in the determined directions (0 elsewhere)
    sigma: np.ndarray  # √diag(P); inf for a parameter not determined
    determined: np.ndarray  # (14 + p) bool: the parameter lies in the determined span
    rank: int  # determined directions of [α0, β]
    cost: float  # ‖whitened residual‖² at the fit
    start_cost: float
    converged: bool
    nfev: int
    status: str


def fit_structure(structure: str, model: RigModel, alpha: np.ndarray, means: np.ndarray,
                  counts: np.ndarray, moment_floor: float, beta: np.ndarray | None = None,
                  *, max_nfev: int = FIT_MAX_EVALUATIONS) -> StructureEstimate:
    """The exact least-squares (maximum-likelihood, W fixed at the start's α) fit of a
    structure's [α0, β] to condition means: Levenberg–Marquardt
    (``scipy.optimize.least_squares``, analytic Jacobian) from (α, β) — the constant-angle fit
    and β = 0 by default — in the directions the conditions determine: the singular vectors of
    the whitened Jacobian at the start, columns scaled to unit length, with singular values
    ≥ ``RANK_TOLERANCE`` of the largest. The other directions stay at the start (the prior),
    carry no covariance and their parameters are reported as not determined. Converged: the
    solver stopped on its tolerances (not on ``max_nfev``), the result is finite and the cost
    did not rise."""
    alpha = np.asarray(alpha, float)
    p = len(parameter_names(structure, model))
    beta0 = np.zeros(p) if beta is None else np.asarray(beta, float)
    theta0 = np.concatenate([alpha, beta0])
    na = len(alpha)
    Li = _whitener(model, alpha, moment_floor)

    def split(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return th[:na], th[na:]

    J0 = _white_jacobian(structure, model, alpha, beta0, means, counts, Li)
    cs = np.linalg.norm(J0, axis=0)
    cs = np.where(cs > 0, cs, 1.0)
    _, s, Vt = np.linalg.svd(J0 / cs, full_matrices=False)
    keep = s > RANK_TOLERANCE * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    B = Vt[keep].T / cs[:, None]  # θ = θ0 + B ξ
    r = B.shape[1]
    r0 = _white_residual(structure, model, alpha, beta0, means, counts, Li)
    start_cost = float(r0 @ r0)
    if r == 0:
        return StructureEstimate(structure, alpha.copy(), beta0.copy(),
                                 np.zeros((na + p, na + p)), np.full(na + p, np.inf),
                                 np.zeros(na + p, bool), 0, start_cost, start_cost, False, 0,
                                 "nothing determined")

    def fun(xi: np.ndarray) -> np.ndarray:
        return _white_residual(structure, model, *split(theta0 + B @ xi), means, counts, Li)

    def jac(xi: np.ndarray) -> np.ndarray:
        Jx: np.ndarray = _white_jacobian(structure, model, *split(theta0 + B @ xi), means,
                                         counts, Li) @ B
        return Jx

    with np.errstate(all="ignore"):
        sol = least_squares(fun, np.zeros(r), jac=jac, method="lm", xtol=FIT_TOLERANCE,
                            ftol=FIT_TOLERANCE, gtol=FIT_TOLERANCE, max_nfev=max_nfev)
    theta = theta0 + B @ sol.x
    cost = float(sol.fun @ sol.fun)
    ok = bool(sol.status > 0 and np.isfinite(theta).all() and np.isfinite(cost)
              and cost <= start_cost * (1 + 1e-9) + 1e-9)
    Jr = np.asarray(sol.jac)  # method="lm": a dense array
    if not np.isfinite(Jr).all():
        Jr = jac(sol.x)
    Pxi = np.linalg.pinv(Jr.T @ Jr, hermitian=True)
    P = B @ Pxi @ B.T
    # a parameter is determined when its unit vector lies in the span of B (scaled columns)
    Vk = Vt[keep].T
    outside = 1.0 - np.sum(Vk**2, axis=1)
    det = outside < 1e-9
    sigma = np.where(det, np.sqrt(np.maximum(np.diag(P), 0.0)), np.inf)
    a, b = split(theta)
    a = alpha + np.angle(np.exp(1j * (a - alpha)))  # the equivalent nearest the start
    return StructureEstimate(structure, a, b, P, sigma, det, r, cost, start_cost, ok,
                             int(sol.nfev), str(sol.message))


def hub_sigma(structure: str, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
              P: np.ndarray, means: np.ndarray) -> np.ndarray:
    """σ (C, 6; N, N·m, body axes) of the static hub-load estimate under a structure at each
    condition that comes from the uncertainty P of its [α0, β] alone (``R₀⁻¹ ∂m/∂θ``)."""
    C = len(np.atleast_2d(means))
    J = _white_jacobian(structure, model, alpha, beta, means, np.ones(C), np.eye(6))
    Ri = np.linalg.inv(hub_transfer_matrix(model.geometry, "body"))
    JH = np.einsum("ab,nbk->nak", Ri, J.reshape(C, 6, -1))
    result: np.ndarray = np.sqrt(np.maximum(np.einsum("nak,kl,nal->na", JH, P, JH), 0.0))
    return result


def fit_constant(model: RigModel, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
                 moment_floor: float, iterations: int = GN_ITERATIONS) -> np.ndarray:
    """The constant-angle fit to condition means: Gauss–Newton with the pseudo-inverse (the
    directions the conditions do not determine stay at ``alpha``)."""
    return fit_constant_converged(model, alpha, means, counts, moment_floor, iterations)[0]


def fit_constant_converged(model: RigModel, alpha: np.ndarray, means: np.ndarray,
                           counts: np.ndarray, moment_floor: float,
                           iterations: int = GN_ITERATIONS) -> tuple[np.ndarray, bool]:
    """:func:`fit_constant` and whether its Gauss–Newton steps converged (last step below
    ``CONVERGED_STEP_RAD``): the test's null distribution holds only at a converged fit."""
    a = np.asarray(alpha, float).copy()
    Li = _whitener(model, a, moment_floor)
    converged = False
    for _ in range(iterations):
        r, Ja, _ = _stack(model, a, means, counts, Li, ())
        step, *_ = np.linalg.lstsq(Ja, r, rcond=RANK_TOLERANCE)
        a = a + step
        if np.max(np.abs(step)) < CONVERGED_STEP_RAD:
            converged = True
            break
    # J is 2π-periodic in the angles: the equivalent nearest the start
    return alpha + np.angle(np.exp(1j * (a - alpha))), converged


def settle_constant(model: RigModel, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
                    moment_floor: float, iterations: int = 4 * FIT_MAX_EVALUATIONS) -> np.ndarray:
    """The constant fit's minimum from ``alpha`` by damped Gauss–Newton (Levenberg–Marquardt):
    where few conditions leave directions weakly determined, undamped steps from a run's
    estimate wander by tens of degrees. The minimum is the same point the Gauss–Newton fit
    converges at; this only finds it (``fit_constant_converged`` then judges convergence)."""
    a = np.asarray(alpha, float).copy()
    Li = _whitener(model, a, moment_floor)
    r, Ja, _ = _stack(model, a, means, counts, Li, ())
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        A = Ja.T @ Ja
        d = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        try:
            step = np.linalg.solve(A + lam * np.diag(d), Ja.T @ r)
        except np.linalg.LinAlgError:
            break
        r2, J2, _ = _stack(model, a + step, means, counts, Li, ())
        c2 = float(r2 @ r2)
        if np.isfinite(c2) and c2 <= cost:
            a, r, Ja, cost = a + step, r2, J2, c2
            lam = max(lam / 3.0, 1e-9)
            if np.max(np.abs(step)) < CONVERGED_STEP_RAD:
                break
        else:
            lam *= 4.0
            if lam > 1e9:
                break
    out: np.ndarray = np.asarray(alpha, float) + np.angle(np.exp(1j * (a - alpha)))
    return out


def constant_misfit(model: RigModel, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
                    moment_floor: float) -> tuple[float, int]:
    """The constant model's whitened misfit over the conditions at ``alpha`` and its dof
    (6C − the rank of the angle columns)."""
    Li = _whitener(model, alpha, moment_floor)
    r, Ja, _ = _stack(model, np.asarray(alpha, float), means, counts, Li, ())
    sv = np.linalg.svd(Ja, compute_uv=False)
    rank = int(np.sum(sv > RANK_TOLERANCE * sv[0])) if len(sv) and sv[0] > 0 else 0
    return float(r @ r), len(r) - rank


@dataclass
class StructureFit:
    """One structure against the constant model on the accumulated conditions."""

    structure: str
    rank: int  # testable directions (determined after the angles)
    nominal: int  # number of parameters
    statistic: float  # q_s, χ²_rank under constant angles
    limit: float  # the rejection limit at this look
    log10_p: float  # log10 of the p-value of q_s
    misfit: float  # what is left after the structure
    misfit_dof: int
    misfit_limit: float
    beta: np.ndarray  # min-norm estimate in the determined directions
    sigma: np.ndarray  # its standard deviation (inf where not determined)
    determined: bool  # every parameter determined (rank == nominal)
    alpha: np.ndarray | None = None  # the angles of the joint fit (α0 of the structure)
    P: np.ndarray | None = None  # covariance of the joint fit [α0, β] (pseudo-inverse)
    converged: bool = False  # the joint fit (fit_structure) converged

    @property
    def rejects_constant(self) -> bool:
        return self.rank > 0 and self.statistic > self.limit

    @property
    def explains(self) -> bool:
        return self.misfit <= self.misfit_limit


def test_structures(model: RigModel, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
                    moment_floor: float, level: float,
                    structures: Sequence[str] = tuple(STRUCTURES), joint: bool | None = True,
                    starts: dict[str, Any] | None = None
                    ) -> tuple[list[StructureFit], dict[str, Any]]:
    """Every structure against the constant-angle model on condition means at α (already the
    constant fit); ``level``: the false-alarm rate of this look (split over the structures).
    ``joint``: fit every structure's [α0, β] exactly (:func:`fit_structure`); ``None``: only
    when some structure rejects the constant model at this look (the fit is what costs);
    ``False``: never (the linear estimates and misfits). ``starts``: per structure, the
    (α0, β) the joint fit starts from (the previous look's; default the constant fit, β = 0)."""
    Li = _whitener(model, alpha, moment_floor)
    r, Ja, Js = _stack(model, alpha, means, counts, Li, structures)
    Ua = _range_basis(Ja)
    e = r - Ua @ (Ua.T @ r)  # the whitened residual of the constant fit
    total = float(e @ e)
    n_eq, ra = len(r), Ua.shape[1]
    each = level / max(len(structures), 1)
    fits = []
    if joint is None:  # does any structure reject? (the linear statistics are cheap)
        joint = False
        for st in structures:
            X = _unit_columns(Js[st])[0]
            Ub = _range_basis(X - Ua @ (Ua.T @ X))
            if Ub.shape[1] and float(np.sum((Ub.T @ e) ** 2)) > chi2.isf(each, Ub.shape[1]):
                joint = True
                break
    for st in structures:
        X, cs = _unit_columns(Js[st])  # the rank on unit columns: units do not matter
        X = X - Ua @ (Ua.T @ X)
        p = X.shape[1]
        U, s, Vt = np.linalg.svd(X, full_matrices=False)
        keep = s > RANK_TOLERANCE * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
        rank = int(keep.sum())
        Uk, sk, Vk = U[:, keep], s[keep], Vt[keep].T
        proj = Uk.T @ e
        q = float(proj @ proj)
        beta = (Vk @ (proj / sk) if rank else np.zeros(p)) / cs
        var = (Vk**2) @ (1.0 / sk**2) if rank else np.full(p, np.inf)
        sigma = np.sqrt(var) / cs
        if rank < p:  # a parameter with a component outside the determined directions
            outside = 1.0 - np.sum(Vk**2, axis=1) if rank else np.ones(p)
            sigma = np.where(outside > 1e-9, np.inf, sigma)
        mdof = n_eq - ra - rank
        limit = float(chi2.isf(each, rank)) if rank else math.inf
        mlimit = float(chi2.isf(each, mdof)) if mdof > 0 else math.inf
        a_fit = np.asarray(alpha, float).copy()
        P_joint = None
        misfit = total - q
        converged = False
        if rank and joint:  # the joint (α0, β) fit, exact in β (fit_structure): estimate and misfit;
            # the statistic stays the linearised one (χ² under constant angles, also where
            # the nonlinear fit could exploit weakly determined angles)
            a_s, b_s = (starts or {}).get(st, (alpha, None))
            est = fit_structure(st, model, a_s, means, counts, moment_floor, b_s)
            if not est.converged and b_s is not None:  # from the constant fit, β = 0
                est = fit_structure(st, model, alpha, means, counts, moment_floor)
            converged = est.converged
            if converged:
                beta, a_fit, P_joint, misfit = est.beta, est.alpha, est.P, est.cost
                sigma = est.sigma[len(a_fit):]
        logp = float(chi2.logsf(q, rank) / math.log(10)) if rank else 0.0
        fits.append(StructureFit(st, rank, p, q, limit, logp, max(misfit, 0.0), mdof, mlimit,
                                 beta, sigma, rank == p, a_fit, P_joint, converged))
    info = {"equations": n_eq, "angle_rank": ra, "residual": total,
            "residual_dof": n_eq - ra}
    return fits, info


def design_ranks(model: RigModel, alpha: np.ndarray, means: np.ndarray,
                 counts: np.ndarray | None = None, moment_floor: float = 100.0,
                 structures: Sequence[str] = tuple(STRUCTURES)) -> dict[str, Any]:
    """What a design (its condition means) can tell: the rank of the angles, per structure
    the rank left after the angles, and per pair of structures the rank of their union — a
    union rank below the sum means directions the design cannot tell apart."""
    counts = np.ones(len(means)) if counts is None else counts
    Li = _whitener(model, alpha, moment_floor)
    _, Ja, Js = _stack(model, alpha, means, counts, Li, structures)
    Ua = _range_basis(Ja)

    def after(X: np.ndarray) -> np.ndarray:
        out: np.ndarray = X - Ua @ (Ua.T @ X)
        return out

    ranks = {st: _range_basis(after(Js[st])).shape[1] for st in structures}
    pairs: dict[str, dict[str, int]] = {}
    for i, a in enumerate(structures):
        for b in structures[i + 1:]:
            u = _range_basis(after(np.hstack([Js[a], Js[b]]))).shape[1]
            pairs[f"{a}+{b}"] = {"union": u, "shared": ranks[a] + ranks[b] - u}
    return {"equations": Ja.shape[0], "angle_rank": Ua.shape[1],
            "nominal": {st: Js[st].shape[1] for st in structures}, "rank": ranks,
            "pairs": pairs}


def spend(look: int, total: float = FALSE_ALARM) -> float:
    """The alpha-spending rule: the level of look k (1, 2, …), Σ_k = total."""
    return total * 6.0 / (math.pi**2 * look**2)


# ------------------------------------------------------------------------------------------
# The time-varying candidate: angles on a slow trend 
# ------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------
# The sequential test
# ------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------
# The selected structure in the hub-load estimate (the service's per-sample path)
# ------------------------------------------------------------------------------------------
APPLIED = tuple(STRUCTURES)  # the structures a selected fit may name


def fit_payload(selected: dict[str, Any], model: RigModel) -> dict[str, Any]:
    """The JSON-ready ``structure_fit`` (angles record, posterior file, config fragment;
    docs/telemetry.md) of a :attr:`StructureVerdict.selected`: the structure, α0 (rad), β in
    its SI units, their σ (None: not determined — held at the prior, never invented), and
    the reference cell loads ``T_ref`` (N) about which the estimator linearises the angles."""
    st = selected["structure"]
    na = model.geometry.n_cells * 2
    sig = np.asarray(selected["sigma_all"], float)
    return {"structure": st,
            "parameters": list(parameter_names(st, model)),
            "alpha0": [float(v) for v in selected["alpha"]],
            "beta": [float(v) for v in selected["beta"]],
            "alpha0_sigma": [float(v) if math.isfinite(v) else None for v in sig[:na]],
            "beta_sigma": [float(v) if math.isfinite(v) else None for v in sig[na:]],
            "T_ref": [float(v) for v in selected["T_ref"]]}


def check_fit_payload(d: object, model: RigModel) -> dict[str, Any]:
    """A ``structure_fit`` read from a file or a record, checked (ValueError naming what is
    wrong); returns it with float lists."""
    if not isinstance(d, dict):
        raise ValueError("structure_fit must be an object")
    st = d.get("structure")
    if st not in APPLIED:
        raise ValueError(f"structure_fit.structure {st!r} is not one of {list(APPLIED)}")
    na, p = 2 * model.geometry.n_cells, len(parameter_names(st, model))
    out = dict(d)
    for key, n in (("alpha0", na), ("beta", p), ("T_ref", model.geometry.n_cells)):
        try:
            v = np.asarray(d.get(key), float)
        except (TypeError, ValueError):
            raise ValueError(f"structure_fit.{key} is not a list of numbers") from None
        if v.shape != (n,) or not np.isfinite(v).all():
            raise ValueError(f"structure_fit.{key} must be {n} finite numbers")
        out[key] = v.tolist()
    return out


class StructureCorrection:
    """The hub-load model of a selected structure in the form the per-sample path takes:
    the filter keeps ``R₀`` and ``S(alpha)``; the measured CG wrench z is replaced by
    ``correct(z, T)`` so that ``R₀⁻¹ (correct(z, T) − S(alpha) T)`` is the structure's
    hub load:

    * ``cell_load_angles``: ``alpha = α0 + g∘T_ref`` and
      ``correct = z − B (T∘(T − T_ref))``, B (6×7) the first-order change of S T with the
      angles (``B[:, c] = Σ_{k∈c} ∂S/∂α_k[:, c] g_k``) — S(α0 + g∘T) T to first order in
      g∘(T − T_ref); the second order is ½ |∂²S| (g ΔT)² T (≈ 3 N at 0.75° and 30 kN);
    * ``hub_position``, ``external_load``: ``alpha = α0``,
      ``correct = z − (I − R₀ R(β)⁻¹)(z − S(α0) T)`` (exact: the hub load is R(β)⁻¹(z − S T));
    * ``balance``: ``alpha = α0``, z unchanged (the balance's error is in the reference).

    The instantaneous cell load drives the angles (a deflection follows the load well below
    the mount modes); the simulator moves them with the static load, which differs at the
    harmonics only (their mean is unchanged)."""

    def __init__(self, model: RigModel, fit: dict[str, Any]) -> None:
        fit = check_fit_payload(fit, model)
        self.structure = fit["structure"]
        a0, beta = np.asarray(fit["alpha0"]), np.asarray(fit["beta"])
        self.T_ref = np.asarray(fit["T_ref"])
        c = structure_of(self.structure).correction(model, a0, beta, self.T_ref)
        self.alpha, self.B, self.M = c.alpha, c.B, c.M
        if c.S is not None:
            self.S = c.S

    def correct(self, z: np.ndarray, T: np.ndarray) -> np.ndarray:
        if self.B is not None:
            result: np.ndarray = z - self.B @ (T * (T - self.T_ref))
            return result
        if self.M is not None:
            corrected: np.ndarray = z - self.M @ (z - self.S @ T)
            return corrected
        return z
