"""Live, a sample's first step (up to hub_loads) runs in the bus thread and the rest in the
service thread (docs/performance.md P5b): an identification result is scheduled where the
samples are counted, so the sample it applies from is the one its record says — a replay of
the record reproduces the live hub loads bit for bit, however far the bus thread ran ahead."""
from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.runtime.records import AnglesRecord
from rsra.daq.runtime.sample_loop import SampleLoop
from rsra.daq.runtime.service import Service, ServiceOptions
from rsra.daq.runtime.supervision import Supervision


@pytest.fixture(scope="module")
def cfg():
    return load_config()


@pytest.fixture(scope="module")
def run(cfg):
    from rsra.sim_bus import simulate

    return simulate(cfg, "ground-test", seed=3, n_samples=120)


def _sample(run, i):
    return SimpleNamespace(seq=i, sync=i % 240 + 1, t=float(run.t[i]), T=run.T[i],
                           accel=run.accel[i], flags=[], drive=None, omega=float(run.omega[i]),
                           azimuth=float(run.azimuth[i]), known_H=run.H_balance[i],
                           cell_status=np.zeros(7, int), lost_before=0)


def _result(cfg, planned: int) -> AnglesRecord:
    """An accepted result that moves every angle by 0.3° (its effect on H is plain)."""
    names = list(cfg.rig_model().geometry.angle_names)
    alpha = np.asarray(cfg.identification.initial_angles_rad, float) + np.radians(0.3)
    d = {k: None for k in AnglesRecord.FIELDS}
    d.update(names=names, alpha=alpha.tolist(), P=np.eye(len(names)).tolist(), accepted=True,
             applies_from_seq=planned, reason=None, mode="known_loads", content="static")
    for k in ("restarted", "condition", "structure", "candidates", "next_conditions",
              "structure_fit", "late"):
        d.pop(k, None)
    return AnglesRecord.from_dict(d)


def _hub(records):
    return [p for k, p in records if k == "hub_loads"]


def test_a_late_result_applies_from_the_sample_the_first_step_takes_it_in_at(cfg, run):
    """Samples 0..59 fully processed; the bus thread then runs the first steps of 60, 61 and
    62 before the service thread (at sample 59) hands over a result planned for sample 50.
    It applies from 63 — where the first step takes it in — and its record says so; a replay
    that delivers the record reproduces every hub load."""
    job_id, planned = 0, 50
    live = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    hubs, angles, pend = [], [], []
    for i in range(60):
        hubs += _hub(live.process(_sample(run, i)).records)
    for i in range(60, 63):  # the bus thread ahead of the service thread
        st = live.stages(_sample(run, i))
        hubs += _hub(next(st).records)
        pend.append(st)
    live.outstanding[job_id] = planned
    live.deliver(_result(cfg, planned), arrival_seq=59, job_id=job_id)
    for st in pend:  # the service thread catches up
        next(st)
    for i in range(63, 120):
        out = live.process(_sample(run, i))
        hubs += _hub(out.records)
        angles += [p for k, p in out.records if k == "angles"]
    assert len(angles) == 1 and angles[0].applies_from_seq == 63 and angles[0].late is True

    replay = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    replay.deliver(angles[0])
    again = []
    for i in range(120):
        again += _hub(replay.process(_sample(run, i)).records)
    assert [h["seq"] for h in again] == [h["seq"] for h in hubs] == list(range(120))
    for a, b in zip(hubs, again):
        assert np.array_equal(np.asarray(a["H_static"], float),
                              np.asarray(b["H_static"], float)), a["seq"]
    # and the result did change the hub loads from 63 on (the comparison above can fail)
    plain = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    before = [_hub(plain.process(_sample(run, i)).records)[0] for i in range(64)]
    assert np.array_equal(before[62]["H_static"], hubs[62]["H_static"])
    assert not np.array_equal(before[63]["H_static"], hubs[63]["H_static"])


def test_an_early_result_applies_at_its_planned_sample(cfg, run):
    live = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    live.outstanding[7] = 40
    for i in range(30):
        live.process(_sample(run, i))
    live.deliver(_result(cfg, 40), arrival_seq=29, job_id=7)
    angles = []
    for i in range(30, 50):
        angles += [(i, p) for k, p in live.process(_sample(run, i)).records if k == "angles"]
    assert [(i, a.applies_from_seq, a.late) for i, a in angles] == [(40, 40, False)]


