"""Maximum-likelihood identification of the load-cell angles (model.md §7; report Eq 2.17–2.28,
Appendix C).

Two residuals, one likelihood:

* known-load mode: ``e = z − S(θ) T_m − R₀ H_m − E q_m`` (the balance measures H, so no filter);
* filter-error mode: ``e`` are the innovations of the fixed-gain calibration filter, with the
  sensitivity recursion of Eq 2.22–2.24 (gain fixed, because J = R C does not depend on θ).

The likelihood is the effective-variance one of model §7.2 (errors in variables: load-cell noise is in
the regressors too), ``V(θ) = ½ Σ eᵀ W(θ)⁻¹ e`` with ``W(θ) = Σ_z + S Σ_T Sᵀ (+ R₀ Σ_H R₀ᵀ)``
from the configured sensor accuracies — never the residual covariance of Eq 2.19 (the report's
relaxation, biased here; :func:`relaxation_estimate` keeps it for the documented comparison).
In filter-error mode W is replaced by the innovation covariance ``B(θ) = J P⁻(θ) Jᵀ + W(θ)``.
No log-det term. Minimised by Levenberg–Marquardt from the prior mean; Cramér–Rao bounds
conventional and corrected for coloured residuals (Morelli & Klein 1995).

Pure numerics: numpy in, numpy out.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Protocol, Sequence

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.signal

from .balance import measurement_covariance
from .geometry import hub_transfer_matrix, wrench_matrix, wrench_matrix_jacobian
from .params import RigModel

# Non-angle parameters that can be calibrated (model.md §2.2: "any subset of parameters"),
# through central finite differences (checked against a halved step by check_derivatives).
_AXES3 = ("x", "y", "z")
_INERTIA = ("I_xx", "I_yy", "I_zz")
_MASS = ("m_x", "m_y", "m_z")


def parameter_names(model: RigModel) -> tuple[str, ...]:
    """Every name :class:`Parameterisation` accepts: the 14 angles first (contract order), then
    cell attach points ``x_A`` … ``z_G``, hub centre ``hub_x`` … ``hub_z``, effective masses
    ``m_x`` … and moments of inertia ``I_xx`` …."""
    g = model.geometry
    pos = tuple(f"{a}_{c}" for c in g.cell_names for a in _AXES3)
    return g.angle_names + pos + tuple(f"hub_{a}" for a in _AXES3) + _MASS + _INERTIA


@dataclass(frozen=True)
class Terms:
    """The model at θ: residual ``e = A x`` per sample and the weight W, with derivatives.

    ``x`` stacks the measured channels of one sample: ``[z (6), T (n_cells), H (6, known-load
    mode only), q (Q)]``; so ``A = [diag(z scale), −S, −R₀, −E]``.
    """

    A: np.ndarray  # (6, ncol)
    dA: np.ndarray  # (p, 6, ncol)
    W: np.ndarray  # (6, 6)
    dW: np.ndarray  # (p, 6, 6)
    S: np.ndarray  # (6, n_cells)


class Parameterisation:
    """Maps the identified parameter vector θ (any subset of named parameters) to the model.

    Angles have analytic derivatives (dS/dα of model §2, and ∂W/∂α = dS Σ_T Sᵀ + S Σ_T dSᵀ);
    geometry and mass parameters use central finite differences of A and W.
    """

    def __init__(
        self,
        model: RigModel,
        names: Sequence[str] | None = None,
        alpha: np.ndarray | None = None,
        *,
        moment_floor: float,
        known_loads: bool,
        fd_step: float = 1e-5,
    ) -> None:
        g = model.geometry
        self.model = model
        self.names: tuple[str, ...] = tuple(g.angle_names if names is None else names)
        allowed = parameter_names(model)
        bad = [n for n in self.names if n not in allowed]
        if bad or len(set(self.names)) != len(self.names) or not self.names:
            raise ValueError(f"unknown or repeated parameter names {bad or list(self.names)}; "
                             f"choose distinct names from {list(allowed)}")
        self.alpha0 = np.zeros(2 * g.n_cells) if alpha is None else np.asarray(alpha, float).copy()
        self.moment_floor = float(moment_floor)
        self.known_loads = bool(known_loads)
        self.fd_step = float(fd_step)
        self.angle_slots = [g.angle_names.index(n) for n in self.names if n in g.angle_names]
        self.angle_pos = [k for k, n in enumerate(self.names) if n in g.angle_names]
        self.other_pos = [k for k, n in enumerate(self.names) if n not in g.angle_names]
        self._mass0 = np.concatenate([model.mass.mass, model.mass.inertia]).astype(float)
        self._sigma_T2 = np.asarray(model.cell_sigma, float) ** 2
        self._R0 = hub_transfer_matrix(g, "body")

    # -- layout ---------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def n_cells(self) -> int:
        return self.model.geometry.n_cells

    @property
    def n_columns(self) -> int:
        q = self.model.external.wrenches.shape[1]
        return int(6 + self.n_cells + (6 if self.known_loads else 0) + q)

    def stack(self, z: np.ndarray, T: np.ndarray, H: np.ndarray | None = None,
              q: np.ndarray | None = None) -> np.ndarray:
        """x (N, ncol) = [z, T, H, q] in the column order of :class:`Terms`."""
        parts = [np.asarray(z, float), np.asarray(T, float)]
        if self.known_loads:
            if H is None:
                raise ValueError("known-load mode needs the measured hub loads H")
            parts.append(np.asarray(H, float))
        Q = self.model.external.wrenches.shape[1]
        if Q:
            if q is None:
                raise ValueError(f"the rig has {Q} measured external loads: pass q")
            parts.append(np.asarray(q, float).reshape(len(parts[0]), Q))
        return np.hstack(parts)

    # -- values ---------------------------------------------------------------------------
    def initial(self) -> np.ndarray:
        """θ of the base model (angles from ``alpha``)."""
        return self._values(self.model, self.alpha0)

    def alpha(self, theta: np.ndarray) -> np.ndarray:
        """The 14 angles at θ (angles not identified stay at their base values)."""
        a = self.alpha0.copy()
        a[self.angle_slots] = np.asarray(theta, float)[self.angle_pos]
        return a

    def _values(self, model: RigModel, alpha: np.ndarray) -> np.ndarray:
        g = model.geometry
        out = np.empty(self.n)
        for k, name in enumerate(self.names):
            if name in g.angle_names:
                out[k] = alpha[g.angle_names.index(name)]
            elif name.startswith("hub_"):
                out[k] = g.hub_position[_AXES3.index(name[4])]
            elif name in _MASS:
                out[k] = model.mass.mass[_MASS.index(name)]
            elif name in _INERTIA:
                out[k] = model.mass.inertia[_INERTIA.index(name)]
            else:
                axis, cell = name.split("_", 1)
                out[k] = g.cell_positions[g.cell_names.index(cell), _AXES3.index(axis)]
        return out

    def model_at(self, theta: np.ndarray) -> RigModel:
        """The rig model with the non-angle parameters of θ substituted."""
        if not self.other_pos:
            return self.model
        m = self.model
        g = m.geometry
        pos, hub = g.cell_positions.copy(), g.hub_position.copy()
        mass, inertia = m.mass.mass.copy(), m.mass.inertia.copy()
        for k in self.other_pos:
            name, v = self.names[k], float(theta[k])
            if name.startswith("hub_"):
                hub[_AXES3.index(name[4])] = v
            elif name in _MASS:
                mass[_MASS.index(name)] = v
            elif name in _INERTIA:
                inertia[_INERTIA.index(name)] = v
            else:
                axis, cell = name.split("_", 1)
                pos[g.cell_names.index(cell), _AXES3.index(axis)] = v
        return replace(m, geometry=replace(g, cell_positions=pos, hub_position=hub),
                       mass=replace(m.mass, mass=mass, inertia=inertia))

    # -- the model at θ -------------------------------------------------------------------
    def _A_W(self, model: RigModel, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        S = wrench_matrix(model.geometry, alpha)
        scale = np.concatenate([model.mass.mass, model.mass.inertia]) / self._mass0
        blocks = [np.diag(scale), -S]
        if self.known_loads:
            blocks.append(-hub_transfer_matrix(model.geometry, "body"))
        if model.external.wrenches.shape[1]:
            blocks.append(-model.external.wrenches)
        W = measurement_covariance(model, alpha, self.moment_floor, self.known_loads)
        return np.hstack(blocks), W, S

    def terms(self, theta: np.ndarray) -> Terms:
        theta = np.asarray(theta, float)
        model, alpha = self.model_at(theta), self.alpha(theta)
        A, W, S = self._A_W(model, alpha)
        p, nc = self.n, self.n_cells
        dA = np.zeros((p, 6, A.shape[1]))
        dW = np.zeros((p, 6, 6))
        if self.angle_pos:
            # analytic: only the T block of A moves, dA = −dS/dα (model §2); W through S.
            dS = wrench_matrix_jacobian(model.geometry, alpha)[self.angle_slots]
            dA[self.angle_pos, :, 6:6 + nc] = -dS
            X = np.einsum("jac,c,bc->jab", dS, np.asarray(model.cell_sigma, float) ** 2, S)
            dW[self.angle_pos] = X + X.transpose(0, 2, 1)
        for k in self.other_pos:
            h = self.fd_step * max(1.0, abs(theta[k]))
            tp, tm = theta.copy(), theta.copy()
            tp[k] += h
            tm[k] -= h
            Ap, Wp, _ = self._A_W(self.model_at(tp), alpha)
            Am, Wm, _ = self._A_W(self.model_at(tm), alpha)
            dA[k] = (Ap - Am) / (2 * h)
            dW[k] = (Wp - Wm) / (2 * h)
        return Terms(A=A, dA=dA, W=W, dW=dW, S=S)

    def check_derivatives(self, theta: np.ndarray) -> float:
        """Largest relative disagreement of the finite-difference derivatives of the non-angle
        parameters between the configured step and half of it (0 when all are angles)."""
        if not self.other_pos:
            return 0.0
        full = self.terms(theta)
        half = Parameterisation(self.model, self.names, self.alpha0, moment_floor=self.moment_floor,
                                known_loads=self.known_loads, fd_step=self.fd_step / 2).terms(theta)
        worst = 0.0
        for k in self.other_pos:
            for a, b in ((full.dA[k], half.dA[k]), (full.dW[k], half.dW[k])):
                scale = max(np.abs(b).max(), 1e-300)
                worst = max(worst, float(np.abs(a - b).max() / scale))
        return worst


# ------------------------------------------------------------------------------------------
# Evaluations of the likelihood
# ------------------------------------------------------------------------------------------
@dataclass
class Evaluation:
    """V(θ), its gradient and the Gauss–Newton information M at one θ."""

    theta: np.ndarray
    cost: float  # V
    gradient: np.ndarray | None  # (p,)
    information: np.ndarray | None  # (p, p) M
    weight: np.ndarray  # W (known loads) or B (filter error), 6x6
    residual_sum: np.ndarray  # Σ e eᵀ, 6x6
    n_scored: int
    end_state: "FilterErrorState | None" = None


class Problem(Protocol):
    """What Levenberg–Marquardt needs from a residual model."""

    mode: str
    par: Parameterisation

    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> Evaluation: ...

    def residual_series(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def _gradient_information(
    dA: np.ndarray, Winv: np.ndarray, AG: np.ndarray, G: np.ndarray,
    dW: np.ndarray | None, E: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """g_j = tr(W⁻¹ A G dA_jᵀ) − ½ tr(W⁻¹ ∂W_j W⁻¹ E),  M_ij = tr(dA_iᵀ W⁻¹ dA_j G)."""
    g = np.einsum("jab,ab->j", dA, Winv @ AG)
    if dW is not None:
        g -= 0.5 * np.einsum("jab,ba->j", dW, Winv @ E @ Winv)
    WdAG = np.einsum("ac,jcd->jad", Winv, dA) @ G
    M = np.einsum("iab,jab->ij", dA, WdAG)
    return g, 0.5 * (M + M.T)


def _sensitivities(x: np.ndarray, dA: np.ndarray) -> np.ndarray:
    """∂(A x_n)/∂θ_j for every sample: (N, 6, p), as one matrix product."""
    p, m, k = dA.shape
    result: np.ndarray = (x @ dA.transpose(2, 1, 0).reshape(k, m * p)).reshape(len(x), m, p)
    return result


def moments_information(par: Parameterisation, G: np.ndarray, n_scored: int,
                        theta: np.ndarray) -> np.ndarray | None:
    """The information (Gauss–Newton M) about θ of known-load windows given by their moments
    ``G = Σ x xᵀ`` and scored count, at ``theta``."""
    return _moments_evaluation(par, G, n_scored, theta, True, None).information


def moments_gradient_information(par: Parameterisation, G: np.ndarray, n_scored: int,
                                 theta: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The gradient of V and the information M about θ of known-load windows given by their
    moments, at ``theta`` (None when either is not finite)."""
    ev = _moments_evaluation(par, G, n_scored, theta, True, None)
    g, M = ev.gradient, ev.information
    if g is None or M is None or not (np.all(np.isfinite(g)) and np.all(np.isfinite(M))):
        return None
    return g, M


