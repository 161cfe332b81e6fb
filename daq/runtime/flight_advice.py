"""What would determine the directions a filter-error window leaves undetermined
(docs/identification.md "Which additions would determine the rest"): the rig's side of
:mod:`estimator.flight_advice` — the candidates from ``[identification.advice]`` and the
``advice`` object of the filter-error `angles` records (docs/telemetry.md). Runs on the
identification worker after the window's run: one more pass of the calibration filter's
sensitivities at the run's estimate, one Lyapunov equation per candidate accelerometer and
the filter's transfer function over the band (tens of milliseconds a window)."""
from __future__ import annotations

import logging

import numpy as np

from rsra.estimator.flight_advice import AXES, advise, candidates_from

log = logging.getLogger("rsra.identification")


class FlightAdvice:
    """Candidates fixed per rig; :meth:`for_window` gives one window's ``advice``."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        adv = cfg.identification.advice
        self.enabled = adv is not None
        if adv is None:
            return
        self.candidates = candidates_from(
            [(n, p, s) for n, p, s in adv.accelerometers],
            [(a, r) for a, r in zip(AXES, adv.manoeuvre_rms) if r > 0], adv.band_hz,
            [c.stiffness_N_per_m for c in cfg.cells])

    def for_window(self, ident) -> dict | None:
        """The advice of the window ``ident`` (a filter-error PeriodicIdentification) just ran,
        or None (off, no window, or a window whose information cannot be evaluated)."""
        last = getattr(ident, "last_window", None)
        if not self.enabled or last is None:
            return None
        prob, theta = last
        if not np.all(np.isfinite(theta)) or prob.n_scored == 0:
            return None
        try:
            _, de, B = prob.residual_series(theta)
            return advise(prob.par, theta, de, B, ident.design,
                          {"moment_floor": self.cfg.identification.moment_floor_Nm},
                          ident.posterior.sigma_max, prob.n_scored, ident.fs,
                          self.candidates, ident.content_sos)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            log.warning("identification: no advice for this window (%s)", e)
            return None
