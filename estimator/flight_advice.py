"""Which addition would determine the directions a filter-error window leaves undetermined
(docs/identification.md "Which additions would determine the rest").

Pure numerics, no I/O. Everything is read from the window's own information matrix in the
units of the information rule of filter-error runs: the eigenvalues λ of ``s M s`` (s = the
parameters' ``sigma_max``), a direction being determined by the window when λ ≥ 1. With k the
number the window determines, the figure of merit of an addition is how many directions it
would determine then (``gain`` = newly determined ones) and the (k+1)-th eigenvalue after it
(``next``: the strongest direction the window did not determine; by Weyl's inequality it
can only grow). Three kinds of addition, each a bounded computation:

* **an accelerometer** (a triaxial one at a named candidate position, with the noise of the
  rig's own): the inertial loads' covariance of model §3 and model §4 with the candidate appended
  (:func:`~estimator.balance.measurement_covariance`, the same angular regime), the
  innovation covariance B of the same fixed-gain calibration filter, and the window's own
  sensitivities re-weighted, ``Σ ∂eᵀ B_c⁻¹ ∂e``. Exact for the fixed gain (the sensitivities
  do not depend on W); a redesigned gain would differ a little. On a rig in the report's
  regime (``angular = "neglect"``) one more triax only averages the linear specific force:
  it takes three non-collinear ones to measure the angular accelerations.
* **a manoeuvre on hub axis j** — more precisely, extra transmission excitation that the
  cells carry and the accelerometers measure (inertially balanced, the kind of content the
  window's information comes from), a load on hub axis j of the configured RMS, spread flat
  over the configured band. A linearised proxy from the window's Jacobians: the cells carry
  ``t = split(R e_j)`` (minimum strain energy with the cells' stiffnesses), its regressor is
  ``G = ∂A/∂θ [0; t]``, and the calibration filter passes it with its innovation transfer
  function ``H(f) = I − JΦ (e^{iω}I − (I−KJ)Φ)⁻¹ K`` (the design's Φ: in azimuth mode the
  time-varying harmonics are taken at the design's Ω) times the content filter's gain c(f):
  ``ΔM = n · rms² · mean_f |c(f)|² Re(Gᵀ H(f)ᴴ B⁻¹ H(f) G)`` over the band. A pilot's
  manoeuvre whose hub loads the cells carry is no such content: the unknown hub loads absorb
  it (model §7 identifiability) or it is content outside the model — what informs is the
  transmission's measured acceleration on that axis.
* **a longer window**: the information grows with the scored samples, ``M ∝ n``, so the
  next direction is determined after ``n/fs · (1/λ_next − 1)`` more seconds.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.signal import sosfreqz

from .balance import measurement_covariance
from .geometry import wrench_matrix
from .identification import Parameterisation, innovation_covariance
from .params import RigModel

AXES = ("X", "Y", "Z", "L", "M", "N")
BAND_POINTS = 48  # frequencies of the manoeuvre proxy's band (a flat spectrum over them)
MAX_CANDIDATES = 16  # of each kind: the cost per window is bounded


@dataclass(frozen=True)
class AccelerometerCandidate:
    name: str
    position: np.ndarray  # (3,) m, body axes relative to the CG
    sigma: float  # m/s² per axis


@dataclass(frozen=True)
class ManoeuvreCandidate:
    axis: str  # one of AXES (hub axes)
    rms: float  # N or N·m


@dataclass(frozen=True)
class AdviceCandidates:
    """What the advice weighs (from the rig config: ``identification.advice``)."""

    accelerometers: tuple[AccelerometerCandidate, ...] = ()
    manoeuvres: tuple[ManoeuvreCandidate, ...] = ()
    band_hz: tuple[float, float] = (5.0, 40.0)
    stiffness: np.ndarray | None = None  # (n_cells,) N/m for the split; None: equal


def scaled_eigenvalues(M: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Eigenvalues of s M s, largest first (the information rule's; determined at ≥ 1)."""
    s = np.asarray(s, float)
    Ms = np.asarray(M, float) * s[:, None] * s[None, :]
    lam: np.ndarray = np.linalg.eigvalsh(0.5 * (Ms + Ms.T))[::-1]
    return lam


