"""Scenario files of the simulated aircraft (model.md §8): data in config/scenarios/*.toml.

A scenario says what the aircraft does, not how the physics works: the static load schedule,
the rotor harmonics, manoeuvres, the shaker sweep, rotor-speed variation, base vibration, the
true deformation angles, the unmodelled external load, the drive loads, and the random seed.
Every mistake names the key, the value and the fix (the rig loader's ConfigError), e.g.::

    ground-test.toml: angles.mode = 'stepp': unknown value (did you mean "step"?); fix: ...

``load_scenario(name, **variants)`` applies variants to the raw TOML before it is checked, so a
variant is validated exactly like the file (``angles="step"``, ``noise=False``,
``unmodelled=True``, ``base_vibration=False``, any ``[scenario]`` key such as ``seed=7``, or a
dotted key ``**{"angles.step_at_s": [30.0]}``).
"""
from __future__ import annotations

import copy
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rsra.config.readfile import UnreadableFile, read_text
from rsra.config.rig import ConfigError, Section, config_dir
from rsra.config.rigfile import MISSING
from rsra.config.units import LBF_N

AXES = ("X", "Y", "Z", "L", "M", "N")
ANGLE_MODES = ("constant", "step", "linear", "cell_load", "drift")
LOAD_FRAMES = ("body", "shaft")
OPTIONAL_NODE_ROLES = ("rotor_speed", "balance", "drive_load")
SCENARIO_KEYS = ("noise", "seed", "gravity", "quasi_static", "duration_s", "run_s")
# variant shortcuts: name -> (section, key)
VARIANT_SHORTCUTS = {
    "angles": ("angles", "mode"),
    "unmodelled": ("unmodelled", "enabled"),
    "base_vibration": ("base_vibration", "enabled"),
    "turbulence": ("turbulence", "enabled"),
}


@dataclass(frozen=True)
class LoadSchedule:
    """Static hub-load conditions held in turn, with linear ramps between them (cycle time)."""

    frame: str  # "body" or "shaft": the axes the scenario's hub loads are written in
    hold_s: float  # time slot of each condition (its ramp to the next included)
    ramp_s: float
    conditions: np.ndarray  # (n, 6) [X, Y, Z, L, M, N] in N and N·m

    @property
    def cycle_s(self) -> float:
        return self.hold_s * len(self.conditions)


@dataclass(frozen=True)
class Harmonic:
    """A rotor harmonic of the hub loads: amplitudes drawn per component, random phases,
    slowly varying amplitude and phase (model §8)."""

    order: int | str  # multiple of the rotor frequency, or "blades" for N_b/rev
    amplitude_min: np.ndarray  # (6,)
    amplitude_max: np.ndarray  # (6,)
    amplitude_variation: float  # fraction: amplitude * (1 + v * m(t)), |m| <= 1
    phase_variation_rad: float
    variation_period_s: float  # time scale of the slow variation

    def resolve_order(self, blades: int) -> int:
        return blades if self.order == "blades" else int(self.order)


@dataclass(frozen=True)
class Manoeuvre:
    """A smooth (raised-cosine) excursion of the static hub loads, in cycle time."""

    start_s: float
    duration_s: float
    peak: np.ndarray  # (6,)


@dataclass(frozen=True)
class Shaker:
    """The report's shake test: a force swept f_start -> f_stop along each axis in turn at
    each level; amplitude ramps at both ends, then a gap in which the frequency returns."""

    f_start_hz: float
    f_stop_hz: float
    sweep_s: float
    ramp_s: float
    gap_s: float
    axes: tuple[int, ...]  # indices into X, Y, Z, L, M, N
    levels: tuple[float, ...]  # N (or N·m for moment axes)

    @property
    def segment_s(self) -> float:
        return 2 * self.ramp_s + self.sweep_s + self.gap_s

    @property
    def cycle_s(self) -> float:
        return self.segment_s * len(self.axes) * len(self.levels)


@dataclass(frozen=True)
class RotorMotion:
    omega_variation: float  # fraction: Omega = Omega_nominal (1 + v m(t)), |m| <= 1
    omega_period_s: float
    follow_shaker: bool  # Omega = 2 pi f_shaker / N_b (the shaker is the N_b/rev harmonic)
    # a governor-like oscillation on top: + amplitude sin(2 pi f t), fraction of
    # Omega_nominal; 0 = none
    governor_amplitude: float = 0.0
    governor_hz: float = 1.0