@pytest.mark.timeout(60)
def test_live_hub_loads_come_from_the_bus_thread_and_the_rest_from_the_service_thread(cfg):
    """Real time (bounded, no timing asserted): hub_loads is published by the thread that
    completed the sample, every other record by the service loop's; --duration still gives
    exactly its samples, every one with its channels."""
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=1.0, duration=1.0, zenoh=False,
                                      identification=False, seed=2))
    seen: dict[str, set[str]] = {}
    seqs: dict[str, list[int]] = {"hub_loads": [], "channels": []}

    def sink(key, payload):
        seen.setdefault(key, set()).add(threading.current_thread().name)
        if key in seqs:
            seqs[key].append(payload["seq"])

    svc.add_sink(sink)
    main = threading.current_thread().name
    svc.run()
    assert main not in seen["hub_loads"], seen
    assert seen["channels"] == {main}, seen
    n = round(cfg.sample_rate_hz)
    assert len(seqs["hub_loads"]) == len(seqs["channels"]) == n
    assert seqs["hub_loads"] == seqs["channels"]
    assert seqs["hub_loads"] == list(range(seqs["hub_loads"][0], seqs["hub_loads"][0] + n))


def test_a_slow_first_step_goes_whole_to_the_service_thread_in_order(cfg, run):
    """A rotor speed outside every cached design (a redesign: 10–60 ms) or a result to
    apply: the bus thread passes the whole sample to the service thread instead of stalling
    frame reading, and the samples after it too until that one is done; then it takes first
    steps again. The hub loads are those of one thread doing every sample in order (bit for
    bit). Break-checked: with first_step_is_quick always True, the redesign runs in the bus
    thread (the whole-sample assertions fail)."""
    import queue

    def sample(i):
        s = _sample(run, i)
        if 40 <= i < 60:
            s.omega = s.omega * 1.2  # a speed step beyond the prefilled band
        return s

    ref = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    want = [_hub(ref.process(sample(i)).records)[0] for i in range(100)]

    published = []
    pipeline = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad,
                                 identification=False)
    source = SimpleNamespace(deterministic=False, recorder=None,
                             reader=SimpleNamespace(items=SimpleNamespace(queue=queue.Queue(16))))
    loop = SampleLoop(pipeline, SimpleNamespace(publish=lambda k, p: published.append((k, p))),
                      Supervision(pipeline), source, threading.Event(), 1.0 / cfg.sample_rate_hz)
    kinds = []
    pending = []
    for i in range(100):
        item = loop.first_step(sample(i))  # the bus thread
        kinds.append("whole" if item.rest is None else "step")
        pending.append(item)
        if i % 3 == 2 or i == 99:  # the service thread, behind by a few samples
            for it in pending:
                loop.on_sample(it)
            pending.clear()
    assert kinds[:40] == ["step"] * 40
    assert kinds[40] == "whole"  # the redesign: not in the bus thread
    assert "step" in kinds[41:] and kinds[-1] == "step"  # first steps again once it is done
    got = [p for k, p in published if k == "hub_loads"]
    assert [h["seq"] for h in got] == list(range(100))
    for a, b in zip(got, want):
        assert np.array_equal(np.asarray(a["H"], float), np.asarray(b["H"], float)), a["seq"]


def test_first_step_is_quick_only_without_a_design_or_a_result_to_take_in(cfg, run):
    p = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    s = _sample(run, 0)
    assert p.first_step_is_quick(s)
    s.omega *= 1.2
    assert not p.first_step_is_quick(s)  # no design for it yet
    s.omega = float("nan")
    assert p.first_step_is_quick(s)  # refused: no redesign
    p.outstanding[1] = 5
    p.deliver(_result(cfg, 5), arrival_seq=0, job_id=1)
    assert not p.first_step_is_quick(_sample(run, 1))  # a result to take in


def test_a_pipeline_not_prefilled_gives_the_same_records(cfg, run):
    """A run not paced by the wall clock (a replay) designs the load filter for each rotor
    speed when first met instead of the whole band at start: the same records, bit for
    bit, over a rotor speed that crosses many of the band's design points."""
    from rsra.daq.jsonout import dumps

    w0 = cfg.rotor.omega_nominal_rad_s
    pre = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False)
    lazy = EstimatorPipeline(cfg, cfg.identification.initial_angles_rad, identification=False,
                             prefill=False)
    made = lazy.cache.designs_made
    assert made < pre.cache.designs_made  # (only the nominal speed designed at start)
    for i in range(120):
        s = _sample(run, i)
        s.omega = w0 * (1 + 0.018 * np.sin(i / 10))  # through the band, back and forth
        a, b = pre.process(s).records, lazy.process(s).records
        assert [dumps(x) for _, x in a] == [dumps(x) for _, x in b], i
    assert lazy.cache.designs_made > made + 5  # the speeds met were designed on the way
