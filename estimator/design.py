"""Experiment design for known-load calibration: which static load condition to apply next
(docs/identification.md, "The next load conditions").

Pure numerics, no I/O. The rule is D-optimal and greedy: of a set of candidate hub-load
conditions, the next one is the one whose expected Fisher information most increases the
log-determinant of each structure's current information, summed over the structures; the
condition after it is chosen the same way with the first one's information added, and so on.
For a Gaussian posterior ``½ [log det(M₀ + M_c) − log det(M₀)] = ½ log det(I + P₀ M_c)`` is
the expected information gain (mutual information, in nats) of the condition about the
structure's parameters: the reduction of the posterior entropy, i.e. of ½ log det P.

The interface (what a structure must provide)
---------------------------------------------
A structure is a :class:`Structure`:

* ``name`` — e.g. ``"constant"``, ``"cell_gain"``;
* ``information(H) -> M`` — the **information function**: ``H`` is an array (k, 6) of
  candidate static hub loads ``[X, Y, Z, L, M, N]`` (N, N·m, body axes at the hub centre,
  the axes of the reference balance), ``M`` an array (k, p, p): the Fisher information about
  the structure's p parameters that holding each condition for the stated number of scored
  samples adds (Gauss–Newton, ``Σ ∂eᵀ/∂θ W⁻¹ ∂e/∂θ``, evaluated at the current estimate);
* ``M0`` — (p, p) the information already held: the posterior's ``P⁻¹`` (prior included).

Any parameterisation can plug in: a structure test that proposes a hub-position error,
a balance scale, an external load, … only has to give such a function and its current
information. Two are built here: :func:`constant_angle_structure` (the 14 constant angles —
or any :class:`~estimator.identification.Parameterisation`: the information of a condition
follows from its ``Terms``, so attach points, hub centre and masses work too) and
:func:`cell_gain_structure` (angles plus per-cell load gains: each angle of cell i moves
by κ_j·T_i with the cell's own load T_i, 14 + 14 parameters — the "compliance-like gain per
cell" the structure test names ``cell_load_angles``, which a thrust held near one level
cannot separate from the constant angles).

What a condition does to the cells
----------------------------------
A candidate is a static hub load; the cells carry ``S(α) T = I_rest − R₀ H`` (I_rest the
inertial loads at rest, gravity only), split among the seven cells by minimum strain energy
with the configured cell stiffnesses (``T = K Sᵀ (S K Sᵀ)⁻¹ w``, the simulator's split).
Candidates whose cell loads exceed a cell's full scale, or whose hub load exceeds the
balance's full scale, are not candidates (:func:`feasible`).
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .balance import inertial_load_matrix, measurement_covariance
from .geometry import hub_transfer_matrix, wrench_matrix, wrench_matrix_jacobian
from .identification import Parameterisation
from .params import RigModel

AXES = ("X", "Y", "Z", "L", "M", "N")
STANDARD_GRAVITY = 9.80665  # m/s², the accelerometers read −g on z at rest (level)
DEFAULT_COUNT = 3  # next conditions recommended
# the grid of candidates: each axis at these fractions of its limit (thrust finer: it is
# the load the cells carry most of, and what separates a load gain from a constant angle)
GRID_LEVELS = (-1.0, 0.0, 1.0)
THRUST_LEVELS = (-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5)
# prior σ of a per-cell load gain: 1° per 100 kN of the cell's own load (the simulator's
# linear-angle mode is 1° per 100 kN of thrust)
CELL_GAIN_PRIOR_RAD_PER_N = math.radians(1.0) / 1.0e5

InformationFunction = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Structure:
    """One competing model structure: its parameters, information function and the
    information already held (see the module docstring)."""

    name: str
    names: tuple[str, ...]
    information: InformationFunction
    M0: np.ndarray


@dataclass(frozen=True)
class Recommendation:
    """One recommended condition: the hub load and its expected information gain (nats),
    total and per structure, given the conditions recommended before it."""

    H: np.ndarray  # (6,) N, N·m
    information_gain: float
    by_structure: dict[str, float]

    def to_dict(self) -> dict[str, object]:
        return {"H": [float(x) for x in self.H], "information_gain": float(self.information_gain),
                "by_structure": {k: float(v) for k, v in self.by_structure.items()}}


# ------------------------------------------------------------------ conditions → cell loads
def rest_inertial_loads(model: RigModel) -> np.ndarray:
    """I at rest and level (6,): the accelerometers read specific force (0, 0, −g)."""
    K = model.accelerometers.positions.shape[0]
    f = np.tile([0.0, 0.0, -STANDARD_GRAVITY], K)
    result: np.ndarray = inertial_load_matrix(model) @ f
    return result


def cell_loads(model: RigModel, alpha: np.ndarray, H: np.ndarray,
               stiffness: np.ndarray | None = None) -> np.ndarray:
    """The cell loads T (k, 7) that static hub loads H (k, 6) produce at angles ``alpha``:
    the minimum-strain-energy split of ``I_rest − R₀ H`` (stiffness per cell, default equal)."""
    H = np.atleast_2d(np.asarray(H, float))
    S = wrench_matrix(model.geometry, alpha)
    R0 = hub_transfer_matrix(model.geometry, "body")
    k = np.ones(S.shape[1]) if stiffness is None else np.asarray(stiffness, float)
    Kd = np.diag(k)
    split = Kd @ S.T @ np.linalg.inv(S @ Kd @ S.T)  # (7, 6)
    w = rest_inertial_loads(model)[None, :] - H @ R0.T
    result: np.ndarray = w @ split.T
    return result


def feasible(model: RigModel, alpha: np.ndarray, H: np.ndarray, *, cell_full_scale: np.ndarray,
             force_limit: float, moment_limit: float,
             stiffness: np.ndarray | None = None) -> np.ndarray:
    """Mask (k,) of the conditions within the balance's and every cell's full scale."""
    H = np.atleast_2d(np.asarray(H, float))
    T = cell_loads(model, alpha, H, stiffness)
    ok: np.ndarray = np.all(np.abs(T) <= np.asarray(cell_full_scale, float)[None, :], axis=1)
    ok &= np.all(np.abs(H[:, :3]) <= force_limit, axis=1)
    ok &= np.all(np.abs(H[:, 3:]) <= moment_limit, axis=1)
    return ok


def candidate_grid(limits: Sequence[float], levels: Sequence[float] = GRID_LEVELS,
                   thrust_levels: Sequence[float] = THRUST_LEVELS) -> np.ndarray:
    """Every combination of ``levels`` × limit on X, Y, L, M, N and ``thrust_levels`` × limit
    on Z (negative Z is thrust, z down): (k, 6)."""
    lim = np.asarray(limits, float)
    if lim.shape != (6,) or not np.all(np.isfinite(lim)) or np.any(lim < 0):
        raise ValueError(f"limits must be six non-negative numbers, got {limits!r}")
    axes = [np.asarray(thrust_levels if j == 2 else levels, float) * lim[j] for j in range(6)]
    return np.unique(np.array(list(itertools.product(*axes)), float), axis=0)


# ------------------------------------------------------------------ information functions
def _gauss_newton(D: np.ndarray, Winv: np.ndarray, n: float) -> np.ndarray:
    """n · Dᵀ W⁻¹ D for D (k, 6, p) → (k, p, p)."""
    result: np.ndarray = n * np.einsum("kip,ij,kjq->kpq", D, Winv, D)
    return result


def parameterisation_information(par: Parameterisation, theta: np.ndarray, n_samples: float,
                                 stiffness: np.ndarray | None = None) -> InformationFunction:
    """The information function of any known-load parameterisation at θ: a condition H held
    for ``n_samples`` scored samples, with the cell loads of the static split and the rest
    inertial loads, gives ``n · Σ (dA x)ᵀ W⁻¹ (dA x)`` (the Gauss–Newton information the
    identification reports for such data)."""
    if not par.known_loads:
        raise ValueError("the design rule is for known-load parameterisations")
    terms = par.terms(np.asarray(theta, float))
    Winv = np.linalg.inv(terms.W)
    model = par.model
    alpha = par.alpha(theta)
    I_rest = rest_inertial_loads(model)
    Q = model.external.wrenches.shape[1]

    def info(H: np.ndarray) -> np.ndarray:
        H = np.atleast_2d(np.asarray(H, float))
        T = cell_loads(model, alpha, H, stiffness)
        z = np.broadcast_to(I_rest, (len(H), 6))
        x = par.stack(z, T, H, np.zeros((len(H), Q)) if Q else None)  # (k, ncol)
        D = np.einsum("pic,kc->kip", terms.dA, x)  # (k, 6, p)
        return _gauss_newton(D, Winv, n_samples)

    return info


def constant_angle_structure(model: RigModel, alpha: np.ndarray, P: np.ndarray,
                             n_samples: float, *, moment_floor: float,
                             stiffness: np.ndarray | None = None,
                             names: Sequence[str] | None = None) -> Structure:
    """The constant-angle model (or any parameter subset ``names``) with posterior
    covariance ``P``; ``alpha`` the 14 angles at the current estimate."""
    par = Parameterisation(model, names, alpha, moment_floor=moment_floor, known_loads=True)
    theta = par.initial()
    return Structure("constant", par.names,
                     parameterisation_information(par, theta, n_samples, stiffness),
                     np.linalg.inv(np.asarray(P, float)))


def cell_gain_jacobian(model: RigModel, alpha: np.ndarray, T: np.ndarray) -> np.ndarray:
    """∂e/∂[α, κ] (k, 6, 28) of the known-load residual e = z − S(α + κ∘T_cell) T − R₀ H at
    κ = 0: an angle's column is −(∂S/∂α_j) T, its gain's the same times its cell's load."""
    dS = wrench_matrix_jacobian(model.geometry, alpha)  # (14, 6, 7)
    T = np.atleast_2d(np.asarray(T, float))
    Da = -np.einsum("jic,kc->kij", dS, T)  # (k, 6, 14)
    cell_of = np.repeat(np.arange(model.geometry.n_cells), 2)  # angle j belongs to cell j // 2
    Dk = Da * T[:, cell_of][:, None, :]
    return np.concatenate([Da, Dk], axis=2)