@dataclass(frozen=True)
class AngleModel:
    mode: str  # "constant", "step" or "linear"
    base: str | np.ndarray  # "random" (uniform within +-range) or (14,) rad
    range_rad: float
    step_rad: float  # every angle steps by this, random sign, at each step time
    step_at_s: tuple[float, ...]
    linear_rad_per_unit: np.ndarray  # (6,) per N, N·m of static hub load; random sign per angle
    resolution_rad: float  # the linear part is held on this grid (one discretisation per value)
    # "cell_load": every angle moves with the static load of its own cell, by this
    # much per N, random sign per angle: the estimator's ``cell_load_angles`` structure
    cell_gain_rad_per_N: float = 0.0
    # "drift": the angles ``drift_angles`` (indices in model order) move linearly in time,
    # ``drift_rad`` over ``drift_over_s`` (a temperature-like drift)
    drift_rad: float = 0.0
    drift_over_s: float = 240.0
    drift_angles: tuple[int, ...] = ()


@dataclass(frozen=True)
class BaseVibration:
    enabled: bool
    rms_g: float  # RMS of the fuselage-side acceleration per axis
    band_hz: tuple[float, float]


@dataclass(frozen=True)
class Turbulence:
    """Broadband hub loads outside the filter's load model (flight turbulence): band-limited Gaussian noise
    (Butterworth band-pass of white noise) with the given RMS per hub-load component."""

    enabled: bool
    rms: np.ndarray  # (6,) N and N·m
    band_hz: tuple[float, float]


@dataclass(frozen=True)
class UnmodelledLoad:
    """Report Phase I: a roll torque and an x-force proportional to the applied Y and X loads,
    with a phase (180 deg: elastic), in no measured channel."""

    enabled: bool
    roll_Nm_per_N_Y: float
    x_N_per_N_X: float
    phase_rad: float


@dataclass(frozen=True)
class RigErrors:
    """Errors of the rig the estimator's constant model does not know (the competing
    structures): the true hub centre is off the configured one by ``hub_offset_m``; the
    reference balance reads with per-axis scale errors and an alignment error — it reads
    ``H_b`` with ``H_true = [(I + skew φ)(1 + s_F)∘F_b; (I + skew φ)(1 + s_M)∘M_b]``. Zero:
    none (the default, bit-identical to before)."""

    hub_offset_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    balance_scale: np.ndarray = field(default_factory=lambda: np.zeros(6))
    balance_align_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def any(self) -> bool:
        return bool(np.any(self.hub_offset_m) or np.any(self.balance_scale)
                    or np.any(self.balance_align_rad))


@dataclass(frozen=True)
class DriveLoads:
    """Measured external loads D q (model §3): per configured channel, static + one harmonic."""

    static: float
    amplitude: float
    order: int | str


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    source: str
    duration_s: float  # one cycle of the load schedule; it repeats until stopped
    run_s: float  # the default length of a run (simulate() without a length, 'half-way')
    seed: int
    quasi_static: bool  # no inertia: T is the minimum-strain-energy split (paper)
    gravity: bool
    noise: bool
    nodes_present: tuple[str, ...]  # optional node roles the simulated aircraft has on its bus
    loads: LoadSchedule
    harmonics: tuple[Harmonic, ...]
    manoeuvres: tuple[Manoeuvre, ...]
    shaker: Shaker | None
    rotor: RotorMotion
    angles: AngleModel
    base_vibration: BaseVibration
    unmodelled: UnmodelledLoad
    drive: DriveLoads
    rig_overrides: dict = field(default_factory=dict)  # for load_config(overrides=...)
    variants: dict = field(default_factory=dict)
    turbulence: Turbulence = field(default_factory=lambda: Turbulence(
        False, np.zeros(6), (0.5, 40.0)))
    rig_errors: RigErrors = field(default_factory=RigErrors)


def scenario_dir() -> Path:
    return config_dir() / "scenarios"


def list_scenarios() -> list[str]:
    """Names of the packaged scenarios."""
    return sorted(p.stem for p in scenario_dir().glob("*.toml"))


