"""The sequential posterior of the periodic identification runs (model.md §7).

Every run takes the previous posterior as its prior, inflated by a random walk
(``P_p = P + q·Δt``), minimises J from the prior mean, and is then judged in order:

1. ``stale_input`` — too many samples of the window lack a required channel (no run);
2. ``not_converged`` / ``diverged`` — the run is not sound;
   ``out_of_range`` — its estimate leaves the physical range of the angles
   (``identification.angle_limit_deg``);
3. ``inconsistent`` — the consistency gate ``ν = Δθᵀ D⁺ Δθ > χ²_{d,0.999}`` with
   ``D = P_p − P_post``; after ``reset_after`` of them in a row the covariance is reset to the
   first prior's around the current mean (``reset``), so a real change is learned again
   ("in a row" counts the runs that reached the gate: a run rejected before it carries no
   evidence either way, so it neither extends nor breaks the streak; an accepted run does);
4. ``not_identifiable`` — a consistent run whose data add no real information: the largest
   eigenvalue of ``P_p^{1/2} M P_p^{1/2}`` is below ``min_information``;
5. otherwise accepted: (θ_post, P_post) replace the prior, and apply from
   ``window_end + apply_delay`` (later when the result arrives late).

Model §7 puts the information test before the gate. Taken literally that freezes the
tracker: once the posterior has converged no 5-s window can halve any variance (measured on
the ground-test: information ratios 0.7–0.95 from the third sweep on), so no run ever reaches
the gate and a 1° step is never detected (the tracking benchmark, bench/a4_tracking.py). The gate needs no minimum information — a
window with ratio λ moves the mean by λ/(1+λ) of a change and ν grows with it — so here every
sound run is gated and the information test only decides acceptance
(``gate_low_information=False`` restores the literal order). On the report's Phase II set-up
the gate passes (ν ≈ 2–6 on 14 directions) and the runs stay ``not_identifiable`` (the report's Phase II benchmark, bench/a5_paper.py).

Known-load mode re-linearises (docs/identification.md, findings 3–4): the likelihood depends
on a window only through its moments G = Σ x xᵀ, so the posterior keeps the moments of the
windows accepted since an anchor and each run re-solves their exact likelihood (from the
previous posterior mean), judged by the likelihood-ratio form of the gate; the anchor moves
to the posterior once every direction is determined. A window `not_identifiable` on its own is
held and counted with the next one. Both are needed from a cold start: one load condition's
constraints are curved in α, and a Gaussian summary made 4–8° from the truth misleads every
later window (measured: 42 `inconsistent` runs and a worst χ²₁₄ of 52.9 over 100 seeds
before, none and 21.1 after).

A rejected run leaves the posterior as it was. :class:`PeriodicIdentification` ties windows
of (content-filtered) data, the identification of ``estimator.identification`` and this
posterior together, carrying the filter-error state and its sensitivities from window to
window. Pure numerics; the posterior's JSON text is made and checked here
(:meth:`PosteriorState.to_dict`, :func:`posterior_from_json`); the files and their text are
daq.runtime.persistence's.
"""
from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .identification import (
    FilterErrorProblem,
    FilterErrorState,
    AccumulatedKnownLoadProblem,
    IdentificationResult,
    KnownLoadProblem,
    Parameterisation,
    SPECTRUM_SEGMENT,
    innovation_autocovariance,
    innovation_spectrum_test,
    levenberg_marquardt,
    predicted_score_covariance,
    score_covariance_hac,
    scattered_missing_fraction,
    scored_mask,
)
from .curvature import nonlinearity
from .load_spread import LoadSpread
from .params import RigModel
from .structure import DriftTest, StructureTest, StructureVerdict, fit_payload
from .judgement import (  # noqa: F401  (re-exported: their home was this module)
    GATE_PROBABILITY as GATE_PROBABILITY,
    GATE_RELATIVE_EIGENVALUE as GATE_RELATIVE_EIGENVALUE,
    FilterErrorChecks as FilterErrorChecks,
    FilterErrorDecision as FilterErrorDecision,
    Judgement as Judgement,
    _prior_cov as _prior_cov,
    consider_gate as consider_gate,
    consider_update as consider_update,
    consistency_gate as consistency_gate,
    filter_error_decision as filter_error_decision,
    information_ratio as information_ratio,
    input_verdict as input_verdict,
    judge as judge,
    out_of_range as out_of_range,
    window_measurement_cov as window_measurement_cov,
)
from .verdict import (  # noqa: F401  (re-exported: their home was this module)
    ACCEPTED as ACCEPTED,
    DETAILS as DETAILS,
    MODES as MODES,
    REASONS as REASONS,
    Detail,
    Mode,
    Reason,
    Verdict,
)

SIGMA_MAX_OTHER_FRACTION = 0.04  # non-angle parameters: determined at 0.04 × prior σ (model §7.4)
MAX_ACCUMULATED_WINDOWS = 64  # re-linearisation: fold at the latest after this many windows
LOAD_REFERENCE_WINDOWS = 24  # filter error: the reference (trim) load's windows (2 min)
MAX_HELD_WINDOWS = 12  # not-identifiable windows held for the next run (one sweep of 60 s)


