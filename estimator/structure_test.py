"""The sequential test of constant angles against the competing structures (estimator.structure's
docstring: the clusters of windows at the same load, the change in time, the linearised
statistics under alpha spending, the candidates and the selected structure). Pure numerics.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.stats import chi2

from .params import RigModel
from .structure_fits import (
    CLUSTER_TOLERANCE,
    DRIFTING,
    FALSE_ALARM,
    HUB_SIGMA_FRACTION,
    MAX_CLUSTERS,
    MAX_PARAMETERS_REPORTED,
    NESTED,
    STRUCTURES,
    StructureFit,
    TIME_LEVEL,
    _whitener,
    constant_misfit,
    fit_constant_converged,
    hub_sigma,
    parameter_names,
    parameter_units,
    per_kN,
    residual,
    settle_constant,
    spend,
    test_structures,
)
from .drift_test import DriftTest, DriftVerdict


@dataclass
class _Cluster:
    sum_x: np.ndarray
    n: int
    windows: int

    @property
    def mean(self) -> np.ndarray:
        return self.sum_x / self.n


@dataclass
class StructureVerdict:
    """What the ``angles`` record carries (docs/telemetry.md): ``structure`` and
    ``candidates``, plus the test's own numbers."""

    structure: str  # VERDICTS
    candidates: list[dict[str, Any]] = field(default_factory=list)
    look: int = 0
    conditions: int = 0
    level: float = 0.0
    restarted: bool = False  # a change in time restarted the accumulation at this window
    selected: dict[str, Any] | None = None  # the structure the estimator may use (determined, separable)
    fits: list[StructureFit] = field(default_factory=list)
    drift: DriftVerdict | None = None  # the time-varying candidate (DriftTest)

    def to_dict(self) -> dict[str, Any]:
        return {"structure": self.structure, "candidates": self.candidates,
                "drift": None if self.drift is None else self.drift.to_dict()}


