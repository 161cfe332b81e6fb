"""The runtime's shape (docs/architecture.md "Runtime"): sources instead of mode flags, the
lock-step driver without re-entrant processing, typed records serialised as before."""
from __future__ import annotations

import dataclasses
import pickle
import threading

import numpy as np
import pytest

from rsra.daq.jsonout import dumps
from rsra.daq.runtime.records import ABSENT, AnglesRecord, IdentJob
from rsra.daq.runtime.service import ServiceOptions
from rsra.daq.runtime.sources import (
    BusSource,
    LockstepSource,
    RealtimeSimSource,
    ReplaySource,
    SimOptions,
    make_source,
)

REBOOT = "reboot:cell_C@0.3"
STEPS = 200  # 1 s at 200 samples/s: the reboot, its restart over SDO, the node back


# -- sources ------------------------------------------------------------------------------------
@pytest.mark.parametrize("opts,kind,deterministic,saves", [
    (dict(interface="virtual", channel="x"), BusSource, False, True),
    (dict(sim="ground-test"), RealtimeSimSource, False, True),
    (dict(sim="ground-test", speed=None), LockstepSource, True, True),
    (dict(sim="ground-test", speed=4.0), LockstepSource, True, True),
    (dict(replay=["somewhere"]), ReplaySource, True, False),
])
def test_the_options_choose_a_source_class_and_nothing_else(cfg, opts, kind, deterministic,
                                                            saves):
    src = make_source(cfg, ServiceOptions(**opts))
    assert type(src) is kind
    assert src.deterministic is deterministic and src.saves_posterior is saves
    assert src.reader is None  # nothing opened before the service enters it


# -- the lock-step driver ---------------------------------------------------------------------
def _lockstep_run(cfg, folder):
    """The simulator in lock-step with a node reboot: every frame as the reader recorded it
    (times from the simulator's t0), pump calls made inside a transmission, restarts."""
    from rsra.daq.bus.replay import read_frames

    src = LockstepSource(cfg, SimOptions("ground-test", seed=5, faults=REBOOT), speed=None,
                         record=str(folder))
    nested = []
    sending = threading.local()
    with src:
        reader, handoff = src.reader, src.driver.handoff
        send, pump = handoff.send, reader.pump

        def watched_send(msg, timeout=None):
            sending.on = True
            try:
                send(msg, timeout)
            finally:
                sending.on = False

        def watched_pump():
            nested.append(getattr(sending, "on", False))
            return pump()

        handoff.send = watched_send
        reader.pump = watched_pump
        src.driver.peer = reader
        stop = threading.Event()
        for n, _ in enumerate(src.items(stop)):
            if src.driver.steps >= STEPS:
                break
        restarts = reader.master.reconfigured
        t0 = src.sim.t0
    frames = [(m.arbitration_id, bytes(m.data), round(m.timestamp - t0, 6))
              for m in read_frames([folder])]
    return frames, nested, restarts


def test_lockstep_restarts_a_node_without_reentrant_pumping_and_deterministically(cfg, tmp_path):
    """A node reboots; the reader's master reconfigures it over SDO and starts it while the
    driver holds simulated time. No frame is processed inside a transmission (the old
    hook pumped the simulator and the reader from inside ``send_message``), and two runs
    record the same frames at the same times."""
    a, nested_a, restarts = _lockstep_run(cfg, tmp_path / "a")
    assert restarts == 1
    assert nested_a and not any(nested_a), "a pump ran inside a transmission (re-entrant)"
    sdo = [f for f in a if 0x580 < f[0] <= 0x5FF or 0x600 < f[0] <= 0x67F]
    assert len(sdo) > 10  # the reconfiguration's SDO exchange is in the recording
    b, _, _ = _lockstep_run(cfg, tmp_path / "b")
    assert a == b


# -- typed records ------------------------------------------------------------------------------
def _angles_dict():
    """An angles record's JSON object as the worker makes it today: the estimator's keys in
    its order, then restarted and condition (daq.ident_worker.run_job)."""
    d = {k: i for i, k in enumerate(_estimator_keys())}
    d.update(names=["a", "b"], alpha=[0.1, float("nan")], P=[[1.0, 0.0], [0.0, 2.0]],
             accepted=True, applies_from_seq=17, late=False, reason=None)
    d["restarted"] = False
    d["condition"] = 3.5
    return d


