"""The ``health`` record (docs/telemetry.md §2.5): typed, frozen, built in one place.

::

    HealthMonitor.snapshot(t)   (daq.bus.reader: the tap's 1 Hz deadline, or Reader.health())
        └▶ Health(t, nodes, bus, samples, queues, recording, sync)       ─▶ HealthReport
    HealthReporter              (daq.runtime.run_report)
        └▶ dataclasses.replace(health, latency_ms=…, queues=…, identification=…, …)
    Outputs.publish("health", health)  ─▶ Health.to_dict()  ─▶ jsonout.dumps (strict JSON)

Every part is a frozen dataclass, changed only with :func:`dataclasses.replace`. A field
left at :data:`OMIT` is not in the JSON object (the payload's optional keys); ``None`` is
``null``. :meth:`_Part.to_dict` is the one serialisation: keys in the fields' order (the
order the payload always had), tuples as lists, mappings as objects.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar, TypeVar, dataclass_transform


class _Omit:
    """A field the record does not carry: left out of the JSON object."""

    def __repr__(self) -> str:
        return "OMIT"

    def __bool__(self) -> bool:
        return False


OMIT: Any = _Omit()


def frozen_map(d: Mapping[str, Any]) -> Mapping[str, Any]:
    """A read-only view of a copy of ``d`` (a section whose keys are names: nodes, identity)."""
    return MappingProxyType(dict(d))


def _json(v: Any) -> Any:
    if isinstance(v, _Part):
        return v.to_dict()
    if isinstance(v, (tuple, list)):
        return [_json(x) for x in v]
    if isinstance(v, Mapping):
        return {k: _json(x) for k, x in v.items()}
    return v


class _Part:
    """A part of the health record: its JSON object is its fields, in order, minus OMIT."""

    __slots__ = ()
    _FIELDS: ClassVar[tuple[str, ...]] = ()
    __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]  # (@_part: dataclass)

    def to_dict(self) -> dict[str, Any]:
        out = {}
        for k in self._FIELDS:
            v = getattr(self, k)
            if v is not OMIT:
                out[k] = _json(v)
        return out


_P = TypeVar("_P", bound=_Part)


@dataclass_transform(frozen_default=True)  # (type checkers see each part's fields)
def _part(cls: type[_P]) -> type[_P]:
    cls = dataclass(frozen=True, slots=True)(cls)
    cls._FIELDS = tuple(f.name for f in dataclasses.fields(cls))
    return cls


@_part
class BusCounts(_Part):
    """``bus``: frames seen by the tap and what was wrong with them."""

    frames: int
    errors: int
    bus_off: int
    unknown: int
    malformed: int
    duplicate: int
    orphan: int
    remote: int
    callback_errors: int
    last_callback_error: Any = OMIT  # str, only once there was one
    late: Any = OMIT  # int, replay only, once there was one: frames beyond the reorder window


@_part
class SampleCounts(_Part):
    """``samples``: what the assembler emitted."""

    complete: int
    incomplete: int
    lost: int


@_part
class SampleQueue(_Part):
    """``queues.samples``: the reader's item queue."""

    depth: int
    size: int
    max_depth: int
    dropped: int
    blocked: int


@_part
class EventQueue(_Part):
    """``queues.master_events``: the CANopen master's restart requests."""

    depth: int
    dropped: int


@_part
class IdentQueue(_Part):
    """``queues.identification`` (added by the service)."""

    submitted: int
    dropped: int
    errors: int


@_part
class PublisherQueue(_Part):
    """``queues.publisher`` (added by the service)."""

    depth: int
    dropped: int


@_part
class Queues(_Part):
    samples: SampleQueue
    master_events: Any = OMIT  # EventQueue, with a master
    identification: Any = OMIT  # IdentQueue (service)
    publisher: Any = OMIT  # PublisherQueue (service)


@_part
class SyncHealth(_Part):
    """``sync``: SYNC counts and times (docs/telemetry.md §2.5 ``sync.*``)."""

    duplicate: int
    bad_timestamp: int
    late_received: int = 0  # SYNCs later than their counter puts them (frame times)
    late: Any = OMIT  # int, with our own SYNC producer thread
    periods_not_taken: Any = OMIT
    rate_hz: float | None = None
    rate_low: bool = False
    discontinuities: int = 0  # SYNCs whose time went back (two recordings joined, a clock step)
    gaps: int = 0  # SYNCs more than 1 s after the one before (a stalled producer, a paused bus)
    gap_longest_s: float = 0.0


@_part
class Emcy(_Part):
    """One EMCY frame of a node's history."""

    t: float
    code: int
    register: int
    info: str
    length: int


@_part
class NodeHealth(_Part):
    """``nodes.<node>``."""

    state: str
    heartbeat_age: float | None
    emcy: tuple[Emcy, ...]
    required: bool
    boots: int
    losses: int
    emcy_count: int
    identity: Any = OMIT  # Mapping[str, int], once read
    error: Any = OMIT  # str, after a failed verification or restart


@_part
class RecorderQueue(_Part):
    """``recording.queue``: the live recorder's writer queue."""

    depth: int
    size: int
    queued: int
    max_depth: int
    overflow: int


@_part
class RecordingHealth(_Part):
    """``recording``: ``active`` only when nothing records."""

    active: bool
    dir: Any = OMIT
    format: Any = OMIT
    frames: Any = OMIT
    bytes: Any = OMIT
    files: Any = OMIT
    dropped: Any = OMIT
    error: Any = OMIT
    queue: Any = OMIT  # RecorderQueue, live

    @classmethod
    def from_status(cls, st: Mapping[str, Any]) -> RecordingHealth:
        """From :meth:`daq.bus.recorder.Recorder.status`."""
        q = st.get("queue")
        return cls(**{**st, **({"queue": RecorderQueue(**q)} if q is not None else {})})


@_part
class Latency(_Part):
    """``latency_ms`` (added by the service; live only has numbers)."""

    p50: float | None
    p99: float | None
    max: Any = OMIT
    deadline_misses: Any = OMIT


@_part
class Health(_Part):
    """The ``health`` record. The reader fills the first seven fields; the service adds the
    rest (``dataclasses.replace``). ``identification``, ``foxglove`` and ``estimator`` are
    read-only mappings of the parts that report them (their keys: docs/telemetry.md)."""

    t: float | None
    nodes: Mapping[str, NodeHealth]
    bus: BusCounts
    samples: SampleCounts
    queues: Queues
    recording: RecordingHealth
    sync: SyncHealth
    latency_ms: Any = OMIT  # Latency
    identification: Any = OMIT  # Mapping[str, Any]
    foxglove: Any = OMIT  # Mapping[str, Any]
    estimator: Any = OMIT  # Mapping[str, Any]
    warnings: Any = OMIT  # tuple[str, ...]
