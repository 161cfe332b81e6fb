"""The rig TOML's schema, validated by pydantic (v2): what each table may hold, of which type,
in which range, with which default, and the checks across keys.

The models mirror the file (degrees where the file has degrees, EDS paths as written);
config.rig turns a validated file into the service's RigConfig and every failure into one
ConfigError line naming the key, the value and the fix (:func:`config_error`).

Pydantic gives the structure: tables and arrays of tables, unknown keys (``extra="forbid"``),
missing keys, types without coercion (``strict``: "5" is not a number, 1.0 is not true),
finite numbers, ranges (``gt``/``ge``), lengths, choices (``Literal``), defaults and the dotted
location of every error. What it cannot say in the file's words (a cell listed twice, a
harmonic above Nyquist, a node a cell names that no ``[[nodes]]`` block defines) is checked by
validators raising :class:`Invalid`, which names the key relative to the table checked.
"""
import difflib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

from rsra.config.devices import DEVICE_PROFILES
from rsra.config.readfile import regular_file_problem

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails, PydanticCustomError

MAX_SAMPLE_RATE_HZ = 10_000.0  # a SYNC every 100 µs: more than any CAN bus carries
# the sensor roles a [[nodes]] block may name: those of the device-profile table
ROLES = tuple(DEVICE_PROFILES)
CONTENTS = ("static", "harmonics", "broadband", "vibration")
COB_MAX_11BIT = 0x7FF
# the rotor-speed band the load filter is designed for at start-up (flight: +-2 %); every
# modelled harmonic must stay below Nyquist over it (daq.pipeline prefills it)
DESIGN_BAND = 0.02
# a position farther than this from the reference point is a typing mistake (1e308 would
# overflow the geometry's arithmetic): no rotor transmission is 100 m across
POSITION_MAX_M = 100.0
# [identification.structure]: the number of parameters β of each structure
# (estimator.structure.parameter_names; config may import estimator.params only)
STRUCTURE_PARAMETERS = {"cell_load_angles": 14, "hub_position": 3, "balance": 9,
                        "external_load": 18}

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


class Invalid(ValueError):
    """A check across keys failed: ``key`` relative to the table the validator checks
    ("" for that table or field itself, "[3]" for an element)."""

    def __init__(self, key: str, value: Any, problem: str, fix: str):
        super().__init__(problem)
        self.key, self.value, self.problem, self.fix = key, value, problem, fix


# -- field types ----------------------------------------------------------------------------

def _whole(v: Any) -> Any:
    """A whole float (``10.0``) counts as the integer it is; anything else goes on to int."""
    if isinstance(v, float) and math.isfinite(v) and v.is_integer():
        return int(v)
    return v


def _near(x: float) -> float:
    if abs(x) > POSITION_MAX_M:
        raise PydanticCustomError(
            "position_range", f"is more than {POSITION_MAX_M:g} m from the reference point",
            {"fix": f"give the position in m, within +-{POSITION_MAX_M:g}"})
    return x


def _meta(**kw: Any) -> Any:
    """Field metadata the error messages use: ``unit`` (of a vector's numbers), ``fix``."""
    return Field(json_schema_extra=kw)


def _known_role(role: str) -> str:
    """A role of the device-profile table (read when validating: a role added to the table
    is a choice at once), refused as an unknown choice otherwise."""
    if role not in DEVICE_PROFILES:
        raise PydanticCustomError("literal_error", "Input should be {expected}", {
            "expected": ", ".join(repr(r) for r in DEVICE_PROFILES)})
    return role


Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]
Whole = Annotated[int, BeforeValidator(_whole)]
PosWhole = Annotated[int, BeforeValidator(_whole), Field(gt=0)]
Position = Annotated[list[Annotated[float, AfterValidator(_near)]],
                     Field(min_length=3, max_length=3), _meta(unit=" in m")]


def _vector(v: Any, n: int, *, positive: bool = False, unit: str = "") -> list[float]:
    """A list of ``n`` finite numbers (for the keys that take a number or a word as well)."""
    if not isinstance(v, list) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise Invalid("", v, "must be a list of numbers", f"write it as [x, y, …]{unit}")
    if len(v) != n:
        raise Invalid("", v, f"must have {n} values, has {len(v)}", f"give {n} numbers{unit}")
    for i, x in enumerate(v):
        if not math.isfinite(x):
            raise Invalid(f"[{i}]", x, "must be finite", "replace it with a finite number")
        if positive and x <= 0:
            raise Invalid(f"[{i}]", float(x), "must be > 0", f"give a positive value{unit}")
    return [float(x) for x in v]


