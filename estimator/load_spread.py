"""The spread of a ground calibration over the loads its angles follow
(docs/identification.md, "A ground calibration over loads the angles follow").

A constant-angle known-load posterior pools windows held at different static loads. Where the
angles move with the load — within the rig's 1-σ sensitivity bound ``s`` (per unit load on
each axis, ``identification.angle_load_sensitivity_deg_per_unit``) — each window's data are of
the angles at its own load, ``α(L_j) = α_ref + g (L_j − L_ref)``. The gains ``g_k`` (14 per
load axis) are unknown, 1 σ = ``s_k`` each: they are solved for beside the angles, not only
considered. Linearised at the estimate with each window's information ``M_j`` and gradient
``γ_j`` (from its moments), the joint information of ``[α_ref, u_k = g_k / s_k]`` is

    Λ = [[Λ_aa, s_k B_k], [s_k B_kᵀ, s_k s_l C_kl + δ_kl I]],
    Λ_aa = Σ_j M_j + P₀⁻¹,  B_k = Σ_j ΔL_jk M_j,  C_kl = Σ_j ΔL_jk ΔL_jl M_j

(``ΔL_j = L_j − L_ref``, ``P₀`` the first prior). The angles at the reference load then have
the marginal covariance ``Σ_aa = [Λ⁻¹]_aa`` and the estimate moves by one Gauss–Newton step of
the joint problem less the step of the angles alone,
``δ = (P_w − Σ_aa) Σ_j γ_j − Σ_au b`` with ``b_k = s_k Σ_j ΔL_jk γ_j`` and ``P_w = Λ_aa⁻¹``.
What the service states (``ReferenceLoad.reported``) is its own posterior plus ``Σ_aa − P_w``
(positive semi-definite: what not knowing the gains costs) about its estimate plus ``δ``.

Every term is of the same windows at the same estimate: the earlier rule,
``P Σ_k s_k² A_k A_kᵀ`` with ``A_k = P B_k`` and ``P`` the service's sequential posterior,
mixed a covariance accumulated at earlier estimates (and inflated by the random walk) with
windows' information recomputed at the last one; ``P B_k`` then no longer cancels where the
windows agree, and the stated σ grew with every window (flight rig, 120-s ground test:
9.1° on psi_F, 13.5° along one direction; 240 s: 18.4°). Solved for, the marginal can only
narrow as windows are added (more information about the same ``[α_ref, u]``): 0.18° → 0.14°
largest σ of the windows' own posterior from 120 to 240 s on the same test.

Bounded: the accepted windows' moments since the posterior's reference began (a reset, a
restore or a move to a flight trim starts it again), at most ``MAX_WINDOWS`` (the oldest
leave first); the held windows a run takes in with it are kept beside.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from .identification import moments_gradient_information

MAX_WINDOWS = 512  # accepted known-load windows kept (≈ 43 min of 5-s windows)


class LoadSpread:
    """The known-load posterior's load spread (module doc). ``after(rec, moments, load)``
    after every known-load run: a held window is kept for the run that takes it in, an
    accepted run's windows join the accepted ones and the posterior's ``reference.shift`` and
    ``reference.cov`` are computed afresh at its estimate."""

    def __init__(self, post: Any, par: Any, sensitivity: np.ndarray | None,
                 drift_rate: float = 0.0) -> None:
        # post: the SequentialPosterior (not imported: posterior imports this module)
        self.post, self.par = post, par
        self.sensitivity = np.zeros(6) if sensitivity is None else np.asarray(sensitivity, float)
        # the bound (1 σ, rad/s) on each angle's drift rate: time is one more axis, each
        # window at its own time, the reference the newest accepted window's
        self.drift_rate = float(drift_rate)
        # (moments, scored count, [static load (6), time])
        self.windows: deque[tuple[np.ndarray, int, np.ndarray]] = deque(maxlen=MAX_WINDOWS)
        self.held: list[tuple[np.ndarray, int, np.ndarray]] = []
        self._reference: object = post.reference

    def after(self, rec: Any, moments: tuple[np.ndarray, int],
              static_load: np.ndarray | None, t: float = 0.0) -> None:
        post = self.post
        if post.reference is not self._reference:  # reset, restored or carried: start again
            self.windows.clear()
            self.held = []
            self._reference = post.reference
        h = None if static_load is None else np.asarray(static_load, float)
        if h is None or h.shape != (6,) or not np.all(np.isfinite(h)):
            return
        here = (np.asarray(moments[0], float).copy(), int(moments[1]), np.append(h, float(t)))
        held_now = int(post.moments.windows_held)
        if rec.accepted:
            self.windows.extend(self.held)
            self.windows.append(here)
            self.held = []
            self.refresh()
        elif held_now == 0:
            self.held = []
        elif held_now == len(self.held) + 1:
            self.held.append(here)
        else:  # the posterior dropped some: keep the newest it holds
            self.held = (self.held + [here])[-held_now:]

    def covariance(self) -> np.ndarray | None:
        """The covariance the unknown gains add at the reference (module doc; None: no
        windows or no reference)."""
        adj = self.adjustment()
        return None if adj is None else adj[1]

    def refresh(self) -> None:
        """Set the posterior's ``reference.shift`` and ``reference.cov`` afresh."""
        adj = self.adjustment()
        ref = self.post.reference
        ref.shift, ref.cov = (None, None) if adj is None else adj

    def adjustment(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(δ, Σ_aa − P_w)`` at the posterior's estimate and reference (module doc)."""
        post = self.post
        ref = post.reference.load
        if ref is None or not self.windows:
            return None
        theta = np.asarray(post.theta, float)
        p = len(theta)
        # under a trend the drift is the structure test's (its rates move the posterior)
        rate = self.drift_rate if getattr(post, "trend", None) is None else 0.0
        bound = np.append(self.sensitivity, rate)
        ks = np.flatnonzero(bound > 0)
        if len(ks) == 0:
            return None
        # a window given by its load alone (the pooled calibration) is at time 0
        wins = [(G, n, L if len(L) > 6 else np.append(L, 0.0)) for G, n, L in self.windows]
        ref = np.append(ref, max(float(L[6]) for _, _, L in wins))
        P0 = getattr(post, "P0", None)
        lam_aa = np.zeros((p, p)) if P0 is None else np.linalg.inv(P0)
        grad = np.zeros(p)
        m = len(ks)
        B = np.zeros((m, p, p))  # s_k Σ_j ΔL_jk M_j
        C = np.zeros((m, m, p, p))  # s_k s_l Σ_j ΔL_jk ΔL_jl M_j
        b = np.zeros((m, p))  # s_k Σ_j ΔL_jk γ_j
        for G, n, L in wins:
            gm = moments_gradient_information(self.par, G, n, theta)
            if gm is None:
                continue
            g, M = gm[0], 0.5 * (gm[1] + gm[1].T)
            d = (L - ref)[ks] * bound[ks]
            lam_aa += M
            grad += g
            B += d[:, None, None] * M[None]
            C += (d[:, None] * d[None, :])[:, :, None, None] * M[None, None]
            b += d[:, None] * g[None]
        lam = np.zeros((p * (m + 1), p * (m + 1)))
        lam[:p, :p] = lam_aa
        for i in range(m):
            lam[:p, p * (i + 1):p * (i + 2)] = B[i]
            lam[p * (i + 1):p * (i + 2), :p] = B[i].T
            for j in range(m):
                lam[p * (i + 1):p * (i + 2), p * (j + 1):p * (j + 2)] = (
                    C[i, j] + (np.eye(p) if i == j else 0.0))
        try:
            S = np.linalg.inv(0.5 * (lam + lam.T))
            P_w = np.linalg.inv(lam_aa)
        except np.linalg.LinAlgError:
            return None
        S_aa = S[:p, :p]
        shift = (P_w - S_aa) @ grad - S[:p, p:] @ b.reshape(-1)
        w, V = np.linalg.eigh(0.5 * ((S_aa - P_w) + (S_aa - P_w).T))
        cov = (V * np.clip(w, 0.0, None)) @ V.T
        if not (np.all(np.isfinite(shift)) and np.all(np.isfinite(cov))):
            return None
        return shift, cov
