"""The compiled hub path (issue 26, daq/runtime/hubpath.py) against the pure-Python reference:
the same recordings through both give the same published records, bit for bit — the kernel
calls numpy's own BLAS as ndarray.dot does and does the elementwise steps in numpy's order.

Recordings: a ground test, and a faulted flight (lost frames, malformed and unknown frames,
error frames, lost SYNCs, a stuck channel, an over-range cell and a node reboot), both made
by the lock-step simulator. New angles are delivered half-way (the kernel's plan is rebuilt
on the new S). These tests need the kernel: they fail (never skip) when it is not built.

The records carry ``sigma_filter`` (estimator/filter_sigma.py), which the kernel computes for
the report's tuning (a diagonal error gain) and leaves to FilterSigma.update for another
(``tuning = "noise"``): both are compared, and so are FilterSigma's two averages, bit for bit.
Break-checked: the kernel's FilterSigma step skipped, or its slow average not fed, fails the
comparison."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.daq.bus.decoder import DecodeTable
from rsra.daq.bus.reader import HealthReport, OfflineReader
from rsra.daq.bus.replay import read_frames
from rsra.daq.jsonout import dumpb
from rsra.daq.runtime import hubpath
from rsra.daq.runtime.pipeline import EstimatorPipeline
from rsra.daq.runtime.records import AnglesRecord
from rsra.daq.runtime.service import Service, ServiceOptions

DURATION_S = 6.0
FLIGHT_FAULTS = ("drop:cell_B:0.1@0.5-1.5;malformed:cell_D:0.1@1-2;unknown:0.2@1-2;"
                 "errorframe:0.1@1.5-2.5;lostsync:0.05@2-3;stuck:cell_E@3-3.4;"
                 "overrange:cell_A@3.5-3.7;reboot:cell_G@4.5")


def _record(tmp_path_factory, scenario: str, faults: str | None) -> list:
    folder = tmp_path_factory.mktemp(f"rec-{scenario}") / "rec"
    Service(load_config(), ServiceOptions(sim=scenario, seed=26, faults=faults, speed=None,
                                          duration=DURATION_S, zenoh=False,
                                          identification=False, record=str(folder))).run()
    return list(read_frames([str(folder)]))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    return {"ground": _record(tmp_path_factory, "ground-test", None),
            "faulted flight": _record(tmp_path_factory, "flight", FLIGHT_FAULTS)}


def _samples(cfg, frames) -> list:
    r = OfflineReader(cfg)
    out = []
    for m in frames:
        r.feed(m)
        out.extend(x for x in r.poll() if not isinstance(x, HealthReport))
    r.assembler.finish()
    out.extend(x for x in r.poll() if not isinstance(x, HealthReport))
    return out


def _equal_paths(cfg, samples, name: str):
    """Both paths on ``samples``: every record and the states behind them the same bits.
    Returns the kernel's pipeline."""
    ref, p_ref = _run(cfg, samples, kernel=False)
    fast, p_fast = _run(cfg, samples, kernel=True)
    assert p_ref.hub_kernel is None
    assert p_fast.hub_kernel is not None, p_fast.hub_kernel_status
    assert len(ref) == len(fast) and [k for k, _ in ref] == [k for k, _ in fast]
    diff = [i for i, (a, b) in enumerate(zip(ref, fast)) if a != b]
    assert diff == [], f"{len(diff)} records differ, first {ref[diff[0]]} / {fast[diff[0]]}"
    assert sum(k == "angles" for k, _ in fast) == 1  # the delivered angles applied
    # every hub_loads record of a filtered sample has its sigma_filter (not a stale or
    # missing one on either side)
    hub = [payload for k, payload in fast if k == "hub_loads"]
    assert sum(b'"sigma_filter":[' in t for t in hub) > 0.5 * len(hub)
    # the calibration branch (the content filters run in the kernel): the identification
    # window and the filters' states, bit for bit
    b_ref, b_fast = p_ref.calibration.buffer, p_fast.calibration.buffer
    for a in ("T", "z", "H", "seq", "ok", "known", "omega"):
        assert getattr(b_ref, a).tobytes() == getattr(b_fast, a).tobytes(), a
    for mode, cf in p_ref.calibration.content.items():
        assert cf._zi.tobytes() == p_fast.calibration.content[mode]._zi.tobytes(), mode
    # FilterSigma's state: its two averages and its sample count
    fr, ff = p_ref.filter_sigma, p_fast.filter_sigma
    assert fr._Mf.tobytes() == ff._Mf.tobytes() and fr._Ms.tobytes() == ff._Ms.tobytes()
    assert (fr._n, fr._started) == (ff._n, ff._started) and fr._n > fr.settle
    return p_fast


