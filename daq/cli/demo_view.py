"""The live terminal view of `rsra demo`: hub loads against the simulator's truth, the angles
converging with their Cramér–Rao bounds, every identification run's verdict, bus and node
health, sample rate, latency and lost samples. Fed by the service's in-process sink (the
same records Zenoh subscribers get), so it costs the estimator nothing but a dict copy."""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from rsra.config.units import axis_units, to_units
from rsra.estimator.verdict import held_window

if TYPE_CHECKING:
    from rich.console import RenderableType

AXES = ("X", "Y", "Z", "L", "M", "N")
SETTLE_S = 1.0  # the filtered H is scored once the filter has settled from its zero start


class DemoState:
    """The latest records, updated from the service thread, read by the view thread."""

    def __init__(self, cfg, static_bound: np.ndarray, angle_names: tuple[str, ...]):
        from rsra.daq.analysis.accuracy import PhaseAccuracy

        self.cfg = cfg
        self.lock = threading.Lock()
        self.hub: dict | None = None
        self.health: dict | None = None
        self.angles: dict | None = None
        self.runs: deque[dict] = deque(maxlen=6)
        self.truth_H: np.ndarray | None = None
        self.truth_alpha: np.ndarray | None = None
        self.static_bound = static_bound
        self.angle_names = angle_names
        self.samples = 0
        self.first_t: float | None = None
        self.wall0 = time.monotonic()
        # the error against truth by phase (daq.analysis.accuracy: before the first accepted
        # calibration, transient, calibrated steady state), each sample against the σ its
        # hub_loads record published
        self.calibrated = False
        self.acc = {"H": PhaseAccuracy(), "H_static": PhaseAccuracy()}
        self.sigma_H: np.ndarray | None = None  # the latest record's published σ of H
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        self.flags: dict[str, int] = {}
        self.rate_marks: deque[tuple[float, int]] = deque(maxlen=40)  # (wall, samples)

    def on_record(self, key: str, payload: dict, truth=None) -> None:
        handler = self._HANDLERS.get(key)
        if handler is not None:
            with self.lock:
                handler(self, payload, truth)

    def _on_hub_loads(self, payload: dict, truth) -> None:
        from rsra.daq.analysis.accuracy import published_sigma, starts_calibrated

        self.hub = payload
        self.samples += 1
        if self.first_t is None:
            self.first_t = payload["t"]
        flags = payload.get("flags") or []
        if self.samples == 1 and starts_calibrated(flags):
            self.calibrated = True  # a saved posterior: no start phase
        for f in flags:
            self.flags[f] = self.flags.get(f, 0) + 1
        self.sigma_H = (None if payload.get("H") is None
                        else published_sigma(payload, self.static_bound, "H"))
        if truth is not None:
            self._score(payload, flags, truth, payload["t"] - self.first_t > SETTLE_S)

    def _score(self, payload: dict, flags: list, truth, settled: bool) -> None:
        """The record's H (once the filter has settled) and static H against the truth, in
        the phase the run is in."""
        from rsra.daq.analysis.accuracy import phase_of, published_sigma

        self.truth_H = np.asarray(truth.H_true, float)
        self.truth_alpha = np.asarray(truth.alpha_true, float)
        phase = phase_of(self.calibrated, flags)
        H, Hs = payload.get("H"), payload.get("H_static")
        if H is not None and self.sigma_H is not None and settled:
            self.acc["H"].add(phase, np.asarray(H, float) - self.truth_H, self.sigma_H)
        if Hs is not None:
            self.acc["H_static"].add(phase, np.asarray(Hs, float) - self.truth_H,
                                     published_sigma(payload, self.static_bound, "H_static"))

    def _on_health(self, payload: dict, truth) -> None:
        self.health = payload

    def _on_angles(self, payload: dict, truth) -> None:
        self.angles = payload
        self.runs.append(payload)
        if payload.get("accepted"):
            self.accepted += 1
            self.calibrated = True  # (published at the sample it applies from)
        else:
            r = str(payload.get("reason"))
            self.rejected[r] = self.rejected.get(r, 0) + 1

    _HANDLERS = {"hub_loads": _on_hub_loads, "health": _on_health, "angles": _on_angles}

    def by_phase(self) -> dict:
        """{"H": …, "H_static": …}: PhaseAccuracy.summary() of each (call under the lock)."""
        return {k: a.summary() for k, a in self.acc.items()}