def load_scenario(name_or_path: str | Path, **variants: Any) -> Scenario:
    """Load a packaged scenario by name, or a scenario file by path, with variants applied."""
    p = Path(name_or_path)
    if isinstance(name_or_path, Path) or p.suffix == ".toml" or len(p.parts) > 1:
        path = p
    else:
        path = scenario_dir() / f"{name_or_path}.toml"
        if not path.is_file():
            raise ConfigError("scenario", str(name_or_path), "no such scenario",
                              "use one of " + ", ".join(list_scenarios()) + " or a .toml path")
    try:  # without blocking, within the size limit (config.readfile)
        raw = tomllib.loads(read_text(path))
    except UnreadableFile as e:
        raise ConfigError("scenario", str(path), e.problem,
                          "give the path of a scenario TOML") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("<file>", str(path), f"not valid TOML ({e})",
                          "fix the TOML syntax", path.name) from None
    raw = _apply_variants(raw, variants, path.name)
    try:
        return parse_scenario(raw, source=path.name, variants=variants)
    except ConfigError as e:  # a value a --variant set: that option named, not the file
        option = _variant_of(e.key, variants)
        if option is None:
            raise
        raise ConfigError(e.key, e.value, e.problem, e.fix, option) from None


_VARIANT_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _variant_place(key: str) -> tuple[str, str] | None:
    """(section, key) a variant sets, or None for a name that is not KEY or SECTION.KEY."""
    if "." in key or "__" in key:
        parts = key.replace("__", ".").split(".")
        if len(parts) != 2 or not all(_VARIANT_KEY.fullmatch(x) for x in parts):
            return None
        return parts[0], parts[1]
    if key in SCENARIO_KEYS:
        return "scenario", key
    return VARIANT_SHORTCUTS.get(key)


def _variant_of(error_key: str, variants: dict) -> str | None:
    """``--variant KEY=VALUE`` when the faulty key is one a variant set (or inside it)."""
    for key, value in variants.items():
        place = _variant_place(key)
        if place is None:
            continue
        dotted = ".".join(place) if place[0] != "scenario" else place[1]
        if error_key in (dotted, ".".join(place), place[0]) or error_key.startswith(dotted + ".") \
                or error_key.startswith(dotted + "["):
            return f"--variant {key}={value!r}"
    return None


def _plain(v: Any) -> Any:
    """numpy scalars and arrays to TOML-like Python values."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _apply_variants(raw: dict, variants: dict, source: str) -> dict:
    raw = copy.deepcopy(raw)
    for key, value in variants.items():
        place = _variant_place(key)
        if place is None:
            raise ConfigError(f"--variant {key}", MISSING, "unknown variant (not KEY or "
                              "SECTION.KEY)",
                              "use one of " + ", ".join(SCENARIO_KEYS + tuple(VARIANT_SHORTCUTS))
                              + ' or a dotted key such as "angles.step_at_s"')
        section, sub = place
        table = raw.setdefault(section, {})
        if not isinstance(table, dict):
            raise ConfigError(section, table, "must be a table to take a variant",
                              f"write [{section}] as a table", f"--variant {key}")
        table[sub] = _plain(value)
    return raw


def _six(sec: Section, name: str, default: Any = None) -> np.ndarray:
    args = () if default is None else (default,)
    return sec.vector(name, 6, *args, unit=" [X, Y, Z, L, M, N] in N and N·m")


def _order(sec: Section, name: str, default: Any) -> int | str:
    v = sec.get(name, default)
    if v == "blades" or (isinstance(v, int) and not isinstance(v, bool) and v > 0):
        return v
    raise sec.error(name, v, "must be a positive whole number or \"blades\"",
                    f'write {name} = 1 for 1/rev or {name} = "blades" for N_b/rev')


def _angle_indices(sec: Section, name: str, default: list[int]) -> tuple[int, ...]:
    v = sec.get(name, default)
    if (not isinstance(v, list) or any(isinstance(i, bool) or not isinstance(i, int)
                                       or not 0 <= i < 14 for i in v)
            or len(set(v)) != len(v)):
        raise sec.error(name, v, "must be a list of distinct angle indices 0-13 (model order)",
                        f"e.g. {name} = [0, 6, 11]")
    return tuple(int(i) for i in v)


def _head(top: Section, source: str) -> dict[str, Any]:
    """``[scenario]``: Scenario's first fields."""
    sc = top.table("scenario")
    name = sc.string("name")
    duration = sc.number("duration_s", positive=True)
    head: dict[str, Any] = {
        "name": name, "source": source, "duration_s": duration,
        "run_s": sc.number("run_s", duration, positive=True),
        "seed": sc.number("seed", integer=True, nonneg=True),
        "quasi_static": sc.boolean("quasi_static", False),
    }
    nodes = sc.get("nodes_present", [])
    if not isinstance(nodes, list) or any(n not in OPTIONAL_NODE_ROLES for n in nodes):
        raise sc.error("nodes_present", nodes, "must be a list of optional node roles",
                       "use any of " + ", ".join(f'"{r}"' for r in OPTIONAL_NODE_ROLES))
    head |= {"description": sc.string("description", ""),
             "gravity": sc.boolean("gravity", True), "noise": sc.boolean("noise", True),
             "nodes_present": tuple(nodes)}
    sc.finish()
    return head


