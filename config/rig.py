"""The one typed loader of the rig TOML.

Every error names the key, the bad value and the fix, e.g.::

    rig.toml: mass.effective_mass_kg[1] = -5.0: must be > 0; fix: give the effective mass in kg

The loader builds the numerical core's parameter objects (estimator.params) from it.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tomllib
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel

from rsra.config.readfile import UnreadableFile, read_text
from rsra.config.units import G0 as G0  # (re-exported: the loader's users import it from here)
from rsra.config.rigfile import (  # noqa: F401  (names the loader's users import from here)
    CONTENTS,
    COB_MAX_11BIT,
    DESIGN_BAND,
    MAX_SAMPLE_RATE_HZ,
    MISSING,
    POSITION_MAX_M,
    ROLES,
    STRUCTURE_PARAMETERS,
    AccelerometerTable,
    AdviceTable,
    RigFile,
    StructureTable,
    predefined_cob_ids,
    validate,
    zenoh_endpoint_problem,
)
from rsra.estimator.params import (
    Accelerometers,
    ExternalLoads,
    Geometry,
    MassProperties,
    RigModel,
)

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration mistake: which key, what value, what to do."""

    def __init__(self, key: str, value: Any, problem: str, fix: str, source: str = ""):
        self.key, self.value, self.problem, self.fix, self.source = key, value, problem, fix, source
        where = f"{source}: " if source else ""
        shown = "" if value is MISSING else f" = {shown_value(value)}"
        super().__init__(f"{where}{key}{shown}: {problem}; fix: {fix}")


_MISSING = object()
SHOWN_MAX = 120  # characters of a value an error line echoes


def shown_value(value: Any) -> str:
    """A value as an error line shows it: its repr, cut to :data:`SHOWN_MAX` characters (a
    2-million-element array is named by its length, not echoed)."""
    text = repr(value)
    if len(text) <= SHOWN_MAX:
        return text
    size = f" ({len(value)} elements)" if isinstance(value, (list, tuple, dict)) else ""
    return f"{text[:SHOWN_MAX]}…{size}"


class Section:
    """Typed access to one TOML table, tracking the dotted key path and unknown keys (the
    simulator's scenario files, sim_bus.scenarios; the rig TOML is validated by pydantic:
    config.rigfile)."""

    def __init__(self, data: dict[str, Any], path: str, source: str):
        if not isinstance(data, dict):
            raise ConfigError(path, data, "must be a table", f"write [{path}] as a TOML table", source)
        self.data, self.path, self.source = data, path, source
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, value: Any, problem: str, fix: str) -> ConfigError:
        return ConfigError(self.key(name), value, problem, fix, self.source)

    def get(self, name: str, default: Any = _MISSING) -> Any:
        self.used.add(name)
        if name in self.data:
            return self.data[name]
        if default is _MISSING:
            raise ConfigError(self.key(name), None, "is missing", f"add {name} = … to [{self.path}]",
                              self.source)
        return default

    def number(self, name: str, default: Any = _MISSING, *, positive: bool = False,
               nonneg: bool = False, integer: bool = False, fix: str = "") -> float:
        v = self.get(name, default)
        if not _is_number(v, integer):
            kind = "a whole number" if integer else "a finite number"
            raise self.error(name, v, f"must be {kind}", fix or f"set {name} to {kind}")
        if positive and v <= 0:
            raise self.error(name, v, "must be > 0", fix or f"set {name} to a positive value")
        if nonneg and v < 0:
            raise self.error(name, v, "must be >= 0", fix or f"set {name} to zero or more")
        return int(v) if integer else float(v)

    def string(self, name: str, default: Any = _MISSING, choices: tuple[str, ...] | None = None) -> str:
        v = self.get(name, default)
        if not isinstance(v, str):
            raise self.error(name, v, "must be a string", f'write {name} = "…"')
        if choices is not None and v not in choices:
            near = difflib.get_close_matches(v, choices, n=1)
            hint = f' (did you mean "{near[0]}"?)' if near else ""
            raise self.error(name, v, f"unknown value{hint}",
                             "use one of " + ", ".join(f'"{c}"' for c in choices))
        return v

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        v = self.get(name, default)
        if not isinstance(v, bool):
            raise self.error(name, v, "must be true or false", f"write {name} = true or false")
        return v

    def vector(self, name: str, length: int | None = None, default: Any = _MISSING, *,
               positive: bool = False, unit: str = "", max_abs: float | None = None) -> np.ndarray:
        v = self.get(name, default)
        if not isinstance(v, list) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v
        ):
            raise self.error(name, v, "must be a list of numbers", f"write {name} = [x, y, …]{unit}")
        if length is not None and len(v) != length:
            raise self.error(name, v, f"must have {length} values, has {len(v)}",
                             f"give {length} numbers{unit}")
        a = np.asarray(v, dtype=float)
        for i, x in enumerate(a):
            problem = _element_problem(x, positive, unit, max_abs)
            if problem is not None:
                raise ConfigError(f"{self.key(name)}[{i}]", *problem, self.source)
        return a

    def table(self, name: str, default: Any = _MISSING) -> "Section":
        return Section(self.get(name, default), self.key(name), self.source)

    def tables(self, name: str, default: Any = _MISSING) -> list["Section"]:
        v = self.get(name, default)
        if not isinstance(v, list):
            raise self.error(name, v, "must be an array of tables", f"write [[{self.key(name)}]] blocks")
        return [Section(t, f"{self.key(name)}[{i}]", self.source) for i, t in enumerate(v)]

    def finish(self) -> None:
        """Refuse keys nobody read: almost always a typo."""
        for k in self.data:
            if k not in self.used:
                near = difflib.get_close_matches(k, sorted(self.used), n=1)
                hint = f'rename it to "{near[0]}"' if near else "remove it"
                raise ConfigError(self.key(k), self.data[k], "unknown key", hint, self.source)


