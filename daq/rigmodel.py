"""The rig description checked against the estimator's balance.

``rsra.config.rig`` parses and types a rig TOML without knowing the balance (the simulator and
the tools import it). What the service must refuse before it starts — a rig whose balance cannot
be solved (S singular at the starting angles, R not invertible, an angular solution the
accelerometers cannot give) or an identification naming parameters the service does not
identify — needs the estimator, so it is checked here, by every command that loads a rig.
"""
from __future__ import annotations

import difflib
from pathlib import Path

import numpy as np

from rsra.config.rig import ConfigError, RigConfig, build_rig_model, load_config, parse_config
from rsra.estimator.balance import accel_solution_matrix
from rsra.estimator.filters import DesignCache
from rsra.estimator.geometry import hub_transfer_matrix, wrench_matrix


def load_rig(path: str | Path | None = None, overrides: dict | None = None) -> RigConfig:
    """Load a rig TOML (default: the packaged rig) and check its balance. Raises ConfigError."""
    return check_model(load_config(path, overrides))


def parse_rig(raw: dict, source: str = "<config>", base_dir: Path | None = None) -> RigConfig:
    """Parse a rig dict and check its balance. Raises ConfigError."""
    return check_model(parse_config(raw, source=source, base_dir=base_dir))


def check_model(cfg: RigConfig) -> RigConfig:
    """Refuse a rig whose balance cannot be solved: singular S at the starting angles, or R."""
    model = build_rig_model(cfg)
    S = wrench_matrix(model.geometry, cfg.identification.initial_angles_rad)
    sv = np.linalg.svd(S, compute_uv=False)
    if sv[-1] < 1e-9 * sv[0]:
        raise ConfigError("cells", "positions/nominal_axis",
                          f"S is singular at the starting angles (condition {sv[0] / max(sv[-1], 1e-300):.3g}): "
                          "the seven cells do not resist all six loads",
                          "check the cell positions and nominal axes", cfg.source)
    names = model.geometry.angle_names
    params = cfg.identification.parameters
    if params != "angles":
        bad = [n for n in params if n not in names]
        if bad:
            near = difflib.get_close_matches(bad[0], names, n=1)
            hint = f' (did you mean "{near[0]}"?)' if near else ""
            raise ConfigError("identification.parameters", bad[0],
                              f"the service identifies load-cell angles only{hint}",
                              "name angles such as delta_A, theta_A, …; calibrate geometry and "
                              "masses off-line with `rsra calibrate --params`", cfg.source)
    R = hub_transfer_matrix(model.geometry)
    if abs(np.linalg.det(R)) < 1e-12:
        raise ConfigError("geometry", "hub_centre_m/shaft_tilt_deg", "R is not invertible",
                          "check the hub centre and shaft tilt", cfg.source)
    try:
        accel_solution_matrix(model.accelerometers)
    except ValueError as e:
        raise ConfigError("inertial.angular", cfg.angular, str(e).split(";")[0],
                          'use angular = "neglect" or add accelerometers', cfg.source) from None
    _check_accel_condition(cfg, model)
    return cfg


#: the least-squares angular solution's condition number beyond which the accelerometer
#: geometry is refused (three triaxes nearly on one line: the rank test passes, the noise does
#: not — 1e-7 m from collinear gave a noise budget of 6.7e9 N)
ACCEL_CONDITION_MAX = 1e4


def _check_accel_condition(cfg: RigConfig, model) -> None:
    """The accelerometer geometry judged by the condition of its solve, not only its rank:
    refused with the noise budget's σ it would give."""
    from rsra.estimator.geometry import skew
    from rsra.estimator.noise_budget import noise_budget

    acc = model.accelerometers
    if acc.angular != "least_squares":
        return
    G = np.vstack([np.hstack([np.eye(3), -skew(r)]) for r in acc.positions])
    cond = float(np.linalg.cond(G))
    if cond <= ACCEL_CONDITION_MAX:
        return
    sigma = noise_budget(model, cfg.identification.initial_angles_rad).total
    axes = ("X", "Y", "Z", "L", "M", "N")
    worst = int(np.argmax(sigma))
    raise ConfigError(
        "accelerometers[].position_m", "three triaxes",
        f"nearly collinear: the angular solution's condition is {cond:.3g} (limit "
        f"{ACCEL_CONDITION_MAX:.0e}), the noise budget's σ{axes[worst]} would be "
        f"{sigma[worst]:.3g} {'N' if worst < 3 else 'N m'}",
        'place three accelerometers well off one line, or use angular = "neglect"', cfg.source)


def design_cache(cfg: RigConfig, *, model=None, low_frequency: bool | None = None,
                 alpha: np.ndarray | None = None, tuning: str | None = None,
                 time_constant_s: float | None = None,
                 omega_min: float | None = None) -> DesignCache:
    """The load filter's design cache (model §6) as the rig config describes it — the one
    way to build it, for the pipeline, the identification worker and the benchmarks. Keyword
    arguments override one setting (the worker's filter-error model has no low-frequency
    states; a benchmark may try another tuning or start from other angles)."""
    f, rotor, idc = cfg.filter, cfg.rotor, cfg.identification
    return DesignCache(
        cfg.rig_model() if model is None else model, harmonics=tuple(f.harmonics),
        dt=1.0 / cfg.sample_rate_hz, tuning=f.tuning if tuning is None else tuning,
        time_constant_s=f.time_constant_s if time_constant_s is None else time_constant_s,
        low_frequency=f.low_frequency_states if low_frequency is None else low_frequency,
        psd=f.process_noise_psd, alpha=idc.initial_angles_rad if alpha is None else alpha,
        moment_floor=idc.moment_floor_Nm, frame=None, redesign_band=rotor.redesign_band,
        cache_resolution=rotor.cache_resolution,
        omega_min=(rotor.omega_min_fraction * rotor.omega_nominal_rad_s
                   if omega_min is None else omega_min),
        omega_default=None if rotor.stopped else rotor.omega_nominal_rad_s)
