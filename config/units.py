"""Display units: SI inside, US (lbf, ft lbf) as a presentation option."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

LBF_N = 4.4482216152605  # N per lbf
FT_LBF_NM = 1.3558179483314004  # N m per ft lbf
G0 = 9.80665  # standard gravity, m/s^2

AXIS_KIND = ("force", "force", "force", "moment", "moment", "moment")


def axis_units(units: str) -> list[str]:
    f, m = ("N", "N·m") if units == "si" else ("lbf", "ft·lbf")
    return [f if k == "force" else m for k in AXIS_KIND]


def to_units(values: ArrayLike, units: str, kinds: Sequence[str] = AXIS_KIND) -> np.ndarray:
    """Convert SI values per axis (force/moment) to the display units."""
    v = np.asarray(values, dtype=float)
    if units == "si":
        return v
    scale = np.array([1 / LBF_N if k == "force" else 1 / FT_LBF_NM for k in kinds])
    out: np.ndarray = v * scale
    return out