def window_information(de: np.ndarray, B: np.ndarray) -> np.ndarray:
    """M = Σ ∂eᵀ B⁻¹ ∂e over the samples of ``de`` (N, 6, p) (unscored samples zero)."""
    n, m, p = de.shape
    D = de.reshape(n * m, p)
    BD = (np.linalg.inv(B) @ de).reshape(n * m, p)
    M = D.T @ BD
    result: np.ndarray = 0.5 * (M + M.T)
    return result


def innovation_transfer(Phi: np.ndarray, K: np.ndarray, J: np.ndarray, freqs_hz: np.ndarray,
                        fs: float) -> np.ndarray:
    """H(f) (F, 6, 6): the fixed-gain filter's innovations per unit input y = z − S T,
    ``e = y − JΦ x⁺(n−1)``, ``x⁺ = (I−KJ)Φ x⁺(n−1) + K y`` → ``H(z) = I − JΦ (zI − Acl)⁻¹ K``."""
    ns = Phi.shape[0]
    Acl = (np.eye(ns) - K @ J) @ Phi
    JPhi = J @ Phi
    zs = np.exp(2j * np.pi * np.asarray(freqs_hz, float) / fs)
    out = np.empty((len(zs), J.shape[0], J.shape[0]), complex)
    for i, z in enumerate(zs):
        out[i] = np.eye(J.shape[0]) - JPhi @ np.linalg.solve(z * np.eye(ns) - Acl, K)
    return out


def accelerometer_model(model: RigModel, candidate: AccelerometerCandidate) -> RigModel:
    """The rig with one more triaxial accelerometer (the same angular regime)."""
    acc = model.accelerometers
    return replace(model, accelerometers=replace(
        acc, positions=np.vstack([acc.positions, np.asarray(candidate.position, float)[None]]),
        sigma=np.concatenate([np.asarray(acc.sigma, float), [float(candidate.sigma)]])))


def cell_split(model: RigModel, alpha: np.ndarray, stiffness: np.ndarray | None = None
               ) -> np.ndarray:
    """(n_cells, 6): the cell loads that carry a wrench at the CG, by minimum strain energy."""
    S = wrench_matrix(model.geometry, alpha)
    k = np.ones(S.shape[1]) if stiffness is None else np.asarray(stiffness, float)
    result: np.ndarray = (k[:, None] * S.T) @ np.linalg.inv((S * k[None, :]) @ S.T)
    return result


def excitation_information(par: Parameterisation, theta: np.ndarray, Phi: np.ndarray,
                           K: np.ndarray, J: np.ndarray, B: np.ndarray, n: int, fs: float,
                           band_hz: tuple[float, float], content_sos: np.ndarray | None,
                           stiffness: np.ndarray | None = None) -> np.ndarray:
    """(6, p, p): the information a unit-RMS excitation on each hub axis adds over ``n``
    scored samples (the manoeuvre proxy of the module docstring); multiply by rms²."""
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), 0.49 * fs)
    if not 0.0 < lo < hi:
        raise ValueError(f"the excitation band {band_hz} Hz is empty below Nyquist ({fs / 2} Hz)")
    freqs = np.linspace(lo, hi, BAND_POINTS)
    H = innovation_transfer(Phi, K, J, freqs, fs)  # (F, 6, 6)
    c2 = np.ones(len(freqs))
    if content_sos is not None:
        _, h = sosfreqz(content_sos, worN=freqs, fs=fs)
        c2 = np.abs(h) ** 2
    model, alpha = par.model_at(theta), par.alpha(theta)
    t = cell_split(model, alpha, stiffness)  # (n_cells, 6): cells per unit inertial load
    nc = par.n_cells
    dAT = par.terms(theta).dA[:, :, 6:6 + nc]  # (p, 6, n_cells): ∂A/∂θ on the T block
    G = np.einsum("pic,cj->jip", dAT, t)  # (6 axes, 6 rows, p)
    Binv = np.linalg.inv(B)
    HG = np.einsum("fab,jbp->fjap", H, G)  # (F, axes, 6, p)
    Q = np.einsum("f,fjap,ab,fjbq->jpq", c2, np.conj(HG), Binv, HG).real / len(freqs)
    result: np.ndarray = float(n) * 0.5 * (Q + Q.transpose(0, 2, 1))
    return result


