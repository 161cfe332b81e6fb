"""Independent synthetic data for the identification tests (model.md §8 quasi-static limit).

Truth is built here, NOT with estimator.geometry: the cell axes come from
scipy.spatial.transform.Rotation and the wrench matrix from np.cross, straight from the rig
config, so a sign error in the estimator shows instead of cancelling. The load cells share
the load by the minimum-strain-energy split (equal stiffness: T = S_true⁺ (I − R H)), as in
the report's simulation. Vectorised over samples and seeds-friendly (one numpy Generator).
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.signal
from scipy.constants import g as STANDARD_GRAVITY
from scipy.spatial.transform import Rotation

from rsra.config.rig import RigConfig, config_dir


def scenario(name: str) -> dict:
    """A scenario data file of config/scenarios/ (model.md §8), parsed."""
    with open(config_dir() / "scenarios" / f"{name}.toml", "rb") as f:
        return tomllib.load(f)


_GROUND = scenario("ground-test")
# model.md §8 ground-test: thrust near 80 kN up (−z), then thrust plus in turn 10 kN on X and
# on Y, 20 kN·m on L and on M, 15 kN·m on N (body axes, N and N·m) — from the scenario file.
GROUND_TEST_CONDITIONS = np.array(_GROUND["loads"]["conditions"], float)
GROUND_TEST_HOLD_S = float(_GROUND["loads"]["hold_s"])
GROUND_TEST_RAMP_S = float(_GROUND["loads"]["ramp_s"])


def harmonic_ranges(name: str) -> list[tuple[int | str, np.ndarray, np.ndarray]]:
    """(order, amplitude_min (6,), amplitude_max (6,)) of a scenario's hub-load harmonics;
    ``"blades"`` stands for N_b. A missing maximum means a fixed amplitude."""
    out = []
    for h in scenario(name)["harmonics"]:
        lo = np.array(h["amplitude_min"], float)
        out.append((h["order"], lo, np.array(h.get("amplitude_max", lo), float)))
    return out


class TruthGeometry:
    """Cell axes, S and R of the true rig, built independently of estimator.geometry."""

    # rotation sequence (extrinsic: first angle about the first axis) by nominal direction
    _SEQ = {0: "yz", 1: "xz", 2: "xy"}  # n ~ x: longitudinal; y: lateral; z: vertical

    def __init__(self, cfg: RigConfig) -> None:
        self.positions = np.array([c.position_m for c in cfg.cells], float)
        self.nominal = np.array([c.nominal_axis for c in cfg.cells], float)
        self.seq = [self._SEQ[int(np.argmax(np.abs(n)))] for n in self.nominal]
        self.hub = np.asarray(cfg.hub_centre_m, float)
        self.tilt = float(cfg.shaft_tilt_rad)

    def axes(self, alpha: np.ndarray) -> np.ndarray:
        a = np.asarray(alpha, float).reshape(-1, 2)
        return np.array([Rotation.from_euler(s, ai).apply(n)
                         for s, ai, n in zip(self.seq, a, self.nominal)])

    def S(self, alpha: np.ndarray) -> np.ndarray:
        u = self.axes(alpha)
        return np.vstack([u.T, np.cross(self.positions, u).T])

    def R(self, frame: str = "body") -> np.ndarray:
        C = np.eye(3) if frame == "body" else Rotation.from_euler("y", -self.tilt).as_matrix()
        R = np.zeros((6, 6))
        R[:3, :3] = C
        R[3:, 3:] = C
        R[3:, :3] = np.cross(self.hub[None, :], C.T).T  # columns p_H × c_k
        return R


@dataclass
class SyntheticRun:
    fs: float
    t: np.ndarray  # (N,)
    alpha: np.ndarray  # (N, 14) true angles
    H: np.ndarray  # (N, 6) true hub loads (body axes)
    I: np.ndarray  # (N, 6) true inertial loads (incl. the neglected angular part)
    T_true: np.ndarray  # (N, 7)
    T: np.ndarray  # (N, 7) measured
    accel: np.ndarray  # (N, K, 3) measured specific force
    H_m: np.ndarray  # (N, 6) reference-balance measurement
    condition: np.ndarray  # (N,) index of the static condition


def _sigmas(cfg: RigConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    sT = np.array([c.full_scale_N * c.accuracy_fs for c in cfg.cells])
    sa = np.array([a.full_scale_g * STANDARD_GRAVITY * a.accuracy_fs for a in cfg.accelerometers])
    b = cfg.balance
    sH = np.array([b.full_scale_force_N] * 3 + [b.full_scale_moment_Nm] * 3) * b.accuracy_fs
    return sT, sa, sH


def harmonic_loads(cfg: RigConfig, t: np.ndarray, rng: np.random.Generator,
                   ranges: list[tuple[int | str, np.ndarray, np.ndarray]]
                   ) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """Hub loads at rotor harmonics: per component an amplitude uniform in [min, max]
    (N; N·m) and a random phase, constant. Returns (H (N, 6), coefficients (n_h, 6, 2) with
    H = Σ a cos kΩt − b sin kΩt, the orders k)."""
    Om = cfg.rotor.omega_nominal_rad_s
    H = np.zeros((len(t), 6))
    coef = np.zeros((len(ranges), 6, 2))
    orders = []
    for i, (order, lo, hi) in enumerate(ranges):
        k = cfg.rotor.blades if order == "blades" else int(order)
        orders.append(k)
        amp = rng.uniform(lo, hi)
        ph = rng.uniform(0, 2 * np.pi, 6)
        coef[i, :, 0], coef[i, :, 1] = amp * np.cos(ph), amp * np.sin(ph)
        H += amp * np.cos(k * Om * t[:, None] + ph)
    return H, coef, tuple(orders)


def static_run(
    cfg: RigConfig,
    alpha_true: np.ndarray,
    rng: np.random.Generator,
    *,
    conditions: np.ndarray = GROUND_TEST_CONDITIONS,
    sweeps: int = 2,
    condition_s: float = GROUND_TEST_HOLD_S,
    ramp_s: float = GROUND_TEST_RAMP_S,
    shaker: list[tuple[int | str, np.ndarray, np.ndarray]] | None = None,
    noise: bool = True,
    angular_noise_Nm: float | None = None,
    gravity: bool = True,
    step: np.ndarray | None = None,
    step_time_s: float | None = None,
) -> SyntheticRun:
    """Known-load static calibration (model §8 ground-test) in the quasi-static limit:
    the static conditions held ``condition_s`` each (linear ramps of ``ramp_s`` into each),
    plus shaker harmonics (default: the scenario file's ranges); the body at rest, so the
    accelerometers read −g; the neglected angular inertial load is white with σ = the
    configured moment floor (the model error that W's floor stands for); §4 sensor noise.
    ``step`` adds to the true angles from ``step_time_s`` on."""
    fs = cfg.sample_rate_hz
    geo = TruthGeometry(cfg)
    n_cond = len(conditions) * sweeps
    N = int(round(n_cond * condition_s * fs))
    t = np.arange(N) / fs
    idx = np.minimum((t // condition_s).astype(int), n_cond - 1)
    seq = np.tile(np.arange(len(conditions)), sweeps)
    level = conditions[seq[idx]]
    prev = conditions[seq[np.maximum(idx - 1, 0)]]
    frac = np.clip((t - idx * condition_s) / ramp_s, 0.0, 1.0)[:, None] if ramp_s > 0 else 1.0
    Hs = prev + (level - prev) * frac
    Hh, _, _ = harmonic_loads(cfg, t, rng, harmonic_ranges("ground-test") if shaker is None
                              else shaker)
    H = Hs + Hh
    alpha = np.tile(np.asarray(alpha_true, float), (N, 1))
    if step is not None:
        alpha[t >= step_time_s] += step
    m = np.asarray(cfg.effective_mass_kg, float)
    f = np.array([0.0, 0.0, -STANDARD_GRAVITY]) if gravity else np.zeros(3)  # z down: f = −g
    floor = cfg.identification.moment_floor_Nm if angular_noise_Nm is None else angular_noise_Nm
    I = np.zeros((N, 6))
    I[:, :3] = m * f
    if noise and floor > 0:
        I[:, 3:] = floor * rng.standard_normal((N, 3))  # neglected I·ω̇ (white)
    return _measure(cfg, geo, t, alpha, H, I, f, rng, noise, idx)


def paper_run(cfg: RigConfig, rng: np.random.Generator, *, duration_s: float,
              noise: bool = True, alpha_true: np.ndarray | None = None
              ) -> tuple[SyntheticRun, np.ndarray, tuple[int, ...]]:
    """The report's Phase II set-up (model §8 ``paper``, amplitudes from its scenario file):
    the two harmonics only, quasi-static, no inertia and no gravity (accelerometers read
    zero), true angles 0 by default. Returns the run, the harmonic coefficients (n_h, 6, 2)
    of H(t) = Σ a cos kΩt − b sin kΩt, and the orders k."""
    fs = cfg.sample_rate_hz
    geo = TruthGeometry(cfg)
    N = int(round(duration_s * fs))
    t = np.arange(N) / fs
    H, coef, orders = harmonic_loads(cfg, t, rng, harmonic_ranges("paper"))
    alpha = np.zeros((N, 14)) if alpha_true is None else np.tile(alpha_true, (N, 1))
    run = _measure(cfg, geo, t, alpha, H, np.zeros((N, 6)), np.zeros(3), rng, noise,
                   np.zeros(N, int))
    return run, coef, orders


def _measure(cfg, geo, t, alpha, H, I, f, rng, noise, cond) -> SyntheticRun:
    N = len(t)
    R = geo.R(cfg.hub_frame)
    b = I - H @ R.T  # S T = I − R H
    T = np.empty((N, len(cfg.cells)))
    # piecewise-constant angles: one pseudo-inverse per run of equal angles
    change = np.flatnonzero(np.any(np.diff(alpha, axis=0) != 0, axis=1)) + 1
    for s, e in zip(np.concatenate([[0], change]), np.concatenate([change, [N]])):
        T[s:e] = b[s:e] @ np.linalg.pinv(geo.S(alpha[s])).T  # minimum strain energy
    sT, sa, sH = _sigmas(cfg)
    pos = np.array([a.position_m for a in cfg.accelerometers], float)
    # each accelerometer reads f + ω̇ × r; the angular part here is tiny and left out
    acc = np.broadcast_to(f, (N, len(pos), 3)).copy()
    Tm, Hm = T.copy(), H.copy()
    if noise:
        Tm += sT * rng.standard_normal(T.shape)
        acc += sa[None, :, None] * rng.standard_normal(acc.shape)
        Hm += sH * rng.standard_normal(H.shape)
    return SyntheticRun(cfg.sample_rate_hz, t, alpha, H, I, T, Tm, acc, Hm, cond)


# ------------------------------------------------------------------------------------------
# A small calibration-filter design for the filter-error tests (model §5–§6, time-constant
# tuning), independent of estimator.filters.
# ------------------------------------------------------------------------------------------
@dataclass
class SmallDesign:
    Phi: np.ndarray
    C: np.ndarray
    J: np.ndarray
    K: np.ndarray
    Qd: np.ndarray
    slowest_time_constant_s: float


def small_design(cfg: RigConfig, *, tau: float | None = None, psd: float = 1e8,
                 harmonics: tuple[int, ...] | None = None) -> SmallDesign:
    """Harmonic oscillators per hub-load component (states (H_k, Ḣ_k)), poles of each
    whitened component placed at e^{−Δt/τ}·eig(Φ_c) (scipy.signal.place_poles on the dual),
    K mapped back through R⁻¹; Q_d by Van Loan with a white acceleration PSD."""
    tau = cfg.filter.time_constant_s if tau is None else tau
    harmonics = tuple(cfg.filter.harmonics) if harmonics is None else harmonics
    dt, Om = 1.0 / cfg.sample_rate_hz, cfg.rotor.omega_nominal_rad_s
    nh = len(harmonics)
    Fc = np.zeros((2 * nh, 2 * nh))
    Gc = np.zeros((2 * nh, nh))
    for i, k in enumerate(harmonics):
        Fc[2 * i:2 * i + 2, 2 * i:2 * i + 2] = [[0, 1], [-(k * Om) ** 2, 0]]
        Gc[2 * i + 1, i] = 1.0
    Cc = np.zeros((1, 2 * nh))
    Cc[0, 0::2] = 1.0
    Phic = scipy.linalg.expm(Fc * dt)
    poles = np.exp(-dt / tau) * np.linalg.eigvals(Phic)
    L = scipy.signal.place_poles(Phic.T, (Phic.T @ Cc.T), poles).gain_matrix
    Kc = L.T  # eig((I − K C) Φ) = poles
    n = 2 * nh
    # Van Loan
    Z = np.zeros((2 * n, 2 * n))
    Z[:n, :n] = -Fc
    Z[:n, n:] = Gc @ Gc.T * psd
    Z[n:, n:] = Fc.T
    EZ = scipy.linalg.expm(Z * dt)
    Qc = EZ[n:, n:].T @ EZ[:n, n:]
    Phi = np.kron(np.eye(6), Phic)
    C = np.kron(np.eye(6), Cc)
    Kw = np.kron(np.eye(6), Kc)
    R = TruthGeometry(cfg).R(cfg.hub_frame)
    return SmallDesign(Phi=Phi, C=C, J=R @ C, K=Kw @ np.linalg.inv(R),
                       Qd=np.kron(np.eye(6), 0.5 * (Qc + Qc.T)), slowest_time_constant_s=tau)


def harmonic_state(design: SmallDesign, coef: np.ndarray, omega: float,
                   harmonics: tuple[int, ...], t0: float = 0.0) -> np.ndarray:
    """The small design's state (H_k, Ḣ_k per component) of H(t) = Σ a cos kΩt − b sin kΩt
    at t0 (the simulator's own initial state)."""
    x = np.zeros(design.Phi.shape[0])
    nh = len(harmonics)
    for c in range(6):
        for i, k in enumerate(harmonics):
            a, b = coef[i, c]
            w = k * omega
            x[c * 2 * nh + 2 * i] = a * np.cos(w * t0) - b * np.sin(w * t0)
            x[c * 2 * nh + 2 * i + 1] = -w * (a * np.sin(w * t0) + b * np.cos(w * t0))
    return x


# ------------------------------------------------------------------------------------------
# The statistical decisions of performance.md (overall false-alarm rate 10⁻³, Bonferroni)
# ------------------------------------------------------------------------------------------
FALSE_ALARM = 1e-3


@dataclass
class Decisions:
    chi2: np.ndarray  # (n,) joint χ² of each seed's error against its covariance
    chi2_limit: float
    z_mean: np.ndarray  # (p,) mean error / its standard error
    z_limit: float
    spread: np.ndarray  # (p,) sample variance of error/σ_CR
    spread_limits: tuple[float, float]

    @property
    def passed(self) -> bool:
        lo, hi = self.spread_limits
        return bool(np.all(self.chi2 <= self.chi2_limit)
                    and np.all(np.abs(self.z_mean) <= self.z_limit)
                    and np.all((self.spread >= lo) & (self.spread <= hi)))

    def summary(self) -> str:
        return (f"chi2 max {self.chi2.max():.1f} (limit {self.chi2_limit:.1f}), "
                f"|mean|/se max {np.abs(self.z_mean).max():.2f} (limit {self.z_limit:.2f}), "
                f"spread {self.spread.min():.2f}..{self.spread.max():.2f} "
                f"(limits {self.spread_limits[0]:.2f}..{self.spread_limits[1]:.2f})")


def decisions(errors: np.ndarray, covariances: np.ndarray) -> Decisions:
    """performance.md: per seed the joint χ²_p of the error against the reported covariance
    ≤ χ²_p(1 − 10⁻³/n) (48.7 for 14 angles and 100 seeds); the mean error of each angle within
    z(10⁻³/2p) standard errors (3.97); the variance of error/σ_CR inside the two-sided χ²_{n−1}
    bounds at 10⁻³/2p per tail."""
    from scipy.stats import chi2, norm

    errors = np.asarray(errors, float)
    n, p = errors.shape
    c = np.array([e @ np.linalg.solve(P, e) for e, P in zip(errors, covariances)])
    se = errors.std(axis=0, ddof=1) / np.sqrt(n)
    sig = np.sqrt(np.einsum("kii->ki", np.asarray(covariances)))
    spread = (errors / sig).var(axis=0, ddof=1)
    a = FALSE_ALARM / (2 * p)
    return Decisions(
        chi2=c, chi2_limit=float(chi2.isf(FALSE_ALARM / n, p)),
        z_mean=errors.mean(axis=0) / se, z_limit=float(norm.isf(a)),
        spread=spread,
        spread_limits=(float(chi2.ppf(a, n - 1) / (n - 1)), float(chi2.isf(a, n - 1) / (n - 1))),
    )
