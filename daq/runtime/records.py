"""Typed, frozen records for what crosses a layer or a process (docs/architecture.md).

* :class:`IdentJob` — an identification window, estimator thread → worker process.
* :class:`AnglesRecord` — the ``angles`` record (telemetry.md), worker → estimator thread →
  outputs and the recording; changed only with :func:`dataclasses.replace`
  (``late``/``applies_from_seq`` on delivery, ``restarted`` after a worker restart).
* :class:`IdentResult` / :class:`IdentError` — what the worker sends back for a job.
* :class:`InitialAngles` — the recording's first ``angles.jsonl`` line (the starting
  posterior of the run).

Serialisation happens in one place per record (``to_dict``: the JSON object, keys in the
fields' order) and parsing in one (``from_dict``). The records are frozen; numpy arrays in
them are not copied again and must not be written to after the record is built.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np


class _Absent:
    """A field the record does not carry (a recorded record of another version): left out
    of the JSON object, as it was."""

    _instance: ClassVar[_Absent | None] = None

    def __new__(cls) -> _Absent:  # one instance, also after pickling (the worker process)
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __reduce__(self) -> tuple:
        return (_Absent, ())

    def __repr__(self) -> str:
        return "ABSENT"

    def __bool__(self) -> bool:
        return False


ABSENT: Any = _Absent()


@dataclass(frozen=True, slots=True)
class AnglesRecord:
    """The ``angles`` record (telemetry.md "angles"), SI units (radians).

    The fields' order is the JSON object's key order. **Adding a field to the record is one
    line here** (``name: Any = ABSENT``, at the place it takes in the JSON object) plus
    setting it where the record is made (``daq.ident_worker.run_job``); a key this class does
    not declare is still carried, in ``extra``, after the declared ones (so a recording of
    another version replays its records as written)."""

    t: Any = ABSENT
    seq: Any = ABSENT
    mode: Any = ABSENT
    content: Any = ABSENT
    accepted: Any = ABSENT
    reason: Any = ABSENT
    detail: Any = ABSENT
    names: Any = ABSENT
    alpha: Any = ABSENT
    P: Any = ABSENT
    sigma_cr: Any = ABSENT
    sigma_cr_corrected: Any = ABSENT
    determined: Any = ABSENT
    window_determined: Any = ABSENT
    information: Any = ABSENT
    nu: Any = ABSENT
    cost: Any = ABSENT
    iterations: Any = ABSENT
    window: Any = ABSENT
    applies_from_seq: Any = ABSENT
    late: Any = ABSENT
    restarted: Any = ABSENT
    condition: Any = ABSENT
    structure: Any = ABSENT  # known loads: the structure test
    candidates: Any = ABSENT
    next_conditions: Any = ABSENT  # known loads: the experiment design
    structure_fit: Any = ABSENT  # known loads: the structure the hub loads use
    explanation: Any = ABSENT  # one line: the figures behind reason/detail
    hint: Any = ABSENT  # one line: the likely cause and what to do (null when accepted)
    drift: Any = ABSENT  # known loads: the drift test, angles on a trend
    samples_used: Any = ABSENT  # the window's samples the likelihood used
    missing_inputs: Any = ABSENT  # the inputs the window's other samples lacked
    advice: Any = ABSENT  # filter error: what would determine the rest
    extra: tuple[tuple[str, Any], ...] = ()  # keys not declared above, in their order

    FIELDS: ClassVar[tuple[str, ...]]
    _KNOWN: ClassVar[frozenset[str]]

    def to_dict(self) -> dict[str, Any]:
        """The JSON object (published, recorded): the fields it carries, then ``extra``."""
        out = {}
        for k in self.FIELDS:
            v = getattr(self, k)
            if v is not ABSENT:
                out[k] = v
        out.update(self.extra)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AnglesRecord:
        """A record from its JSON object (a recording's ``angles.jsonl``, ``to_dict``)."""
        known = cls._KNOWN
        return cls(**{k: v for k, v in d.items() if k in known},
                   extra=tuple((k, v) for k, v in d.items() if k not in known))

    def get(self, key: str, default: Any = None) -> Any:
        """A key of the JSON object (declared field or ``extra``), ``default`` if absent."""
        if key in self._KNOWN:
            v = getattr(self, key)
            return default if v is ABSENT else v
        return dict(self.extra).get(key, default)


AnglesRecord.FIELDS = tuple(f.name for f in dataclasses.fields(AnglesRecord)
                            if f.name != "extra")
AnglesRecord._KNOWN = frozenset(AnglesRecord.FIELDS)


@dataclass(frozen=True, slots=True)
class InitialAngles:
    """The first line of a recording's ``angles.jsonl``: the posterior the run starts from
    (``alpha_all``: every angle of the rig; ``names``/``alpha``/``P``: the identified ones)."""

    names: list[str]
    alpha: list[float]
    P: list[list[float]]
    alpha_all: list[float]
    structure_fit: dict | None = None  # the saved posterior's structure, if any

    def to_dict(self) -> dict[str, Any]:
        d = {"initial": True, "names": self.names, "alpha": self.alpha, "P": self.P,
             "alpha_all": self.alpha_all, "applies_from_seq": None}
        if self.structure_fit is not None:  # absent otherwise: the line as it always was
            d["structure_fit"] = self.structure_fit
        return d


@dataclass(frozen=True, slots=True)
class IdentJob:
    """One identification window (the last ``window_s`` of content-filtered samples, in
    time order) and what to do with it. Arrays are the job's own copies."""

    job_id: int
    mode: str  # "known_loads" | "filter_error"
    content: str
    applies_from_seq: int  # the planned sample (the last sample + apply delay)
    alpha: np.ndarray  # the angles in force when the window was cut
    T: np.ndarray
    z: np.ndarray
    known_H: np.ndarray
    seq: np.ndarray
    t: np.ndarray
    ok: np.ndarray
    known: np.ndarray
    omega: np.ndarray
    # the rotor's turn since the previous sample (rad; NaN where the azimuth was missing or
    # refused), azimuth mode only: the calibration filter's Φ(Δψ)
    dpsi: np.ndarray | None = None
    # what each sample lacked (bits: calibration_branch.CalibrationBranch.input_labels)
    missing: np.ndarray | None = None
    # the window's mean raw cell loads (7,) and z (6,) over its complete samples: its static
    # load, for the filter-error load excursion; None: no complete sample
    T_mean: np.ndarray | None = None
    z_mean: np.ndarray | None = None

    def as_mapping(self) -> dict[str, Any]:
        """The job as the numerics take it (``daq.ident_worker.run_job``; no copies)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True, slots=True)
class IdentResult:
    """A job's ``angles`` record; ``save_error``: the posterior save after an accepted run
    failed (the text), None when it worked, ABSENT when none was attempted."""

    job_id: int | None
    record: AnglesRecord
    save_error: Any = ABSENT


@dataclass(frozen=True, slots=True)
class IdentError:
    """A job that failed (``job_id``), or a worker that could not start (``fatal``)."""

    error: str
    job_id: int | None = None
    traceback: str | None = None
    fatal: bool = False