def _is_number(v: Any, integer: bool) -> bool:
    """A finite number (a whole one if ``integer``), not a bool."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool)
    if integer:
        ok = ok and float(v).is_integer()
    return ok and math.isfinite(float(v))


def _element_problem(x: Any, positive: bool, unit: str, max_abs: float | None
                     ) -> tuple[Any, str, str] | None:
    """What is wrong with one number of a vector (the value shown, problem, fix), or None."""
    if not math.isfinite(x):
        return x, "must be finite", "replace it with a finite number"
    if positive and x <= 0:
        return float(x), "must be > 0", f"give a positive value{unit}"
    if max_abs is not None and abs(x) > max_abs:
        u = unit.replace(" in ", " ").rstrip()
        return (float(x), f"is more than {max_abs:g}{u} from the reference point",
                f"give the position{unit}, within +-{max_abs:g}")
    return None


@dataclass(frozen=True)
class CellConfig:
    name: str
    node: str
    position_m: np.ndarray
    nominal_axis: np.ndarray
    full_scale_N: float
    accuracy_fs: float
    stiffness_N_per_m: float

    @property
    def sigma_N(self) -> float:
        return self.full_scale_N * self.accuracy_fs


@dataclass(frozen=True)
class AccelerometerConfig:
    name: str
    node: str
    position_m: np.ndarray
    full_scale_g: float
    accuracy_fs: float

    @property
    def sigma_m_s2(self) -> float:
        return self.full_scale_g * G0 * self.accuracy_fs


@dataclass(frozen=True)
class NodeConfig:
    name: str
    role: str
    node_id: int
    eds: Path
    required: bool


@dataclass(frozen=True)
class RotorConfig:
    blades: int
    omega_nominal_rad_s: float
    node: str
    omega_min_fraction: float
    redesign_band: float
    cache_resolution: float
    stopped: bool
    # "design" (the harmonic states advance by the design's Ω) or "azimuth" (by the measured
    # azimuth of the rotor-speed node; gain held ±5 %)
    harmonic_phase: str


@dataclass(frozen=True)
class BalanceConfig:
    node: str
    full_scale_force_N: float
    full_scale_moment_Nm: float
    accuracy_fs: float

    @property
    def sigma(self) -> np.ndarray:
        f = self.full_scale_force_N * self.accuracy_fs
        m = self.full_scale_moment_Nm * self.accuracy_fs
        return np.array([f, f, f, m, m, m])


@dataclass(frozen=True)
class ExternalLoadConfig:
    name: str
    node: str
    wrench_per_unit: np.ndarray
    sigma: float


@dataclass(frozen=True)
class FilterConfig:
    harmonics: tuple[int, ...]
    low_frequency_states: bool
    tuning: str
    time_constant_s: float
    process_noise_psd: str | np.ndarray
    invalid_after_s: float


@dataclass(frozen=True)
class IdentificationConfig:
    parameters: str | tuple[str, ...]
    initial_angles_rad: np.ndarray
    prior_sigma_rad: float
    period_s: float
    window_s: float
    drift_rate_rad2_s: float
    min_information: float
    sigma_max_rad: float
    apply_delay_s: float
    content_known_loads: str
    content_filter_error: str
    moment_floor_Nm: float
    max_iterations: int
    reset_after: int
    stale_fraction: float
    settle_time_constants: float
    gap_s: float
    state_file: str
    angle_limit_rad: float
    # filter-error runs: the update rule ("consider": only along the window's determined
    # directions; "bayes": its information in full) and the windows' systematic error σ_b, a
    # floor on the fused σ along each window's determined directions
    filter_error_update: str
    filter_error_floor_rad: float
    # a bound (1 σ, rad per N / N·m) on the angles' dependence on the static hub load away
    # from the reference (trim) load: filter-error windows away from trim carry it
    angle_load_sensitivity_rad_per_unit: tuple[float, ...]
    # filter-error windows: at most this fraction missing in short runs
    filter_error_scattered_fraction: float
    # known loads: a bound (1 σ, rad/s) on each angle's drift rate, solved for beside the
    # angles (estimator.load_spread); 0: constant angles up to the random walk
    angle_drift_rate_rad_per_s: float
    # known loads: a run whose Gaussian summary misses the curvature of the likelihood's
    # valley by more than this (χ² units) is held (estimator.curvature); inf: off
    nonlinearity_check: bool  # docs/configuration.md
    nonlinearity_limit: float
    # [identification.structure] (`rsra calibrate` writes it): the structure the hub loads
    # use from the start, as estimator.structure.fit_payload (SI); None: constant
    structure_fit: dict[str, Any] | None
    # [identification.advice]: the additions a filter-error window's advice weighs; None: no
    # advice
    advice: "AdviceConfig | None"


@dataclass(frozen=True)
class AdviceConfig:
    band_hz: tuple[float, float]
    manoeuvre_rms: tuple[float, ...]  # (6,) N, N·m on X Y Z L M N; 0: not a candidate
    accelerometers: tuple[tuple[str, np.ndarray, float], ...]  # (name, position m, σ m/s²)


@dataclass(frozen=True)
class SyncConfig:
    producer: str
    cob_id: int
    counter_overflow: int


@dataclass(frozen=True)
class HeartbeatConfig:
    producer_ms: int
    timeout_factor: float
    boot_timeout_s: float


@dataclass(frozen=True)
class TelemetryConfig:
    prefix: str
    mode: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    multicast_scouting: bool
    innovations_hz: float
    zenoh_config: str


@dataclass(frozen=True)
class RecordingConfig:
    dir: str
    format: str
    rotate_mb: float
    cap_mb: float
    flush_s: float


@dataclass(frozen=True)
class SimulatorConfig:
    damping_ratio: float
    damping_reference_hz: float
    substeps: int


@dataclass(frozen=True)
class StuckConfig:
    """Stuck-channel detection (daq/runtime/stuck.py): a run of exactly equal readings."""

    enabled: bool
    false_alarm_per_hour: float  # per channel, honest channel at rest
    max_delay_s: float  # a channel needing a longer run to meet the rate is untested


@dataclass(frozen=True)
class LimitsConfig:
    """The rig's hub-load limits per axis (N, N·m; 0: none), for `rsra survey`'s peaks."""

    X: float
    Y: float
    Z: float
    L: float
    M: float
    N: float

    def per_axis(self) -> tuple[float, ...]:
        """X … N in SI, NaN where the rig states none."""
        return tuple(v if v > 0 else math.nan for v in
                     (self.X, self.Y, self.Z, self.L, self.M, self.N))


@dataclass(frozen=True)
class RigConfig:
    source: str
    rig_name: str
    sample_rate_hz: float
    hub_centre_m: np.ndarray
    shaft_tilt_rad: float
    hub_frame: str
    effective_mass_kg: np.ndarray
    inertia_kg_m2: np.ndarray
    cells: tuple[CellConfig, ...]
    angular: str
    accelerometers: tuple[AccelerometerConfig, ...]
    rotor: RotorConfig
    balance: BalanceConfig
    external_loads: tuple[ExternalLoadConfig, ...]
    filter: FilterConfig
    identification: IdentificationConfig
    sync: SyncConfig
    heartbeat: HeartbeatConfig
    nodes: tuple[NodeConfig, ...]
    calibration: dict[str, tuple[float, float]]
    telemetry: TelemetryConfig
    recording: RecordingConfig
    simulator: SimulatorConfig
    stuck: StuckConfig
    limits: LimitsConfig
    raw: dict[str, Any] = field(repr=False, default_factory=dict)
    #: dotted key -> the file its value came from ("default": the packaged rig); empty when
    #: the rig was not loaded from layered files (config.rig.merge_layers)
    origins: dict[str, str] = field(repr=False, default_factory=dict, compare=False)

    @property
    def sample_period_s(self) -> float:
        return 1.0 / self.sample_rate_hz

    def node(self, name: str) -> NodeConfig | None:
        for n in self.nodes:
            if n.name == name:
                return n
        return None

    def rig_model(self) -> RigModel:
        return build_rig_model(self)

    def effective(self) -> dict[str, Any]:
        """The configuration as loaded, with secrets (Zenoh config paths) removed."""
        d = {k: v for k, v in self.raw.items()}
        tel = dict(d.get("telemetry", {}))
        if tel.get("zenoh_config"):
            tel["zenoh_config"] = "<removed>"
        d["telemetry"] = tel
        return d


def default_config_path() -> Path:
    return Path(str(resources.files("rsra.config").joinpath("rig.toml")))


def config_dir() -> Path:
    return Path(str(resources.files("rsra.config")))


def packaged_rigs() -> dict[str, Path]:
    """The rigs that come with rsra, by name: ``default`` (``rig.toml``) and ``<name>`` for
    every ``<name>-rig.toml`` beside it (``flight``: the flight rig)."""
    out = {DEFAULT_SOURCE: default_config_path()}
    for f in sorted(config_dir().glob("*-rig.toml")):
        out[f.name[:-len("-rig.toml")]] = f
    return out


def rig_path(given: str | Path) -> Path:
    """Where ``--config`` (or ``extends``) points: an existing path always wins; a bare name
    (no ``/``, no ``.toml``) names a packaged rig (:func:`packaged_rigs`); anything else is
    the path as given (not there: loading it says so)."""
    p = Path(given)
    text = str(given)
    if p.exists() or "/" in text or text.endswith(".toml"):
        return p
    return packaged_rigs().get(text, p)


def build_rig_model(cfg: RigConfig) -> RigModel:
    geometry = Geometry(
        cell_names=tuple(c.name for c in cfg.cells),
        cell_positions=np.array([c.position_m for c in cfg.cells]),
        cell_axes=np.array([c.nominal_axis for c in cfg.cells]),
        hub_position=np.asarray(cfg.hub_centre_m, float),
        shaft_tilt_rad=cfg.shaft_tilt_rad,
        hub_frame=cfg.hub_frame,
    )
    acc = Accelerometers(
        positions=np.array([a.position_m for a in cfg.accelerometers]),
        sigma=np.array([a.sigma_m_s2 for a in cfg.accelerometers]),
        angular=cfg.angular,
    )
    ext = ExternalLoads(
        names=tuple(e.name for e in cfg.external_loads),
        wrenches=(np.array([e.wrench_per_unit for e in cfg.external_loads]).T
                  if cfg.external_loads else np.zeros((6, 0))),
        sigma=np.array([e.sigma for e in cfg.external_loads]),
    )
    return RigModel(
        geometry=geometry,
        mass=MassProperties(mass=cfg.effective_mass_kg, inertia=cfg.inertia_kg_m2),
        accelerometers=acc,
        cell_sigma=np.array([c.sigma_N for c in cfg.cells]),
        balance_sigma=cfg.balance.sigma,
        external=ext,
    )


ConfigPaths = str | Path | Sequence[str | Path] | None
DEFAULT_SOURCE = "default"  # the origin of a value the packaged rig gives


EXTENDS_MAX = 32  # rig TOMLs in one ``extends`` chain (a longer one is a mistake, not a rig)


def _read_toml(p: Path, key: str = "--config", source: str = "") -> dict[str, Any]:
    """A rig TOML read without blocking and within the size limit (config.readfile);
    ``key`` and ``source``: what named it (``--config``, or ``extends`` in a file)."""
    try:
        text = read_text(p)
    except UnreadableFile as e:
        names = ", ".join(packaged_rigs())
        bare = "/" not in str(p) and not str(p).endswith(".toml")
        fix = ((f"give the path of a rig TOML or a packaged rig's name ({names}; `rsra "
                "config list`)" if bare else
                "give the path of a rig TOML, or omit --config for the default rig")
               if key == "--config" else
               f"give the path of the rig TOML this one extends, or a packaged rig's name "
               f"({names})")
        raise ConfigError(key, str(p), e.problem, fix, source) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("<file>", str(p), f"not valid TOML ({e})", "fix the TOML syntax") from None


def _layer_files(p: Path) -> list[tuple[Path, dict[str, Any]]]:
    """The layers a rig TOML stands for, base first: its ``extends`` chain (a rig TOML it
    names, relative to it; ``"default"`` or none: the packaged rig, not listed), then
    itself (without ``extends``). At most :data:`EXTENDS_MAX` files in a chain."""
    chain: list[tuple[Path, dict[str, Any]]] = []
    seen: set[Path] = set()
    key, source = "--config", ""
    p = rig_path(p)
    while True:
        rp = p.resolve()
        if rp in seen:
            raise ConfigError("extends", str(p), "the files extend each other in a circle",
                              "make one of them extend \"default\"", source)
        if len(chain) >= EXTENDS_MAX:
            raise ConfigError("extends", str(p), f"the chain of bases is longer than "
                              f"{EXTENDS_MAX} files", "merge some of the bases into one file",
                              source)
        seen.add(rp)
        raw = _read_toml(p, key, source)
        base = raw.pop("extends", DEFAULT_SOURCE)
        if not isinstance(base, str) or not base:
            raise ConfigError("extends", base, "must be a path or \"default\"",
                              "name the rig TOML this one extends", p.name)
        chain.append((p, raw))
        if base == DEFAULT_SOURCE:
            return chain[::-1]
        key, source = "extends", str(p)
        here = Path(base) if Path(base).is_absolute() else p.parent / base
        p = here if here.exists() else rig_path(base)  # a file beside it, else a rig's name


def layer_paths(paths: ConfigPaths) -> list[Path]:
    """Every rig TOML a command reads for ``--config`` (the packaged rig, the files and the
    bases they ``extends``) and every EDS file they name (beside the layer or in the packaged
    folder): what a command reads besides its recordings. Files that cannot be read are left
    out (loading the rig says why)."""
    dflt = default_config_path()
    out: list[Path] = []
    layers: list[tuple[Path, dict[str, Any]]] = []
    try:
        layers.append((dflt, _read_toml(dflt)))
    except ConfigError:
        pass
    for f in config_files(paths):
        try:
            layers += _layer_files(Path(f))
        except ConfigError:
            continue
    for lp, layer in layers:
        out.append(lp)
        for eds in map(Path, _eds_named(layer)):
            out += [eds] if eds.is_absolute() else [lp.parent / eds, dflt.parent / eds]
    return list(dict.fromkeys(out))


def config_files(paths: ConfigPaths) -> list[str | Path]:
    """``--config`` as a list of files (one path, several, or none)."""
    return [paths] if isinstance(paths, (str, Path)) else list(paths or ())


def _eds_named(layer: dict[str, Any]) -> list[str]:
    """The EDS paths a layer's ``[[nodes]]`` blocks give (as written)."""
    nodes = layer.get("nodes")
    return [n["eds"] for n in (nodes if isinstance(nodes, list) else ())
            if isinstance(n, dict) and isinstance(n.get("eds"), str)]


