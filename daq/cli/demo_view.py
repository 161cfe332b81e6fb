"""The live terminal view of `rsra demo`: hub loads against the simulator's truth, the angles
converging with their Cramér–Rao bounds, every identification run's verdict, bus and node
health, sample rate, latency and lost samples. Fed by the service's in-process sink (the
same records Zenoh subscribers get), so it costs the estimator nothing but a dict copy."""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from rsra.config.units import axis_units, to_units

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
        from rsra.daq.analysis.accuracy import phase_of, published_sigma, starts_calibrated

        with self.lock:
            if key == "hub_loads":
                self.hub = payload
                self.samples += 1
                if self.first_t is None:
                    self.first_t = payload["t"]
                flags = payload.get("flags") or []
                if self.samples == 1 and starts_calibrated(flags):
                    self.calibrated = True  # a saved posterior: no start phase
                for f in flags:
                    self.flags[f] = self.flags.get(f, 0) + 1
                H, Hs = payload.get("H"), payload.get("H_static")
                self.sigma_H = sigma_H = (None if H is None
                                          else published_sigma(payload, self.static_bound, "H"))
                if truth is not None:
                    self.truth_H = np.asarray(truth.H_true, float)
                    self.truth_alpha = np.asarray(truth.alpha_true, float)
                    phase = phase_of(self.calibrated, flags)
                    if H is not None and sigma_H is not None and \
                            payload["t"] - self.first_t > SETTLE_S:
                        self.acc["H"].add(phase, np.asarray(H, float) - self.truth_H, sigma_H)
                    if Hs is not None:
                        self.acc["H_static"].add(
                            phase, np.asarray(Hs, float) - self.truth_H,
                            published_sigma(payload, self.static_bound, "H_static"))
            elif key == "health":
                self.health = payload
            elif key == "angles":
                self.angles = payload
                self.runs.append(payload)
                if payload.get("accepted"):
                    self.accepted += 1
                    self.calibrated = True  # (published at the sample it applies from)
                else:
                    r = str(payload.get("reason"))
                    self.rejected[r] = self.rejected.get(r, 0) + 1

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


def render(state: DemoState, title: str, units: str):
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    with state.lock:
        hub, health, ang = state.hub, state.health, state.angles
        runs = list(state.runs)
        tH = None if state.truth_H is None else state.truth_H.copy()
        ta = None if state.truth_alpha is None else state.truth_alpha.copy()
        n, first_t = state.samples, state.first_t
        bp = state.by_phase()
        sH = None if state.sigma_H is None else state.sigma_H.copy()
        acc, rej = state.accepted, dict(state.rejected)
    parts: list[RenderableType] = []
    now = time.monotonic()
    state.rate_marks.append((now, n))
    w0, n0 = state.rate_marks[0]
    rate = (n - n0) / (now - w0) if now > w0 else 0.0
    acq = 0.0 if hub is None or first_t is None else hub["t"] - first_t
    lat = (health or {}).get("latency_ms") or {}
    smp = (health or {}).get("samples") or {}
    latency = ("latency n/a (lock-step)" if lat.get("p50") is None else
               f"latency p50 {lat['p50']:.2f} ms  p99 {_f(lat.get('p99'), '{:.2f}')} ms")
    head = Text.assemble(
        (f"{title}  ", "bold"),
        f"acquisition {acq:7.1f} s   {rate:6.0f} samples/s   lost {smp.get('lost', 0)}   "
        + (f"not taken {nt}   " if (nt := ((health or {}).get("sync") or {}).get(
            "periods_not_taken")) is not None else "")
        + f"{latency}")
    parts.append(head)

    u = axis_units(units)
    t = Table(title="hub loads (" + (hub or {}).get("frame", "body") + " axes); err/σ, >3σ: "
              "steady state", expand=False)
    for c in ("axis", "truth", "Ĥ", "static", "σ Ĥ", "err/σ", ">3σ"):
        t.add_column(c, justify="left" if c == "axis" else "right", no_wrap=True,
                     min_width=7 if c == "axis" else 5 if c in ("err/σ", ">3σ") else 8)

    def conv(v):
        return None if v is None else to_units(np.asarray(v, float), units)

    H = conv(None if hub is None else hub.get("H"))
    Hs = conv(None if hub is None else hub.get("H_static"))
    T = conv(tH)
    S = conv(sH)
    st = (bp.get("H") or {}).get("steady")
    g = "{:8.0f}"
    for i, ax in enumerate(AXES):
        t.add_row(f"{ax} [{u[i]}]", _f(None if T is None else T[i], g),
                  _f(None if H is None else H[i], g), _f(None if Hs is None else Hs[i], g),
                  _f(None if S is None else S[i], g),
                  _f(None if st is None else st["rms_over_sigma"][i], "{:.2f}"),
                  _f(None if st is None else 100 * st["beyond_3sigma"][i], "{:.1f}%"))
    flags = (hub or {}).get("flags") or []
    flag_text = Text("flags: " + (", ".join(flags) if flags else "none") + "\n"
                     + phase_line(bp))

    at = Table(title="load-cell angles (deg)", expand=False)
    for c in ("angle", "truth", "estimate", "± σ", "err/σ"):
        at.add_column(c, justify="left" if c == "angle" else "right")
    if ang is not None and ang.get("alpha") is not None:
        names = ang.get("names") or []
        P = ang.get("P")
        smax = math.degrees(state.cfg.identification.sigma_max_rad)
        for i, name in enumerate(names):
            a = math.degrees(ang["alpha"][i])
            s = math.degrees(math.sqrt(max(P[i][i], 0.0))) if P else float("nan")
            tru = None
            if ta is not None and name in state.angle_names:
                tru = math.degrees(ta[state.angle_names.index(name)])
            z = None if tru is None or not s > 0 else (a - tru) / s
            at.add_row(name, _f(tru, "{:7.3f}"), f"{a:7.3f}",
                       f"[green]{s:6.3f}[/]" if s <= smax else f"{s:6.3f}", _f(z, "{:+5.1f}"))
    else:
        at.add_row("(no run yet)", "", "", "", "")
    grid = Table.grid(padding=(0, 2))
    grid.add_row(Group(t, flag_text), at)
    parts.append(grid)

    rt = Table(title=f"identification runs: {acc} accepted, " + (
        ", ".join(f"{v} {k}" for k, v in rej.items()) or "0 rejected"), expand=False)
    for c in ("end s", "mode", "content", "verdict", "det.", "info", "ν"):
        rt.add_column(c, justify="right" if c not in ("mode", "content", "verdict") else "left")
    for r in reversed(runs):
        verdict = ("[green]accepted[/]" + (" (late)" if r.get("late") else "")
                   if r.get("accepted") else f"[yellow]{r.get('reason')}[/]")
        rt.add_row(_f(None if first_t is None or r.get("t") is None else r["t"] - first_t,
                      "{:.1f}"), str(r.get("mode")), str(r.get("content")), verdict,
                   f"{r.get('determined')}/{len(r.get('names') or [])}",
                   _f(r.get("information"), "{:.3g}"), _f(r.get("nu"), "{:.1f}"))
    if health:
        nt = Table(title="nodes", expand=False)
        nt.add_column("node")
        nt.add_column("state")
        nt.add_column("hb age s", justify="right")
        nt.add_column("EMCY", justify="right")
        for name, nd in (health.get("nodes") or {}).items():
            st = str(nd.get("state"))
            nt.add_row(name, st if st == "operational" else f"[bold red]{st}[/]",
                       _f(nd.get("heartbeat_age"), "{:.2f}"), str(len(nd.get("emcy") or [])))
        g2 = Table.grid(padding=(0, 2))
        g2.add_row(rt, nt)
        parts.append(g2)
    else:
        parts.append(rt)
    if health:
        b = health.get("bus") or {}
        parts.append(Text(
            f"bus: frames {b.get('frames')}  error frames {b.get('errors')}  bus-off "
            f"{b.get('bus_off')}  unknown {b.get('unknown')}  malformed {b.get('malformed')} | "
            f"samples complete {smp.get('complete')}  incomplete {smp.get('incomplete')}  "
            f"lost {smp.get('lost')}"))
        parts.append(Text("sync: " + sync_text(health)))
    return Panel(Group(*parts), title="rsra demo — Ctrl-C to stop", expand=False)



