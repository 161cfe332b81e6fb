"""P7 — memory: resident size over 10 minutes at 200 samples/s with recording on.

The service (``daq.service.Service``) with the simulated ground-test aircraft, recording
every frame (python-can log, the angles schedule, the truth file at the end), publishing
over Zenoh (loopback, no subscriber needed) and running the periodic identification in its
worker process — in a fresh spawned process. A sink reads the resident set size of the
service process and of the identification worker (``/proc/<pid>/statm``) every
``EVERY_S`` of acquisition time.

Lock-step (``--speed max``): the same 120 000 samples, frames and identification windows as
10 minutes in real time (model.md §8: simulated time is the one clock), in about 3 minutes
of wall time, so that ``python -m bench.run_all`` stays within its budget. Anything the
service keeps grows per sample or per window, which this covers; wall-clock-driven growth
(none is known) would not show.

The service runs with the simulated aircraft in its process (the virtual bus is in-process
only); the simulator's truth bookkeeping (every sample it sent and every SYNC, kept for the
truth file, bounded at one hour ≈ 0.65 kB a sample) is the harness's memory, not the
service's: it is subtracted (and the figure with it reported).

Target: flat — growth < 5 MB after the first minute (service + worker).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from bench.common import BLAS_ENV, arg_parser, use_single_thread_blas, writer_from_args

BENCH = "p7_memory"
DURATION_S = 600.0
EVERY_S = 5.0
AFTER_S = 60.0
LIMIT_MB = 5.0
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb(pid: int | str = "self") -> float | None:
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * _PAGE / 2**20
    except (OSError, ValueError, IndexError):
        return None


def run_service(duration: float, every_s: float, record_dir: str) -> dict:
    import socket

    from rsra.config.rig import load_config
    from rsra.daq.runtime.service import Service, ServiceOptions

    cfg = load_config()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    opts = ServiceOptions(sim="ground-test", speed=None, duration=duration, seed=1,
                          record=record_dir, zenoh=True,
                          zenoh_listen=[f"tcp/127.0.0.1:{port}"])
    svc = Service(cfg, opts)
    every = max(1, round(every_s * cfg.sample_rate_hz))
    # bounded: duration / every_s entries
    series: list[tuple[float, float | None, float | None, float]] = []

    def truth_mb() -> float:
        """Memory of the in-process simulator's truth bookkeeping (the test harness's record
        of what it sent): the TruthBuffer chunks held in memory (full ones are spilled to an
        anonymous file) and the compact per-SYNC table ``sync_info``."""
        sim = svc.sim
        if sim is None:
            return 0.0
        total = 0
        for part in (getattr(sim, "samples", None), getattr(sim, "sync_info", None)):
            total += getattr(part, "nbytes", 0)
        return total / 2**20

    def sink(key: str, payload: dict) -> None:
        if key == "hub_loads" and payload["seq"] % every == 0:
            worker = svc.worker.proc.pid if svc.worker is not None else None
            series.append((payload["seq"] / cfg.sample_rate_hz, rss_mb(),
                           rss_mb(worker) if worker else None, truth_mb()))

    svc.add_sink(sink)
    summary = svc.run()
    rec_bytes = sum(f.stat().st_size for f in Path(record_dir).rglob("*") if f.is_file())
    return {"series": series, "summary": {k: summary.get(k) for k in (
        "samples", "lost", "identification_runs", "accepted", "published")},
        "recorded_bytes": rec_bytes}


def _entry(duration: float, every_s: float, record_dir: str, out) -> None:
    try:
        out.put(run_service(duration, every_s, record_dir))
    except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
        out.put({"error": f"{type(e).__name__}: {e}"})


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    duration, every_s, after = (5.0, 1.0, 2.0) if args.tiny else (DURATION_S, EVERY_S, AFTER_S)
    use_single_thread_blas()
    os.environ.update(BLAS_ENV)
    tmp = tempfile.mkdtemp(prefix="rsra-bench-p7-")
    try:
        ctx = mp.get_context("spawn")
        q = ctx.Queue()
        p = ctx.Process(target=_entry, args=(duration, every_s, os.path.join(tmp, "rec"), q))
        p.start()
        try:
            res = q.get(timeout=duration * 2 + 600)
        finally:
            p.join(60)
            if p.is_alive():
                p.terminate()
                p.join(5)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if "error" in res:
        raise RuntimeError(f"the service run failed: {res['error']}")
    s = np.array([(t, np.nan if a is None else a, np.nan if b is None else b, c)
                  for t, a, b, c in res["series"]])
    t, svc_mb, wrk_mb, truth = s[:, 0], s[:, 1], np.nan_to_num(s[:, 2]), s[:, 3]
    own = svc_mb - truth + wrk_mb  # the service's own memory: the harness's truth removed
    total = svc_mb + wrk_mb
    k = min(int(np.searchsorted(t, after)), len(t) - 1)

    win = max(1, round(after / every_s))  # one minute of points

    def growth(x: np.ndarray) -> float:
        """Median of the last minute − median of the minute after the first (the worker's
        RSS moves by a few MB with each window it solves: medians, not single points)."""
        return float(np.median(x[-win:]) - np.median(x[k:k + win]))

    def max_rise(x: np.ndarray) -> float:
        return float(np.max(x[k:]) - x[k])

    def slope(x: np.ndarray) -> float | None:
        return float(np.polyfit(t[k:], x[k:], 1)[0] * 60.0) if len(t) - k >= 3 else None

    g_own, g_total = growth(own), growth(total)
    w.add("rss_growth_after_first_minute", g_own, "MB (last minute − second minute, medians)",
          target=f"< {LIMIT_MB:g} MB after the first minute (service + identification worker)",
          met=g_own < LIMIT_MB, slope_mb_per_min=slope(own), largest_rise_mb=max_rise(own),
          growth_including_simulator_truth_mb=g_total,
          slope_including_simulator_truth_mb_per_min=slope(total),
          simulator_truth_history_mb_end=float(truth[-1]),
          note="the service runs with the simulated aircraft in its process (--sim); the "
               "simulator keeps a truth history of every sample and SYNC (bounded at one hour) for the "
               "truth file, which is not the service's memory: it is subtracted, and the "
               "figure with it is given too",
          service_rss_mb_at_1min=float(svc_mb[k]), service_rss_mb_end=float(svc_mb[-1]),
          worker_rss_mb_end=float(wrk_mb[-1]), acquisition_s=duration,
          mode="lock-step (--speed max), recording on, Zenoh on", series_every_s=every_s,
          series_t_service_worker_truth_mb=[[round(a, 1), round(b, 2), round(c, 2), round(d, 2)]
                                            for a, b, c, d in zip(t, svc_mb, wrk_mb, truth)],
          service_summary=res["summary"], recorded_bytes=res["recorded_bytes"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