def _run(cfg, samples, kernel: bool):
    """Every record the pipeline gives, as published (JSON text), and the pipeline."""
    p = EstimatorPipeline(cfg, np.asarray(cfg.identification.initial_angles_rad, float),
                          identification=True, hub_kernel=kernel)
    names = list(p.model.geometry.angle_names)
    half = samples[len(samples) // 2].seq
    alpha = (np.asarray(cfg.identification.initial_angles_rad, float) + 1e-3).tolist()
    p.deliver(AnglesRecord(seq=half - 1, accepted=True, names=names, alpha=alpha,
                           applies_from_seq=half))
    text = []
    for s in samples:
        for key, payload in p.process(s).records:
            text.append((key, dumpb(payload if isinstance(payload, dict)
                                    else payload.to_dict())))
    return text, p


def test_the_kernel_is_built_and_uses_numpys_blas():
    kernel, why = hubpath.load()
    assert kernel is not None, f"the compiled hub path is missing: {why}"
    assert why.startswith("compiled (")


@pytest.mark.parametrize("name", ["ground", "faulted flight"])
def test_compiled_and_reference_paths_publish_the_same_records(recordings, name):
    cfg = load_config()
    samples = _samples(cfg, recordings[name])
    p_fast = _equal_paths(cfg, samples, name)
    # the kernel computed the measured samples (the rest took the reference path), their
    # sigma_filter included (the report's tuning: a diagonal error gain)
    n = len(samples)
    share = p_fast.hub_kernel.samples / n
    assert share > (0.95 if name == "ground" else 0.5), share
    assert p_fast.hub_kernel.samples < n if name == "faulted flight" else True
    assert p_fast.hub_kernel.sigma_samples == p_fast.hub_kernel.samples


def test_with_another_error_gain_the_kernel_leaves_sigma_filter_to_python(recordings):
    """``tuning = "noise"`` (a Riccati gain: the error gain is not diagonal, FilterSigma's
    einsum): the kernel does the rest of the first step and FilterSigma.update computes
    sigma_filter on the kernel's innovation — the records are the reference's all the same."""
    cfg = load_config()
    cfg = dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, tuning="noise"))
    p_fast = _equal_paths(cfg, _samples(cfg, recordings["ground"]), "ground")
    assert p_fast.hub_kernel.samples > 0.95 * p_fast.filter_sigma._n
    assert p_fast.hub_kernel.sigma_samples == 0


def _sample_key(s) -> tuple:
    """Every field of a Sample, arrays as their bytes (bit for bit)."""
    def b(x):
        return None if x is None else (np.asarray(x).dtype.str, np.asarray(x).tobytes())
    return (s.seq, s.sync, s.t, b(s.T), s.cell_status, b(s.accel), s.omega, s.azimuth,
            b(s.known_H), b(s.drive), s.missing, s.lost_before, s.flags, s.complete)


@pytest.mark.parametrize("name", ["ground", "faulted flight"])
@pytest.mark.parametrize("calibrated", [False, True])
def test_compiled_and_reference_decode_give_the_same_samples(monkeypatch, recordings, name,
                                                             calibrated):
    """The sample's decode (SampleAssembler._pass_on: the joined TPDOs unpacked and
    calibrated) in the kernel (unpack_cal) and in Python (RSRA_HUB_KERNEL=off): the same
    samples, every field bit for bit — with the packaged calibration (gain 1, offset 0) and
    with a gain and an offset on every value channel. Break-checked: the offset not added
    in the kernel fails it, and so does a status byte read from the next channel."""
    cfg = load_config()
    if calibrated:
        keys = [c.key for c in DecodeTable(cfg).channels if not c.is_status]
        cfg = dataclasses.replace(cfg, calibration={
            k: (1.0 + 0.01 * (i + 1) / 3.0, 0.1 * (i + 1) / 7.0) for i, k in enumerate(keys)})
    fast = _samples(cfg, recordings[name])
    monkeypatch.setenv(hubpath.OFF_ENV, "off")
    r = OfflineReader(cfg)
    assert r.assembler.layout._unpack_cal is None
    ref = _samples(cfg, recordings[name])
    monkeypatch.delenv(hubpath.OFF_ENV)
    assert OfflineReader(cfg).assembler.layout._unpack_cal is not None
    assert len(ref) == len(fast) > 1000
    diff = [i for i, (a, b) in enumerate(zip(ref, fast)) if _sample_key(a) != _sample_key(b)]
    assert diff == [], f"{len(diff)} samples differ, first {ref[diff[0]]} / {fast[diff[0]]}"
    if name == "faulted flight":  # flagged and incomplete samples among them
        assert any(s.flags for s in fast) and not all(s.complete for s in fast)


def test_without_the_kernel_the_reference_runs_and_says_why(monkeypatch, recordings):
    monkeypatch.setattr(hubpath, "_STATE", {})
    monkeypatch.setenv(hubpath.OFF_ENV, "off")
    cfg = load_config()
    p = EstimatorPipeline(cfg, np.asarray(cfg.identification.initial_angles_rad, float))
    assert p.hub_kernel is None and p.hub_kernel_status == f"off ({hubpath.OFF_ENV}=off)"
    for s in _samples(cfg, recordings["ground"])[:50]:
        assert [k for k, _ in p.process(s).records][:1] == ["hub_loads"]


def test_the_kernel_follows_the_estimator_code_it_mirrors():
    """The kernel does what LoadFilter.step/_build, TransientDetector.update,
    HubAngleVariance, ContentFilter._step and FilterSigma.update do; when they change (issue 25: the harmonic states in the rotor's
    frame), the kernel is off until it is brought in line and the tests above pass again
    with the new fingerprint in daq/runtime/hubpath.py."""
    assert hubpath.estimator_fingerprint() == hubpath.MIRRORS_FINGERPRINT


def test_the_fingerprint_reads_the_code_not_its_annotations():
    """Annotating the mirrored estimator steps (mypy) keeps the kernel on; changing what they
    compute turns it off (daq/runtime/hubpath.py, _code_only)."""
    from rsra.daq.runtime.hubpath import _code_only

    plain = "def f(self, x, k=2):\n    y = x * k\n    return y + 1\n"
    typed = ('def f(self, x: np.ndarray, k: int = 2) -> np.ndarray:\n'
             '    """Doc."""\n    z: float\n    y: np.ndarray = x * k  # a comment\n'
             '    return y + 1\n')
    assert _code_only(plain) == _code_only(typed)
    assert _code_only(plain) != _code_only(plain.replace("y + 1", "1 + y"))
    assert _code_only(plain) != _code_only(plain.replace("k=2", "k=3"))