@dataclass
class AnglesRecord:
    """Everything the ``angles`` record (docs/telemetry.md §2.4) carries, plus the run's own
    estimate."""

    t: float | None
    seq: int | None
    mode: str
    content: str
    accepted: bool
    reason: str | None
    names: tuple[str, ...]
    alpha: np.ndarray  # posterior mean after this run (unchanged when rejected)
    P: np.ndarray  # posterior covariance after this run
    sigma_cr: np.ndarray | None  # this run's conventional Cramér–Rao bounds
    sigma_cr_corrected: np.ndarray | None  # coloured-residual corrected (Morelli & Klein)
    determined: int  # directions of P with σ ≤ sigma_max
    information: float | None  # largest data-to-prior information ratio
    nu: float | None  # gate statistic
    cost: float | None
    iterations: int
    window: tuple[int, int]
    applies_from_seq: int | None
    late: bool = False
    # beyond the telemetry record
    gate_dof: int = 0
    condition: float | None = None  # condition number of the posterior information
    run_theta: np.ndarray | None = None  # the run's estimate θ_post
    run_P: np.ndarray | None = None  # the run's (M + P_p⁻¹)⁻¹
    status: str | None = None  # LM status
    undetermined: np.ndarray | None = None  # (p, k) directions with σ > sigma_max
    detail: str | None = None  # the test that decided (docs/telemetry.md §2.4; DETAILS)
    verdict: Verdict | None = None  # the judgement: reason, detail and the limit it used
    innovation: float | None = None  # filter error: q / its model-predicted mean
    innovation_limit: float | None = None  # the 1 − 10⁻³ point of the same ratio
    window_determined: int = 0  # directions the window's own (robust) information determines
    # known loads: the structure test (estimator.structure; None in filter-error mode)
    structure: str | None = None  # "constant", "not_constant", "undetermined", "drifting"
    candidates: list[dict[str, Any]] | None = None  # ranked, with their evidence (not_constant only)
    drift: dict[str, Any] | None = None  # the drift test (DriftVerdict.to_dict), known loads
    structure_verdict: StructureVerdict | None = None
    # the selected structure the hub-load estimate uses (structure.fit_payload), None: none
    structure_fit: dict[str, Any] | None = None
    # the run's cost J at its start (the prior mean) and after each iteration (how a run
    # that did not converge was going: the shell's explanation of a rejection)
    cost_start: float | None = None
    cost_history: tuple[float, ...] | None = None
    # the window's samples the likelihood used (scored; samples lacking an input are left
    # out); None: not set by the caller
    samples_used: int | None = None
    # filter error with angle_load_sensitivity configured : the window's static
    # load away from the reference (trim) load and the σ (rad, each angle) of the angles'
    # move that far — the window's truth is the posterior's α ± this beside P
    load_excursion: dict[str, Any] | None = None
    # known loads : the run's curvature index (estimator.curvature); None: not
    # computed (filter error, a run that did not converge, the limit off)
    nonlinearity: float | None = None
    # filter error : the posterior carried from the load it referred to (a ground
    # calibration's) to this window's reference (trim): the move {delta, sigma} (N, N·m; rad)
    reference_move: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The telemetry ``angles`` payload (SI: radians), values as computed (numpy arrays,
        NaN): the shell makes it strict JSON (``rsra.daq.jsonout.sanitise``, the one
        converter)."""
        keys = ("t", "seq", "mode", "content", "accepted", "reason", "detail", "names", "alpha",
                "P", "sigma_cr", "sigma_cr_corrected", "determined", "window_determined",
                "information", "nu", "cost", "iterations", "window", "applies_from_seq", "late")
        out = {k: getattr(self, k) for k in keys}
        for k in ("mode", "reason", "detail"):  # the enums' strings, as plain str
            out[k] = None if out[k] is None else str(out[k])
        if self.samples_used is not None:
            out["samples_used"] = int(self.samples_used)
        if self.mode == "known_loads":
            out["structure"] = None if self.structure is None else str(self.structure)
            out["candidates"] = self.candidates or []
            out["structure_fit"] = self.structure_fit
            out["drift"] = self.drift
        if self.load_excursion is not None:
            out["load_excursion"] = self.load_excursion
        if self.nonlinearity is not None:
            out["nonlinearity"] = float(self.nonlinearity)
        if self.reference_move is not None:
            out["reference_move"] = self.reference_move
        return out


FORMAT_VERSION = 2  # 2: with the rig fingerprint; 1 (no fingerprint) is still read
FINGERPRINT_ATOL = 1e-9  # m, and unit-vector components: a TOML → JSON round trip is exact


def rig_fingerprint(geometry: Any) -> dict[str, Any]:
    """What the angles of a posterior mean (docs/identification.md): every cell's name,
    attach point and nominal axis, the hub position and the angle names, JSON-ready."""
    return {
        "cells": [{"name": str(n), "position_m": [float(v) for v in p],
                   "nominal_axis": [float(v) for v in a]}
                  for n, p, a in zip(geometry.cell_names, np.asarray(geometry.cell_positions),
                                     np.asarray(geometry.cell_axes))],
        "hub_position_m": [float(v) for v in np.asarray(geometry.hub_position)],
        "angle_names": [str(n) for n in geometry.angle_names],
    }


def rig_difference(saved: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """The first item in which two rig fingerprints differ, named (None when they agree)."""
    def vec(x: Any) -> np.ndarray:
        return np.asarray(x, float).reshape(-1)

    def differ(a: Any, b: Any) -> bool:
        a, b = vec(a), vec(b)
        return a.shape != b.shape or not np.allclose(a, b, rtol=0.0, atol=FINGERPRINT_ATOL)

    sc, cc = list(saved["cells"]), list(current["cells"])
    if len(sc) != len(cc):
        return f"number of cells: {len(sc)} in the file, {len(cc)} configured"
    for i, (a, b) in enumerate(zip(sc, cc)):
        if str(a["name"]) != str(b["name"]):
            return f"cells[{i}].name: {a['name']!r} in the file, {b['name']!r} configured"
        for key in ("position_m", "nominal_axis"):
            if differ(a[key], b[key]):
                return (f"cells[{i}].{key} (cell {b['name']}): {vec(a[key]).tolist()} in the "
                        f"file, {vec(b[key]).tolist()} configured")
    if differ(saved["hub_position_m"], current["hub_position_m"]):
        return (f"hub_position_m: {vec(saved['hub_position_m']).tolist()} in the file, "
                f"{vec(current['hub_position_m']).tolist()} configured")
    if [str(n) for n in saved["angle_names"]] != [str(n) for n in current["angle_names"]]:
        return (f"angle_names: {list(saved['angle_names'])} in the file, "
                f"{list(current['angle_names'])} configured")
    return None


def _check_fingerprint(rig: Any) -> None:
    """Raise ValueError unless ``rig`` has the shape :func:`rig_fingerprint` writes."""
    if not isinstance(rig, dict) or not isinstance(rig.get("cells"), list):
        raise ValueError("rig fingerprint is not an object with a list of cells")
    for c in rig["cells"]:
        if not isinstance(c, dict) or not isinstance(c.get("name"), str):
            raise ValueError("rig fingerprint: a cell without a name")
        for key in ("position_m", "nominal_axis"):
            if np.asarray(c.get(key), float).shape != (3,):
                raise ValueError(f"rig fingerprint: cell {c['name']} {key} is not 3 numbers")
    if np.asarray(rig.get("hub_position_m"), float).shape != (3,):
        raise ValueError("rig fingerprint: hub_position_m is not 3 numbers")
    if not isinstance(rig.get("angle_names"), list):
        raise ValueError("rig fingerprint: angle_names is not a list")


@dataclass
class PosteriorState:
    """What is saved and loaded: the posterior and the sample it applies from, and the rig
    fingerprint of what its angles mean (None: a version-1 file, or not known)."""

    names: tuple[str, ...]
    theta: np.ndarray
    P: np.ndarray
    applies_from_seq: int | None = None
    t: float | None = None
    rig: dict[str, Any] | None = None
    # optional : the selected structure the hub-load estimate uses
    # (structure.fit_payload); files without it load as before
    structure: dict[str, Any] | None = None
    # optional : the static hub load (6, N and N·m, the estimator's frame) the
    # angles refer to — the mean of the accepted known-load windows' — so that a flight at
    # another load widens the posterior by the rig's load-sensitivity bound (ReferenceLoad)
    reference_load: np.ndarray | None = None

    @property
    def version(self) -> int:
        return FORMAT_VERSION if self.rig is not None else 1

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"format": "rsra-posterior", "version": self.version}
        if self.rig is not None:
            d["rig"] = self.rig
        d.update({"names": list(self.names), "theta": self.theta.tolist(), "P": self.P.tolist(),
                  "applies_from_seq": self.applies_from_seq, "t": self.t})
        if self.structure is not None:
            d["structure"] = self.structure
        if self.reference_load is not None:
            d["reference_load"] = [float(x) for x in self.reference_load]
        return d


class PosteriorFileError(ValueError):
    """A posterior file that cannot be used, with the reason and what to do."""

    FIX = ("pass a posterior written by rsra (the service saves one to "
           "identification.state_file after an accepted identification run)")

    def __init__(self, path: str | Path, problem: str, fix: str | None = None) -> None:
        self.path, self.problem = str(path), problem
        super().__init__(f"posterior file {path}: {problem} — {fix or self.FIX}")


def check_posterior(state: PosteriorState, path: str | Path, *, rig: Mapping[str, Any],
                    angle_names: Sequence[str], angle_limit_rad: float,
                    accept_rig_mismatch: bool = False) -> str | None:
    """Whether a loaded posterior may be used on this rig: every angle within the physical
    range ±``angle_limit_rad`` (always), and the file's rig fingerprint equal to ``rig``
    (unless ``accept_rig_mismatch``). Raises :class:`PosteriorFileError` naming the angle or
    the differing item; returns a one-line warning for a version-1 file (no fingerprint) or
    an accepted mismatch, else None."""
    for n, v in zip(state.names, state.theta):
        if n in angle_names and not abs(v) <= angle_limit_rad:
            raise PosteriorFileError(
                path, f"angle {n} = {v:.6g} rad is outside the physical range "
                f"±{math.degrees(angle_limit_rad):g}° (identification.angle_limit_deg)")
    if state.rig is None:
        return (f"posterior file {path}: format version 1 carries no rig fingerprint; its "
                "angles are taken to belong to this rig (the next save writes version 2)")
    diff = rig_difference(state.rig, rig)
    if diff is None:
        return None
    if accept_rig_mismatch:
        return (f"posterior file {path}: from another rig ({diff}); used anyway "
                "(--accept-rig-mismatch)")
    raise PosteriorFileError(path, f"its angles belong to another rig: {diff}",
                             "check --config, or pass --accept-rig-mismatch to use it anyway")


def posterior_from_json(text: str, path: str | Path,
                        names: Sequence[str] | None = None) -> PosteriorState:
    """Parse and check a saved posterior's text (``path`` names it in the errors); a corrupt
    or mismatched one raises :class:`PosteriorFileError`."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PosteriorFileError(path, f"not readable JSON ({exc})") from None
    if not isinstance(raw, dict) or raw.get("format") != "rsra-posterior":
        raise PosteriorFileError(path, 'not a posterior (missing "format": "rsra-posterior")')
    version = raw.get("version")
    if version not in (1, FORMAT_VERSION) or isinstance(version, bool):
        raise PosteriorFileError(path, f"unsupported version {version!r}")
    rig = None
    if version >= 2:
        rig = raw.get("rig")
        try:
            _check_fingerprint(rig)
        except (TypeError, ValueError) as exc:
            raise PosteriorFileError(path, f"malformed rig fingerprint ({exc})") from None
    try:
        fnames = tuple(str(n) for n in raw["names"])
        theta = np.asarray(raw["theta"], dtype=float)
        P = np.asarray(raw["P"], dtype=float)
        afs = raw.get("applies_from_seq")
        t = raw.get("t")
    except (KeyError, TypeError, ValueError) as exc:
        raise PosteriorFileError(path, f"missing or malformed field ({exc})") from None
    _check_posterior_arrays(path, fnames, theta, P)
    if names is not None and tuple(names) != fnames:
        raise PosteriorFileError(path, f"parameters {list(fnames)} differ from the configured "
                                 f"{list(names)}")
    if afs is not None and not isinstance(afs, int):
        raise PosteriorFileError(path, "applies_from_seq must be an integer or null")
    if t is not None and not isinstance(t, (int, float)):
        raise PosteriorFileError(path, "t must be a number or null")
    structure, ref = _optional_sections(path, raw)
    return PosteriorState(fnames, theta, P, afs, None if t is None else float(t), rig,
                          structure, ref)


def _check_posterior_arrays(path: str | Path, fnames: tuple[str, ...], theta: np.ndarray,
                            P: np.ndarray) -> None:
    """θ and P of a saved posterior: their shapes, finite, P symmetric positive definite."""
    p = len(fnames)
    if theta.shape != (p,) or P.shape != (p, p):
        raise PosteriorFileError(path, f"shapes {theta.shape} and {P.shape} do not match "
                                 f"{p} names")
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(P))):
        raise PosteriorFileError(path, "non-finite numbers")
    if not np.allclose(P, P.T, rtol=1e-9, atol=0.0):
        raise PosteriorFileError(path, "covariance not symmetric")
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise PosteriorFileError(path, "covariance not positive definite") from None


def _optional_sections(path: str | Path, raw: dict[str, Any]
                       ) -> tuple[dict[str, Any] | None, np.ndarray | None]:
    """The optional ``structure`` and ``reference_load`` of a saved posterior (None: absent)."""
    structure = raw.get("structure")
    if structure is not None and not (isinstance(structure, dict)
                                      and isinstance(structure.get("structure"), str)):
        raise PosteriorFileError(path, "malformed structure section (an object naming its "
                                 "structure, or absent)")
    ref = raw.get("reference_load")
    if ref is not None:
        try:
            ref = np.asarray(ref, dtype=float)
        except (TypeError, ValueError):
            ref = None
        if ref is None or ref.shape != (6,) or not np.all(np.isfinite(ref)):
            raise PosteriorFileError(path, "reference_load must be 6 finite numbers (N, N·m) "
                                     "or absent")
    return structure, ref




