"""What a run says of itself: the health record with the service's parts (latency, queues,
identification, Foxglove, the estimator's refusals, start-up warnings) and the end summary
(`rsra run`/`replay` print it; docs/cli.md). Both read a :class:`SampleLoop`'s counts.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from rsra.config.rig import RigConfig
    from rsra.daq.bus.health import Health
    from rsra.daq.runtime.sample_loop import SampleLoop

log = logging.getLogger("rsra.service")

# What the shared loopback bus carries (measured with a do-nothing master and
# responder through python-can-remote on a 2-core machine): quoted, not enforced
SHARED_BUS_CEILING_HZ = 112


def rate_low_reason(interface: str | None, rate: float, target: float) -> str:
    """One line, in words, for a run whose samples come slower than the rig asks: the bus it
    is on and what to do."""
    head = f"samples arrive at {rate:.0f}/s, below the rig's sample_rate_hz {target:g}: "
    if interface == "remote":
        return head + (f"the shared bus (python-can-remote, `rsra bus`) carries about "
                       f"{SHARED_BUS_CEILING_HZ} samples/s of this rig's frames on a 2-core "
                       "machine (docs/performance.md, the shared bus's rate) — set rig.sample_rate_hz to about "
                       "100 in a rig file for both sides, or run on a real bus (socketcan)")
    return head + ("this bus or this machine does not keep up — check the health's bus "
                   "errors and the nodes, lower rig.sample_rate_hz in a rig file, or free "
                   "the cores (docs/user-guide.md, troubleshooting)")


class RateLowNotice:
    """Says :func:`rate_low_reason` once, the first time ``health.sync`` reports the rate
    low (the reader's measure over its last health periods)."""

    def __init__(self) -> None:
        self.said: str | None = None

    def check(self, sync: Any, interface: str | None, target: float) -> str | None:
        if self.said is not None or not getattr(sync, "rate_low", False):
            return None
        rate = getattr(sync, "rate_hz", None)
        if rate is None:
            return None
        self.said = rate_low_reason(interface, rate, target)
        log.warning("%s", self.said)
        return self.said


def latency_percentiles(latencies: Iterable[float]) -> dict[str, float] | None:
    """{"p50", "p99", "max"} in ms of latencies in seconds; None when there are none."""
    a = np.fromiter(latencies, float) * 1e3
    if not a.size:
        return None
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


class HealthReporter:
    """The reader's health records (daq.bus.health) with the service's parts, replaced into
    them; published as they are (serialised once, ``Health.to_dict``). A recording that
    stops is logged once, when its error first appears."""

    def __init__(self, loop: SampleLoop, warnings: list[str]):
        self._loop = loop
        self._warnings = warnings  # (the service's list: start-up problems it went on with)
        #: the latest health record published
        self.last: Health | None = None
        #: a run that cannot keep up is told why, once
        self._rate_low = RateLowNotice()

    def __call__(self, item: Any) -> None:
        from rsra.daq.bus.health import Latency, frozen_map

        loop = self._loop
        h = item.health
        lat = latency_percentiles(loop.latencies)
        latency = (Latency(deadline_misses=loop.deadline_misses, **lat) if lat is not None
                   else Latency(p50=None, p99=None))
        queues, more = _queues_and_parts(loop, h.queues)
        more["estimator"] = frozen_map(_estimator_health(loop.pipeline))
        if self._warnings:
            more["warnings"] = tuple(self._warnings)
        h = dataclasses.replace(h, latency_ms=latency, queues=queues, **more)
        prev = self.last.recording.error if self.last is not None else None
        err = h.recording.error
        if err and err != prev:
            log.error("recording stopped: %s", err)
        if loop.live:  # (a replay's rate is the recording's: said by its health alone)
            self._rate_low.check(h.sync, getattr(loop.source, "interface", None),
                                 loop.pipeline.cfg.sample_rate_hz)
        self.last = h
        loop.outputs.publish("health", h)


def _queues_and_parts(loop: SampleLoop, queues: Any) -> tuple[Any, dict[str, Any]]:
    """The reader's queues with the identification worker's and the low-rate publisher's
    put in, and the health of the worker and the Foxglove relay (when running)."""
    from rsra.daq.bus.health import IdentQueue, PublisherQueue, frozen_map

    more: dict[str, Any] = {}
    worker = loop.supervision.worker
    if worker is not None:
        queues = dataclasses.replace(queues, identification=IdentQueue(
            submitted=worker.submitted, dropped=worker.dropped,
            errors=loop.supervision.errors))
        more["identification"] = frozen_map(worker.health())
    outputs = loop.outputs
    if outputs.low_rate is not None:
        queues = dataclasses.replace(queues, publisher=PublisherQueue(
            depth=outputs.low_rate.queue.qsize(), dropped=outputs.low_rate.dropped))
    if outputs.foxglove is not None:
        more["foxglove"] = frozen_map(outputs.foxglove.health())
    return queues, more


def _estimator_health(p: Any) -> dict[str, Any]:
    """Readings the estimator refused (bad input, counted) and how it runs."""
    est = {"implausible_omega": p.implausible_omega,
           "design_errors": p.design_errors,
           "inertial": p.cfg.angular,
           "harmonic_phase": p.cfg.rotor.harmonic_phase,
           "hub_kernel": p.hub_kernel_status,
           "hub_kernel_samples": 0 if p.hub_kernel is None else p.hub_kernel.samples}
    if p.azimuth_mode:
        est["azimuth_missing"] = p.azimuth_missing
        est["azimuth_refused"] = p.azimuth.refused
    if p.stuck is not None:
        est.update(p.stuck.health())
    return est


def run_summary(loop: SampleLoop, reader: Any, warnings: list[str],
                schedule: dict | None, cfg: RigConfig) -> dict:
    """The end summary of a run: the loop's counts, the reader's, what the estimator
    refused, the latency, the last angles and (replay) where they came from."""
    rej = dict(loop.angles.rejected)
    out: dict[str, Any] = {
        "samples": loop.samples, "lost": loop.lost,
        "duration_s": (None if loop.first_t is None or loop.last_t is None
                       else loop.last_t - loop.first_t),
        "identification_runs": loop.angles.runs,
        "accepted": loop.angles.runs - sum(rej.values()),
        "rejected": rej, "published": dict(loop.outputs.counts),
        "deadline_misses": loop.deadline_misses}
    if reader is not None:  # the reader's counts, as a replay of the run reports them
        out.update(_reader_counts(reader))
    if warnings:
        out["warnings"] = list(warnings)
    p = loop.pipeline
    out.update(_estimator_refusals(p))
    lat = latency_percentiles(loop.latencies)
    if lat is not None:
        out["latency_ms"] = lat
    if loop.angles.log:
        out["angles"] = _last_angles(loop.angles.log[-1])
    out["alpha_applied"] = p.alpha.tolist()
    if schedule is not None:
        out["angles_schedule"] = schedule_summary(schedule, loop.last_seq, cfg)
    return out


def _reader_counts(reader: Any) -> dict[str, Any]:
    """The reader's complete and incomplete samples, and the SYNC gaps when there were any."""
    h = reader.health()
    out: dict[str, Any] = {"samples_complete": h.samples.complete,
                           "samples_incomplete": h.samples.incomplete}
    if h.sync.gaps:
        out["sync_gaps"] = {"count": h.sync.gaps, "longest_s": h.sync.gap_longest_s}
    return out


def _estimator_refusals(p: Any) -> dict[str, Any]:
    """What the estimator refused: implausible rotor speeds and design errors, stuck
    episodes (each only when it happened)."""
    out: dict[str, Any] = {}
    if p.implausible_omega or p.design_errors:
        out["implausible_omega"] = p.implausible_omega
        out["design_errors"] = p.design_errors
    st = p.stuck.health() if p.stuck is not None else None
    if st is not None and st["stuck_episodes"]:
        out["stuck"] = {"episodes": st["stuck_episodes"], "samples": st["stuck_samples"]}
    return out


def _last_angles(last: Any) -> dict[str, Any]:
    """The last angles record's names, angles and σ (√P_ii)."""
    return {"names": last.get("names"), "alpha": last.get("alpha"),
            "sigma": [math.sqrt(max(last.P[i][i], 0.0))
                      for i in range(len(last.get("names") or []))]
            if last.get("P") else None}


def schedule_summary(schedule: dict, last_seq: int | None, cfg: RigConfig) -> dict:
    """Replay: where the angles came from. A recorded schedule is partial when the
    recording runs on for more than a period, the apply delay and a second past its last
    record (a live run publishes one record per period)."""
    sch = dict(schedule)
    if sch["source"] != "recorded" or last_seq is None:
        return sch
    idc = cfg.identification
    fs = cfg.sample_rate_hz
    last = sch["last_applies_from_seq"]
    sch["last_seq"] = last_seq
    if last is not None:
        sch["uncovered_s"] = max(0, last_seq - last) / fs
        sch["partial"] = last_seq - last > (idc.period_s + idc.apply_delay_s + 1.0) * fs
    return sch