class Table(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


# -- the tables -----------------------------------------------------------------------------

class RigTable(Table):
    name: str = "bench"
    sample_rate_hz: Pos = 200.0

    @model_validator(mode="after")
    def _check(self) -> "RigTable":
        if not self.name or "/" in self.name or any(c in self.name for c in "*?$#"):
            raise Invalid("name", self.name, "must be a plain name", "use letters, digits, - or _")
        if self.sample_rate_hz > MAX_SAMPLE_RATE_HZ:  # beyond any CAN bus
            raise Invalid("sample_rate_hz", self.sample_rate_hz,
                          f"must be at most {MAX_SAMPLE_RATE_HZ:g} Hz",
                          "set rig.sample_rate_hz to the SYNC rate of the bus (200 by default)")
        return self


class GeometryTable(Table):
    hub_centre_m: Position
    shaft_tilt_deg: float = 0.0
    hub_frame: Literal["body", "shaft"] = "body"


class MassTable(Table):
    effective_mass_kg: Annotated[list[Pos], Field(min_length=3, max_length=3), _meta(unit=" in kg")]
    inertia_kg_m2: Annotated[list[Pos], Field(min_length=3, max_length=3),
                             _meta(unit=" in kg m^2")]


class CellTable(Table):
    name: str
    node: str
    position_m: Position
    nominal_axis: Annotated[list[float], Field(min_length=3, max_length=3)]
    full_scale_N: Pos
    accuracy_fs: Pos
    stiffness_N_per_m: Pos = 1.0e8

    @field_validator("nominal_axis")
    @classmethod
    def _nonzero(cls, v: list[float]) -> list[float]:
        if not any(v):
            raise Invalid("", v, "is zero", "give the cell's direction")
        return v


class InertialTable(Table):
    angular: Literal["neglect", "least_squares"] = "neglect"


class AccelerometerTable(Table):
    name: str
    node: str
    position_m: Position
    full_scale_g: Pos
    accuracy_fs: Pos


class RotorTable(Table):
    blades: PosWhole
    omega_nominal_rad_s: Pos
    node: str = ""
    omega_min_fraction: Pos = 0.1
    redesign_band: Pos = 0.005
    cache_resolution: Pos = 0.001
    stopped: bool = False
    # "design" (the harmonic states advance by the design's Ω) or "azimuth"
    harmonic_phase: Literal["design", "azimuth"] = "design"

    @model_validator(mode="after")
    def _check(self) -> "RotorTable":
        if self.harmonic_phase == "azimuth" and not self.node:
            raise Invalid("harmonic_phase", "azimuth", "needs the rotor-speed node's azimuth",
                          'set rotor.node, or harmonic_phase = "design"')
        return self


class BalanceTable(Table):
    node: str = ""
    full_scale_force_N: Pos = 200000.0
    full_scale_moment_Nm: Pos = 50000.0
    accuracy_fs: Pos = 0.0002


class ExternalLoadTable(Table):
    name: str
    node: str
    wrench_per_unit: Annotated[list[float], Field(min_length=6, max_length=6)]
    sigma: Pos


class FilterTable(Table):
    harmonics: Any = None  # None: [1, rotor.blades]; checked with the rotor (RigFile)
    low_frequency_states: bool = True
    tuning: Literal["time_constant", "noise"] = "time_constant"
    time_constant_s: Pos = 0.1
    process_noise_psd: Any = "auto"
    invalid_after_s: Pos = 0.5

    @field_validator("process_noise_psd", mode="before")
    @classmethod
    def _psd(cls, v: Any) -> Any:
        if isinstance(v, str):
            if v != "auto":
                raise Invalid("", v, "unknown value", 'use "auto" or a list of six positive PSDs')
            return v
        return _vector(v, 6, positive=True)


class StructureTable(Table):
    """``[identification.structure]`` (`rsra calibrate` writes it)."""

    structure: Literal[tuple(STRUCTURE_PARAMETERS)]  # type: ignore[valid-type]
    alpha0_deg: Annotated[list[float], Field(min_length=14, max_length=14),
                          _meta(unit=" in degrees")]
    beta: list[float]
    T_ref_N: Annotated[list[float], Field(min_length=7, max_length=7), _meta(unit=" in N")]

    @model_validator(mode="after")
    def _check(self) -> "StructureTable":
        p = STRUCTURE_PARAMETERS[self.structure]
        if len(self.beta) != p:
            raise Invalid("beta", self.beta, f"must have {p} values, has {len(self.beta)}",
                          f"give {p} numbers (SI: rad/N, m, fraction and rad, N/N)")
        return self


class AdviceAccelerometerTable(Table):
    """A candidate accelerometer position (``[[identification.advice.accelerometers]]``);
    its noise is the rig's first accelerometer's unless given."""

    name: str
    position_m: Position
    full_scale_g: Pos | None = None
    accuracy_fs: Pos | None = None


class AdviceTable(Table):
    """``[identification.advice]``: the additions the filter-error windows'
    advice weighs (docs/identification.md "Which additions would determine the rest")."""

    enabled: bool = True
    band_hz: Annotated[list[Pos], Field(min_length=2, max_length=2), _meta(unit=" in Hz")] = \
        [5.0, 40.0]
    manoeuvre_rms: Annotated[list[NonNeg], Field(min_length=6, max_length=6),
                             _meta(unit=" in N, N m")] = [3000.0, 3000.0, 3000.0,
                                                           200.0, 200.0, 200.0]
    accelerometers: list[AdviceAccelerometerTable] = []

    @model_validator(mode="after")
    def _check(self) -> "AdviceTable":
        if not self.band_hz[0] < self.band_hz[1]:
            raise Invalid("band_hz", self.band_hz, "must be [low, high] with low < high",
                          "give the excitation band, e.g. [5.0, 40.0]")
        names = [a.name for a in self.accelerometers]
        if len(set(names)) != len(names) or not all(names):
            raise Invalid("accelerometers", names, "need distinct, non-empty names",
                          "name each candidate position once")
        return self


class IdentificationTable(Table):
    parameters: Any = "angles"
    initial_angles_deg: Any = 0.0
    prior_sigma_deg: Pos = 5.0
    period_s: Pos = 5.0
    window_s: Pos = 5.0
    drift_rate_rad2_s: NonNeg = 1e-9
    min_information: Pos = 1.0
    sigma_max_deg: Pos = 0.2
    apply_delay_s: NonNeg = 1.0
    content_known_loads: Literal[CONTENTS] = "static"  # type: ignore[valid-type]
    content_filter_error: Literal[CONTENTS] = "harmonics"  # type: ignore[valid-type]
    moment_floor_Nm: NonNeg = 100.0
    max_iterations: PosWhole = 10
    reset_after: PosWhole = 3
    stale_fraction: NonNeg = 0.5
    settle_time_constants: NonNeg = 5.0
    gap_s: Pos = 0.5
    state_file: str = ""
    angle_limit_deg: Pos = 10.0
    filter_error_update: Literal["consider", "bayes"] = "consider"
    filter_error_floor_deg: NonNeg = 0.0
    # filter-error runs: a bound (1 σ) on how far each angle moves per unit of
    # static hub load X Y Z (N) L M N (N·m) away from the flight's reference (trim) load
    angle_load_sensitivity_deg_per_unit: Annotated[
        list[NonNeg], Field(min_length=6, max_length=6),
        _meta(unit=" in ° per N (X, Y, Z) and per N·m (L, M, N)")] = [0.0] * 6
    filter_error_scattered_fraction: NonNeg = 0.02
    # known loads: a bound (1 σ) on each angle's drift rate, solved for beside the angles
    # (estimator.load_spread); 0: constant angles up to the random walk
    angle_drift_rate_deg_per_s: NonNeg = 0.0
    # known loads: the Gaussian summary's curvature index above which a run is held
    # (not_identifiable, detail nonlinear; estimator.curvature)
    nonlinearity_check: bool = True
    nonlinearity_limit: NonNeg = 1.0
    structure: StructureTable | None = None
    advice: AdviceTable = Field(default_factory=AdviceTable)

    @field_validator("parameters", mode="before")
    @classmethod
    def _parameters(cls, v: Any) -> Any:
        if isinstance(v, list):
            if not v or not all(isinstance(x, str) for x in v) or len(set(v)) != len(v):
                raise Invalid("", v, "must be distinct parameter names",
                              'use "angles" or a list such as ["delta_A", "theta_A"]')
            return tuple(v)
        if v != "angles":
            raise Invalid("", v, "unknown value", 'use "angles" or a list of names')
        return v

    @field_validator("initial_angles_deg", mode="before")
    @classmethod
    def _initial(cls, v: Any) -> Any:
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            # one value for all 14 (checked finite like every number: nan made S singular)
            if not math.isfinite(v):
                raise Invalid("", v, "must be a finite number", "set initial_angles_deg to a "
                              "finite number")
            return float(v)
        return _vector(v, 14, unit=" in degrees")

    @model_validator(mode="after")
    def _check(self) -> "IdentificationTable":
        if self.window_s > self.period_s:
            raise Invalid("window_s", self.window_s,
                          f"exceeds period_s = {self.period_s} (samples would count twice)",
                          "make window_s <= period_s")
        init = self.initial_angles_deg
        for a in (init if isinstance(init, list) else [init]):
            if not abs(a) <= self.angle_limit_deg:
                raise Invalid("initial_angles_deg", float(a),
                              f"outside the physical range ±{self.angle_limit_deg:g}° "
                              "(identification.angle_limit_deg)",
                              "give angles within the range, or widen angle_limit_deg")
        return self


class SyncTable(Table):
    producer: Literal["service", "external"] = "service"
    cob_id: PosWhole = 0x80
    counter_overflow: Annotated[int, BeforeValidator(_whole), Field(ge=0)] = 240

    @model_validator(mode="after")
    def _check(self) -> "SyncTable":
        if self.cob_id > COB_MAX_11BIT:
            raise Invalid("cob_id", self.cob_id, "is not an 11-bit COB-ID",
                          "use 0x80 (the CANopen default)")
        if not (self.counter_overflow == 0 or 2 <= self.counter_overflow <= 240):
            raise Invalid("counter_overflow", self.counter_overflow, "CiA 301 allows 0 or 2…240",
                          "use 240 (the default)")
        return self


class HeartbeatTable(Table):
    producer_ms: PosWhole = 100
    timeout_factor: Pos = 2.5
    boot_timeout_s: Pos = 2.0


class NodeTable(Table):
    name: str
    role: Annotated[str, AfterValidator(_known_role)]
    node_id: Whole
    eds: str
    required: bool = True
    _eds_path: Path | None = PrivateAttr(default=None)  # resolved by RigFile

    @property
    def eds_path(self) -> Path:
        """The EDS file the node names, as found when the whole file was validated."""
        if self._eds_path is None:  # a NodeTable validated outside a RigFile
            raise ValueError(f"node {self.name!r}: its EDS path is resolved by RigFile")
        return self._eds_path

    @field_validator("node_id")
    @classmethod
    def _id(cls, v: int) -> int:
        if not 1 <= v <= 127:
            raise Invalid("", v, "CANopen node ids are 1…127", "choose an id in 1…127")
        return v


class CalibrationEntry(Table):
    gain: float = 1.0
    offset: float = 0.0

    @field_validator("gain")
    @classmethod
    def _gain(cls, v: float) -> float:
        if v == 0:
            raise Invalid("", v, "a zero gain erases the channel",
                          "give the channel's gain (value = gain * raw + offset), e.g. 1.0")
        return v


_ENDPOINTS = 'e.g. {key} = ["tcp/127.0.0.1:7447"]'


class TelemetryTable(Table):
    prefix: str = ""  # "": rsra/<rig.name>
    mode: Literal["peer", "client", "router"] = "peer"
    listen: Annotated[list[str], _meta(fix=_ENDPOINTS.format(key="listen"))] = \
        ["tcp/127.0.0.1:7447"]
    connect: Annotated[list[str], _meta(fix=_ENDPOINTS.format(key="connect"))] = []
    multicast_scouting: bool = False
    innovations_hz: Pos = 20.0
    zenoh_config: str = ""

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str], info: ValidationInfo) -> list[str]:
        for ep in v:
            problem = zenoh_endpoint_problem(ep)
            if problem:
                raise Invalid("", ep, problem, _ENDPOINTS.format(key=info.field_name))
        return v


