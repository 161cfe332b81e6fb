"""The fixed-gain Kalman filter of the hub loads (model.md §5–§6; report Eq 2.10–2.16).

    x⁻(n) = Φ x⁺(n−1)
    e(n)  = z(n) − S(α) T_m(n) − J x⁻(n)        J = R C (does not depend on α)
    x⁺(n) = x⁻(n) + K e(n)
    Ĥ(n)  = C x⁺(n)

The gain is designed once per Ω and tuning (report: "the algorithms can be greatly
simplified by using the steady state value of the Kalman gains"); no covariance is updated
per sample. Three layers:

* ``design_filter`` — one design (Φ, K, B, …) for one Ω;
* ``DesignCache`` — redesign when Ω leaves a band around the design point, designs cached by
  Ω rounded (relatively) to ``cache_resolution``; the stopped-rotor design below ``omega_min``;
* ``LoadFilter`` (the per-sample path of the live service and of a bit-exact replay) and
  ``filter_batch`` (the same recursion for whole arrays, off-line: six single-output IIR
  filters, docs/performance.md, the batch filter's budget).
"""
from __future__ import annotations

import weakref
from collections import OrderedDict
from dataclasses import dataclass
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import numpy as np
from scipy.linalg import cholesky, eigh, solve_discrete_are, solve_discrete_lyapunov
from scipy.optimize import brentq
from scipy.signal import lfilter, place_poles, sosfilt, zpk2sos

from .balance import measurement_covariance
from .dynamics import (
    N_COMPONENTS,
    component_states,
    hub_load_dynamics,
    low_frequency_states,
    state_labels,
)
from .geometry import hub_transfer_matrix, wrench_matrix
from .params import Geometry, RigModel

TUNINGS = ("time_constant", "noise")

# Flags of the published hub loads (the vocabulary of docs/telemetry.md §2.1).
PREDICT_ONLY = "predict_only"
INVALID = "invalid"
LOST_BEFORE = "lost_before"
ROTOR_STOPPED = "rotor_stopped"
AZIMUTH_MISSING = "azimuth_missing"  # azimuth mode: the harmonics advanced by the design's Ω

# Harmonic phase (config ``rotor.harmonic_phase``): "design" — the harmonic states advance by
# the design's kΩΔt every sample (model §5 as the report had it); "azimuth" — by k times the
# rotor's measured turn Δψ since the last sample , the gain held constant.
HARMONIC_PHASES = ("design", "azimuth")
# azimuth mode: the gain is held while Ω stays within this band of the design point
# (the rotation per sample follows the azimuth; the gain only sets how fast amplitudes move)
AZIMUTH_GAIN_BAND = 0.05


@dataclass(frozen=True, eq=False)
class FilterDesign:
    """One fixed-gain design. State layout: ``estimator.dynamics`` (``labels``).

    ``harmonics`` are the harmonics that have states in this design (empty when the rotor
    is stopped); ``omega`` the Ω it was designed for (0 when stopped); ``blocks`` groups of
    states that the closed loop (I − K J) Φ leaves uncoupled (one per component for the
    time-constant tuning, all states for the Riccati gain); ``rotation`` and
    ``rotated_gains`` the six single-output filters both tunings decompose into, which the
    batch path runs.
    """

    Phi: np.ndarray  # (n, n)
    C: np.ndarray  # (6, n)
    J: np.ndarray  # (6, n) = R C
    K: np.ndarray  # (n, 6)
    B: np.ndarray  # (6, 6) innovation covariance J P⁻ Jᵀ + W
    P_minus: np.ndarray  # (n, n)
    Qd: np.ndarray  # (n, n)
    W: np.ndarray  # (6, 6) measurement covariance W(α_config)
    omega: float
    dt: float
    harmonics: tuple[int, ...]
    low_frequency: bool
    rotor_stopped: bool
    slowest_time_constant_s: float
    tuning: str
    time_constant_s: float = 0.1
    psd: np.ndarray | None = None  # (6,) process-noise amplitude diffusion rates used
    R: np.ndarray | None = None  # (6, 6) hub transfer matrix of the design's frame
    geometry: Geometry | None = None  # for S(α) in the batch path
    blocks: tuple[tuple[int, ...], ...] = ()
    labels: tuple[tuple[int, int, int], ...] = ()
    # Time-constant tuning: the one gain every component has in whitened coordinates
    # (K = blockdiag(K_c) R⁻¹ with K_c = component_gain); None for the Riccati gain.
    component_gain: np.ndarray | None = None
    # Both tunings are six single-output filters in rotated whitened coordinates
    # y = M R⁻¹ (z − S T), x̃ = (M ⊗ I_m) x: K = (M⁻¹ ⊗ I_m) blockdiag(k̃_i) M R⁻¹ with
    # M = ``rotation`` (6, 6; I for the time-constant gain) and k̃_i = ``rotated_gains[i]``
    # (6, m). The batch path runs on this; None for a design without that structure.
    rotation: np.ndarray | None = None
    rotated_gains: np.ndarray | None = None

    @property
    def n_states(self) -> int:
        return int(self.Phi.shape[0])

    @property
    def closed_loop(self) -> np.ndarray:
        """(I − K J) Φ: x⁺(n) = (I − K J) Φ x⁺(n−1) + K (z − S T)."""
        result: np.ndarray = self.Phi - self.K @ (self.J @ self.Phi)
        return result


def _closed_loop_time_constants(A: np.ndarray, dt: float) -> np.ndarray:
    """τ_i = −Δt / ln|λ_i| of every eigenvalue (0 for λ = 0, inf when not stable)."""
    mags = np.abs(np.linalg.eigvals(A))
    taus = np.full(mags.shape, np.inf)
    taus[mags == 0] = 0.0
    ok = (mags > 0) & (mags < 1)
    taus[ok] = -dt / np.log(mags[ok])
    return taus