def _summary(lam: np.ndarray, k0: int) -> dict[str, Any]:
    nxt = float(lam[k0]) if k0 < len(lam) else None
    return {"determined": int(np.sum(lam >= 1.0)), "gain": int(np.sum(lam >= 1.0)) - k0,
            "next": nxt}


def _rank(item: dict[str, Any]) -> tuple[int, float]:
    return (int(item["gain"]), float(item["next"] or 0.0))


def advise(par: Parameterisation, theta: np.ndarray, de: np.ndarray, B: np.ndarray,
           design: object, W_args: dict[str, Any], sigma_max: np.ndarray, n_scored: int, fs: float,
           candidates: AdviceCandidates, content_sos: np.ndarray | None = None
           ) -> dict[str, Any] | None:
    """The advice of one filter-error window at the run's estimate ``theta``: ``de`` (N, 6, p)
    its sensitivities (zero where not scored), ``B`` its innovation covariance, ``design`` the
    calibration filter (``Phi, K, J, Qd``), ``W_args`` the keywords of
    :func:`measurement_covariance` beyond model and angles (``moment_floor``). None when the
    window determines every direction (nothing to advise)."""
    s = np.asarray(sigma_max, float)
    M0 = window_information(de, B)
    lam0 = scaled_eigenvalues(M0, s)
    k0 = int(np.sum(lam0 >= 1.0))
    p = len(lam0)
    if k0 >= p:
        return None
    Phi, K, J, Qd = (np.asarray(getattr(design, a), float) for a in ("Phi", "K", "J", "Qd"))
    out: dict[str, Any] = {"determined": k0, "next": float(lam0[k0]), "n_scored": int(n_scored)}
    alpha = par.alpha(theta)
    acc = []
    for c in candidates.accelerometers[:MAX_CANDIDATES]:
        Wc = measurement_covariance(accelerometer_model(par.model_at(theta), c), alpha,
                                    **W_args)
        Bc, _ = innovation_covariance(Phi, K, J, Qd, Wc)
        lam = scaled_eigenvalues(window_information(de, Bc), s)
        acc.append({"name": c.name, "position_m": [float(x) for x in c.position],
                    **_summary(lam, k0)})
    man = []
    if candidates.manoeuvres:
        unit = excitation_information(par, theta, Phi, K, J, B, n_scored, fs,
                                      candidates.band_hz, content_sos, candidates.stiffness)
        for mc in candidates.manoeuvres[:MAX_CANDIDATES]:
            lam = scaled_eigenvalues(M0 + mc.rms**2 * unit[AXES.index(mc.axis)], s)
            man.append({"axis": mc.axis, "rms": float(mc.rms), **_summary(lam, k0)})
    out["accelerometers"], out["manoeuvres"] = acc, man
    nxt = float(lam0[k0])
    extra = n_scored / fs * (1.0 / nxt - 1.0) if nxt > 0 and n_scored > 0 else None
    out["window"] = {"extra_s": None if extra is None or not np.isfinite(extra) else float(extra),
                     "gain": 1}
    ranked = [("accelerometer", a["name"], a) for a in acc] + \
             [("manoeuvre", m["axis"], m) for m in man]
    best = None
    if ranked:
        kind, name, item = max(ranked, key=lambda r: _rank(r[2]))
        best = {"kind": kind, "name": name, "gain": item["gain"], "next": item["next"]}
    out["best"] = best
    return out