def absolute_eds(raw: dict[str, Any], base_dir: Path) -> dict[str, Any]:
    """A layer's node EDS paths made absolute (relative to its own file), so that layers
    from several folders can mix."""
    nodes = raw.get("nodes")
    if not isinstance(nodes, list):
        return raw
    out = []
    for n in nodes:
        if isinstance(n, dict) and isinstance(n.get("eds"), str) \
                and not Path(n["eds"]).is_absolute() and (base_dir / n["eds"]).is_file():
            # absolute: a layer named by a relative path is looked up from the working folder
            n = {**n, "eds": str(base_dir.absolute() / n["eds"])}  # (else: the packaged folder's)
        out.append(n)
    return {**raw, "nodes": out}


def merge_layers(paths: ConfigPaths) -> tuple[dict[str, Any], dict[str, str]]:
    """The effective raw rig of ``--config`` files applied in order over the packaged rig
    (each after the bases it ``extends``), and the origin of every value: dotted key →
    the file that set it last (``default``: the packaged rig).

    The rule: tables merge key by key; a value, an array, an array of tables (``[[cells]]``,
    ``[[nodes]]``, …) is replaced whole by the last layer that gives it."""
    files = config_files(paths)
    dflt = default_config_path()
    raw = _read_toml(dflt)  # its EDS paths stay relative (to the package's config folder)
    origins: dict[str, str] = {}
    _note(raw, "", DEFAULT_SOURCE, origins)
    for f in files:
        for lp, layer in _layer_files(Path(f)):
            layer = absolute_eds(layer, lp.parent)
            raw = _merge(raw, layer)
            _note(layer, "", str(lp), origins)
    return raw, origins


