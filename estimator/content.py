"""Content filters of the identification (model.md §7.3 "What content to identify from").

One causal filter, applied alike to the load cells T, the inertial loads z and any known
loads, so that the balance I = S T + R H (+ D q) still holds exactly in the filtered data.

* ``static``: 4th-order Butterworth low-pass at half the 1/rev frequency (24 dB down at
  1/rev): the angular inertial loads the default rig neglects vanish at low frequency.
* ``harmonics``: the parallel sum of second-order peaking filters (``scipy.signal.iirpeak``,
  Q = 5) at the modelled harmonics (the report's Phase II band-pass). The plain sum is off
  at each harmonic because the other peaks' skirts add to it; each peak therefore gets a
  complex weight — realised as two real numerator coefficients, p·(1 − z⁻²) + q·(z⁻¹ − z⁻²),
  which keep the zero at DC so the static load stays out — solved so that the sum is
  exactly 1∠0° at every modelled harmonic.
* ``broadband``: identity.
* ``vibration``: 4th-order Butterworth high-pass at half the 1/rev frequency — everything but
  the static loads and manoeuvres (which the calibration filter, without low-frequency states,
  does not model): for filter-error runs on fuselage-borne vibration of a rig that measures its
  angular accelerations (docs/identification.md, the information rule).

Filters are returned as second-order sections (the parallel sum converted to a cascade with
its poles and zeros). ``ContentFilter`` keeps the filter state between calls.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, iirpeak, sosfilt, sosfilt_zi, zpk2sos

KINDS = ("static", "harmonics", "broadband", "vibration")
PEAK_Q = 5.0  # report Phase II band-pass (model.md §7)
STATIC_ORDER = 4
STATIC_CUTOFF_FRACTION = 0.5  # of the 1/rev frequency


def _one_per_rev_hz(omega: float) -> float:
    if not omega > 0:
        raise ValueError(f"the content filters need a positive rotor speed, got omega={omega!r}")
    return omega / (2.0 * np.pi)


def _harmonics_sos(fs: float, omega: float, harmonics: tuple[int, ...]) -> np.ndarray:
    f1 = _one_per_rev_hz(omega)
    freqs = np.array([k * f1 for k in harmonics], float)
    if np.any(freqs >= fs / 2):
        raise ValueError(f"harmonics {harmonics} at omega={omega} reach the Nyquist frequency {fs / 2} Hz")
    dens = [iirpeak(f, PEAK_Q, fs=fs)[1] for f in freqs]
    basis = (np.array([1.0, 0.0, -1.0]), np.array([0.0, 1.0, -1.0]))
    zm = np.exp(-1j * 2 * np.pi * freqs / fs)  # z⁻¹ at each harmonic
    M = len(freqs)
    # Response of branch k's two numerator terms at harmonic m: b(z)/a_k(z).
    G = np.zeros((M, 2 * M), complex)
    for k, a in enumerate(dens):
        ak = np.polyval(a[::-1], zm)  # a0 + a1 z⁻¹ + a2 z⁻²
        for j, b in enumerate(basis):
            G[:, 2 * k + j] = np.polyval(b[::-1], zm) / ak
    # Real weights: Re and Im of Σ w G = 1 at every harmonic (2M equations, 2M unknowns).
    w = np.linalg.solve(np.vstack([G.real, G.imag]), np.concatenate([np.ones(M), np.zeros(M)]))
    # Parallel sum Σ_k b_k / a_k = (Σ_k b_k Π_{j≠k} a_j) / Π_k a_k.
    num = np.zeros(2 * M + 1)
    for k in range(M):
        bk = w[2 * k] * basis[0] + w[2 * k + 1] * basis[1]
        others = np.array([1.0])
        for j in range(M):
            if j != k:
                others = np.convolve(others, dens[j])
        num += np.convolve(bk, others)
    poles = np.concatenate([np.roots(a) for a in dens])  # each a quadratic: accurate
    # num holds powers of z⁻¹, so its roots as a polynomial in z are the zeros (roots()
    # keeps trailing zero coefficients as zeros at the origin). Σ p_k ≠ 0 is the lead.
    if num[0] == 0:
        raise ValueError(f"degenerate harmonic weights for harmonics {harmonics}")
    # Every branch has b(1) = 0, so (1 − z⁻¹) divides num: keep that DC zero exact and find
    # the others from the deflated polynomial.
    rest, rem = np.polydiv(num, np.array([1.0, -1.0]))
    assert np.max(np.abs(rem)) <= 1e-9 * np.max(np.abs(num))
    zeros = np.concatenate([[1.0], np.roots(rest)])
    lead = num[0]
    return zpk2sos(zeros, poles, lead)


def design_content_filter(kind: str, fs: float, omega: float,
                          harmonics: tuple[int, ...] | list[int]) -> np.ndarray:
    """Second-order sections of the content filter ``kind`` at sample rate ``fs`` (Hz) and
    rotor speed ``omega`` (rad/s); ``harmonics`` the modelled multiples of 1/rev."""
    if kind == "broadband":
        return np.array([[1.0, 0.0, 0.0, 1.0, 0.0, 0.0]])
    if kind in ("static", "vibration"):
        f1 = _one_per_rev_hz(omega)
        return butter(STATIC_ORDER, STATIC_CUTOFF_FRACTION * f1,
                      btype="low" if kind == "static" else "high", fs=fs, output="sos")
    if kind == "harmonics":
        harmonics = tuple(int(k) for k in harmonics)
        if not harmonics:
            raise ValueError("the harmonics content filter needs at least one harmonic")
        return _harmonics_sos(fs, omega, harmonics)
    raise ValueError(f"content filter kind must be one of {KINDS}, not {kind!r}")


def slowest_time_constant_samples(sos: np.ndarray) -> float:
    """−1 / ln|p| of the slowest pole, in samples (0 for an FIR / identity)."""
    poles = np.concatenate([np.roots(s[3:]) for s in sos]) if len(sos) else np.array([])
    r = np.max(np.abs(poles)) if poles.size else 0.0
    return 0.0 if r == 0 else float(-1.0 / np.log(r))


class ContentFilter:
    """One content-filter design applied causally to ``n_channels`` independent columns,
    with its state kept between ``process`` calls (so chunks equal one long call).

    The state starts at the steady state of the first sample held constant — linear in
    the data, so the balance still holds in the filtered channels, and a static load does
    not ring through the start-up. ``settle_samples`` = ``settle_time_constants`` × the
    slowest pole's time constant (model.md §7: the transient is part of the settling).
    """

    def __init__(self, kind: str, fs: float, omega: float, harmonics: tuple[int, ...] | list[int],
                 n_channels: int, settle_time_constants: float = 5.0) -> None:
        self.kind = kind
        self.fs = float(fs)
        self.omega = float(omega) if omega is not None else None
        self.harmonics = tuple(int(k) for k in harmonics)
        self.n_channels = int(n_channels)
        self.sos = design_content_filter(kind, fs, omega, self.harmonics)
        self._identity = kind == "broadband"
        self._zi_unit = sosfilt_zi(self.sos)  # (sections, 2): steady state for a unit input
        self._zi: np.ndarray | None = None
        # the per-sample path (one row: the live estimator thread) runs the sections itself
        # with Python-float coefficients — the same operations in the same order as
        # scipy's sosfilt (direct form II transposed), bit for bit, without sosfilt's
        # per-call validation and reshaping (docs/performance.md)
        self._sections = [tuple(float(c) for c in row) for row in self.sos]
        self.settle_samples = int(np.ceil(settle_time_constants
                                          * slowest_time_constant_samples(self.sos)))

    def reset(self) -> None:
        """Forget the state: the next ``process`` starts again from its first sample."""
        self._zi = None

    def process(self, X: np.ndarray) -> np.ndarray:
        """Filter a block (N, n_channels); returns a new array of the same shape."""
        X = np.asarray(X, float)
        if X.ndim != 2 or X.shape[1] != self.n_channels:
            raise ValueError(f"expected (N, {self.n_channels}) samples, got {X.shape}")
        if self._identity or X.shape[0] == 0:
            return X.copy()
        if self._zi is None:
            self._zi = self._zi_unit[:, :, None] * X[0][None, None, :]
        if X.shape[0] == 1:
            return self._step(X[0])[None, :]
        Y: np.ndarray
        Y, self._zi = sosfilt(self.sos, X, axis=0, zi=self._zi)
        return Y

    def correct_past_inputs(self, E: np.ndarray) -> None:
        """The inputs of the last ``len(E)`` samples were off by the rows of ``E`` (oldest
        first): the state becomes what they would have left with ``E`` added (the filter is
        linear: the state ``E`` alone leaves from rest, added; its outputs stay as they
        were). Nothing before the first sample or for the identity."""
        E = np.asarray(E, float)
        if self._identity or self._zi is None or E.size == 0:
            return
        if E.ndim != 2 or E.shape[1] != self.n_channels:
            raise ValueError(f"expected (N, {self.n_channels}) corrections, got {E.shape}")
        _, zf = sosfilt(self.sos, E, axis=0, zi=np.zeros_like(self._zi))
        self._zi += zf  # in place: the compiled hub path steps this array

    def _step(self, x: np.ndarray) -> np.ndarray:
        """One sample through every section, the state updated in place: scipy's sosfilt
        loop (``y = b0 x + z0; z0 = b1 x − a1 y + z1; z1 = b2 x − a2 y``), elementwise."""
        zi = self._zi
        assert zi is not None  # process() sets it before the first step
        for s, (b0, b1, b2, _, a1, a2) in enumerate(self._sections):
            z = zi[s]
            y = b0 * x + z[0]
            z[0] = b1 * x - a1 * y + z[1]
            z[1] = b2 * x - a2 * y
            x = y
        return x


# -- samples lacking an input  ---------------------------------------------------
# samples: a longer gap of samples lacking an input stays held (the known-load benchmark's
# dropped samples; identification.md)
MAX_INTERPOLATED = 2


class MissingHold:
    """The content filter's input for samples lacking an input: the last complete sample
    held, every channel of it (load cells, inertial loads, known loads), so the balance
    I = S T + R H (+ D q) still holds exactly in the filtered data and the filtered loads keep
    their level. The identification leaves the held samples out (not scored); what the hold
    perturbs is the load content between two samples (at 1/rev a 2·sin(πf/fs) fraction of
    it), which the content filter attenuates like any other — zeros instead spread the
    whole harmonic load, and its modelling error, into the static band (measured: χ²₁₄ of
    146–305 against the true angles with 10 % of the samples zeroed, 7–10 held: the known-load benchmark's seed 7,
    windows 2–4). Before the first complete sample the input passes as it is.

    When a gap of at most ``max_interpolated`` samples closes, :meth:`correction` gives what
    the held inputs lacked against the straight line between the complete samples on either
    side (row j of g: (j / (g + 1)) · (x_next − x_last), oldest first): the content filter
    adds it to its state (:meth:`ContentFilter.correct_past_inputs`), so that from the next
    complete sample on its output is the one of the interpolated input, without delaying a
    sample (the filter is linear; the held samples' own outputs, not scored, stay). A
    straight line between two complete samples keeps the balance exact too; it leaks the
    load content a hold modulates into the static band to second order instead of first
    (the known-load benchmark's ``drop_cell_A`` arm: docs/identification.md). Longer gaps stay held."""

    def __init__(self, max_interpolated: int = MAX_INTERPOLATED) -> None:
        self.last: np.ndarray | None = None
        self.max_interpolated = int(max_interpolated)
        self.held = 0  # samples held since ``last``
        self._correction: np.ndarray | None = None

    def input(self, x: np.ndarray, usable: bool) -> np.ndarray:
        if usable:
            if self.last is not None and 0 < self.held <= self.max_interpolated:
                w = np.arange(1, self.held + 1) / (self.held + 1)
                self._correction = w[:, None] * (np.asarray(x, float) - self.last)[None, :]
            self.last, self.held = x, 0
            return x
        if self.last is None:
            return x
        self.held += 1
        return self.last

    def correction(self) -> np.ndarray | None:
        """The correction of the gap the last :meth:`input` closed (once), else None."""
        c, self._correction = self._correction, None
        return c


def hold_missing(X: np.ndarray, usable: np.ndarray,
                 max_interpolated: int = MAX_INTERPOLATED) -> np.ndarray:
    """:class:`MissingHold` over a block (N, channels), as the content filter's output sees
    it at the usable rows: rows not ``usable`` replaced by the straight line between the
    usable rows on either side where at most ``max_interpolated`` lie between them, else by
    the last usable row before them (kept as they are before the first)."""
    X = np.array(X, float)
    usable = np.asarray(usable, bool)
    n = len(X)
    idx = np.where(usable, np.arange(n), -1)
    np.maximum.accumulate(idx, out=idx)
    fill = ~usable & (idx >= 0)
    nxt = np.where(usable, np.arange(n), n)
    nxt = np.minimum.accumulate(nxt[::-1])[::-1]  # the next usable row (n: none)
    X_held = X.copy()
    X_held[fill] = X[idx[fill]]
    gap = nxt - idx - 1
    interp = fill & (nxt < n) & (gap <= max_interpolated)
    k = np.flatnonzero(interp)
    if k.size:
        a, b = idx[k], nxt[k]
        w = ((k - a) / (b - a))[:, None]
        X_held[k] = X[a] + w * (X[b] - X[a])
    return X_held