class RecordingTable(Table):
    dir: str = ""
    format: Literal["log", "blf", "asc", "mf4"] = "log"
    rotate_mb: Pos = 64.0
    cap_mb: Pos = 4096.0
    flush_s: Pos = 1.0

    @field_validator("flush_s")
    @classmethod
    def _flush(cls, v: float) -> float:
        if v > 1.0:
            raise Invalid("", v, "recordings flush at least once a second", "set flush_s <= 1")
        return v


class SimulatorTable(Table):
    damping_ratio: NonNeg = 0.02
    damping_reference_hz: Pos = 50.0
    substeps: PosWhole = 10


class LimitsTable(Table):
    """The rig's hub-load limits per axis of the hub loads' axes (N, N·m): what `rsra survey`
    reports each test point's peak against; 0: no limit on that axis."""

    X: NonNeg = 0.0
    Y: NonNeg = 0.0
    Z: NonNeg = 0.0
    L: NonNeg = 0.0
    M: NonNeg = 0.0
    N: NonNeg = 0.0


class StuckTable(Table):
    """Stuck-channel detection (daq/runtime/stuck.py): a run of exactly equal readings."""

    enabled: bool = True
    false_alarm_per_hour: Annotated[  # per channel, honest channel at rest
        Pos, _meta(fix="give the accepted false alarms per channel-hour, e.g. 1e-6")] = 1.0e-6
    max_delay_s: Annotated[  # a channel needing a longer run to meet the rate is untested
        Pos, _meta(fix="give the longest run to wait for, in s, e.g. 0.5")] = 0.5

    @field_validator("false_alarm_per_hour")
    @classmethod
    def _rate(cls, v: float) -> float:
        if v >= 1.0:
            raise Invalid("", v, "must be below 1 (a probability per channel-hour)",
                          "use e.g. 1e-6")
        return v


