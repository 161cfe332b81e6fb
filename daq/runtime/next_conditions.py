"""The next load conditions to apply (docs/identification.md "The next load
conditions"): the rig's side of :mod:`estimator.design` — the candidate conditions from the
configured load limits, the structures from the current posterior and the conditions seen,
and the ``next_conditions`` list that `rsra calibrate` and the live known-load `angles`
records carry (docs/telemetry.md).

Candidates: every combination of −1, 0, +1 × the balance's full scale on X, Y, L, M, N and
−1 … +0.5 × its full-scale force on Z (thrust is −Z), kept when no cell load exceeds the
cell's full scale and the balance stays within its full scale (``[balance]``, ``[[cells]]``
of the rig config). Each condition is taken as held for one identification window
(``identification.window_s``).
"""
from __future__ import annotations

import numpy as np

from rsra.estimator.design import (
    DEFAULT_COUNT,
    ConditionTracker,
    Structure,
    candidate_grid,
    cell_gain_structure,
    constant_angle_structure,
    feasible,
    next_conditions,
)


class NextConditions:
    """Candidates (fixed per rig) and the load-gain information of the conditions seen."""

    def __init__(self, cfg, count: int = DEFAULT_COUNT) -> None:
        self.cfg = cfg
        self.model = cfg.rig_model()
        idc = cfg.identification
        self.alpha0 = np.asarray(idc.initial_angles_rad, float)
        self.stiffness = np.array([c.stiffness_N_per_m for c in cfg.cells], float)
        b = cfg.balance
        limits = [b.full_scale_force_N] * 3 + [b.full_scale_moment_Nm] * 3
        grid = candidate_grid(limits)
        ok = feasible(self.model, self.alpha0, grid,
                      cell_full_scale=np.array([c.full_scale_N for c in cfg.cells], float),
                      force_limit=b.full_scale_force_N, moment_limit=b.full_scale_moment_Nm,
                      stiffness=self.stiffness)
        self.candidates = grid[ok]
        self.n_samples = float(round(idc.window_s * cfg.sample_rate_hz))
        self.count = int(count)
        self.tracker = ConditionTracker(self.model, idc.prior_sigma_rad,
                                        moment_floor=idc.moment_floor_Nm)

    def add_window(self, alpha: np.ndarray, T: np.ndarray, n_scored: int) -> None:
        self.tracker.add_window(alpha, T, n_scored)

    def structures(self, names, alpha: np.ndarray, P: np.ndarray) -> list[Structure]:
        """The constant structure from the posterior (names, P) at the 14 angles ``alpha``,
        and the per-cell load-gain structure from the conditions seen."""
        fl = self.cfg.identification.moment_floor_Nm
        const = constant_angle_structure(self.model, alpha, P, self.n_samples, moment_floor=fl,
                                         stiffness=self.stiffness, names=names)
        gain = cell_gain_structure(self.model, alpha, self.tracker.M, self.n_samples,
                                   moment_floor=fl, stiffness=self.stiffness)
        return [const, gain]

    def recommend(self, names, alpha: np.ndarray, P: np.ndarray) -> list[dict] | None:
        """The ``next_conditions`` list, or None when there is nothing to recommend from
        (no candidate within the limits, or a posterior that is not a covariance)."""
        P = np.asarray(P, float)
        if not len(self.candidates) or not np.all(np.isfinite(P)):
            return None
        try:
            recs = next_conditions(self.structures(names, alpha, P), self.candidates,
                                   self.count)
        except np.linalg.LinAlgError:
            return None
        return [r.to_dict() for r in recs]


def for_calibration(cfg, result) -> list[dict] | None:
    """`rsra calibrate`'s ``next_conditions``: the batch posterior (its names and P) for the
    constant structure; for the load-gain structure the recording's scored samples in
    stretches of one window each (as the live windows see them)."""
    nc = NextConditions(cfg)
    d = result.data
    idx = np.flatnonzero(d.scored)
    n = max(int(nc.n_samples), 1)
    for k in range(0, len(idx), n):
        part = idx[k:k + n]
        nc.add_window(result.alpha_all, d.T[part], len(part))
    return nc.recommend(result.names, result.alpha_all, result.ident.P)


def describe(H, gain: float) -> str:
    """One line per recommended condition: the loaded axes and the expected gain."""
    axes = ("X", "Y", "Z", "L", "M", "N")
    unit = ("kN",) * 3 + ("kN·m",) * 3
    loads = ", ".join(f"{a} {v / 1e3:+g} {u}" for a, v, u in zip(axes, H, unit) if v != 0)
    return f"{loads or 'no load'}: expected information gain {gain:.1f} nats"