# how an accepted filter-error run updates the posterior (identification.filter_error_update)
FILTER_ERROR_UPDATES = ("consider", "bayes")






PREDICTION_WIDTH_RATIO = 10.0  # variance ratio beyond which the posterior replaces the fit


def bounded_against_posterior(pred: tuple[np.ndarray, np.ndarray], theta_ref: np.ndarray,
                              P_ref: np.ndarray, ratio: float = PREDICTION_WIDTH_RATIO
                              ) -> tuple[np.ndarray, np.ndarray]:
    """The drift bound's prediction (θ_b, P_b) with the directions in which it is more than
    ``ratio`` times wider (variance) than the reference (the last accepted posterior moved
    along the bound's drift) taken from the reference: in the whitened generalised
    eigenbasis of (P_b, P_ref) those components get the reference's mean and variance, the
    others keep the prediction's. The fit of window means cannot know a direction only the
    posterior's full moments determine; there the prediction is no prior at all."""
    th_b, P_b = np.asarray(pred[0], float), np.asarray(pred[1], float)
    try:
        L = np.linalg.cholesky(0.5 * (P_ref + P_ref.T))
    except np.linalg.LinAlgError:
        return th_b, P_b
    Li = np.linalg.inv(L)
    lam, U = np.linalg.eigh(Li @ (0.5 * (P_b + P_b.T)) @ Li.T)
    wide = lam > ratio
    if not wide.any():
        return th_b, P_b
    w = U.T @ (Li @ (th_b - theta_ref))
    w[wide] = 0.0
    lam = np.where(wide, 1.0, lam)
    T = L @ U
    P = T @ np.diag(lam) @ T.T
    return theta_ref + T @ w, 0.5 * (P + P.T)


def _moment_cost(par: Parameterisation, G: np.ndarray, theta: np.ndarray) -> float:
    """V(θ) = ½ tr(W⁻¹ A G Aᵀ) of windows given by their moments G (known loads)."""
    t = par.terms(theta)
    return 0.5 * float(np.sum(np.linalg.inv(t.W) * (t.A @ G @ t.A.T)))








def load_excursion_variance(sensitivity: np.ndarray, delta: np.ndarray) -> float:
    """The variance (rad², each angle) of the angles' move between the reference (trim) load
    and a window's static load ``delta`` away from it, given a bound (1 σ) on their
    sensitivity per unit of load on each axis (``identification.angle_load_sensitivity_deg_
    per_unit``): Σ_k (s_k Δ_k)² (docs/identification.md, "Load excursions")."""
    d = np.asarray(delta, float) * np.asarray(sensitivity, float)
    return float(d @ d)


def determined_directions(P: np.ndarray, sigma_max: np.ndarray) -> tuple[int, np.ndarray, float]:
    """(number of eigen-directions of P, scaled by sigma_max, with σ ≤ sigma_max; the
    undetermined directions (p, k) in parameter units; condition number of P⁻¹)."""
    s = np.asarray(sigma_max, float)
    lam, V = np.linalg.eigh((P / s[:, None]) / s[None, :])
    det = lam <= 1.0
    U = s[:, None] * V[:, ~det]
    cond = float(lam[-1] / lam[0]) if lam[0] > 0 else math.inf
    return int(det.sum()), U, cond


class WindowMoments:
    """The known-load windows behind the re-linearised runs (docs/identification.md, findings
    3–4): the anchor (the posterior they were last folded into), the moments G = Σ x xᵀ of the
    windows accepted since, and those of the windows held back as not identifiable on their
    own. Bounded: at most ``max_held`` windows are held (then holding starts afresh); the
    caller folds after ``max_accumulated`` accepted ones."""

    def __init__(self, theta: np.ndarray, P: np.ndarray, *, max_accumulated: int,
                 max_held: int) -> None:
        self.max_accumulated = int(max_accumulated)
        self.max_held = int(max_held)
        self.fold(theta, P)

    def fold(self, theta: np.ndarray, P: np.ndarray) -> None:
        """``(theta, P)`` becomes the anchor; the accumulated and held windows are forgotten."""
        self.anchor_theta, self.anchor_P = theta.copy(), P.copy()
        self.anchor_dt = 0.0
        self.G_acc: np.ndarray | None = None
        self.n_acc = 0
        self.windows_acc = 0
        self.drop_held()

    def drop_held(self) -> None:
        """Forget the windows held back as not identifiable on their own."""
        self.G_held: np.ndarray | None = None
        self.n_held = 0
        self.windows_held = 0

    def held(self) -> tuple[np.ndarray | None, int, int]:
        return self.G_held, self.n_held, self.windows_held

    def restore_held(self, held: tuple[np.ndarray | None, int, int]) -> None:
        self.G_held, self.n_held, self.windows_held = held

    def hold(self, moments: tuple[np.ndarray, int]) -> None:
        """Hold a window (``moments`` already include the windows held so far: the run used
        them all)."""
        if self.windows_held + 1 > self.max_held:
            self.drop_held()  # bounded: start holding afresh from this window
            return
        self.G_held, self.n_held = np.array(moments[0], float), int(moments[1])
        self.windows_held += 1

    def accumulate(self, moments: tuple[np.ndarray, int], dt: float) -> bool:
        """Add an accepted window (and the held ones it included); True when the
        accumulation is full (the caller folds)."""
        G, n = moments
        self.G_acc = np.array(G, float) if self.G_acc is None else self.G_acc + G
        self.n_acc += int(n)
        self.windows_acc += 1 + self.windows_held
        self.drop_held()
        self.anchor_dt += max(float(dt), 0.0)
        return self.windows_acc >= self.max_accumulated