def _note(layer: dict[str, Any], prefix: str, source: str, origins: dict[str, str]) -> None:
    for k, v in layer.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict) and v:
            _note(v, key, source, origins)
        else:
            for old in [o for o in origins if o.startswith(key + ".")]:
                del origins[old]  # a layer's value replaces what a table held below it
            origins[key] = source


def origin_of(key: str, origins: dict[str, str]) -> str | None:
    """The file a dotted key (``cells[2].position_m``, ``geometry.hub_centre_m``) came from."""
    k = re.sub(r"\[\d+\]", "", key)
    while k:
        if k in origins:
            return origins[k]
        k = k.rpartition(".")[0]
    return None


def load_config(path: ConfigPaths = None, overrides: dict[str, Any] | None = None) -> RigConfig:
    """Load and check a rig: the packaged rig, with the ``--config`` files (one path or a
    list) applied over it in order (:func:`merge_layers`). Raises ConfigError naming the
    file the faulty value came from."""
    files = config_files(path)
    if not files:  # the packaged rig alone, exactly as before
        p = default_config_path()
        raw = _read_toml(p)
        if overrides:
            raw = _merge(raw, overrides)
        return parse_config(raw, source=p.name, base_dir=p.parent)
    raw, origins = merge_layers(files)
    if overrides:
        raw = _merge(raw, overrides)
        _note(overrides, "", "<overrides>", origins)
    source = ", ".join(rig_path(f).name for f in files)
    try:
        cfg = parse_config(raw, source=source, base_dir=config_dir())
    except ConfigError as e:
        where = origin_of(e.key, origins)
        if where is None or where == e.source:
            raise
        raise ConfigError(e.key, e.value, e.problem, e.fix,
                          "the packaged rig" if where == DEFAULT_SOURCE else where) from None
    return dataclasses.replace(cfg, origins=origins)


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _radians(v: Any) -> Any:
    return [math.radians(float(x)) for x in v] if isinstance(v, list) else math.radians(v)