def _moments_evaluation(par: Parameterisation, G: np.ndarray, n_scored: int, theta: np.ndarray,
                        derivatives: bool, fixed_weight: np.ndarray | None) -> Evaluation:
    """V, its gradient and M of the known-load likelihood from the moments G = Σ x xᵀ."""
    t = par.terms(theta)
    W = t.W if fixed_weight is None else fixed_weight
    Winv = np.linalg.inv(W)
    AG = t.A @ G
    E = AG @ t.A.T  # Σ e eᵀ
    V = 0.5 * float(np.sum(Winv * E))
    g = M = None
    if derivatives:
        g, M = _gradient_information(t.dA, Winv, AG, G, t.dW if fixed_weight is None else None,
                                     E)
    return Evaluation(np.asarray(theta, float).copy(), V, g, M, W, E, n_scored)


class KnownLoadProblem:
    """Known-load residuals ``e = z − S(θ) T_m − R₀ H_m (− E q_m)`` over the scored samples.

    W(θ) is the same for every sample, so V, its gradient and M follow from the second
    moments ``G = Σ x xᵀ`` of the stacked channels: one pass over the data, then every
    iteration is O(1) in the number of samples (the identification's time budget, docs/performance.md).
    """

    mode = "known_loads"

    def __init__(self, par: Parameterisation, z: np.ndarray, T: np.ndarray, H: np.ndarray,
                 q: np.ndarray | None = None, scored: np.ndarray | None = None) -> None:
        if not par.known_loads:
            raise ValueError("the parameterisation must be built with known_loads=True")
        self.par = par
        x = par.stack(z, T, H, q)
        self.scored = np.ones(len(x), bool) if scored is None else np.asarray(scored, bool)
        self._x = np.where(self.scored[:, None], x, 0.0)  # unscored samples count as zero
        self.n_scored = int(self.scored.sum())
        self.G = self._x.T @ self._x

    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> Evaluation:
        return _moments_evaluation(self.par, self.G, self.n_scored, theta, derivatives,
                                   fixed_weight)

    def residual_series(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(e (N, 6), ∂e/∂θ (N, 6, p), weight) with zeros at unscored samples."""
        t = self.par.terms(theta)
        return self._x @ t.A.T, _sensitivities(self._x, t.dA), t.W

    def with_moments(self, G: np.ndarray, n_scored: int) -> "AccumulatedKnownLoadProblem":
        """This window together with earlier windows given by their moments ``G = Σ x xᵀ``
        (and scored sample count): W(θ) is the same for every sample and there is no log-det
        term, so V of the union is exactly V of the summed moments."""
        return AccumulatedKnownLoadProblem(self, G, n_scored)


class AccumulatedKnownLoadProblem:
    """The exact known-load likelihood of earlier windows (summed moments) plus one window.

    Used by the sequential posterior to re-linearise: every run re-solves the batch problem of
    all windows since the last fold instead of trusting Gaussian summaries made far from the
    answer. The residual series (for the coloured-residual bound) is the new window's; the
    earlier windows enter that bound with their conventional information
    (:meth:`uncorrelated_information`)."""

    mode = "known_loads"

    def __init__(self, window: KnownLoadProblem, G_extra: np.ndarray, n_extra: int) -> None:
        self.window, self.par = window, window.par
        self.G_extra = np.asarray(G_extra, float)
        self.G = window.G + self.G_extra
        self.n_scored = int(window.n_scored) + int(n_extra)
        self.n_series = int(window.n_scored)

    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> Evaluation:
        return _moments_evaluation(self.par, self.G, self.n_scored, theta, derivatives,
                                   fixed_weight)

    def residual_series(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.window.residual_series(theta)

    def uncorrelated_information(self, theta: np.ndarray) -> np.ndarray:
        """Gauss–Newton information of the earlier windows at θ."""
        t = self.par.terms(theta)
        Winv = np.linalg.inv(t.W)
        WdAG = np.einsum("ac,jcd->jad", Winv, t.dA) @ self.G_extra
        M = np.einsum("iab,jab->ij", t.dA, WdAG)
        result: np.ndarray = 0.5 * (M + M.T)
        return result


# ------------------------------------------------------------------------------------------
# Filter-error mode
# ------------------------------------------------------------------------------------------
@dataclass
class FilterErrorState:
    """Calibration-filter state x⁺ and its sensitivities ∂x⁺/∂θ at the end of a window,
    evaluated at ``theta``: the next window starts from ``x + dx (θ − theta)``."""

    x: np.ndarray  # (ns,)
    dx: np.ndarray  # (ns, p)
    theta: np.ndarray  # (p,)

    def at(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.x + self.dx @ (np.asarray(theta, float) - self.theta), self.dx


def innovation_covariance(
    Phi: np.ndarray, K: np.ndarray, J: np.ndarray, Qd: np.ndarray, W: np.ndarray,
    dW: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """B = J P⁻ Jᵀ + W with P⁻ = Φ(I−KJ) P⁻ (I−KJ)ᵀΦᵀ + Φ K W Kᵀ Φᵀ + Q_d (model §7), and
    ∂B/∂θ_j = J ∂P⁻_j Jᵀ + ∂W_j, ∂P⁻_j solving the same equation with source Φ K ∂W_j Kᵀ Φᵀ."""
    ns = Phi.shape[0]
    a = Phi @ (np.eye(ns) - K @ J)
    PK = Phi @ K
    P = scipy.linalg.solve_discrete_lyapunov(a, PK @ W @ PK.T + Qd)
    B = J @ P @ J.T + W
    B = 0.5 * (B + B.T)
    dB = None
    if dW is not None:
        dB = np.empty_like(dW)
        for j in range(dW.shape[0]):
            src = PK @ dW[j] @ PK.T
            dP = scipy.linalg.solve_discrete_lyapunov(a, 0.5 * (src + src.T))
            dB[j] = J @ dP @ J.T + dW[j]
    return B, dB


def scored_mask(valid: np.ndarray, settle: int, gap: int, start_discontinuity: bool) -> np.ndarray:
    """Samples scored by the filter-error likelihood: valid, and not within ``settle`` samples
    after a discontinuity (the window start when flagged, or a run of more than ``gap``
    invalid samples): the filter transient must die out first (report: "allowed to reach
    steady state before the Maximum Likelihood algorithm begins")."""
    valid = np.asarray(valid, bool)
    scored = valid.copy()
    if start_discontinuity:
        scored[:settle] = False
    # runs of invalid samples: [start, end); a run longer than `gap` is a discontinuity
    flips = np.flatnonzero(np.diff(np.concatenate([[1], valid.astype(np.int8), [1]])))
    for start, end in zip(flips[0::2], flips[1::2]):
        if end - start > gap:
            scored[end:end + settle] = False
    return scored


def scattered_missing_fraction(valid: np.ndarray, gap: int) -> float:
    """The fraction of a window's samples lacking an input in runs of at most ``gap`` samples
    (single dropped frames): runs no settling follows (:func:`scored_mask`), whose held
    samples perturb the content filter's output at the valid samples after them."""
    valid = np.asarray(valid, bool)
    if not len(valid):
        return 0.0
    flips = np.flatnonzero(np.diff(np.concatenate([[1], valid.astype(np.int8), [1]])))
    short = sum(int(e - s) for s, e in zip(flips[0::2], flips[1::2]) if e - s <= gap)
    return short / len(valid)


class FilterErrorProblem:
    """Innovations of the fixed-gain calibration filter and their sensitivities (Eq 2.22–2.24):

        x⁻(n) = Φ x⁺(n−1),  e(n) = z − S(θ) T_m − E q_m − J x⁻(n),  x⁺(n) = x⁻(n) + K e(n)
        ∂x⁻ = Φ ∂x⁺(n−1),   ∂e = −(∂S/∂θ) T_m − J ∂x⁻,              ∂x⁺ = ∂x⁻ + K ∂e

    Missing samples (``valid`` false) are predict-only. The state and its sensitivities start
    from ``state`` (continued from the previous window) or zero. After a discontinuity (the
    start when ``discontinuity`` is true — by default when there is no state — or a run of
    more than ``gap`` missing samples) ``settle`` samples are not scored. ``method="loop"``
    runs the recursion sample by sample on all 1 + p columns at once (the default: about
    7 µs a sample here); ``"modal"`` is the batch form — the LTI recursion in the closed-loop
    eigenbasis, one ``scipy.signal.lfilter`` per conjugate pair of modes — equal to rounding,
    but slower at these sizes (its complex intermediates cost more than the loop saves).
    """

    mode = "filter_error"

    def __init__(
        self,
        par: Parameterisation,
        Phi: np.ndarray,
        K: np.ndarray,
        J: np.ndarray,
        Qd: np.ndarray,
        z: np.ndarray,
        T: np.ndarray,
        q: np.ndarray | None = None,
        *,
        valid: np.ndarray | None = None,
        settle: int = 0,
        gap: int | None = None,
        state: FilterErrorState | None = None,
        discontinuity: bool | None = None,
        method: str = "loop",
        Phi_n: np.ndarray | None = None,
    ) -> None:
        if par.known_loads:
            raise ValueError("filter-error mode has no known loads: build the parameterisation "
                             "with known_loads=False")
        if any(par.names[k].startswith("hub_") for k in par.other_pos):
            raise ValueError("hub position parameters change J = R C: not identifiable in "
                             "filter-error mode")
        self.par = par
        self.Phi, self.K, self.J, self.Qd = (np.asarray(a, float) for a in (Phi, K, J, Qd))
        self._x = par.stack(z, T, None, q)
        N = len(self._x)
        self.valid = np.ones(N, bool) if valid is None else np.asarray(valid, bool)
        self.state = state
        gap = N + 1 if gap is None else int(gap)
        start = state is None if discontinuity is None else bool(discontinuity)
        self.scored = scored_mask(self.valid, int(settle), gap, start)
        self.n_scored = int(self.scored.sum())
        if method not in ("modal", "loop"):
            raise ValueError("method must be 'modal' or 'loop'")
        ns = self.Phi.shape[0]
        self._Acl = (np.eye(ns) - self.K @ self.J) @ self.Phi
        self._JPhi = self.J @ self.Phi
        self.method = method
        # azimuth mode : Φ of every sample (N, ns, ns), from the rotor's measured
        # turn (``filters.azimuth_transition``); the time-varying recursion runs as the loop
        self.Phi_n = None if Phi_n is None else np.asarray(Phi_n, float)
        if self.Phi_n is not None:
            if self.Phi_n.shape != (N, ns, ns):
                raise ValueError(f"Phi_n must have shape ({N}, {ns}, {ns}), got {self.Phi_n.shape}")
            self.method = "loop"
        lam, V = np.linalg.eig(self._Acl)
        self._modal = bool(np.linalg.cond(V) < 1e8)  # a defective closed loop: use the loop
        if not self._modal:
            self.method = "loop"
        if self._modal:
            Vinv = np.linalg.inv(V)
            # conjugate modes of a real system: keep one of each pair, weight 2 on Re(·)
            keep = lam.imag >= 0
            self._lam = lam[keep]
            self._VinvK = Vinv[keep] @ self.K
            self._Vinv = Vinv[keep]
            w = np.where(lam[keep].imag > 0, 2.0, 1.0)
            self._Vw = V[:, keep] * w
            self._JPhiVw = self._JPhi @ self._Vw
            # Lyapunov of a = Φ(I − KJ) = Φ Acl Φ⁻¹ in its eigenbasis U = Φ V
            self._U = self.Phi @ V
            self._Uinv = Vinv @ np.linalg.inv(self.Phi)
            self._lyap_den = 1.0 - lam[:, None] * np.conj(lam)[None, :]
        # segments of equal validity, in order
        edges = np.flatnonzero(np.diff(self.valid.astype(np.int8))) + 1
        self._segments = list(zip(np.concatenate([[0], edges]), np.concatenate([edges, [N]])))

    def _innovation_covariance(self, W: np.ndarray, dW: np.ndarray | None
                               ) -> tuple[np.ndarray, np.ndarray | None]:
        """B and ∂B/∂θ (see :func:`innovation_covariance`); the Lyapunov equations solved in
        the eigenbasis of Φ(I − KJ), which is fixed, so each source costs two products."""
        if not self._modal:
            return innovation_covariance(self.Phi, self.K, self.J, self.Qd, W, dW)
        PK = self.Phi @ self.K
        U, Ui, den = self._U, self._Uinv, self._lyap_den

        def lyap(q: np.ndarray) -> np.ndarray:
            result: np.ndarray = (U @ ((Ui @ q @ Ui.conj().T) / den) @ U.conj().T).real
            return result

        P = lyap(PK @ W @ PK.T + self.Qd)
        B = self.J @ P @ self.J.T + W
        B = 0.5 * (B + B.T)
        if dW is None:
            return B, None
        src = PK @ dW @ PK.T  # (p, ns, ns)
        Xt = (Ui @ src @ Ui.conj().T) / den
        dP = (U @ Xt @ U.conj().T).real
        dB = self.J @ dP @ self.J.T + dW
        return B, 0.5 * (dB + dB.transpose(0, 2, 1))

    # the filter on all columns at once: Y (N, 6, c), X0 (ns, c) -> E (N, 6, c), X_end (ns, c)
    def _run(self, Y: np.ndarray, X0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        E = np.zeros_like(Y)
        X = X0
        c = Y.shape[2]
        for s, e in self._segments:
            L = int(e - s)
            if not self.valid[s]:
                if self.Phi_n is not None:
                    for n in range(s, e):
                        X = self.Phi_n[n] @ X
                    continue
                X = np.linalg.matrix_power(self.Phi, L) @ X  # predict through
                continue
            if self.Phi_n is not None:
                for n in range(s, e):
                    Xm = self.Phi_n[n] @ X
                    E[n] = Y[n] - self.J @ Xm
                    X = Xm + self.K @ E[n]
                continue
            if self.method == "loop":  # the per-sample reference, literally Eq 2.22–2.24
                for n in range(s, e):
                    Xm = self.Phi @ X
                    E[n] = Y[n] - self.J @ Xm
                    X = Xm + self.K @ E[n]
                continue
            # batch (modal): ξ(n) = λ ξ(n−1) + V⁻¹K Y(n);  E(n) = Y(n) − JΦ V ξ(n−1)
            Yb = Y[s:e]
            m = len(self._lam)
            U = (self._VinvK @ Yb.transpose(1, 0, 2).reshape(6, L * c)).reshape(m, L, c)
            xi0 = self._Vinv @ X  # (m, c)
            xi = np.empty((m, c, L + 1), complex)
            xi[:, :, 0] = xi0
            for k, lam in enumerate(self._lam):
                xi[k, :, 1:], _ = scipy.signal.lfilter(
                    [1.0], [1.0, -lam], U[k].T, axis=-1, zi=(lam * xi0[k])[:, None])
            prev = xi[:, :, :-1].reshape(m, c * L)
            E[s:e] = Yb - (self._JPhiVw @ prev).real.reshape(6, c, L).transpose(2, 0, 1)
            X = (self._Vw @ xi[:, :, -1]).real
        return E, X

    def _inputs(self, theta: np.ndarray, t: Terms, derivatives: bool
                ) -> tuple[np.ndarray, np.ndarray]:
        x0, dx0 = (self.state.at(theta) if self.state is not None
                   else (np.zeros(self.Phi.shape[0]), np.zeros((self.Phi.shape[0], self.par.n))))
        y = self._x @ t.A.T  # (N, 6): z − S T − E q
        if not derivatives:
            return y[:, :, None], x0[:, None]
        dy = _sensitivities(self._x, t.dA)  # (N, 6, p)
        return np.concatenate([y[:, :, None], dy], axis=2), np.column_stack([x0, dx0])

    def innovations(self, theta: np.ndarray, derivatives: bool = True
                    ) -> tuple[np.ndarray, np.ndarray | None, FilterErrorState | None]:
        """(e (N, 6), ∂e/∂θ (N, 6, p) or None, end state) over all samples (invalid ones 0)."""
        theta = np.asarray(theta, float)
        t = self.par.terms(theta)
        Y, X0 = self._inputs(theta, t, derivatives)
        E, X = self._run(Y, X0)
        state = (FilterErrorState(X[:, 0].copy(), X[:, 1:].copy(), theta.copy())
                 if derivatives else None)
        return E[:, :, 0], (E[:, :, 1:] if derivatives else None), state

    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> Evaluation:
        theta = np.asarray(theta, float)
        t = self.par.terms(theta)
        Y, X0 = self._inputs(theta, t, derivatives)
        Eall, X = self._run(Y, X0)
        sc = self.scored
        e = Eall[sc, :, 0]
        if fixed_weight is None:
            B, dB = self._innovation_covariance(t.W, t.dW if derivatives else None)
        else:
            B, dB = fixed_weight, None
        Binv = np.linalg.inv(B)
        Esum = e.T @ e
        V = 0.5 * float(np.sum(Binv * Esum))
        g = M = None
        state = None
        if derivatives:
            de = Eall[sc, :, 1:]  # (n, 6, p)
            n_s, p = len(e), de.shape[2]
            g = (e @ Binv).reshape(1, -1) @ de.reshape(n_s * 6, p)
            g = g.ravel()
            if dB is not None:
                g -= 0.5 * np.einsum("jab,ba->j", dB, Binv @ Esum @ Binv)
            BD = (Binv @ de)  # (n, 6, p)
            M = de.reshape(n_s * 6, p).T @ BD.reshape(n_s * 6, p)
            M = 0.5 * (M + M.T)
            state = FilterErrorState(X[:, 0].copy(), X[:, 1:].copy(), theta.copy())
        return Evaluation(theta.copy(), V, g, M, B, Esum, self.n_scored, state)

    def residual_series(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, de, _ = self.innovations(theta)
        assert de is not None  # derivatives=True
        e = np.where(self.scored[:, None], e, 0.0)
        de = np.where(self.scored[:, None, None], de, 0.0)
        B, _ = self._innovation_covariance(self.par.terms(theta).W, None)
        return e, de, B


# ------------------------------------------------------------------------------------------
# Cramér–Rao bounds corrected for coloured residuals (Morelli & Klein 1995)
# ------------------------------------------------------------------------------------------
def residual_autocorrelation(e: np.ndarray, max_lag: int, n: int | None = None) -> np.ndarray:
    """R(k) = (1/n) Σ_i e_i e_{i+k}ᵀ for k = 0 … max_lag: (max_lag+1, 6, 6), by FFT."""
    N, m = e.shape
    n = N if n is None else n
    L = int(min(max_lag, N - 1))
    M = scipy.fft.next_fast_len(N + L + 1, real=True)
    F = np.fft.rfft(e, n=M, axis=0)  # (F, m)
    cross = np.fft.irfft(np.conj(F)[:, :, None] * F[:, None, :], n=M, axis=0)
    return cross[: L + 1] / max(n, 1)


def coloured_residual_information(
    e: np.ndarray, de: np.ndarray, weight: np.ndarray, max_lag: int, n: int | None = None,
) -> tuple[np.ndarray, int]:
    """Q = Σ_i Σ_j D_iᵀ W⁻¹ R(i−j) W⁻¹ D_j (Morelli & Klein 1995), R the residual
    autocorrelation up to the lag where its whitened trace tr(W⁻¹R(k)) first crosses zero
    (at most ``max_lag``). Returns (Q, lags used). With white residuals Q ≈ M.

    Evaluated exactly in the frequency domain: zero-padding to M ≥ N + L makes the circular
    convolution linear, and Parseval turns the double sum into (1/M) Σ_f Ĝ_fᴴ R̂_f Ĝ_f.
    """
    Winv = np.linalg.inv(weight)
    R = residual_autocorrelation(e, max_lag, n)
    rho = np.einsum("ab,kba->k", Winv, R)
    cross = np.flatnonzero(rho[1:] <= 0.0)
    L = int(cross[0]) if cross.size else len(R) - 1  # lags 0..L are kept
    return _score_quadratic(R, Winv @ de, L), L


def _score_quadratic(gamma: np.ndarray, G: np.ndarray, L: int) -> np.ndarray:
    """Σ_i Σ_j G_iᵀ Γ(j−i) G_j for G (N, 6, p) and the autocovariance Γ(k), k = 0 … L
    (Γ(−k) = Γ(k)ᵀ), exactly: zero-padding to M ≥ N + L makes the circular convolution
    Y_i = Σ_j c(i−j) G_j, c(d) = Γ(−d), linear, and Parseval turns the double sum into
    (1/M) Σ_f Ĝ_fᴴ R̂_f Ĝ_f."""
    N, _, p = G.shape
    M = scipy.fft.next_fast_len(N + L + 1, real=True)
    rc = np.zeros((M, 6, 6))
    rc[: L + 1] = gamma[: L + 1].transpose(0, 2, 1)
    if L:
        rc[M - L:] = gamma[1: L + 1][::-1]
    Rf = np.fft.rfft(rc, axis=0)  # (F, 6, 6)
    Gf = np.fft.rfft(G, n=M, axis=0)  # (F, 6, p)
    w = np.full(Rf.shape[0], 2.0 / M)
    w[0] = 1.0 / M
    if M % 2 == 0:
        w[-1] = 1.0 / M
    RG = Rf @ Gf
    Gw = np.conj(Gf) * w[:, None, None]
    Q = (Gw.reshape(-1, p).T @ RG.reshape(-1, p)).real
    result: np.ndarray = 0.5 * (Q + Q.T)
    return result


# ------------------------------------------------------------------------------------------
# Levenberg–Marquardt
# ------------------------------------------------------------------------------------------
@dataclass
class IdentificationResult:
    """One minimisation of J(θ) = V(θ) + ½ (θ − θ_p)ᵀ P_p⁻¹ (θ − θ_p)."""

    names: tuple[str, ...]
    mode: str
    theta: np.ndarray  # θ at the end
    P: np.ndarray  # (M + P_p⁻¹)⁻¹, conventional Cramér–Rao
    P_corrected: np.ndarray | None  # coloured-residual corrected
    information: np.ndarray  # M at θ
    prior_mean: np.ndarray
    prior_cov: np.ndarray | None
    cost: float  # J at θ
    cost_start: float  # J at the prior mean
    iterations: int
    status: str  # "converged", "not_converged", "diverged"
    n_scored: int
    lags: int = 0
    weight: np.ndarray | None = None
    end_state: FilterErrorState | None = None
    history: list[float] = field(default_factory=list)

    @property
    def sigma_cr(self) -> np.ndarray:
        result: np.ndarray = np.sqrt(np.clip(np.diag(self.P), 0.0, None))
        return result

    @property
    def sigma_cr_corrected(self) -> np.ndarray | None:
        if self.P_corrected is None:
            return None
        result: np.ndarray = np.sqrt(np.clip(np.diag(self.P_corrected), 0.0, None))
        return result

    @property
    def sound(self) -> bool:
        """Converged, finite, and J did not increase (model §7)."""
        return (self.status == "converged" and bool(np.all(np.isfinite(self.theta)))
                and bool(np.all(np.isfinite(self.P))) and self.cost <= self.cost_start)


def _prior_inverse(prior_cov: np.ndarray | None, p: int) -> np.ndarray:
    if prior_cov is None:
        return np.zeros((p, p))
    return np.linalg.inv(np.asarray(prior_cov, float))


def levenberg_marquardt(
    problem: Problem,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray | None = None,
    *,
    max_iterations: int = 10,
    lambda0: float = 1e-3,
    rel_tol: float = 1e-4,
    step_tol: float = 0.01,
    max_lag: int | None = None,
    max_retries: int = 12,
    warm_start: bool = True,
    start: np.ndarray | None = None,
) -> IdentificationResult:
    """Minimise J from the prior mean exactly as model §7 says:
    Δθ = −(M + P_p⁻¹ + λ diag(M + P_p⁻¹))⁻¹ g, λ from 1e-3, ×10 after a step that raises J
    (then retried), ÷10 after one that lowers it; stop when the relative change of J < 1e-4
    and every step < 0.01 of its posterior σ; at most ``max_iterations`` (else
    ``not_converged``). ``max_lag`` (samples) enables the coloured-residual bound.

    ``warm_start``: first the same Levenberg–Marquardt with the weight frozen at W(θ_p) (a
    nearly linear least-squares problem that converges in a few steps), then the effective-
    variance objective from there. Far from the answer (a 4° start) the full objective can
    lower V by inflating W(θ), and LM then crawls for tens of iterations; the frozen-weight
    stage goes straight to the neighbourhood of the optimum, which the full stage then refines
    to the same minimum. ``iterations`` counts both stages; each has at most
    ``max_iterations``.

    ``start``: where the iterations begin (default the prior mean); the sequential posterior
    starts a re-linearised run (prior = the anchor) from the previous posterior mean. J must
    not increase from there."""
    theta_p = np.asarray(prior_mean, float).copy()
    p = theta_p.size
    Pinv = _prior_inverse(prior_cov, p)
    theta_s = theta_p if start is None else np.asarray(start, float).copy()
    search = _Search(problem, theta_p, Pinv, lambda0=lambda0, rel_tol=rel_tol,
                     step_tol=step_tol, max_retries=max_retries)
    theta = theta_s.copy()
    ev = _evaluate(problem, theta)
    names = problem.par.names
    if ev is None or ev.gradient is None or not _finite_cost(ev):
        nanP = np.full((p, p), np.nan)
        return IdentificationResult(names, problem.mode, theta, nanP, None, nanP, theta_p,
                                    prior_cov, np.nan, np.nan, 0, "diverged", 0)
    J0 = Jc = search.total(ev, theta)
    warm_iterations = 0
    if warm_start:
        stage = levenberg_marquardt(
            _FrozenWeight(problem, ev.weight), theta_p, prior_cov,
            max_iterations=max_iterations, lambda0=lambda0, rel_tol=rel_tol, step_tol=step_tol,
            max_retries=max_retries, warm_start=False, start=theta_s)
        warm_iterations = stage.iterations
        theta, ev, Jc = search.warm(stage, theta, ev, Jc)
    theta, ev, Jc, iterations, status = search.run(theta, ev, Jc, max_iterations)
    # angles are 2π-periodic in J: report the equivalent closest to the prior mean (an LM step
    # through a region where W(θ) is inflated can land whole turns away)
    ang = problem.par.angle_pos
    if ang and np.all(np.isfinite(theta)):
        theta = theta.copy()
        theta[ang] = theta_s[ang] + np.angle(np.exp(1j * (theta[ang] - theta_s[ang])))
        if ev.end_state is not None:  # the filter state is periodic in θ too
            ev.end_state.theta = theta.copy()
    assert ev.information is not None  # evaluated with derivatives
    P = _symmetric_inverse(ev.information + Pinv)
    if not (np.all(np.isfinite(theta)) and np.isfinite(Jc) and Jc <= J0):
        status = "diverged"
    P_corr, lags = None, 0
    if max_lag is not None and status != "diverged" and np.all(np.isfinite(P)):
        P_corr, lags = _coloured_covariance(problem, theta, P, Pinv, max_lag)
    return IdentificationResult(
        names=names, mode=problem.mode, theta=theta, P=P, P_corrected=P_corr,
        information=ev.information, prior_mean=theta_p, prior_cov=prior_cov, cost=Jc,
        cost_start=J0, iterations=iterations + warm_iterations, status=status,
        n_scored=ev.n_scored, lags=lags,
        weight=ev.weight, end_state=ev.end_state, history=search.history,
    )


_EVALUATION_ERRORS = (np.linalg.LinAlgError, ValueError, FloatingPointError)


def _evaluate(problem: Problem, theta: np.ndarray, derivatives: bool = True
              ) -> Evaluation | None:
    """The problem at θ, None where it cannot be evaluated there."""
    try:
        return problem.evaluate(theta, derivatives)
    except _EVALUATION_ERRORS:
        return None


def _finite_cost(ev: Evaluation) -> bool:
    return bool(np.isfinite(ev.cost)) and (ev.gradient is None
                                            or bool(np.all(np.isfinite(ev.gradient))))


def _symmetric_inverse(H: np.ndarray) -> np.ndarray:
    """(H⁻¹ + H⁻ᵀ)/2; NaN where H is singular."""
    try:
        P = np.linalg.inv(H)
        return 0.5 * (P + P.T)
    except np.linalg.LinAlgError:
        return np.full(H.shape, np.nan)


def _coloured_covariance(problem: Problem, theta: np.ndarray, P: np.ndarray, Pinv: np.ndarray,
                         max_lag: int) -> tuple[np.ndarray, int]:
    """The coloured-residual corrected covariance P (Q + P_p⁻¹) P (Morelli & Klein) and the
    lags it used."""
    e, de, Wt = problem.residual_series(theta)
    Q, lags = coloured_residual_information(e, de, Wt, max_lag,
                                            getattr(problem, "n_series", problem_n(problem)))
    extra = getattr(problem, "uncorrelated_information", None)
    if extra is not None:
        Q = Q + extra(theta)
    P_corr = P @ (Q + Pinv) @ P
    return 0.5 * (P_corr + P_corr.T), lags


class _Search:
    """The iterations of :func:`levenberg_marquardt` (model §7): J = V + ½ (θ − θ_p)ᵀ P_p⁻¹
    (θ − θ_p), the damped steps and their stopping rules; ``history`` the J of each accepted
    step (the start's first)."""

    def __init__(self, problem: Problem, theta_p: np.ndarray, Pinv: np.ndarray, *,
                 lambda0: float, rel_tol: float, step_tol: float, max_retries: int) -> None:
        self.problem, self.theta_p, self.Pinv = problem, theta_p, Pinv
        self.lam = lambda0  # the damping, carried from step to step
        self.rel_tol, self.step_tol, self.max_retries = rel_tol, step_tol, max_retries
        self.history: list[float] = []

    def total(self, ev: Evaluation, th: np.ndarray) -> float:
        d = th - self.theta_p
        return ev.cost + 0.5 * float(d @ self.Pinv @ d)

    def warm(self, stage: IdentificationResult, theta: np.ndarray, ev: Evaluation, Jc: float
             ) -> tuple[np.ndarray, Evaluation, float]:
        """Continue from the frozen-weight stage's end where the full objective is no
        higher there (and its gradient finite); else from where it started."""
        if stage.status == "diverged" or not np.all(np.isfinite(stage.theta)):
            return theta, ev, Jc
        ev_w = _evaluate(self.problem, stage.theta)
        J_w = np.inf if ev_w is None else self._total_or_inf(ev_w, stage.theta)
        if (ev_w is not None and np.isfinite(J_w) and J_w <= Jc and ev_w.gradient is not None
                and np.all(np.isfinite(ev_w.gradient))):
            return stage.theta.copy(), ev_w, J_w
        return theta, ev, Jc

    def run(self, theta: np.ndarray, ev: Evaluation, Jc: float, max_iterations: int
            ) -> tuple[np.ndarray, Evaluation, float, int, str]:
        """Iterate from θ: (θ, its evaluation, J, iterations, status)."""
        self.history = [Jc]
        iterations = 0
        while iterations < max_iterations:
            assert ev.gradient is not None and ev.information is not None
            g = ev.gradient + self.Pinv @ (theta - self.theta_p)
            Hm = ev.information + self.Pinv
            step = self._step(theta, g, Hm, Jc)
            if step is None:
                # no step lowers J any more: a minimum to working precision when the undamped
                # step is already negligible against the posterior σ
                return theta, ev, Jc, iterations, ("converged" if self._stalled(Hm, g)
                                                   else "not_converged")
            iterations += 1
            theta = theta + step
            ev = self.problem.evaluate(theta)
            J_new = self.total(ev, theta)
            rel = abs(Jc - J_new) / max(abs(J_new), 1e-300)
            Jc = J_new
            self.history.append(Jc)
            if rel < self.rel_tol and self._small(step, ev):
                return theta, ev, Jc, iterations, "converged"
        return theta, ev, Jc, iterations, "not_converged"

    def _step(self, theta: np.ndarray, g: np.ndarray, Hm: np.ndarray, Jc: float
              ) -> np.ndarray | None:
        """Δθ = −(H + λ diag H)⁻¹ g, λ ×10 after a step that raises J (then retried), ÷10
        after one that lowers it; None when no retry lowers J."""
        dH = np.diag(np.diag(Hm))
        for _ in range(self.max_retries + 1):
            try:
                step = -np.linalg.solve(Hm + self.lam * dH, g)
            except np.linalg.LinAlgError:
                self.lam *= 10.0
                continue
            trial = theta + step
            ev_t = _evaluate(self.problem, trial, derivatives=False)
            Jt = np.inf if ev_t is None else self._total_or_inf(ev_t, trial)
            if np.isfinite(Jt) and Jt <= Jc:
                self.lam /= 10.0
                return step
            self.lam *= 10.0
        return None

    def _total_or_inf(self, ev: Evaluation, th: np.ndarray) -> float:
        try:
            return self.total(ev, th)
        except _EVALUATION_ERRORS:
            return np.inf

    def _stalled(self, Hm: np.ndarray, g: np.ndarray) -> bool:
        """The undamped (Newton) step below ``step_tol`` of every posterior σ."""
        try:
            sig = np.sqrt(np.diag(np.linalg.inv(Hm)))
            newton = np.linalg.solve(Hm, g)
        except np.linalg.LinAlgError:
            return False
        return bool(np.all(np.abs(newton) < self.step_tol * sig))

    def _small(self, step: np.ndarray, ev: Evaluation) -> bool:
        """Every component of the step below ``step_tol`` of its posterior σ."""
        assert ev.information is not None
        try:
            sig = np.sqrt(np.diag(np.linalg.inv(ev.information + self.Pinv)))
        except np.linalg.LinAlgError:
            sig = np.full(len(step), np.inf)
        return bool(np.all(np.abs(step) < self.step_tol * sig))


class _FrozenWeight:
    """A problem whose weight is held fixed (the warm-start stage of levenberg_marquardt)."""

    def __init__(self, problem: Problem, weight: np.ndarray):
        self.problem, self.weight = problem, weight
        self.mode, self.par = problem.mode, problem.par
        self.n_scored = getattr(problem, "n_scored", 0)

    def evaluate(self, theta: np.ndarray, derivatives: bool = True,
                 fixed_weight: np.ndarray | None = None) -> Evaluation:
        return self.problem.evaluate(theta, derivatives, fixed_weight=self.weight)

    def residual_series(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.problem.residual_series(theta)


def problem_n(problem: Problem) -> int:
    return int(getattr(problem, "n_scored"))


# ------------------------------------------------------------------------------------------
# The report's relaxation (Eq 2.17–2.21): kept for the documented comparison only
# ------------------------------------------------------------------------------------------
def relaxation_estimate(
    problem: Problem, theta0: np.ndarray, *, max_iterations: int = 50, step_tol: float = 1e-4,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The report's method: W = (1/N) Σ e eᵀ from the residuals (Eq 2.19) and Gauss–Newton
    with W held fixed (Eq 2.21), alternated to convergence. NOT the method of this project —
    with noisy load cells in the regressors it is biased (model §7, docs/identification.md).
    Returns (θ, claimed covariance M⁻¹, iterations)."""
    theta = np.asarray(theta0, float).copy()
    for it in range(1, max_iterations + 1):
        W = problem.evaluate(theta, derivatives=False).residual_sum / problem_n(problem)
        ev = problem.evaluate(theta, fixed_weight=W)
        assert ev.information is not None and ev.gradient is not None  # derivatives=True
        step = -np.linalg.solve(ev.information, ev.gradient)
        theta = theta + step
        sig = np.sqrt(np.diag(np.linalg.inv(ev.information)))
        if np.all(np.abs(step) < step_tol * sig):
            break
    W = problem.evaluate(theta, derivatives=False).residual_sum / problem_n(problem)
    ev = problem.evaluate(theta, fixed_weight=W)
    assert ev.information is not None  # derivatives=True
    return theta, np.linalg.inv(ev.information), it


# ------------------------------------------------------------------------------------------
# Conveniences
# ------------------------------------------------------------------------------------------
def identify_known_loads(
    model: RigModel,
    z: np.ndarray,
    T: np.ndarray,
    H: np.ndarray,
    *,
    prior_mean: np.ndarray,
    prior_cov: np.ndarray | None,
    moment_floor: float,
    names: Sequence[str] | None = None,
    alpha: np.ndarray | None = None,
    q: np.ndarray | None = None,
    scored: np.ndarray | None = None,
    max_iterations: int = 10,
    max_lag: int | None = None,
) -> IdentificationResult:
    """Known-load identification of ``names`` (default: the 14 angles) from one window."""
    par = Parameterisation(model, names, alpha, moment_floor=moment_floor, known_loads=True)
    prob = KnownLoadProblem(par, z, T, H, q, scored)
    return levenberg_marquardt(prob, prior_mean, prior_cov, max_iterations=max_iterations,
                               max_lag=max_lag)


# ------------------------------------------------------------------------------------------
# Filter-error mode: what the filter model predicts for its innovations, and a score
# covariance robust to content outside the model (docs/identification.md, "the information
# rule of filter-error runs")
# ------------------------------------------------------------------------------------------
def innovation_model(
    Phi: np.ndarray, K: np.ndarray, J: np.ndarray, Qd: np.ndarray, W: np.ndarray,
    content_sos: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, G, C, D, U): ξ' = A ξ + G u, e = C ξ + D u, u white with covariance U — the
    calibration filter's innovations as its own model predicts them: hub loads from the load model (x⁺ = Φ x + w, w ~ Q_d), the
    measurement noise white with covariance W(θ) and then passed through the causal content
    filter (the same filter on every channel, ``content_sos``; None: no filter), and the fixed
    gain K. Coloured by design — the content filter and a gain that is not the Riccati gain —
    so a plain whiteness or NIS test against B would reject or pass everything.

    In the filter's error coordinates ε = x − x⁻ (stationary: the hub-load states themselves
    are undamped oscillators) with the content-filter states c of the six noise channels,
    driven by u = [w, v]:  ε' = Φ(I − KJ) ε + w − ΦK (C_f c + D_f v),  c' = A_f c + B_f v,
    e = J ε + C_f c + D_f v. Stationary covariance by the discrete Lyapunov equation."""
    ns = Phi.shape[0]
    if content_sos is None:
        Af, Bf, Cf, Df = (np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                          np.ones((1, 1)))
    else:
        Af, Bf, Cf, Df = scipy.signal.tf2ss(*scipy.signal.sos2tf(np.asarray(content_sos)))
        Df = np.atleast_2d(Df)
    nf = Af.shape[0]
    I6 = np.eye(6)
    AF, BF, CF, DF = (np.kron(I6, Af), np.kron(I6, Bf), np.kron(I6, Cf), np.kron(I6, Df))
    n = ns + 6 * nf
    A = np.zeros((n, n))
    G = np.zeros((n, ns + 6))
    es, cs = slice(0, ns), slice(ns, n)
    PK = Phi @ K
    A[es, es] = Phi @ (np.eye(ns) - K @ J)
    A[es, cs] = -PK @ CF
    G[es, :ns] = np.eye(ns)
    G[es, ns:] = -PK @ DF
    A[cs, cs] = AF
    G[cs, ns:] = BF
    C = np.zeros((6, n))
    C[:, es] = J
    C[:, cs] = CF
    D = np.zeros((6, ns + 6))
    D[:, ns:] = DF
    U = scipy.linalg.block_diag(Qd, W)
    return A, G, C, D, U


def innovation_autocovariance(
    Phi: np.ndarray, K: np.ndarray, J: np.ndarray, Qd: np.ndarray, W: np.ndarray,
    content_sos: np.ndarray | None, max_lag: int,
) -> np.ndarray:
    """Γ(k) = E[e_{n+k} e_nᵀ], k = 0 … max_lag, of the calibration filter's innovations as its
    own model predicts them (:func:`innovation_model`)."""
    A, G, C, D, U = innovation_model(Phi, K, J, Qd, W, content_sos)
    Sigma = scipy.linalg.solve_discrete_lyapunov(A, G @ U @ G.T)
    out = np.empty((max_lag + 1, 6, 6))
    out[0] = C @ Sigma @ C.T + D @ U @ D.T
    X = A @ Sigma @ C.T + G @ U @ D.T  # E[ξ_{n+1} e_nᵀ]
    for k in range(1, max_lag + 1):
        out[k] = C @ X
        X = A @ X
    out[0] = 0.5 * (out[0] + out[0].T)
    return out


@dataclass
class InnovationTest:
    """The outcome of :func:`innovation_spectrum_test`: the statistic, its mean under the
    model, its limit at the false-alarm rate, and whether it passed (one-sided: only excess
    innovation — content the model does not predict — fails)."""

    statistic: float
    mean: float
    limit: float
    passed: bool


def score_covariance_hac(e: np.ndarray, de: np.ndarray, weight: np.ndarray,
                         max_lag: int) -> np.ndarray:
    """Robust (sandwich) covariance of the score Σ sₙ, sₙ = (∂eₙ/∂θ)ᵀ B⁻¹ eₙ, from the
    window's own score series: Newey–West (Bartlett weights up to ``max_lag``). Unlike M it
    does not assume the residuals are what the model says: residual content the load model
    does not describe (broadband loads, leakage of off-design harmonics) inflates it. Rows of
    ``e``/``de`` that are zero (unscored samples) contribute nothing."""
    Winv = np.linalg.inv(weight)
    s = np.einsum("nap,ab,nb->np", de, Winv, e)  # (N, p)
    N, p = s.shape
    L = int(min(max_lag, N - 1))
    M = scipy.fft.next_fast_len(N + L + 1, real=True)
    F = np.fft.rfft(s, n=M, axis=0)
    cross = np.fft.irfft(np.conj(F)[:, :, None] * F[:, None, :], n=M, axis=0)[: L + 1]
    w = 1.0 - np.arange(L + 1) / (L + 1.0)
    Q = cross[0] + np.einsum("k,kab->ab", w[1:], cross[1:] + cross[1:].transpose(0, 2, 1))
    result: np.ndarray = 0.5 * (Q + Q.T)
    return result


def predicted_score_covariance(de: np.ndarray, weight: np.ndarray, gamma: np.ndarray
                               ) -> np.ndarray:
    """Covariance of the score Σ Dₙᵀ B⁻¹ eₙ when the innovations have the autocovariance Γ(k)
    the filter model predicts (k = 0 … len(gamma) − 1): Σ_i Σ_j D_iᵀ B⁻¹ Γ(j − i) B⁻¹ D_j,
    exactly, by FFT (zero-padded, as :func:`coloured_residual_information`). Under the model
    this is the true variance of the score — M assumes white innovations of covariance B,
    which the content filter and the narrow-band hub-load states make far from true."""
    N = de.shape[0]
    L = int(min(len(gamma) - 1, N - 1))
    return _score_quadratic(gamma, np.linalg.inv(weight) @ de, L)


SPECTRUM_SEGMENT = 256  # samples per Welch segment of the innovation spectrum test (1.3 s)
SPECTRUM_FLOOR = 1e-3  # bins whose predicted power is below this fraction of the peak: not tested


def expected_welch_spectrum(gamma: np.ndarray, segment: int = SPECTRUM_SEGMENT) -> np.ndarray:
    """E_j (F, 6, 6) = Σ_{|τ|<L} Γ(τ) c(τ) e^{−iω_j τ}: the expectation of the Hann-window
    Welch estimate of a process with autocovariance Γ (leakage included), L = ``segment``."""
    L = int(segment)
    w = np.hanning(L)
    c = np.correlate(w, w, "full")[L - 1:] / float(w @ w)  # c(τ), τ = 0 … L − 1
    G = (gamma[:L] * c[:, None, None]).reshape(L, 36)
    Gt = gamma[1:L].transpose(0, 2, 1) * c[1:, None, None]
    F = L // 2 + 1
    ph = np.exp(-2j * np.pi * np.outer(np.arange(F), np.arange(L)) / L)  # (F, L)
    result: np.ndarray = (ph @ G + ph[:, 1:].conj() @ Gt.reshape(L - 1, 36)).reshape(F, 6, 6)
    return result


def innovation_spectrum_test(e: np.ndarray, scored: np.ndarray, gamma: np.ndarray | None,
                             false_alarm: float = 1e-3, segment: int = SPECTRUM_SEGMENT, *,
                             expected: np.ndarray | None = None) -> InnovationTest:
    """The window's innovations against the spectrum the filter model predicts, bin by bin.

    Welch estimate Ŝ_j (Hann, 50 % overlap) of the longest run of scored samples; its
    expectation under the model E_j = Σ_{|τ|<L} Γ(τ) c(τ) e^{−iω_j τ} (c: the window's
    normalised autocorrelation, so leakage is predicted exactly); t_j = tr(E_j⁻¹ Ŝ_j)/6, mean 1.
    Under the model 12 K t_j is about χ²_{12K} (K segments); the limit is its
    1 − false_alarm/bins point (Bonferroni over the bins tested). The statistic is max_j t_j:
    load content the model does not describe (broadband hub loads, a harmonic off its design
    frequency, a neglected angular inertia) shows as excess power in some bins, which a lag-0
    test against a loose hub-load model cannot see. The false-alarm rate is checked by Monte
    Carlo on the model itself (tests/test_identification.py)."""
    from scipy.stats import chi2 as _chi2

    scored = np.asarray(scored, bool)
    flips = np.flatnonzero(np.diff(np.concatenate([[0], scored.astype(np.int8), [0]])))
    runs = list(zip(flips[0::2], flips[1::2]))
    L = int(segment)
    if not runs:
        return InnovationTest(0.0, 1.0, np.inf, True)
    a, b = max(runs, key=lambda r: r[1] - r[0])
    x = np.asarray(e[a:b], float)
    step = L // 2
    starts = range(0, len(x) - L + 1, step)
    K = len(starts)
    if K < 2 or (expected is None and gamma is not None and len(gamma) < L):
        return InnovationTest(0.0, 1.0, np.inf, True)
    w = np.hanning(L)
    w2 = float(w @ w)
    X = np.fft.rfft(np.stack([w[:, None] * x[s:s + L] for s in starts]), axis=1)  # (K, F, 6)
    S = np.einsum("kfa,kfb->fab", X, X.conj()) / (K * w2)
    if expected is None:
        assert gamma is not None, "innovation_spectrum_test needs gamma or expected"
        E = expected_welch_spectrum(gamma, L)
    else:
        E = expected
    tr = np.real(np.einsum("faa->f", E))
    keep = tr >= SPECTRUM_FLOOR * tr.max()
    t = np.real(np.einsum("faa->f", np.linalg.solve(E[keep], S[keep]))) / 6.0
    nb = int(keep.sum())
    limit = float(_chi2.isf(false_alarm / nb, 12 * K) / (12 * K))
    q = float(t.max())
    return InnovationTest(q, 1.0, limit, bool(q <= limit))
