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
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from rsra.estimator.params import (
    Accelerometers,
    ExternalLoads,
    Geometry,
    MassProperties,
    RigModel,
)

MAX_SAMPLE_RATE_HZ = 10_000.0  # a SYNC every 100 µs: more than any CAN bus carries

G0 = 9.80665  # standard gravity, m/s^2
ROLES = ("load_cell", "accelerometer", "rotor_speed", "balance", "drive_load")
CONTENTS = ("static", "harmonics", "broadband", "vibration")


# Zenoh's link protocols (zenoh-link) and those whose address is <host>:<port>
ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial",
                   "vsock")
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def zenoh_endpoint_problem(ep: str) -> str | None:
    """What is wrong with a Zenoh endpoint ``<protocol>/<address>[?<metadata>][#<config>]``,
    or None. Zenoh itself accepts an unknown protocol or a bad address in its config and
    fails only when the session opens (or, for some, listens nowhere without a word)."""
    proto, sep, rest = ep.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if not sep or not address:
        return "not a Zenoh endpoint (<protocol>/<address>)"
    if proto not in ZENOH_PROTOCOLS:
        return f"unknown Zenoh protocol {proto!r} (one of {', '.join(ZENOH_PROTOCOLS)})"
    if proto in _IP_PROTOCOLS:
        host, colon, port = address.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            return "the address must be <host>:<port> with a port 0…65535"
        bracketed = host.startswith("[") and host.endswith("]")
        if (":" in host or "[" in host or "]" in host) and not bracketed:
            return "an IPv6 address goes in brackets: [::1]:7447"
    return None


class ConfigError(ValueError):
    """A configuration mistake: which key, what value, what to do."""

    def __init__(self, key: str, value: Any, problem: str, fix: str, source: str = ""):
        self.key, self.value, self.problem, self.fix, self.source = key, value, problem, fix, source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key} = {value!r}: {problem}; fix: {fix}")


_MISSING = object()
COB_MAX_11BIT = 0x7FF
# the rotor-speed band the load filter is designed for at start-up (flight: +-2 %); every
# modelled harmonic must stay below Nyquist over it (daq.pipeline prefills it)
DESIGN_BAND = 0.02
# a position farther than this from the reference point is a typing mistake (1e308 would
# overflow the geometry's arithmetic): no rotor transmission is 100 m across
POSITION_MAX_M = 100.0


def predefined_cob_ids(node_id: int) -> dict[int, str]:
    """COB-ID -> use, for a node's CiA 301 predefined connection set (and NMT)."""
    ids = {0x000: "NMT", 0x080 + node_id: "EMCY", 0x580 + node_id: "SDO response",
           0x600 + node_id: "SDO request", 0x700 + node_id: "heartbeat"}
    for n in range(4):
        ids[0x180 + 0x100 * n + node_id] = f"TPDO{n + 1}"
        ids[0x200 + 0x100 * n + node_id] = f"RPDO{n + 1}"
    return ids


class Section:
    """Typed access to one TOML table, tracking the dotted key path and unknown keys."""

    def __init__(self, data: dict, path: str, source: str):
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
        ok = isinstance(v, (int, float)) and not isinstance(v, bool)
        if integer:
            ok = ok and float(v).is_integer()
        if not ok or not math.isfinite(float(v)):
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
            if not math.isfinite(x):
                raise ConfigError(f"{self.key(name)}[{i}]", x, "must be finite",
                                  "replace it with a finite number", self.source)
            if positive and x <= 0:
                raise ConfigError(f"{self.key(name)}[{i}]", float(x), "must be > 0",
                                  f"give a positive value{unit}", self.source)
            if max_abs is not None and abs(x) > max_abs:
                u = unit.replace(" in ", " ").rstrip()
                raise ConfigError(f"{self.key(name)}[{i}]", float(x),
                                  f"is more than {max_abs:g}{u} from the reference point",
                                  f"give the position{unit}, within +-{max_abs:g}", self.source)
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
    # issue 25: "design" (the harmonic states advance by the design's Ω, the default) or
    # "azimuth" (by the measured azimuth of the rotor-speed node; gain held ±5 %)
    harmonic_phase: str = "design"


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
    angle_limit_rad: float = math.radians(10.0)
    # filter-error runs (issue 25): the update rule ("consider": only along the window's
    # determined directions; "bayes": its information in full) and the windows' systematic
    # error σ_b, a floor on the fused σ along each window's determined directions
    filter_error_update: str = "consider"
    filter_error_floor_rad: float = 0.0
    # [identification.structure] (issue 19; `rsra calibrate` writes it): the structure the
    # hub loads use from the start, as estimator.structure.fit_payload (SI); None: constant
    structure_fit: dict | None = None


