"""The words of a run's judgement (estimator/verdict.py): every ``detail`` the package writes or
compares is one of ``DETAILS`` and every one of them is made by the judge and documented; the
enums are their strings (the records' JSON unchanged)."""
from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import numpy as np
import pytest

from rsra.estimator.posterior import DETAILS, MODES, REASONS
from rsra.estimator.verdict import Detail, Mode, Reason, Verdict

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("daq", "estimator", "sim_bus", "config")
# where the decisions are made (estimator.judgement) and turned into records
JUDGE = ("estimator/judgement.py", "estimator/posterior.py")


def _detail_literals() -> dict[str, list[str]]:
    """Every string literal the package passes as ``detail=`` or compares with a ``detail``
    (``x.detail == "..."``, ``detail in ("...", ...)``) -> where."""
    found: dict[str, list[str]] = {}

    def named_detail(node: ast.AST) -> bool:
        return (isinstance(node, ast.Name) and node.id == "detail") or (
            isinstance(node, ast.Attribute) and node.attr == "detail")

    def strings(node: ast.AST) -> list[str]:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [node.value]
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return [s for e in node.elts for s in strings(e)]
        return []

    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            where = path.relative_to(ROOT).as_posix()
            for node in ast.walk(ast.parse(path.read_text())):
                values: list[str] = []
                if isinstance(node, ast.keyword) and node.arg == "detail":
                    values = strings(node.value)
                elif isinstance(node, ast.Compare):
                    sides = [node.left, *node.comparators]
                    if any(named_detail(s) for s in sides):
                        values = [v for s in sides for v in strings(s)]
                for v in values:
                    found.setdefault(v, []).append(f"{where}:{node.lineno}")
    return found


def test_every_detail_written_or_compared_is_in_DETAILS():
    found = _detail_literals()
    assert {"nonlinear", "scattered_samples"} <= set(found)  # the scan sees the shell's words
    unknown = {v: w for v, w in found.items() if v not in DETAILS}
    assert unknown == {}, "details outside estimator.verdict.Detail: add them there (and to " \
        "docs/telemetry.md's angles `detail`)"


def test_every_detail_is_made_by_the_judge_and_documented():
    used = set()
    for rel in JUDGE:
        for node in ast.walk(ast.parse((ROOT / rel).read_text())):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id == "Detail"):
                used.add(Detail[node.attr])
    assert set(DETAILS) == used, f"never decided: {sorted(set(DETAILS) - used)}"
    doc = (ROOT / "docs" / "telemetry.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `detail` |"))
    documented = set(re.findall(r"`([a-z_]+)`", row))
    assert set(DETAILS) <= documented, sorted(set(DETAILS) - documented)


def test_the_enums_are_their_strings_in_records_and_json():
    assert MODES == ("known_loads", "filter_error")
    assert REASONS == ("not_converged", "diverged", "not_identifiable", "inconsistent", "reset",
                       "stale_input", "out_of_range")
    v = Verdict(Reason.RESET, Detail.GATE, 36.1, 80.0, 14)
    assert v.reason == "reset" and not v.accepted and Verdict(None, Detail.PASSED).accepted
    assert json.dumps({"mode": Mode.KNOWN_LOADS, "reason": v.reason, "detail": v.detail}) == \
        '{"mode": "known_loads", "reason": "reset", "detail": "gate"}'
    assert f"{Detail.NONLINEAR}" == "nonlinear" and str(Reason.STALE_INPUT) == "stale_input"


def _run(theta, prior_mean, prior_cov, M):
    from rsra.estimator.identification import IdentificationResult

    P = np.linalg.inv(M + np.linalg.inv(prior_cov))
    return IdentificationResult(tuple("abc"), "known_loads", np.asarray(theta, float), P, None,
                                M, np.asarray(prior_mean, float), prior_cov, 1.0, 2.0, 3,
                                "converged", 100)


def test_each_verdict_carries_the_limit_its_test_used():
    # a posterior configured off the defaults: gate at 0.99, min_information 0.5, stale 0.3 —
    # every record's verdict states the limit that decided it, not a module constant
    from scipy.stats import chi2

    from rsra.estimator.posterior import SequentialPosterior

    post = SequentialPosterior(tuple("abc"), np.zeros(3), np.ones(3), drift_rate=0.0,
                               min_information=0.5, sigma_max=np.full(3, 0.1), reset_after=3,
                               stale_fraction=0.3, gate_probability=0.99, relinearise=False)
    kw = dict(window=(0, 99), mode="known_loads", content="static")
    stale = post.update(None, missing_fraction=0.5, **kw)
    assert (stale.reason, stale.detail, stale.verdict.limit) == ("stale_input",
                                                                 "missing_samples", 0.3)
    M = np.diag([1e4, 1e4, 1e4])
    far = post.update(_run([5.0, 0.0, 0.0], np.zeros(3), np.eye(3), M), **kw)
    assert (far.reason, far.detail) == ("inconsistent", "gate") and far.gate_dof == 3
    assert far.verdict.limit == pytest.approx(chi2.ppf(0.99, 3))  # 11.3, not 16.3 at 0.999
    low = post.update(_run(np.zeros(3), np.zeros(3), np.eye(3), np.diag([0.1, 0, 0])), **kw)
    assert (low.reason, low.detail, low.verdict.limit) == ("not_identifiable",
                                                           "information_ratio", 0.5)
    ok = post.update(_run([0.01, 0.0, 0.0], np.zeros(3), np.eye(3), M), **kw)
    assert ok.accepted and ok.detail == "passed" and ok.reason is None
    assert ok.verdict.limit == pytest.approx(chi2.ppf(0.99, ok.gate_dof))
    d = ok.to_dict()
    assert type(d["mode"]) is str and type(d["detail"]) is str and d["reason"] is None


def test_a_held_window_reads_held_in_the_demo_view_and_listen():
    """A known-load window too weak on its own, its information kept for the next runs, is
    'held' where the views name the last run, not 'rejected'; a refused one stays rejected."""
    from rsra.daq.cli.commands.listen import _angles_table
    from rsra.daq.cli.demo_view import _plain_last_run

    held = {"accepted": False, "mode": "known_loads", "content": "static",
            "reason": "not_identifiable", "detail": "information_ratio", "determined": 14,
            "names": ["a"] * 14}
    assert " held, 14/14 determined" in _plain_last_run(held)
    assert "held, 14 of 14 determined" in str(_angles_table(held).title)
    refused = {**held, "reason": "inconsistent", "detail": "gate"}
    assert "rejected (inconsistent)" in _plain_last_run(refused)
