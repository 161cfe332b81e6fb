"""What every benchmark shares: machine and library identification, the JSON-lines result
writer, side-by-side timing and the RESULTS.md table (docs/performance.md).

Result lines (one JSON object per line, strict JSON: non-finite numbers are written as
null) carry::

    bench, check, run_id, date, command, tiny, status ("measured" | "skipped"),
    figure, unit, peer, peer_figure, ratio, ratio_is, target, met,
    machine {cores, usable_cores, cpu, load_average, python, platform}, versions {...},
    details {...}

``ratio_is`` says which way the ratio is taken ("figure/peer" for throughputs, "peer/figure"
for times, so that a ratio > 1 always means "we are faster"); ``met`` is the target's
decision, None when nothing was measured. The machines are shared and noisy (2 cores):
ratios measured in the same run are the figures to trust, absolute times are indicative.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import importlib.metadata as _md
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"
RESULTS_MD = BENCH_DIR / "RESULTS.md"
RUN_ID_ENV = "RSRA_BENCH_RUN_ID"
COMMAND_ENV = "RSRA_BENCH_COMMAND"
# single-threaded BLAS: the machines have 2 shared cores, and the Monte Carlo benchmarks run
# one process per core (set before numpy is first imported by a benchmark process)
BLAS_ENV = {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}

# benchmark modules in report order (run_all and the RESULTS.md table follow it)
MODULES = ("p1_decode", "p2_filter_step", "p3_batch", "p4_identification", "p5_latency",
           "p5b_service_cpu",
           "p5c_shared_bus", "p6_max_rate", "p6a_shared_bus_rate", "p7_memory", "p8_busy_core",
           "p9_replay",
           "a1_noise_budget", "a2_filter_accuracy", "a3_known_load", "a4_tracking", "a4_drift",
           "a5_paper",
           "a6_flight", "a7_structure", "a8_survey",
           "c1_campaign_speedup", "c2_vs_process_pool", "c3_worker_rate", "c4_rerun_unchanged",
           "c5_pooled")

_LIBRARIES = {"numpy": "numpy", "scipy": "scipy", "python-can": "python-can",
              "canopen": "canopen", "zenoh": "eclipse-zenoh", "filterpy": "filterpy",
              "statsmodels": "statsmodels", "rsra": "rsra"}

RESULT_KEYS = ("bench", "check", "run_id", "date", "command", "tiny", "status", "figure",
               "unit", "peer", "peer_figure", "ratio", "ratio_is", "target", "met", "machine",
               "versions", "details")


def use_single_thread_blas() -> None:
    """Ask BLAS for one thread (effective when called before numpy is imported; child
    processes started afterwards inherit it)."""
    for k, v in BLAS_ENV.items():
        os.environ.setdefault(k, v)


# ------------------------------------------------------------------------------ the machine
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {"cores": os.cpu_count(), "usable_cores": usable, "cpu": cpu_model(),
            "load_average": load,
            "python": platform.python_version(),
            "implementation": platform.python_implementation(),
            "platform": platform.platform()}


def library_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for key, dist in _LIBRARIES.items():
        try:
            out[key] = _md.version(dist)
        except _md.PackageNotFoundError:
            out[key] = None
    return out


# ------------------------------------------------------------------------------ JSON lines
def jsonable(x: Any) -> Any:
    """Plain JSON values: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):  # numpy array or scalar
        return jsonable(x.tolist())
    if isinstance(x, bool) or x is None or isinstance(x, (int, str)):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return str(x)


def ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or not den or not math.isfinite(num) or not math.isfinite(den):
        return None
    return float(num) / float(den)