def _eds_file(i: int, name: str, base_dir: Path, packaged_dir: Path | None) -> Path:
    """The EDS file node ``i`` names: relative to the rig file, else in the packaged EDS
    folder; a regular file."""
    eds = Path(name)
    path = eds if eds.is_absolute() else base_dir / eds
    if not path.exists() and packaged_dir is not None and (Path(packaged_dir) / eds).exists():
        path = Path(packaged_dir) / eds  # the packaged EDS folder
    if not path.exists():
        raise Invalid(f"nodes[{i}].eds", name, f"file not found (looked in {base_dir})",
                      "give the EDS path relative to the config file")
    problem = regular_file_problem(path)  # a FIFO or device would block its reader
    if problem is not None:
        raise Invalid(f"nodes[{i}].eds", name, problem, "give the node's EDS file")
    return path


def predefined_cob_ids(node_id: int) -> dict[int, str]:
    """COB-ID -> use, for a node's CiA 301 predefined connection set (and NMT)."""
    ids = {0x000: "NMT", 0x080 + node_id: "EMCY", 0x580 + node_id: "SDO response",
           0x600 + node_id: "SDO request", 0x700 + node_id: "heartbeat"}
    for n in range(4):
        ids[0x180 + 0x100 * n + node_id] = f"TPDO{n + 1}"
        ids[0x200 + 0x100 * n + node_id] = f"RPDO{n + 1}"
    return ids


