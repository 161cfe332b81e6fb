"""The noise budget of the static estimate (model.md §4; report Appendix B, Eq B9–B11).

Q_H = R^-1 (M_f Q_a M_f^T + S Q_T S^T) R^-T: the lower bound on static accuracy without
statistical processing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .balance import accelerometer_covariance
from .geometry import hub_transfer_matrix, wrench_matrix
from .params import RigModel

AXES = ("X", "Y", "Z", "L", "M", "N")


@dataclass(frozen=True)
class NoiseBudget:
    total: np.ndarray  # (6,) sigma per axis, N and N m
    load_cells: np.ndarray  # (6,) load-cell part
    accelerometers: np.ndarray  # (6,) accelerometer part
    covariance: np.ndarray  # (6, 6) Q_H


def load_cell_covariance(model: RigModel, alpha: np.ndarray) -> np.ndarray:
    S = wrench_matrix(model.geometry, alpha)
    result: np.ndarray = S @ np.diag(np.asarray(model.cell_sigma, float) ** 2) @ S.T
    return result


def noise_budget(model: RigModel, alpha: np.ndarray | None = None,
                 frame: str | None = None) -> NoiseBudget:
    alpha = np.zeros(2 * model.geometry.n_cells) if alpha is None else np.asarray(alpha)
    Rinv = np.linalg.inv(hub_transfer_matrix(model.geometry, frame))
    QT = Rinv @ load_cell_covariance(model, alpha) @ Rinv.T
    Qa = Rinv @ accelerometer_covariance(model) @ Rinv.T
    Q = QT + Qa
    return NoiseBudget(
        total=np.sqrt(np.diag(Q)),
        load_cells=np.sqrt(np.diag(QT)),
        accelerometers=np.sqrt(np.diag(Qa)),
        covariance=Q,
    )