def cell_gain_names(model: RigModel) -> tuple[str, ...]:
    """The 28 parameters of the per-cell load-gain structure: the 14 angles, then
    ``k_<angle>`` (rad per N of the cell's own load)."""
    a = model.geometry.angle_names
    return tuple(a) + tuple(f"k_{n}" for n in a)


def cell_gain_structure(model: RigModel, alpha: np.ndarray, M0: np.ndarray, n_samples: float,
                        *, moment_floor: float, stiffness: np.ndarray | None = None
                        ) -> Structure:
    """Angles plus per-cell load gains (28 parameters, :func:`cell_gain_names`), with the
    information ``M0`` (28, 28) already held (:func:`cell_gain_prior` plus the conditions
    seen, :class:`ConditionTracker`)."""
    W = measurement_covariance(model, alpha, moment_floor, known_loads=True)
    Winv = np.linalg.inv(W)

    def info(H: np.ndarray) -> np.ndarray:
        T = cell_loads(model, alpha, H, stiffness)
        return _gauss_newton(cell_gain_jacobian(model, alpha, T), Winv, n_samples)

    return Structure("cell_gain", cell_gain_names(model), info, np.asarray(M0, float))


def cell_gain_prior(angle_sigma: float | np.ndarray, n_angles: int = 14,
                    gain_sigma: float = CELL_GAIN_PRIOR_RAD_PER_N) -> np.ndarray:
    """Prior information (28, 28) of the load-gain structure: diag(σ_α⁻², σ_κ⁻²)."""
    sa = np.broadcast_to(np.asarray(angle_sigma, float), (n_angles,))
    return np.diag(np.concatenate([sa ** -2.0, np.full(n_angles, gain_sigma ** -2.0)]))


