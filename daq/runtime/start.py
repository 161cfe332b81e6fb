"""How a run starts (the service's wiring, before anything opens): the starting angles and
their covariance, the structure the hub loads use from the start, whether the identification
runs, and the pipeline built from them.

``plan_start(cfg, opts, source)`` reads the options, the source's angle plan (a replay's
recorded schedule) and a saved posterior once, and returns a frozen :class:`StartPlan`; the
service opens its outputs, worker and source from it (daq.runtime.service).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rsra.config.rig import RigConfig
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.runtime.records import AnglesRecord, InitialAngles

if TYPE_CHECKING:
    from rsra.daq.runtime.sources import Source

log = logging.getLogger("rsra.service")


def initial_angles(cfg: RigConfig, state_path: str | None,
                   accept_rig_mismatch: bool = False) -> tuple[np.ndarray, Any, str | None]:
    """(alpha0, posterior state or None, warning or None) from the config or a saved
    posterior (of this rig, within the angles' physical range: daq.posterior_file)."""
    alpha0 = np.asarray(cfg.identification.initial_angles_rad, float).copy()
    if not state_path:
        return alpha0, None, None
    from rsra.daq.runtime.posterior_file import load_checked

    names = cfg.rig_model().geometry.angle_names
    idc = cfg.identification
    wanted = names if idc.parameters == "angles" else tuple(idc.parameters)
    # PosteriorFileError on a corrupt file, another rig's, or angles out of range
    state, warning = load_checked(cfg, state_path, wanted,
                                  accept_rig_mismatch=accept_rig_mismatch)
    for n, v in zip(state.names, state.theta):
        if n in names:
            alpha0[names.index(n)] = v
    return alpha0, state, warning


@dataclass(frozen=True)
class StartPlan:
    """What a run starts from, decided before anything opens.

    ``alpha0`` the starting angles (all of the rig's), ``state`` a saved posterior or None,
    ``recorded_initial`` a replay's starting record when the run uses it (no ``--angles``),
    ``recorded`` the recorded angles records to apply from their samples, ``use_ident`` the
    identification runs, ``start_fit`` the structure the hub loads use from the start,
    ``schedule`` a replay's ``angles_schedule`` summary, ``warnings`` start-up problems the
    run goes on with (already logged)."""

    cfg: RigConfig
    alpha0: np.ndarray
    state: Any = None
    recorded_initial: dict | None = None
    recorded: list[AnglesRecord] = field(default_factory=list)
    use_ident: bool = False
    start_fit: Any = None
    schedule: dict | None = None
    warnings: tuple[str, ...] = ()
    #: the load filter's band designed at start (live: a redesign in the bus thread would
    #: miss its deadline); a run not paced by the wall clock designs each speed when met
    prefill: bool = True

    def initial_record(self) -> InitialAngles:
        """The first line of a recording's ``angles.jsonl``: the angles the run starts from."""
        names = self.cfg.rig_model().geometry.angle_names
        if self.state is not None:
            P = self.state.P.tolist()
            rec_names = list(self.state.names)
            theta = self.state.theta.tolist()
        else:
            s = self.cfg.identification.prior_sigma_rad
            rec_names = list(names)
            theta = self.alpha0.tolist()
            P = (np.eye(len(names)) * s * s).tolist()
        return InitialAngles(names=rec_names, alpha=theta, P=P, alpha_all=self.alpha0.tolist(),
                             structure_fit=self.start_fit)

    def pipeline(self) -> EstimatorPipeline:
        """The estimator pipeline at the starting angles, their covariance (hub_loads
        sigma_angles), the starting structure and the recorded records to apply."""
        p = EstimatorPipeline(self.cfg, self.alpha0, identification=self.use_ident,
                              prefill=self.prefill)
        # the covariance of the starting angles: the recording's starting posterior in a
        # replay, else the saved posterior's or the prior
        start = (self.recorded_initial if self.recorded_initial is not None
                 else self.initial_record().to_dict())
        p.angles.set_covariance(start.get("names"), start.get("P"))
        if self.start_fit is not None:
            p.angles.set_structure(self.start_fit)
        for rec in self.recorded:
            p.deliver(rec)
        return p


def plan_start(cfg: RigConfig, opts: Any, source: Source) -> StartPlan:
    """The start of a run from its options (ServiceOptions) and its source. Raises (before
    anything opens) a ReplayError for a recorded start that does not fit the rig, a
    PosteriorFileError for a saved posterior that cannot be used, a ConfigError for a state
    file that is not ours to write."""
    plan = source.angles_plan(opts.identification, opts.recompute)
    warnings: list[str] = []
    recorded_initial = plan.recorded_initial if not opts.angles else None
    if recorded_initial is not None:
        alpha0 = _recorded_angles(cfg, recorded_initial, plan.folder)
        state = None
    else:
        alpha0, state, warning = initial_angles(cfg, opts.angles, opts.accept_rig_mismatch)
        if warning:
            log.warning("%s", warning)
            warnings.append(warning)
    use_ident = opts.identification and (source.saves_posterior or plan.recompute)
    if use_ident:
        # the worker saves accepted runs there: only over a posterior of ours
        # (ConfigError naming the key otherwise, before acquisition starts)
        from rsra.daq.runtime.posterior_file import prepare_state_file

        for warning in prepare_state_file(cfg, accept_rig_mismatch=opts.accept_rig_mismatch):
            log.warning("%s", warning)
            warnings.append(warning)
    return StartPlan(cfg=cfg, alpha0=alpha0, state=state, recorded_initial=recorded_initial,
                     recorded=list(plan.recorded), use_ident=use_ident,
                     start_fit=_start_fit(cfg, recorded_initial, state),
                     schedule=plan.schedule, warnings=tuple(warnings),
                     prefill=not source.deterministic)


def _recorded_angles(cfg: RigConfig, recorded_initial: dict, folder: Path | None) -> np.ndarray:
    """The recording's starting angles; a ReplayError when their count is not the rig's."""
    alpha0 = np.asarray(recorded_initial.get("alpha_all", recorded_initial["alpha"]), float)
    n_angles = len(cfg.rig_model().geometry.angle_names)
    if alpha0.shape != (n_angles,):
        from rsra.daq.bus.replay import ReplayError

        folder = folder if folder is not None else Path(".")
        raise ReplayError(f"{folder / 'angles.jsonl'}: the starting record holds "
                          f"{alpha0.size} angles, the rig has {n_angles}; fix: "
                          "replay with --recompute or give the recording's --config")
    return alpha0


def _start_fit(cfg: RigConfig, recorded_initial: dict | None, state: Any) -> Any:
    """The structure the hub loads use from the start: the recording's first line in a
    replay; else the saved posterior's, else the config's."""
    if recorded_initial is not None:
        return recorded_initial.get("structure_fit")
    if state is not None and state.structure is not None:
        return state.structure
    return cfg.identification.structure_fit
