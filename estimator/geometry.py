"""Cell axes, the wrench matrix S(alpha) and its analytic derivative, and R (model.md §2)."""
from __future__ import annotations

import functools
from typing import Sequence

import numpy as np

from .params import ANGLE_AXES, Geometry, cell_kind

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
    result: np.ndarray = skew(_E[axis]) @ rot(axis, angle)
    return result


# rot(axis, a) as a flat 3×3: where 1, c, c, s and −s go
_ROT_FLAT = {"x": (0, 4, 8, 7, 5), "y": (4, 0, 8, 2, 6), "z": (8, 0, 4, 3, 1)}


@functools.lru_cache(maxsize=64)
def _rot_index(axes: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    return tuple(np.array(col) for col in zip(*(_ROT_FLAT[ax] for ax in axes)))


def rot_cells(axes: Sequence[str], angle: np.ndarray) -> np.ndarray:
    """rot(axes[i], angle[..., i]) for every cell i at once: (..., n, 3, 3), the same
    numbers as :func:`rot`."""
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    one, c1, c2, sp, sn = _rot_index(tuple(axes))
    cells = np.arange(angle.shape[-1])
    R = np.zeros(angle.shape + (9,))
    R[..., cells, one] = 1.0
    R[..., cells, c1] = c
    R[..., cells, c2] = c
    R[..., cells, sp] = s
    R[..., cells, sn] = -s
    return R.reshape(angle.shape + (3, 3))


@functools.lru_cache(maxsize=64)
def _cell_frames(nominal: bytes) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray, np.ndarray]:
    """Per cell: the first and the second angle's axis, skew() of each (by the nominal axes'
    bytes: Geometry.cell_kinds recomputes the kinds at every call)."""
    kinds = [cell_kind(a) for a in np.frombuffer(nominal).reshape(-1, 3)]
    first, second = zip(*(ANGLE_AXES[k] for k in kinds))
    return (first, second, np.array([skew(_E[ax]) for ax in first]),
            np.array([skew(_E[ax]) for ax in second]))


def angle_axes(geometry: Geometry) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The first and the second angle's rotation axis of every cell (params.ANGLE_AXES)."""
    return _frames(geometry)[:2]


def _frames(geometry: Geometry) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray,
                                         np.ndarray]:
    return _cell_frames(np.ascontiguousarray(geometry.cell_axes, dtype=float).tobytes())


def cell_axes(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """Actual unit axes u_i (7, 3) from the nominal axes and the 14 angles (Eq A2)."""
    alpha = np.asarray(alpha, dtype=float)
    first, second, _, _ = _frames(geometry)
    R = np.matmul(rot_cells(second, alpha[1::2]), rot_cells(first, alpha[0::2]))
    result: np.ndarray = np.matmul(R, np.asarray(geometry.cell_axes, float)[:, :, None])[:, :, 0]
    return result


def cell_axes_jacobian(geometry: Geometry, alpha: np.ndarray) -> np.ndarray:
    """du_i/dalpha: (7, 2, 3), the derivative of cell i's axis by its own two angles."""
    alpha = np.asarray(alpha, dtype=float)
    first, second, K1, K2 = _frames(geometry)
    R1, R2 = rot_cells(first, alpha[0::2]), rot_cells(second, alpha[1::2])
    n = np.asarray(geometry.cell_axes, float)[:, :, None]
    du = np.empty((geometry.n_cells, 2, 3))
    du[:, 0] = np.matmul(np.matmul(R2, np.matmul(K1, R1)), n)[:, :, 0]  # R2 · (K1 R1) · n
    du[:, 1] = np.matmul(np.matmul(np.matmul(K2, R2), R1), n)[:, :, 0]  # (K2 R2) · R1 · n
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