class RigFile(Table):
    """A whole rig TOML (after its layers are merged: config.rig.merge_layers)."""

    rig: RigTable = Field(default_factory=RigTable)
    geometry: GeometryTable
    mass: MassTable
    cells: list[CellTable]
    inertial: InertialTable = Field(default_factory=InertialTable)
    accelerometers: list[AccelerometerTable]
    rotor: RotorTable
    balance: BalanceTable = Field(default_factory=BalanceTable)
    external_loads: list[ExternalLoadTable] = []
    filter: FilterTable = Field(default_factory=FilterTable)
    identification: IdentificationTable = Field(default_factory=IdentificationTable)
    sync: SyncTable = Field(default_factory=SyncTable)
    heartbeat: HeartbeatTable = Field(default_factory=HeartbeatTable)
    nodes: list[NodeTable]
    calibration: dict[str, CalibrationEntry] = {}
    telemetry: TelemetryTable = Field(default_factory=TelemetryTable)
    recording: RecordingTable = Field(default_factory=RecordingTable)
    simulator: SimulatorTable = Field(default_factory=SimulatorTable)
    stuck: StuckTable = Field(default_factory=StuckTable)
    limits: LimitsTable = Field(default_factory=LimitsTable)

    @model_validator(mode="after")
    def _across(self, info: ValidationInfo) -> "RigFile":
        self._cells()
        if not self.accelerometers:
            raise Invalid("accelerometers", [], "at least one triaxial accelerometer is needed",
                          "add an [[accelerometers]] block")
        self._harmonics()
        self._windows()
        context = info.context or {}
        self._nodes(Path(context.get("base_dir", ".")), context.get("packaged_dir"))
        self._references()
        self._prefix()
        return self

    def _windows(self) -> None:
        """The identification's window and period each at least one sample long."""
        rate = self.rig.sample_rate_hz
        idt = self.identification
        for key, v in (("window_s", idt.window_s), ("period_s", idt.period_s)):
            if round(v * rate) < 1:
                raise Invalid(f"identification.{key}", v,
                              f"is less than one sample at rig.sample_rate_hz = {rate:g}",
                              f"give at least {1 / rate:g} s (one sample); the default is 5.0")

    def _prefix(self) -> None:
        prefix = self.telemetry.prefix or f"rsra/{self.rig.name}"
        if prefix.startswith("/") or prefix.endswith("/") or any(c in prefix for c in "*$?#"):
            raise Invalid("telemetry.prefix", prefix, "not a valid Zenoh key prefix",
                          'use e.g. "rsra/bench" (no wildcards, no leading or trailing /)')

    def _cells(self) -> None:
        seen: dict[str, str] = {}
        for i, c in enumerate(self.cells):
            if c.name in seen:
                raise Invalid(f"cells[{i}].name", c.name,
                              f"cell listed twice (also at {seen[c.name]})",
                              "give every cell its own name")
            seen[c.name] = f"cells[{i}]"
        if len(self.cells) != 7:
            raise Invalid("cells", len(self.cells),
                          "the model has exactly seven load cells (14 angles)",
                          "list seven [[cells]] blocks")
        unit = [[x / math.hypot(*c.nominal_axis) for x in c.nominal_axis] for c in self.cells]
        kinds = sorted(max(range(3), key=lambda k: abs(u[k])) for u in unit)
        if kinds != [0, 1, 1, 2, 2, 2, 2]:
            raise Invalid("cells[*].nominal_axis", [[round(x, 3) for x in u] for u in unit],
                          "need four vertical, two lateral and one longitudinal cell",
                          "check the nominal axes (vertical along z, lateral along y, "
                          "longitudinal along x)")

    def _harmonics(self) -> None:
        blades, omega = self.rotor.blades, self.rotor.omega_nominal_rad_s
        rate = self.rig.sample_rate_hz
        harm = self.filter.harmonics
        if harm is None:
            harm = self.filter.harmonics = [1, blades]
        if (not isinstance(harm, list) or not harm
                or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in harm)
                or len(set(harm)) != len(harm)):
            raise Invalid("filter.harmonics", harm,
                          "must be a list of distinct positive whole numbers",
                          f"e.g. harmonics = [1, {blades}] for 1/rev and N_b/rev")
        # every harmonic below Nyquist over the rotor-speed band designed at start-up: above
        # it the load filter cannot be designed (the Riccati solver fails; model §5)
        for h in sorted(harm, reverse=True):
            f_h = h * omega * (1 + DESIGN_BAND) / (2 * math.pi)
            if f_h >= rate / 2:
                f_rot = omega / (2 * math.pi)
                raise Invalid("filter.harmonics", harm,
                              f"harmonic {h} is at {f_h:.3g} Hz ({h} × {f_rot:.3g} Hz rotor "
                              f"frequency, +{DESIGN_BAND:.0%} design band), at or above the "
                              f"Nyquist frequency {rate / 2:g} Hz of rig.sample_rate_hz = "
                              f"{rate:g}",
                              f"remove harmonic {h} or raise rig.sample_rate_hz above "
                              f"{2 * f_h:.3g} Hz")

    def _nodes(self, base_dir: Path, packaged_dir: Path | None) -> None:
        if not self.nodes:  # (else every cell's node would be blamed on the file naming it)
            raise Invalid("nodes", [], "is empty: the rig would have no CAN nodes",
                          "list the rig's [[nodes]] blocks, or remove nodes = [] to keep the "
                          "ones it extends")
        names: dict[str, str] = {}
        ids: dict[int, str] = {}
        for i, n in enumerate(self.nodes):
            if n.name in names:
                raise Invalid(f"nodes[{i}].name", n.name,
                              f"node listed twice (also at {names[n.name]})",
                              "give every node its own name")
            names[n.name] = f"nodes[{i}]"
            if n.node_id in ids:
                raise Invalid(f"nodes[{i}].node_id", n.node_id,
                              f"id already used by node {ids[n.node_id]!r}",
                              "give every node its own id")
            ids[n.node_id] = n.name
            n._eds_path = _eds_file(i, n.eds, base_dir, packaged_dir)
        self._sync_cob_id()

    def _sync_cob_id(self) -> None:
        """The SYNC COB-ID against every COB-ID of the configured nodes' predefined
        connection set (CiA 301: a SYNC on a node's COB-ID is taken for that node's frame, and
        the reverse, so no sample is ever assembled); the TPDO COB-IDs the EDS files give are
        checked against it again with the decode table (daq.decoder)."""
        cob = self.sync.cob_id
        for n in self.nodes:
            owner = predefined_cob_ids(n.node_id).get(cob)
            if owner is not None:
                raise Invalid("sync.cob_id", hex(cob),
                              f"is the {owner} COB-ID of node {n.name!r} (id 0x{n.node_id:02X})",
                              "use 0x80 (the CANopen default), or a COB-ID no node uses")

    def _references(self) -> None:
        role = {n.name: n.role for n in self.nodes}

        def need(key: str, node: str, want: str, optional: bool = False) -> None:
            if optional and not node:
                return
            if node not in role:
                raise Invalid(key, node, "no [[nodes]] entry with that name",
                              f'add a [[nodes]] block with name = "{node}" and role = "{want}"')
            if role[node] != want:
                raise Invalid(key, node, f"node has role {role[node]!r}, expected {want!r}",
                              "point it at the right node")

        used: dict[str, str] = {}
        for i, c in enumerate(self.cells):
            need(f"cells[{i}].node", c.node, "load_cell")
            if c.node in used:
                raise Invalid(f"cells[{i}].node", c.node, f"node already used by {used[c.node]}",
                              "give each cell its own node")
            used[c.node] = f"cells[{i}]"
        for i, a in enumerate(self.accelerometers):
            need(f"accelerometers[{i}].node", a.node, "accelerometer")
        need("rotor.node", self.rotor.node, "rotor_speed", optional=True)
        need("balance.node", self.balance.node, "balance", optional=True)
        for i, e in enumerate(self.external_loads):
            need(f"external_loads[{i}].node", e.node, "drive_load")
        for k, entry in self.calibration.items():
            if k.split(".")[0] not in role:
                raise Invalid(f"calibration.{k}", entry.model_dump(exclude_unset=True),
                              f"no node named {k.split('.')[0]!r}",
                              'use keys "<node>.<channel>", e.g. "cell_A.force"')


