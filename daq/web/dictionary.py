"""The Open MCT telemetry dictionary of a rig, its limits, and telemetry payloads as points.

Pure: no I/O. One *measurement* is one Open MCT telemetry object (one series): an id such as
``hub.H.Z``, a name, a unit, a format, the Zenoh key it comes from, and optional limit lines.
:func:`points` turns one telemetry payload (docs/telemetry.md) into ``(id, datum)`` pairs;
a datum is ``{"utc": ms, "value": …, …}`` and carries ``"lim"`` (``"yellow"``/``"red"``) when
it is outside its limits, so the browser only maps that to Open MCT's limit classes.

Limits, from what rsra knows (docs/cli.md §15):

* hub loads: the static estimate against the filter estimate, per axis, in units of the
  static-estimate noise σ of the noise budget (model §4): yellow beyond the two-sided 10⁻³
  quantile of a normal variable (3.29 σ), red beyond 10⁻⁶ (4.89 σ); the band
  ``H ± 3.29 σ`` is drawn as two series (``hub.upper.*``, ``hub.lower.*``); the σ of the
  hub-load error due to the angles in force (``hub.angles.*``, ``sigma_angles``) yellow
  beyond that static σ (the flag ``angles_uncertain``);
* NIS: the χ² band with 6 degrees of freedom — yellow outside the two-sided 10⁻³ band,
  red above the 10⁻⁶ upper quantile (absolute limit lines in the plot);
* node states: ``operational`` fine, ``booting``/``pre-operational``/``stopped`` yellow,
  ``missing``/``lost``/``error`` red (an optional node never heard: no limit); flags and cell status bytes: faults red, the rest yellow;
* identification verdicts: accepted fine, ``inconsistent``/``reset``/``diverged``/
  ``out_of_range`` red, other rejections yellow; health counters of errors and losses
  yellow (red for bus-off) once non-zero.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from scipy.stats import chi2, norm

from rsra.estimator.verdict import held_window

AXES = ("X", "Y", "Z", "L", "M", "N")
AXIS_UNITS = ("N", "N", "N", "N·m", "N·m", "N·m")
AXIS_NAMES = ("X force", "Y force", "Z force", "L moment", "M moment", "N moment")
ACC_AXES = ("x", "y", "z")

FALSE_ALARM_YELLOW = 1e-3  # per sample, two-sided
FALSE_ALARM_RED = 1e-6
Z_YELLOW = float(norm.isf(FALSE_ALARM_YELLOW / 2))  # 3.29
Z_RED = float(norm.isf(FALSE_ALARM_RED / 2))  # 4.89
NIS_DOF = 6
NIS_YELLOW = (float(chi2.ppf(FALSE_ALARM_YELLOW / 2, NIS_DOF)),
              float(chi2.isf(FALSE_ALARM_YELLOW / 2, NIS_DOF)))
NIS_RED_HIGH = float(chi2.isf(FALSE_ALARM_RED, NIS_DOF))

NODE_STATE_LIMIT = {"operational": None, "booting": "yellow", "pre-operational": "yellow",
                    "stopped": "yellow", "missing": "red", "lost": "red", "error": "red"}
VERDICT_RED = ("inconsistent", "reset", "diverged", "out_of_range")
# health counters shown: (path in the health record, name, unit, limit once non-zero)
COUNTERS = (
    ("bus.frames", "bus frames", "", None),
    ("bus.errors", "bus error frames", "", "yellow"),
    ("bus.bus_off", "bus-off events", "", "red"),
    ("bus.malformed", "malformed frames", "", "yellow"),
    ("samples.complete", "complete samples", "", None),
    ("samples.incomplete", "incomplete samples", "", "yellow"),
    ("samples.lost", "lost samples", "", "yellow"),
    ("queues.samples.dropped", "samples dropped (queue)", "", "yellow"),
    ("queues.identification.dropped", "identification windows dropped", "", None),
    ("identification.deaths", "identification process deaths", "", "yellow"),
    ("sync.rate_hz", "sample rate", "Hz", None),
    ("latency_ms.p99", "latency p99", "ms", None),
)


@dataclass
class Measurement:
    id: str
    name: str
    group: str
    source: str  # the Zenoh key under the prefix
    unit: str = ""
    format: str = "float"  # "float", "integer" or "string"
    extra: tuple[tuple[str, str, str], ...] = ()  # (key, name, unit) more values of a datum
    limits: dict[str, Any] | None = None  # absolute limit lines (Open MCT getLimits)
    value_name: str = ""  # the value's column name where it differs from the name
    decimals: int = 1  # digits after the point Open MCT shows ("float")
    # a plotted series' line breaks where no point came for longer than this (ms; a stopped
    # or restarted service); None: never (tables, strings, low-rate keys)
    gap_ms: float | None = None
    # shown in thousands (kN, kN·m: values stay SI in the points): the hub loads, whose tick
    # numbers of five digits ran into the plots' axis labels
    kilo: bool = False

    def as_json(self) -> dict:
        d = {"id": self.id, "name": self.name, "group": self.group, "source": self.source,
             "unit": self.unit, "format": self.format,
             "value_name": self.value_name or self.name, "decimals": self.decimals,
             "extra": [{"key": k, "name": n, "unit": u} for k, n, u in self.extra]}
        if self.limits is not None:
            d["limits"] = self.limits
        if self.gap_ms is not None:
            d["gap_ms"] = self.gap_ms
        if self.kilo:
            d["kilo"] = True
        return d


@dataclass
class Dictionary:
    rig: str
    prefix: str
    frame: str
    measurements: list[Measurement]
    sigma_static: list[float]  # per axis, SI
    cells: tuple[str, ...]
    accelerometers: tuple[str, ...]
    nodes: tuple[str, ...]
    angles: tuple[str, ...]
    #: whose telemetry it is, in words (the service's rig, host, process and start; or why
    #: none is named): the page's title says it
    source: str = ""
    by_id: dict[str, Measurement] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.by_id = {m.id: m for m in self.measurements}

    def as_json(self) -> dict:
        return {"rig": self.rig, "prefix": self.prefix, "source": self.source,
                "frame": self.frame,
                "sigma_static": self.sigma_static, "z_yellow": Z_YELLOW, "z_red": Z_RED,
                "nis_band": list(NIS_YELLOW), "nis_red": NIS_RED_HIGH,
                "cells": list(self.cells), "accelerometers": list(self.accelerometers),
                "nodes": list(self.nodes), "angles": list(self.angles),
                "measurements": [m.as_json() for m in self.measurements]}


def build_dictionary(cfg, prefix: str | None = None, source: str = "") -> Dictionary:
    """The dictionary of a rig config (:class:`rsra.config.rig.RigConfig`); ``source``: whose
    telemetry the page shows, in words."""
    from rsra.estimator.noise_budget import noise_budget

    model = cfg.rig_model()
    sigma = [float(s) for s in noise_budget(model, cfg.identification.initial_angles_rad).total]
    cells = tuple(c.name for c in cfg.cells)
    accs = tuple(a.name for a in cfg.accelerometers)
    nodes = tuple(n.name for n in cfg.nodes)
    angles = tuple(model.geometry.angle_names)
    ms: list[Measurement] = []
    for i, ax in enumerate(AXES):
        u = AXIS_UNITS[i]
        ms.append(Measurement(f"hub.H.{ax}", f"{ax} filter", "Hub loads", "hub_loads", u))
        ms.append(Measurement(f"hub.static.{ax}", f"{ax} static", "Hub loads", "hub_loads", u,
                              extra=(("ref", "filter", u), ("dev", "deviation", "σ"))))
        ms.append(Measurement(f"hub.upper.{ax}", f"{ax} band +{Z_YELLOW:.2f}σ", "Hub loads",
                              "hub_loads", u))
        ms.append(Measurement(f"hub.lower.{ax}", f"{ax} band −{Z_YELLOW:.2f}σ", "Hub loads",
                              "hub_loads", u))
        ms.append(Measurement(f"hub.angles.{ax}", f"{ax} σ from the angles", "Hub loads",
                              "hub_loads", u))
    ms.append(Measurement("hub.omega", "rotor speed", "Hub loads", "hub_loads", "rad/s"))
    ms.append(Measurement("hub.flags", "sample flags", "Hub loads", "hub_loads", "",
                          format="string"))
    for c in cells:
        ms.append(Measurement(f"cell.{c}", f"cell {c} force", "Load cells", "channels", "N",
                              extra=(("status", "status byte", ""),)))
    for a in accs:
        for ax in ACC_AXES:
            ms.append(Measurement(f"accel.{a}.{ax}", f"{a} {ax}", "Accelerations", "channels",
                                  "m/s²"))
    ms.append(Measurement("nis", "NIS (χ², 6 dof)", "Innovations", "innovations", "",
                          limits={"yellow": list(NIS_YELLOW), "red": [None, NIS_RED_HIGH]},
                          gap_ms=gap_ms(cfg.telemetry.innovations_hz)))
    for n in angles:
        # three decimals: an identified angle's σ is a few hundredths of a degree (0.05°), so
        # 0.1° would hide what the estimate knows
        ms.append(Measurement(f"angle.{n}", n, "Angles", "angles", "deg", value_name="angle",
                              decimals=3,
                              extra=(("sigma", "σ", "deg"), ("lo", "−1σ", "deg"),
                                     ("hi", "+1σ", "deg"))))
    ms.append(Measurement("ident.verdict", "identification verdict", "Identification", "angles",
                          format="string", extra=(("detail", "decided by", ""),
                                                  ("mode", "mode", ""),
                                                  ("content", "content", ""))))
    # named as the log's calibration line and `rsra angles show` name it (the posterior's);
    # the advice says what one window determines
    ms.append(Measurement("ident.determined",
                          f"directions determined (posterior, of {len(angles)})", "Identification",
                          "angles", format="integer"))
    ms.append(Measurement("ident.advice", "what would determine the rest", "Identification",
                          "angles", format="string"))
    for n in nodes:
        ms.append(Measurement(f"node.{n}", f"{n} state", "Nodes", "health", format="string",
                              value_name="state",
                              extra=(("boots", "boots", ""), ("losses", "losses", ""),
                                     ("emcy", "EMCY count", ""))))
    for path, name, unit, _ in COUNTERS:
        fmt = "float" if unit else "integer"
        ms.append(Measurement(f"health.{path}", name, "Health", "health", unit, format=fmt))
    plotted = ("hub.H.", "hub.static.", "hub.upper.", "hub.lower.", "hub.angles.", "cell.",
               "accel.")
    for m in ms:
        if m.id.startswith(plotted):
            m.gap_ms = gap_ms(cfg.sample_rate_hz)
        m.kilo = m.group == "Hub loads" and m.unit in ("N", "N·m")
    return Dictionary(cfg.rig_name, prefix or cfg.telemetry.prefix, cfg.hub_frame, ms, sigma,
                      cells, accs, nodes, angles, source)


GAP_MIN_S = 1.0  # a break in a plotted line: at least this long without a point
# The band lines are drawn as their envelope over this much time (a rotor revolution or more):
# over the real-time window's two minutes the per-sample band lines (H ± 3.29 σ, which swing
# with H's 1/rev loads) merged with the estimate into one block
BAND_CHUNK_MS = 500.0
BAND_SIDES = {"hub.upper.": 1, "hub.lower.": -1}


def band_side(pid: str) -> int:
    """+1 for an upper band line, −1 for a lower one, 0 for any other series."""
    return BAND_SIDES.get(pid[:len("hub.upper.")], 0)


class BandEnvelope:
    """The band lines (``hub.upper.*``, ``hub.lower.*``) as their envelope: in each chunk of
    BAND_CHUNK_MS the point furthest out, so every sample's H ± 3.29 σ lies between the two
    lines and the estimate shows between them over minutes. A chunk's point is given when
    the next chunk starts (one chunk late); bounded: one open chunk per band series."""

    def __init__(self, chunk_ms: float = BAND_CHUNK_MS) -> None:
        self.chunk_ms = chunk_ms
        #: per band series: its open chunk's number and the point furthest out in it
        self.open: dict[str, tuple[int, dict]] = {}

    def add(self, pid: str, d: dict) -> dict | None:
        """Take one band point; returns the finished chunk's point when ``d`` starts another
        (a point with no finite time is in no chunk: returned as it is)."""
        utc = d["utc"]
        if not (isinstance(utc, int | float) and math.isfinite(utc)):
            return d
        c = math.floor(utc / self.chunk_ms)
        cur = self.open.get(pid)
        if cur is not None and cur[0] == c:
            if band_side(pid) * (d["value"] - cur[1]["value"]) > 0:
                self.open[pid] = (c, d)
            return None
        self.open[pid] = (c, d)
        return None if cur is None else cur[1]

    def reduce(self, pts: list[tuple[str, dict]]) -> list[tuple[str, dict]]:
        """Live points with the band lines' replaced by their envelope's."""
        out = []
        for pid, d in pts:
            if not band_side(pid):
                out.append((pid, d))
            elif (done := self.add(pid, d)) is not None:
                out.append((pid, done))
        return out


def envelope(pid: str, data: list[dict], chunk_ms: float = BAND_CHUNK_MS) -> list[dict]:
    """A history answer (in time order) of series ``pid``: a band line's envelope, any other
    series unchanged."""
    if not band_side(pid):
        return data
    env = BandEnvelope(chunk_ms)
    out = [done for d in data if (done := env.add(pid, d)) is not None]
    if pid in env.open:
        out.append(env.open[pid][1])
    return out


def gap_ms(rate_hz: float) -> float:
    """The longest time between two points of a series at ``rate_hz`` that a plot still joins
    by a line: ten periods, at least GAP_MIN_S (a few lost samples stay one line; a stopped
    or restarted service, or a filter without valid estimates, leaves a gap)."""
    return 1000.0 * max(GAP_MIN_S, 10.0 / rate_hz)


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _get(d: Any, path: str) -> Any:
    for p in path.split("."):
        if not isinstance(d, dict):
            return None
        d = d.get(p)
    return d


def _idx(v: Any, i: int) -> Any:
    return v[i] if isinstance(v, list) and i < len(v) else None


def static_limit(dev_sigma: float) -> str | None:
    a = abs(dev_sigma)
    return "red" if a > Z_RED else "yellow" if a > Z_YELLOW else None


def nis_limit(nis: float) -> str | None:
    if nis > NIS_RED_HIGH:
        return "red"
    return "yellow" if not NIS_YELLOW[0] <= nis <= NIS_YELLOW[1] else None


def flags_limit(flags: list[str]) -> str | None:
    red = any(f == "invalid" or f.startswith(("missing:", "fault:", "overrange:"))
              for f in flags)
    return "red" if red else "yellow" if flags else None


def verdict_limit(accepted: Any, reason: Any) -> str | None:
    if accepted:
        return None
    return "red" if reason in VERDICT_RED else "yellow"


def node_limit(state: Any, required: Any = True) -> str | None:
    """An optional node never heard is normal (no limit); other states by the table."""
    if state == "missing" and required is False:
        return None
    return NODE_STATE_LIMIT.get(state, "yellow")


def status_limit(status: Any) -> str | None:
    if not isinstance(status, int) or isinstance(status, bool):
        return None
    return "red" if status & 0b11 else None


def _datum(utc: float, value: Any, lim: str | None = None, **extra) -> dict:
    d = {"utc": utc, "value": value, **extra}
    if lim:
        d["lim"] = lim
    return d


def points(dic: Dictionary, key: str, p: dict) -> list[tuple[str, dict]]:
    """The Open MCT points of one telemetry payload of ``key`` (the key under the prefix);
    missing or null values give no point."""
    t = _num(p.get("t")) if isinstance(p, dict) else None
    if t is None:
        return []
    utc = round(t * 1000.0, 3)
    out: list[tuple[str, dict]] = []
    if key == "hub_loads":
        H, S = p.get("H"), p.get("H_static")
        for i, ax in enumerate(AXES):
            h, s, sig = _num(_idx(H, i)), _num(_idx(S, i)), dic.sigma_static[i]
            if h is not None:
                out.append((f"hub.H.{ax}", _datum(utc, h)))
                out.append((f"hub.upper.{ax}", _datum(utc, h + Z_YELLOW * sig)))
                out.append((f"hub.lower.{ax}", _datum(utc, h - Z_YELLOW * sig)))
            if s is not None:
                dev = None if h is None or sig <= 0 else (s - h) / sig
                out.append((f"hub.static.{ax}", _datum(
                    utc, s, None if dev is None else static_limit(dev), ref=h,
                    dev=None if dev is None else round(dev, 3))))
            a = _num(_idx(p.get("sigma_angles"), i))
            if a is not None:  # yellow where the flag angles_uncertain says so
                out.append((f"hub.angles.{ax}", _datum(utc, a, "yellow" if a > sig else None)))
        om = _num(p.get("omega"))
        if om is not None:
            out.append(("hub.omega", _datum(utc, om)))
        flags = [f for f in (p.get("flags") or []) if isinstance(f, str)]
        out.append(("hub.flags", _datum(utc, ", ".join(flags) or "none", flags_limit(flags))))
    elif key == "channels":
        T, status = p.get("T"), p.get("status") or {}
        for i, c in enumerate(dic.cells):
            v = _num(_idx(T, i))
            if v is not None:
                st = status.get(c) if isinstance(status, dict) else None
                out.append((f"cell.{c}", _datum(utc, v, status_limit(st), status=st)))
        acc = p.get("accel")
        for i, aname in enumerate(dic.accelerometers):
            vec = _idx(acc, i)
            for j, ax in enumerate(ACC_AXES):
                v = _num(_idx(vec, j))
                if v is not None:
                    out.append((f"accel.{aname}.{ax}", _datum(utc, v)))
    elif key == "innovations":
        v = _num(p.get("nis"))
        if v is not None:
            out.append(("nis", _datum(utc, v, nis_limit(v))))
    elif key == "angles":
        names, alpha, P = p.get("names") or [], p.get("alpha") or [], p.get("P")
        for i, n in enumerate(names):
            a = _num(_idx(alpha, i))
            if a is None or f"angle.{n}" not in dic.by_id:
                continue
            var = _num(_idx(_idx(P, i), i))
            deg = math.degrees(a)
            sig_deg = math.degrees(math.sqrt(var)) if var is not None and var >= 0 else None
            out.append((f"angle.{n}", _datum(
                utc, deg, sigma=sig_deg, lo=None if sig_deg is None else deg - sig_deg,
                hi=None if sig_deg is None else deg + sig_deg)))
        acc, reason = p.get("accepted"), p.get("reason")
        held = not acc and held_window(p)  # its information kept for the next runs
        out.append(("ident.verdict", _datum(
            utc, "accepted" if acc else "held" if held
            else f"rejected: {reason}", None if held else verdict_limit(acc, reason),
            detail=p.get("detail"), mode=p.get("mode"), content=p.get("content"))))
        det = p.get("determined")
        if isinstance(det, int) and not isinstance(det, bool):
            out.append(("ident.determined", _datum(utc, det)))
        from rsra.estimator.flight_advice import advice_summary

        adv = advice_summary(p.get("advice"))  # filter error: what would determine the rest
        if adv:
            out.append(("ident.advice", _datum(utc, adv)))
    elif key == "health":
        nodes = p.get("nodes") or {}
        for n in dic.nodes:
            nd = nodes.get(n) if isinstance(nodes, dict) else None
            if not isinstance(nd, dict):
                continue
            st = nd.get("state")
            out.append((f"node.{n}", _datum(
                utc, str(st), node_limit(st, nd.get("required")), boots=nd.get("boots"),
                losses=nd.get("losses"), emcy=nd.get("emcy_count"))))
        for path, _, _, lim in COUNTERS:
            v = _num(_get(p, path))
            if v is not None:
                out.append((f"health.{path}", _datum(utc, v, lim if v > 0 else None)))
    return out