def _conditions(ld: Section, source: str) -> np.ndarray:
    conds_raw = ld.get("conditions", [[0.0] * 6])
    if (not isinstance(conds_raw, list) or not conds_raw
            or not all(isinstance(c, list) and len(c) == 6 for c in conds_raw)
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                       for c in conds_raw for x in c)):
        raise ld.error("conditions", conds_raw, "must be a list of [X, Y, Z, L, M, N] rows",
                       "write conditions = [[0.0, 0.0, -80000.0, 0.0, 0.0, 0.0], ...] in N and N·m")
    conditions = np.asarray(conds_raw, dtype=float)
    bad = np.argwhere(~np.isfinite(conditions))
    if bad.size:
        i, j = (int(x) for x in bad[0])
        raise ConfigError(f"{ld.key('conditions')}[{i}][{j}]", float(conditions[i, j]),
                          f"must be finite (the {AXES[j]} load of condition {i + 1})",
                          "replace it with a finite load in N or N·m", source)
    return conditions


def _loads(top: Section, duration: float, source: str) -> LoadSchedule:
    """``[loads]``: the static load conditions, held in turn over one cycle."""
    ld = top.table("loads", {})
    frame = ld.string("frame", "body", LOAD_FRAMES)
    conditions = _conditions(ld, source)
    hold = ld.number("hold_s", duration / len(conditions), positive=True)
    ramp = ld.number("ramp_s", 0.5, nonneg=True)
    several = len(conditions) > 1
    if several and ramp >= hold:
        raise ld.error("ramp_s", ramp, f"must be shorter than hold_s = {hold}",
                       "shorten the ramp or lengthen the hold")
    loads = LoadSchedule(frame=frame, hold_s=hold, ramp_s=ramp, conditions=conditions)
    if several and abs(loads.cycle_s - duration) > 1e-9 * duration:
        raise ld.error("hold_s", hold, f"{len(conditions)} conditions x hold_s = {loads.cycle_s} s "
                       f"is not the cycle duration_s = {duration} s",
                       "make len(conditions) * hold_s equal scenario.duration_s")
    ld.finish()
    return loads


def _harmonic(h: Section) -> Harmonic:
    """One ``[[harmonics]]`` block."""
    amin = h.vector("amplitude_min", 6, unit=" amplitudes in N and N·m")
    amax = h.vector("amplitude_max", 6, amin.tolist(), unit=" amplitudes in N and N·m")
    if np.any(amin < 0) or np.any(amax < amin):
        raise h.error("amplitude_max", amax.tolist(),
                      "needs 0 <= amplitude_min <= amplitude_max",
                      "give non-negative ranges, min first")
    av = h.number("amplitude_variation", 0.0, nonneg=True)
    if av >= 1.0:
        raise h.error("amplitude_variation", av, "must be < 1 (a fraction of the amplitude)",
                      "e.g. amplitude_variation = 0.2")
    harmonic = Harmonic(
        order=_order(h, "order", 1), amplitude_min=amin, amplitude_max=amax,
        amplitude_variation=av,
        phase_variation_rad=math.radians(h.number("phase_variation_deg", 0.0, nonneg=True)),
        variation_period_s=h.number("variation_period_s", 20.0, positive=True),
    )
    h.finish()
    return harmonic


