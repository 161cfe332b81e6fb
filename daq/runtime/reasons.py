"""Why an identification run was rejected, in words: the ``explanation`` and ``hint`` of an
``angles`` record (docs/telemetry.md "angles").

The decision is the estimator's (estimator.posterior: ``reason`` and ``detail``); this module
only reports the figures behind it — which input the window's incomplete samples lacked and in
what fraction of the window, the iterations and the cost trend of a run that did not converge,
the gate statistic against its limit — and the likely cause, each in one line."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

SHOWN_INPUTS = 3  # inputs named in a stale_input explanation (the most often missing first)
MANY_NODES = 3  # this many nodes missing in the same window: the bus, not a node


def input_labels(cfg: Any) -> tuple[str, ...]:
    """The flags that name an input a sample lacks (``missing:<node>``, ``overrange:<cell>``,
    ``fault:<cell or accelerometer>``), then ``"unusable"`` (no flag says why). At most 64."""
    labels = [f"missing:{n.name}" for n in cfg.nodes]
    for c in cfg.cells:
        labels += [f"overrange:{c.name}", f"fault:{c.name}"]
    labels += [f"fault:{a.name}" for a in cfg.accelerometers]
    labels = list(dict.fromkeys(labels))[:63]
    return (*labels, "unusable")


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %" if x < 0.995 else f"{100 * x:.0f} %"


def _input_words(label: str) -> str:
    kind, _, name = label.partition(":")
    return {"missing": f"{name} missing", "overrange": f"{name} over range",
            "fault": f"{name} stuck or faulty", "unusable": "a non-finite reading (no flag)"
            }.get(kind, label)


def missing_inputs(job: Mapping[str, Any], labels: Sequence[str]) -> list[tuple[str, float]]:
    """(label, fraction of the window's samples) for every input some sample lacked, the most
    often missing first; the balance (``balance``) for a known-load window."""
    n = len(job["T"])
    if n == 0:
        return []
    out: list[tuple[str, float]] = []
    bits = job.get("missing")
    bits = (np.zeros(n, np.uint64) if bits is None or len(bits) != n
            else np.asarray(bits, np.uint64))
    # a sample refused with no bit naming why counts as "unusable" (the last label)
    bits = bits | np.where(~np.asarray(job["ok"], bool) & (bits == 0),
                           np.uint64(1 << (len(labels) - 1)), np.uint64(0))
    for k, lab in enumerate(labels):
        c = int(np.count_nonzero(bits & np.uint64(1 << k)))
        if c:
            out.append((lab, c / n))
    if job.get("mode") == "known_loads":
        c = int(np.count_nonzero(~np.asarray(job["known"], bool)))
        if c:
            out.append(("balance", c / n))
    out.sort(key=lambda x: -x[1])
    return out


def _stale(job: Mapping[str, Any], labels: Sequence[str], stale_fraction: float,
           scattered_gap: int | None = None) -> tuple[str, str]:
    n = len(job["T"])
    if n == 0:
        return ("the window holds no sample", "no sample reached the identification: is the "
                "bus delivering complete samples? (rsra listen)")
    valid = np.asarray(job["ok"], bool)
    if job.get("mode") == "known_loads":
        valid = valid & np.asarray(job["known"], bool)
    items = missing_inputs(job, labels)
    shown = ", ".join(f"{_input_words(lab) if lab != 'balance' else 'the balance absent'} in "
                      f"{_pct(f)}" for lab, f in items[:SHOWN_INPUTS])
    more = len(items) - SHOWN_INPUTS
    text = _unusable_share(valid, n, stale_fraction, scattered_gap)
    text += (f": {shown}" if shown else "") + (f" and {more} more input(s)" if more > 0 else "")
    if not items:
        return text, "samples unusable without a flag naming why: check the decoding (rsra listen)"
    return text, _stale_hint(items)


def _unusable_share(valid: np.ndarray, n: int, stale_fraction: float,
                    scattered_gap: int | None) -> str:
    """How much of the window's ``n`` samples was unusable, against what its mode allows."""
    if scattered_gap is None:
        bad = 1.0 - float(np.count_nonzero(valid)) / n
        return f"{_pct(bad)} of the window's {n} samples unusable (allowed {_pct(stale_fraction)})"
    # filter error: dropped frames bias the estimate (identification.md)
    from rsra.estimator.identification import scattered_missing_fraction

    return (f"{_pct(scattered_missing_fraction(valid, scattered_gap))} of the window's {n} "
            f"samples lacking an input in short gaps (≤ {scattered_gap} samples; allowed "
            f"{_pct(stale_fraction)} in a filter-error window)")


# what to check when one input is missed most, by its label's kind (missing_inputs)
_INPUT_HINTS = {
    "missing": "{} silent or dropping frames: check its power, wiring and node id "
               "(rsra nodes; health shows its state)",
    "overrange": "{} reports over range: the load exceeds its full scale "
                 "(or the cell's zero drifted: rsra zero)",
    "fault": "{} reads stuck or reports a fault: check the sensor and its cable",
}


def _stale_hint(items: list[tuple[str, float]]) -> str:
    """What to check, from the inputs missed (most often first): the balance, many nodes at
    once (the bus or the machine), else the input missed most."""
    top, _ = items[0]
    nodes = [lab.split(":", 1)[1] for lab, _ in items if lab.startswith("missing:")]
    if top == "balance":
        return ("the balance stopped (or started) reporting during a known-load window, which "
                "needs it throughout: check the balance node, or hold the known load until "
                "the window is complete")
    if len(nodes) >= MANY_NODES:
        return (f"samples incomplete across {len(nodes)} nodes: their frames arrive too late "
                "for the SYNC — a bus or a machine too slow for rig.sample_rate_hz (a shared "
                "or loaded bus, a busy machine): lower the rate, lighten the bus or give the "
                "service --realtime-priority")
    kind, _, name = top.partition(":")
    hint = _INPUT_HINTS.get(kind)
    if hint is None:
        return "non-finite readings without a flag: check the decoding (rsra listen)"
    return hint.format(" and ".join(nodes[:2]) if kind == "missing" else name)


def _trend(rec: Any) -> str:
    hist = list(getattr(rec, "cost_history", None) or ())
    j0 = getattr(rec, "cost_start", None)
    if j0 is None or not hist:
        return "no cost recorded"
    j1 = hist[-1]
    text = f"cost {j0:.6g} → {j1:.6g}"
    change = _relative_change(j0, j1)
    if change is not None:
        text += f" ({change:+.3g} %)"
    last = _relative_change(hist[-2], j1) if len(hist) >= 2 else None
    if last is not None:
        text += f", last iteration {last:+.2g} %"
    return text


def _relative_change(j0: float, j1: float) -> float | None:
    """100 (j1 − j0)/|j0| (%), None when either is not finite or j0 is 0."""
    if math.isfinite(j0) and math.isfinite(j1) and j0 != 0:
        return 100 * (j1 - j0) / abs(j0)
    return None


STILL_FALLING = 1e-4  # a last iteration that lowered J by more than this (relative; the
# search's own tolerance, estimator.identification.levenberg_marquardt rel_tol): still falling


def _still_falling(rec: Any) -> bool:
    hist = list(getattr(rec, "cost_history", None) or ())
    return (len(hist) >= 2 and all(math.isfinite(x) for x in hist[-2:])
            and hist[-2] - hist[-1] > STILL_FALLING * abs(hist[-2]))


class _Why:
    """What every explanation reads: the record, its window, the config, the labels, and the
    limit the deciding test used (as the estimator's verdict carries it: the gate's χ² point
    at the configured probability, the minimum information, ...)."""

    def __init__(self, rec: Any, job: Mapping[str, Any], idc: Any, labels: Sequence[str]):
        self.rec, self.job, self.idc, self.labels = rec, job, idc, labels
        verdict = getattr(rec, "verdict", None)
        self.limit = None if verdict is None else verdict.limit

    def gate_text(self) -> str:
        from scipy.stats import chi2

        rec, limit = self.rec, self.limit
        d = int(getattr(rec, "gate_dof", 0) or 0)
        if rec.nu is None or d == 0 or limit is None:
            return "no gate (no direction to test)"
        level = float(chi2.sf(limit, d))  # the gate's false-alarm probability
        words = "10⁻³" if abs(level - 1e-3) < 1e-9 else f"{level:.3g}"
        return (f"gate ν {rec.nu:.3g} {'≤' if rec.nu <= limit else '>'} {limit:.3g} "
                f"(χ², {d} dof, {words})")


def explain(rec: Any, job: Mapping[str, Any], idc: Any, labels: Sequence[str]
            ) -> tuple[str, str | None]:
    """(explanation, hint) of an estimator record (estimator.posterior.AnglesRecord) for the
    window ``job`` (IdentJob.as_mapping()); ``idc``: the IdentificationConfig. The hint is
    None for an accepted run."""
    why = _Why(rec, job, idc, labels)
    if rec.accepted:
        info = "" if rec.information is None else f"information ratio {rec.information:.3g}; "
        return (f"{rec.determined} of {len(rec.names)} directions determined; {info}"
                f"{why.gate_text()}", None)
    explain_reason = _BY_REASON.get(str(rec.reason))
    if explain_reason is None:
        return f"rejected: {rec.reason} ({rec.detail})", "see docs/identification.md"
    return explain_reason(why)


def _explain_stale(why: _Why) -> tuple[str, str | None]:
    job, idc, limit = why.job, why.idc, why.limit
    if why.rec.detail == "scattered_samples":
        seq, t = np.asarray(job["seq"], float), np.asarray(job["t"], float)
        fs = (seq[-1] - seq[0]) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 0.0
        return _stale(job, why.labels, idc.filter_error_scattered_fraction if limit is None
                      else limit, scattered_gap=int(round(idc.gap_s * fs)))
    return _stale(job, why.labels, idc.stale_fraction if limit is None else limit)


def _explain_not_converged(why: _Why) -> tuple[str, str | None]:
    rec, idc = why.rec, why.idc
    text = (f"stopped after {rec.iterations} iterations (identification.max_iterations "
            f"{idc.max_iterations} per stage: a warm start, then the full search) without "
            f"meeting the tolerance; {_trend(rec)}")
    if _still_falling(rec):
        return text, ("the cost was still falling at the limit: the starting angles were "
                      "far off; the next window continues from here (or raise "
                      "identification.max_iterations)")
    return text, ("the cost barely moves but the steps do not settle: a flat direction "
                  "(the window's loads too little varied, or a ramp in it); the next "
                  "window is tried")


def _explain_diverged(why: _Why) -> tuple[str, str | None]:
    return (f"the run diverged after {why.rec.iterations} iterations; {_trend(why.rec)}",
            "the run left the region where the model holds (a transient in the window, or "
            "starting angles far off); the next window is tried")


def _explain_not_identifiable(why: _Why) -> tuple[str, str | None]:
    rec, idc, limit, detail = why.rec, why.idc, why.limit, why.rec.detail
    smax = math.degrees(idc.sigma_max_rad)
    if detail == "information_ratio":
        ratio = rec.information if rec.information is not None else float("nan")
        least = idc.min_information if limit is None else limit
        return (f"largest information ratio {ratio:.3g} below identification."
                f"min_information {least:g}",
                "this window adds less than the posterior already knows: it is held and "
                "used with the next windows (nothing is lost); to learn faster, apply the "
                "load conditions the record's next_conditions lists")
    if detail == "nonlinear":
        nl = getattr(rec, "nonlinearity", None)
        return (f"the run's Gaussian summary misses the likelihood's curvature by "
                f"{nl if nl is not None else float('nan'):.3g} (χ²; "
                "identification.nonlinearity_limit "
                f"{idc.nonlinearity_limit if limit is None else limit:g})",
                "the angles are still far from known in some directions (the cold start); "
                "the window's information is kept and the next window is solved with it")
    if detail == "own_information":
        return (f"the window alone determines no direction to σ ≤ {smax:g}° "
                "(identification.sigma_max_deg)",
                "more load variation (manoeuvres, rotor-speed changes) or a longer window "
                "(identification.window_s)")
    return ("no direction stays determined once the score's variance is taken from the "
            "data (sandwich), not assumed white",
            "the innovations are coloured beyond the filter model: load content outside "
            "the model (a resonance, a transient); steadier excitation helps")


def _explain_inconsistent(why: _Why) -> tuple[str, str | None]:
    rec, idc = why.rec, why.idc
    if rec.detail == "innovations":
        inn, lim = getattr(rec, "innovation", None), getattr(rec, "innovation_limit", None)
        fig = ("" if inn is None or lim is None else
               f": {inn:.3g}× their predicted mean, limit {lim:.3g}×")
        return (f"the innovations exceed what the filter model predicts{fig}",
                "load content the filter model does not hold (a manoeuvre, a ramp, a "
                "resonance): no evidence about the angles; the reset streak is unchanged")
    if rec.detail == "structure":
        return ("the structure test rejects constant angles (structure not_constant)",
                "the angles change with the load: see the record's candidates; rsra "
                "calibrate fits a structure")
    return (f"this window's angles disagree with the posterior: {why.gate_text()}",
            f"a change in the rig (a cell moved, a load path changed) or an unmodelled "
            f"load; {idc.reset_after} in a row reset the posterior")


def _explain_reset(why: _Why) -> tuple[str, str | None]:
    return (f"{why.idc.reset_after} inconsistent runs in a row ({why.gate_text()}): the "
            "posterior σ reopened to the prior around the current mean",
            "a real change of the rig is likely: the next runs identify the angles again")


def _explain_out_of_range(why: _Why) -> tuple[str, str | None]:
    rec = why.rec
    lim = math.degrees(why.idc.angle_limit_rad)
    theta = getattr(rec, "run_theta", None)
    worst = ""
    if theta is not None and len(theta) == len(rec.names):
        k = int(np.argmax(np.abs(theta)))
        worst = f": {rec.names[k]} at {math.degrees(float(theta[k])):+.3g}°"
    return (f"the run's angles leave the physical range ±{lim:g}° "
            f"(identification.angle_limit_deg){worst}",
            "a wrong rig description (cell positions, nominal axes) or a bad channel: "
            "check --config and the cells' readings")


#: the explanation of each reason a run is not accepted
_BY_REASON = {"stale_input": _explain_stale, "not_converged": _explain_not_converged,
              "diverged": _explain_diverged, "not_identifiable": _explain_not_identifiable,
              "inconsistent": _explain_inconsistent, "reset": _explain_reset,
              "out_of_range": _explain_out_of_range}