def candidates_from(accelerometers: Sequence[tuple[str, Sequence[float], float]],
                    manoeuvres: Sequence[tuple[str, float]], band_hz: Sequence[float],
                    stiffness: Sequence[float] | None = None) -> AdviceCandidates:
    """:class:`AdviceCandidates` from plain values (the shell's config)."""
    for axis, rms in manoeuvres:
        if axis not in AXES or not rms > 0:
            raise ValueError(f"a manoeuvre is an axis of {AXES} and a positive RMS, "
                             f"got {axis!r}, {rms!r}")
    return AdviceCandidates(
        accelerometers=tuple(AccelerometerCandidate(str(n), np.asarray(p, float), float(sg))
                             for n, p, sg in accelerometers),
        manoeuvres=tuple(ManoeuvreCandidate(str(a), float(r)) for a, r in manoeuvres),
        band_hz=(float(band_hz[0]), float(band_hz[1])),
        stiffness=None if stiffness is None else np.asarray(stiffness, float))


#: the hub axes in words, for the advice sentence (body axes: X forward, Y right, Z down)
AXIS_WORDS = {"X": "fore-aft (X)", "Y": "lateral (Y)", "Z": "vertical (Z)", "L": "roll (L)",
              "M": "pitch (M)", "N": "yaw (N)"}


def _load_text(axis: str, rms: object) -> str:
    if not isinstance(rms, (int, float)) or isinstance(rms, bool):
        return ""
    unit = "N·m" if axis in ("L", "M", "N") else "N"
    r = float(rms)
    return (f" of ~{r / 1000:.1f} k{unit} RMS" if abs(r) >= 1000 else f" of ~{r:.0f} {unit} RMS")


def _more(gain: object) -> str:
    g = gain if isinstance(gain, int) and not isinstance(gain, bool) else 0
    return "add none" if g <= 0 else f"determine {g} more direction" + ("s" if g > 1 else "")


def advice_summary(advice: dict[str, Any] | None, total: int | None = None) -> str | None:
    """One plain sentence for people (``rsra listen``, the browser view, the service log, the
    report) from an ``advice`` object (:func:`advise`; a record's JSON): how many directions
    this window determines (of ``total``), then what would determine more — each
    manoeuvre (transmission excitation along a hub axis, the window's band) and accelerometer
    that adds a direction, best first, the best accelerometer even when it adds none, and how
    much longer the window would need; the numbers behind it stay in the record."""
    if not isinstance(advice, dict):
        return None
    k = advice.get("determined")
    of = f" of {total}" if isinstance(total, int) else ""
    head = f"This window determines {k}{of} directions."
    items: list[tuple[int, float, str]] = []
    for m in advice.get("manoeuvres") or []:
        if isinstance(m, dict) and isinstance(m.get("gain"), int) and m["gain"] > 0:
            ax = str(m.get("axis"))
            items.append((m["gain"], float(m.get("next") or 0.0),
                          f"a {AXIS_WORDS.get(ax, ax)} excitation{_load_text(ax, m.get('rms'))}"
                          f" would {_more(m['gain'])}"))
    accs = [a for a in advice.get("accelerometers") or [] if isinstance(a, dict)
            and isinstance(a.get("gain"), int)]
    for a in accs:
        if a["gain"] > 0:
            items.append((a["gain"], float(a.get("next") or 0.0),
                          f"an accelerometer at {a.get('name')} would {_more(a['gain'])}"))
    parts = [t for _, _, t in sorted(items, key=lambda x: (-x[0], -x[1]))]
    if accs and not any(a["gain"] > 0 for a in accs):
        best_acc = max(accs, key=_rank)
        parts.append(f"an accelerometer at {best_acc.get('name')} would add none")
    w = advice.get("window")
    extra = w.get("extra_s") if isinstance(w, dict) else None
    if isinstance(extra, (int, float)) and not isinstance(extra, bool):
        parts.append(f"about {extra:.1f} s more of such data would determine 1 more")
    if not parts:
        parts.append("no listed addition would determine another direction")
    nxt = advice.get("next")
    tail = (f" (the strongest undetermined direction has {nxt:.2f} of the information it "
            "needs)" if isinstance(nxt, (int, float)) and not isinstance(nxt, bool) else "")
    text = "; ".join(parts)
    return f"{head} {text[0].upper()}{text[1:]}{tail}."