def _manoeuvre(m: Section, duration: float) -> Manoeuvre:
    """One ``[[manoeuvres]]`` block, inside one cycle."""
    mv = Manoeuvre(start_s=m.number("start_s", nonneg=True),
                   duration_s=m.number("duration_s", positive=True), peak=_six(m, "peak"))
    if mv.start_s + mv.duration_s > duration:
        raise m.error("duration_s", mv.duration_s,
                      f"ends at {mv.start_s + mv.duration_s} s, after the cycle ({duration} s)",
                      "keep each manoeuvre inside one cycle")
    m.finish()
    return mv


def _shaker(top: Section, duration: float) -> Shaker | None:
    """``[shaker]``, or None without one."""
    if "shaker" not in top.data:
        return None
    sh = top.table("shaker")
    axes_raw = sh.get("axes", ["X", "Y", "Z"])
    if not isinstance(axes_raw, list) or not axes_raw or any(a not in AXES for a in axes_raw):
        raise sh.error("axes", axes_raw, "must be a list of hub-load axes",
                       "use names from " + ", ".join(AXES))
    lv = sh.vector("levels_lbf", None, positive=True, unit=" in lbf")
    shaker = Shaker(
        f_start_hz=sh.number("f_start_hz", positive=True),
        f_stop_hz=sh.number("f_stop_hz", positive=True),
        sweep_s=sh.number("sweep_s", positive=True),
        ramp_s=sh.number("ramp_s", 0.5, positive=True),
        gap_s=sh.number("gap_s", 1.0, positive=True),
        axes=tuple(AXES.index(a) for a in axes_raw),
        levels=tuple(float(x) * LBF_N for x in lv),
    )
    if shaker.cycle_s > duration + 1e-9:
        raise sh.error("sweep_s", shaker.sweep_s,
                       f"one pass takes {shaker.cycle_s} s, more than duration_s = {duration}",
                       f"set scenario.duration_s >= {shaker.cycle_s}")
    sh.finish()
    return shaker


def _rotor(top: Section, shaker: Shaker | None) -> RotorMotion:
    """``[rotor]``: the rotor speed's variation and governor."""
    ro = top.table("rotor", {})
    rotor = RotorMotion(
        omega_variation=ro.number("omega_variation", 0.0, nonneg=True),
        omega_period_s=ro.number("omega_period_s", 30.0, positive=True),
        follow_shaker=ro.boolean("follow_shaker", False),
        governor_amplitude=ro.number("governor_amplitude", 0.0, nonneg=True),
        governor_hz=ro.number("governor_hz", 1.0, positive=True),
    )
    if rotor.omega_variation + rotor.governor_amplitude >= 0.5:
        raise ro.error("governor_amplitude", rotor.governor_amplitude,
                       "omega_variation + governor_amplitude must be < 0.5 (fractions)",
                       "e.g. governor_amplitude = 0.003")
    if rotor.omega_variation >= 0.5:
        raise ro.error("omega_variation", rotor.omega_variation, "must be < 0.5 (a fraction)",
                       "e.g. omega_variation = 0.02 for +-2 %")
    if rotor.follow_shaker and shaker is None:
        raise ro.error("follow_shaker", True, "there is no [shaker]", "add [shaker] or set false")
    ro.finish()
    return rotor


def _angle_base(an: Section) -> str | np.ndarray:
    """``angles.base``: "random", one angle for all 14, or 14 angles (degrees in the file)."""
    base_raw = an.get("base", 0.0)
    if base_raw == "random":
        return "random"
    if isinstance(base_raw, (int, float)) and not isinstance(base_raw, bool):
        return np.full(14, math.radians(float(base_raw)))
    if isinstance(base_raw, list):
        return np.radians(an.vector("base", 14, unit=" in degrees"))
    raise an.error("base", base_raw, 'must be "random", a number or 14 numbers (degrees)',
                   'write base = "random" or base = 0.0')