class SequentialPosterior:
    """The posterior (θ, P) of the periodic runs and the decisions of model §7.

    It keeps the state and the order of the tests (:meth:`_judge`); the pieces are their
    own: the re-linearisation's windows (:class:`WindowMoments`), the filter-error
    information rule (:func:`filter_error_decision`), the record (:func:`angles_record`)
    and the construction from the rig's configuration (:func:`posterior_from_config`)."""

    def __init__(
        self,
        names: Sequence[str],
        theta0: np.ndarray,
        sigma0: np.ndarray,
        *,
        drift_rate: np.ndarray | float,
        min_information: float,
        sigma_max: np.ndarray,
        reset_after: int,
        stale_fraction: float,
        gate_probability: float = GATE_PROBABILITY,
        gate_low_information: bool = True,
        relinearise: bool = True,
        max_accumulated_windows: int = MAX_ACCUMULATED_WINDOWS,
        max_held_windows: int = MAX_HELD_WINDOWS,
        limit: np.ndarray | float = math.inf,
        rig: dict[str, Any] | None = None,
        filter_error_update: str = "consider",
        filter_error_floor: float = 0.0,
    ) -> None:
        self.names = tuple(names)
        if filter_error_update not in FILTER_ERROR_UPDATES:
            raise ValueError(f"filter_error_update must be one of {FILTER_ERROR_UPDATES}")
        # the filter-error update (consider_update) and its systematic floor σ_b in units of
        # sigma_max (docs/identification.md, "The consider update")
        self.filter_error_update = filter_error_update
        self.filter_error_floor = float(filter_error_floor)
        p = len(self.names)
        # the physical range |θ_k| ≤ limit_k (angles: identification.angle_limit_deg)
        self.limit = np.broadcast_to(np.asarray(limit, float), (p,)).copy()
        self.rig = rig  # the fingerprint saved with the posterior (rig_fingerprint)
        self.structure_fit: dict[str, Any] | None = None  # the selected structure (saved)
        self.reference = ReferenceLoad()  # the static load the angles refer to 
        self.theta = np.asarray(theta0, float).copy()
        self.P0 = np.diag(np.broadcast_to(np.asarray(sigma0, float), (p,)) ** 2)
        self.P = self.P0.copy()
        self.drift = np.broadcast_to(np.asarray(drift_rate, float), (p,)).copy()
        self.min_information = float(min_information)
        self.sigma_max = np.broadcast_to(np.asarray(sigma_max, float), (p,)).copy()
        self.reset_after = int(reset_after)
        self.stale_fraction = float(stale_fraction)
        self.gate_probability = float(gate_probability)
        self.gate_low_information = bool(gate_low_information)
        self.inconsistent_in_a_row = 0
        self.applies_from_seq: int | None = None
        self.t: float | None = None
        self.relinearise = bool(relinearise)
        # the re-linearisation's windows (known loads): anchor, accumulated and held moments
        self.moments = WindowMoments(self.theta, self.P, max_accumulated=max_accumulated_windows,
                                     max_held=max_held_windows)
        # angles on a trend (the structure test's `drifting`): the trend's rates
        # (rad/s over ``names``; None: constant angles with the random walk) and, per run,
        # the drift fit's prediction of the angles at the run's window (set_prediction)
        self.trend: np.ndarray | None = None
        self.prediction: tuple[np.ndarray, np.ndarray] | None = None
        self.fold()

    def set_trend(self, names: Sequence[str] | None, rate: np.ndarray | None = None) -> None:
        """Track angles on a trend (``names``: the rates' parameters, e.g. the 14 angles;
        ``None`` ends it). While a trend is in force each run's prior is the drift fit's
        prediction at its window (:meth:`set_prediction`) when there is one, no window
        moments are accumulated (they assume constant angles), and a run that is not
        accepted still moves the posterior to that prediction."""
        if names is None or rate is None:
            self.trend = None
            self.prediction = None
            return
        p = len(self.names)
        r, _ = over_names(self.names, names, np.asarray(rate, float), None, np.zeros(p),
                                np.zeros((p, p)))
        if self.trend is None:
            self.fold()  # the accumulated windows were fitted as constant angles
        self.trend = r

    def set_prediction(self, names: Sequence[str] | None, theta: np.ndarray | None = None,
                       P: np.ndarray | None = None) -> None:
        """The next run's prior under a trend: the angles the drift fit (of the windows
        before this one) predicts at its window, with the prediction's covariance (the
        rates' uncertainty included); parameters it does not name keep the posterior's
        (uncorrelated). None: the random-walk prior."""
        if names is None or theta is None or P is None:
            self.prediction = None
            return
        th, Pp = over_names(self.names, names, np.asarray(theta, float), np.asarray(P, float),
                                  self.theta, np.diag(np.diag(self.P)))
        if self.moments.G_acc is not None:
            self.fold()  # the prediction is a summary of those windows too
        self.prediction = (th, 0.5 * (Pp + Pp.T))

    # ------------------------------------------------------------- re-linearisation (known loads)
    def fold(self) -> None:
        """Make the current posterior the anchor and forget the accumulated window moments
        (its Gaussian summary is now trusted: all directions determined, a reset, a restore,
        a filter-error run, or the accumulation cap)."""
        self.moments.fold(self.theta, self.P)

    def _hold(self, moments: tuple[np.ndarray, int] | None) -> None:
        if self.relinearise and moments is not None:
            self.moments.hold(moments)

    def anchor_prior(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The prior of a re-linearised run: the anchor, inflated by the random walk since
        (and moved along the trend in force)."""
        if self.prediction is not None:
            return self.prediction[0].copy(), self.prediction[1].copy()
        m = self.moments
        return m.anchor_theta.copy(), m.anchor_P + np.diag(
            self.drift * (m.anchor_dt + max(float(dt), 0.0)))

    def _after_accepted(self, moments: tuple[np.ndarray, int] | None, dt: float) -> None:
        if (not (self.relinearise and moments is not None) or self.trend is not None
                or self.prediction is not None):
            self.fold()
            return
        full = self.moments.accumulate(moments, dt)
        det, _, _ = determined_directions(self.P, self.sigma_max)
        if det == len(self.names) or full:
            self.fold()

    @classmethod
    def from_config(cls, ident: Any, names: Sequence[str], angle_names: Sequence[str],
                    **kw: Any) -> "SequentialPosterior":
        """:func:`posterior_from_config` (``RigConfig.identification``)."""
        return posterior_from_config(ident, names, angle_names, **kw)

    def state(self) -> PosteriorState:
        return PosteriorState(self.names, self.reference.reported_theta(self.theta),
                              self.reference.reported(self.P),
                              self.applies_from_seq, self.t, self.rig,
                              self.structure_fit, self.reference.load)

    def restore(self, state: PosteriorState) -> None:
        """Start from a saved posterior (``--angles``)."""
        if tuple(state.names) != self.names:
            raise ValueError(f"saved parameters {list(state.names)} differ from {list(self.names)}")
        self.theta, self.P = state.theta.copy(), state.P.copy()
        self.applies_from_seq, self.t = state.applies_from_seq, state.t
        self.structure_fit = state.structure
        self.reference = ReferenceLoad.restored(getattr(state, "reference_load", None))
        self.inconsistent_in_a_row = 0
        self.fold()

    def prior(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The next run's prior: the posterior, its covariance inflated by q·Δt (and, under a
        trend, moved by rate·Δt with the rates' covariance·Δt² added)."""
        if self.prediction is not None:
            return self.prediction[0].copy(), self.prediction[1].copy()
        return self.theta.copy(), self.P + np.diag(self.drift * max(float(dt), 0.0))

    def update(self, result: IdentificationResult | None, **kw: Any) -> AnglesRecord:
        """Judge one run (:meth:`_judge`). Under a trend (or the drift bound's prediction) a
        run that is not accepted still moves the posterior to its window (the drift fit's
        prediction), so the mean keeps up with the angles through rejected runs."""
        rec = self._judge(result, **kw)
        if self.prediction is not None and not rec.accepted:
            self.theta, self.P = self.prior(kw.get("dt", 0.0))
            held = self.moments.held()
            self.fold()
            if self.trend is None:  # the bound's held windows count with the next run
                self.moments.restore_held(held)
        return rec

    def _judge(
        self,
        result: IdentificationResult | None,
        *,
        window: tuple[int, int],
        mode: str,
        content: str,
        t: float | None = None,
        missing_fraction: float = 0.0,
        apply_delay_samples: int = 0,
        arrived_seq: int | None = None,
        moments: tuple[np.ndarray, int] | None = None,
        dt: float = 0.0,
        gate: tuple[float, int] | None = None,
        checks: "FilterErrorChecks | None" = None,
        structure: StructureVerdict | None = None,
        nonlinear: bool = False,
        nonlinearity_limit: float | None = None,
        stale: Verdict | None = None,
    ) -> AnglesRecord:
        """Judge one run whose prior was :meth:`prior` (it is read from ``result``): the
        decision is :func:`estimator.judgement.judge`'s; here its bookkeeping is applied
        (:meth:`_apply`) and the record made.

        ``moments``: the window's known-load moments (G, scored samples); an accepted run adds
        them to the accumulation the next runs re-solve (``dt``: the run's random-walk time).
        ``gate``: (ν, d) computed by the caller (the likelihood-ratio form of a re-linearised
        run) instead of the linearised ``Δθᵀ D⁺ Δθ``. ``stale``: the input's verdict of a
        window that was not run (:func:`estimator.judgement.input_verdict`)."""
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}")
        j = judge(self, result, missing_fraction=missing_fraction, stale=stale, gate=gate,
                  checks=checks, structure=structure, nonlinear=nonlinear,
                  nonlinearity_limit=nonlinearity_limit)
        late = self._apply(j, result, moments, dt, window, apply_delay_samples, arrived_seq, t)
        dec = j.decision
        return angles_record(self, verdict=j.verdict, late=late, mode=Mode(mode),
                             content=content, window=window, t=t, structure=structure,
                             result=result, information=j.information, checks=checks,
                             window_determined=0 if dec is None else dec.window_determined)

    def _apply(self, j: Judgement, result: IdentificationResult | None,
               moments: tuple[np.ndarray, int] | None, dt: float, window: tuple[int, int],
               apply_delay_samples: int, arrived_seq: int | None, t: float | None) -> bool:
        """What a judged run changes: the held known-load windows (held with a run that
        lacked only information; dropped with one whose data disagree — in known-load mode,
        where they were part of the run), the gate's streak and its reset, and an accepted
        run's update. Returns whether an accepted run is applied late."""
        v, known = j.verdict, j.decision is None
        if v.detail in (Detail.NONLINEAR, Detail.INFORMATION_RATIO):
            self._hold(moments)  # the window's information counts with the next run
        elif v.detail in (Detail.RANGE, Detail.STRUCTURE) and known:
            self.moments.drop_held()  # the held windows were part of this run
        elif v.detail == Detail.GATE:
            self._gate_failed(drop_held=known)
        elif v.accepted and result is not None:
            self.inconsistent_in_a_row = 0
            if j.decision is not None and j.decision.theta is not None \
                    and j.decision.P is not None:
                self.theta, self.P = j.decision.theta, j.decision.P
                self.fold()
            else:
                self.theta, self.P = result.theta.copy(), result.P.copy()
                self._after_accepted(moments, dt)
            return self._applies_from(window, apply_delay_samples, arrived_seq, t)
        return False

    def _gate_failed(self, *, drop_held: bool) -> None:
        """A run the consistency gate rejects: ``inconsistent``, or — the ``reset_after``-th in
        a row, a real change — ``reset``: the covariance reopened around the current mean."""
        self.inconsistent_in_a_row += 1
        if self.inconsistent_in_a_row >= self.reset_after:
            self.P = self.P0.copy()
            self.reference = ReferenceLoad()
            self.inconsistent_in_a_row = 0
            self.fold()
        elif drop_held:
            self.moments.drop_held()  # the held windows were part of an inconsistent run

    def _applies_from(self, window: tuple[int, int], apply_delay_samples: int,
                      arrived_seq: int | None, t: float | None) -> bool:
        """An accepted run applies from ``window end + apply delay`` (later when the result
        arrived after that sample: ``late``, returned)."""
        planned = int(window[1]) + int(apply_delay_samples)
        late = arrived_seq is not None and arrived_seq + 1 > planned
        self.applies_from_seq = int(arrived_seq) + 1 if late and arrived_seq is not None \
            else planned
        self.t = t
        return late




