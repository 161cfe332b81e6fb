"""The words of an identification run's judgement and the verdict that carries them (model §7;
docs/telemetry.md §2.4, the ``angles`` record's ``mode``, ``reason`` and ``detail``).

Modes, reasons and details are :class:`enum.StrEnum` members: each *is* its string, so the
records, their JSON and every comparison with the literal stay as they were. One run's
judgement is one :class:`Verdict` — the reason (None: accepted), the test that decided it
(``detail``) and the limit that test used — made by the posterior's judge
(:meth:`estimator.posterior.SequentialPosterior.judge`) and read, not recomputed, by whoever
explains it (``rsra.daq.runtime.reasons``). Pure data.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any


class Mode(enum.StrEnum):
    """How a window identifies the angles (docs/identification.md)."""

    KNOWN_LOADS = "known_loads"  # the balance measures the hub loads
    FILTER_ERROR = "filter_error"  # the calibration filter predicts them (flight)


class Reason(enum.StrEnum):
    """Why a run was not accepted (the record's ``reason``; None when accepted)."""

    NOT_CONVERGED = "not_converged"
    DIVERGED = "diverged"
    NOT_IDENTIFIABLE = "not_identifiable"
    INCONSISTENT = "inconsistent"
    RESET = "reset"
    STALE_INPUT = "stale_input"
    OUT_OF_RANGE = "out_of_range"


class Detail(enum.StrEnum):
    """The test that decided a run (the record's ``detail``), in the order they are applied."""

    PASSED = "passed"  # accepted: every test passed
    MISSING_SAMPLES = "missing_samples"  # too much of the window lacks an input
    SCATTERED_SAMPLES = "scattered_samples"  # filter error: too many short gaps
    CONVERGENCE = "convergence"  # the search did not converge or diverged
    INFORMATION_RATIO = "information_ratio"  # the data add too little to the prior
    OWN_INFORMATION = "own_information"  # filter error: the window alone determines nothing
    ROBUST_INFORMATION = "robust_information"  # ... once the score's variance is the data's
    INNOVATIONS = "innovations"  # filter error: innovations beyond the filter model
    GATE = "gate"  # the consistency gate
    RANGE = "range"  # the estimate leaves the physical range of the angles
    STRUCTURE = "structure"  # known loads: the structure test rejects constant angles
    NONLINEAR = "nonlinear"  # known loads: the run's Gaussian summary misses the curvature


ACCEPTED = None  # the reason of an accepted run
MODES: tuple[Mode, ...] = tuple(Mode)
REASONS: tuple[Reason, ...] = tuple(Reason)
DETAILS: tuple[Detail, ...] = tuple(Detail)


# a known-load window not identifiable on its own whose information is held for the next
# runs (docs/identification.md, the min_information rule): not a refusal of its data
HELD_DETAILS = frozenset({Detail.INFORMATION_RATIO, Detail.NONLINEAR})


def held_window(rec: Any) -> bool:
    """A known-load window (an `angles` record as a dict) whose information is held for the
    next runs, not refused."""
    return (rec.get("mode") == Mode.KNOWN_LOADS and rec.get("reason") == Reason.NOT_IDENTIFIABLE
            and rec.get("detail") in HELD_DETAILS)


@dataclass(frozen=True)
class Verdict:
    """One run's judgement: ``reason`` (None: accepted), the ``detail`` of the test that
    decided, and ``limit`` — the threshold that test compared against, in the test's own
    units (None where the test has no single number):

    * ``missing_samples``, ``scattered_samples``: the allowed fraction of the window;
    * ``information_ratio``: the minimum information ratio;
    * ``own_information``, ``robust_information``: 1 (a direction's information, in units
      of σ_max⁻², at which the window alone determines it);
    * ``innovations``: the innovation statistic's 1 − 10⁻³ point over its predicted mean;
    * ``gate`` (``inconsistent``, ``reset``) and ``passed``: the gate's χ²_{d, p} point
      (None when the gate had no direction to test);
    * ``range``: the physical range (rad, the largest parameter limit);
    * ``nonlinear``: the curvature index's limit.

    ``nu``/``dof``: the gate statistic and its degrees of freedom where the gate ran."""

    reason: Reason | None
    detail: Detail
    limit: float | None = None
    nu: float | None = None
    dof: int = 0

    @property
    def accepted(self) -> bool:
        return self.reason is None