def _angles(top: Section, run_s: float) -> AngleModel:
    """``[angles]``: how the simulated load-cell angles move."""
    an = top.table("angles", {})
    mode = an.string("mode", "constant", ANGLE_MODES)
    base = _angle_base(an)
    steps = an.vector("step_at_s", None, [], unit=" in s")
    angles = AngleModel(
        mode=mode, base=base,
        range_rad=math.radians(an.number("range_deg", 4.0, nonneg=True)),
        step_rad=math.radians(an.number("step_deg", 1.0)),
        step_at_s=tuple(float(s) for s in steps),
        linear_rad_per_unit=np.radians(_six(an, "linear_deg_per_unit", [0, 0, 1e-5, 0, 0, 0])),
        resolution_rad=math.radians(an.number("resolution_deg", 0.01, positive=True)),
        cell_gain_rad_per_N=math.radians(an.number("cell_gain_deg_per_kN", 0.0, nonneg=True))
        / 1000.0,
        drift_rad=math.radians(an.number("drift_deg", 0.5)),
        drift_over_s=an.number("drift_over_s", 240.0, positive=True),
        drift_angles=_angle_indices(an, "drift_angles", [0, 6, 11]),
    )
    if mode == "step" and not angles.step_at_s:
        raise an.error("step_at_s", [], 'mode = "step" needs at least one step time',
                       f"e.g. step_at_s = [{run_s / 2}] (half-way through run_s)")
    an.finish()
    return angles


def _check_band(sec: Section, band: np.ndarray, example: str) -> tuple[float, float]:
    """A ``band_hz = [low, high]`` key, low < high."""
    if band[0] >= band[1]:
        raise sec.error("band_hz", band.tolist(), "must be [low, high] with low < high",
                        f"e.g. band_hz = {example}")
    return float(band[0]), float(band[1])


def _base_vibration(top: Section, quasi: bool) -> BaseVibration:
    """``[base_vibration]``: the rig's base shaken (not in the quasi-static limit)."""
    bv = top.table("base_vibration", {})
    band = bv.vector("band_hz", 2, [5.0, 40.0], positive=True, unit=" in Hz")
    base_vibration = BaseVibration(enabled=bv.boolean("enabled", False),
                                   rms_g=bv.number("rms_g", 0.05, nonneg=True),
                                   band_hz=(float(band[0]), float(band[1])))
    _check_band(bv, band, "[5.0, 40.0]")
    if base_vibration.enabled and quasi:
        raise bv.error("enabled", True, "base vibration has no effect in the quasi-static limit",
                       "set enabled = false or scenario.quasi_static = false")
    bv.finish()
    return base_vibration


def _turbulence(top: Section) -> Turbulence:
    """``[turbulence]``: broadband hub loads."""
    tb = top.table("turbulence", {})
    tband = tb.vector("band_hz", 2, [0.5, 40.0], positive=True, unit=" in Hz")
    trms = _six(tb, "rms", [2000.0, 2000.0, 3000.0, 2000.0, 2000.0, 1000.0])
    band = _check_band(tb, tband, "[0.5, 40.0]")
    if np.any(trms < 0):
        raise tb.error("rms", trms.tolist(), "must be >= 0", "give RMS values in N and N·m")
    turbulence = Turbulence(enabled=tb.boolean("enabled", False), rms=trms, band_hz=band)
    tb.finish()
    return turbulence


def _unmodelled(top: Section) -> UnmodelledLoad:
    um = top.table("unmodelled", {})
    unmodelled = UnmodelledLoad(
        enabled=um.boolean("enabled", False),
        roll_Nm_per_N_Y=um.number("roll_Nm_per_N_Y", 0.3),
        x_N_per_N_X=um.number("x_N_per_N_X", 0.1),
        phase_rad=math.radians(um.number("phase_deg", 180.0)),
    )
    um.finish()
    return unmodelled


def _rig_errors(top: Section) -> RigErrors:
    """``[rig_errors]``: where the simulated rig differs from its configuration."""
    re_ = top.table("rig_errors", {})
    rig_errors = RigErrors(
        hub_offset_m=re_.vector("hub_offset_m", 3, [0.0, 0.0, 0.0], unit=" in m"),
        balance_scale=_six(re_, "balance_scale", [0.0] * 6),
        balance_align_rad=np.radians(re_.vector("balance_align_deg", 3, [0.0, 0.0, 0.0],
                                                unit=" in degrees")))
    if np.any(np.abs(rig_errors.balance_scale) >= 0.5):
        raise re_.error("balance_scale", rig_errors.balance_scale.tolist(),
                        "must be fractions within +-0.5", "e.g. balance_scale = [0.01, 0, 0, 0, 0, 0]")
    re_.finish()
    return rig_errors