def _riccati_gain_1(Phi_c: np.ndarray, C_c: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Steady-state (a posteriori) Kalman gain of a single-output system with r = 1."""
    P = solve_discrete_are(Phi_c.T, C_c.T, Q, np.eye(1))
    result: np.ndarray = P @ C_c.T / (C_c @ P @ C_c.T + 1.0)
    return result


def auto_psd_ratio(Phi_c: np.ndarray, C_c: np.ndarray, Qd_unit: np.ndarray,
                   time_constant_s: float, dt: float) -> float:
    """q/r such that the Riccati gain of one component has τ as slowest time constant (model §6).

    The steady gain depends on q and r only through q/r, and the slowest time constant falls
    monotonically as q/r grows, so a bracketed 1-D root search in log(q/r) is enough.
    """
    eye = np.eye(Phi_c.shape[0])

    def slowest(log_rho: float) -> float:
        K = _riccati_gain_1(Phi_c, C_c, np.exp(log_rho) * Qd_unit)
        return float(np.max(_closed_loop_time_constants((eye - K @ C_c) @ Phi_c, dt)))

    def f(log_rho: float) -> float:
        return float(np.log(slowest(log_rho)) - np.log(time_constant_s))

    # Continuous random-walk Kalman filter: τ = sqrt(r dt / q) → start from q/r = dt/τ².
    return float(np.exp(_root_log(f, np.log(dt / time_constant_s**2), time_constant_s)))


def _root_log(f: Callable[[float], float], centre: float, time_constant_s: float) -> float:
    """Root of a decreasing f(log ρ), bracketed outwards from ``centre``."""
    lo, hi = centre - 4.0, centre + 4.0
    for _ in range(20):
        flo, fhi = f(lo), f(hi)
        if flo > 0 > fhi:
            break
        if flo <= 0:
            lo -= 4.0
        if fhi >= 0:
            hi += 4.0
    else:
        raise ValueError(f"no process-noise PSD gives a slowest time constant of {time_constant_s} s")
    return float(brentq(f, lo, hi, xtol=1e-10, rtol=1e-12))


def _placed_gain(Phi_c: np.ndarray, C_c: np.ndarray, harmonics: tuple[int, ...],
                 omega: float, dt: float, low_frequency: bool, time_constant_s: float) -> np.ndarray:
    """K_c placing eig((I − K_c C_c) Φ_c) at e^{−Δt/τ}·eig(Φ_c) (report: all τ = 0.1 s).

    eig(Φ_c) are e^{±i kΩΔt} and 1 (random walk), written exactly so the requested poles
    are exact conjugate pairs. On the dual system, eig(Φ_cᵀ − Φ_cᵀ C_cᵀ K_cᵀ) are the same
    eigenvalues, so ``place_poles(Φ_cᵀ, Φ_cᵀ C_cᵀ)`` returns K_cᵀ; one output → unique gain.
    """
    r = np.exp(-dt / time_constant_s)
    poles: list[complex] = []
    for k in harmonics:
        p = r * np.exp(1j * k * omega * dt)
        poles += [p, np.conj(p)]
    if low_frequency:
        poles.append(r)
    if len(poles) == 1:  # a single real state: K = 1 − r exactly
        return np.array([[1.0 - r]])
    res = place_poles(Phi_c.T, Phi_c.T @ C_c.T, np.array(poles))
    return res.gain_matrix.T


def design_filter(
    model: RigModel,
    *,
    harmonics: tuple[int, ...] | list[int],
    omega: float | None,
    dt: float,
    tuning: str = "time_constant",
    time_constant_s: float = 0.1,
    low_frequency: bool = True,
    psd: str | np.ndarray | float = "auto",
    alpha: np.ndarray | None = None,
    moment_floor: float = 100.0,
    frame: str | None = None,
    omega_min: float = 0.0,
) -> FilterDesign:
    """The fixed gain K and innovation covariance B for one Ω (model.md §6).

    ``omega`` None, ≤ 0 or below ``omega_min``: stopped rotor — the harmonic states are
    dropped (pole placement at Ω = 0 is singular) and only the six random walks run,
    whatever ``low_frequency`` says (a filter with no state could not absorb any load).
    ``psd``: "auto" (per component, the Riccati gain has τ as slowest time constant) or
    (6,) amplitude diffusion rates (``estimator.dynamics``). ``alpha``: α_config for W.
    """
    if tuning not in TUNINGS:
        raise ValueError(f"tuning must be one of {TUNINGS}, not {tuning!r}")
    if not time_constant_s > 0:
        raise ValueError(f"time_constant_s must be positive, got {time_constant_s!r}")
    geometry = model.geometry
    alpha = np.zeros(2 * geometry.n_cells) if alpha is None else np.asarray(alpha, float)
    stopped = omega is None or not omega > 0.0 or omega < omega_min
    if stopped:
        harmonics, low_frequency, omega_d = (), True, 0.0
    else:
        assert omega is not None  # not stopped
        harmonics, omega_d = tuple(int(k) for k in harmonics), float(omega)

    R = hub_transfer_matrix(geometry, frame)
    Rinv = np.linalg.inv(R)
    W = measurement_covariance(model, alpha, moment_floor=moment_floor)
    W = 0.5 * (W + W.T)
    # Whitened (decoupled) measurement z' = R⁻¹ (z − S T) = C x + R⁻¹ v: component c sees
    # only its own states; r_c its noise variance.
    r_w = np.diag(Rinv @ W @ Rinv.T)

    unit = hub_load_dynamics(harmonics, omega_d, dt, low_frequency, psd=np.ones(N_COMPONENTS))
    n = unit.n_states
    idx0 = component_states(harmonics, low_frequency, 0)
    Phi_c = unit.Phi[np.ix_(idx0, idx0)]  # identical for every component
    C_c = unit.C[0:1, idx0]
    Qd_unit_c = unit.Qd[np.ix_(idx0, idx0)]

    if isinstance(psd, str):
        if psd != "auto":
            raise ValueError(f'psd must be "auto" or six PSDs, not {psd!r}')
        rho = auto_psd_ratio(Phi_c, C_c, Qd_unit_c, time_constant_s, dt)
        q = rho * r_w
    else:
        q = np.broadcast_to(np.asarray(psd, float), (N_COMPONENTS,)).copy()
    dyn = hub_load_dynamics(harmonics, omega_d, dt, low_frequency, psd=q)
    Phi, C, Qd = dyn.Phi, dyn.C, dyn.Qd
    J = R @ C
    blocks = tuple(tuple(int(i) for i in component_states(harmonics, low_frequency, c))
                   for c in range(N_COMPONENTS))

    if tuning == "time_constant":
        Kc = _placed_gain(Phi_c, C_c, harmonics, omega_d, dt, low_frequency, time_constant_s)
        Kw = np.zeros((n, N_COMPONENTS))
        for c, blk in enumerate(blocks):
            Kw[list(blk), c] = Kc[:, 0]
        K = Kw @ Rinv  # whitened innovation R⁻¹ e → K = K_w R⁻¹
        # Error loop of the fixed gain: P⁻ = A P⁻ Aᵀ + Φ K W Kᵀ Φᵀ + Qd, A = Φ (I − K J).
        A = Phi @ (np.eye(n) - K @ J)
        P = solve_discrete_lyapunov(A, Phi @ K @ W @ K.T @ Phi.T + Qd)
        rotation, rotated_gains = np.eye(N_COMPONENTS), np.tile(Kc[:, 0], (N_COMPONENTS, 1))
    else:
        if np.any(q <= 0):
            raise ValueError("the noise tuning needs positive process-noise PSDs")
        # W couples the whitened components. M with M W' Mᵀ = I and M diag(q) Mᵀ = diag(μ)
        # (W' = R⁻¹ W R⁻ᵀ; the symmetric-definite eigenproblem q v = μ W' v, M = Vᵀ)
        # decouples them again: Φ = I ⊗ Φ_c, C = I ⊗ c and Qd = diag(q) ⊗ Qd_c commute with
        # M ⊗ I_m, so in x̃ = (M ⊗ I_m) x with y = M R⁻¹ (z − S T) (unit noise) the Riccati
        # equation of Eq 2.12–2.14 is six single-output ones with q/r = μ_i — the same
        # solution as the 30-state one, exactly decoupled and better conditioned.
        Wn = Rinv @ W @ Rinv.T
        mu, V = eigh(np.diag(q), 0.5 * (Wn + Wn.T))
        M, Mi = V.T, (0.5 * (Wn + Wn.T)) @ V  # Vᵀ W' V = I → (Vᵀ)⁻¹ = W' V
        if isinstance(psd, str):
            # The slowest of the six is the one with the least process noise (τ falls as
            # q/r grows): one common factor on the PSDs gives it τ, the slowest time
            # constant of the whole design — the two tunings then agree.
            scale = rho / float(np.min(mu))
            q, mu, Qd = q * scale, mu * scale, Qd * scale
        m = len(idx0)
        rotated_gains = np.empty((N_COMPONENTS, m))
        P_rot = np.zeros((n, n))
        for i in range(N_COMPONENTS):
            Pi = solve_discrete_are(Phi_c.T, C_c.T, mu[i] * Qd_unit_c, np.eye(1))
            Pi = 0.5 * (Pi + Pi.T)
            rotated_gains[i] = (Pi @ C_c.T / (C_c @ Pi @ C_c.T + 1.0))[:, 0]
            P_rot[i * m:(i + 1) * m, i * m:(i + 1) * m] = Pi
        Mik = np.kron(Mi, np.eye(m))
        K = Mik @ _blockdiag_gain(rotated_gains) @ (M @ Rinv)
        P = Mik @ P_rot @ Mik.T
        blocks = (tuple(range(n)),)
        rotation = M
        Kc = None
    P = 0.5 * (P + P.T)
    B = J @ P @ J.T + W
    B = 0.5 * (B + B.T)
    taus = _closed_loop_time_constants(Phi - K @ J @ Phi, dt)
    if tuning == "noise" and isinstance(psd, str) and abs(np.max(taus) / time_constant_s - 1) > 1e-6:
        # e.g. many closely spaced harmonics: no PSD ratio reaches τ (the search saturates)
        raise ValueError(f"no process-noise PSD gives a slowest time constant of {time_constant_s} s"
                         f" (got {np.max(taus):.4g} s)")
    return FilterDesign(
        Phi=Phi, C=C, J=J, K=K, B=B, P_minus=P, Qd=Qd, W=W, omega=omega_d, dt=float(dt),
        harmonics=harmonics, low_frequency=low_frequency, rotor_stopped=stopped,
        slowest_time_constant_s=float(np.max(taus)), tuning=tuning,
        time_constant_s=float(time_constant_s), psd=q, R=R, geometry=geometry,
        blocks=blocks, labels=state_labels(harmonics, low_frequency),
        component_gain=None if Kc is None else Kc[:, 0].copy(),
        rotation=rotation, rotated_gains=rotated_gains,
    )


def _blockdiag_gain(gains: np.ndarray) -> np.ndarray:
    """(n, 6) gain with column i = k̃_i on the states of component i (component-major)."""
    nc, m = gains.shape
    Kb = np.zeros((nc * m, nc))
    for i in range(nc):
        Kb[i * m:(i + 1) * m, i] = gains[i]
    return Kb


class DesignCache:
    """Designs by Ω (model.md §5): a band ±``redesign_band`` (relative) around the design
    point, so Ω jitter does not make the gain chatter; new designs at Ω rounded on a
    relative grid of ``cache_resolution`` and kept (at most ``max_designs``, LRU).

    ``omega_min`` (rad/s): below it the rotor counts as stopped. ``design_for(None)`` means
    no rotor-speed data: the design at ``omega_default`` when given (the configured Ω),
    otherwise — a stopped rotor configured — the stopped design.
    """

    def __init__(
        self,
        model: RigModel,
        *,
        harmonics: tuple[int, ...] | list[int],
        dt: float,
        tuning: str = "time_constant",
        time_constant_s: float = 0.1,
        low_frequency: bool = True,
        psd: str | np.ndarray = "auto",
        alpha: np.ndarray | None = None,
        moment_floor: float = 100.0,
        frame: str | None = None,
        redesign_band: float = 0.005,
        cache_resolution: float = 0.001,
        omega_min: float = 0.0,
        omega_default: float | None = None,
        max_designs: int = 64,
    ) -> None:
        if not redesign_band >= 0 or not cache_resolution > 0:
            raise ValueError("redesign_band must be >= 0 and cache_resolution > 0")
        self.model = model
        self.harmonics = tuple(int(k) for k in harmonics)
        self.dt = float(dt)
        self.low_frequency = bool(low_frequency)
        self.redesign_band = float(redesign_band)
        self.cache_resolution = float(cache_resolution)
        self.omega_min = float(omega_min)
        self.omega_default = omega_default
        self.max_designs = int(max_designs)
        # design_filter's keyword arguments (each of its own type)
        self._kw: dict[str, Any] = {"harmonics": self.harmonics, "dt": self.dt, "tuning": tuning,
                    "time_constant_s": time_constant_s, "low_frequency": self.low_frequency,
                    "psd": psd, "alpha": alpha, "moment_floor": moment_floor, "frame": frame}
        self._designs: OrderedDict[int, FilterDesign] = OrderedDict()
        self._stopped: FilterDesign | None = None
        self._last: FilterDesign | None = None
        self.designs_made = 0

    def is_stopped(self, omega: float | None) -> bool:
        if omega is None:
            omega = self.omega_default
        return omega is None or not omega > 0.0 or omega < self.omega_min

    def _grid(self, omega: float) -> tuple[int, float]:
        step = np.log1p(self.cache_resolution)
        key = round(float(np.log(omega) / step))
        return key, float(np.exp(key * step))

    def prefill(self, omega_lo: float, omega_hi: float) -> int:
        """Design every grid point in [omega_lo, omega_hi] now (a design takes ~10–60 ms,
        longer than a sample period: call this at start-up for the expected Ω range so that
        a redesign in the real-time thread is a cache hit). Returns the number designed;
        at most ``max_designs`` are kept."""
        lo, hi = self._grid(max(omega_lo, self.omega_min, 1e-9))[0], self._grid(omega_hi)[0]
        made = 0
        for key in range(lo, hi + 1):
            if key not in self._designs and len(self._designs) < self.max_designs:
                omega_d = float(np.exp(key * np.log1p(self.cache_resolution)))
                self._designs[key] = design_filter(self.model, omega=omega_d, **self._kw)
                self.designs_made += 1
                made += 1
        return made

    def has_design(self, omega: float | None, current: FilterDesign | None = None) -> bool:
        """Whether :meth:`design_for` would return at once (the design in use, or one
        cached), not design a filter (~10–60 ms)."""
        ref = self._last if current is None else current
        if omega is None:
            omega = self.omega_default
        if omega is None or self.is_stopped(omega):
            return self._stopped is not None
        if (ref is not None and not ref.rotor_stopped
                and abs(omega / ref.omega - 1.0) <= self.redesign_band):
            return True
        return self._grid(omega)[0] in self._designs

    def design_for(self, omega: float | None, current: FilterDesign | None = None) -> FilterDesign:
        """The design to use at rotor speed ``omega``.

        ``current``: the design in use (default: the one this cache returned last); it is
        kept while Ω stays within the band around its design point.
        """
        ref = self._last if current is None else current
        if omega is None:
            omega = self.omega_default
        if omega is None or self.is_stopped(omega):
            if self._stopped is None:
                self._stopped = design_filter(self.model, omega=None, **self._kw)
                self.designs_made += 1
            self._last = self._stopped
            return self._stopped
        if (ref is not None and not ref.rotor_stopped
                and abs(omega / ref.omega - 1.0) <= self.redesign_band):
            self._last = ref
            return ref
        key, omega_d = self._grid(omega)
        d = self._designs.get(key)
        if d is None:
            d = design_filter(self.model, omega=omega_d, **self._kw)
            self.designs_made += 1
            self._designs[key] = d
            while len(self._designs) > self.max_designs:
                self._designs.popitem(last=False)
        else:
            self._designs.move_to_end(key)
        self._last = d
        return d


class StepResult(NamedTuple):
    H: np.ndarray | None  # (6,) Ĥ, None when invalid
    x: np.ndarray  # (n,) x⁺ (x⁻ on a predict-only step); a fresh array, not the state
    e: np.ndarray | None  # (6,) innovation, None on a predict-only step
    nis: float | None  # eᵀ B⁻¹ e
    flags: tuple[str, ...]


def _wrench(geometry: Geometry | None, alpha: np.ndarray) -> np.ndarray:
    """S from the 14 angles, or S itself when a (6, 7) matrix is passed."""
    a = np.asarray(alpha, float)
    if a.ndim == 2:
        return a
    if geometry is None:
        raise ValueError("the design carries no geometry: pass S (6, 7) instead of angles")
    return wrench_matrix(geometry, a)


def map_state(old: FilterDesign, new: FilterDesign, x: np.ndarray) -> np.ndarray:
    """Carry the state over a redesign (an Ω redesign is no discontinuity, model §5).

    States with the same label (harmonic, component, derivative) carry over unchanged —
    they are physical loads and load rates, valid at any Ω. When the new design has the
    random walks, whatever Ĥ the dropped states held is folded into H_0 so that Ĥ = C x is
    continuous (e.g. the rotor stopping: the harmonics' instantaneous value goes to H_0).
    """
    if old.labels == new.labels:
        return x.copy()
    where = {lab: i for i, lab in enumerate(old.labels)}
    xn = np.zeros(new.n_states)
    for j, lab in enumerate(new.labels):
        i = where.get(lab)
        if i is not None:
            xn[j] = x[i]
    if new.low_frequency:
        xn[low_frequency_states(new.harmonics)] += old.C @ x - new.C @ xn
    return xn


class HarmonicPairs(NamedTuple):
    """The (H_k,c, Ḣ_k,c) state pairs of a design: indices, harmonic order k, and k Ω_d."""

    i0: np.ndarray  # (P,) index of H_k,c
    i1: np.ndarray  # (P,) index of Ḣ_k,c
    k: np.ndarray  # (P,) harmonic order
    w: np.ndarray  # (P,) k Ω_d (rad/s)


def harmonic_pairs(design: FilterDesign) -> HarmonicPairs:
    i0 = [i for i, (k, _c, o) in enumerate(design.labels) if k > 0 and o == 0]
    i1 = [i + 1 for i in i0]
    assert all(design.labels[j][2] == 1 for j in i1)
    k = np.array([design.labels[i][0] for i in i0], float)
    return HarmonicPairs(np.array(i0, int), np.array(i1, int), k, k * design.omega)


def azimuth_transition(design: FilterDesign, dpsi: float | np.ndarray) -> np.ndarray:
    """Φ of one step in which the rotor turned by ``dpsi`` (rad; scalar → (n, n), array (N,)
    → (N, n, n)): per harmonic k the block [[c, s/w], [−w s, c]], c, s = cos, sin(k Δψ),
    w = k Ω_d — in (H, Ḣ/(kΩ_d)) the rotation by kΔψ, exactly the design's Φ at
    Δψ = Ω_d Δt; identity on the random walks (model §5)."""
    d = np.atleast_1d(np.asarray(dpsi, float))
    hp = harmonic_pairs(design)
    n = design.n_states
    Phi = np.broadcast_to(np.eye(n), (len(d), n, n)).copy()
    a = d[:, None] * hp.k[None, :]
    c, s = np.cos(a), np.sin(a)
    Phi[:, hp.i0, hp.i0] = c
    Phi[:, hp.i1, hp.i1] = c
    Phi[:, hp.i0, hp.i1] = s / hp.w
    Phi[:, hp.i1, hp.i0] = -s * hp.w
    return Phi[0] if np.ndim(dpsi) == 0 else Phi


class AzimuthTracker:
    """The rotor's turn Δψ since the last sample from the measured azimuth (mod 2π).

    ``step(azimuth, omega, steps)``: ``steps`` sample periods since the last call (1 + lost).
    The turn is unwrapped around the expected ``steps·Ω·Δt`` (Ω the measured speed when given,
    else ``omega_ref``) and refused (None) when it differs from it by more than ``tolerance``
    of it — a frozen, jumping or stale azimuth — or when the azimuth or the previous one is
    missing: the caller then advances by the design's Ω (today's behaviour) and flags it.
    """

    def __init__(self, omega_ref: float, dt: float, tolerance: float = 0.1) -> None:
        self.omega_ref, self.dt, self.tolerance = float(omega_ref), float(dt), float(tolerance)
        self._last: float | None = None
        self.refused = 0  # implausible turns (counted)

    def reset(self) -> None:
        self._last = None

    def step(self, azimuth: float | None, omega: float | None = None, steps: int = 1
             ) -> float | None:
        last, self._last = self._last, None
        if azimuth is None or not np.isfinite(azimuth):
            return None
        az = float(azimuth)
        self._last = az
        if last is None:
            return None
        w = omega if omega is not None and np.isfinite(omega) and omega > 0 else self.omega_ref
        expected = w * self.dt * steps
        d = expected + float(np.remainder(az - last - expected + np.pi, 2 * np.pi) - np.pi)
        if not abs(d - expected) <= self.tolerance * expected:
            self.refused += 1
            return None
        return d

    def turns(self, azimuth: np.ndarray, omega: np.ndarray | None = None,
              seq: np.ndarray | None = None) -> np.ndarray:
        """Δψ of every sample of a window (NaN where refused or missing; the first is NaN
        unless the tracker saw the sample before it): the batch form of :meth:`step`."""
        az = np.asarray(azimuth, float)
        om = np.full(len(az), np.nan) if omega is None else np.asarray(omega, float)
        steps = np.ones(len(az), int) if seq is None else np.diff(
            np.concatenate([[seq[0] - 1], seq])).astype(int)
        out = np.full(len(az), np.nan)
        for i in range(len(az)):
            v = self.step(az[i], om[i], int(max(steps[i], 1)))
            if v is not None:
                out[i] = v
        return out


class LoadFilter:
    """The per-sample fixed-gain filter (live service, bit-exact replay).

    One fused product per measured step: [x⁺; Ĥ; e; L⁻¹e] = G [x⁺(n−1); z; T] with
    G built from Φ, K, J, C, S(α) and the Cholesky factor L of B (nis = |L⁻¹e|²).
    """

    def __init__(self, cache: DesignCache, alpha: np.ndarray, invalid_after_samples: int,
                 *, omega: float | None = None, azimuth: bool = False) -> None:
        self._cache = cache
        # azimuth mode : x⁻ = Φ(Δψ) x⁺(n−1) from the rotor's measured turn, then
        # the fused product on [x⁻; z; T]; the gain is the design's, held (AZIMUTH_GAIN_BAND)
        self.azimuth = bool(azimuth)
        self._invalid_after = int(invalid_after_samples)
        self._S = _wrench(cache.model.geometry, alpha)
        self._design = cache.design_for(omega, current=None)
        self._run = 0  # consecutive predict-only (and lost) samples
        self._build(np.zeros(self._design.n_states))

    # -- design-dependent precomputation -------------------------------------------------
    def _build(self, x: np.ndarray) -> None:
        """Precompute for the current design and S; ``x`` the state to continue from."""
        d = self._design
        n = d.n_states
        # [x⁺(n−1); z; T]: the state lives in the first n entries between steps.
        self._buf = np.zeros(n + N_COMPONENTS + self._S.shape[1])
        self._buf[:n] = x
        if self.azimuth:  # G acts on [x⁻; z; T]: Φ(Δψ) is applied before it
            JPhi = d.J
            A = np.eye(n) - d.K @ d.J
            hp = harmonic_pairs(d)
            self._pairs = hp
            self._kset, self._kidx = np.unique(hp.k, return_inverse=True)
        else:
            JPhi = d.J @ d.Phi
            A = d.Phi - d.K @ JPhi
        Linv = np.linalg.inv(cholesky(d.B, lower=True))
        S = self._S
        I6 = np.eye(N_COMPONENTS)
        E = np.hstack([-JPhi, I6, -S])  # e = z − S T − J Φ x
        Xp = np.hstack([A, d.K, -d.K @ S])  # x⁺ = Φ x + K e
        G = np.vstack([Xp, d.C @ Xp, E, Linv @ E])
        self._G = np.ascontiguousarray(G)
        self._n = n
        self._Phi = d.Phi
        self._C = d.C
        self._phi_pow: dict[int, np.ndarray] = {}
        stopped = (ROTOR_STOPPED,) if d.rotor_stopped else ()
        self._flags = stopped
        self._flags_lost = (LOST_BEFORE,) + stopped
        self._flags_pred = (PREDICT_ONLY,) + stopped
        self._flags_pred_lost = (PREDICT_ONLY, LOST_BEFORE) + stopped
        self._flags_inv = (PREDICT_ONLY, INVALID) + stopped
        self._flags_inv_lost = (PREDICT_ONLY, INVALID, LOST_BEFORE) + stopped

    def _phi_power(self, k: int) -> np.ndarray:
        M = self._phi_pow.get(k)
        if M is None:
            M = np.linalg.matrix_power(self._Phi, k)
            if len(self._phi_pow) < 64:  # bounded: gaps of the same length recur
                self._phi_pow[k] = M
        return M

    # -- public API ----------------------------------------------------------------------
    @property
    def design(self) -> FilterDesign:
        return self._design

    @property
    def state(self) -> np.ndarray:
        return self._buf[:self._n].copy()

    @property
    def predict_only_run(self) -> int:
        return self._run

    def reset(self, x0: np.ndarray | None = None) -> None:
        x = np.zeros(self._n) if x0 is None else np.array(x0, float)
        if x.shape != (self._n,):
            raise ValueError(f"x0 must have shape ({self._n},), got {x.shape}")
        self._buf[:self._n] = x
        self._run = 0

    def set_alpha(self, alpha: np.ndarray) -> None:
        """New angles from the sample after this one on. The estimate moves at once to the
        one the new angles give: with the last measured T, the static estimate changes by
        R⁻¹ (S_old − S_new) T, and the random-walk states take that change. Left alone they
        would see it as a step in the innovations and follow it with the filter's time
        constant — a transient of several times the static bound under large loads."""
        S_new = _wrench(self._cache.model.geometry, alpha)
        x = self.state
        d = self._design
        lf = [i for i, (k, _c, _o) in enumerate(d.labels) if k == 0]
        if lf:
            T_last = self._buf[self._n + N_COMPONENTS:]
            assert d.R is not None  # design_filter sets it
            dH = np.linalg.solve(d.R, (self._S - S_new) @ T_last)
            comps = [d.labels[i][1] for i in lf]
            x[lf] += dH[comps]
        self._S = S_new
        self._build(x)

    def set_omega(self, omega: float | None) -> None:
        if (self.azimuth and omega is not None and not self._design.rotor_stopped
                and not self._cache.is_stopped(omega)
                and abs(omega / self._design.omega - 1.0) <= AZIMUTH_GAIN_BAND):
            return  # the azimuth turns the harmonics: the gain is held
        new = self._cache.design_for(omega, current=self._design)
        if new is self._design:
            return
        x = map_state(self._design, new, self.state)
        self._design = new
        self._build(x)

    def _advance(self, dpsi: float | None, steps: int) -> bool:
        """Azimuth mode: x⁻ = Φ(Δψ) x⁺ in place (``dpsi`` the turn over ``steps`` sample
        periods), or Φ_d^steps when it is None (returns False: flag ``azimuth_missing``)."""
        buf, n = self._buf, self._n
        if dpsi is None or self._design.rotor_stopped:
            buf[:n] = self._phi_power(steps).dot(buf[:n]) if steps > 1 else self._Phi.dot(buf[:n])
            return dpsi is not None or self._design.rotor_stopped
        hp = self._pairs
        a = self._kset * dpsi
        c, s = np.cos(a)[self._kidx], np.sin(a)[self._kidx]
        h, hd = buf[hp.i0], buf[hp.i1]
        buf[hp.i0] = c * h + (s / hp.w) * hd
        buf[hp.i1] = c * hd - (s * hp.w) * h
        return True

    def step(self, T: np.ndarray, z: np.ndarray, measured: bool = True, lost: int = 0,
             dpsi: float | None = None) -> StepResult:
        """One sample. ``lost``: samples lost just before this one (predicted through with
        Φ^lost); ``measured`` False: a predict-only step (a required channel missing,
        over-range or faulted). Ĥ is None after ``invalid_after_samples`` such samples.
        ``dpsi`` (azimuth mode): the rotor's turn since the last sample, over the lost ones
        too (``AzimuthTracker``); None: the design's Ω, flagged ``azimuth_missing``.
        The arrays returned are fresh each step (not the filter's own state)."""
        if self.azimuth:
            return self._step_azimuth(T, z, measured, lost, dpsi)
        buf, n = self._buf, self._n
        if lost:
            buf[:n] = self._phi_power(lost).dot(buf[:n])
            self._run += lost
        if measured:
            return self._measured(T, z, lost)
        x = self._Phi.dot(buf[:n])
        buf[:n] = x
        return self._predicted(x, lost)

    def _step_azimuth(self, T: np.ndarray, z: np.ndarray, measured: bool, lost: int,
                      dpsi: float | None) -> StepResult:
        n = self._n
        extra = () if self._advance(dpsi, lost + 1) else (AZIMUTH_MISSING,)
        if lost:
            self._run += lost
        if measured:
            return self._measured(T, z, lost, extra)
        return self._predicted(self._buf[:n].copy(), lost, extra)

    def _measured(self, T: np.ndarray, z: np.ndarray, lost: int,
                  extra: tuple[str, ...] = ()) -> StepResult:
        """The update of a measured sample (the state already predicted to it): one product
        with the stacked gain matrix G, the run of predict-only steps ended."""
        buf, n = self._buf, self._n
        buf[n:n + 6] = z
        buf[n + 6:] = T
        y = self._G.dot(buf)
        buf[:n] = y[:n]
        self._run = 0
        w = y[n + 12:]
        return StepResult(y[n:n + 6], y[:n], y[n + 6:n + 12], w.dot(w),
                          (self._flags_lost if lost else self._flags) + extra)

    def _predicted(self, x: np.ndarray, lost: int, extra: tuple[str, ...] = ()) -> StepResult:
        """A predict-only step's result at the predicted state ``x``: Ĥ from the prediction,
        None once ``invalid_after_samples`` such steps have run in a row."""
        self._run += 1
        if self._run >= self._invalid_after:
            return StepResult(None, x, None, None,
                              (self._flags_inv_lost if lost else self._flags_inv) + extra)
        return StepResult(self._C.dot(x), x, None, None,
                          (self._flags_pred_lost if lost else self._flags_pred) + extra)


class BatchResult:
    """The batch filter's output: ``x_plus`` (N, n), ``e`` (N, 6), ``H`` (N, 6), ``x_last`` (n,).

    ``x_plus`` is computed on first access: replays and identification windows need Ĥ, e
    and the final state, and the whole state history costs more than all of those together.
    Unpacks like a tuple ``(x_plus, e, H, x_last)``.
    """

    __slots__ = ("H", "_make", "_x_plus", "e", "x_last")

    def __init__(self, x_plus: np.ndarray | None, e: np.ndarray, H: np.ndarray,
                 x_last: np.ndarray, make: Callable[[], np.ndarray] | None = None) -> None:
        self.e, self.H, self.x_last = e, H, x_last
        self._x_plus, self._make = x_plus, make

    @property
    def x_plus(self) -> np.ndarray:
        if self._x_plus is None:
            assert self._make is not None  # given with x_plus=None
            self._x_plus = self._make()
            self._make = None
        return self._x_plus

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter((self.x_plus, self.e, self.H, self.x_last))


def _modes(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lam, V = np.linalg.eig(A)
    return lam.astype(complex), V.astype(complex), np.linalg.inv(V).astype(complex)


def _modal_states(A: np.ndarray, K: np.ndarray, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x(n) = A x(n−1) + K u(n), n = 0..N−1, x(−1) = x0, by modes: ξ = V⁻¹ x, each ξ_j a
    first-order recursion run by ``lfilter``; one mode of each conjugate pair is filtered
    (u is real, so its partner is the conjugate). Returns (N, m)."""
    lam, V, Vi = _modes(A)
    keep = np.flatnonzero(lam.imag >= 0)
    G = Vi[keep] @ K  # (M, inputs)
    xi0 = Vi[keep] @ x0
    uT = u.T
    drive = (G.real @ uT) + 1j * (G.imag @ uT)  # (M, N), rows contiguous
    xi = np.empty_like(drive)
    for j, i in enumerate(keep):
        lj = lam[i]
        if lj.imag == 0:
            xi[j] = lfilter([1.0], [1.0, -lj.real], drive[j].real, zi=[lj.real * xi0[j].real])[0]
        else:
            xi[j] = lfilter([1.0], [1.0, -lj], drive[j], zi=[lj * xi0[j]])[0]
    Vk = V[:, keep] * np.where(lam[keep].imag > 0, 2.0, 1.0)  # a pair adds 2 Re(v ξ)
    result: np.ndarray = (xi.real.T @ Vk.real.T) - (xi.imag.T @ Vk.imag.T)
    return result


def _x_plus_modal(design: FilterDesign, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    A = design.closed_loop
    xp = np.empty((u.shape[0], design.n_states))
    for blk in design.blocks or (tuple(range(design.n_states)),):
        ix = np.asarray(blk)
        xp[:, ix] = _modal_states(A[np.ix_(ix, ix)], design.K[ix], u, x0[ix])
    return xp


def _siso_sos(A: np.ndarray, b: np.ndarray, c: np.ndarray, d: float) -> np.ndarray:
    """Second-order sections of y = (c (qI − A)⁻¹ b + d) u, d ≠ 0: poles eig(A), zeros the
    invariant zeros eig(A − b c / d) — eigenvalues, not polynomial roots, for accuracy."""
    zeros = np.linalg.eigvals(A - np.outer(b, c) / d)
    poles = np.linalg.eigvals(A)
    # complex zeros and poles (conjugate pairs): scipy takes them, scipy-stubs types them real
    sos: np.ndarray = zpk2sos(zeros, poles, d)  # type: ignore[arg-type]  # complex z, p: above
    return sos


def _decay_samples(lam: np.ndarray, V: np.ndarray, N: int, tail: float = 1e-20) -> int:
    """Samples after which every mode has decayed below ``tail`` (relative, with cond V)."""
    rmax = float(np.max(np.abs(lam)))
    if rmax >= 1.0:
        return N
    if rmax == 0.0:
        return min(N, 1)
    n = int(np.ceil(np.log(tail / np.linalg.cond(V)) / np.log(rmax))) + 1
    return min(N, max(n, 1))


class _Group(NamedTuple):
    """Rotated components sharing one gain k: x̃(n) = A x̃(n−1) + k y(n), A = (I − k c) Φ_c."""

    rows: slice | np.ndarray
    k: np.ndarray  # (m,)
    A: np.ndarray  # (m, m)
    sos: np.ndarray  # innovation filter ẽ = [Π(1 − p q⁻¹) / Π(1 − λ q⁻¹)] y, p ∈ eig Φ_c
    h: float  # 1 − c k:  Ĥ' = c x̃⁺ = c Φ_c x̃(n−1) + c k ẽ = y − (1 − c k) ẽ
    lam: np.ndarray  # (m,) modes of A, V, V⁻¹
    V: np.ndarray
    Vi: np.ndarray
    e_x0: np.ndarray  # (nf, m): row n = λⁿ ∘ (−c Φ_c V), ẽ's response to x̃(−1) in modes
    Ak_rev: np.ndarray  # (nf, m): row nf−1−j = A^j k (the inputs that still matter for x̃(N−1))


class _Plan(NamedTuple):
    """Design-dependent part of the batch path (made once per design, cached weakly)."""

    m: int
    M: np.ndarray | None  # rotation (None: identity)
    Mi: np.ndarray | None  # M⁻¹
    P: np.ndarray  # (6, 6) M R⁻¹: y = P (z − S T)
    R_Mi: np.ndarray  # (6, 6) R M⁻¹: e = R M⁻¹ ẽ
    groups: tuple[_Group, ...]


_PLANS: weakref.WeakKeyDictionary[FilterDesign, _Plan | None] = weakref.WeakKeyDictionary()  # bounded by live designs


def _make_plan(design: FilterDesign) -> _Plan | None:
    """The six single-output filters of a design, or None when it lacks that structure
    (checked on its own Φ, C and K, so a design built or altered elsewhere is never run
    through a decomposition it does not satisfy)."""
    M, gains = design.rotation, design.rotated_gains
    n = design.n_states
    m = n // N_COMPONENTS
    if M is None or gains is None or design.R is None or gains.shape != (N_COMPONENTS, m):
        return None
    I6 = np.eye(N_COMPONENTS)
    Phi_c, c = design.Phi[:m, :m], design.C[0, :m]
    if (np.max(np.abs(design.Phi - np.kron(I6, Phi_c))) > 1e-12 * np.max(np.abs(Phi_c))
            or not np.array_equal(design.C, np.kron(I6, c[None, :]))):
        return None
    Mi = np.linalg.inv(M)
    Rinv = np.linalg.inv(design.R)
    K = np.kron(Mi, np.eye(m)) @ _blockdiag_gain(gains) @ (M @ Rinv)
    if np.max(np.abs(K - design.K)) > 1e-12 * np.max(np.abs(design.K)):
        return None
    groups = []
    done = np.zeros(N_COMPONENTS, bool)
    for i in range(N_COMPONENTS):  # components with the same gain share one filter call
        if done[i]:
            continue
        same = np.flatnonzero(np.all(gains == gains[i], axis=1) & ~done)
        done[same] = True
        rows = slice(same[0], same[-1] + 1) if np.all(np.diff(same) == 1) else same
        k = gains[i].copy()
        cPhi = c @ Phi_c
        A = Phi_c - np.outer(k, cPhi)
        lam, V, Vi = _modes(A)
        nf = _decay_samples(lam, V, 1 << 40)
        if nf >= 1 << 40:  # not a stable closed loop: no decomposition into decaying modes
            return None
        powers = lam[None, :] ** np.arange(nf)[:, None]
        groups.append(_Group(
            rows=rows, k=k, A=A, sos=_siso_sos(A, k, -cPhi, 1.0), h=float(1.0 - c @ k),
            lam=lam, V=V, Vi=Vi, e_x0=powers * (-cPhi @ V)[None, :],
            Ak_rev=np.ascontiguousarray(((powers * (Vi @ k)[None, :]) @ V.T).real[::-1])))
    identity = np.array_equal(M, I6)
    return _Plan(m=m, M=None if identity else M, Mi=None if identity else Mi,
                 P=Rinv if identity else M @ Rinv, R_Mi=design.R if identity else design.R @ Mi,
                 groups=tuple(groups))


def _plan(design: FilterDesign) -> _Plan | None:
    try:
        return _PLANS[design]
    except KeyError:
        plan = _PLANS[design] = _make_plan(design)
        return plan


def _group_states(g: _Group, Y: np.ndarray, X0: np.ndarray) -> np.ndarray:
    """x̃(n) = A x̃(n−1) + k y(n) of every row of Y (rows, N) from x̃(−1) = X0 (rows, m), by
    modes: ξ = V⁻¹ x̃, one first-order ``lfilter`` per mode over all rows at once; one mode
    of each conjugate pair (its partner is the conjugate). Returns (N, rows, m)."""
    rows, N = Y.shape
    out = np.zeros((N, rows, g.A.shape[0]))
    for j in np.flatnonzero(g.lam.imag >= 0):
        lj, vj = g.lam[j], g.V[:, j]
        gj, xi0 = g.Vi[j] @ g.k, X0 @ g.Vi[j]
        if lj.imag == 0:
            xi = lfilter([1.0], [1.0, -lj.real], gj.real * Y, axis=-1,
                         zi=(lj.real * xi0.real)[:, None])[0]
            out += xi.T[:, :, None] * vj.real
        else:  # a pair adds 2 Re(v ξ)
            xi = lfilter([1.0], [1.0, -lj], gj * Y, axis=-1, zi=(lj * xi0)[:, None])[0].T
            out += 2.0 * (xi.real[:, :, None] * vj.real - xi.imag[:, :, None] * vj.imag)
    return out


_CHUNK = 4096  # columns per BLAS call in ``_dot_cols``


def _dot_cols(A: np.ndarray, X: np.ndarray, A2: np.ndarray | None = None,
              X2: np.ndarray | None = None) -> np.ndarray:
    """A X (+ A2 X2), X (k, N) of any layout (e.g. z.T), as a C-contiguous (p, N), in blocks
    of ``_CHUNK`` columns: one call over all N columns of such a skinny product is large
    enough for OpenBLAS to use every thread, and on a shared machine that took 15–35 ms
    instead of 0.25 ms (measured, N = 40 000, 2 loaded cores); blocks stay single-threaded
    and in cache."""
    N = X.shape[1]
    out = np.empty((A.shape[0], N))
    for s in range(0, N, _CHUNK):
        blk = np.dot(A, X[:, s:s + _CHUNK])
        if A2 is not None:
            assert X2 is not None  # given with A2
            blk += np.dot(A2, X2[:, s:s + _CHUNK])
        out[:, s:s + _CHUNK] = blk
    return out


def _batch_rotated(design: FilterDesign, plan: _Plan, S: np.ndarray, T: np.ndarray,
                   z: np.ndarray, x0: np.ndarray) -> BatchResult:
    """Six single-output filters in y = M R⁻¹ (z − S T), x̃ = (M ⊗ I) x (``FilterDesign``).

    Per rotated component only the innovation ẽ is filtered — one IIR filter whose zeros are
    the open-loop poles eig Φ_c and whose poles are the closed loop's, as second-order
    sections over all rows sharing a gain; Ĥ' = y − (1 − c k) ẽ needs no filter. The response
    to x0 is added by modes; e = R M⁻¹ ẽ, Ĥ = M⁻¹ Ĥ'. Nothing of size N × n is made unless
    ``x_plus`` is asked for."""
    N, m = z.shape[0], plan.m
    P, Q = plan.P, -(plan.P @ S)
    y = _dot_cols(P, z.T, Q, T.T)  # (6, N), rows contiguous for sosfilt
    X0 = x0.reshape(N_COMPONENTS, m)
    if plan.M is not None:
        X0 = plan.M @ X0
    X_last = np.empty((N_COMPONENTS, m))
    e = None if len(plan.groups) == 1 else np.empty_like(y)
    for g in plan.groups:
        yr = y[g.rows]
        er = sosfilt(g.sos, yr, axis=-1)
        nf = min(N, g.e_x0.shape[0])
        z0 = X0[g.rows] @ g.Vi.T  # modal x̃(−1), one row per component
        # einsum, not BLAS: a (1, m) × (m, nf) product is a gemv that OpenBLAS threads, and
        # waking threads on a loaded machine cost 7–20 ms per call (measured).
        er[:, :nf] += np.einsum("rj,nj->rn", z0, g.e_x0[:nf]).real  # −c Φ_c Aⁿ x̃(−1)
        # x̃(N−1) = A^N x̃(−1) + Σ_{j<nf} A^j k y(N−1−j): older inputs decayed below 1e-20
        X_last[g.rows] = (np.einsum("rn,nj->rj", yr[:, N - nf:], g.Ak_rev[-nf:])
                          + ((z0 * g.lam**N) @ g.V.T).real)
        if isinstance(g.rows, slice):
            yr -= g.h * er  # now Ĥ' (a view: y itself is no longer needed)
        else:
            y[g.rows] = yr - g.h * er
        if e is None:
            e = er
        else:
            e[g.rows] = er
    del yr, er  # views that would keep the pre-mixing arrays alive
    assert e is not None  # a plan has one group at least
    if plan.Mi is not None:
        y = _dot_cols(plan.Mi, y)
        X_last = plan.Mi @ X_last
    e = _dot_cols(plan.R_Mi, e)

    def make() -> np.ndarray:
        Y = _dot_cols(P, z.T, Q, T.T)
        Xt = np.empty((N, N_COMPONENTS, m))
        for g in plan.groups:
            Xt[:, g.rows] = _group_states(g, Y[g.rows], X0[g.rows])
        if plan.Mi is not None:  # x = (M⁻¹ ⊗ I) x̃
            Xt = np.einsum("ai,nis->nas", plan.Mi, Xt)
        return Xt.reshape(N, N_COMPONENTS * m)

    return BatchResult(None, e.T, y.T, X_last.reshape(-1), make=make)


def filter_batch(design: FilterDesign, alpha: np.ndarray, T: np.ndarray, z: np.ndarray,
                 x0: np.ndarray | None = None) -> BatchResult:
    """The recursion of ``LoadFilter.step`` (every sample measured) over whole arrays.

    Linear time-invariant for one design: x⁺(n) = (I − KJ)Φ x⁺(n−1) + K u(n) with
    u = z − S T; e(n) = u(n) − JΦ x⁺(n−1); Ĥ = C x⁺. Designs of ``design_filter`` (both
    tunings) run as six single-output filters (``_batch_rotated``); any other design mode
    by mode over the whole state. ``alpha``: the 14 angles or S (6, 7). ``H`` and ``e`` may
    be transposed views (not C-contiguous).
    """
    S = _wrench(design.geometry, alpha)
    T = np.asarray(T, float)
    z = np.asarray(z, float)
    N, n = z.shape[0], design.n_states
    x0 = np.zeros(n) if x0 is None else np.asarray(x0, float)
    if x0.shape != (n,):
        raise ValueError(f"x0 must have shape ({n},), got {x0.shape}")
    if N == 0:
        return BatchResult(np.zeros((0, n)), np.zeros((0, 6)), np.zeros((0, 6)), x0.copy())
    plan = _plan(design)
    if plan is not None:
        return _batch_rotated(design, plan, S, T, z, x0)
    u = z - T @ S.T
    xp = _x_plus_modal(design, u, x0)
    JPhi = design.J @ design.Phi
    e = np.empty_like(u)
    e[0] = u[0] - JPhi @ x0
    e[1:] = u[1:] - xp[:-1] @ JPhi.T
    return BatchResult(xp, e, xp @ design.C.T, xp[-1].copy())
