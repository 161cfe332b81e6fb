"""A rejected run's explanation and hint (daq/runtime/reasons.py, issue 28): the figures
behind the decision and the likely cause, one line each — computed, never deciding."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rsra.daq.runtime.reasons import explain, input_labels
from rsra.estimator.judgement import GATE_PROBABILITY, gate_limit
from rsra.estimator.verdict import Detail, Reason, Verdict

N = 1000


def _rec(reason, **kw):
    base = dict(accepted=False, reason=reason, names=["a"] * 14, detail=None, nu=None,
                information=None, determined=0, iterations=0, cost_start=None,
                cost_history=None)
    return SimpleNamespace(**{**base, **kw})


def _job(cfg, missing: dict[str, slice], mode="filter_error", balance_gone=slice(0, 0)):
    labels = input_labels(cfg)
    bits = np.zeros(N, np.uint64)
    ok = np.ones(N, bool)
    for lab, sl in missing.items():
        bits[sl] |= np.uint64(1 << labels.index(lab))
        ok[sl] = False
    known = np.ones(N, bool)
    known[balance_gone] = False
    return {"T": np.zeros((N, 7)), "ok": ok, "known": known, "missing": bits,
            "mode": mode}, labels


@pytest.mark.parametrize("missing, balance, names, hint", [
    ({"missing:cell_C": slice(0, 180)}, slice(0, 0), ["cell_C missing in 18.0 %"],
     "cell_C silent or dropping frames"),
    ({"missing:cell_A": slice(0, 60), "missing:cell_B": slice(100, 170),
      "missing:accel_1": slice(300, 380)}, slice(0, 0),
     ["accel_1 missing in 8.0 %", "cell_B missing in 7.0 %", "cell_A missing in 6.0 %"],
     "incomplete across 3 nodes: their frames arrive too late for the SYNC"),
    ({}, slice(500, 600), ["the balance absent in 10.0 %"], "the balance stopped"),
    ({"overrange:D": slice(0, 90)}, slice(0, 0), ["D over range in 9.0 %"],
     "exceeds its full scale"),
])
def test_stale_input_names_the_input_its_fraction_and_the_cause(cfg, missing, balance, names,
                                                                hint):
    job, labels = _job(cfg, missing, "known_loads", balance)
    text, h = explain(_rec("stale_input", detail="missing_samples"), job, cfg.identification,
                      labels)
    assert "allowed 50.0 %" in text and "\n" not in text + h
    pos = [text.index(n) for n in names]  # every input named, the most often missing first
    assert pos == sorted(pos), text
    assert hint in h, h


def test_stale_input_says_the_unusable_share_of_the_window(cfg):
    """A known-load window's unusable samples: those lacking an input and those without the
    balance (180 + 100 of 1000), against the share the mode allows."""
    job, labels = _job(cfg, {"missing:cell_C": slice(0, 180)}, "known_loads", slice(500, 600))
    text, _ = explain(_rec("stale_input", detail="missing_samples"), job, cfg.identification,
                      labels)
    assert text.startswith("28.0 % of the window's 1000 samples unusable (allowed 50.0 %)"), text


def test_not_converged_gives_iterations_the_cost_trend_and_which_way_it_went(cfg):
    idc = cfg.identification
    falling = _rec("not_converged", iterations=20, cost_start=100.0, cost_history=(90.0, 80.0))
    text, h = explain(falling, {"T": []}, idc, ())
    assert "stopped after 20 iterations" in text and "cost 100 → 80 (-20 %)" in text
    assert "still falling" in h
    flat = _rec("not_converged", iterations=20, cost_start=100.0,
                cost_history=(90.0, 89.99999))
    assert "barely moves" in explain(flat, {"T": []}, idc, ())[1]


def _gate(dof, probability=GATE_PROBABILITY):
    return Verdict(Reason.INCONSISTENT, Detail.GATE, gate_limit(probability, dof), 80.0, dof)


@pytest.mark.parametrize("reason, detail, kw, words", [
    ("inconsistent", "gate", dict(nu=80.0, gate_dof=14, verdict=_gate(14)), "gate ν 80 > 36.1"),
    ("reset", "gate", dict(nu=80.0, gate_dof=14, verdict=_gate(14)),
     "inconsistent runs in a row"),
    ("not_identifiable", "information_ratio", dict(information=0.5), "0.5 below"),
    ("out_of_range", "range", dict(run_theta=np.r_[0.3, np.zeros(13)]), "a at +17.2°"),
    ("diverged", "convergence", dict(iterations=3, cost_start=1.0, cost_history=(2.0,)),
     "diverged after 3 iterations"),
])
def test_every_rejection_has_its_figures_and_a_hint(cfg, reason, detail, kw, words):
    text, h = explain(_rec(reason, detail=detail, **kw), {"T": []}, cfg.identification, ())
    assert words in text, text
    assert h and "\n" not in text + h


def test_the_gate_is_explained_with_the_limit_its_verdict_used(cfg):
    # a gate at another probability than the module's default: the explanation states the
    # limit the run was judged by (the verdict's), not one recomputed from a constant
    loose = _gate(14, probability=0.99)
    rec = _rec("inconsistent", detail="gate", nu=30.0, gate_dof=14, verdict=loose)
    text, _ = explain(rec, {"T": []}, cfg.identification, ())
    assert f"gate ν 30 > {loose.limit:.3g}" in text and "29.1" in text, text
    assert "0.01" in text, text  # its false-alarm probability, not 10⁻³
    info = Verdict(Reason.NOT_IDENTIFIABLE, Detail.INFORMATION_RATIO, 0.25)
    rec = _rec("not_identifiable", detail="information_ratio", information=0.1, verdict=info)
    assert "min_information 0.25" in explain(rec, {"T": []}, cfg.identification, ())[0]
