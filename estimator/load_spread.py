"""The spread of a ground calibration over the loads its angles follow
(docs/identification.md, "A ground calibration over loads the angles follow").

A constant-angle known-load posterior pools windows held at different static loads. Where the
angles move with the load — within the rig's 1-σ sensitivity bound ``s`` (per unit load on
each axis, ``identification.angle_load_sensitivity_deg_per_unit``) — each window's data are of
the angles at its own load, ``α(L_j) = α_ref + g (L_j − L_ref)``, and the pooled estimate,
linearised, is ``Σ_j P M_j α(L_j)``: the reference's angles plus a bias ``Σ_k A_k g_k`` with
``A_k = P Σ_j (L_jk − L_ref,k) M_j`` (``P`` the posterior, ``M_j`` window j's information at the
estimate). The gains ``g_ik`` are unknown with 1-σ ``s_k`` each (the same isotropic bound as a
flight window's load excursion), so the posterior the service states is ``P + Σ_k s_k² A_k A_kᵀ``
about the angles at the reference load. Windows that determine different directions at
different loads make ``A_k`` larger than ``s ΔL`` along weakly determined directions — the
amplification a floor of ``(s ΔL)²`` would miss.

Bounded: the accepted windows' moments since the posterior's reference began (a reset, a
restore or a move to a flight trim starts it again), at most ``MAX_WINDOWS`` (the oldest
leave first); the held windows a run takes in with it are kept beside.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from .identification import moments_information

MAX_WINDOWS = 512  # accepted known-load windows kept (≈ 43 min of 5-s windows)


class LoadSpread:
    """The known-load posterior's load spread (module doc). ``after(rec, moments, load)``
    after every known-load run: a held window is kept for the run that takes it in, an
    accepted run's windows join the accepted ones and the posterior's ``reference.cov`` is
    computed afresh at its estimate."""

    def __init__(self, post: Any, par: Any, sensitivity: np.ndarray) -> None:
        # post: the SequentialPosterior (not imported: posterior imports this module)
        self.post, self.par = post, par
        self.sensitivity = np.asarray(sensitivity, float)
        self.windows: deque[tuple[np.ndarray, int, np.ndarray]] = deque(maxlen=MAX_WINDOWS)
        self.held: list[tuple[np.ndarray, int, np.ndarray]] = []
        self._reference: object = post.reference

    def after(self, rec: Any, moments: tuple[np.ndarray, int],
              static_load: np.ndarray | None) -> None:
        post = self.post
        if post.reference is not self._reference:  # reset, restored or carried: start again
            self.windows.clear()
            self.held = []
            self._reference = post.reference
        h = None if static_load is None else np.asarray(static_load, float)
        if h is None or h.shape != (6,) or not np.all(np.isfinite(h)):
            return
        here = (np.asarray(moments[0], float).copy(), int(moments[1]), h.copy())
        held_now = int(post.moments.windows_held)
        if rec.accepted:
            self.windows.extend(self.held)
            self.windows.append(here)
            self.held = []
            post.reference.cov = self.covariance()
        elif held_now == 0:
            self.held = []
        elif held_now == len(self.held) + 1:
            self.held.append(here)
        else:  # the posterior dropped some: keep the newest it holds
            self.held = (self.held + [here])[-held_now:]

    def covariance(self) -> np.ndarray | None:
        """``Σ_k s_k² A_k A_kᵀ`` at the posterior's estimate and reference (module doc)."""
        post = self.post
        ref = post.reference.load
        if ref is None or not self.windows:
            return None
        theta, P = post.theta, post.P
        p = len(theta)
        B = np.zeros((6, p, p))  # Σ_j (L_jk − L_ref,k) M_j
        for G, n, L in self.windows:
            M = moments_information(self.par, G, n, theta)
            if M is None or not np.all(np.isfinite(M)):
                continue
            B += (L - ref)[:, None, None] * (0.5 * (M + M.T))[None]
        C = np.zeros((p, p))
        for k in np.flatnonzero(self.sensitivity):
            A = P @ B[k]
            C += self.sensitivity[k] ** 2 * (A @ A.T)
        return 0.5 * (C + C.T)
