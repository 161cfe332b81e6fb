"""The live terminal view of `rsra demo`: hub loads against the simulator's truth, the angles
converging with their Cramér–Rao bounds, every identification run's verdict, bus and node
health, sample rate, latency and lost samples. Fed by the service's in-process sink (the
same records Zenoh subscribers get), so it costs the estimator nothing but a dict copy."""
from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np

from rsra.config.units import axis_units, to_units

AXES = ("X", "Y", "Z", "L", "M", "N")
HELD_FRACTION = 0.1  # a load is "held" when its revolution mean moved less than this × bound


class DemoState:
    """The latest records, updated from the service thread, read by the view thread."""

    def __init__(self, cfg, static_bound: np.ndarray, angle_names: tuple[str, ...]):
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
        self.err2 = np.zeros(6)
        self.err_n = 0
        # "held" loads: the truth's mean over the last rotor revolution differs from the
        # revolution before by less than HELD_FRACTION of the static bound (the mean over a
        # revolution removes the rotor harmonics) — the figure to compare with the bound;
        # ramps between conditions are scored too, in err2, but a τ = 0.1 s filter lags them
        rev = 2 * math.pi / max(cfg.rotor.omega_nominal_rad_s, 1e-9) * cfg.sample_rate_hz
        self._rev_n = max(1, int(round(rev)))
        self.held_err2 = np.zeros(6)
        self.held_n = 0
        self._recent_truth: deque[np.ndarray] = deque(maxlen=2 * self._rev_n)
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        self.flags: dict[str, int] = {}
        self.rate_marks: deque[tuple[float, int]] = deque(maxlen=40)  # (wall, samples)

    def on_record(self, key: str, payload: dict, truth=None) -> None:
        with self.lock:
            if key == "hub_loads":
                self.hub = payload
                self.samples += 1
                if self.first_t is None:
                    self.first_t = payload["t"]
                for f in payload.get("flags") or []:
                    self.flags[f] = self.flags.get(f, 0) + 1
                if truth is not None:
                    self.truth_H = np.asarray(truth.H_true, float)
                    self.truth_alpha = np.asarray(truth.alpha_true, float)
                    H = payload.get("H")
                    # score after the filter has settled (1 s)
                    if H is not None and payload["t"] - self.first_t > 1.0:
                        e = np.asarray(H, float) - self.truth_H
                        self.err2 += e * e
                        self.err_n += 1
                    self._recent_truth.append(self.truth_H)
                    rt = self._recent_truth
                    if (H is not None and payload["t"] - self.first_t > 1.0
                            and len(rt) == rt.maxlen):
                        a = np.array(rt)
                        step = a[self._rev_n:].mean(0) - a[: self._rev_n].mean(0)
                        if np.all(np.abs(step) <= HELD_FRACTION * self.static_bound):
                            self.held_err2 += e * e
                            self.held_n += 1
            elif key == "health":
                self.health = payload
            elif key == "angles":
                self.angles = payload
                self.runs.append(payload)
                if payload.get("accepted"):
                    self.accepted += 1
                else:
                    r = str(payload.get("reason"))
                    self.rejected[r] = self.rejected.get(r, 0) + 1


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
        rms = np.sqrt(state.held_err2 / state.held_n) if state.held_n else None
        acc, rej = state.accepted, dict(state.rejected)
    parts = []
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
    t = Table(title="hub loads (" + (hub or {}).get("frame", "body") + " axes)", expand=False)
    for c in ("axis", "truth", "Ĥ", "static", "RMS held", "bound σ"):
        t.add_column(c, justify="left" if c == "axis" else "right", no_wrap=True,
                     min_width=7 if c == "axis" else 8)

    def conv(v):
        return None if v is None else to_units(np.asarray(v, float), units)

    H = conv(None if hub is None else hub.get("H"))
    Hs = conv(None if hub is None else hub.get("H_static"))
    T = conv(tH)
    R = conv(rms)
    B = conv(state.static_bound)
    g = "{:8.0f}"
    for i, ax in enumerate(AXES):
        t.add_row(f"{ax} [{u[i]}]", _f(None if T is None else T[i], g),
                  _f(None if H is None else H[i], g), _f(None if Hs is None else Hs[i], g),
                  _f(None if R is None else R[i], g), _f(B[i], g))
    flags = (hub or {}).get("flags") or []
    flag_text = Text("flags: " + (", ".join(flags) if flags else "none"))

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

