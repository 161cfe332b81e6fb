"""The simulated aircraft's physics (model.md §8): truth for the estimator to be scored on.

It deliberately shares no code path with `estimator/`: the cell axes come from
`scipy.spatial.transform.Rotation`, the wrench and hub matrices are built here from the rig
config, and a test cross-checks them against the estimator's S(alpha) and R.

Model. The rotor/transmission is a rigid body (6 DOF; per-axis effective masses and the
inertias of the config) on seven axial spring-damper cells along the TRUE axes u_i(alpha_true).
With q the small displacement of the body at its CG (translation; rotation) and d the motion
of the fuselage (rigid, translational base vibration), cell i carries

    T_i = -k_i s_i^T (q - [d; 0]) - c_i s_i^T (q' - [d'; 0]),   s_i = [u_i; p_i x u_i],

(s_i^T q is u_i^T dp_i for dp_i = dx + dtheta x p_i), so S T is the cells' wrench at the CG,
K = S diag(k) S^T and, with stiffness-proportional damping c_i = beta k_i, C = beta K. Newton-
Euler: M q'' = S T + R H + W_g + W_u + D q_drive, and the accelerometers read the specific
force f = a + omega' x r - g, so the balance I = M [f; omega'] = S T + R H + W_u + D q_drive
(report Eq 1.1) holds exactly at every sample (gravity W_g = M g enters both sides).

Discretisation. C = beta K gives classical normal modes (eigh(K, M)), each a damped oscillator
discretised exactly with expm at h = dt / substeps (first-order hold of the forcing between
substeps, so a harmonic load is not delayed by half a substep), then lifted to one map per
sample: xi_{k+1} = P xi_k + sum_j G_j f_{k,j}. Over a run of samples with the same true angles
the recursion is diagonalised and run by scipy.signal.lfilter over the whole run; short runs
(angles moving with the load) use a log-depth prefix scan. The run starts in static
equilibrium (the deflection under the initial loads and its rate; the base at rest).

Everything is computed in fixed blocks of samples, so the streaming `next_sample()` and the
off-line `simulate()` produce the same numbers bit for bit.
"""
from __future__ import annotations

import itertools
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy import linalg, signal
from scipy.spatial.transform import Rotation

from rsra.config.rig import G0, ConfigError, RigConfig
from rsra.config.rigfile import MISSING

from .scenarios import Scenario, check_against_rig, load_scenario

BLOCK_SIZE = 1000  # samples per computed block (fixed: it makes streaming == off-line exact)
LFILTER_MIN_RUN = 256  # runs of constant angles this long use lfilter, shorter ones a scan
MOUNT_CACHE_SIZE = 1024  # discretisations kept (one per distinct true-angle vector)
_SLOW_TERMS = 3  # sinusoids in each slow random variation
# the two rotation axes of each kind of cell, first then second (model.md §2 table)
_KIND_AXES = {2: "xy", 1: "xz", 0: "yz"}  # dominant nominal component -> rotation axes


@dataclass
class SimSample:
    """One sample period of physics (one SYNC). Noisy channels are before bus encoding."""

    index: int
    t: float  # simulated seconds since start
    T: np.ndarray  # (7,) noisy load-cell forces, N
    cell_status: np.ndarray  # (7,) uint8, bit 0 over-range (|T| > full scale)
    accel: np.ndarray  # (K, 3) noisy specific force, m/s^2, body axes
    omega: float  # rad/s
    azimuth: float  # rad in [0, 2 pi)
    H_balance: np.ndarray  # (6,) noisy reference-balance reading, body axes at the hub
    drive: np.ndarray  # (Q,) measured external loads
    # truth
    H_true: np.ndarray  # (6,) applied hub load, body axes, at the hub centre
    alpha_true: np.ndarray  # (14,) rad, model order
    T_true: np.ndarray  # (7,)
    accel_true: np.ndarray  # (K, 3)
    unmodelled: np.ndarray  # (6,) wrench at the CG of the unmodelled external load
    I_true: np.ndarray  # (6,) inertial loads [m f; I omega'] at the CG (left side of Eq 1.1)
    drive_true: np.ndarray  # (Q,)
    base_accel: np.ndarray  # (3,) fuselage-side (base) acceleration, m/s^2


SAMPLE_FIELDS = tuple(f.name for f in fields(SimSample))


# --------------------------------------------------------------------------- geometry (own)