def _schema_value(tables: Sequence[BaseModel], name: str) -> Any:
    """The value of a dataclass field in the first schema table that has it: the key of the
    same name, or for a ``…_rad…`` field the table's ``…_deg…`` key in radians."""
    deg = name.replace("_rad", "_deg")
    for t in tables:
        if name in type(t).model_fields:
            return getattr(t, name)
        if deg != name and deg in type(t).model_fields:
            return _radians(getattr(t, deg))
    raise KeyError(f"{name}: no schema table holds it; give it to from_schema")


def _typed(hint: Any, v: Any) -> Any:
    """A schema value as the dataclass field holds it: a table as the field's dataclass, an
    array of tables as a tuple of them, a list of numbers as an array (where the field is
    one) or a tuple."""
    if isinstance(v, BaseModel):
        return from_schema(hint, v)
    if isinstance(v, list) and v and isinstance(v[0], BaseModel):
        return tuple(from_schema(typing.get_args(hint)[0], t) for t in v)
    if isinstance(v, list):
        return np.asarray(v, float) if np.ndarray in (hint, *typing.get_args(hint)) else tuple(v)
    return v


def from_schema(cls: type[T], *tables: BaseModel, **given: Any) -> T:
    """A config dataclass built from its validated schema tables (config.rigfile), the only
    place a default is written: every field without a default here takes the tables' value
    of the same name (:func:`_schema_value`, :func:`_typed`); ``given``: the fields the file
    holds in another shape (a unit vector, a sorted tuple, a value made of several keys)."""
    hints = typing.get_type_hints(cls)
    values = dict(given)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        own_default = f.default is not dataclasses.MISSING \
            or f.default_factory is not dataclasses.MISSING
        if f.name not in given and not own_default:
            values[f.name] = _typed(hints[f.name], _schema_value(tables, f.name))
    return cls(**values)


