"""The competing structures of the known-load model as a registry (estimator.structure's
docstring): one :class:`Structure` subclass each, and the :data:`STRUCTURES` table that
picks one by name. A structure adds a term to the constant-angle model
``m = S(α) T + R₀ H (+ E q)`` that is zero at β = 0; a subclass says what its parameters β
are (names, units), what it predicts (one condition, or C at once), its Jacobians (at β = 0
for the linearised test, exact at β for the joint fit), and the hub loads it implies.

A new structure is one subclass here and one entry in :data:`STRUCTURES`. Pure numerics.
"""
from __future__ import annotations

from typing import ClassVar, Final, NamedTuple

import numpy as np

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

AXES = ("X", "Y", "Z", "L", "M", "N")


def skews(v: np.ndarray) -> np.ndarray:
    """The batched skew(v) (C, 3, 3) of C vectors (C, 3): skews(v)[c] @ x = v[c] × x."""
    o = np.zeros((len(v), 3, 3))
    o[:, 0, 1], o[:, 0, 2], o[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    o[:, 1, 0], o[:, 2, 0], o[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return o


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


def _cells(model: RigModel) -> np.ndarray:
    """The cell each angle belongs to (2 angles per cell)."""
    return np.arange(2 * model.geometry.n_cells) // 2


class Correction(NamedTuple):
    """A selected structure in the per-sample path's form: the angles the filter uses, and
    z's correction — ``z − B (T∘(T − T_ref))`` (B), ``z − M (z − S T)`` (M, S), or none."""

    alpha: np.ndarray
    B: np.ndarray | None
    M: np.ndarray | None
    S: np.ndarray | None


class Structure:
    """One competing structure: its parameters β and what it predicts. The defaults are those
    of a structure acting on the hub-transfer matrix only (``R(β)`` in place of ``R₀``)."""

    #: the structure's name (records, files, configuration)
    name: ClassVar[str] = ""

    def parameter_names(self, model: RigModel) -> tuple[str, ...]:
        """The parameters β, in order."""
        raise NotImplementedError

    def parameter_units(self, model: RigModel) -> tuple[str, ...]:
        """Unit of each parameter per kN of load (the ``per_kN`` of a candidate)."""
        raise NotImplementedError

    def per_kN(self, beta: np.ndarray) -> np.ndarray:
        """β expressed per kN of load in :meth:`parameter_units`."""
        return beta * 1e3

    def matrices(self, beta: np.ndarray, model: RigModel) -> dict[str, np.ndarray]:
        """The exact (not linearised) model pieces at β, for hub loads: ``R`` (6×6), the
        hub-transfer matrix, and any the structure adds."""
        return {"R": hub_transfer_matrix(model.geometry, "body")}

    def predict(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, T: np.ndarray,
                H: np.ndarray) -> np.ndarray:
        """m(α, β; T, H) of C conditions (C, 7), (C, 6) → (C, 6), without the external
        loads (exact in β; the cell-load gains act on the mean cell load)."""
        R = self.matrices(beta, model)["R"]
        result: np.ndarray = T @ wrench_matrix(model.geometry, alpha).T + H @ R.T
        return result

    def jacobian(self, model: RigModel, dS: np.ndarray, T: np.ndarray, H: np.ndarray
                 ) -> np.ndarray:
        """∂m/∂β (C, 6, p) at β = 0 of C conditions; ``dS`` the wrench matrix's Jacobian in
        the angles at the α of the test."""
        raise NotImplementedError

    def exact_jacobians(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                        T: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """∂m/∂α (C, 6, 14) and ∂m/∂β (C, 6, p), exact at (α, β) (the joint fit's)."""
        dS = wrench_matrix_jacobian(model.geometry, alpha)
        return np.einsum("kac,nc->nak", dS, T), self.jacobian(model, dS, T, H)

    def hub_loads(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, z: np.ndarray,
                  T: np.ndarray) -> np.ndarray:
        """The static estimate Ĥ (N, 6) under the structure: ``R(β)⁻¹ (z − S(α) T)``."""
        S = wrench_matrix(model.geometry, alpha)
        return np.linalg.solve(self.matrices(beta, model)["R"], (z - T @ S.T).T).T

    def correction(self, model: RigModel, alpha0: np.ndarray, beta: np.ndarray,
                   T_ref: np.ndarray) -> Correction:
        """The structure in the per-sample path's form (estimator.structure's
        StructureCorrection): the angles the filter uses and z's correction — here
        ``z − (I − R₀ R(β)⁻¹)(z − S(α0) T)``, exact (the hub load is R(β)⁻¹(z − S T))."""
        g = model.geometry
        alpha = alpha0.copy()
        R = self.matrices(beta, model)["R"]
        M = np.eye(6) - hub_transfer_matrix(g, "body") @ np.linalg.inv(R)
        return Correction(alpha, None, M, wrench_matrix(g, alpha))


class CellLoadAngles(Structure):
    """Every angle moves with the load its own cell carries, ``α_k = α0_k + g_k T_c(k)``
    (14 gains, rad/N: what a deflecting transmission can be identified as)."""

    name = "cell_load_angles"

    def parameter_names(self, model: RigModel) -> tuple[str, ...]:
        return tuple(f"g_{a}" for a in model.geometry.angle_names)

    def parameter_units(self, model: RigModel) -> tuple[str, ...]:
        return ("deg/kN",) * len(self.parameter_names(model))  # per kN on its own cell

    def per_kN(self, beta: np.ndarray) -> np.ndarray:
        result: np.ndarray = np.degrees(beta) * 1e3
        return result

    def matrices(self, beta: np.ndarray, model: RigModel) -> dict[str, np.ndarray]:
        return {**super().matrices(beta, model), "gain": beta}

    def predict(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, T: np.ndarray,
                H: np.ndarray) -> np.ndarray:
        cell = _cells(model)
        Sc, _ = _cell_columns(model, alpha[None, :] + beta[None, :] * T[:, cell])
        R0 = hub_transfer_matrix(model.geometry, "body")
        result: np.ndarray = np.einsum("nac,nc->na", Sc, T) + H @ R0.T
        return result

    def jacobian(self, model: RigModel, dS: np.ndarray, T: np.ndarray, H: np.ndarray
                 ) -> np.ndarray:
        # α_k = α0_k + g_k T_c(k): ∂(S T)/∂g_k = ∂S/∂α_k[:, c] T_c · T_c
        cell = _cells(model)
        D = dS[np.arange(len(cell)), :, cell]  # (14, 6)
        result: np.ndarray = D.T[None, :, :] * (T[:, cell] ** 2)[:, None, :]
        return result

    def exact_jacobians(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                        T: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cell = _cells(model)  # every condition at its own angles α + β∘T_c
        _, D = _cell_columns(model, alpha[None, :] + beta[None, :] * T[:, cell])
        Ja = D.transpose(0, 2, 1) * T[:, cell][:, None, :]
        return Ja, Ja * T[:, cell][:, None, :]

    def correction(self, model: RigModel, alpha0: np.ndarray, beta: np.ndarray,
                   T_ref: np.ndarray) -> Correction:
        """``alpha = α0 + g∘T_ref`` and ``z − B (T∘(T − T_ref))``, B (6×7) the first-order
        change of S T with the angles (``B[:, c] = Σ_{k∈c} ∂S/∂α_k[:, c] g_k``)."""
        g, cell = model.geometry, _cells(model)
        alpha = alpha0 + beta * T_ref[cell]
        dS = wrench_matrix_jacobian(g, alpha)
        B = np.zeros((6, g.n_cells))
        for k in range(2 * g.n_cells):
            B[:, cell[k]] += dS[k, :, cell[k]] * beta[k]
        return Correction(alpha, B, None, None)

    def hub_loads(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, z: np.ndarray,
                  T: np.ndarray) -> np.ndarray:
        g, cell = model.geometry, _cells(model)
        out = np.empty_like(z)
        for n in range(len(z)):
            S = wrench_matrix(g, alpha + beta * T[n, cell])
            out[n] = z[n] - S @ T[n]
        return np.linalg.solve(self.matrices(beta, model)["R"], out.T).T


class HubPosition(Structure):
    """The hub centre is off by δp (3, m): ``R(p_H + δp)``."""

    name = "hub_position"

    def parameter_names(self, model: RigModel) -> tuple[str, ...]:
        return ("hub_dx", "hub_dy", "hub_dz")

    def parameter_units(self, model: RigModel) -> tuple[str, ...]:
        return ("N·m/kN",) * 3  # moment error per kN of hub force (= mm of hub offset)

    def matrices(self, beta: np.ndarray, model: RigModel) -> dict[str, np.ndarray]:
        R = hub_transfer_matrix(model.geometry, "body").copy()
        R[3:, :3] = skew(model.geometry.hub_position + beta)
        return {"R": R}

    def jacobian(self, model: RigModel, dS: np.ndarray, T: np.ndarray, H: np.ndarray
                 ) -> np.ndarray:
        J = np.zeros((len(H), 6, 3))
        J[:, 3:] = -skews(H[:, :3])  # δp × F
        return J


class Balance(Structure):
    """The reference balance has per-axis scale errors s (6) and an alignment error φ (3,
    rad): the true hub load is ``[(I + skew φ)(1 + s_F)∘F_b; (I + skew φ)(1 + s_M)∘M_b]``.
    It changes only the reference, not the estimate."""

    name = "balance"

    def parameter_names(self, model: RigModel) -> tuple[str, ...]:
        return tuple(f"scale_{a}" for a in AXES) + ("align_x", "align_y", "align_z")

    def parameter_units(self, model: RigModel) -> tuple[str, ...]:
        return ("N/kN",) * 3 + ("N·m/kN",) * 3 + ("N/kN",) * 3  # error per kN (N·m) read

    def predict(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, T: np.ndarray,
                H: np.ndarray) -> np.ndarray:
        Rp = np.eye(3) + skew(beta[6:9])
        Ht = np.hstack([(H[:, :3] * (1 + beta[:3])) @ Rp.T, (H[:, 3:] * (1 + beta[3:6])) @ Rp.T])
        R0 = hub_transfer_matrix(model.geometry, "body")
        result: np.ndarray = T @ wrench_matrix(model.geometry, alpha).T + Ht @ R0.T
        return result

    def jacobian(self, model: RigModel, dS: np.ndarray, T: np.ndarray, H: np.ndarray
                 ) -> np.ndarray:
        D = np.zeros((len(H), 6, 9))
        D[:, np.arange(6), np.arange(6)] = H  # scale: (1 + s) ∘ H
        D[:, :3, 6:] = -skews(H[:, :3])  # alignment: φ × F, φ × M
        D[:, 3:, 6:] = -skews(H[:, 3:])
        result: np.ndarray = np.einsum("ab,nbk->nak", hub_transfer_matrix(model.geometry,
                                                                          "body"), D)
        return result

    def exact_jacobians(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray,
                        T: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Ja = np.einsum("kac,nc->nak", wrench_matrix_jacobian(model.geometry, alpha), T)
        F, Mo = H[:, :3], H[:, 3:]
        Rp = np.eye(3) + skew(beta[6:9])
        D = np.zeros((len(H), 6, 9))
        D[:, :3, :3] = Rp[None] * F[:, None, :]
        D[:, 3:, 3:6] = Rp[None] * Mo[:, None, :]
        D[:, :3, 6:] = -np.stack([skew(f) for f in F * (1 + beta[:3])])
        D[:, 3:, 6:] = -np.stack([skew(m) for m in Mo * (1 + beta[3:6])])
        return Ja, np.einsum("ab,nbk->nak", hub_transfer_matrix(model.geometry, "body"), D)

    def hub_loads(self, model: RigModel, alpha: np.ndarray, beta: np.ndarray, z: np.ndarray,
                  T: np.ndarray) -> np.ndarray:
        return constant_hub_loads(model, alpha, z, T)

    def correction(self, model: RigModel, alpha0: np.ndarray, beta: np.ndarray,
                   T_ref: np.ndarray) -> Correction:
        return Correction(alpha0.copy(), None, None, None)  # z unchanged: only the reference


class ExternalLoad(Structure):
    """An unmodelled load path: a CG wrench linear in the applied hub forces, ``U F`` (6×3,
    N or N·m per N)."""

    name = "external_load"

    def parameter_names(self, model: RigModel) -> tuple[str, ...]:
        return tuple(f"ext_{r}_per_{c}" for r in AXES for c in AXES[:3])

    def parameter_units(self, model: RigModel) -> tuple[str, ...]:
        return tuple("N/kN" if n.split("_")[1] in "XYZ" else "N·m/kN"
                     for n in self.parameter_names(model))

    def matrices(self, beta: np.ndarray, model: RigModel) -> dict[str, np.ndarray]:
        R = hub_transfer_matrix(model.geometry, "body").copy()
        R[:, :3] += beta.reshape(6, 3)
        return {"R": R}

    def jacobian(self, model: RigModel, dS: np.ndarray, T: np.ndarray, H: np.ndarray
                 ) -> np.ndarray:
        J = np.zeros((len(H), 6, 18))
        for i in range(6):  # U F, U row-major (6×3)
            J[:, i, 3 * i:3 * i + 3] = H[:, :3]
        return J


def constant_hub_loads(model: RigModel, alpha: np.ndarray, z: np.ndarray, T: np.ndarray
                       ) -> np.ndarray:
    """The constant-angle model's static estimate ``R₀⁻¹ (z − S(α) T)`` (N, 6)."""
    S = wrench_matrix(model.geometry, alpha)
    return np.linalg.solve(hub_transfer_matrix(model.geometry, "body"), (z - T @ S.T).T).T


#: the structures by name, in the order the test reports them
STRUCTURES: Final[dict[str, Structure]] = {
    s.name: s for s in (CellLoadAngles(), HubPosition(), Balance(), ExternalLoad())}


def structure_of(name: str) -> Structure:
    """The structure called ``name`` (ValueError naming the choices)."""
    try:
        return STRUCTURES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown structure {name!r}; choose from {tuple(STRUCTURES)}"
                         ) from None
