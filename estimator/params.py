"""Parameter dataclasses of the rigid-body load-cell model (model.md §1–§4).

These are plain values: the shell (rsra.config.rig) builds them from the rig TOML.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Rotation axes of the two deformation angles of each kind of cell (model.md §2):
# u = R_second(a2) R_first(a1) n.
ANGLE_AXES = {"vertical": ("x", "y"), "lateral": ("x", "z"), "longitudinal": ("y", "z")}
_AXIS_SYMBOL = {"x": "delta", "y": "theta", "z": "psi"}


def cell_kind(nominal_axis: np.ndarray) -> str:
    """The kind of a cell from the dominant component of its nominal axis."""
    k = int(np.argmax(np.abs(nominal_axis)))
    return ("longitudinal", "lateral", "vertical")[k]


@dataclass(frozen=True)
class Geometry:
    """Attach points and nominal axes of the cells, the hub centre and the shaft tilt."""

    cell_names: tuple[str, ...]
    cell_positions: np.ndarray  # (7, 3) m, relative to the CG
    cell_axes: np.ndarray  # (7, 3) nominal unit axes
    hub_position: np.ndarray  # (3,) m
    shaft_tilt_rad: float = 0.0
    hub_frame: str = "body"  # "body" or "shaft"

    @property
    def n_cells(self) -> int:
        return len(self.cell_names)

    @property
    def cell_kinds(self) -> tuple[str, ...]:
        return tuple(cell_kind(a) for a in self.cell_axes)

    @property
    def angle_names(self) -> tuple[str, ...]:
        """Names of the 14 angles in the contract order [dA tA dB tB ... tG pG]."""
        names = []
        for name, kind in zip(self.cell_names, self.cell_kinds):
            for ax in ANGLE_AXES[kind]:
                names.append(f"{_AXIS_SYMBOL[ax]}_{name}")
        return tuple(names)


@dataclass(frozen=True)
class MassProperties:
    mass: np.ndarray  # (3,) effective masses m_x, m_y, m_z, kg
    inertia: np.ndarray  # (3,) I_xx, I_yy, I_zz, kg m^2


@dataclass(frozen=True)
class Accelerometers:
    positions: np.ndarray  # (K, 3) m
    sigma: np.ndarray  # (K,) m/s^2 per axis
    angular: str = "neglect"  # "neglect" or "least_squares"


@dataclass(frozen=True)
class ExternalLoads:
    """Measured external loads D q (model §3): one wrench column per channel."""

    names: tuple[str, ...] = ()
    wrenches: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))  # (6, Q)
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (Q,)


@dataclass(frozen=True)
class RigModel:
    """Everything the numerical core needs to know about the rig."""

    geometry: Geometry
    mass: MassProperties
    accelerometers: Accelerometers
    cell_sigma: np.ndarray  # (7,) N
    balance_sigma: np.ndarray  # (6,) N, N m
    external: ExternalLoads = field(default_factory=ExternalLoads)