def _structure_fit(st: StructureTable | None) -> dict[str, Any] | None:
    """``[identification.structure]`` as estimator.structure.fit_payload (SI); None: the
    constant structure."""
    if st is None:
        return None
    return {"structure": st.structure, "alpha0": np.radians(st.alpha0_deg).tolist(),
            "beta": [float(b) for b in st.beta], "T_ref": [float(t) for t in st.T_ref_N]}


def _advice(adv: AdviceTable, first: AccelerometerTable) -> AdviceConfig | None:
    """``[identification.advice]``; a candidate position's noise is the rig's first
    accelerometer's unless it gives its own."""
    if not adv.enabled:
        return None
    return from_schema(AdviceConfig, adv, accelerometers=tuple(
        (a.name, np.asarray(a.position_m, float),
         (a.full_scale_g or first.full_scale_g) * G0 * (a.accuracy_fs or first.accuracy_fs))
        for a in adv.accelerometers))


def _identification(f: RigFile) -> IdentificationConfig:
    idt = f.identification
    init = np.broadcast_to(np.asarray(idt.initial_angles_deg, float), (14,))
    return from_schema(IdentificationConfig, idt, initial_angles_rad=np.radians(init),
                       structure_fit=_structure_fit(idt.structure),
                       advice=_advice(idt.advice, f.accelerometers[0]))