PHASE_WORDS = {"start": "uncalibrated angles", "transient": "ramps, manoeuvres",
               "steady": "calibrated: the claim"}


def phase_line(by_phase: dict) -> str:
    """The filtered H per phase: worst axis RMS error/σ, fraction beyond 3σ, samples, and
    what the phase is — one line each."""
    from rsra.daq.analysis.accuracy import PHASES

    rows = []
    for p in PHASES:
        v = (by_phase.get("H") or {}).get(p)
        if v:
            rows.append(f"  {p:9s} {max(v['rms_over_sigma']):5.2f} "
                        f"{100 * max(v['beyond_3sigma']):5.1f} % {v['samples']:>7d}  "
                        f"{PHASE_WORDS[p]}")
    return "Ĥ vs published σ: worst-axis err/σ, beyond 3σ, samples" + (
        "\n" + "\n".join(rows) if rows else ": —")


def _f(x, fmt="{:9.1f}") -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def sync_text(health: dict | None) -> str:
    """The health ``sync`` section in one line (demo view, ``rsra listen``): sample slots
    never taken (late SYNCs), duplicated SYNCs, bad timestamps, the measured sample rate and
    its flag below 99 % of the configured rate."""
    sy = (health or {}).get("sync")
    if not sy:
        return "—"  # a service without the section
    parts = []
    if "periods_not_taken" in sy:
        parts.append(f"not taken {sy['periods_not_taken']} (late SYNCs {sy.get('late')})")
    parts.append(f"duplicate SYNCs {sy.get('duplicate', 0)}  bad timestamps "
                 f"{sy.get('bad_timestamp', 0)}")
    rate = sy.get("rate_hz")
    if rate is not None:
        parts.append(f"rate {rate:.1f}/s" + ("  RATE LOW (< 99 %)" if sy.get("rate_low") else ""))
    return "  ".join(parts)


@dataclass(frozen=True)
class View:
    """What one frame of the view shows: the state's records copied under its lock."""

    hub: dict | None
    health: dict | None
    angles: dict | None
    runs: list[dict]
    truth_H: np.ndarray | None
    truth_alpha: np.ndarray | None
    sigma_H: np.ndarray | None
    samples: int
    first_t: float | None
    by_phase: dict
    accepted: int
    rejected: dict[str, int]

    @classmethod
    def of(cls, state: DemoState) -> "View":
        with state.lock:
            return cls(state.hub, state.health, state.angles, list(state.runs),
                       _copy(state.truth_H), _copy(state.truth_alpha), _copy(state.sigma_H),
                       state.samples, state.first_t, state.by_phase(), state.accepted,
                       dict(state.rejected))

    @property
    def acquisition_s(self) -> float:
        return 0.0 if self.hub is None or self.first_t is None else self.hub["t"] - self.first_t

    def section(self, name: str) -> dict:
        """A section of the latest health record ({} before one)."""
        return (self.health or {}).get(name) or {}

    def hub_value(self, name: str) -> Any:
        return (self.hub or {}).get(name)

    def hub_columns(self, units: str) -> tuple[Any, ...]:
        """Per axis, in ``units``: the truth, Ĥ, the static Ĥ, the published σ of Ĥ, and the
        steady state's RMS error/σ and percent beyond 3σ (None: not known yet)."""
        st = (self.by_phase.get("H") or {}).get("steady")
        return (_conv(self.truth_H, units), _conv(self.hub_value("H"), units),
                _conv(self.hub_value("H_static"), units), _conv(self.sigma_H, units),
                None if st is None else st["rms_over_sigma"],
                None if st is None else [100 * x for x in st["beyond_3sigma"]])


