"""How far the angles in force can move the hub loads (docs/identification.md, "How far
the angles in force can move the hub loads").

The static estimate is ``H = R⁻¹ (z − S(α) T)`` (model §2, §3), so an error δα of the angles
in force moves it by ``δH = J δα`` with

    J = −R⁻¹ (∂S/∂α · T)            (6 × 14, one column per angle)

and, for angles whose error has covariance P_α, the hub load's error covariance from the
angles is ``J P_α Jᵀ``. Per axis k it is a quadratic form in the cell loads,
``σ_k² = Tᵀ Q_k T`` with ``Q_k = A_k P_α A_kᵀ`` (7 × 7) and ``A = R⁻¹ ∂S/∂α`` (6 × 7 × 14):
Q is computed when the angles in force or their covariance change, and a sample costs two
small matrix-vector products. Pure numerics (no I/O)."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from .geometry import hub_transfer_matrix, wrench_matrix_jacobian
from .params import Geometry

# the hub_loads flag: sigma_angles exceeds the static noise bound on some axis (telemetry.md)
ANGLES_UNCERTAIN = "angles_uncertain"


def hub_angle_sensitivity(geometry: Geometry, alpha: np.ndarray,
                          frame: str | None = None) -> np.ndarray:
    """A = R⁻¹ ∂S/∂α at ``alpha``: (6, 7, 14), ``A[k, i, j] = (R⁻¹ ∂S/∂α_j)[k, i]``, so
    that ∂H_static/∂α_j = −A[:, :, j] @ T (the hub loads in ``frame``, default the rig's)."""
    Rinv = np.linalg.inv(hub_transfer_matrix(geometry, frame))
    dS = wrench_matrix_jacobian(geometry, alpha)  # (14, 6, 7)
    result: np.ndarray = np.einsum("kl,jli->kij", Rinv, dS)
    return result


def hub_angle_jacobian(A: np.ndarray, T: np.ndarray) -> np.ndarray:
    """J = ∂H_static/∂α = −A · T: (6, 14) for one sample's cell loads T (7,)."""
    return -np.tensordot(A, np.asarray(T, float), axes=([1], [0]))


def hub_angle_quadratic(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Q (6, 7, 7), ``Q_k = A_k P A_kᵀ``: the hub-load variance of axis k from angles of
    covariance P (14 × 14) is ``Tᵀ Q_k T`` — ``diag(J P Jᵀ)`` without forming J."""
    P = np.asarray(P, float)
    Q = np.einsum("kij,jl,kml->kim", A, P, A)
    result: np.ndarray = 0.5 * (Q + Q.transpose(0, 2, 1))
    return result


class HubAngleVariance:
    """The per-sample form: ``variance(T) = diag(J(T) P Jᵀ(T))`` from a precomputed Q,
    as one (42 × 7) and one (6 × 7) matrix-vector product."""

    def __init__(self, geometry: Geometry, alpha: np.ndarray, P: np.ndarray,
                 frame: str | None = None) -> None:
        self.A = hub_angle_sensitivity(geometry, alpha, frame)
        self.Q = hub_angle_quadratic(self.A, P)
        n = self.Q.shape[1]
        self._Q2 = np.ascontiguousarray(self.Q.reshape(-1, n))  # (6·7, 7)
        self._rows = self.Q.shape[0]

    def variance(self, T: np.ndarray) -> np.ndarray:
        """(6,) per-axis variance of the hub-load error due to the angles (N², (N·m)²)."""
        result: np.ndarray = self._Q2.dot(T).reshape(self._rows, -1).dot(T)
        return result


def angle_covariance(angle_names: tuple[str, ...] | list[str],
                     names: Sequence[str] | None, P: ArrayLike | None,
                     base: np.ndarray) -> np.ndarray:
    """The angles' covariance (n × n, in ``angle_names`` order) after a posterior over
    ``names`` with covariance ``P``: the angles it names take its block, their
    cross-covariance with the angles it does not name is 0, those keep ``base``'s
    variance. Parameters that are not angles are ignored."""
    out = np.array(base, float, copy=True)
    if names is None or P is None:
        return out
    P = np.asarray(P, float)
    idx = [(angle_names.index(n), i) for i, n in enumerate(names) if n in angle_names]
    if not idx or P.shape != (len(names), len(names)):
        return out
    a = np.array([k for k, _ in idx])
    p = np.array([i for _, i in idx])
    out[a, :] = 0.0
    out[:, a] = 0.0
    out[np.ix_(a, a)] = P[np.ix_(p, p)]
    return out
