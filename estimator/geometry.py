"""Cell axes, the wrench matrix S(alpha) and its analytic derivative, and R (model.md §2)."""
from __future__ import annotations

import numpy as np

from .params import ANGLE_AXES, Geometry

_E = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b over the last axis (length 3), broadcast: np.cross's arithmetic, bit for bit,
    without its per-call overhead (np.cross costs ~40 µs on 3-vectors; the structure test's
    Jacobians call it ~10⁵ times in a Monte Carlo)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: skew(a) @ b == a x b."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rot(axis: str, angle: float) -> np.ndarray:
    """Right-handed rotation about a body axis."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _drot(axis: str, angle: float) -> np.ndarray:
    return skew(_E[axis]) @ rot(axis, angle)


def rot_cells(axes, angle: np.ndarray) -> np.ndarray:
    """rot(axes[i], angle[..., i]) for every cell i at once: (..., n, 3, 3), the same
    numbers as :func:`rot`."""
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    for axis, (i, j, k) in (("x", (0, 1, 2)), ("y", (1, 2, 0)), ("z", (2, 0, 1))):
        sel = [m for m, ax in enumerate(axes) if ax == axis]
        if sel:  # about axis i: (j, k) turn by +angle, [[c, -s], [s, c]]
            cc, ss = c[..., sel], s[..., sel]
            R[..., sel, i, i] = 1.0
            R[..., sel, j, j], R[..., sel, j, k] = cc, -ss
            R[..., sel, k, j], R[..., sel, k, k] = ss, cc
    return R


def cell_axes(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """Actual unit axes u_i (7, 3) from the nominal axes and the 14 angles (Eq A2)."""
    alpha = np.asarray(alpha, dtype=float)
    u = np.empty((geometry.n_cells, 3))
    for i, kind in enumerate(geometry.cell_kinds):
        first, second = ANGLE_AXES[kind]
        a1, a2 = alpha[2 * i], alpha[2 * i + 1]
        u[i] = rot(second, a2) @ rot(first, a1) @ geometry.cell_axes[i]
    return u


def cell_axes_jacobian(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """du_i/dalpha: (7, 2, 3), the derivative of cell i's axis by its own two angles."""
    alpha = np.asarray(alpha, dtype=float)
    du = np.empty((geometry.n_cells, 2, 3))
    for i, kind in enumerate(geometry.cell_kinds):
        first, second = ANGLE_AXES[kind]
        a1, a2 = alpha[2 * i], alpha[2 * i + 1]
        n = geometry.cell_axes[i]
        du[i, 0] = rot(second, a2) @ _drot(first, a1) @ n
        du[i, 1] = _drot(second, a2) @ rot(first, a1) @ n
    return du


def wrench_matrix(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """S(alpha), 6x7: column i is [u_i; p_i x u_i] (Eq A3)."""
    u = cell_axes(geometry, alpha)
    m = cross3(geometry.cell_positions, u)
    return np.vstack([u.T, m.T])


def wrench_matrix_jacobian(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """dS/dalpha as an array (14, 6, 7); angle j only moves column j // 2."""
    du = cell_axes_jacobian(geometry, alpha)
    n = geometry.n_cells
    m = cross3(np.asarray(geometry.cell_positions, dtype=float)[:, None, :], du)  # (7, 2, 3)
    dS = np.zeros((2 * n, 6, n))
    j = np.arange(2 * n)
    dS[j, :3, j // 2] = du.reshape(2 * n, 3)
    dS[j, 3:, j // 2] = m.reshape(2 * n, 3)
    return dS


def shaft_rotation(geometry: Geometry, frame: str | None = None) -> np.ndarray:
    """C_s: from the frame the hub loads are given in to body axes (model.md §2).

    A forward shaft tilt t is Ry(-t) with x forward and z down.
    """
    frame = geometry.hub_frame if frame is None else frame
    if frame == "body":
        return np.eye(3)
    if frame == "shaft":
        return rot("y", -geometry.shaft_tilt_rad)
    raise ValueError(f"hub frame must be 'body' or 'shaft', not {frame!r}")


def hub_transfer_matrix(geometry: Geometry, frame: str | None = None) -> np.ndarray:
    """R, 6x6: moves the hub wrench to the CG, R = [[C, 0], [skew(p_H) C, C]] (Eq A8).

    Unlike the report's Eq A8 the small h_x*Y_H term of the yaw row is kept.
    """
    C = shaft_rotation(geometry, frame)
    R = np.zeros((6, 6))
    R[:3, :3] = C
    R[3:, :3] = skew(geometry.hub_position) @ C
    R[3:, 3:] = C
    return R