# [identification.structure]: the number of parameters β of each structure
# (estimator.structure.parameter_names; config may import estimator.params only)
STRUCTURE_PARAMETERS = {"cell_load_angles": 14, "hub_position": 3, "balance": 9,
                        "external_load": 18}


def _structure_fit(st: "Section") -> dict:
    """``[identification.structure]`` → the structure's fit payload (SI)."""
    name = st.string("structure", choices=tuple(STRUCTURE_PARAMETERS))
    p = STRUCTURE_PARAMETERS[name]
    fit = {"structure": name,
           "alpha0": np.radians(st.vector("alpha0_deg", 14, unit=" in degrees")).tolist(),
           "beta": st.vector("beta", p, unit=" (SI: rad/N, m, fraction and rad, N/N)").tolist(),
           "T_ref": st.vector("T_ref_N", 7, unit=" in N").tolist()}
    st.finish()
    return fit


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

    enabled: bool = True
    false_alarm_per_hour: float = 1.0e-6  # per channel, honest channel at rest
    max_delay_s: float = 0.5  # a channel needing a longer run to meet the rate is untested


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
    stuck: StuckConfig = field(default_factory=StuckConfig)
    raw: dict = field(repr=False, default_factory=dict)
    #: dotted key -> the file its value came from ("default": the packaged rig); empty when
    #: the rig was not loaded from layered files (config.rig.merge_layers)
    origins: dict = field(repr=False, default_factory=dict, compare=False)

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

    def effective(self) -> dict:
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


def _read_toml(p: Path) -> dict:
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("--config", str(p), "file not found",
                          "give the path of a rig TOML, or omit --config for the default rig") from None
    except (OSError, UnicodeDecodeError) as e:  # a folder, no permission, not text
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        raise ConfigError("--config", str(p), f"cannot be read ({why})",
                          "give the path of a rig TOML, or omit --config for the default rig") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("<file>", str(p), f"not valid TOML ({e})", "fix the TOML syntax") from None


def _layer_files(p: Path, chain: tuple[Path, ...] = ()) -> list[tuple[Path, dict]]:
    """The layers a rig TOML stands for, base first: its ``extends`` chain (a rig TOML it
    names, relative to it; ``"default"`` or none: the packaged rig, not listed), then
    itself (without ``extends``)."""
    rp = p.resolve()
    if rp in chain:
        raise ConfigError("extends", str(p), "the files extend each other in a circle",
                          "make one of them extend \"default\"", str(chain[-1]))
    raw = _read_toml(p)
    base = raw.pop("extends", DEFAULT_SOURCE)
    if not isinstance(base, str) or not base:
        raise ConfigError("extends", base, "must be a path or \"default\"",
                          "name the rig TOML this one extends", p.name)
    out: list[tuple[Path, dict]] = []
    if base != DEFAULT_SOURCE:
        bp = Path(base) if Path(base).is_absolute() else p.parent / base
        if not bp.is_file():
            raise ConfigError("extends", base, f"file not found (looked in {p.parent})",
                              "give the path of the rig TOML this one extends", p.name)
        out = _layer_files(bp, chain + (rp,))
    return out + [(p, raw)]


def absolute_eds(raw: dict, base_dir: Path) -> dict:
    """A layer's node EDS paths made absolute (relative to its own file), so that layers
    from several folders can mix."""
    nodes = raw.get("nodes")
    if not isinstance(nodes, list):
        return raw
    out = []
    for n in nodes:
        if isinstance(n, dict) and isinstance(n.get("eds"), str) \
                and not Path(n["eds"]).is_absolute() and (base_dir / n["eds"]).is_file():
            n = {**n, "eds": str(base_dir / n["eds"])}  # (else: the packaged folder's)
        out.append(n)
    return {**raw, "nodes": out}