def over_names(to: Sequence[str], names: Sequence[str], v: np.ndarray, P: np.ndarray | None,
               fill_v: np.ndarray, fill_P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``v`` (and ``P``) over ``names`` placed over the parameters ``to``; those ``names``
    does not hold keep ``fill_v`` (``fill_P``)."""
    idx = {n: i for i, n in enumerate(names)}
    out_v, out_P = fill_v.copy(), fill_P.copy()
    sel = [(i, idx[n]) for i, n in enumerate(to) if n in idx]
    for i, j in sel:
        out_v[i] = v[j]
        if P is not None:
            for k, m in sel:
                out_P[i, k] = P[j, m]
    return out_v, out_P


def angles_record(post: "SequentialPosterior", *, verdict: Verdict, mode: str, content: str,
                  window: tuple[int, int], t: float | None,
                  result: IdentificationResult | None, information: float | None,
                  late: bool = False, checks: "FilterErrorChecks | None" = None,
                  window_determined: int = 0,
                  structure: StructureVerdict | None = None) -> AnglesRecord:
    """The angles record of a judged run: the posterior now in force (after the run), the
    run's own estimate and the verdict that decided it (docs/telemetry.md §2.4)."""
    det, U, cond = determined_directions(post.P, post.sigma_max)
    return AnglesRecord(
        structure=None if structure is None else structure.structure,
        candidates=None if structure is None else structure.candidates,
        drift=None if structure is None or structure.drift is None
        else structure.drift.to_dict(),
        structure_verdict=structure,
        t=t, seq=int(window[1]), mode=mode, content=content, accepted=verdict.accepted,
        reason=verdict.reason, verdict=verdict, names=post.names,
        alpha=post.reference.reported_theta(post.theta), P=post.reference.reported(post.P),
        sigma_cr=None if result is None else result.sigma_cr,
        sigma_cr_corrected=None if result is None else result.sigma_cr_corrected,
        determined=det, information=information, nu=verdict.nu,
        cost=None if result is None else float(result.cost),
        iterations=0 if result is None else int(result.iterations),
        window=(int(window[0]), int(window[1])), applies_from_seq=post.applies_from_seq,
        late=late, gate_dof=verdict.dof, condition=cond,
        run_theta=None if result is None else result.theta.copy(),
        run_P=None if result is None else result.P.copy(),
        status=None if result is None else result.status, undetermined=U,
        detail=verdict.detail, window_determined=int(window_determined),
        innovation=None if checks is None else checks.innovation.statistic
        / checks.innovation.mean,
        innovation_limit=None if checks is None else checks.innovation.limit
        / checks.innovation.mean,
        cost_start=None if result is None else float(result.cost_start),
        cost_history=None if result is None else tuple(float(c) for c in result.history),
        load_excursion=None if checks is None or checks.load_delta is None else {
            "delta": [float(x) for x in checks.load_delta],
            "sigma": math.sqrt(max(float(checks.load_variance), 0.0))},
    )


def posterior_from_config(
    ident: Any,
    names: Sequence[str],
    angle_names: Sequence[str],
    *,
    theta0: np.ndarray | None = None,
    other_prior_sigma: Mapping[str, float] | None = None,
    rig: dict[str, Any] | None = None,
) -> "SequentialPosterior":
    """From ``RigConfig.identification``: angles get ``prior_sigma_rad``, drift
    ``drift_rate_rad2_s``, ``sigma_max_rad`` and the range ±``angle_limit_rad``; other
    parameters need their prior σ in ``other_prior_sigma`` (no drift; determined at
    0.04 × prior σ; no range). ``rig``: the fingerprint saved with it."""
    other_prior_sigma = dict(other_prior_sigma or {})
    sig0, drift, smax = [], [], []
    for n in names:
        if n in angle_names:
            sig0.append(ident.prior_sigma_rad)
            drift.append(ident.drift_rate_rad2_s)
            smax.append(ident.sigma_max_rad)
        elif n in other_prior_sigma:
            sig0.append(float(other_prior_sigma[n]))
            drift.append(0.0)
            smax.append(SIGMA_MAX_OTHER_FRACTION * float(other_prior_sigma[n]))
        else:
            raise ValueError(f"parameter {n!r} needs a prior sigma (other_prior_sigma)")
    if theta0 is None:
        theta0 = np.array([ident.initial_angles_rad[list(angle_names).index(n)]
                           for n in names])
    limit = [ident.angle_limit_rad if n in angle_names else math.inf for n in names]
    return SequentialPosterior(names, theta0, np.array(sig0), drift_rate=np.array(drift),
               min_information=ident.min_information, sigma_max=np.array(smax),
               reset_after=ident.reset_after, stale_fraction=ident.stale_fraction,
               limit=np.array(limit), rig=rig,
               filter_error_update=ident.filter_error_update,
               filter_error_floor=ident.filter_error_floor_rad / ident.sigma_max_rad)








def likelihood_ratio_gate(post: SequentialPosterior, par: Parameterisation,
                          max_iterations: int, window_prob: Any, res: IdentificationResult,
                          theta_a: np.ndarray, P_a: np.ndarray, theta_prev: np.ndarray,
                          P_p: np.ndarray) -> tuple[float, int]:
    """The consistency gate of a re-linearised run as a likelihood ratio:
    ν = 2 [J_{prev+w}(θ_run) − J_prev(θ_prev) − min V_w], d = rank of the window's
    information against the prior. For a linear model this is exactly model §7's
    Δθᵀ D⁺ Δθ; unlike it, it does not assume the previous posterior is Gaussian, which it
    is not while directions are still undetermined (the constraints of one load
    condition are curved in α: a Gaussian around the mode puts the truth at χ² in the
    hundreds after the first windows — measured)."""
    Pinv_a = np.linalg.inv(P_a)
    da = theta_prev - theta_a
    J_prev = 0.5 * float(da @ Pinv_a @ da)
    if post.moments.G_acc is not None:
        J_prev += _moment_cost(par, post.moments.G_acc, theta_prev)
    # the window alone: its minimum from the run's estimate (a broad prior keeps the
    # rank-deficient problem solvable; it can only lower ν, by (Δ/σ₀)² ≈ 1e-4)
    alone = levenberg_marquardt(window_prob, res.theta, post.P0,
                                max_iterations=max_iterations)
    th_w = alone.theta if np.all(np.isfinite(alone.theta)) else res.theta
    V_w = min(_moment_cost(par, window_prob.G, th_w),
              _moment_cost(par, window_prob.G, res.theta))
    nu = max(2.0 * (res.cost - J_prev - V_w), 0.0)
    L = np.linalg.cholesky(P_p)
    lam = np.linalg.eigvalsh(L.T @ res.information @ L)
    d = int(np.sum(lam > GATE_RELATIVE_EIGENVALUE * max(lam[-1], 0.0))) if lam[-1] > 0 else 0
    return nu, d


class ReferenceLoad:
    """The static hub load (6,) a posterior's angles refer to (docs/identification.md,
    "A ground calibration carried to the flight's trim"): the mean of the accepted known-load
    windows' loads (a restored one counts as one window), or the trim it was last carried to;
    None: not known (a configured start, a file written before it was saved)."""

    def __init__(self, load: np.ndarray | None = None, windows: int = 0) -> None:
        self.load, self.windows = load, windows
        # what solving for the angles' load dependence adds at this reference (LoadSpread):
        # the covariance and the move of the estimate, set at each accepted known-load run of
        # a rig with a sensitivity bound
        self.cov: np.ndarray | None = None
        self.shift: np.ndarray | None = None

    @classmethod
    def restored(cls, load: Any) -> "ReferenceLoad":
        return cls() if load is None else cls(np.asarray(load, float).copy(), 1)

    def note(self, static_load: np.ndarray | None) -> None:
        """An accepted known-load window at ``static_load`` (6,): the mean takes it in."""
        h = None if static_load is None else np.asarray(static_load, float)
        if h is None or h.shape != (6,) or not np.all(np.isfinite(h)):
            return
        n = self.windows
        self.load = h.copy() if self.load is None or n == 0 else (self.load * n + h) / (n + 1)
        self.windows = n + 1

    def reported(self, P: np.ndarray) -> np.ndarray:
        """``P`` with the load spread added: what records and files state."""
        return P.copy() if self.cov is None else P + self.cov

    def reported_theta(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` moved by the solved-for load dependence: what records and files state."""
        return theta.copy() if self.shift is None else theta + self.shift


def move_reference(post: "SequentialPosterior", reference: np.ndarray,
                   sensitivity: np.ndarray | None) -> tuple[np.ndarray, float] | None:
    """Carry ``post`` to the angles at another static load (a flight's trim):
    P + σ_L² I with σ_L² = Σ_k (s_k Δ_k)² for the move Δ from the load it referred to
    (load_excursion_variance; the rig's 1-σ bound on the angles' load sensitivity), each
    angle's variance held within limit²/3 (an angle anywhere in its physical range), the mean
    unchanged (the bound's sign is unknown). Returns (Δ, σ_L) when it moved a reference it
    had; a posterior with none takes this one without widening (a configured start is a
    statement about the angles where the run starts)."""
    r = np.asarray(reference, float)
    if r.shape != (6,) or not np.all(np.isfinite(r)):
        return None
    old = post.reference.load
    # the ground runs' load spread goes with it
    post.theta = post.reference.reported_theta(post.theta)
    post.P = post.reference.reported(post.P)
    post.reference = ReferenceLoad(r.copy(), 0)
    if old is None or sensitivity is None:
        return None
    delta = r - old
    v = load_excursion_variance(sensitivity, delta)
    if v <= 0.0:
        return None
    # bounded by the physical limit: no angle's variance beyond that of an angle anywhere
    # in its ±limit range (uniform, limit²/3) — a larger move than the rig allows says nothing
    cap = np.where(np.isfinite(post.limit), post.limit ** 2 / 3.0, math.inf)
    post.P = post.P + np.diag(np.minimum(v, np.maximum(cap - np.diag(post.P), 0.0)))
    post.fold()
    return delta, math.sqrt(v)


class LoadReference:
    """The reference (trim) load of filter-error windows and each window's excursion from it
    (docs/identification.md, "Load excursions"): the median of the last
    LOAD_REFERENCE_WINDOWS windows' static loads (bounded)."""

    def __init__(self, sensitivity: np.ndarray | None) -> None:
        k = None if sensitivity is None else np.asarray(sensitivity, float)
        self.sensitivity = k if k is not None and np.any(k > 0) else None
        self.loads: deque[np.ndarray] = deque(maxlen=LOAD_REFERENCE_WINDOWS)
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # (the window's load, median)

    def observe(self, static_load: np.ndarray | None) -> np.ndarray | None:
        """A window's static load: the reference (the median with it) after it, or None
        (no sensitivity configured, or no finite load: the window is left out)."""
        self._last = None
        if self.sensitivity is None or static_load is None:
            return None
        h = np.asarray(static_load, float)
        if h.shape != (6,) or not np.all(np.isfinite(h)):
            return None
        self.loads.append(h.copy())
        ref: np.ndarray = np.median(np.array(self.loads), axis=0)
        self._last = (h.copy(), ref)
        return ref

    def judge(self, checks: FilterErrorChecks) -> None:
        """Set the observed window's ``load_delta`` and ``load_variance`` in ``checks``
        (nothing when the window was not observed)."""
        if self._last is None or self.sensitivity is None:
            return
        h, ref = self._last
        delta = h - ref
        checks.load_delta = delta
        checks.load_variance = load_excursion_variance(self.sensitivity, delta)


@dataclass
class PeriodicIdentification:
    """Windows of content-filtered data → identification → posterior (model §7, periodic runs).

    The shared skeleton of a window's run (:meth:`run_window`: the window's input and its
    settling, the prior, the solve, the judgement, the bookkeeping after it); each mode is
    its own subclass — :class:`KnownLoadIdentification`, :class:`FilterErrorIdentification` —
    owning its problem, its solve and its checks. The class is chosen at the door: the
    constructor called with ``mode=...`` makes that mode's class (:data:`IDENTIFICATIONS`),
    so the mode is never compared inside a run.

    Known-load mode: ``run_window(z, T, H)``; filter-error mode: ``run_window(z, T)`` with the
    calibration filter's ``Phi, K, J, Qd`` (``design``: any object with those attributes and
    ``slowest_time_constant_s``). The filter-error state and its sensitivities continue from
    window to window. After a discontinuity the first samples settle unscored: at the start
    and after a gap (:meth:`mark_discontinuity`) the content filter's settling
    (``content_settle_samples``, e.g. ``ContentFilter.settle_samples``) — in both modes: the
    balance holds through the content filter's transient, but its start-up state carries one
    sample's full (unfiltered) noise for a second or so, which the likelihood would count as
    hundreds of independent samples (measured: χ² of 400 after one such window) — plus, in
    filter-error mode, ``settle_time_constants × slowest τ`` of the calibration filter; after
    new angles are applied (an accepted run) the calibration filter settles again.
    """

    model: RigModel
    posterior: SequentialPosterior
    mode: str
    content: str
    fs: float
    moment_floor: float
    max_iterations: int
    apply_delay_samples: int
    correlation_time_s: float  # τ: coloured-residual lags ≤ 5τ
    settle_time_constants: float = 5.0
    content_settle_samples: int = 0
    gap_samples: int | None = None
    # filter error: more than this fraction of the window missing in short runs (dropped
    # frames) is stale_input, detail "scattered_samples" (docs/identification.md)
    scattered_fraction: float = math.inf
    # known loads: the curvature index (estimator.curvature) above which a run is held
    nonlinearity_limit: float = math.inf
    design: Any = None
    alpha_base: np.ndarray | None = None
    # the content filter (filter error: Γ(k) of the information rule, docs/identification.md)
    content_sos: np.ndarray | None = None
    robust_filter_error: bool = True  # False: model §7's decisions only (for comparison)
    false_alarm: float = 1e-3  # the innovation test's
    structure_test: bool = True  # known loads: test constant angles (estimator.structure)
    # a bound (1 σ, rad per N / N·m) on the angles' move per unit of static hub load away from
    # the reference load — the median of the last LOAD_REFERENCE_WINDOWS windows' static
    # loads (the trim; filter error) or the accepted windows' mean (known loads: the load
    # spread); None or zeros: the angles do not depend on the load
    angle_load_sensitivity: np.ndarray | None = None
    # known loads: a bound (1 σ, rad/s) on each angle's drift rate, solved for beside the
    # angles in what the posterior states (estimator.load_spread); 0: none
    angle_drift_rate: float = 0.0
    filter_state: FilterErrorState | None = field(default=None, init=False)
    _settle_pending: int = field(default=0, init=False)
    _last_end: int | None = field(default=None, init=False)
    # filter error: the last window's problem and the θ its run ended at (the prior mean when
    # the run was not sound), for what reads the window's information afterwards
    # (estimator.flight_advice: what would determine the rest); None after a known-load or
    # stale window
    last_window: tuple[FilterErrorProblem, np.ndarray] | None = field(default=None, init=False)
    # the drift bound's fit in use (DriftTest look) and the one held windows started from
    _bound_look: int | None = field(default=None, init=False)
    _held_look: int | None = field(default=None, init=False)
    # the last accepted posterior (θ, P) and the time its angles are at (the window's middle
    # when its prior was the bound's; None: the data's mean time): what the drift bound's
    # shift moves (None: none since the start or a reset)
    _accepted: tuple[np.ndarray, np.ndarray, float | None] | None = field(default=None,
                                                                           init=False)
    _t_mid: float | None = field(default=None, init=False)  # the running window's middle

    def __new__(cls, *args: Any, **kw: Any) -> "PeriodicIdentification":
        # the door: PeriodicIdentification(mode=...) is that mode's class
        if cls is PeriodicIdentification:
            mode = kw.get("mode", args[2] if len(args) > 2 else None)
            if mode not in IDENTIFICATIONS:
                raise ValueError(f"mode must be one of {MODES}")
            cls = IDENTIFICATIONS[Mode(mode)]
        return super().__new__(cls)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}")
        self.mode = Mode(self.mode)
        self.par = Parameterisation(self.model, self.posterior.names, self.alpha_base,
                                    moment_floor=self.moment_floor,
                                    known_loads=self.mode == Mode.KNOWN_LOADS)
        self._load_reference = LoadReference(self.angle_load_sensitivity)
        self._spread: LoadSpread | None = None
        self.structure: StructureTest | None = None
        self.mark_discontinuity()

    @property
    def filter_settle_samples(self) -> int:
        """Samples the calibration filter takes to settle (filter error; 0 otherwise)."""
        return 0

    def mark_discontinuity(self) -> None:
        """The start or a gap longer than the configured one: content filter and calibration
        filter both settle at the start of the next window."""
        self._settle_pending = int(self.content_settle_samples) + self.filter_settle_samples

    def alpha(self) -> np.ndarray:
        """The 14 angles of the current posterior."""
        return self.par.alpha(self.posterior.theta)

    def run_window(
        self,
        z: np.ndarray,
        T: np.ndarray,
        H: np.ndarray | None = None,
        q: np.ndarray | None = None,
        *,
        seq0: int,
        valid: np.ndarray | None = None,
        t: float | None = None,
        arrived_seq: int | None = None,
        dpsi: np.ndarray | None = None,
        static_load: np.ndarray | None = None,
    ) -> AnglesRecord:
        """One window. ``dpsi`` (filter error, azimuth mode): the rotor's measured turn since
        the previous sample, per sample (NaN: the design's Ω) — the calibration filter's
        harmonic states turn with it (``filters.azimuth_transition``).
        ``static_load``: the window's mean static hub-load estimate (6,): in filter-error
        mode for the load excursion and the reference move (``angle_load_sensitivity``), in
        known-load mode (accepted) for the posterior's reference load."""
        w = _Window.of(self, z, T, H, q, seq0, valid, static_load, dpsi)
        moved = self._carry_reference(static_load)
        post = self.posterior
        verdict = None if self.structure is None else self.structure.last
        self.last_window = None
        stale = input_verdict(w.missing, post.stale_fraction, *self._scattered(w))
        if stale is not None:
            # what is left determines too little (below, the run uses the samples it has —
            # those lacking an input are left out, the information reduced so)
            rec = post.update(None, window=w.span, mode=self.mode, content=self.content, t=t,
                              missing_fraction=w.missing, structure=verdict, dt=w.dt,
                              stale=stale)
            rec.samples_used = 0
            return rec
        prob, moments, verdict = self._problem(w, verdict)
        theta_p, P_p = post.prior(w.dt)
        self._settle_pending = max(self._settle_pending - w.n, 0)
        res, lm_prior, gate, solved = self._solve(prob, moments, theta_p, P_p, w.dt)
        judged = self._checks(solved, res, lm_prior, verdict)
        rec = post.update(res, window=w.span, mode=self.mode, content=self.content,
                          t=t, missing_fraction=w.missing,
                          apply_delay_samples=self.apply_delay_samples,
                          arrived_seq=arrived_seq, moments=moments, dt=w.dt, gate=gate,
                          **judged)
        if moved is not None:
            rec.reference_move = {"delta": [float(x) for x in moved[0]], "sigma": moved[1]}
        self._after(rec, res, moments, w)
        rec.samples_used = int(prob.scored.sum() if isinstance(prob, FilterErrorProblem)
                               else np.count_nonzero(w.scored))
        if rec.accepted:
            # new angles applied: the calibration filter settles again
            self._settle_pending = max(self._settle_pending, self.filter_settle_samples)
        return rec

    # ------------------------------------------------------------- what each mode supplies
    def _carry_reference(self, static_load: np.ndarray | None
                         ) -> tuple[np.ndarray, float] | None:
        """Before the prior: carry the posterior to the window's reference load (filter
        error); the move (Δ, σ_L), or None."""
        return None

    def _scattered(self, w: "_Window") -> tuple[Callable[[], float] | None, float]:
        """The window's fraction missing in short gaps (a callable, evaluated only when the
        window is otherwise complete enough) and its limit; (None, ∞): not tested."""
        return None, math.inf

    def _problem(self, w: "_Window", verdict: StructureVerdict | None
                 ) -> tuple[Any, tuple[np.ndarray, int] | None, StructureVerdict | None]:
        """The window's likelihood problem, its known-load moments (G, scored samples; None
        in filter-error mode) and the structure verdict the run is judged with."""
        raise NotImplementedError

    def _solve(self, prob: Any, moments: tuple[np.ndarray, int] | None, theta_p: np.ndarray,
               P_p: np.ndarray, dt: float
               ) -> "_Solved":
        """The run: (result, the prior its search used, the caller's gate (ν, d) or None,
        the problem it solved)."""
        res = levenberg_marquardt(prob, theta_p, P_p, max_iterations=self.max_iterations,
                                  max_lag=self._max_lag())
        return res, (theta_p, P_p), None, prob

    def _max_lag(self) -> int:
        return int(math.ceil(5.0 * self.correlation_time_s * self.fs))

    def _checks(self, prob: Any, res: IdentificationResult,
                lm_prior: tuple[np.ndarray, np.ndarray],
                verdict: StructureVerdict | None) -> dict[str, Any]:
        """The mode's own checks of a run, as the judge's keyword arguments."""
        return {"structure": verdict}

    def _after(self, rec: AnglesRecord, res: IdentificationResult,
               moments: tuple[np.ndarray, int] | None, w: "_Window") -> None:
        """The mode's bookkeeping after the judgement."""


@dataclass
class _Window:
    """One window's span, its settling and its input fractions (the skeleton's first step)."""

    n: int
    span: tuple[int, int]
    dt: float  # the random-walk time since the previous window
    valid: np.ndarray
    scored: np.ndarray
    missing: float
    gap: int
    z: np.ndarray
    T: np.ndarray
    H: np.ndarray | None
    q: np.ndarray | None
    static_load: np.ndarray | None
    dpsi: np.ndarray | None

    @classmethod
    def of(cls, ident: PeriodicIdentification, z: np.ndarray, T: np.ndarray,
           H: np.ndarray | None, q: np.ndarray | None, seq0: int, valid: np.ndarray | None,
           static_load: np.ndarray | None, dpsi: np.ndarray | None) -> "_Window":
        N = len(T)
        valid = np.ones(N, bool) if valid is None else np.asarray(valid, bool)
        seq1 = seq0 + N - 1
        dt = 0.0 if ident._last_end is None else (seq1 - ident._last_end) / ident.fs
        ident._last_end = seq1
        gap = N + 1 if ident.gap_samples is None else ident.gap_samples
        # a gap inside the window settles the content filter (and the calibration filter)
        scored = valid & scored_mask(valid, int(ident.content_settle_samples)
                                     + ident.filter_settle_samples, gap, False)
        scored[: ident._settle_pending] = False
        missing = 1.0 - float(valid.mean()) if N else 1.0
        return cls(N, (seq0, seq1), dt, valid, scored, missing, gap, z, T, H, q, static_load,
                   dpsi)


class KnownLoadIdentification(PeriodicIdentification):
    """Known-load windows (the balance measures H): the re-linearised exact likelihood of the
    windows since the anchor, the curvature check, the structure and drift tests, and the
    load spread of the windows' loads."""

    def __post_init__(self) -> None:
        super().__post_init__()
        sens = self._load_reference.sensitivity
        rate = float(self.angle_drift_rate)
        self._spread = (None if sens is None and rate <= 0.0
                        else LoadSpread(self.posterior, self.par, sens, rate))
        self._own: tuple[np.ndarray, int] | None = None  # the window's own moments
        self._nonlinearity: float | None = None  # the last run's curvature index
        if self.structure_test and self.content == "static":
            # the test compares window means: static content only (docs/identification.md)
            self.structure = StructureTest(self.model, self.moment_floor)

    def _problem(self, w: _Window, verdict: StructureVerdict | None
                 ) -> tuple[Any, tuple[np.ndarray, int] | None, StructureVerdict | None]:
        post = self.posterior
        if self.structure is not None:
            x = self.par.stack(w.z, w.T, w.H, w.q)[w.scored]
            # the window's middle (s) for the drift test
            t_mid = self._t_mid = 0.5 * (w.span[0] + w.span[1]) / self.fs
            verdict = self.structure.add_window(x, self.par.alpha(post.theta), t=t_mid)
            self._follow_drift(verdict, t_mid)
        if w.H is None:
            raise ValueError("a known-load window needs its known loads H")
        window = KnownLoadProblem(self.par, w.z, w.T, w.H, w.q, scored=w.scored)
        self._own = (window.G, window.n_scored)  # this window's alone (LoadSpread)
        prob: KnownLoadProblem | AccumulatedKnownLoadProblem = window
        if post.relinearise and post.moments.G_held is not None:
            # windows held back as not identifiable on their own count with this one
            prob = window.with_moments(post.moments.G_held, post.moments.n_held)
        return prob, (prob.G, prob.n_scored), verdict

    def _solve(self, prob: Any, moments: tuple[np.ndarray, int] | None, theta_p: np.ndarray,
               P_p: np.ndarray, dt: float
               ) -> "_Solved":
        """Re-linearised (the posterior's ``relinearise``): solve the exact likelihood of
        every window since the anchor, starting from the previous posterior mean, then judge
        the run as this window's (gate and information against the previous posterior, as
        model §7 says)."""
        post = self.posterior
        if moments is None or not post.relinearise:
            return super()._solve(prob, moments, theta_p, P_p, dt)
        window_prob = prob
        theta_a, P_a = post.anchor_prior(dt)
        if post.moments.G_acc is not None:
            if isinstance(window_prob, KnownLoadProblem):
                prob = window_prob.with_moments(post.moments.G_acc, post.moments.n_acc)
            elif isinstance(window_prob, AccumulatedKnownLoadProblem):
                prob = window_prob.window.with_moments(
                    window_prob.G_extra + post.moments.G_acc,
                    window_prob.n_scored - window_prob.n_series + post.moments.n_acc)
        res = levenberg_marquardt(prob, theta_a, P_a, max_iterations=self.max_iterations,
                                  max_lag=self._max_lag(), start=theta_p)
        M_w = _window_information(window_prob, res)
        res = replace(res, prior_mean=theta_p, prior_cov=P_p, information=M_w,
                      n_scored=window_prob.n_scored,
                      status=res.status if np.all(np.isfinite(M_w)) else "diverged")
        gate = None
        if res.sound:
            gate = likelihood_ratio_gate(post, self.par, self.max_iterations, window_prob,
                                         res, theta_a, P_a, theta_p, P_p)
        return res, (theta_a, P_a), gate, prob

    def _checks(self, prob: Any, res: IdentificationResult,
                lm_prior: tuple[np.ndarray, np.ndarray],
                verdict: StructureVerdict | None) -> dict[str, Any]:
        nonlinear = None
        if math.isfinite(self.nonlinearity_limit) and res.sound and lm_prior[1] is not None:
            # does the run's Gaussian summary hold? (estimator.curvature: the cold start's
            # curved valley; its window's information is held for the next run)
            nonlinear = nonlinearity(prob, lm_prior[0], lm_prior[1], res.theta, res.P,
                                     math.sqrt(float(np.max(np.diag(self.posterior.P0)))))
        self._nonlinearity = nonlinear
        held = nonlinear is not None and nonlinear > self.nonlinearity_limit
        if self.structure is not None and res.sound and not held:
            # a cold start's look had no verdict: judge it at the run's own estimate, before
            # the run is accepted on angles the structure test has not seen
            verdict = self.structure.rejudge(res.theta)
        return {"structure": verdict, "nonlinear": held,
                "nonlinearity_limit": self.nonlinearity_limit}

    def _after(self, rec: AnglesRecord, res: IdentificationResult,
               moments: tuple[np.ndarray, int] | None, w: _Window) -> None:
        post = self.posterior
        rec.nonlinearity = self._nonlinearity
        if rec.accepted:
            post.reference.note(w.static_load)
        if self._spread is not None and moments is not None and self._own is not None:
            self._spread.after(rec, self._own, w.static_load, float(rec.t or 0.0))
            # the record states the spread it added
            rec.alpha = post.reference.reported_theta(post.theta)
            rec.P = post.reference.reported(post.P)
        if self.structure is not None:
            self._structure_after(rec)
        if rec.accepted:
            bounded = self._bound_look is not None and post.trend is None
            self._accepted = (post.theta.copy(), post.P.copy(),
                              self._t_mid if bounded else None)
        elif rec.reason == Reason.RESET:
            self._accepted = None

    def _follow_drift(self, verdict: StructureVerdict, t: float) -> None:
        """The trend the posterior tracks with : the drift test's while it selects
        it; none once the test finds the angles constant again (testable, not rejected) or
        restarts (a step is not a trend); otherwise the one in force stays."""
        if self.structure is None:  # (only called with a structure test)
            return
        d = verdict.drift
        post = self.posterior
        names = self.model.geometry.angle_names
        if verdict.structure == "not_constant":
            # a load dependence is not a trend, and the constant-angle fits the prediction
            # comes from do not hold: nothing moves the posterior while it is rejected
            post.set_trend(None)
            post.set_prediction(None)
            self._bound_look = None
            return
        if d is not None and d.selected:
            post.set_trend(names, d.rate)
        elif post.trend is not None and (
                (d is not None and d.restarted)
                or (d is not None and d.dof > 0 and not d.rejects_constant)):
            post.set_trend(None)
        drift = self.structure.drift
        # under the trend its prediction; before one is selected, the prediction under the
        # drift the windows cannot exclude (DriftTest.bounded_prediction)
        pred = None
        self._bound_look = None
        if drift is not None and post.trend is not None:
            pred = drift.prediction
        elif drift is not None and post.moments.windows_held and self._held_look is not None:
            # windows held since: the bound's fit from before them, the held moments added
            pred = self._bounded(drift, t, self._held_look)
            self._bound_look = self._held_look
        elif drift is not None:
            pred = self._bounded(drift, t, drift.bounded_look)
            self._bound_look = drift.bounded_look
            if pred is not None and post.moments.windows_held and self._accepted is None:
                post.moments.drop_held()  # the prediction holds them already
        if pred is not None:
            post.set_prediction(names, *pred)
        else:
            post.set_prediction(None)

    def _bounded(self, drift: DriftTest, t: float, look: int | None
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        """The bound's prediction (:meth:`DriftTest.predict_bounded`), kept from its fit where
        that fit is informative and replaced by the last accepted posterior (moved by the
        bound's drift since, :meth:`DriftTest.bounded_shift`) where the fit of window means
        alone is far wider — :func:`bounded_against_posterior` (the drift benchmark's constant arm, seed 68: σ 14°
        in a direction the posterior held to 0.2°, and a run re-solved into another valley)."""
        if look is None:
            return None
        pred: tuple[np.ndarray, np.ndarray] | None = drift.predict_bounded(t, look)
        fit_at = drift.bounded_angles(look)
        if pred is None or self._accepted is None:
            return self._with_load_spread(drift, t, look, pred, fit_at)
        theta, P, since = self._accepted
        sh = drift.bounded_shift(t, look, since)
        if sh is None:
            return self._with_load_spread(drift, t, look, pred, fit_at)
        names = self.posterior.names
        idx = [names.index(n) for n in self.model.geometry.angle_names]
        P_acc = self.posterior.reference.reported(P) if self._spread is not None else P
        ref = theta[idx] + sh[0], P_acc[np.ix_(idx, idx)] + sh[1]
        # the fit re-linearised at the reference (DriftTest.predict_bounded_at): the constant
        # fit of the means alone may be far off where only the posterior knows the angles,
        # and its Jacobians there bend the directions the means do determine (the drift benchmark's constant
        # arm, seed 79: 8.7° off, the run accepted at χ²₁₄ 83). Once: re-linearising again
        # at the combination can follow the means back into their valley (seed 79, 184).
        again = drift.predict_bounded_at(t, look, ref[0])
        if again is not None:
            pred, fit_at = again, ref[0]
        spread = self._with_load_spread(drift, t, look, pred, fit_at)
        return bounded_against_posterior(pred if spread is None else spread, *ref)

    def _with_load_spread(self, drift: DriftTest, t: float, look: int,
                          pred: tuple[np.ndarray, np.ndarray] | None,
                          at: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """``pred`` with the spread of its windows' loads added where the rig bounds the
        angles' load sensitivity (:meth:`DriftTest.bounded_load_spread`): the fit
        of window means held at different loads knows nothing of it (the flight benchmark's rig_ground_load arm:
        a flight run at χ²₁₄ 59.0 against 52.3 after its ground calibration's prior was the
        bounded prediction)."""
        if (pred is None or at is None or self._spread is None
                or not np.any(self._spread.sensitivity > 0)):
            return pred
        C = drift.bounded_load_spread(t, look, at, self._spread.sensitivity,
                                      self.posterior.reference.load)
        return pred if C is None else (pred[0], pred[1] + C)

    def _structure_after(self, rec: AnglesRecord) -> None:
        """The bound's fit the held windows' next run starts from, and the structure the
        hub-load estimate uses (docs/identification.md): the selected one, while it stays
        selected; none once the constant model fits again; while the test has not
        (re)selected one, the one in force stays (a restored one)."""
        assert self.structure is not None
        post = self.posterior
        if post.moments.windows_held == 0 or post.prediction is None:
            self._held_look = None
        elif self._held_look is None:
            self._held_look = self._bound_look
        v = self.structure.last
        if v.selected is not None:
            post.structure_fit = fit_payload(v.selected, self.model)
        elif v.structure == "constant":
            post.structure_fit = None
        rec.structure_fit = post.structure_fit



class FilterErrorIdentification(PeriodicIdentification):
    """Filter-error windows (flight: the calibration filter predicts the loads): the filter's
    state and sensitivities carried from window to window, the reference (trim) load and the
    window's excursion from it, and the information rule's checks (the innovation test and
    the sandwich score covariance)."""

    def __post_init__(self) -> None:
        if self.design is None:
            raise ValueError("filter-error mode needs the calibration filter design")
        super().__post_init__()

    @property
    def filter_settle_samples(self) -> int:
        return int(math.ceil(self.settle_time_constants * self.design.slowest_time_constant_s
                             * self.fs))

    def filter_error_checks(self, prob: FilterErrorProblem, theta: np.ndarray
                            ) -> FilterErrorChecks:
        """The innovation test and the sandwich score covariance of a filter-error window
        at the run's estimate θ (docs/identification.md, the information rule)."""
        e, de, B = prob.residual_series(theta)
        W = self.par.terms(theta).W
        d = self.design
        n = max(int(prob.n_scored), 1)
        gamma = innovation_autocovariance(d.Phi, d.K, d.J, d.Qd, W, self.content_sos,
                                          max(n, SPECTRUM_SEGMENT))
        test = innovation_spectrum_test(e, prob.scored, gamma, self.false_alarm)
        lag = int(self.content_settle_samples) + self.filter_settle_samples
        Q_data = score_covariance_hac(e, de, B, lag)
        Q_model = predicted_score_covariance(de, B, gamma)
        return FilterErrorChecks(test, Q_data, Q_model)

    def _carry_reference(self, static_load: np.ndarray | None
                         ) -> tuple[np.ndarray, float] | None:
        # the trim the window's angles refer to; a posterior of another load (a ground
        # calibration) is carried there first (move_reference)
        ref = self._load_reference.observe(static_load)
        if ref is None:
            return None
        return move_reference(self.posterior, ref, self._load_reference.sensitivity)

    def _scattered(self, w: _Window) -> tuple[Callable[[], float] | None, float]:
        # each held sample perturbs the content at the valid samples after it, which the
        # calibration filter's model does not hold: the estimate is biased (measured:
        # flight rig, 10 % of cell_A dropped, χ²₁₄ up to 134 against the window's truth)
        return (lambda: scattered_missing_fraction(w.valid, w.gap)), self.scattered_fraction

    def _problem(self, w: _Window, verdict: StructureVerdict | None
                 ) -> tuple[Any, tuple[np.ndarray, int] | None, StructureVerdict | None]:
        Phi_n = None
        if w.dpsi is not None:
            from .filters import azimuth_transition

            d = self.design
            dp = np.asarray(w.dpsi, float)
            Phi_n = azimuth_transition(d, np.where(np.isfinite(dp), dp, d.omega * d.dt))
        prob = FilterErrorProblem(
            self.par, self.design.Phi, self.design.K, self.design.J, self.design.Qd, w.z, w.T,
            w.q, valid=w.valid, state=self.filter_state, discontinuity=False, Phi_n=Phi_n)
        prob.scored &= w.scored
        prob.n_scored = int(prob.scored.sum())
        return prob, None, verdict

    def _checks(self, prob: Any, res: IdentificationResult,
                lm_prior: tuple[np.ndarray, np.ndarray],
                verdict: StructureVerdict | None) -> dict[str, Any]:
        self.last_window = (prob, res.theta if res.sound else lm_prior[0])
        checks = None
        if self.robust_filter_error and res.sound:
            checks = self.filter_error_checks(prob, res.theta)
            self._load_reference.judge(checks)
        return {"structure": verdict, "checks": checks}

    def _after(self, rec: AnglesRecord, res: IdentificationResult,
               moments: tuple[np.ndarray, int] | None, w: _Window) -> None:
        if res.end_state is not None and res.status != "diverged":
            self.filter_state = res.end_state


# the class of each identification mode (PeriodicIdentification(mode=...) makes it)
IDENTIFICATIONS: dict[Mode, type[PeriodicIdentification]] = {
    Mode.KNOWN_LOADS: KnownLoadIdentification,
    Mode.FILTER_ERROR: FilterErrorIdentification,
}

_Solved = tuple[IdentificationResult, tuple[np.ndarray, np.ndarray], tuple[float, int] | None,
                Any]


def _window_information(window_prob: Any, res: IdentificationResult) -> np.ndarray:
    """The window's own information M at a re-linearised run's estimate (NaN where it cannot
    be evaluated: the run is then taken as diverged)."""
    if np.all(np.isfinite(res.theta)):
        try:
            M_ev = window_prob.evaluate(res.theta).information
            return np.full_like(res.information, np.nan) if M_ev is None else M_ev
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            pass
    return np.full_like(res.information, np.nan)
