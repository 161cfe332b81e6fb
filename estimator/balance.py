"""Inertial loads from accelerometers, the force-and-moment balance and the static
hub-load estimate (model.md §3; report Eq 1.1, 1.2, A3, B2). Vectorised over samples."""
from __future__ import annotations

import numpy as np

from .geometry import hub_transfer_matrix, skew, wrench_matrix
from .params import Accelerometers, MassProperties, RigModel


def accel_solution_matrix(acc: Accelerometers) -> np.ndarray:
    """A (6, 3K): [f; omega_dot] at the CG = A @ stacked triaxial readings.

    least_squares: f_k = f + omega_dot x r_k = f - skew(r_k) omega_dot, solved for
    [f; omega_dot] (needs three non-collinear triaxes); neglect: the mean specific force
    and omega_dot = 0 (the report's assumption).
    """
    K = acc.positions.shape[0]
    if acc.angular == "least_squares":
        G = np.vstack([np.hstack([np.eye(3), -skew(r)]) for r in acc.positions])
        if np.linalg.matrix_rank(G) < 6:
            raise ValueError(
                "angular = 'least_squares' needs at least three non-collinear triaxial "
                "accelerometers; use angular = 'neglect'"
            )
        return np.linalg.pinv(G)
    A = np.zeros((6, 3 * K))
    for k in range(K):
        A[:3, 3 * k : 3 * k + 3] = np.eye(3) / K
    return A


def inertia_matrix(mass: MassProperties) -> np.ndarray:
    """diag(m_x, m_y, m_z, I_xx, I_yy, I_zz)."""
    return np.diag(np.concatenate([mass.mass, mass.inertia]))


def inertial_load_matrix(model: RigModel) -> np.ndarray:
    """M_f (6, 3K): inertial loads I = M_f @ stacked accelerometer readings (m/s^2)."""
    Mf: np.ndarray = inertia_matrix(model.mass) @ accel_solution_matrix(model.accelerometers)
    return Mf


def inertial_loads(model: RigModel, accel: np.ndarray) -> np.ndarray:
    """I (N, 6) from readings (N, K, 3) or (N, 3K) of specific force in body axes."""
    accel = np.asarray(accel, dtype=float)
    flat = accel.reshape(accel.shape[0], -1)
    result: np.ndarray = flat @ inertial_load_matrix(model).T
    return result


def static_estimate(
    model: RigModel,
    alpha: np.ndarray,
    T: np.ndarray,
    I: np.ndarray,
    q: np.ndarray | None = None,
    frame: str | None = None,
) -> np.ndarray:
    """H_hat = R^-1 (I_m - S(alpha) T_m - D q_m) per sample (Eq 1.2, B2): (N, 6)."""
    S = wrench_matrix(model.geometry, alpha)
    R = hub_transfer_matrix(model.geometry, frame)
    rhs = np.asarray(I, float) - np.asarray(T, float) @ S.T
    if q is not None and model.external.wrenches.shape[1]:
        rhs = rhs - np.asarray(q, float) @ model.external.wrenches.T
    return np.linalg.solve(R, rhs.T).T


def balance_residual(
    model: RigModel, alpha: np.ndarray, T: np.ndarray, I: np.ndarray, H: np.ndarray,
    q: np.ndarray | None = None, frame: str | None = None,
) -> np.ndarray:
    """I - S T - R H - D q (N, 6): zero when the balance of Eq 1.1 holds."""
    S = wrench_matrix(model.geometry, alpha)
    R = hub_transfer_matrix(model.geometry, frame)
    r: np.ndarray = (np.asarray(I, float) - np.asarray(T, float) @ S.T
                     - np.asarray(H, float) @ R.T)
    if q is not None and model.external.wrenches.shape[1]:
        r = r - np.asarray(q, float) @ model.external.wrenches.T
    return r


def accelerometer_covariance(model: RigModel) -> np.ndarray:
    """Covariance (6, 6) of the inertial loads from accelerometer noise: M_f Q_a M_f^T."""
    acc = model.accelerometers
    Qa = np.diag(np.repeat(np.asarray(acc.sigma, float) ** 2, 3))
    Mf = inertial_load_matrix(model)
    result: np.ndarray = Mf @ Qa @ Mf.T
    return result


def measurement_covariance(
    model: RigModel,
    alpha: np.ndarray,
    moment_floor: float = 100.0,
    known_loads: bool = False,
) -> np.ndarray:
    """W(alpha) of model.md §7 (effective variance, errors in variables), 6x6:

    W = Sigma_z + S(alpha) Sigma_T S(alpha)^T (+ R0 Sigma_H R0^T with known loads), where
    Sigma_z is the inertial-load covariance from the accelerometer specs plus a floor on the
    moment rows for what the model neglects (the angular inertial loads). R0 is R with
    C_s = I: the reference balance measures in body axes. Always the unfiltered covariance.
    """
    S = wrench_matrix(model.geometry, alpha)
    W: np.ndarray = accelerometer_covariance(model) + np.diag([0, 0, 0, 1.0, 1.0, 1.0]) * moment_floor**2
    W = W + S @ np.diag(np.asarray(model.cell_sigma, float) ** 2) @ S.T
    if model.external.wrenches.shape[1]:
        E = model.external.wrenches
        W = W + E @ np.diag(np.asarray(model.external.sigma, float) ** 2) @ E.T
    if known_loads:
        R0 = hub_transfer_matrix(model.geometry, "body")
        W = W + R0 @ np.diag(np.asarray(model.balance_sigma, float) ** 2) @ R0.T
    return W