def _estimator_keys():
    """The keys of estimator.posterior.AnglesRecord.to_dict, in order (read from a record)."""
    from rsra.estimator.posterior import AnglesRecord as Numeric

    fields = {f.name: None for f in dataclasses.fields(Numeric)}
    return list(Numeric(**fields).to_dict())


def test_the_angles_record_declares_todays_keys_in_todays_order():
    # the estimator's keys, the service's two, then issue 19's known-load fields: the
    # structure test and the experiment design (docs/telemetry.md §2.4)
    assert AnglesRecord.FIELDS == (*_estimator_keys(), "restarted", "condition", "structure",
                                   "candidates", "next_conditions", "structure_fit",
                                   "explanation", "hint",  # issue 28: why, in words
                                   "drift",  # issue 27: the drift test
                                   # issue 29: what a window with missing samples used
                                   "samples_used", "missing_inputs",
                                   "advice")  # issue 25 item 5: what would determine the rest


def test_the_angles_record_serialises_byte_for_byte_as_the_dict_did():
    d = _angles_dict()
    rec = AnglesRecord.from_dict(d)
    assert dumps(rec.to_dict()) == dumps(d)
    assert list(rec.to_dict()) == list(d)
    # delivery rewrites two fields in place, not at the end
    late = dataclasses.replace(rec, applies_from_seq=20, late=True)
    assert list(late.to_dict()) == list(d)
    assert dumps(late.to_dict()) == dumps({**d, "applies_from_seq": 20, "late": True})
    # an undeclared key (a recording of another version) is carried, after the others
    more = AnglesRecord.from_dict({**d, "future_field": {"x": 1}})
    assert dumps(more.to_dict()) == dumps({**d, "future_field": {"x": 1}})
    # an absent key stays absent (an older recording without "condition")
    less = {k: v for k, v in d.items() if k != "condition"}
    assert dumps(AnglesRecord.from_dict(less).to_dict()) == dumps(less)
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.late = True  # type: ignore[misc]


def test_records_cross_the_process_boundary_intact():
    rec = pickle.loads(pickle.dumps(AnglesRecord.from_dict({"accepted": False, "seq": 3})))
    assert rec.names is ABSENT and rec.to_dict() == {"seq": 3, "accepted": False}
    job = IdentJob(4, "known_loads", "band", 99, np.zeros(2), *[np.arange(3)] * 8)
    back = pickle.loads(pickle.dumps(job))
    assert back.job_id == 4 and np.array_equal(back.seq, job.seq)
    assert list(back.as_mapping())[:4] == ["job_id", "mode", "content", "applies_from_seq"]


def test_paced_lockstep_goes_on_at_its_pace_after_a_hold_up(monkeypatch):
    """`--speed 2` (paced lock-step) on a virtual clock: a consumer that holds the loop for
    0.5 s (a subscriber waited for, the machine stalled) is not caught up in a burst — the
    next samples are paced again at once (a DROP subscriber would lose a burst); a hold-up
    within PACE_SLACK_S is caught up. No wall-clock timing is asserted."""
    import types

    from rsra.config.rig import load_config
    from rsra.daq.runtime import sources
    from rsra.daq.runtime.service import Service

    now = [1000.0]
    sleeps: list[tuple[int, float]] = []
    seen = [0]

    def sleep(s):
        sleeps.append((seen[0], s))
        now[0] += s

    fake = types.SimpleNamespace(monotonic=lambda: now[0], sleep=sleep, time=__import__("time").time)
    monkeypatch.setattr(sources, "time", fake)
    cfg = load_config()
    dt = 1.0 / cfg.sample_rate_hz / 2.0  # paced at 2x real time
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=2.0, duration=0.5, zenoh=False,
                                      identification=False, seed=1))

    def sink(key, payload):
        if key == "hub_loads":
            seen[0] += 1
            if seen[0] == 20:
                now[0] += 0.5  # held up 0.5 s: 100 samples' worth
            elif seen[0] == 60:
                now[0] += 0.5 * sources.PACE_SLACK_S  # a small delay: caught up

    svc.add_sink(sink)
    svc.run()
    after = [s for k, s in sleeps if 20 <= k < 25]
    assert after and all(s == pytest.approx(dt, abs=1e-9) for s in after), sleeps[15:30]
    # within the slack: the next samples run without pausing until the schedule is met
    at = [k for k, s in sleeps if k >= 60]  # 0.025 s = 10 samples at 2.5 ms: caught up
    assert at and at[0] >= 68, [x for x in sleeps if 55 <= x[0] < 75]