def merge_layers(paths: ConfigPaths) -> tuple[dict, dict[str, str]]:
    """The effective raw rig of ``--config`` files applied in order over the packaged rig
    (each after the bases it ``extends``), and the origin of every value: dotted key →
    the file that set it last (``default``: the packaged rig).

    The rule: tables merge key by key; a value, an array, an array of tables (``[[cells]]``,
    ``[[nodes]]``, …) is replaced whole by the last layer that gives it."""
    files = [paths] if isinstance(paths, (str, Path)) else list(paths or ())
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


def _note(layer: dict, prefix: str, source: str, origins: dict[str, str]) -> None:
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


def load_config(path: ConfigPaths = None, overrides: dict | None = None) -> RigConfig:
    """Load and check a rig: the packaged rig, with the ``--config`` files (one path or a
    list) applied over it in order (:func:`merge_layers`). Raises ConfigError naming the
    file the faulty value came from."""
    files = [path] if isinstance(path, (str, Path)) else list(path or ())
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
    source = ", ".join(Path(f).name for f in files)
    try:
        cfg = parse_config(raw, source=source, base_dir=config_dir())
    except ConfigError as e:
        where = origin_of(e.key, origins)
        if where is None or where == e.source:
            raise
        raise ConfigError(e.key, e.value, e.problem, e.fix,
                          "the packaged rig" if where == DEFAULT_SOURCE else where) from None
    return dataclasses.replace(cfg, origins=origins)


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def parse_config(raw: dict, source: str = "<config>", base_dir: Path | None = None) -> RigConfig:
    base_dir = base_dir or config_dir()
    top = Section(raw, "", source)

    rig = top.table("rig", {})
    rig_name = rig.string("name", "bench")
    if not rig_name or "/" in rig_name or any(c in rig_name for c in "*?$#"):
        raise rig.error("name", rig_name, "must be a plain name", "use letters, digits, - or _")
    rate = rig.number("sample_rate_hz", 200.0, positive=True)
    if rate > MAX_SAMPLE_RATE_HZ:  # beyond any CAN bus (1 Mbit/s: ~1 100 samples/s here)
        raise rig.error("sample_rate_hz", rate, f"must be at most {MAX_SAMPLE_RATE_HZ:g} Hz",
                        "set rig.sample_rate_hz to the SYNC rate of the bus (200 by default)")
    rig.finish()

    geo = top.table("geometry")
    hub = geo.vector("hub_centre_m", 3, unit=" in m", max_abs=POSITION_MAX_M)
    tilt = math.radians(geo.number("shaft_tilt_deg", 0.0))
    frame = geo.string("hub_frame", "body", ("body", "shaft"))
    geo.finish()

    mass = top.table("mass")
    m = mass.vector("effective_mass_kg", 3, positive=True, unit=" in kg")
    inertia = mass.vector("inertia_kg_m2", 3, positive=True, unit=" in kg m^2")
    mass.finish()

    cells = []
    seen: dict[str, str] = {}
    for c in top.tables("cells"):
        name = c.string("name")
        if name in seen:
            raise c.error("name", name, f"cell listed twice (also at {seen[name]})",
                          "give every cell its own name")
        seen[name] = c.path
        axis = c.vector("nominal_axis", 3)
        nrm = float(np.linalg.norm(axis))
        if nrm == 0:
            raise c.error("nominal_axis", axis.tolist(), "is zero", "give the cell's direction")
        cells.append(CellConfig(
            name=name, node=c.string("node"), position_m=c.vector("position_m", 3, unit=" in m",
                                                                max_abs=POSITION_MAX_M),
            nominal_axis=axis / nrm,
            full_scale_N=c.number("full_scale_N", positive=True),
            accuracy_fs=c.number("accuracy_fs", positive=True),
            stiffness_N_per_m=c.number("stiffness_N_per_m", 1.0e8, positive=True),
        ))
        c.finish()
    if len(cells) != 7:
        raise ConfigError("cells", len(cells), "the model has exactly seven load cells (14 angles)",
                          "list seven [[cells]] blocks", source)
    kinds = sorted(int(np.argmax(np.abs(c.nominal_axis))) for c in cells)
    if kinds != [0, 1, 1, 2, 2, 2, 2]:
        raise ConfigError("cells[*].nominal_axis", [c.nominal_axis.round(3).tolist() for c in cells],
                          "need four vertical, two lateral and one longitudinal cell",
                          "check the nominal axes (vertical along z, lateral along y, longitudinal along x)",
                          source)

    inertial = top.table("inertial", {})
    angular = inertial.string("angular", "neglect", ("neglect", "least_squares"))
    inertial.finish()

    accs = []
    for a in top.tables("accelerometers"):
        accs.append(AccelerometerConfig(
            name=a.string("name"), node=a.string("node"),
            position_m=a.vector("position_m", 3, unit=" in m", max_abs=POSITION_MAX_M),
            full_scale_g=a.number("full_scale_g", positive=True),
            accuracy_fs=a.number("accuracy_fs", positive=True),
        ))
        a.finish()
    if not accs:
        raise ConfigError("accelerometers", [], "at least one triaxial accelerometer is needed",
                          "add an [[accelerometers]] block", source)

    rot = top.table("rotor")
    rotor = RotorConfig(
        blades=rot.number("blades", integer=True, positive=True),
        omega_nominal_rad_s=rot.number("omega_nominal_rad_s", positive=True),
        node=rot.string("node", ""),
        omega_min_fraction=rot.number("omega_min_fraction", 0.1, positive=True),
        redesign_band=rot.number("redesign_band", 0.005, positive=True),
        cache_resolution=rot.number("cache_resolution", 0.001, positive=True),
        stopped=rot.boolean("stopped", False),
        harmonic_phase=rot.string("harmonic_phase", "design", ("design", "azimuth")),
    )
    if rotor.harmonic_phase == "azimuth" and not rotor.node:
        raise rot.error("harmonic_phase", "azimuth", "needs the rotor-speed node's azimuth",
                        'set rotor.node, or harmonic_phase = "design"')
    rot.finish()

    bal = top.table("balance", {})
    balance = BalanceConfig(
        node=bal.string("node", ""),
        full_scale_force_N=bal.number("full_scale_force_N", 200000.0, positive=True),
        full_scale_moment_Nm=bal.number("full_scale_moment_Nm", 50000.0, positive=True),
        accuracy_fs=bal.number("accuracy_fs", 0.0002, positive=True),
    )
    bal.finish()

    ext = []
    for e in top.tables("external_loads", []):
        ext.append(ExternalLoadConfig(
            name=e.string("name"), node=e.string("node"),
            wrench_per_unit=e.vector("wrench_per_unit", 6),
            sigma=e.number("sigma", positive=True),
        ))
        e.finish()

    flt = top.table("filter", {})
    harm_raw = flt.get("harmonics", [1, rotor.blades])
    if (not isinstance(harm_raw, list) or not harm_raw
            or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in harm_raw)
            or len(set(harm_raw)) != len(harm_raw)):
        raise flt.error("harmonics", harm_raw, "must be a list of distinct positive whole numbers",
                        f"e.g. harmonics = [1, {rotor.blades}] for 1/rev and N_b/rev")
    psd_raw = flt.get("process_noise_psd", "auto")
    if isinstance(psd_raw, str):
        if psd_raw != "auto":
            raise flt.error("process_noise_psd", psd_raw, "unknown value",
                            'use "auto" or a list of six positive PSDs')
        psd: str | np.ndarray = "auto"
    else:
        psd = flt.vector("process_noise_psd", 6, positive=True)
    # every harmonic below Nyquist over the rotor-speed band designed at start-up: above it
    # the load filter cannot be designed (the Riccati solver fails; model §5)
    for h in sorted(harm_raw, reverse=True):
        f_h = h * rotor.omega_nominal_rad_s * (1 + DESIGN_BAND) / (2 * math.pi)
        if f_h >= rate / 2:
            f_rot = rotor.omega_nominal_rad_s / (2 * math.pi)
            raise flt.error("harmonics", harm_raw,
                            f"harmonic {h} is at {f_h:.3g} Hz ({h} × {f_rot:.3g} Hz rotor "
                            f"frequency, +{DESIGN_BAND:.0%} design band), at or above the "
                            f"Nyquist frequency {rate / 2:g} Hz of rig.sample_rate_hz = {rate:g}",
                            f"remove harmonic {h} or raise rig.sample_rate_hz above "
                            f"{2 * f_h:.3g} Hz")
    filt = FilterConfig(
        harmonics=tuple(sorted(harm_raw)),
        low_frequency_states=flt.boolean("low_frequency_states", True),
        tuning=flt.string("tuning", "time_constant", ("time_constant", "noise")),
        time_constant_s=flt.number("time_constant_s", 0.1, positive=True),
        process_noise_psd=psd,
        invalid_after_s=flt.number("invalid_after_s", 0.5, positive=True),
    )
    flt.finish()

    idt = top.table("identification", {})
    params = idt.get("parameters", "angles")
    if isinstance(params, list):
        if not params or not all(isinstance(x, str) for x in params) or len(set(params)) != len(params):
            raise idt.error("parameters", params, "must be distinct parameter names",
                            'use "angles" or a list such as ["delta_A", "theta_A"]')
        params = tuple(params)
    elif params != "angles":
        raise idt.error("parameters", params, "unknown value", 'use "angles" or a list of names')
    ia = idt.get("initial_angles_deg", 0.0)
    if isinstance(ia, (int, float)) and not isinstance(ia, bool):
        # one value for all 14 (checked finite like every number: nan made S singular)
        init = np.full(14, math.radians(idt.number("initial_angles_deg", 0.0)))
    else:
        init = np.radians(idt.vector("initial_angles_deg", 14, unit=" in degrees"))
    window = idt.number("window_s", 5.0, positive=True)
    period = idt.number("period_s", 5.0, positive=True)
    if window > period:
        raise idt.error("window_s", window, f"exceeds period_s = {period} (samples would count twice)",
                        "make window_s <= period_s")
    for key, v in (("window_s", window), ("period_s", period)):
        if round(v * rate) < 1:
            raise idt.error(key, v, f"is less than one sample at rig.sample_rate_hz = {rate:g}",
                            f"give at least {1 / rate:g} s (one sample); the default is 5.0")
    ident = IdentificationConfig(
        parameters=params,
        initial_angles_rad=init,
        prior_sigma_rad=math.radians(idt.number("prior_sigma_deg", 5.0, positive=True)),
        period_s=period,
        window_s=window,
        drift_rate_rad2_s=idt.number("drift_rate_rad2_s", 1e-9, nonneg=True),
        min_information=idt.number("min_information", 1.0, positive=True),
        sigma_max_rad=math.radians(idt.number("sigma_max_deg", 0.2, positive=True)),
        apply_delay_s=idt.number("apply_delay_s", 1.0, nonneg=True),
        content_known_loads=idt.string("content_known_loads", "static", CONTENTS),
        content_filter_error=idt.string("content_filter_error", "harmonics", CONTENTS),
        moment_floor_Nm=idt.number("moment_floor_Nm", 100.0, nonneg=True),
        max_iterations=idt.number("max_iterations", 10, integer=True, positive=True),
        reset_after=idt.number("reset_after", 3, integer=True, positive=True),
        stale_fraction=idt.number("stale_fraction", 0.05, nonneg=True),
        settle_time_constants=idt.number("settle_time_constants", 5.0, nonneg=True),
        gap_s=idt.number("gap_s", 0.5, positive=True),
        state_file=idt.string("state_file", ""),
        angle_limit_rad=math.radians(idt.number("angle_limit_deg", 10.0, positive=True)),
        filter_error_update=idt.string("filter_error_update", "consider", ("consider", "bayes")),
        filter_error_floor_rad=math.radians(idt.number("filter_error_floor_deg", 0.0,
                                                       nonneg=True)),
        structure_fit=_structure_fit(idt.table("structure")) if "structure" in idt.data
        else None,
    )
    over = np.flatnonzero(~(np.abs(init) <= ident.angle_limit_rad))
    if over.size:
        raise idt.error("initial_angles_deg", float(np.degrees(init[over[0]])),
                        f"outside the physical range ±{math.degrees(ident.angle_limit_rad):g}° "
                        "(identification.angle_limit_deg)",
                        "give angles within the range, or widen angle_limit_deg")
    idt.finish()

    sy = top.table("sync", {})
    sync = SyncConfig(
        producer=sy.string("producer", "service", ("service", "external")),
        cob_id=sy.number("cob_id", 0x80, integer=True, positive=True),
        counter_overflow=sy.number("counter_overflow", 240, integer=True, nonneg=True),
    )
    if sync.cob_id > COB_MAX_11BIT:
        raise sy.error("cob_id", sync.cob_id, "is not an 11-bit COB-ID",
                       "use 0x80 (the CANopen default)")
    if not (sync.counter_overflow == 0 or 2 <= sync.counter_overflow <= 240):
        raise sy.error("counter_overflow", sync.counter_overflow, "CiA 301 allows 0 or 2…240",
                       "use 240 (the default)")
    sy.finish()

    hb = top.table("heartbeat", {})
    heartbeat = HeartbeatConfig(
        producer_ms=hb.number("producer_ms", 100, integer=True, positive=True),
        timeout_factor=hb.number("timeout_factor", 2.5, positive=True),
        boot_timeout_s=hb.number("boot_timeout_s", 2.0, positive=True),
    )
    hb.finish()

    nodes = []
    names: dict[str, str] = {}
    ids: dict[int, str] = {}
    for n in top.tables("nodes"):
        name = n.string("name")
        if name in names:
            raise n.error("name", name, f"node listed twice (also at {names[name]})",
                          "give every node its own name")
        names[name] = n.path
        nid = n.number("node_id", integer=True)
        if not 1 <= nid <= 127:
            raise n.error("node_id", nid, "CANopen node ids are 1…127", "choose an id in 1…127")
        if nid in ids:
            raise n.error("node_id", nid, f"id already used by node {ids[nid]!r}",
                          "give every node its own id")
        ids[nid] = name
        eds = Path(n.string("eds"))
        eds_path = eds if eds.is_absolute() else base_dir / eds
        if not eds_path.is_file():
            # fall back to the packaged EDS folder
            alt = config_dir() / eds
            if alt.is_file():
                eds_path = alt
            else:
                raise n.error("eds", str(eds), f"file not found (looked in {base_dir})",
                              "give the EDS path relative to the config file")
        nodes.append(NodeConfig(name=name, role=n.string("role", choices=ROLES), node_id=nid,
                                eds=eds_path, required=n.boolean("required", True)))
        n.finish()

    # the SYNC COB-ID against every COB-ID of the configured nodes' predefined connection set
    # (CiA 301: a SYNC on a node's COB-ID is taken for that node's frame, and the reverse, so
    # no sample is ever assembled); the TPDO COB-IDs the EDS files give are checked against
    # it again with the decode table (daq.decoder)
    for nc in nodes:
        owner = predefined_cob_ids(nc.node_id).get(sync.cob_id)
        if owner is not None:
            raise ConfigError("sync.cob_id", hex(sync.cob_id),
                              f"is the {owner} COB-ID of node {nc.name!r} (id 0x{nc.node_id:02X})",
                              "use 0x80 (the CANopen default), or a COB-ID no node uses", source)

    def need_node(key: str, node: str, role: str, optional: bool = False) -> None:
        if optional and not node:
            return
        nc = next((x for x in nodes if x.name == node), None)
        if nc is None:
            raise ConfigError(key, node, "no [[nodes]] entry with that name",
                              f'add a [[nodes]] block with name = "{node}" and role = "{role}"', source)
        if nc.role != role:
            raise ConfigError(key, node, f"node has role {nc.role!r}, expected {role!r}",
                              "point it at the right node", source)

    used_nodes: dict[str, str] = {}
    for i, c in enumerate(cells):
        need_node(f"cells[{i}].node", c.node, "load_cell")
        if c.node in used_nodes:
            raise ConfigError(f"cells[{i}].node", c.node, f"node already used by {used_nodes[c.node]}",
                              "give each cell its own node", source)
        used_nodes[c.node] = f"cells[{i}]"
    for i, a in enumerate(accs):
        need_node(f"accelerometers[{i}].node", a.node, "accelerometer")
    need_node("rotor.node", rotor.node, "rotor_speed", optional=True)
    need_node("balance.node", balance.node, "balance", optional=True)
    for i, e in enumerate(ext):
        need_node(f"external_loads[{i}].node", e.node, "drive_load")

    cal_sec = top.table("calibration", {})
    calibration: dict[str, tuple[float, float]] = {}
    for k in list(cal_sec.data):
        entry = cal_sec.table(k)
        node_name = k.split(".")[0]
        if node_name not in names:
            raise cal_sec.error(k, cal_sec.data[k], f"no node named {node_name!r}",
                                'use keys "<node>.<channel>", e.g. "cell_A.force"')
        gain = entry.number("gain", 1.0)
        if gain == 0:
            raise entry.error("gain", gain, "a zero gain erases the channel",
                              "give the channel's gain (value = gain * raw + offset), e.g. 1.0")
        calibration[k] = (gain, entry.number("offset", 0.0))
        entry.finish()
    cal_sec.finish()

    tel = top.table("telemetry", {})
    prefix = tel.string("prefix", "") or f"rsra/{rig_name}"
    if prefix.startswith("/") or prefix.endswith("/") or any(c in prefix for c in "*$?#"):
        raise tel.error("prefix", prefix, "not a valid Zenoh key prefix",
                        'use e.g. "rsra/bench" (no wildcards, no leading or trailing /)')
    listen = tel.get("listen", ["tcp/127.0.0.1:7447"])
    connect = tel.get("connect", [])
    for key, eps in (("listen", listen), ("connect", connect)):
        if not isinstance(eps, list) or not all(isinstance(x, str) for x in eps):
            raise tel.error(key, eps, "must be a list of Zenoh endpoints",
                            f'e.g. {key} = ["tcp/127.0.0.1:7447"]')
        for ep in eps:
            problem = zenoh_endpoint_problem(ep)
            if problem:
                raise tel.error(key, ep, problem, f'e.g. {key} = ["tcp/127.0.0.1:7447"]')
    telemetry = TelemetryConfig(
        prefix=prefix,
        mode=tel.string("mode", "peer", ("peer", "client", "router")),
        listen=tuple(listen), connect=tuple(connect),
        multicast_scouting=tel.boolean("multicast_scouting", False),
        innovations_hz=tel.number("innovations_hz", 20.0, positive=True),
        zenoh_config=tel.string("zenoh_config", ""),
    )
    tel.finish()

    rec = top.table("recording", {})
    recording = RecordingConfig(
        dir=rec.string("dir", ""),
        format=rec.string("format", "log", ("log", "blf", "asc", "mf4")),
        rotate_mb=rec.number("rotate_mb", 64.0, positive=True),
        cap_mb=rec.number("cap_mb", 4096.0, positive=True),
        flush_s=rec.number("flush_s", 1.0, positive=True),
    )
    if recording.flush_s > 1.0:
        raise rec.error("flush_s", recording.flush_s, "recordings flush at least once a second",
                        "set flush_s <= 1")
    rec.finish()

    sim = top.table("simulator", {})
    simulator = SimulatorConfig(
        damping_ratio=sim.number("damping_ratio", 0.02, nonneg=True),
        damping_reference_hz=sim.number("damping_reference_hz", 50.0, positive=True),
        substeps=sim.number("substeps", 10, integer=True, positive=True),
    )
    sim.finish()

    stk = top.table("stuck", {})
    stuck = StuckConfig(
        enabled=stk.boolean("enabled", True),
        false_alarm_per_hour=stk.number(
            "false_alarm_per_hour", 1.0e-6, positive=True,
            fix="give the accepted false alarms per channel-hour, e.g. 1e-6"),
        max_delay_s=stk.number("max_delay_s", 0.5, positive=True,
                               fix="give the longest run to wait for, in s, e.g. 0.5"),
    )
    if stuck.false_alarm_per_hour >= 1.0:
        raise stk.error("false_alarm_per_hour", stuck.false_alarm_per_hour,
                        "must be below 1 (a probability per channel-hour)",
                        "use e.g. 1e-6")
    stk.finish()
    top.finish()

    cfg = RigConfig(
        source=source, rig_name=rig_name, sample_rate_hz=rate, hub_centre_m=hub,
        shaft_tilt_rad=tilt, hub_frame=frame, effective_mass_kg=m, inertia_kg_m2=inertia,
        cells=tuple(cells), angular=angular, accelerometers=tuple(accs), rotor=rotor,
        balance=balance, external_loads=tuple(ext), filter=filt, identification=ident,
        sync=sync, heartbeat=heartbeat, nodes=tuple(nodes), calibration=calibration,
        telemetry=telemetry, recording=recording, simulator=simulator, stuck=stuck, raw=raw,
    )
    return cfg