def cell_axes_true(nominal_axes: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """u_i = R_second(a2) R_first(a1) n_i (7, 3), built with scipy's Rotation (extrinsic)."""
    nominal_axes = np.asarray(nominal_axes, float)
    alpha = np.asarray(alpha, float).reshape(-1, 2)
    kind = np.argmax(np.abs(nominal_axes), axis=1)
    u = np.empty_like(nominal_axes)
    for k, seq in _KIND_AXES.items():
        sel = np.flatnonzero(kind == k)
        if len(sel):
            u[sel] = Rotation.from_euler(seq, alpha[sel]).apply(nominal_axes[sel])
    return u


def wrench_matrix_true(positions: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """S (6, 7): column i = [u_i; p_i x u_i], the wrench at the CG of a unit cell force."""
    return np.vstack([axes.T, np.cross(positions, axes).T])


def hub_matrix(hub_position: np.ndarray, tilt_rad: float = 0.0, frame: str = "body") -> np.ndarray:
    """R (6, 6): the CG wrench of a hub load given in `frame` ("body" or "shaft")."""
    if frame == "shaft":
        C = Rotation.from_euler("y", -tilt_rad).as_matrix()  # forward tilt: Ry(-tilt), z down
    elif frame == "body":
        C = np.eye(3)
    else:
        raise ValueError(f"hub frame must be 'body' or 'shaft', not {frame!r}")
    R = np.zeros((6, 6))
    R[:3, :3] = C
    R[3:, 3:] = C
    R[3:, :3] = np.cross(np.asarray(hub_position, float), C.T).T  # moment of each force column
    return R


def skew3(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: skew3(a) @ b == a x b."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def minimum_strain_energy_split(S: np.ndarray, k: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """T minimising sum T_i^2 / (2 k_i) subject to S T + wrench = 0 (report Phase II)."""
    K = (S * k) @ S.T
    return -(k[:, None] * S.T) @ np.linalg.solve(K, np.asarray(wrench, float).T)


# --------------------------------------------------------------------------- the mounts

MODE_HZ_MIN = 1e-3  # a mount mode slower than this is no mount (the cells carry nothing)
MODE_RAD_PER_STEP_MAX = 1e6  # a mode this many radians per substep: no mass behind the cells


def _check_modes(w2: np.ndarray, h: float) -> None:
    """The mount modes the configured stiffness and masses give are ones the simulator can
    integrate: a ConfigError naming the keys to change, not a numerical failure later."""
    keys = "cells[].stiffness_N_per_m, mass.effective_mass_kg, mass.inertia_kg_m2"
    if not np.all(np.isfinite(w2)) or float(np.max(w2)) * h * h > MODE_RAD_PER_STEP_MAX ** 2:
        raise ConfigError("mass.effective_mass_kg", MISSING, "with the cells' stiffness the "
                          "mount modes are too fast to simulate (a mass or inertia near zero)",
                          f"give real masses and inertias ({keys})")
    f_min = math.sqrt(max(float(np.min(w2)), 0.0)) / (2 * math.pi)
    if f_min < MODE_HZ_MIN:
        raise ConfigError("cells[].stiffness_N_per_m", MISSING, f"the slowest mount mode is "
                          f"{f_min:.3g} Hz (below {MODE_HZ_MIN:g} Hz): the cells are too soft "
                          "for the masses to be a mount", "raise the cells' stiffness_N_per_m "
                          "(the packaged rig: 1e8 N/m) or check the masses")


class _Mounts:
    """The cells at one set of true angles: S, K, normal modes and the lifted sample map."""

    def __init__(self, phys: MountDynamics, alpha: np.ndarray):
        self.alpha = alpha
        self.S = wrench_matrix_true(phys.positions, cell_axes_true(phys.nominal_axes, alpha))
        self.K = (self.S * phys.k) @ self.S.T
        self.C = phys.beta * self.K
        if phys.quasi_static:
            return
        with np.errstate(all="ignore"):  # (a 1e-300 mass: judged below, not warned about)
            w2, V = linalg.eigh(self.K, np.diag(phys.mass_diag))  # V^T M V = I, V^T K V = diag(w2)
        _check_modes(w2, phys.dt / phys.substeps)
        self.omega_n = np.sqrt(w2)
        self.V = V
        self.VtM = V.T * phys.mass_diag  # modal coordinates eta = V^T M q
        n, h = phys.substeps, phys.dt / phys.substeps
        m = len(w2)
        # per-mode eta'' + beta w2 eta' + w2 eta = f, FOH exact discretisation (Franklin-Powell)
        em = np.zeros((m, 4, 4))
        em[:, 0, 1] = h
        em[:, 1, 0] = -w2 * h
        em[:, 1, 1] = -phys.beta * w2 * h
        em[:, 1, 2] = h
        em[:, 2, 3] = 1.0
        E = linalg.expm(em)
        Ph, G0_, Gb = E[:, :2, :2], E[:, :2, 2], E[:, :2, 3]
        Ga = G0_ - Gb  # weight of f_j; Gb weighs f_{j+1}
        # lifted over the n substeps of a sample: x_n = P x_0 + sum_j Gt_j f_j, j = 0..n,
        # Gt_j = Ph^(n-1-j) Ga [j < n] + Ph^(n-j) Gb [j > 0]
        powers = np.empty((n + 1, m, 2, 2))
        powers[0] = np.eye(2)
        for i in range(n):
            powers[i + 1] = Ph @ powers[i]
        PGa = powers @ Ga[None, :, :, None]  # (n + 1, m, 2, 1): Ph^i Ga
        PGb = powers @ Gb[None, :, :, None]
        Gt = np.zeros((n + 1, m, 2))
        Gt[:n] += PGa[n - 1::-1, ..., 0]  # j = 0..n-1 takes Ph^(n-1-j) Ga
        Gt[1:] += PGb[n - 1::-1, ..., 0]  # j = 1..n takes Ph^(n-j) Gb
        self.Gt = Gt.transpose(1, 0, 2).copy()  # (6, n + 1, 2)
        P = powers[n]  # (6, 2, 2) one-sample map per mode
        lam, W = np.linalg.eig(P)
        if np.any(np.linalg.cond(W) > 1e8):
            raise ValueError("mount modes near critical damping: lower simulator.damping_ratio")
        self.lam = lam  # (6, 2)
        self.W = W  # (6, 2, 2) columns = eigenvectors
        self.Winv = np.linalg.inv(W)

    def propagate(self, q0: np.ndarray, qd0: np.ndarray, force: np.ndarray, n: int):
        """States at the L sample instants of a run and at its end.

        force: (L n + 1, 6) generalised force at the CG at every substep point of the run
        (the last point is the next sample's first). Returns q, qd (L + 1, 6).
        """
        L = (force.shape[0] - 1) // n
        f = force @ self.V  # modal forces (L n + 1, 6)
        f_in = f[:-1].reshape(L, n, 6)  # substeps 0..n-1 of each sample
        f_next = f[n::n]  # substep n = the next sample's first point
        g = np.empty((L, 6, 2))
        for c in range(2):  # lifted input: sum_j G_j f_j
            g[:, :, c] = (np.einsum("ljm,mj->lm", f_in, self.Gt[:, :n, c])
                          + f_next * self.Gt[:, n, c])
        xi0 = np.stack([self.VtM @ q0, self.VtM @ qd0], axis=-1)  # (6, 2)
        xi = np.empty((L + 1, 6, 2))
        xi[0] = xi0
        # diagonalised: z_{k+1} = lam z_k + gz_k per mode and eigenvector (12 complex scalars)
        z0 = np.einsum("mab,mb->ma", self.Winv, xi0)
        gz = (self.Winv[None, :, :, 0] * g[:, :, None, 0]
              + self.Winv[None, :, :, 1] * g[:, :, None, 1])  # (L, 6, 2)
        if L >= LFILTER_MIN_RUN:
            Z = np.empty((L, 6, 2), complex)
            for mi in range(6):
                for c in range(2):
                    lam = self.lam[mi, c]
                    Z[:, mi, c] = signal.lfilter([1.0], [1.0, -lam], gz[:, mi, c],
                                                 zi=[lam * z0[mi, c]])[0]
        else:
            Z = _first_order_scan(self.lam, gz, z0)
        xi[1:] = (self.W[None, :, :, 0] * Z[:, :, None, 0]
                  + self.W[None, :, :, 1] * Z[:, :, None, 1]).real
        q = xi[..., 0] @ self.V.T
        qd = xi[..., 1] @ self.V.T
        return q, qd


def _first_order_scan(lam: np.ndarray, x: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """y_k = lam y_{k-1} + x_k (k = 0..L-1, y_{-1} = y0) for many scalars at once: a
    log-depth prefix scan (Hillis-Steele), so short runs cost no Python loop per sample."""
    y = x.astype(complex)
    y[0] += lam * y0
    p = lam.copy()
    s = 1
    while s < len(y):
        y[s:] += p * y[:-s]  # the right side is evaluated first: old values
        p = p * p
        s *= 2
    return y


# --------------------------------------------------------------------------- load model helpers

def _slow_variation(rng: np.random.Generator, shape: tuple, period_s: float):
    """Random smooth functions m(t) with |m| <= 1: sums of a few sinusoids near 1/period."""
    f = rng.uniform(0.5, 1.5, shape + (_SLOW_TERMS,)) / period_s
    p = rng.uniform(0.0, 2 * np.pi, shape + (_SLOW_TERMS,))
    c = rng.uniform(0.2, 1.0, shape + (_SLOW_TERMS,))
    c /= c.sum(axis=-1, keepdims=True)
    return 2 * np.pi * f, p, c


def _eval_slow(t: np.ndarray, w: np.ndarray, p: np.ndarray, c: np.ndarray) -> np.ndarray:
    """m(t) (len(t), *shape)."""
    return np.einsum("...j,t...j->t...", c, np.sin(t[:, *([None] * w.ndim)] * w + p))


def _interp_samples(v: np.ndarray, frac: np.ndarray, B: int, n: int) -> np.ndarray:
    """Linear interpolation of (B + 1, 6) sample-instant values to the B n + 1 substeps."""
    out = np.empty((B * n + 1, v.shape[1]))
    np.multiply((v[1:] - v[:-1])[:, None, :], frac, out=out[:-1].reshape(B, n, -1))
    out[:-1].reshape(B, n, -1)[...] += v[:-1, None, :]
    out[-1] = v[-1]
    return out


class _Piecewise:
    """Piecewise-linear channels over one cycle, with their exact running integral."""

    def __init__(self, knots: np.ndarray, values: np.ndarray, period: float):
        self.knots = np.asarray(knots, float)
        self.values = np.asarray(values, float).reshape(len(self.knots), -1)
        self.period = period
        seg = np.diff(self.knots)[:, None] * 0.5 * (self.values[1:] + self.values[:-1])
        self.cum = np.vstack([np.zeros((1, self.values.shape[1])), np.cumsum(seg, axis=0)])

    def _locate(self, tc: np.ndarray):
        i = np.clip(np.searchsorted(self.knots, tc, side="right") - 1, 0, len(self.knots) - 2)
        t0 = self.knots[i]
        span = self.knots[i + 1] - t0
        return i, tc - t0, span

    def value(self, tc: np.ndarray) -> np.ndarray:
        i, dt, span = self._locate(tc)
        v0, v1 = self.values[i], self.values[i + 1]
        return v0 + (v1 - v0) * (dt / span)[:, None]

    def integral(self, t: np.ndarray) -> np.ndarray:
        """int_0^t of the periodic function (absolute time)."""
        cycles = np.floor(t / self.period)
        tc = t - cycles * self.period
        i, dt, span = self._locate(tc)
        v0, v1 = self.values[i], self.values[i + 1]
        part = self.cum[i] + v0 * dt[:, None] + 0.5 * (v1 - v0) * (dt * dt / span)[:, None]
        return cycles[:, None] * self.cum[-1] + part


class _BaseVibration:
    """Fuselage-side vibration of the three cell-base axes: the acceleration is a Butterworth
    band-pass (2 x order poles) of white noise, so the displacement (that / s^2) is strictly
    proper with relative degree >= 4 and d, d', d'' are all outputs of its states. Exact ZOH
    discretisation at the substep h, run in modal form (distinct poles: one complex
    first-order recursion per conjugate pair, lfilter over a block), starting at rest.
    Piecewise-constant noise of variance sigma^2 is white noise of intensity sigma^2 h far
    below 1/h, so sigma comes from the (well-conditioned) continuous Lyapunov equation."""

    def __init__(self, band_hz: tuple[float, float], h: float, rms: float, rng, order: int = 4):
        b, a = signal.butter(order, [2 * np.pi * band_hz[0], 2 * np.pi * band_hz[1]],
                             btype="band", analog=True)
        gain = b[0]  # acceleration / noise = gain s^order / a(s)
        A, B, C, _ = signal.tf2ss(np.r_[gain, np.zeros(order - 2)], a)  # d = gain s^(o-2) / a
        Cs = np.vstack([C, C @ A, C @ A @ A])  # d, d', d''
        P = linalg.solve_continuous_lyapunov(A, -B @ B.T)
        self.sigma = rms / math.sqrt(float(Cs[2] @ P @ Cs[2]) * h)
        nx = A.shape[0]
        em = np.zeros((nx + 1, nx + 1))
        em[:nx, :nx], em[:nx, nx:] = A * h, B * h
        E = linalg.expm(em)
        lam, V = np.linalg.eig(E[:nx, :nx])
        keep = np.flatnonzero(lam.imag > 0)  # one of each conjugate pair (the input is real)
        if 2 * len(keep) != nx:
            raise ValueError("base-vibration filter: expected complex pole pairs")
        self.lam = lam[keep]
        self.gam = (np.linalg.solve(V, E[:nx, nx:])[keep, 0])
        CV = 2 * (Cs @ V[:, keep])  # y = sum over kept modes of Re(CV z)
        self.CV_re, self.CV_im = CV.real.copy(), CV.imag.copy()
        self.z = np.zeros((len(keep), 3), complex)  # (mode, axis), at rest
        self.rng = rng

    def block(self, npts_in: int) -> np.ndarray:
        """d, d', d'' (3, npts_in + 1, 3 axes) at the points of one block and the next one."""
        w = self.rng.standard_normal((3, npts_in)) * self.sigma  # (axis, point)
        m = len(self.lam)
        zs = np.empty((m, 3, npts_in + 1), complex)
        zs[:, :, 0] = self.z
        for i, lam in enumerate(self.lam):
            zs[i, :, 1:] = signal.lfilter([1.0], [1.0, -lam], self.gam[i] * w, axis=-1,
                                          zi=(lam * self.z[i])[:, None])[0]
        self.z = zs[:, :, -1].copy()
        flat = zs.reshape(m, -1)
        y = self.CV_re @ flat.real - self.CV_im @ flat.imag  # Re(CV z): (output, axis * point)
        return y.reshape(3, 3, npts_in + 1).transpose(0, 2, 1)


# --------------------------------------------------------------------------- the aircraft

def _draw_parameters(sc: Scenario, blades: int, Q: int, rng: np.random.Generator,
                     angles_rng: np.random.Generator) -> dict:
    """All per-seed random parameters, drawn in a fixed order whatever the variant (the order
    is the contract: every seed's aircraft stays the same); the base angles from their own
    stream (the same aircraft in every scenario). The load model's and the true angles' draws
    interleave, so they are drawn here, in one place, and handed to each."""
    d: dict = {}
    d["harm_orders"] = np.array([h.resolve_order(blades) for h in sc.harmonics], int)
    d["harm_amp"] = np.array([rng.uniform(h.amplitude_min, h.amplitude_max)
                              for h in sc.harmonics]).reshape(-1, 6)
    d["harm_phase"] = rng.uniform(0, 2 * np.pi, (len(sc.harmonics), 6))
    d["harm_slow"] = [(_slow_variation(rng, (6,), h.variation_period_s),
                       _slow_variation(rng, (6,), h.variation_period_s))
                      for h in sc.harmonics]
    d["omega_slow"] = _slow_variation(rng, (), sc.rotor.omega_period_s)
    ang = sc.angles
    rng.uniform(-ang.range_rad, ang.range_rad, 14)  # the former draw: the rest unchanged
    base_draw = angles_rng.uniform(-ang.range_rad, ang.range_rad, 14)
    d["alpha_base"] = base_draw if isinstance(ang.base, str) else np.array(ang.base, float)
    step_signs = rng.choice([-1.0, 1.0], (max(len(ang.step_at_s), 1), 14))
    d["alpha_steps"] = step_signs[: len(ang.step_at_s)] * ang.step_rad
    lin_signs = rng.choice([-1.0, 1.0], (14, 6))
    d["alpha_gain"] = lin_signs * ang.linear_rad_per_unit  # (14, 6) rad per N, N·m
    d["drive_phase"] = rng.uniform(0, 2 * np.pi, Q)
    d["drive_order"] = (blades if sc.drive.order == "blades" else int(sc.drive.order))
    d["cell_gain"] = np.zeros(14)
    if ang.mode == "cell_load":  # the last draw of this stream: the others unchanged
        d["cell_gain"] = rng.choice([-1.0, 1.0], 14) * ang.cell_gain_rad_per_N
    return d


class MountDynamics:
    """The transmission on its seven cells (model.md §8): the rig's masses, cell axes,
    stiffness and damping, one discretisation per set of true angles (cached, bounded), and
    the body's response to a block's CG wrench and base motion — the cell forces and the
    body's acceleration, the state carried from block to block."""

    def __init__(self, cfg: RigConfig, scenario: Scenario, dt: float, substeps: int):
        self.dt, self.substeps = dt, substeps
        self.quasi_static = scenario.quasi_static
        # rig: positions, axes, stiffness, damping, masses (config only)
        self.positions = np.array([c.position_m for c in cfg.cells])
        self.nominal_axes = np.array([c.nominal_axis for c in cfg.cells])
        self.k = np.array([c.stiffness_N_per_m for c in cfg.cells])
        sim = cfg.simulator  # stiffness-proportional: zeta = beta w / 2, zeta_ref at f_ref
        self.beta = 2 * sim.damping_ratio / (2 * np.pi * sim.damping_reference_hz)
        self.c = self.beta * self.k
        self.mass_diag = np.concatenate([cfg.effective_mass_kg, cfg.inertia_kg_m2])
        self.acc_pos = np.array([a.position_m for a in cfg.accelerometers])
        rig_err = scenario.rig_errors
        # the true hub centre (a scenario's rig error moves it off the configured one)
        self.R_body = hub_matrix(np.asarray(cfg.hub_centre_m) + rig_err.hub_offset_m
                                 if np.any(rig_err.hub_offset_m) else cfg.hub_centre_m,
                                 cfg.shaft_tilt_rad, "body")
        self.D = (np.array([e.wrench_per_unit for e in cfg.external_loads]).T
                  if cfg.external_loads else np.zeros((6, 0)))
        self.Q = self.D.shape[1]
        self.g_vec = np.array([0.0, 0.0, G0]) if scenario.gravity else np.zeros(3)  # z down
        self.W_g = np.concatenate([cfg.effective_mass_kg * self.g_vec, np.zeros(3)])
        self._mounts: OrderedDict[bytes, _Mounts] = OrderedDict()
        self._state: tuple[np.ndarray, np.ndarray] | None = None

    def mode_frequencies_hz(self, alpha: np.ndarray) -> np.ndarray:
        """The six mount-mode frequencies at the angles ``alpha``."""
        S = wrench_matrix_true(self.positions, cell_axes_true(self.nominal_axes, alpha))
        w2 = linalg.eigh((S * self.k) @ S.T, np.diag(self.mass_diag), eigvals_only=True)
        return np.sqrt(w2) / (2 * np.pi)

    def mount(self, alpha: np.ndarray) -> _Mounts:
        key = alpha.tobytes()
        m = self._mounts.get(key)
        if m is None:
            m = _Mounts(self, alpha.copy())
            self._mounts[key] = m
            if len(self._mounts) > MOUNT_CACHE_SIZE:
                self._mounts.popitem(last=False)
        else:
            self._mounts.move_to_end(key)
        return m

    def respond(self, alpha: np.ndarray, w: np.ndarray, d: np.ndarray,
                v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The true cell forces (B, 7) and the body's acceleration q'' (B, 6) at the B sample
        instants of a block: ``alpha`` the true angles per sample, ``w`` the CG wrench and
        ``d``, ``v`` the base displacement and velocity at the B n + 1 substep points."""
        B, n, dt = len(alpha), self.substeps, self.dt
        S0 = slice(0, B * n, n)  # substep 0 of every sample: the sample instants
        T_true = np.empty((B, 7))
        qdd = np.zeros((B, 6))
        change = np.flatnonzero(np.any(alpha[1:] != alpha[:-1], axis=1)) + 1
        starts = [0, *change.tolist(), B]  # runs of samples with the same true angles
        for a_, b_ in itertools.pairwise(starts):
            m = self.mount(alpha[a_])
            wk = w[a_ * n: b_ * n + 1: n][: b_ - a_]
            if self.quasi_static:
                q = np.linalg.solve(m.K, wk.T).T  # no inertia: static deflection
                T_true[a_:b_] = -self.k * (q @ m.S)
                continue  # qdd stays 0: the body does not accelerate
            if self._state is None:
                # start in (quasi-)static equilibrium: the deflection under the loads at t = 0
                # and its rate (K q' = w'(0), a 2nd-order one-sided difference over substeps),
                # so the harmonics start without a mount transient; the base is at rest
                w_rate = (-3 * w[0] + 4 * w[1] - w[2]) / (2 * dt / n)
                self._state = (np.linalg.solve(m.K, w[0]), np.linalg.solve(m.K, w_rate))
            seg = slice(a_ * n, b_ * n + 1)
            # M q'' + C q' + K q = w + K [d; 0] + C [d'; 0]: the base drives the cells
            force = w[seg] + d[seg] @ m.K[:, :3].T + v[seg] @ m.C[:, :3].T
            q, qd = m.propagate(self._state[0], self._state[1], force, n)
            self._state = (q[-1], qd[-1])
            q, qd = q[:-1], qd[:-1]
            dq = q.copy()
            dq[:, :3] -= d[S0][a_:b_]
            dqd = qd.copy()
            dqd[:, :3] -= v[S0][a_:b_]
            T = -self.k * (dq @ m.S) - self.c * (dqd @ m.S)
            T_true[a_:b_] = T
            qdd[a_:b_] = (T @ m.S.T + wk) / self.mass_diag  # Newton-Euler at the sample instant
        return T_true, qdd

    def inertial(self, qdd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inertial loads M [a - g; omega'] (B, 6) and the specific force at each
        accelerometer (B, K, 3) from the body's acceleration q''."""
        B = len(qdd)
        I_true = self.mass_diag * qdd - self.W_g  # M [a - g; omega']
        if self.quasi_static:
            I_true = -np.broadcast_to(self.W_g, (B, 6)).copy()
        lin, ang = qdd[:, :3], qdd[:, 3:]
        accel_true = (lin[:, None, :] + np.cross(ang[:, None, :], self.acc_pos[None])
                      - self.g_vec)  # specific force at each accelerometer (K, 3)
        return I_true, accel_true


class LoadModel:
    """The hub loads a scenario applies (model.md §8): the static schedule and manoeuvres,
    the rotor's speed and azimuth, the harmonics (slowly varying), turbulence, the shaker,
    the unmodelled load and the external (drive) loads, at the substep points of a block."""

    def __init__(self, cfg: RigConfig, scenario: Scenario, draws: dict, dt: float,
                 substeps: int, Q: int, r_turb: np.random.Generator | None):
        self.scenario = scenario
        self.blades = cfg.rotor.blades
        self.omega0 = cfg.rotor.omega_nominal_rad_s
        self.Q = Q
        # scenario axes -> body axes (block-diagonal)
        self.load_frame = hub_matrix(np.zeros(3), cfg.shaft_tilt_rad, scenario.loads.frame)
        self.harm_orders = draws["harm_orders"]
        self.harm_amp = draws["harm_amp"]
        self.harm_phase = draws["harm_phase"]
        self.harm_slow = draws["harm_slow"]
        self.omega_slow = draws["omega_slow"]
        self.drive_phase = draws["drive_phase"]
        self.drive_order = draws["drive_order"]
        self._build_schedules()
        self._turb = None
        if r_turb is not None:
            tb = scenario.turbulence
            # band-passed white noise of unit RMS on 3 + 3 axes (forces, moments)
            self._turb = [_BaseVibration(tb.band_hz, dt / substeps, 1.0, r_turb)
                          for _ in range(2)]

    def _build_schedules(self) -> None:
        sc = self.scenario
        L, D = sc.loads, sc.duration_s
        n = len(L.conditions)
        if n == 1:
            knots, vals = [0.0, D], [L.conditions[0], L.conditions[0]]
        else:
            knots, vals = [], []
            for i, cnd in enumerate(L.conditions):
                knots += [i * L.hold_s, (i + 1) * L.hold_s - L.ramp_s]
                vals += [cnd, cnd]
            knots.append(D)
            vals.append(L.conditions[0])  # ramp back to the first condition: the cycle repeats
        self.static_schedule = _Piecewise(np.array(knots), np.array(vals), D)
        self.shaker_freq = self.shaker_amp = None
        sh = sc.shaker
        if sh is not None:
            kt, fv, av = [], [], []
            t0 = 0.0
            for ax in sh.axes:
                for lev in sh.levels:
                    a = np.zeros(6)
                    a[ax] = lev
                    z = np.zeros(6)
                    kt += [t0, t0 + sh.ramp_s, t0 + sh.ramp_s + sh.sweep_s,
                           t0 + 2 * sh.ramp_s + sh.sweep_s]
                    fv += [sh.f_start_hz, sh.f_start_hz, sh.f_stop_hz, sh.f_stop_hz]
                    av += [z, a, a, z]
                    t0 += sh.segment_s
            kt.append(D)
            fv.append(sh.f_start_hz)  # the frequency returns during the gap (amplitude zero)
            av.append(np.zeros(6))
            self.shaker_freq = _Piecewise(np.array(kt), np.array(fv), D)
            self.shaker_amp = _Piecewise(np.array(kt), np.array(av), D)

    def _rotor(self, t: np.ndarray):
        """Omega (rad/s) and rotor turns (azimuth / 2 pi, unreduced) at times t."""
        sc = self.scenario
        if sc.rotor.follow_shaker:
            sf = self.shaker_freq
            assert sf is not None  # (follow_shaker without a [shaker] is refused at load)
            f = sf.value(t % sc.duration_s)[:, 0]
            turns = sf.integral(t)[:, 0] / self.blades
            return 2 * np.pi * f / self.blades, turns
        v, g = sc.rotor.omega_variation, sc.rotor.governor_amplitude
        if v == 0.0 and g == 0.0:
            return np.full(t.shape, self.omega0), self.omega0 / (2 * np.pi) * t
        eps = np.zeros(t.shape)
        integ = np.zeros(t.shape)
        if v != 0.0:
            w, p, c = self.omega_slow
            arg = t[:, None] * w + p
            eps = v * (np.sin(arg) @ c)
            # exact integral of Omega0 (1 + eps): azimuth is continuous whatever the variation
            integ = v * ((np.cos(p) - np.cos(arg)) / w) @ c
        if g != 0.0:  # the governor's oscillation: g sin(wg t), its integral exact too
            wg = 2 * np.pi * sc.rotor.governor_hz
            eps = eps + g * np.sin(wg * t)
            integ = integ + g * (1.0 - np.cos(wg * t)) / wg
        return self.omega0 * (1 + eps), self.omega0 / (2 * np.pi) * (t + integ)

    def _rotor_substeps(self, t_samp: np.ndarray, ts: np.ndarray, n: int):
        """Omega at the sample instants and rotor turns at the substeps. A slow speed
        variation is evaluated at the sample instants and its azimuth correction interpolated
        linearly in between (exact at every sample instant)."""
        sc = self.scenario
        if sc.rotor.follow_shaker or (sc.rotor.omega_variation == 0.0
                                      and sc.rotor.governor_amplitude == 0.0):
            omega, turns = self._rotor(ts)
            return omega[::n], turns
        omega, turns_s = self._rotor(t_samp)
        corr = turns_s - self.omega0 / (2 * np.pi) * t_samp  # slow part of the azimuth
        B = len(t_samp) - 1
        frac = (np.arange(n) / n)[None, :, None]
        corr_sub = _interp_samples(corr[:, None], frac, B, n)[:, 0]
        return omega, self.omega0 / (2 * np.pi) * ts + corr_sub

    def _static(self, t: np.ndarray) -> np.ndarray:
        """Static part of the hub load (schedule + manoeuvres), scenario axes (len(t), 6)."""
        sc = self.scenario
        tc = t % sc.duration_s
        H = self.static_schedule.value(tc)
        for m in sc.manoeuvres:
            inside = np.flatnonzero((tc >= m.start_s) & (tc < m.start_s + m.duration_s))
            if len(inside):
                x = (tc[inside] - m.start_s) / m.duration_s
                H[inside] += 0.5 * (1 - np.cos(2 * np.pi * x))[:, None] * m.peak  # raised cosine
        return H

    def _harmonic_amplitudes(self, t: np.ndarray) -> np.ndarray:
        """Complex amplitudes (len(t), n_harm, 6) of the harmonics, slowly varying."""
        out = np.empty((len(t), len(self.harm_orders), 6), complex)
        for j, h in enumerate(self.scenario.harmonics):
            amp = np.broadcast_to(self.harm_amp[j], (len(t), 6))
            ph = np.broadcast_to(self.harm_phase[j], (len(t), 6))
            (wa, pa, ca), (wp, pp, cp) = self.harm_slow[j]
            if h.amplitude_variation:
                amp = amp * (1 + h.amplitude_variation * _eval_slow(t, wa, pa, ca))
            if h.phase_variation_rad:
                ph = ph + h.phase_variation_rad * _eval_slow(t, wp, pp, cp)
            out[:, j] = amp * np.exp(1j * ph)
        return out

    def loads(self, t_samp: np.ndarray, ts: np.ndarray, n: int):
        """Hub loads at substep points ts (body axes), the phase-shifted copy for the
        unmodelled load, the static part, Omega and rotor turns at the substeps."""
        sc = self.scenario
        omega, turns = self._rotor_substeps(t_samp, ts, n)
        static = self._static(ts)
        H = static.copy()
        shifted = None
        um = sc.unmodelled
        if um.enabled:
            shifted = math.cos(um.phase_rad) * static  # slow content: scaled by cos(phase)
            rot = np.exp(1j * um.phase_rad)
        if len(self.harm_orders):
            A = self._harmonic_amplitudes(t_samp)  # at the B + 1 sample instants
            B = len(t_samp) - 1
            frac = (np.arange(n) / n)[None, :, None]
            for j, order in enumerate(self.harm_orders):
                theta = 2 * np.pi * np.mod(turns * order, 1.0)
                cos_t, sin_t = np.cos(theta)[:, None], np.sin(theta)[:, None]
                targets = [(H, A[:, j])]
                if shifted is not None:
                    targets.append((shifted, A[:, j] * rot))
                for target, amp in targets:
                    re = _interp_samples(amp.real, frac, B, n)  # slow amplitude: linear in time
                    im = _interp_samples(amp.imag, frac, B, n)
                    target += re * cos_t - im * sin_t  # Re(A e^{i theta})
        if self._turb is not None:  # broadband hub loads outside the filter's load model
            nb = len(ts) - 1
            turb = np.hstack([tv.block(nb)[2] for tv in self._turb])  # (B n + 1, 6)
            H += turb * sc.turbulence.rms
        if sc.shaker is not None:
            assert self.shaker_amp is not None and self.shaker_freq is not None  # (built with it)
            tc = ts % sc.duration_s
            amp = self.shaker_amp.value(tc)
            phase = 2 * np.pi * np.mod(self.shaker_freq.integral(ts)[:, 0], 1.0)
            H += amp * np.cos(phase)[:, None]
            if shifted is not None:
                shifted += amp * np.cos(phase + um.phase_rad)[:, None]
        H = H @ self.load_frame.T  # scenario axes -> body axes
        static = static @ self.load_frame.T
        Wu = np.zeros_like(H)
        if shifted is not None:
            shifted = shifted @ self.load_frame.T
            Wu[:, 0] = um.x_N_per_N_X * shifted[:, 0]
            Wu[:, 3] = um.roll_Nm_per_N_Y * shifted[:, 1]
        return H, Wu, static, omega, turns

    def drive(self, turns: np.ndarray) -> np.ndarray:
        if not self.Q:
            return np.zeros((len(turns), 0))
        dr = self.scenario.drive
        ph = 2 * np.pi * np.mod(turns * self.drive_order, 1.0)
        return dr.static + dr.amplitude * np.cos(ph[:, None] + self.drive_phase)


class TrueAngles:
    """The true deformation angles in time (model.md §8): the aircraft's base angles, and
    as the scenario says steps, a linear dependence on the static load, each angle with its
    own cell's load, or a slow drift — held on the resolution grid (one discretisation of
    the mounts per value)."""

    def __init__(self, scenario: Scenario, draws: dict, mounts: MountDynamics):
        self.scenario = scenario
        self._mounts = mounts  # (the cell_load mode splits the static wrench over the cells)
        self.alpha_base = draws["alpha_base"]
        self.alpha_steps = draws["alpha_steps"]
        self.alpha_gain = draws["alpha_gain"]
        self.cell_gain = draws["cell_gain"]

    def at(self, t: np.ndarray, static_body: np.ndarray) -> np.ndarray:
        """The true angles (len(t), 14) at the sample times ``t``, the static hub load
        ``static_body`` (body axes) at those times."""
        ang = self.scenario.angles
        alpha = np.broadcast_to(self.alpha_base, (len(t), 14)).copy()
        if ang.mode == "step":
            for ts_, step in zip(ang.step_at_s, self.alpha_steps):
                alpha[t >= ts_] += step
        elif ang.mode == "linear":
            d = static_body @ self.alpha_gain.T
            res = ang.resolution_rad
            alpha += res * np.rint(d / res)  # held on a grid: one discretisation per value
        elif ang.mode == "cell_load":
            # each angle moves with its own cell's static load: the minimum-strain-energy split
            # of the static CG wrench at the base angles (S T + R H + W_g = 0 at rest)
            mt = self._mounts
            S = wrench_matrix_true(mt.positions, cell_axes_true(mt.nominal_axes, self.alpha_base))
            T = minimum_strain_energy_split(S, mt.k, static_body @ mt.R_body.T + mt.W_g).T
            d = T[:, np.arange(14) // 2] * self.cell_gain
            res = ang.resolution_rad
            alpha += res * np.rint(d / res)
        elif ang.mode == "drift" and ang.drift_angles:
            # linear in time (a temperature-like drift), held on the resolution grid
            res = ang.resolution_rad
            d = (ang.drift_rad / ang.drift_over_s) * np.asarray(t, float)
            alpha[:, list(ang.drift_angles)] += (res * np.rint(d / res))[:, None]
        return alpha


class SensorModels:
    """What the instruments read of the truth (model.md §8): each load cell's, accelerometer's,
    balance's and drive-load sensor's noise (from their accuracy in the config, each from its
    own random stream), the balance's scale and alignment error, the cells' over-range bit."""

    def __init__(self, cfg: RigConfig, scenario: Scenario, rng: dict):
        self.noise = scenario.noise
        self._rng = rng  # "cell", "acc", "bal", "drive": one stream each
        self.cell_fs = np.array([c.full_scale_N for c in cfg.cells])
        self.cell_sigma = np.array([c.full_scale_N * c.accuracy_fs for c in cfg.cells])
        self.acc_sigma = np.array([a.full_scale_g * G0 * a.accuracy_fs for a in cfg.accelerometers])
        b = cfg.balance
        fs = np.array([b.full_scale_force_N] * 3 + [b.full_scale_moment_Nm] * 3)
        self.balance_sigma = fs * b.accuracy_fs
        rig_err = scenario.rig_errors
        self.balance_read = None  # H_b = balance_read @ H_true when the balance is in error
        if np.any(rig_err.balance_scale) or np.any(rig_err.balance_align_rad):
            Rp = np.eye(3) + skew3(rig_err.balance_align_rad)
            Dm = np.zeros((6, 6))
            Dm[:3, :3] = Rp @ np.diag(1 + rig_err.balance_scale[:3])
            Dm[3:, 3:] = Rp @ np.diag(1 + rig_err.balance_scale[3:])
            self.balance_read = np.linalg.inv(Dm)
        self.drive_sigma = np.array([e.sigma for e in cfg.external_loads])

    def read(self, T_true: np.ndarray, accel_true: np.ndarray, H_true: np.ndarray,
             drive_true: np.ndarray):
        """(T, accel, H_balance, drive, cell_status) as read of a block's truth."""
        B, K, Q = len(T_true), accel_true.shape[1], drive_true.shape[1]
        if self.noise:
            r = self._rng
            T = T_true + r["cell"].standard_normal((B, 7)) * self.cell_sigma
            acc = accel_true + r["acc"].standard_normal((B, K, 3)) * self.acc_sigma[None, :, None]
            Hb = H_true + r["bal"].standard_normal((B, 6)) * self.balance_sigma
            if self.balance_read is not None:
                Hb = (H_true @ self.balance_read.T
                      + (Hb - H_true))  # the balance's reading error, its noise unchanged
            drv = drive_true + r["drive"].standard_normal((B, Q)) * self.drive_sigma
        else:
            T, acc, Hb, drv = T_true.copy(), accel_true.copy(), H_true.copy(), drive_true.copy()
            if self.balance_read is not None:
                Hb = H_true @ self.balance_read.T
        status = (np.abs(T) > self.cell_fs).astype(np.uint8)  # bit 0: over-range
        return T, acc, Hb, drv, status


class AircraftPhysics:
    """The simulated aircraft: `next_sample()` advances one sample period (1/sample_rate_hz).

    Deterministic for a given (cfg, scenario, seed): every random quantity comes from streams
    spawned from the seed (default: the scenario's fixed seed). The parts: the load model
    (:class:`LoadModel`), the true angles (:class:`TrueAngles`), the mount dynamics
    (:class:`MountDynamics`), the sensor models (:class:`SensorModels`); this class holds the
    random streams, the base vibration and the blocks (computed once each, in order).
    """

    def __init__(self, cfg: RigConfig, scenario: Scenario | str, seed: int | None = None,
                 block_size: int = BLOCK_SIZE):
        if isinstance(scenario, str):
            scenario = load_scenario(scenario)
        self.cfg, self.scenario = cfg, scenario
        self.seed = int(scenario.seed if seed is None else seed)
        self.dt = 1.0 / cfg.sample_rate_hz
        self.block_size = int(block_size)
        self.substeps = int(cfg.simulator.substeps)
        if self.substeps < 10:
            raise ValueError("simulator.substeps must be >= 10 (model §8: >= 10x the sample rate)")
        self.mounts = MountDynamics(cfg, scenario, self.dt, self.substeps)
        check_against_rig(scenario, cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s,
                          cfg.rotor.blades)

        # independent random streams (chunk-invariant draws); the aircraft's base angles have a
        # stream of their own, so that every scenario flies the same aircraft for a given seed
        # (a ground test and a flight share their base angles whatever else they draw)
        ss = np.random.SeedSequence(self.seed)
        (params, r_cell, r_acc, r_bal, r_drive, r_base, r_angles) = [np.random.default_rng(s)
                                                                     for s in ss.spawn(7)]
        rng = {"cell": r_cell, "acc": r_acc, "bal": r_bal, "drive": r_drive, "base": r_base}
        draws = _draw_parameters(scenario, cfg.rotor.blades, self.mounts.Q, params, r_angles)
        self.angles = TrueAngles(scenario, draws, self.mounts)
        self.sensors = SensorModels(cfg, scenario, rng)

        self._base = None
        if scenario.base_vibration.enabled:
            bv = scenario.base_vibration
            self._base = _BaseVibration(bv.band_hz, self.dt / self.substeps, bv.rms_g * G0,
                                        rng["base"])
        r_turb = None
        tb = scenario.turbulence
        if tb.enabled:
            if 2 * tb.band_hz[1] >= self.substeps * cfg.sample_rate_hz:
                raise ValueError("turbulence band reaches the simulator's substep Nyquist")
            r_turb = np.random.default_rng(ss.spawn(1)[0])  # a 7th stream: the others unchanged
        self.loads = LoadModel(cfg, scenario, draws, self.dt, self.substeps, self.mounts.Q,
                               r_turb)
        self._k_next = 0  # index of the next block's first sample
        self._block: dict | None = None
        self._pos = 0
        # the next block computed ahead by another thread (compute_ahead: a real-time driver,
        # off the SYNC path); the lock orders it with next_sample's block boundary
        self._next: dict | None = None
        self._next_lock = threading.Lock()

    # the parameters drawn for this seed (tests and benchmarks read them)
    @property
    def alpha_base(self) -> np.ndarray:
        return self.angles.alpha_base

    @property
    def alpha_gain(self) -> np.ndarray:
        return self.angles.alpha_gain

    @property
    def cell_gain(self) -> np.ndarray:
        return self.angles.cell_gain

    @property
    def harm_amp(self) -> np.ndarray:
        return self.loads.harm_amp

    @property
    def harm_phase(self) -> np.ndarray:
        return self.loads.harm_phase

    # ------------------------------------------------------------------ public
    @property
    def index(self) -> int:
        """Index of the sample the next call of next_sample() returns."""
        if self._block is None:
            return self._k_next
        return self._k_next - self.block_size + self._pos

    def next_sample(self) -> SimSample:
        """Advance one sample period."""
        if self._block is None or self._pos >= self.block_size:
            self._block = self._take_block()
            self._pos = 0
        b, i = self._block, self._pos
        self._pos += 1
        vals: dict[str, Any] = {}
        for name in SAMPLE_FIELDS:
            v = b[name][i]
            vals[name] = v.copy() if isinstance(v, np.ndarray) else v.item()
        return SimSample(**vals)

    def next_block(self) -> dict[str, np.ndarray]:
        """The next `block_size` samples as arrays (SimSample fields stacked). Do not mix with
        next_sample() inside one block."""
        if self._block is not None and 0 < self._pos < self.block_size:
            raise RuntimeError("next_block() in the middle of a block consumed by next_sample()")
        out = self._take_block()
        self._block, self._pos = None, 0
        return out

    def compute_ahead(self) -> bool:
        """Compute the next block now, unless it is computed already (a real-time driver's
        thread between SYNCs, so that no SYNC waits for a whole block: 1-2 ms for 100
        samples). The block is the one :meth:`next_sample` would compute at the boundary, bit
        for bit (blocks are computed once each, in order). Returns whether it computed."""
        with self._next_lock:
            if self._next is not None:
                return False
            self._next = self._compute_block(self._k_next)
            return True

    def _take_block(self) -> dict[str, np.ndarray]:
        """The next block: the one computed ahead, else computed now."""
        with self._next_lock:
            b, self._next = self._next, None
            if b is None:
                b = self._compute_block(self._k_next)
            self._k_next += self.block_size
        return b

    def mode_frequencies_hz(self, alpha: np.ndarray | None = None) -> np.ndarray:
        """The six mount-mode frequencies (model §8: clear of 1/rev and N_b/rev)."""
        a = self.alpha_base if alpha is None else np.asarray(alpha, float)
        return self.mounts.mode_frequencies_hz(a)

    def _base_motion(self, B: int, n: int):
        """Base displacement, velocity, acceleration at the B n + 1 substep points (3 axes)."""
        if self._base is None:
            z = np.zeros((B * n + 1, 3))
            return z, z, z
        d, v, a = self._base.block(B * n)
        return d, v, a

    # ------------------------------------------------------------------ one block
    def _compute_block(self, k0: int) -> dict[str, np.ndarray]:
        B, n, dt = self.block_size, self.substeps, self.dt
        mt = self.mounts
        idx = k0 + np.arange(B + 1)
        t_samp = idx * dt  # sample instants (the last one is the next block's first)
        sub = np.arange(n) * (dt / n)
        ts = np.concatenate([(t_samp[:-1, None] + sub[None, :]).reshape(-1), t_samp[-1:]])

        H, Wu, static, omega_s, turns = self.loads.loads(t_samp, ts, n)
        q_drive = self.loads.drive(turns)
        w = H @ mt.R_body.T + Wu + q_drive @ mt.D.T + mt.W_g  # CG wrench (B n + 1, 6)
        d, v, a_base = self._base_motion(B, n)
        S0 = slice(0, B * n, n)  # substep 0 of every sample: the sample instants
        alpha = self.angles.at(t_samp[:-1], static[S0])
        T_true, qdd = mt.respond(alpha, w, d, v)
        I_true, accel_true = mt.inertial(qdd)

        H_true = H[S0]
        unmod = Wu[S0]
        drive_true = q_drive[S0]
        T, acc, Hb, drv, status = self.sensors.read(T_true, accel_true, H_true, drive_true)
        az = 2 * np.pi * np.mod(turns[S0], 1.0)
        az[az >= 2 * np.pi] = 0.0
        return {
            "index": idx[:-1].copy(), "t": t_samp[:-1].copy(), "T": T, "cell_status": status,
            "accel": acc,
            "omega": omega_s[:B].copy(), "azimuth": az, "H_balance": Hb, "drive": drv,
            "H_true": H_true.copy(), "alpha_true": alpha, "T_true": T_true,
            "accel_true": accel_true,
            "unmodelled": unmod.copy(), "I_true": I_true, "drive_true": drive_true.copy(),
            "base_accel": a_base[S0].copy(),
        }
