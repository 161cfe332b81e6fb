"""The angles in force in the estimator pipeline (daq/runtime/pipeline.py): the identified
angles, or a selected structure's (docs/identification.md "structure"), the wrench matrix S
they give the static estimate, and how far they can move the hub loads (`sigma_angles`, flag
`angles_uncertain`: docs/identification.md, estimator/angle_uncertainty.py).
"""
from __future__ import annotations

import logging
import math
from typing import Any, Protocol

import numpy as np

from rsra.daq.runtime.records import ABSENT, AnglesRecord
from rsra.estimator.angle_uncertainty import HubAngleVariance, angle_covariance
from rsra.estimator.geometry import wrench_matrix
from rsra.estimator.params import RigModel
from rsra.estimator.structure import StructureCorrection

log = logging.getLogger("rsra.pipeline")


class FollowsAngles(Protocol):
    """What takes the angles in force too (the load filter: its W and S)."""

    def set_alpha(self, alpha: np.ndarray) -> None: ...


class AnglesInForce:
    """The angles the hub loads use and their uncertainty.

    ``alpha``: the identified angles (an accepted angles record's); ``structure``: a selected
    structure in force (its own angles and the correction of z) or None. ``S`` is the wrench
    matrix of the angles used (the structure's when one is in force), ``var`` their share of
    the hub loads' variance, from the covariance ``P`` (it starts at the prior, then each
    applied angles record's P); :meth:`measure` gives a measured sample's ``sigma`` and
    ``uncertain`` (the variance above the static noise bound ``bound2``: σ², per axis). The
    compiled hub path (daq/runtime/hubpath.py) reads ``S``, ``var`` and ``bound2`` and sets
    ``sigma`` and ``uncertain`` as :meth:`measure` does. ``follower`` (the load filter) is
    given every new set of angles used."""

    def __init__(self, model: RigModel, alpha: np.ndarray, prior_sigma: float,
                 bound2: np.ndarray, follower: FollowsAngles) -> None:
        self.model = model
        self.prior_sigma = prior_sigma
        self.alpha = np.asarray(alpha, float).copy()
        self.structure: StructureCorrection | None = None  # a selected structure in force
        self._structure_fit: dict[str, Any] | None = None
        self.S = wrench_matrix(model.geometry, self.alpha)
        n_a = len(model.geometry.angle_names)
        self.P = np.eye(n_a) * prior_sigma ** 2
        self.bound2 = bound2
        self.var = HubAngleVariance(model.geometry, self.alpha, self.P)
        self.sigma: np.ndarray | None = None  # the last measured sample's (predict-only: kept)
        self.uncertain: bool | np.bool_ = False
        self._follower = follower

    def apply(self, rec: AnglesRecord) -> None:
        """An angles record comes into force: its posterior's covariance, its angles when it
        was accepted (those it names), its structure when it carries one (known loads)."""
        self.set_covariance(rec.get("names"), rec.get("P"))
        if rec.accepted:
            names = rec.names or []
            alpha = self.alpha.copy()
            angle_names = self.model.geometry.angle_names
            for n, v in zip(names, rec.alpha):
                if n in angle_names:
                    alpha[angle_names.index(n)] = v
            self.set_alpha(alpha)
        if rec.structure_fit is not ABSENT:  # known loads: the structure in force
            self.set_structure(rec.structure_fit)

    def set_alpha(self, alpha: np.ndarray) -> None:
        self.alpha = np.asarray(alpha, float).copy()
        if self.structure is None:
            self._use(self.alpha)

    def _use(self, alpha: np.ndarray) -> None:
        self.S = wrench_matrix(self.model.geometry, alpha)
        self._follower.set_alpha(alpha)
        self.var = HubAngleVariance(self.model.geometry, alpha, self._P_in_force())

    def set_covariance(self, names: Any, P: Any) -> None:
        """The covariance of the angles in force: the posterior ``P`` over ``names`` (an
        angles record's — every record carries the posterior whose mean is in force — or the
        starting posterior). Angles it does not name keep theirs; a record without P
        changes nothing."""
        if names is None or P is None:
            return
        P_new = angle_covariance(self.model.geometry.angle_names, names, P, self.P)
        if not np.array_equal(P_new, self.P):
            self.P = P_new
            if self.structure is None:
                self.var = HubAngleVariance(self.model.geometry, self.alpha, P_new)

    def _P_in_force(self) -> np.ndarray:
        """Under a selected structure: its fit's α0 σ where the fit determined it (the prior
        σ elsewhere), its β's uncertainty left out; else the posterior's covariance."""
        if self.structure is None:
            return self.P
        prior = self.prior_sigma
        sig = (self._structure_fit or {}).get("alpha0_sigma") or []
        n_a = len(self.P)
        s = [float(sig[k]) if k < len(sig) and isinstance(sig[k], (int, float))
             and math.isfinite(sig[k]) else prior for k in range(n_a)]
        return np.diag(np.square(s))

    def set_structure(self, fit: dict[str, Any] | None) -> None:
        """Hub loads under a selected structure (estimator.structure.StructureCorrection:
        its angles and the correction of z), or under the constant angles again (None)."""
        if fit == self._structure_fit:
            return
        self._structure_fit = fit
        try:
            self.structure = None if fit is None else StructureCorrection(self.model, fit)
        except ValueError as e:  # a malformed record (another version): constant angles
            log.error("structure_fit not used (%s); hub loads use the constant angles", e)
            self.structure = None
        self._use(self.alpha if self.structure is None else self.structure.alpha)

    def measure(self, T: np.ndarray) -> None:
        """A measured sample's cell loads ``T``: ``sigma`` (per axis) and ``uncertain``."""
        v = self.var.variance(T)
        self.sigma = np.sqrt(np.abs(v))
        self.uncertain = np.count_nonzero(v > self.bound2) > 0