class ResultWriter:
    """Appends the result lines of one benchmark run to ``<out>/<bench>.jsonl``.

    ``check`` names one comparison of the benchmark (e.g. "vs_dispatch_floor"); several
    checks of one run share the run id, so RESULTS.md shows exactly one run per benchmark.
    """

    def __init__(self, bench: str, *, tiny: bool = False, out_dir: str | Path | None = None,
                 echo: bool = True) -> None:
        self.bench = bench
        self.tiny = bool(tiny)
        self.out_dir = Path(out_dir) if out_dir is not None else RESULTS_DIR
        self.path = self.out_dir / f"{bench}.jsonl"
        self.run_id = os.environ.get(RUN_ID_ENV) or (
            _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ") + f"-{os.getpid()}")
        self.command = os.environ.get(COMMAND_ENV) or " ".join(
            ["python", "-m", f"bench.{bench}", *sys.argv[1:]])
        self.echo = echo
        self._versions = library_versions()
        self.lines: list[dict] = []

    def add(self, check: str, figure: float | None, unit: str, *, target: str,
            met: bool | None, peer: str | None = None, peer_figure: float | None = None,
            ratio_value: float | None = None, ratio_is: str | None = None,
            status: str = "measured", **details: Any) -> dict:
        line = {
            "bench": self.bench, "check": check, "run_id": self.run_id,
            "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "command": self.command, "tiny": self.tiny, "status": status,
            "figure": figure, "unit": unit, "peer": peer, "peer_figure": peer_figure,
            "ratio": ratio_value, "ratio_is": ratio_is, "target": target,
            "met": None if met is None else bool(met),
            "machine": machine_info(), "versions": self._versions, "details": details,
        }
        line = jsonable(line)
        text = json.dumps(line, allow_nan=False)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with self.path.open("a", encoding="utf-8") as f:
            f.write(text + "\n")
        if self.echo:
            print(text, flush=True)
        self.lines.append(line)
        return line

    def skip(self, check: str, reason: str, *, target: str, unit: str = "") -> dict:
        """A benchmark that cannot run yet: a clear line, nothing measured."""
        print(f"bench.{self.bench}: {check}: {reason}", file=sys.stderr, flush=True)
        return self.add(check, None, unit, target=target, met=None, status="skipped",
                        reason=reason)


def check_line(line: dict) -> None:
    """Raise ValueError unless ``line`` is a well-formed result line (tests use this)."""
    missing = [k for k in RESULT_KEYS if k not in line]
    if missing:
        raise ValueError(f"result line lacks {missing}")
    if line["status"] not in ("measured", "skipped"):
        raise ValueError(f"status {line['status']!r}")
    if not isinstance(line["target"], str) or not line["target"]:
        raise ValueError("a result line needs its target")
    for k in ("figure", "peer_figure", "ratio"):
        v = line[k]
        if v is not None and not isinstance(v, (int, float)):
            raise ValueError(f"{k} must be a number or null, not {v!r}")
    if line["met"] is not None and not isinstance(line["met"], bool):
        raise ValueError("met must be a bool or null")
    if line["status"] == "measured" and (line["figure"] is None or line["met"] is None):
        raise ValueError("a measured line needs a figure and a decision")
    if line["peer_figure"] is not None and line["peer"] is None:
        raise ValueError("a peer figure needs the peer's name")
    for k in ("cores", "cpu", "python"):
        if k not in line["machine"]:
            raise ValueError(f"machine info lacks {k}")
    for k in ("numpy", "scipy", "python-can", "canopen"):
        if k not in line["versions"]:
            raise ValueError(f"versions lack {k}")


def read_lines(path: str | Path) -> list[dict]:
    out = []
    p = Path(path)
    if not p.exists():
        return out
    for raw in p.read_text(encoding="utf-8").splitlines():
        if raw.strip():
            out.append(json.loads(raw))
    return out


# ------------------------------------------------------------------------------ command line
def arg_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--tiny", action="store_true",
                   help="smallest configuration (the test suite's: runs, proves nothing)")
    p.add_argument("--out", default=None,
                   help=f"directory for the result lines (default {RESULTS_DIR})")
    return p


def writer_from_args(bench: str, args: argparse.Namespace) -> ResultWriter:
    return ResultWriter(bench, tiny=args.tiny, out_dir=args.out)


# ------------------------------------------------------------------------------ timing
def interleaved(contestants: dict[str, Callable[[], float]], rounds: int) -> dict[str, list[float]]:
    """Run every contestant once per round, in turn, ``rounds`` times; each returns its own
    figure. Interleaving spreads the shared machine's load over all of them alike."""
    out: dict[str, list[float]] = {k: [] for k in contestants}
    for _ in range(rounds):
        for k, fn in contestants.items():
            out[k].append(float(fn()))
    return out


def time_per_call(fn: Callable[[], Any], n: int) -> float:
    """Seconds per call of ``fn`` over ``n`` calls (one perf_counter pair)."""
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


# ------------------------------------------------------------------------------ the table
def _cell(v: Any) -> str:
    """A markdown table cell: pipes escaped, no line breaks."""
    return str(v).replace("|", "\\|").replace("\n", " ")


def _fmt(v: Any) -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "**no**"
    if isinstance(v, float):
        a = abs(v)
        if a == 0:
            return "0"
        if a >= 1e4:
            return f"{v:,.0f}"
        if a >= 100:
            return f"{v:.0f}"
        if a >= 1:
            return f"{v:.3g}" if a < 10 else f"{v:.1f}"
        return f"{v:.3g}"
    return str(v)