# -- errors in the file's words -------------------------------------------------------------

MISSING = object()  # the value of a key that is missing (ConfigError prints no value)


def _key(loc: tuple[str | int, ...]) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _join(loc_key: str, rel: str) -> str:
    if not rel:
        return loc_key
    if rel.startswith("[") or not loc_key:
        return loc_key + rel
    return f"{loc_key}.{rel}"


def _item(annotation: Any) -> Any:
    """The model or element type inside ``list[...]``, ``dict[str, ...]``, ``X | None``,
    ``Annotated[...]``."""
    while get_origin(annotation) is Annotated:
        annotation = get_args(annotation)[0]
    args = [a for a in get_args(annotation) if a is not type(None)]
    if get_origin(annotation) in (list, dict) and args:
        return args[-1]
    if len(args) == 1:  # X | None
        return args[0]
    return annotation


def _model(tp: Any) -> type[BaseModel] | None:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    args = [a for a in get_args(tp) if a is not type(None)]
    if len(args) == 1 and get_origin(tp) not in (list, dict):
        tp = args[0]
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def _field_at(loc: tuple[str | int, ...]) -> tuple[FieldInfo | None, type[BaseModel] | None, Any]:
    """The field a location names (the last named one, for an element), the model holding
    it, and the type at the location."""
    model: type[BaseModel] | None = RigFile
    fi: FieldInfo | None = None
    holder: type[BaseModel] | None = None
    tp: Any = RigFile
    for p in loc:
        if isinstance(p, str) and model is not None and p in model.model_fields:
            holder, fi = model, model.model_fields[p]
            tp = fi.annotation
        elif isinstance(p, str) and get_origin(_strip(tp)) is dict:
            tp = _item(tp)
        elif isinstance(p, int):
            tp = _item(tp)
        else:
            return fi, model, None  # past the schema (an unknown key)
        model = _model(tp)
    return fi, holder, tp