def _copy(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else a.copy()


def _at(v: Any, i: int) -> Any:
    return None if v is None else v[i]


def _conv(v: Any, units: str) -> np.ndarray | None:
    return None if v is None else to_units(np.asarray(v, float), units)


def _rate(state: DemoState, n: int) -> float:
    """Samples per second over the last marks of the view's refreshes."""
    now = time.monotonic()
    state.rate_marks.append((now, n))
    w0, n0 = state.rate_marks[0]
    return (n - n0) / (now - w0) if now > w0 else 0.0


def _latency(lat: dict) -> str:
    if lat.get("p50") is None:
        return "latency n/a (lock-step)"
    return f"latency p50 {lat['p50']:.2f} ms  p99 {_f(lat.get('p99'), '{:.2f}')} ms"


def _head(v: View, rate: float, title: str):
    from rich.text import Text

    nt = v.section("sync").get("periods_not_taken")
    return Text.assemble(
        (f"{title}  ", "bold"),
        f"acquisition {v.acquisition_s:7.1f} s   {rate:6.0f} samples/s   lost "
        f"{v.section('samples').get('lost', 0)}   "
        + (f"not taken {nt}   " if nt is not None else "")
        + _latency(v.section("latency_ms")))


def _hub_table(v: View, units: str):
    from rich.table import Table

    u = axis_units(units)
    t = Table(title="hub loads (" + (v.hub or {}).get("frame", "body") + " axes); err/σ, >3σ: "
              "steady state", expand=False)
    for c in ("axis", "truth", "Ĥ", "static", "σ Ĥ", "err/σ", ">3σ"):
        t.add_column(c, justify="left" if c == "axis" else "right", no_wrap=True,
                     min_width=7 if c == "axis" else 5 if c in ("err/σ", ">3σ") else 8)
    cols = v.hub_columns(units)
    fmts = ("{:8.0f}",) * 4 + ("{:.2f}", "{:.1f}%")
    for i, ax in enumerate(AXES):
        t.add_row(f"{ax} [{u[i]}]", *(_f(_at(c, i), f) for c, f in zip(cols, fmts)))
    return t


def _flag_text(v: View):
    from rich.text import Text

    flags = v.hub_value("flags") or []
    return Text("flags: " + (", ".join(flags) if flags else "none") + "\n"
                + phase_line(v.by_phase))


def _angle_row(state: DemoState, v: View, ang: dict, i: int, name: str) -> tuple[str, ...]:
    """One angle: the simulator's truth, the estimate, its σ (green once within
    identification.sigma_max) and the error in σ."""
    a = math.degrees(ang["alpha"][i])
    P = ang.get("P")
    s = math.degrees(math.sqrt(max(P[i][i], 0.0))) if P else float("nan")
    ta = v.truth_alpha
    tru = (None if ta is None or name not in state.angle_names
           else math.degrees(ta[state.angle_names.index(name)]))
    z = None if tru is None or not s > 0 else (a - tru) / s
    smax = math.degrees(state.cfg.identification.sigma_max_rad)
    return (name, _f(tru, "{:7.3f}"), f"{a:7.3f}",
            f"[green]{s:6.3f}[/]" if s <= smax else f"{s:6.3f}", _f(z, "{:+5.1f}"))


def _angles_table(state: DemoState, v: View):
    from rich.table import Table

    at = Table(title="load-cell angles (deg)", expand=False)
    for c in ("angle", "truth", "estimate", "± σ", "err/σ"):
        at.add_column(c, justify="left" if c == "angle" else "right")
    ang = v.angles
    if ang is None or ang.get("alpha") is None:
        at.add_row("(no run yet)", "", "", "", "")
        return at
    for i, name in enumerate(ang.get("names") or []):
        at.add_row(*_angle_row(state, v, ang, i, name))
    return at


def _run_row(r: dict, first_t: float | None) -> tuple[str, ...]:
    if r.get("accepted"):
        verdict = "[green]accepted[/]" + (" (late)" if r.get("late") else "")
    else:
        verdict = f"[yellow]{r.get('reason')}[/]"
    end = None if first_t is None or r.get("t") is None else r["t"] - first_t
    return (_f(end, "{:.1f}"), str(r.get("mode")), str(r.get("content")), verdict,
            f"{r.get('determined')}/{len(r.get('names') or [])}",
            _f(r.get("information"), "{:.3g}"), _f(r.get("nu"), "{:.1f}"))


def _runs_table(v: View):
    from rich.table import Table

    rejected = ", ".join(f"{n} {k}" for k, n in v.rejected.items()) or "0 rejected"
    rt = Table(title=f"identification runs: {v.accepted} accepted, {rejected}", expand=False)
    for c in ("end s", "mode", "content", "verdict", "det.", "info", "ν"):
        rt.add_column(c, justify="right" if c not in ("mode", "content", "verdict") else "left")
    for r in reversed(v.runs):
        rt.add_row(*_run_row(r, v.first_t))
    return rt


def _nodes_table(health: dict):
    from rich.table import Table

    nt = Table(title="nodes", expand=False)
    nt.add_column("node")
    nt.add_column("state")
    nt.add_column("hb age s", justify="right")
    nt.add_column("EMCY", justify="right")
    for name, nd in (health.get("nodes") or {}).items():
        st = str(nd.get("state"))
        nt.add_row(name, st if st == "operational" else f"[bold red]{st}[/]",
                   _f(nd.get("heartbeat_age"), "{:.2f}"), str(len(nd.get("emcy") or [])))
    return nt


def _bus_lines(v: View) -> list[RenderableType]:
    from rich.text import Text

    b, smp = v.section("bus"), v.section("samples")
    return [Text(f"bus: frames {b.get('frames')}  error frames {b.get('errors')}  bus-off "
                 f"{b.get('bus_off')}  unknown {b.get('unknown')}  malformed "
                 f"{b.get('malformed')} | samples complete {smp.get('complete')}  incomplete "
                 f"{smp.get('incomplete')}  lost {smp.get('lost')}"),
            Text("sync: " + sync_text(v.health))]


def render(state: DemoState, title: str, units: str):
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table

    v = View.of(state)
    parts: list[RenderableType] = [_head(v, _rate(state, v.samples), title)]
    grid = Table.grid(padding=(0, 2))
    grid.add_row(Group(_hub_table(v, units), _flag_text(v)), _angles_table(state, v))
    parts.append(grid)
    if v.health:
        g2 = Table.grid(padding=(0, 2))
        g2.add_row(_runs_table(v), _nodes_table(v.health))
        parts += [g2, *_bus_lines(v)]
    else:
        parts.append(_runs_table(v))
    return Panel(Group(*parts), title="rsra demo — Ctrl-C to stop", expand=False)


def _plain_hub_rows(v: View, units: str) -> list[str]:
    u = axis_units(units)
    cols = v.hub_columns(units)
    widths = (9, 9, 9, 9, 16, 8)
    fmts = ("{:9.0f}",) * 4 + ("{:.2f}", "{:.1f} %")
    rows = [f"  {'axis':10s} {'truth':>9s} {'H':>9s} {'static':>9s} {'sigma H':>9s} "
            f"{'steady err/sigma':>16s} {'>3sigma':>8s}"]
    for i, ax in enumerate(AXES):
        cells = " ".join(_f(_at(c, i), f).rjust(w) for c, f, w in zip(cols, fmts, widths))
        rows.append(f"  {ax + ' [' + u[i] + ']':10s} {cells}")
    return rows


def _plain_last_run(last: dict) -> str:
    accepted = last.get("accepted")
    verdict = ("accepted" if accepted else "held" if held_window(last)
               else f"rejected ({last.get('reason')})")
    why = "" if accepted or not last.get("explanation") else f": {last['explanation']}"
    return (f"  last run: {last.get('mode')}/{last.get('content')} {verdict}, "
            f"{last.get('determined')}/{len(last.get('names') or [])} determined{why}")


def _plain_angles(ang: dict) -> str:
    worst = max(math.degrees(math.sqrt(max(ang["P"][i][i], 0.0)))
                for i in range(len(ang["alpha"])))
    return (f"  angles: largest σ {worst:.3f}° ({ang.get('determined')} of "
            f"{len(ang['alpha'])} directions determined)")


def render_plain(state: DemoState, title: str, units: str) -> str:
    """What the live view shows, as compact plain text for a pipe or a file (no box drawing,
    no colour): one block per interval."""
    v = View.of(state)
    rejected = "".join(f", {n} {k}" for k, n in v.rejected.items())
    lines = [f"{title}: acquisition {v.acquisition_s:.1f} s, {v.samples} samples, lost "
             f"{v.section('samples').get('lost', 0)}, identification {v.accepted} accepted"
             f"{rejected}", *_plain_hub_rows(v, units),
             "  " + phase_line(v.by_phase).replace("\n", "\n  ")]
    flags = v.hub_value("flags") or []
    if flags:
        lines.append("  flags: " + ", ".join(flags))
    if v.runs:
        lines.append(_plain_last_run(v.runs[-1]))
    ang = v.angles or {}
    if ang.get("alpha") is not None and ang.get("P"):
        lines.append(_plain_angles(ang))
    if v.health:
        lines.append("  sync: " + sync_text(v.health))
    return "\n".join(lines)