class StructureTest:
    """The sequential test of constant angles against the competing structures (module doc).

    ``add_window(x, alpha)``: x (n, ncol) the window's scored rows ``[z, T, H, q]`` of static
    known-load content, α the angles in force (the constant fit starts there)."""

    def __init__(self, model: RigModel, moment_floor: float, *, false_alarm: float = FALSE_ALARM,
                 time_level: float = TIME_LEVEL, structures: Sequence[str] = tuple(STRUCTURES),
                 cluster_tolerance: tuple[float, float] = CLUSTER_TOLERANCE,
                 max_clusters: int = MAX_CLUSTERS, min_samples: int = 50,
                 drift: bool = True) -> None:
        for s in structures:
            parameter_names(s, model)
        self.model, self.moment_floor = model, float(moment_floor)
        self.false_alarm, self.time_level = float(false_alarm), float(time_level)
        self.structures = tuple(structures)
        self.tol = np.array([cluster_tolerance[0]] * 3 + [cluster_tolerance[1]] * 3, float)
        self.max_clusters = int(max_clusters)
        self.min_samples = int(min_samples)
        self.look = 0
        self.rejected = False
        self.restarts = 0
        self.clusters: list[_Cluster] = []
        self._starts: dict[str, Any] = {}  # per structure, the last converged joint fit (α0, β)
        self.bound: np.ndarray | None = None  # the static bound per axis (noise budget)
        # the joint fits (estimate, misfit, selection) at this look; off, a look gives the
        # verdict from the linear statistics only (a Monte Carlo that judges the last look)
        self.joint_fits = True
        self.alpha: np.ndarray | None = None
        self.last = StructureVerdict("undetermined")
        # the time-varying candidate beside the load structures (its own history and spending)
        self.drift = DriftTest(model, moment_floor, false_alarm=false_alarm,
                               time_level=time_level) if drift else None

    def restart(self) -> None:
        """Forget the accumulated conditions (a change in time); the looks keep counting."""
        self.clusters = []
        self.rejected = False
        self.restarts += 1
        self._starts = {}

    def _h_slice(self) -> slice:
        n = self.model.geometry.n_cells
        return slice(6 + n, 12 + n)

    def _find(self, xbar: np.ndarray) -> int | None:
        if not self.clusters:
            return None
        hs = self._h_slice()
        d = np.array([np.max(np.abs(c.mean[hs] - xbar[hs]) / self.tol) for c in self.clusters])
        j = int(np.argmin(d))
        if d[j] <= 1.0 or len(self.clusters) >= self.max_clusters:
            return j
        return None

    def _time_change(self, c: _Cluster, xbar: np.ndarray, n: int, alpha: np.ndarray) -> bool:
        Li = _whitener(self.model, alpha, self.moment_floor)
        d = residual(self.model, alpha, xbar) - residual(self.model, alpha, c.mean)
        w = Li @ d / math.sqrt(1.0 / n + 1.0 / c.n)
        return float(w @ w) > float(chi2.isf(self.time_level, 6))

    def add_window(self, x: np.ndarray, alpha: np.ndarray, t: float | None = None
                   ) -> StructureVerdict:
        """One window (module doc); ``t`` its time (s, the window's middle) for the drift
        test — None: no drift test at this look. The verdict is ``drifting`` when the drift
        test selects its trend and the load test has not rejected the constant model (a
        load dependence is not a trend: ``not_constant`` stays)."""
        x = np.asarray(x, float)
        alpha = np.asarray(alpha, float)
        if len(x) < self.min_samples or not np.isfinite(x).all() or not np.isfinite(alpha).all():
            # too little of this window to count, or a corrupt one (a non-finite value the
            # window's own checks reject): nothing new
            return self.last
        self.look += 1
        v = self._verdict(alpha, self._absorb(x, alpha))
        if self.drift is not None and t is not None:
            v.drift = self.drift.add_window(x, alpha, float(t))
            _mark_drifting(v)
        self.last = v
        return self.last

    def _absorb(self, x: np.ndarray, alpha: np.ndarray) -> bool:
        """The window into its condition's cluster, or a new one; True when its condition
        changed with time (the clusters restarted before it)."""
        xbar, n = x.mean(axis=0), len(x)
        j = self._find(xbar)
        restarted = j is not None and self._time_change(self.clusters[j], xbar, n, alpha)
        if restarted:
            self.restart()
            j = None
        if j is None:
            self.clusters.append(_Cluster(x.sum(axis=0), n, 1))
            return restarted
        c = self.clusters[j]
        c.sum_x += x.sum(axis=0)
        c.n += n
        c.windows += 1
        return restarted

    def rejudge(self, alpha: np.ndarray) -> StructureVerdict:
        """The last look again from other angles (a run's own estimate) when it gave no
        verdict because the constant fit did not converge from the angles in force (a cold
        start): that look spent nothing, so judging it once more at its level keeps the
        test's size. Anything else: the last verdict unchanged."""
        last = self.last
        alpha = np.asarray(alpha, float)
        if (last.structure != "undetermined" or last.fits or not self.clusters
                or not np.isfinite(alpha).all()):
            return last
        means = np.array([c.mean for c in self.clusters])
        counts = np.array([c.n for c in self.clusters], float)
        start = settle_constant(self.model, alpha, means, counts, self.moment_floor)
        v = self._verdict(start, last.restarted, misfit_test=True)
        v.drift = last.drift
        _mark_drifting(v)
        self.last = v
        return v

    def _verdict(self, alpha: np.ndarray, restarted: bool, misfit_test: bool = False
                 ) -> StructureVerdict:
        level = spend(self.look, self.false_alarm)
        means = np.array([c.mean for c in self.clusters])
        counts = np.array([c.n for c in self.clusters], float)
        # from the angles in force at every look (a previous fit on fewer conditions can sit
        # far off in directions they did not determine)
        a, converged = fit_constant_converged(self.model, alpha, means, counts,
                                              self.moment_floor)
        if not converged and not self.rejected and misfit_test \
                and self._misfit_rejects(alpha, means, counts, level):
            self.rejected, a = True, np.asarray(alpha, float)
        self.alpha = a
        if not converged and not self.rejected:
            # far from the angles (a cold start, a run that did not converge): the linearised
            # statistic has no χ² law here — no verdict from this look
            return StructureVerdict("undetermined", look=self.look, conditions=len(self.clusters),
                                    level=level, restarted=restarted, fits=[])
        fits, _ = test_structures(self.model, a, means, counts, self.moment_floor, level,
                                  self.structures, joint=self._joint(), starts=self._starts)
        # the next look's joint fits start from these (a restart forgets them)
        self._starts = {f.structure: (f.alpha, f.beta) for f in fits if f.converged}
        base: dict[str, Any] = dict(look=self.look, conditions=len(self.clusters),
                                    level=level, restarted=restarted, fits=fits)
        return self._judge_fits(fits, base, means, counts)

    def _judge_fits(self, fits: list[StructureFit], base: dict[str, Any], means: np.ndarray,
                    counts: np.ndarray) -> StructureVerdict:
        """The look's verdict from the structures' fits: constant (or undetermined while no
        fit can test it) until one rejects the constant model; then not constant, with the
        candidates ranked and the structure to use when one is selected."""
        level = base["level"]
        if any(f.rejects_constant for f in fits):
            self.rejected = True
        if not self.rejected:
            testable = any(f.rank > 0 and f.misfit_dof > 0 for f in fits)
            return StructureVerdict("constant" if testable else "undetermined", **base)
        ranked = sorted(fits, key=lambda f: (not f.explains, f.log10_p))
        explaining = [f.structure for f in ranked if f.explains]
        cands = [self._candidate(f, explaining) for f in ranked if f.rank > 0]
        selected = self._select(ranked, level, means, counts)
        return StructureVerdict("not_constant", cands, selected=selected, **base)

    def _misfit_rejects(self, alpha: np.ndarray, means: np.ndarray, counts: np.ndarray,
                        level: float) -> bool:
        """(rejudge: ``alpha`` the damped minimum from a run's estimate) Gauss–Newton
        diverging at the constant fit's minimum is the large-residual case: the misfit
        itself, χ² on 6C − rank dof under constant angles, is this look's one test."""
        m, dof = constant_misfit(self.model, alpha, means, counts, self.moment_floor)
        return dof > 0 and m > float(chi2.isf(level, dof))

    def _joint(self) -> bool | None:
        """test_structures' ``joint``: no joint fits when they are off; once the constant
        model is rejected, always; before, as test_structures decides (None)."""
        if not self.joint_fits:
            return False
        return True if self.rejected else None

    def _select(self, ranked: list[StructureFit], level: float, means: np.ndarray,
                counts: np.ndarray) -> dict[str, Any] | None:
        """The structure the estimator may use, or None.

        The top structure when it explains the data, every parameter is determined, its
        joint fit converged and determines the hub loads (_precise), and every other
        explaining structure contains it by construction (NESTED: a hub-position error is an
        external load; parsimony) or is tested — misfit dof left — and leaves a misfit larger
        by more than χ²₁ at this look's level. A structure that fills every testable direction
        explains anything: until the conditions leave it dof, nothing is separated from it and
        nothing is selected (the next conditions say what to apply)."""
        top = ranked[0]
        if not (top.explains and top.determined and top.converged
                and _separated(top, ranked[1:], level) and self._precise(top, means)):
            return None
        assert top.alpha is not None and top.P is not None  # _precise: a joint fit
        na = len(top.alpha)
        sig_all = np.concatenate([np.sqrt(np.maximum(np.diag(top.P)[:na], 0.0)), top.sigma])
        return {"structure": top.structure, "alpha": top.alpha.copy(),
                "beta": top.beta.copy(), "sigma": top.sigma.copy(), "P": top.P,
                "sigma_all": sig_all,
                # the mean cell load of the conditions: where the angles linearise
                "T_ref": np.average(means[:, 6:6 + self.model.geometry.n_cells],
                                    axis=0, weights=counts)}

    def _precise(self, f: StructureFit, means: np.ndarray) -> bool:
        """The fit determines the hub loads: at every condition seen, the σ its parameters'
        uncertainty adds is at most ``HUB_SIGMA_FRACTION`` of the static bound per axis."""
        if f.alpha is None or f.P is None:  # no joint fit
            return False
        if self.bound is None:
            from .noise_budget import noise_budget
            self.bound = noise_budget(self.model, f.alpha, "body").total
        sig = hub_sigma(f.structure, self.model, f.alpha, f.beta, f.P, means)
        return bool(np.all(sig <= HUB_SIGMA_FRACTION * self.bound))

    def _candidate(self, f: StructureFit, explaining: list[str]) -> dict[str, Any]:
        names = parameter_names(f.structure, self.model)
        units = parameter_units(f.structure, self.model)
        pk = per_kN(f.structure, f.beta)
        pks = per_kN(f.structure, f.sigma)
        zs = np.where(np.isfinite(f.sigma) & (f.sigma > 0), np.abs(f.beta) / f.sigma, 0.0)
        order = np.argsort(-zs)[:MAX_PARAMETERS_REPORTED]
        params = [{"name": names[i], "value": float(f.beta[i]),
                   "sigma": float(f.sigma[i]) if math.isfinite(f.sigma[i]) else None,
                   "per_kN": float(pk[i]),
                   "per_kN_sigma": float(pks[i]) if math.isfinite(pks[i]) else None,
                   "unit": units[i]} for i in order]
        return {"structure": f.structure, "parameters": params,
                "per_kN": {p["name"]: p["per_kN"] for p in params},
                "statistic": f.statistic, "dof": f.rank, "nominal": f.nominal,
                "limit": f.limit, "log10_p": f.log10_p, "explains": f.explains,
                "misfit": f.misfit, "misfit_dof": f.misfit_dof,
                "determined": f.determined,
                "not_separated_from": [s for s in explaining if s != f.structure]
                if f.explains else []}


def _mark_drifting(v: StructureVerdict) -> None:
    """The verdict is ``drifting`` when the drift test selected its trend and the load test
    has not rejected the constant model (a load dependence is not a trend)."""
    if v.drift is not None and v.drift.selected and v.structure != "not_constant":
        v.structure = DRIFTING


def _separated(top: StructureFit, others: Sequence[StructureFit], level: float) -> bool:
    """Every other explaining structure contains ``top`` by construction (NESTED) or leaves
    a misfit larger by more than χ²₁ at ``level``."""
    margin = float(chi2.isf(level, 1))
    return all((top.structure, f.structure) in NESTED
               or (f.misfit_dof > 0 and f.misfit - top.misfit > margin)
               for f in others if f.explains)
