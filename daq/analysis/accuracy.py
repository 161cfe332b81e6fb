"""Hub-load accuracy against truth, split by phase and judged against the σ the service
published for each sample: the figures of `rsra report`, the demo's summary and its
live view.

Three phases, because one figure over a whole run mixes three different things:

* ``start`` — before the first accepted calibration: the hub loads use the starting angles,
  uncalibrated; their error is what ``sigma_angles`` says the angles' uncertainty causes, and
  the published σ is large accordingly. A run that starts from calibrated angles (a saved
  posterior, ``--angles``: its first sample is not flagged ``angles_uncertain``) has no start
  phase (:func:`starts_calibrated`);
* ``transient`` — samples the service flagged ``transient`` (load ramps, manoeuvres): the
  filter lags the moving load (``H_static`` follows it);
* ``steady`` — calibrated and not transient: the state the accuracy claim is about.

The σ of a sample is the one its ``hub_loads`` record publishes: per axis
``sqrt(sigma_angles² + sigma_filter²)`` for ``H`` when the record carries ``sigma_filter``
(the filter's own error), else ``sqrt(sigma_angles² + bound²)`` with the static noise bound
(docs/identification.md); for ``H_static`` ``sqrt(sigma_angles² + bound²)``. A record without
``sigma_angles`` (an older recording) counts the bound alone. Each phase gives, per axis, the
RMS error, the RMS of error/σ and the fraction of samples beyond 3σ (0.27 % for a Gaussian
error with that σ). Bounded: sums per phase and axis, no history."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

PHASES = ("start", "transient", "steady")
MEANING = {
    "start": "before the first accepted calibration: the uncalibrated starting angles, their "
             "larger σ published (sigma_angles)",
    "transient": "load ramps and manoeuvres (hub_loads flagged transient): the filter lags "
                 "the moving load",
    "steady": "calibrated steady state: the accuracy claim (beyond 3σ ≈ 0.27 % for a true σ)",
}
TRANSIENT_FLAG = "transient"
UNCERTAIN_FLAG = "angles_uncertain"


def starts_calibrated(first_flags: Iterable[str]) -> bool:
    """A run whose first sample's angles are known to the accuracy the noise budget states
    (no ``angles_uncertain`` flag: a saved posterior) is calibrated from its start."""
    return UNCERTAIN_FLAG not in first_flags


def phase_of(calibrated: bool, flags: Iterable[str]) -> str:
    if not calibrated:
        return "start"
    return "transient" if TRANSIENT_FLAG in flags else "steady"


def published_sigma(rec: dict, bound: np.ndarray, estimate: str = "H") -> np.ndarray:
    """Per axis, the σ a ``hub_loads`` record publishes for ``H`` or ``H_static``."""
    sa = rec.get("sigma_angles")
    sa2 = 0.0 if sa is None else np.asarray([np.nan if x is None else x for x in sa], float) ** 2
    sf = rec.get("sigma_filter") if estimate == "H" else None
    other = (np.asarray(bound, float) if sf is None
             else np.asarray([np.nan if x is None else x for x in sf], float))
    return np.sqrt(sa2 + other ** 2)


class PhaseAccuracy:
    """Running sums of the error against truth per phase and axis (one per estimate)."""

    def __init__(self) -> None:
        self.n = {p: 0 for p in PHASES}
        self.e2 = {p: np.zeros(6) for p in PHASES}
        self.z2 = {p: np.zeros(6) for p in PHASES}
        self.beyond = {p: np.zeros(6, np.int64) for p in PHASES}

    def add(self, phase: str, err: np.ndarray, sigma: np.ndarray) -> None:
        err = np.asarray(err, float)
        sigma = np.asarray(sigma, float)
        if not (np.all(np.isfinite(err)) and np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
            return
        z = err / sigma
        self.n[phase] += 1
        self.e2[phase] += err * err
        self.z2[phase] += z * z
        self.beyond[phase] += np.abs(z) > 3.0

    def add_many(self, phases: np.ndarray, err: np.ndarray, sigma: np.ndarray) -> None:
        """Arrays: (N,) phase names, (N, 6) errors and σ (rows not finite are skipped)."""
        ok = np.isfinite(err).all(1) & np.isfinite(sigma).all(1) & (sigma > 0).all(1)
        for p in PHASES:
            m = ok & (np.asarray(phases) == p)
            if not m.any():
                continue
            e, z = err[m], err[m] / sigma[m]
            self.n[p] += int(m.sum())
            self.e2[p] += (e * e).sum(0)
            self.z2[p] += (z * z).sum(0)
            self.beyond[p] += (np.abs(z) > 3.0).sum(0)

    def summary(self, scale: np.ndarray | None = None) -> dict:
        """Per phase: ``samples``, ``rms_error`` (× ``scale``: units), ``rms_over_sigma``,
        ``beyond_3sigma`` (fractions), per axis; None for a phase without samples."""
        out: dict = {}
        for p in PHASES:
            n = self.n[p]
            if not n:
                out[p] = None
                continue
            rms = np.sqrt(self.e2[p] / n)
            out[p] = {"samples": n,
                      "rms_error": (rms if scale is None else rms * scale).tolist(),
                      "rms_over_sigma": np.sqrt(self.z2[p] / n).tolist(),
                      "beyond_3sigma": (self.beyond[p] / n).tolist()}
        return out


def phase_lines(by_phase: dict, label: str = "H", indent: str = "  ") -> list[str]:
    """Plain-text lines: one per phase with samples (RMS/σ and % beyond 3σ per axis), then
    one line saying what the phases mean."""
    lines = []
    for p in PHASES:
        v = by_phase.get(p)
        if not v:
            continue
        ax = "  ".join(f"{a} {r:.2f}/{100 * b:.1f}%" for a, r, b in
                       zip(("X", "Y", "Z", "L", "M", "N"), v["rms_over_sigma"],
                           v["beyond_3sigma"]))
        lines.append(f"{indent}{label} {p:9s} {v['samples']:6d} samples, RMS err/σ / beyond "
                     f"3σ: {ax}")
    if lines:
        lines.append(f"{indent}(σ: the published σ of each sample; " + "; ".join(
            f"{p}: {MEANING[p]}" for p in PHASES if by_phase.get(p)) + ")")
    return lines