def _strip(tp: Any) -> Any:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    return tp


def _extra(fi: FieldInfo | None, what: str) -> str:
    e = fi.json_schema_extra if fi is not None and isinstance(fi.json_schema_extra, dict) else {}
    return str(e.get(what, ""))


@dataclass(frozen=True)
class _Error:
    """A pydantic error located in the schema: what the messages below are made of."""

    loc: tuple[str | int, ...]
    key: str  # dotted, as the file writes it
    value: Any
    ctx: dict[str, Any]
    tp: Any  # the type at the location
    unit: str  # of a vector's numbers (the field's metadata)
    own_fix: str  # the field's own fix, if it has one

    @property
    def name(self) -> str:
        """The last named key of the location."""
        return next((p for p in reversed(self.loc) if isinstance(p, str)), self.key)

    @property
    def element(self) -> bool:
        """The location is an element of an array."""
        return bool(self.loc) and isinstance(self.loc[-1], int)

    def says(self, problem: str, fix: str) -> tuple[str, Any, str, str]:
        return self.key, self.value, problem, fix


def _missing(e: _Error) -> tuple[str, Any, str, str]:
    loc, key = e.loc, e.key
    if len(loc) == 1:  # a whole table (only a rig given whole, not as layers, lacks one)
        blocks = _model(_item(e.tp)) is not None and get_origin(_strip(e.tp)) is list
        return key, MISSING, "is missing", f"add [[{key}]] blocks" if blocks else \
            f"add a [{key}] table, or give only what differs from the packaged rig"
    where = f"this [[{_key(loc[:-2])}]] block" if isinstance(loc[-2], int) \
        else f"[{_key(loc[:-1])}]"
    return key, MISSING, "is missing", f"add {e.name} = … to {where}"


def _not_a_table(e: _Error) -> tuple[str, Any, str, str]:
    if e.element:
        return e.says("must be a table", f"write it as a [[{_key(e.loc[:-1])}]] block")
    return e.says("must be a table", f"write [{e.key}] as a TOML table")


def _not_a_list(e: _Error) -> tuple[str, Any, str, str]:
    if _model(_item(e.tp)) is not None:
        return e.says("must be an array of tables", f"write [[{e.key}]] blocks")
    if _strip(_item(e.tp)) is str:
        return e.says("must be a list of strings", e.own_fix or f'write {e.name} = ["…"]')
    return e.says("must be a list of numbers", f"write {e.name} = [x, y, …]{e.unit}")


def _not_a_number(e: _Error) -> tuple[str, Any, str, str]:
    if e.element:
        return e.says("must be finite" if e.ctx.get("typ") == "finite_number"
                      else "must be a finite number", "replace it with a finite number")
    return e.says("must be a finite number", e.own_fix or f"set {e.name} to a finite number")