def parse_config(raw: dict[str, Any], source: str = "<config>",
                 base_dir: Path | None = None) -> RigConfig:
    """Validate a whole rig (config.rigfile's pydantic schema) and build its RigConfig from
    it (:func:`from_schema`). Raises ConfigError naming the key, the value and the fix."""
    base_dir = base_dir or config_dir()
    f = validate(raw, base_dir=base_dir, packaged_dir=config_dir())
    if not isinstance(f, RigFile):
        raise ConfigError(*f, source)
    return from_schema(
        RigConfig, f, f.rig, f.geometry, f.mass, f.inertial,
        source=source, rig_name=f.rig.name, raw=raw,
        cells=tuple(from_schema(CellConfig, c, nominal_axis=np.asarray(c.nominal_axis, float)
                                / np.linalg.norm(c.nominal_axis)) for c in f.cells),
        filter=from_schema(FilterConfig, f.filter, harmonics=tuple(sorted(f.filter.harmonics))),
        identification=_identification(f),
        nodes=tuple(from_schema(NodeConfig, n, eds=n.eds_path) for n in f.nodes),
        calibration={k: (e.gain, e.offset) for k, e in f.calibration.items()},
        telemetry=from_schema(TelemetryConfig, f.telemetry,
                              prefix=f.telemetry.prefix or f"rsra/{f.rig.name}"),
    )