def latest_run(lines: Iterable[dict]) -> list[dict]:
    """The lines of the latest full-size run in one results file (tiny runs ignored); a check
    measured more than once in that run (an arm re-run with ``--extend``) by its newest line,
    in the place of its first."""
    lines = [ln for ln in lines if not ln.get("tiny")]
    if not lines:
        return []
    last = max(lines, key=lambda ln: (ln.get("date", ""), ln.get("run_id", "")))["run_id"]
    newest: dict[str, dict] = {}
    for ln in lines:
        if ln.get("run_id") == last:
            key = ln.get("check", "")
            if key not in newest or ln.get("date", "") >= newest[key].get("date", ""):
                newest[key] = ln
    return list(newest.values())


def latest_runs(results_dir: str | Path = RESULTS_DIR) -> Iterator[tuple[str, list[dict]]]:
    """(module, lines of its latest full-size run — empty when never run), in MODULES order."""
    for mod in MODULES:
        yield mod, latest_run(read_lines(Path(results_dir) / f"{mod}.jsonl"))


def render_results(results_dir: str | Path = RESULTS_DIR, out: str | Path = RESULTS_MD,
                   command: str = "python -m bench.run_all") -> str:
    """Regenerate RESULTS.md from the latest full-size run of every benchmark."""
    rows, machines, dates, commands = [], [], [], set()
    for mod, run in latest_runs(results_dir):
        if not run:
            rows.append(f"| {mod} | — | not run | | | | | | |")
            continue
        for ln in run:
            machines.append(ln["machine"])
            dates.append(ln["date"])
            commands.add(ln["command"])
            status = "skipped: " + ln["details"].get("reason", "") if ln["status"] == "skipped" \
                else _fmt(ln["figure"])
            rows.append("| " + " | ".join(_cell(c) for c in (
                ln["bench"], ln["check"], status, ln["unit"], ln["peer"] or "—",
                _fmt(ln["peer_figure"]),
                "—" if ln["ratio"] is None else f"{_fmt(ln['ratio'])} ({ln['ratio_is']})",
                ln["target"], _fmt(ln["met"]))) + " |")
    m = machines[-1] if machines else machine_info()
    loads = [mm["load_average"][0] for mm in machines if mm.get("load_average")]
    v = library_versions()
    head = [
        "# Benchmark results",
        "",
        ("Generated by `bench.common.render_results` from the latest full-size run of each "
        "benchmark in `bench/results/*.jsonl` (docs/performance.md). Do not edit by hand."),
        "",
        f"* command: `{command}`" + (
            "" if commands <= {command} else
            " (lines from: " + ", ".join(f"`{c}`" for c in sorted(commands)) + ")"),
        f"* dates: {min(dates) if dates else '—'} … {max(dates) if dates else '—'} (UTC)",
        (f"* machine: {m.get('cpu')}, {m.get('cores')} cores ({m.get('usable_cores')} usable), "
        f"Python {m.get('python')}"),
        "* load average (1 min) when the lines were written: " + (
            f"{min(loads):.1f} … {max(loads):.1f} on {m.get('cores')} cores (other work shared "
            "the machine)" if loads else "—"),
        "* versions: " + ", ".join(f"{k} {val}" for k, val in v.items() if val),
        "",
        ("Ratios > 1 mean better than the peer (\"figure/peer\" for rates, \"peer/figure\" for "
        "times). The machines are shared and noisy: ratios from one run are the figures to "
        "trust, absolute figures are indicative."),
        "",
        "| bench | check | figure | unit | peer | peer figure | ratio | target | met |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    text = "\n".join(head + rows) + "\n"
    Path(out).write_text(text, encoding="utf-8")
    return text


def simulated_sample(run, i: int, cell_status):
    """Sample ``i`` of a simulated run (``rsra.sim_bus.simulate``) as the service's pipeline
    takes it: every channel present, the run's own rotor speed, azimuth and balance."""
    from types import SimpleNamespace

    om = float(run.omega[i])
    return SimpleNamespace(seq=i, sync=i % 240 + 1, t=float(run.t[i]), T=run.T[i],
                           accel=run.accel[i], flags=[], drive=None,
                           omega=om if math.isfinite(om) else None,
                           azimuth=float(run.azimuth[i]), known_H=run.H_balance[i],
                           cell_status=cell_status, lost_before=0)