# ------------------------------------------------------------------ the design rule
def _logdet(M: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(M)
    return np.where(sign > 0, ld, -np.inf)


def information_gains(structures: Sequence[Structure], candidates: np.ndarray,
                      M_now: Sequence[np.ndarray] | None = None,
                      infos: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """(k, s): ½ [log det(M_s + M_s(c)) − log det(M_s)] for every candidate and structure."""
    cand = np.atleast_2d(np.asarray(candidates, float))
    M_now = [s.M0 for s in structures] if M_now is None else M_now
    out = np.empty((len(cand), len(structures)))
    for j, (s, M) in enumerate(zip(structures, M_now)):
        Mc = s.information(cand) if infos is None else infos[j]
        out[:, j] = 0.5 * (_logdet(M[None] + Mc) - _logdet(M)[()])
    return out


def next_conditions(structures: Sequence[Structure], candidates: np.ndarray,
                    count: int = DEFAULT_COUNT, weights: Sequence[float] | None = None
                    ) -> list[Recommendation]:
    """The greedy D-optimal sequence of ``count`` conditions from ``candidates`` (k, 6): each
    maximises Σ_s w_s · ½ Δ log det of structure s given the ones before it (a condition may
    recur: holding it again still adds information). Pure: the structures are not changed."""
    if not structures:
        raise ValueError("next_conditions needs at least one structure")
    cand = np.atleast_2d(np.asarray(candidates, float))
    if cand.ndim != 2 or cand.shape[1] != 6 or not len(cand):
        raise ValueError(f"candidates must be a non-empty (k, 6) array, got {cand.shape}")
    w = np.ones(len(structures)) if weights is None else np.asarray(weights, float)
    infos = [s.information(cand) for s in structures]
    M_now = [np.array(s.M0, float) for s in structures]
    out = []
    for _ in range(int(count)):
        g = information_gains(structures, cand, M_now, infos)
        score = g @ w
        best = int(np.argmax(np.where(np.isfinite(score), score, -np.inf)))
        out.append(Recommendation(cand[best].copy(), float(score[best]),
                                  {s.name: float(g[best, j]) for j, s in enumerate(structures)}))
        M_now = [M + info[best] for M, info in zip(M_now, infos)]
    return out


def greedy_order(structures: Sequence[Structure], conditions: np.ndarray,
                 weights: Sequence[float] | None = None) -> list[int]:
    """The order in which to apply a given set of conditions (each once): at every step the
    remaining condition with the largest weighted information gain."""
    cond = np.atleast_2d(np.asarray(conditions, float))
    w = np.ones(len(structures)) if weights is None else np.asarray(weights, float)
    infos = [s.information(cond) for s in structures]
    M_now = [np.array(s.M0, float) for s in structures]
    left = list(range(len(cond)))
    order = []
    while left:
        g = information_gains(structures, cond[left], M_now, [i[left] for i in infos]) @ w
        k = left[int(np.argmax(np.where(np.isfinite(g), g, -np.inf)))]
        order.append(k)
        left.remove(k)
        M_now = [M + info[k] for M, info in zip(M_now, infos)]
    return order


def log_det_covariance_path(structure: Structure, conditions: np.ndarray,
                            order: Sequence[int]) -> np.ndarray:
    """log det P after each condition of ``order`` (P = M⁻¹), starting from M0: (len+1,)."""
    cond = np.atleast_2d(np.asarray(conditions, float))
    infos = structure.information(cond)
    M = np.array(structure.M0, float)
    path = [-float(_logdet(M))]
    for k in order:
        M = M + infos[k]
        path.append(-float(_logdet(M)))
    return np.array(path)


class ConditionTracker:
    """The load conditions seen so far, as information of the load-gain structure
    (bounded: one 28×28 sum). Each known-load window adds its scored samples at its mean
    cell loads — a static-content window is one condition held (or a ramp's mean)."""

    def __init__(self, model: RigModel, angle_sigma: float, *, moment_floor: float,
                 gain_sigma: float = CELL_GAIN_PRIOR_RAD_PER_N) -> None:
        self.model = model
        self.moment_floor = float(moment_floor)
        self.M = cell_gain_prior(angle_sigma, len(model.geometry.angle_names), gain_sigma)
        self.windows = 0

    def add_window(self, alpha: np.ndarray, T: np.ndarray, n_scored: int) -> None:
        """A window of cell loads T (N, 7) (content-filtered), ``n_scored`` samples used."""
        T = np.asarray(T, float)
        if not n_scored or not len(T) or not np.all(np.isfinite(T)):
            return
        W = measurement_covariance(self.model, alpha, self.moment_floor, known_loads=True)
        D = cell_gain_jacobian(self.model, alpha, T.mean(axis=0))
        self.M = self.M + _gauss_newton(D, np.linalg.inv(W), float(n_scored))[0]
        self.windows += 1
