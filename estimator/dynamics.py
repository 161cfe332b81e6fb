"""Dynamic model of the hub loads (model.md §5; report Eq 2.2–2.9, 2.29).

Each of the six hub-load components c is a sum of undamped oscillators at the modelled
harmonics k of the rotor speed Ω, plus optionally a random-walk (Wiener) low-frequency state:

    Ḧ_k,c = −(kΩ)² H_k,c + η_k,c        Ḣ_0,c = η_0,c        H_c = H_0,c + Σ_k H_k,c

State layout (the contract of this module; ``state_labels`` spells it out): component-major,
m = 2·n_h (+1) states per component, component c owning ``x[c·m:(c+1)·m]``:

* harmonic index h (position of k in ``harmonics``): ``x[c·m + 2h] = H_k,c``,
  ``x[c·m + 2h + 1] = Ḣ_k,c``;
* then, when ``low_frequency``, ``x[c·m + 2·n_h] = H_0,c``.

Each component is then a contiguous block (the time-constant design is block-diagonal in it).

Process noise ``psd`` (6,), one value q_c per component in N²/s (N²m²/s for moments): the
rate at which every in-phase and quadrature amplitude of component c diffuses. H_0,c is a
random walk of PSD q_c; an oscillator H_k,c = a cos kΩt + b sin kΩt whose a and b each
diffuse at q_c needs the input PSD 2 (kΩ)² q_c (E[d(a²+b²)]/dt = PSD/(kΩ)²). One number per
component then means the same thing for every harmonic and for the random walk.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

N_COMPONENTS = 6


@dataclass(frozen=True, eq=False)
class HubLoadDynamics:
    """Continuous and discrete model of the hub loads for one Ω (see the module doc)."""

    harmonics: tuple[int, ...]
    omega: float
    dt: float
    low_frequency: bool
    F: np.ndarray  # (n, n) continuous dynamics
    Phi: np.ndarray  # (n, n) e^{F dt}
    C: np.ndarray  # (6, n): H = C x
    Qd: np.ndarray  # (n, n) discrete process noise (Van Loan) for psd; zeros without psd
    psd: np.ndarray  # (6,) per-component amplitude diffusion rates used for Qd

    @property
    def n_states(self) -> int:
        return int(self.F.shape[0])

    @property
    def state_labels(self) -> tuple[tuple[int, int, int], ...]:
        """(harmonic k (0 for the random walk), component c, derivative order) per state."""
        return state_labels(self.harmonics, self.low_frequency)

    def component_states(self, c: int) -> np.ndarray:
        """Indices of the states of component c (its harmonics, then its H_0,c)."""
        return component_states(self.harmonics, self.low_frequency, c)


def states_per_component(harmonics: tuple[int, ...], low_frequency: bool) -> int:
    return 2 * len(harmonics) + (1 if low_frequency else 0)


def state_labels(harmonics: tuple[int, ...], low_frequency: bool) -> tuple[tuple[int, int, int], ...]:
    labels = []
    for c in range(N_COMPONENTS):
        labels += [(k, c, d) for k in harmonics for d in (0, 1)]
        if low_frequency:
            labels.append((0, c, 0))
    return tuple(labels)


def component_states(harmonics: tuple[int, ...], low_frequency: bool, c: int) -> np.ndarray:
    m = states_per_component(harmonics, low_frequency)
    return np.arange(c * m, (c + 1) * m)


def low_frequency_states(harmonics: tuple[int, ...]) -> np.ndarray:
    """Indices of H_0,c (c = 0..5) in a model with low-frequency states."""
    m = states_per_component(harmonics, True)
    return np.arange(N_COMPONENTS) * m + 2 * len(harmonics)


def continuous_model(
    harmonics: tuple[int, ...], omega: float, low_frequency: bool, psd: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F, C and the continuous noise intensity Qc (all states, see the module doc)."""
    nh = len(harmonics)
    m = states_per_component(harmonics, low_frequency)
    n = N_COMPONENTS * m
    F = np.zeros((n, n))
    C = np.zeros((N_COMPONENTS, n))
    Qc = np.zeros((n, n))
    for c in range(N_COMPONENTS):
        for h, k in enumerate(harmonics):
            w2 = (k * omega) ** 2
            i = c * m + 2 * h
            F[i, i + 1] = 1.0
            F[i + 1, i] = -w2  # Ḧ = −(kΩ)² H (Eq 2.2)
            C[c, i] = 1.0
            Qc[i + 1, i + 1] = 2.0 * w2 * psd[c]
        if low_frequency:
            i = c * m + 2 * nh
            C[c, i] = 1.0
            Qc[i, i] = psd[c]
    return F, C, Qc


def van_loan(F: np.ndarray, Qc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Φ = e^{F dt} and Qd = ∫₀^dt e^{Fs} Qc e^{Fᵀs} ds (Van Loan, 1978)."""
    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = Qc
    M[n:, n:] = F.T
    E = expm(M * dt)
    Phi = E[n:, n:].T
    Qd = Phi @ E[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)


def hub_load_dynamics(
    harmonics: tuple[int, ...] | list[int],
    omega: float,
    dt: float,
    low_frequency: bool,
    psd: np.ndarray | None = None,
) -> HubLoadDynamics:
    """The model of model §5 at rotor speed ``omega`` (rad/s) and sample period ``dt`` (s).

    ``psd``: (6,) per-component amplitude diffusion rates (module doc); None → Qd = 0.
    ``harmonics`` may be empty (stopped rotor: only the random walks).
    """
    harmonics = tuple(int(k) for k in harmonics)
    if harmonics and not omega > 0.0:
        raise ValueError(f"harmonic states need a positive rotor speed, got omega={omega!r}")
    if not harmonics and not low_frequency:
        raise ValueError("a hub-load model needs harmonics or low-frequency states")
    q = np.zeros(N_COMPONENTS) if psd is None else np.broadcast_to(
        np.asarray(psd, float), (N_COMPONENTS,)).copy()
    if np.any(q < 0) or not np.all(np.isfinite(q)):
        raise ValueError(f"process-noise PSDs must be finite and >= 0, got {q}")
    F, C, Qc = continuous_model(harmonics, float(omega or 0.0), low_frequency, q)
    Phi, Qd = van_loan(F, Qc, dt)
    return HubLoadDynamics(harmonics, float(omega or 0.0), float(dt), bool(low_frequency),
                           F, Phi, C, Qd, q)