def _not_positive(e: _Error) -> tuple[str, Any, str, str]:
    fix = f"give a positive value{e.unit}" if e.element else f"set {e.name} to a positive value"
    return e.says("must be > 0", e.own_fix or fix)


def _length(e: _Error) -> tuple[str, Any, str, str]:
    n = e.ctx.get("min_length") if e.ctx.get("typ") == "too_short" else e.ctx.get("max_length")
    return e.says(f"must have {n} values, has {e.ctx.get('actual_length')}",
                  f"give {n} numbers{e.unit}")


def _unknown_value(e: _Error) -> tuple[str, Any, str, str]:
    choices = re.findall(r"'([^']*)'", str(e.ctx.get("expected", "")))
    near = difflib.get_close_matches(str(e.value), choices, n=1) \
        if isinstance(e.value, str) else []
    hint = f' (did you mean "{near[0]}"?)' if near else ""
    return e.says(f"unknown value{hint}", "use one of " + ", ".join(f'"{c}"' for c in choices))


# pydantic's error type -> the line in the file's words
_DESCRIBE: dict[str, Callable[[_Error], tuple[str, Any, str, str]]] = {
    "missing": _missing,
    "model_type": _not_a_table, "model_attributes_type": _not_a_table, "dict_type": _not_a_table,
    "list_type": _not_a_list,
    "float_type": _not_a_number, "finite_number": _not_a_number, "float_parsing": _not_a_number,
    "int_type": lambda e: e.says("must be a whole number",
                                 e.own_fix or f"set {e.name} to a whole number"),
    "greater_than": _not_positive,
    "greater_than_equal": lambda e: e.says("must be >= 0",
                                           e.own_fix or f"set {e.name} to zero or more"),
    "too_short": _length, "too_long": _length,
    "string_type": lambda e: e.says("must be a string", e.own_fix or f'write {e.name} = "…"'),
    "bool_type": lambda e: e.says("must be true or false", f"write {e.name} = true or false"),
    "literal_error": _unknown_value,
}
_DESCRIBE["int_from_float"] = _DESCRIBE["int_parsing"] = _DESCRIBE["int_type"]


def _unknown_key(loc: tuple[str | int, ...], key: str, value: Any) -> tuple[str, Any, str, str]:
    parent = _model(_field_at(loc[:-1])[2]) if loc[:-1] else RigFile
    near = difflib.get_close_matches(str(loc[-1]), sorted(parent.model_fields), n=1) \
        if parent is not None else []
    return key, value, "unknown key", f'rename it to "{near[0]}"' if near else "remove it"


def describe(err: ErrorDetails) -> tuple[str, Any, str, str]:
    """One pydantic error → (dotted key, value, problem, fix)."""
    loc, typ, ctx, value = tuple(err["loc"]), err["type"], err.get("ctx") or {}, err["input"]
    key = _key(loc)
    error = ctx.get("error")
    if isinstance(error, Invalid):
        return _join(key, error.key), error.value, error.problem, error.fix
    if typ == "extra_forbidden":
        return _unknown_key(loc, key, value)
    fi, _, tp = _field_at(loc)
    e = _Error(loc, key, value, {**ctx, "typ": typ}, tp, _extra(fi, "unit"), _extra(fi, "fix"))
    handler = _DESCRIBE.get(typ)
    if handler is not None:
        return handler(e)
    return key, value, err["msg"][0].lower() + err["msg"][1:], \
        ctx.get("fix") or e.own_fix or "see docs/configuration.md for this key"


def validate(raw: dict[str, Any], base_dir: Path, packaged_dir: Path | None = None
             ) -> RigFile | tuple[str, Any, str, str]:
    """The validated file, or its first error as (key, value, problem, fix)."""
    try:
        return RigFile.model_validate(raw, context={"base_dir": base_dir,
                                                    "packaged_dir": packaged_dir})
    except ValidationError as e:
        return describe(e.errors(include_url=False)[0])


def schema_keys() -> set[tuple[str, str]]:
    """(table, key) of every key the schema knows (an inner table's keys count under its
    top table; ``[calibration]``'s entries as ``"<node>.<channel>"``)."""
    out: set[tuple[str, str]] = set()

    def walk(model: type[BaseModel], table: str) -> None:
        for name, fi in model.model_fields.items():
            out.add((table, name))
            inner = _model(fi.annotation) or _model(_item(fi.annotation))
            if inner is not None:
                walk(inner, table)

    for table, fi in RigFile.model_fields.items():
        inner = _model(fi.annotation) or _model(_item(fi.annotation))
        assert inner is not None, table
        if table == "calibration":
            out.add((table, '"<node>.<channel>"'))
        walk(inner, table)
    return out
