"""Plausibility, not silence (issue 46 item 4): a sign-inverted rotor-speed sensor is flagged
implausible (not `rotor_stopped`); an accelerometer geometry is judged by the condition of its
solve; a scenario's base-vibration band above Nyquist is refused like a harmonic."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from helpers_canopen import LockstepRig

from rsra.config.rig import load_config
from rsra.daq.bus.reader import HealthReport
from rsra.daq.runtime.pipeline import IMPLAUSIBLE_OMEGA, EstimatorPipeline


@pytest.fixture(scope="module")
def samples():
    rig = LockstepRig(load_config())
    try:
        items = rig.step(300)
    finally:
        rig.close()
    out = [x for x in items if not isinstance(x, HealthReport)]
    assert all(s.omega is not None and s.omega > 1.0 for s in out)  # the rotor turns
    return out


@pytest.mark.parametrize("kernel", [False, True])
def test_a_sign_inverted_rotor_speed_is_implausible_not_a_stopped_rotor(samples, kernel):
    """Before: Ω = −19.4 rad/s gave `rotor_stopped` on every sample and no count."""
    cfg = load_config()
    p = EstimatorPipeline(cfg, np.asarray(cfg.identification.initial_angles_rad, float),
                          identification=False, hub_kernel=kernel)
    flags = []
    for s in samples:
        for key, payload in p.process(dataclasses.replace(s, omega=-s.omega)).records:
            if key == "hub_loads":
                flags.append(json.loads(json.dumps(payload.get("flags", [])
                                                   if isinstance(payload, dict)
                                                   else payload.to_dict()["flags"])))
    assert len(flags) == len(samples)
    assert all(IMPLAUSIBLE_OMEGA in f for f in flags)
    assert not any("rotor_stopped" in f for f in flags)
    assert p.implausible_omega == len(samples)
    # a stopped rotor's reading noise (just below zero) is still a stopped rotor, not refused
    p2 = EstimatorPipeline(cfg, np.asarray(cfg.identification.initial_angles_rad, float),
                           identification=False, hub_kernel=kernel)
    for s in samples[:20]:
        p2.process(dataclasses.replace(s, omega=-1e-3))
    assert p2.implausible_omega == 0


def _flight_accels():
    import tomllib
    from pathlib import Path

    raw = tomllib.loads((Path(__file__).parents[1] / "config" / "flight-rig.toml").read_text())
    return Path(__file__).parents[1] / "config" / "flight-rig.toml", raw["accelerometers"]


@pytest.mark.parametrize("offset_m", [1e-7, 1e-5])
def test_nearly_collinear_accelerometers_are_refused_with_the_noise_budgets_sigma(
        offset_m, tmp_path, capsys):
    """Before: 1e-7 m from collinear passed the rank test; the noise budget then said σY
    6.7e9 N."""
    from rsra.config.rig import ConfigError
    from rsra.daq.cli import main
    from rsra.daq.rigmodel import load_rig

    path, accs = _flight_accels()
    a, b = (np.asarray(x["position_m"], float) for x in accs[:2])
    accs[2]["position_m"] = ((a + b) / 2 + [offset_m, 0.0, 0.0]).tolist()  # on a-b, nearly
    with pytest.raises(ConfigError) as e:
        load_rig(path, overrides={"accelerometers": accs})
    text = str(e.value)
    assert "condition" in text and "noise budget" in text and "σ" in text
    assert "neglect" in text
    # through the command line: one line, exit 2
    top = tmp_path / "top.toml"
    top.write_text(f'extends = "{path}"\n\n' + "".join(
        '[[accelerometers]]\n' + "".join(f"{k} = {json.dumps(v)}\n" for k, v in x.items())
        + "\n" for x in accs))
    assert main(["noise-budget", "--config", str(top)]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(err) == 1 and "condition" in err[0], err
    # the packaged flight rig itself loads (condition 2)
    load_rig(path)


def test_a_base_vibration_band_above_nyquist_is_refused_like_a_harmonic(tmp_path, capsys):
    """Before: a band up to 150 Hz (Nyquist 100 Hz) aliased silently."""
    from pathlib import Path

    from rsra.daq.cli import main

    flight = (Path(__file__).parents[1] / "config" / "scenarios" / "flight.toml").read_text()
    old = "band_hz = [5.0, 40.0]"
    assert flight.count(old) == 1 and "[base_vibration]\nenabled = true" in flight
    (tmp_path / "alias.toml").write_text(flight.replace(old, "band_hz = [5.0, 150.0]"))
    assert main(["run", "--sim", str(tmp_path / "alias.toml"), "--speed", "max",
                 "--duration", "1", "--record", str(tmp_path / "R")]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(err) == 1, err
    for w in ("alias.toml", "base_vibration.band_hz", "Nyquist frequency 100 Hz", "fix:"):
        assert w in err[0], (w, err[0])
    assert not (tmp_path / "R").exists()
