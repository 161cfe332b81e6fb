"""When the angles are not constant: competing structures of the known-load model and a
sequential test of the constant-angle model against them (issue 19; docs/identification.md,
"When the angles are not constant: the structure test").

The known-load balance is ``z = S(α) T + R₀ H (+ E q)``; its residual at the constant-angle
model is ``r = z − S(α) T − R₀ H − E q``. Each competing structure adds a term that is zero at
β = 0 and predicts, for the same measured (z, T, H), a model ``m(α, β; T, H)``:

* ``cell_load_angles`` — every angle moves with the load its own cell carries,
  ``α_k = α0_k + g_k T_c(k)`` (14 gains, rad/N: a compliance-like gain per angle; the rigid-body
  model has no link length, so this is what a deflecting transmission can be identified as);
* ``hub_position`` — the hub centre is off by δp (3, m): ``R(p_H + δp)``;
* ``balance`` — the reference balance has per-axis scale errors s (6) and an alignment error φ
  (3, rad): the true hub load is ``[(I + skew φ)(1 + s_F)∘F_b; (I + skew φ)(1 + s_M)∘M_b]``;
* ``external_load`` — an unmodelled load path: a CG wrench linear in the applied hub forces,
  ``U F`` (6×3, N or N·m per N; the report's Phase I roll torque ∝ Y and x-force ∝ X).

**The interface for the experiment design** (another module chooses the next load conditions):
everything the structures are is in three pure functions of (model, α, mean data), no state:
:func:`parameter_names` (names and units), :func:`angle_jacobian` (``∂m/∂α``, 6×14 for one
condition) and :func:`structure_jacobian` (``∂m/∂β`` at β = 0, 6×p for one condition, given
the condition's mean ``x̄ = [z, T, H, q]``; T can be predicted for a planned condition by the
minimum-strain-energy split). The information of a design about (α, β) is
``Σ_c n_c [J_α J_β]ᵀ W⁻¹ [J_α J_β]`` over its conditions; :func:`design_ranks` gives, per
structure, the rank of β left after the angles (the testable directions) and which structures
a design cannot separate.

The test (:class:`StructureTest`): static known-load windows are summarised by their means; a
window of n scored samples has a mean residual of covariance W(α)/n (W the effective-variance
weight of model §7; the static content filter has unit gain at DC). Windows at the same load
(within ``cluster_tolerance``) are pooled: every structure predicts the same residual at the
same load, so pooling loses nothing. At every look (every known-load window):

1. *a change in time* — the new window's mean residual against its cluster's earlier windows
   (χ²₆; the same load, so the difference does not depend on any structure): significant at
   ``time_level`` (10⁻³ per window) restarts the accumulation from this window (a step in the
   angles, bench A4, is a change in time, not a load dependence);
2. the constant-angle model is fitted to the cluster means (Gauss–Newton on the 14 angles,
   pseudo-inverse: directions the design does not determine stay where they are);
3. for each structure s, its whitened Jacobian is projected off the angles' span; the rank
   r_s of what is left (singular values above ``RANK_TOLERANCE`` of the largest) is the
   number of testable directions. The likelihood-ratio statistic of the linearised model,
   ``q_s = ‖U_sᵀ ê‖²`` (ê the whitened residual of the constant fit, U_s the left singular
   vectors kept), is χ²_{r_s} under constant angles;
4. the constant model is rejected at look k when some ``q_s > χ²_{r_s}(1 − a_k/S)``, with the
   alpha-spending rule ``a_k = A · 6/(π² k²)`` (Σ a_k = A = 10⁻³ over any number of looks;
   Bonferroni over the S structures): the false-alarm rate of saying ``not_constant`` at any
   time of the run is at most A, whatever the dependence between looks. Once rejected, the
   verdict stays ``not_constant`` until a change in time restarts the accumulation.

Candidates are ranked: those whose remaining misfit passes at the same level ("explains the
data") first, then by the p-value of q_s (a smaller structure that explains as much ranks
before a larger one that contains it). Each carries the fitted parameters, their σ, the same
per kN of load, and the statistic. The estimate and the misfit come from the joint fit of
[α0, β] (:func:`fit_structure`: Levenberg–Marquardt with the analytic Jacobian, in the
directions the conditions determine only — the others stay at the prior and are reported as
not determined). A structure is *selected* for the hub loads (``StructureVerdict.selected``)
only when it explains the data, is determined, its fit converged and determines the hub loads
(:func:`hub_sigma`), and every other explaining structure contains it by construction
(``NESTED``) or is tested and fits worse; :class:`StructureCorrection` is that structure in
the form the per-sample hub-load path applies.

Pure numerics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.optimize import brentq, least_squares, minimize_scalar
from scipy.stats import chi2, norm

from .balance import measurement_covariance
from .geometry import (
    _E,
    angle_axes,
    cross3,
    hub_transfer_matrix,
    rot_cells,
    skew,
    wrench_matrix,
    wrench_matrix_jacobian,
)
from .params import RigModel

STRUCTURES = ("cell_load_angles", "hub_position", "balance", "external_load")
VERDICTS = ("constant", "not_constant", "undetermined", "drifting")
DRIFTING = "drifting"  # the time-varying candidate (DriftTest, issue 27)
MAX_DRIFT_WINDOWS = 96  # the drift test's history: 8 min of 5-s windows (bounded)
# the drift the data cannot exclude (docs/identification.md, "Angles that drift"):
# the rates' prior scale s at this one-sided upper confidence level of its likelihood
DRIFT_BOUND_LEVEL = 0.8413  # Φ(1): one standard error above the ML estimate
MAX_HELD_LOOKS = 16  # bounded fits kept (≥ the posterior's held windows, 12)
# (smaller, larger): the larger structure contains the smaller one whatever the conditions
# (δp × F is an external load U F)
NESTED = frozenset({("hub_position", "external_load")})
AXES = ("X", "Y", "Z", "L", "M", "N")
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
    g = model.geometry
    if structure == "cell_load_angles":
        return tuple(f"g_{a}" for a in g.angle_names)
    if structure == "hub_position":
        return ("hub_dx", "hub_dy", "hub_dz")
    if structure == "balance":
        return tuple(f"scale_{a}" for a in AXES) + ("align_x", "align_y", "align_z")
    if structure == "external_load":
        return tuple(f"ext_{r}_per_{c}" for r in AXES for c in AXES[:3])
    raise ValueError(f"unknown structure {structure!r}; choose from {STRUCTURES}")


def parameter_units(structure: str, model: RigModel) -> tuple[str, ...]:
    """Unit of each parameter per kN of load (the ``per_kN`` of a candidate)."""
    names = parameter_names(structure, model)
    if structure == "cell_load_angles":
        return ("deg/kN",) * len(names)  # angle change per kN on its own cell
    if structure == "hub_position":
        return ("N·m/kN",) * 3  # moment error per kN of hub force (= mm of hub offset)
    if structure == "balance":
        return ("N/kN",) * 3 + ("N·m/kN",) * 3 + ("N/kN",) * 3  # error per kN (N·m) read
    return tuple("N/kN" if n.split("_")[1] in "XYZ" else "N·m/kN" for n in names)


def per_kN(structure: str, beta: np.ndarray) -> np.ndarray:
    """β expressed per kN of load in :func:`parameter_units` (deg/kN for angle gains)."""
    beta = np.asarray(beta, float)
    if structure == "cell_load_angles":
        result: np.ndarray = np.degrees(beta) * 1e3
        return result
    return beta * 1e3


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
    g = model.geometry
    z, T, H, q = _split(model, xbar)
    beta = np.asarray(beta, float)
    R0 = hub_transfer_matrix(g, "body")
    if structure == "cell_load_angles":
        a = np.asarray(alpha, float) + beta * T[np.arange(2 * g.n_cells) // 2]
        m = wrench_matrix(g, a) @ T + R0 @ H
    elif structure == "balance":
        Rp = np.eye(3) + skew(beta[6:9])
        Ht = np.concatenate([Rp @ ((1 + beta[:3]) * H[:3]), Rp @ ((1 + beta[3:6]) * H[3:])])
        m = wrench_matrix(g, alpha) @ T + R0 @ Ht
    else:
        m = wrench_matrix(g, alpha) @ T + structure_matrices(structure, beta, model)["R"] @ H
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
    g = model.geometry
    z, T, H, q = _split(model, xbar)
    F, Mo = H[:3], H[3:]
    if structure == "cell_load_angles":
        dS = wrench_matrix_jacobian(g, alpha)
        cell = np.arange(2 * g.n_cells) // 2
        # α_k = α0_k + g_k T_c(k): ∂(S T)/∂g_k = ∂S/∂α_k[:, c] T_c · T_c
        return np.stack([dS[k, :, cell[k]] * T[cell[k]] ** 2 for k in range(2 * g.n_cells)],
                        axis=1)
    if structure == "hub_position":
        J = np.zeros((6, 3))
        J[3:] = -skew(F)  # δp × F
        return J
    if structure == "balance":
        R0 = hub_transfer_matrix(g, "body")
        D = np.zeros((6, 9))
        D[:, :6] = np.diag(H)  # scale: (1 + s) ∘ H
        D[:3, 6:] = -skew(F)  # alignment: φ × F, φ × M
        D[3:, 6:] = -skew(Mo)
        return R0 @ D
    if structure == "external_load":
        return np.kron(np.eye(6), F[None, :])  # U F, U row-major (6×3)
    raise ValueError(f"unknown structure {structure!r}; choose from {STRUCTURES}")


def structure_matrices(structure: str, beta: np.ndarray, model: RigModel
                       ) -> dict[str, np.ndarray]:
    """The exact (not linearised) model pieces of a structure at β, for hub loads."""
    g = model.geometry
    beta = np.asarray(beta, float)
    R0 = hub_transfer_matrix(g, "body")
    out: dict[str, np.ndarray] = {"R": R0}
    if structure == "hub_position":
        R = R0.copy()
        R[3:, :3] = skew(g.hub_position + beta)
        out["R"] = R
    elif structure == "external_load":
        R = R0.copy()
        R[:, :3] += beta.reshape(6, 3)
        out["R"] = R
    elif structure == "cell_load_angles":
        out["gain"] = beta
    return out


def hub_loads(structure: str | None, model: RigModel, alpha: np.ndarray, beta: np.ndarray | None,
              z: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The static estimate Ĥ (N, 6, body axes) under a structure: ``R(β)⁻¹ (z − S(α(T)) T)``.
    ``None`` or ``"constant"``: the constant-angle model. A balance error changes only the
    reference, not the estimate (its α0 is what the estimator uses)."""
    z, T = np.atleast_2d(np.asarray(z, float)), np.atleast_2d(np.asarray(T, float))
    g = model.geometry
    alpha = np.asarray(alpha, float)
    if structure in (None, "constant", "balance"):
        S = wrench_matrix(g, alpha)
        return np.linalg.solve(hub_transfer_matrix(g, "body"), (z - T @ S.T).T).T
    assert beta is not None  # a structure other than constant has parameters
    m = structure_matrices(structure, beta, model)
    if structure == "cell_load_angles":
        cell = np.arange(2 * g.n_cells) // 2
        out = np.empty_like(z)
        for n in range(len(z)):
            S = wrench_matrix(g, alpha + m["gain"] * T[n, cell])
            out[n] = z[n] - S @ T[n]
        return np.linalg.solve(m["R"], out.T).T
    S = wrench_matrix(g, alpha)
    return np.linalg.solve(m["R"], (z - T @ S.T).T).T


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
    C = len(X)
    F, Mo = H[:, :3], H[:, 3:]

    def skews(v: np.ndarray) -> np.ndarray:  # (C, 3, 3): −skew(v) · x = x × v … the batched skew(v)
        o = np.zeros((len(v), 3, 3))
        o[:, 0, 1], o[:, 0, 2], o[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
        o[:, 1, 0], o[:, 2, 0], o[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
        return o

    Js: dict[str, np.ndarray] = {}
    for st in structures:
        if st == "cell_load_angles":
            cell = np.arange(2 * n) // 2
            D = dS[np.arange(2 * n), :, cell]  # (14, 6)
            Js[st] = D.T[None, :, :] * (T[:, cell] ** 2)[:, None, :]
        elif st == "hub_position":
            J = np.zeros((C, 6, 3))
            J[:, 3:] = -skews(F)
            Js[st] = J
        elif st == "balance":
            D = np.zeros((C, 6, 9))
            D[:, np.arange(6), np.arange(6)] = H
            D[:, :3, 6:] = -skews(F)
            D[:, 3:, 6:] = -skews(Mo)
            Js[st] = np.einsum("ab,nbk->nak", R0, D)
        elif st == "external_load":
            J = np.zeros((C, 6, 18))
            for i in range(6):
                J[:, i, 3 * i:3 * i + 3] = F
            Js[st] = J
        else:
            raise ValueError(f"unknown structure {st!r}; choose from {STRUCTURES}")
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
    R0 = hub_transfer_matrix(g, "body")
    if st == "cell_load_angles":
        cell = np.arange(2 * n) // 2
        Sc, _ = _cell_columns(model, alpha[None, :] + beta[None, :] * T[:, cell])
        m = np.einsum("nac,nc->na", Sc, T) + H @ R0.T
    elif st == "balance":
        Rp = np.eye(3) + skew(beta[6:9])
        Ht = np.hstack([(H[:, :3] * (1 + beta[:3])) @ Rp.T, (H[:, 3:] * (1 + beta[3:6])) @ Rp.T])
        m = T @ wrench_matrix(g, alpha).T + Ht @ R0.T
    else:
        m = T @ wrench_matrix(g, alpha).T + H @ structure_matrices(st, beta, model)["R"].T
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


def _cell_columns(model: RigModel, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For angle sets A (C, 14): the columns of S (C, 6, 7) and the derivative of each
    angle's own column (C, 14, 6) — geometry.wrench_matrix and wrench_matrix_jacobian for C
    angle sets at once (every cell at once: the Monte Carlo tests call this ~10⁴ times)."""
    g = model.geometry
    C, n = len(A), g.n_cells
    first, second = angle_axes(g)
    R1, R2 = rot_cells(first, A[:, 0::2]), rot_cells(second, A[:, 1::2])
    v1 = np.einsum("ncab,cb->nca", R1, np.asarray(g.cell_axes, float))  # (C, n, 3)
    u = np.einsum("ncab,ncb->nca", R2, v1)
    E1 = np.array([_E[ax] for ax in first])[None]
    E2 = np.array([_E[ax] for ax in second])[None]
    du = np.empty((C, 2 * n, 3))
    du[:, 0::2] = np.einsum("ncab,ncb->nca", R2, cross3(E1, v1))
    du[:, 1::2] = cross3(E2, u)
    pos = np.asarray(g.cell_positions, float)
    S = np.concatenate([u, cross3(pos[None], u)], axis=2).transpose(0, 2, 1)
    cell = np.arange(2 * n) // 2
    D = np.concatenate([du, cross3(pos[cell][None], du)], axis=2)
    return S, D


def _white_jacobian(st: str, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                    means: np.ndarray, counts: np.ndarray, Li: np.ndarray) -> np.ndarray:
    """∂/∂[α, β] of :func:`_white_residual` (6C, 14 + p), exact at (α, β)."""
    g = model.geometry
    n = g.n_cells
    X = np.atleast_2d(np.asarray(means, float))
    T, H = X[:, 6:6 + n], X[:, 6 + n:12 + n]
    C, na = len(X), 2 * n
    cell = np.arange(na) // 2
    beta = np.asarray(beta, float)
    if st == "cell_load_angles":  # every condition at its own angles α + β∘T_c
        _, D = _cell_columns(model, alpha[None, :] + beta[None, :] * T[:, cell])
        Ja = D.transpose(0, 2, 1) * T[:, cell][:, None, :]
        Jb = Ja * T[:, cell][:, None, :]
    else:
        Ja = np.einsum("kac,nc->nak", wrench_matrix_jacobian(g, alpha), T)
        F, Mo = H[:, :3], H[:, 3:]
        if st == "hub_position":
            Jb = np.zeros((C, 6, 3))
            Jb[:, 3:] = -np.stack([skew(f) for f in F])
        elif st == "external_load":
            Jb = np.zeros((C, 6, 18))
            for i in range(6):
                Jb[:, i, 3 * i:3 * i + 3] = F
        elif st == "balance":
            R0 = hub_transfer_matrix(g, "body")
            Rp = np.eye(3) + skew(beta[6:9])
            D = np.zeros((C, 6, 9))
            D[:, :3, :3] = Rp[None] * F[:, None, :]
            D[:, 3:, 3:6] = Rp[None] * Mo[:, None, :]
            D[:, :3, 6:] = -np.stack([skew(f) for f in F * (1 + beta[:3])])
            D[:, 3:, 6:] = -np.stack([skew(m) for m in Mo * (1 + beta[3:6])])
            Jb = np.einsum("ab,nbk->nak", R0, D)
        else:
            raise ValueError(f"unknown structure {st!r}; choose from {STRUCTURES}")
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
                    structures: Sequence[str] = STRUCTURES, joint: bool | None = True,
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
                 structures: Sequence[str] = STRUCTURES) -> dict[str, Any]:
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
# The time-varying candidate: angles on a slow trend (issue 27)
# ------------------------------------------------------------------------------------------
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
        the means do determine (A4 constant arm, seed 79: α̂ 8.7° off, the prediction at
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
        t (issue 25; estimator.load_spread for the posterior): each window mean is of the
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


# ------------------------------------------------------------------------------------------
# The sequential test
# ------------------------------------------------------------------------------------------
@dataclass
class _Cluster:
    sum_x: np.ndarray
    n: int
    windows: int

    @property
    def mean(self) -> np.ndarray:
        return self.sum_x / self.n


@dataclass
class StructureVerdict:
    """What the ``angles`` record carries (docs/telemetry.md): ``structure`` and
    ``candidates``, plus the test's own numbers."""

    structure: str  # VERDICTS
    candidates: list[dict[str, Any]] = field(default_factory=list)
    look: int = 0
    conditions: int = 0
    level: float = 0.0
    restarted: bool = False  # a change in time restarted the accumulation at this window
    selected: dict[str, Any] | None = None  # the structure the estimator may use (determined, separable)
    fits: list[StructureFit] = field(default_factory=list)
    drift: DriftVerdict | None = None  # the time-varying candidate (DriftTest)

    def to_dict(self) -> dict[str, Any]:
        return {"structure": self.structure, "candidates": self.candidates,
                "drift": None if self.drift is None else self.drift.to_dict()}


class StructureTest:
    """The sequential test of constant angles against the competing structures (module doc).

    ``add_window(x, alpha)``: x (n, ncol) the window's scored rows ``[z, T, H, q]`` of static
    known-load content, α the angles in force (the constant fit starts there)."""

    def __init__(self, model: RigModel, moment_floor: float, *, false_alarm: float = FALSE_ALARM,
                 time_level: float = TIME_LEVEL, structures: Sequence[str] = STRUCTURES,
                 cluster_tolerance: tuple[float, float] = CLUSTER_TOLERANCE,
                 max_clusters: int = MAX_CLUSTERS, min_samples: int = 50,
                 drift: bool = True) -> None:
        for s in structures:
            parameter_names(s, model)
        self.model, self.moment_floor = model, float(moment_floor)
        self.false_alarm, self.time_level = float(false_alarm), float(time_level)
        self.structures = tuple(structures)
        self.tol = np.array([cluster_tolerance[0]] * 3 + [cluster_tolerance[1]] * 3, float)
        self.max_clusters = int(max_clusters)
        self.min_samples = int(min_samples)
        self.look = 0
        self.rejected = False
        self.restarts = 0
        self.clusters: list[_Cluster] = []
        self._starts: dict[str, Any] = {}  # per structure, the last converged joint fit (α0, β)
        self.bound: np.ndarray | None = None  # the static bound per axis (noise budget)
        # the joint fits (estimate, misfit, selection) at this look; off, a look gives the
        # verdict from the linear statistics only (a Monte Carlo that judges the last look)
        self.joint_fits = True
        self.alpha: np.ndarray | None = None
        self.last = StructureVerdict("undetermined")
        # the time-varying candidate beside the load structures (its own history and spending)
        self.drift = DriftTest(model, moment_floor, false_alarm=false_alarm,
                               time_level=time_level) if drift else None

    def restart(self) -> None:
        """Forget the accumulated conditions (a change in time); the looks keep counting."""
        self.clusters = []
        self.rejected = False
        self.restarts += 1
        self._starts = {}

    def _h_slice(self) -> slice:
        n = self.model.geometry.n_cells
        return slice(6 + n, 12 + n)

    def _find(self, xbar: np.ndarray) -> int | None:
        if not self.clusters:
            return None
        hs = self._h_slice()
        d = np.array([np.max(np.abs(c.mean[hs] - xbar[hs]) / self.tol) for c in self.clusters])
        j = int(np.argmin(d))
        if d[j] <= 1.0 or len(self.clusters) >= self.max_clusters:
            return j
        return None

    def _time_change(self, c: _Cluster, xbar: np.ndarray, n: int, alpha: np.ndarray) -> bool:
        Li = _whitener(self.model, alpha, self.moment_floor)
        d = residual(self.model, alpha, xbar) - residual(self.model, alpha, c.mean)
        w = Li @ d / math.sqrt(1.0 / n + 1.0 / c.n)
        return float(w @ w) > float(chi2.isf(self.time_level, 6))

    def add_window(self, x: np.ndarray, alpha: np.ndarray, t: float | None = None
                   ) -> StructureVerdict:
        """One window (module doc); ``t`` its time (s, the window's middle) for the drift
        test — None: no drift test at this look. The verdict is ``drifting`` when the drift
        test selects its trend and the load test has not rejected the constant model (a
        load dependence is not a trend: ``not_constant`` stays)."""
        x = np.asarray(x, float)
        alpha = np.asarray(alpha, float)
        if len(x) < self.min_samples or not np.isfinite(x).all() or not np.isfinite(alpha).all():
            # too little of this window to count, or a corrupt one (a non-finite value the
            # window's own checks reject): nothing new
            return self.last
        self.look += 1
        xbar, n = x.mean(axis=0), len(x)
        restarted = False
        j = self._find(xbar)
        if j is not None and self._time_change(self.clusters[j], xbar, n, alpha):
            self.restart()
            restarted, j = True, None
        if j is None:
            self.clusters.append(_Cluster(x.sum(axis=0), n, 1))
        else:
            c = self.clusters[j]
            c.sum_x += x.sum(axis=0)
            c.n += n
            c.windows += 1
        v = self._verdict(alpha, restarted)
        if self.drift is not None and t is not None:
            v.drift = self.drift.add_window(x, alpha, float(t))
            if v.drift is not None and v.drift.selected and v.structure != "not_constant":
                v.structure = DRIFTING
        self.last = v
        return self.last

    def rejudge(self, alpha: np.ndarray) -> StructureVerdict:
        """The last look again from other angles (a run's own estimate) when it gave no
        verdict because the constant fit did not converge from the angles in force (a cold
        start): that look spent nothing, so judging it once more at its level keeps the
        test's size. Anything else: the last verdict unchanged."""
        last = self.last
        alpha = np.asarray(alpha, float)
        if (last.structure != "undetermined" or last.fits or not self.clusters
                or not np.isfinite(alpha).all()):
            return last
        means = np.array([c.mean for c in self.clusters])
        counts = np.array([c.n for c in self.clusters], float)
        start = settle_constant(self.model, alpha, means, counts, self.moment_floor)
        v = self._verdict(start, last.restarted, misfit_test=True)
        v.drift = last.drift
        if v.drift is not None and v.drift.selected and v.structure != "not_constant":
            v.structure = DRIFTING
        self.last = v
        return v

    def _verdict(self, alpha: np.ndarray, restarted: bool, misfit_test: bool = False
                 ) -> StructureVerdict:
        level = spend(self.look, self.false_alarm)
        means = np.array([c.mean for c in self.clusters])
        counts = np.array([c.n for c in self.clusters], float)
        # from the angles in force at every look (a previous fit on fewer conditions can sit
        # far off in directions they did not determine)
        a, converged = fit_constant_converged(self.model, alpha, means, counts,
                                              self.moment_floor)
        if not converged and not self.rejected and misfit_test:
            # (rejudge: ``alpha`` the damped minimum from a run's estimate) Gauss–Newton
            # diverging at the constant fit's minimum is the large-residual case: the misfit
            # itself, χ² on 6C − rank dof under constant angles, is this look's one test
            m, dof = constant_misfit(self.model, alpha, means, counts, self.moment_floor)
            if dof > 0 and m > float(chi2.isf(level, dof)):
                self.rejected, a = True, np.asarray(alpha, float)
        self.alpha = a
        if not converged and not self.rejected:
            # far from the angles (a cold start, a run that did not converge): the linearised
            # statistic has no χ² law here — no verdict from this look
            return StructureVerdict("undetermined", look=self.look, conditions=len(self.clusters),
                                    level=level, restarted=restarted, fits=[])
        fits, _ = test_structures(self.model, a, means, counts, self.moment_floor, level,
                                  self.structures,
                                  joint=(True if self.rejected else None) if self.joint_fits
                                  else False,
                                  starts=self._starts)
        # the next look's joint fits start from these (a restart forgets them)
        self._starts = {f.structure: (f.alpha, f.beta) for f in fits if f.converged}
        base: dict[str, Any] = dict(look=self.look, conditions=len(self.clusters),
                                    level=level, restarted=restarted, fits=fits)
        if any(f.rejects_constant for f in fits):
            self.rejected = True
        if not self.rejected:
            testable = any(f.rank > 0 and f.misfit_dof > 0 for f in fits)
            return StructureVerdict("constant" if testable else "undetermined", **base)
        ranked = sorted(fits, key=lambda f: (not f.explains, f.log10_p))
        explaining = [f.structure for f in ranked if f.explains]
        cands = [self._candidate(f, explaining) for f in ranked if f.rank > 0]
        selected = None
        top = ranked[0]
        # the estimator may use the top structure when it explains the data, every parameter
        # is determined, its joint fit converged and determines the hub loads (_precise),
        # and every other explaining structure contains it by construction (NESTED: a
        # hub-position error is an external load; parsimony) or is tested — misfit dof left —
        # and leaves a misfit larger by more than χ²₁ at this look's level. A structure that
        # fills every testable direction explains anything: until the conditions leave it
        # dof, nothing is separated from it and nothing is selected (the next conditions
        # say what to apply)
        others = [f for f in ranked[1:] if f.explains]
        margin = float(chi2.isf(level, 1))
        if top.explains and top.determined and top.converged and all(
                (top.structure, f.structure) in NESTED
                or (f.misfit_dof > 0 and f.misfit - top.misfit > margin)
                for f in others) and self._precise(top, means):
            assert top.alpha is not None and top.P is not None  # _precise: a joint fit
            na = len(top.alpha)
            sig_all = np.concatenate([np.sqrt(np.maximum(np.diag(top.P)[:na], 0.0)),
                                      top.sigma])
            selected = {"structure": top.structure, "alpha": top.alpha.copy(),
                        "beta": top.beta.copy(), "sigma": top.sigma.copy(), "P": top.P,
                        "sigma_all": sig_all,
                        # the mean cell load of the conditions: where the angles linearise
                        "T_ref": np.average(means[:, 6:6 + self.model.geometry.n_cells],
                                            axis=0, weights=counts)}
        return StructureVerdict("not_constant", cands, selected=selected, **base)

    def _precise(self, f: StructureFit, means: np.ndarray) -> bool:
        """The fit determines the hub loads: at every condition seen, the σ its parameters'
        uncertainty adds is at most ``HUB_SIGMA_FRACTION`` of the static bound per axis."""
        if f.alpha is None or f.P is None:  # no joint fit
            return False
        if self.bound is None:
            from .noise_budget import noise_budget
            self.bound = noise_budget(self.model, f.alpha, "body").total
        sig = hub_sigma(f.structure, self.model, f.alpha, f.beta, f.P, means)
        return bool(np.all(sig <= HUB_SIGMA_FRACTION * self.bound))

    def _candidate(self, f: StructureFit, explaining: list[str]) -> dict[str, Any]:
        names = parameter_names(f.structure, self.model)
        units = parameter_units(f.structure, self.model)
        pk = per_kN(f.structure, f.beta)
        pks = per_kN(f.structure, f.sigma)
        zs = np.where(np.isfinite(f.sigma) & (f.sigma > 0), np.abs(f.beta) / f.sigma, 0.0)
        order = np.argsort(-zs)[:MAX_PARAMETERS_REPORTED]
        params = [{"name": names[i], "value": float(f.beta[i]),
                   "sigma": float(f.sigma[i]) if math.isfinite(f.sigma[i]) else None,
                   "per_kN": float(pk[i]),
                   "per_kN_sigma": float(pks[i]) if math.isfinite(pks[i]) else None,
                   "unit": units[i]} for i in order]
        return {"structure": f.structure, "parameters": params,
                "per_kN": {p["name"]: p["per_kN"] for p in params},
                "statistic": f.statistic, "dof": f.rank, "nominal": f.nominal,
                "limit": f.limit, "log10_p": f.log10_p, "explains": f.explains,
                "misfit": f.misfit, "misfit_dof": f.misfit_dof,
                "determined": f.determined,
                "not_separated_from": [s for s in explaining if s != f.structure]
                if f.explains else []}


# ------------------------------------------------------------------------------------------
# The selected structure in the hub-load estimate (the service's per-sample path)
# ------------------------------------------------------------------------------------------
APPLIED = ("cell_load_angles", "hub_position", "balance", "external_load")


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
        g = model.geometry
        self.structure = fit["structure"]
        a0, beta = np.asarray(fit["alpha0"]), np.asarray(fit["beta"])
        self.T_ref = np.asarray(fit["T_ref"])
        self.B = None
        self.M = None
        if self.structure == "cell_load_angles":
            cell = np.arange(2 * g.n_cells) // 2
            self.alpha = a0 + beta * self.T_ref[cell]
            dS = wrench_matrix_jacobian(g, self.alpha)
            B = np.zeros((6, g.n_cells))
            for k in range(2 * g.n_cells):
                B[:, cell[k]] += dS[k, :, cell[k]] * beta[k]
            self.B = B
        else:
            self.alpha = a0.copy()
            if self.structure in ("hub_position", "external_load"):
                R = structure_matrices(self.structure, beta, model)["R"]
                R0 = hub_transfer_matrix(g, "body")
                self.M = np.eye(6) - R0 @ np.linalg.inv(R)
                self.S = wrench_matrix(g, self.alpha)

    def correct(self, z: np.ndarray, T: np.ndarray) -> np.ndarray:
        if self.B is not None:
            result: np.ndarray = z - self.B @ (T * (T - self.T_ref))
            return result
        if self.M is not None:
            corrected: np.ndarray = z - self.M @ (z - self.S @ T)
            return corrected
        return z