def _drive(top: Section) -> DriveLoads:
    dr = top.table("drive", {})
    drive = DriveLoads(static=dr.number("static", 0.0),
                       amplitude=dr.number("amplitude", 0.0, nonneg=True),
                       order=_order(dr, "order", 1))
    dr.finish()
    return drive


def _rig_overrides(top: Section) -> dict:
    overrides = top.get("rig_overrides", {})
    if not isinstance(overrides, dict):
        raise top.error("rig_overrides", overrides, "must be a table of rig-config overrides",
                        "write [rig_overrides.identification] initial_angles_deg = 4.0")
    return overrides


def parse_scenario(raw: dict, source: str = "<scenario>", variants: dict | None = None) -> Scenario:
    """A scenario TOML's tables, each checked in turn (the first mistake raised as a
    ConfigError naming its key)."""
    top = Section(raw, "", source)
    head = _head(top, source)
    duration = head["duration_s"]
    loads = _loads(top, duration, source)
    harmonics = tuple(_harmonic(h) for h in top.tables("harmonics", []))
    manoeuvres = tuple(_manoeuvre(m, duration) for m in top.tables("manoeuvres", []))
    shaker = _shaker(top, duration)
    scenario = Scenario(**head, loads=loads, harmonics=harmonics, manoeuvres=manoeuvres,
                        shaker=shaker, rotor=_rotor(top, shaker),
                        angles=_angles(top, head["run_s"]),
                        base_vibration=_base_vibration(top, head["quasi_static"]),
                        turbulence=_turbulence(top), unmodelled=_unmodelled(top),
                        rig_errors=_rig_errors(top), drive=_drive(top),
                        rig_overrides=_rig_overrides(top), variants=dict(variants or {}))
    top.finish()
    return scenario


def check_against_rig(sc: Scenario, sample_rate_hz: float, omega_nominal_rad_s: float,
                      blades: int) -> None:
    """Content the rig's sample rate cannot represent, refused when the scenario meets the rig
    (a simulated harmonic or shaker frequency at or above Nyquist would alias silently): a
    :class:`ConfigError` naming the scenario's line and the fix."""
    nyquist = sample_rate_hz / 2
    omega_max = omega_nominal_rad_s * (1 + sc.rotor.omega_variation)
    for i, h in enumerate(sc.harmonics):
        order = h.resolve_order(blades)
        f = order * omega_max / (2 * math.pi)
        if f >= nyquist:
            raise ConfigError(
                f"harmonics[{i}].order", h.order,
                f"harmonic {order}/rev reaches {f:.3g} Hz at the scenario's highest rotor speed, "
                f"at or above the Nyquist frequency {nyquist:g} Hz of rig.sample_rate_hz = "
                f"{sample_rate_hz:g} (it would alias)",
                f"remove that harmonic or raise rig.sample_rate_hz above {2 * f:.3g}",
                source=sc.source)
    bv = sc.base_vibration
    if bv.enabled and bv.band_hz[1] >= nyquist:
        f = bv.band_hz[1]
        raise ConfigError(
            "base_vibration.band_hz", list(bv.band_hz),
            f"reaches {f:g} Hz, at or above the Nyquist frequency {nyquist:g} Hz of "
            f"rig.sample_rate_hz = {sample_rate_hz:g} (it would alias)",
            f"keep the band below {nyquist:g} Hz or raise rig.sample_rate_hz above {2 * f:g}",
            source=sc.source)
    if sc.shaker is not None:
        f = max(sc.shaker.f_start_hz, sc.shaker.f_stop_hz)
        if f >= nyquist:
            key = "f_stop_hz" if sc.shaker.f_stop_hz >= sc.shaker.f_start_hz else "f_start_hz"
            raise ConfigError(
                f"shaker.{key}", f, f"at or above the Nyquist frequency {nyquist:g} Hz of "
                f"rig.sample_rate_hz = {sample_rate_hz:g} (it would alias)",
                f"sweep below {nyquist:g} Hz or raise rig.sample_rate_hz above {2 * f:g}",
                source=sc.source)