def render_plain(state: DemoState, title: str, units: str) -> str:
    """What the live view shows, as compact plain text for a pipe or a file (no box drawing,
    no colour): one block per interval."""
    with state.lock:
        hub, health, ang = state.hub, state.health, state.angles
        tH = None if state.truth_H is None else state.truth_H.copy()
        sH = None if state.sigma_H is None else state.sigma_H.copy()
        n, first_t = state.samples, state.first_t
        bp = state.by_phase()
        acc, rej = state.accepted, dict(state.rejected)
        last = state.runs[-1] if state.runs else None
    acq = 0.0 if hub is None or first_t is None else hub["t"] - first_t
    smp = (health or {}).get("samples") or {}
    u = axis_units(units)

    def conv(v):
        return None if v is None else to_units(np.asarray(v, float), units)

    H, Hs = conv((hub or {}).get("H")), conv((hub or {}).get("H_static"))
    T, S = conv(tH), conv(sH)
    st = (bp.get("H") or {}).get("steady")
    lines = [f"{title}: acquisition {acq:.1f} s, {n} samples, lost {smp.get('lost', 0)}, "
             f"identification {acc} accepted"
             + (", " + ", ".join(f"{v} {k}" for k, v in rej.items()) if rej else "")]
    lines.append(f"  {'axis':10s} {'truth':>9s} {'H':>9s} {'static':>9s} {'sigma H':>9s} "
                 f"{'steady err/sigma':>16s} {'>3sigma':>8s}")
    g = "{:9.0f}"

    def cell(v, i, fmt=g, width=9):
        return _f(None if v is None else v[i], fmt).rjust(width)

    z = None if st is None else st["rms_over_sigma"]
    b = None if st is None else [100 * x for x in st["beyond_3sigma"]]
    for i, ax in enumerate(AXES):
        lines.append(f"  {ax + ' [' + u[i] + ']':10s} {cell(T, i)} {cell(H, i)} {cell(Hs, i)} "
                     f"{cell(S, i)} {cell(z, i, '{:.2f}', 16)} {cell(b, i, '{:.1f} %', 8)}")
    lines.append("  " + phase_line(bp).replace("\n", "\n  "))
    flags = (hub or {}).get("flags") or []
    if flags:
        lines.append("  flags: " + ", ".join(flags))
    if last is not None:
        verdict = "accepted" if last.get("accepted") else f"rejected ({last.get('reason')})"
        lines.append(f"  last run: {last.get('mode')}/{last.get('content')} {verdict}, "
                     f"{last.get('determined')}/{len(last.get('names') or [])} determined"
                     + ("" if last.get("accepted") or not last.get("explanation")
                        else f": {last['explanation']}"))
    if ang is not None and ang.get("alpha") is not None and ang.get("P"):
        worst = max(math.degrees(math.sqrt(max(ang["P"][i][i], 0.0)))
                    for i in range(len(ang["alpha"])))
        lines.append(f"  angles: largest σ {worst:.3f}° ({ang.get('determined')} of "
                     f"{len(ang['alpha'])} directions determined)")
    if health:
        lines.append("  sync: " + sync_text(health))
    return "\n".join(lines)
