"""`rsra demo`: the main job on the embedded default — the simulated aircraft and the service in
one process on python-can's virtual bus, Zenoh on loopback, and a live terminal view."""
from __future__ import annotations

import argparse
import json
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

from rsra.daq.cli.outputs import REPORT_FILES

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
PLAIN_INTERVAL_S = 5.0  # off a terminal: the plain-text view every this many wall seconds
OUTPUTS = {"report": REPORT_FILES, "record": "folder"}  # against the inputs (daq.cli.outputs)


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options
    from rsra.daq.cli.options import add_no_identification, add_realtime_priority, add_sim_options

    p = sub.add_parser(name, help="the simulator and the service in one process, with a live view",
                       description="The main job on the embedded default: the simulated "
                       "aircraft and the service in one process on python-can's virtual bus, "
                       "telemetry on Zenoh (loopback), and a live view of the hub loads against "
                       "the simulator's truth, the load-cell angles converging with their "
                       "Cramér–Rao bounds, every identification run's verdict and the bus "
                       "health. Ctrl-C or --duration ends it with a summary. `rsra listen` in "
                       "another terminal shows the same telemetry.")
    common_options(p)
    p.add_argument("--scenario", default="ground-test",
                   choices=("ground-test", "flight", "paper", "sweep", "calibration"),
                   help="the simulated aircraft's scenario (default ground-test: known loads)")
    add_sim_options(p)
    p.add_argument("--report", metavar="DIR", default=None,
                   help="at the end, write plots (PNG) and a summary here")
    p.add_argument("--record", metavar="DIR", default=None,
                   help="record every frame, the angle schedule and the truth here")
    p.add_argument("--angles", metavar="STATE", default=None,
                   help="start from a saved posterior (e.g. a ground test's "
                   "identification.state_file) instead of the configured initial angles")
    from rsra.daq.cli.options import add_accept_option

    add_accept_option(p)
    add_no_identification(p)
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP",
                   help=f"Zenoh endpoint (default {DEFAULT_ENDPOINT}, or a free loopback port "
                   "when that one is taken)")
    from rsra.daq.runtime.foxglove_out import add_options as add_foxglove_options

    add_foxglove_options(p)
    add_realtime_priority(p)
    p.add_argument("--json", action="store_true",
                   help='also print the final summary as one JSON line {"summary": …} on '
                   "stdout (for scripts)")
    p.add_argument("--log-level", default="warning",
                   choices=("debug", "info", "warning", "error"), help="default warning")
    return p


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def _endpoint(args) -> tuple[list[str], str | None]:
    if args.zenoh_listen:
        return args.zenoh_listen, None
    if _port_free(7447):
        return [DEFAULT_ENDPOINT], None
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return [f"tcp/127.0.0.1:{port}"], f"port 7447 is taken: telemetry on tcp/127.0.0.1:{port}"


def run(args: argparse.Namespace) -> int:
    from rsra.daq.cli.options import UsageError
    from rsra.daq.cli.options import check_sim_faults, config_for_run, setup_logging
    from rsra.daq.cli.console import make_console
    from rsra.daq.cli.demo_view import DemoState
    from rsra.daq.runtime.service import Service, ServiceOptions, initial_angles
    from rsra.estimator.noise_budget import noise_budget
    from rsra.estimator.posterior import PosteriorFileError

    setup_logging(args.log_level, None)
    variants = dict(args.variant)
    cfg = config_for_run(args.config, args.scenario, variants)
    # before anything is created
    check_sim_faults(cfg, args.scenario, args.faults, args.speed, variants)
    try:  # a bad --angles file: one line before anything starts
        alpha0, _, _ = initial_angles(cfg, args.angles, args.accept_rig_mismatch)
    except PosteriorFileError as e:
        raise UsageError(str(e)) from None
    from rsra.daq.runtime.foxglove_out import check_option

    check_option(args)  # a taken port: refused before anything starts
    listen, note = _endpoint(args)
    report_jsonl = None
    closers = []
    if args.report:
        Path(args.report).mkdir(parents=True, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix="rsra-demo-")
        report_jsonl = Path(tmp) / "records.jsonl"
    opts = ServiceOptions(sim=args.scenario, seed=args.seed, faults=args.faults, speed=args.speed,
                          scenario_variants=variants,
                          duration=args.duration, zenoh_listen=listen, record=args.record,
                          angles=args.angles, accept_rig_mismatch=args.accept_rig_mismatch,
                          identification=args.identification,
                          keep_truth=bool(args.report), foxglove=args.foxglove,
                          foxglove_origins=args.foxglove_allow_origin,
                          realtime_priority=args.realtime_priority,
                          truth=str(Path(report_jsonl).parent / "truth.npz") if report_jsonl else None)
    svc = Service(cfg, opts)
    svc.install_signal_handlers()
    model = cfg.rig_model()
    nb = noise_budget(model, alpha0)
    state = DemoState(cfg, nb.total, model.geometry.angle_names)
    svc.add_sink(lambda key, payload: state.on_record(key, payload, _truth_of(svc, key, payload)))
    if report_jsonl is not None:
        from rsra.daq.runtime.service import jsonl_sink

        jsink, jclose = jsonl_sink(report_jsonl)
        svc.add_sink(jsink)
        closers.append(jclose)
    console = make_console()
    opts.foxglove_announce = lambda line: console.print(line, markup=False, highlight=False)
    title = f"{args.scenario}, {_speed_words(args.speed)}"
    console.print(f"[bold]rsra demo[/]: simulated aircraft '{args.scenario}' + service, "
                  f"telemetry on {listen[0]} (try `rsra listen` in another terminal)")
    if note:
        console.print(note)
    result: dict = {}

    def work():
        try:
            result["summary"] = svc.run()
        except BaseException as e:  # reported below, in the main thread
            result["error"] = e

    th = threading.Thread(target=work, name="rsra-service")
    th.start()
    try:
        _show(console, th, state, title, args.units, svc.stop)
    finally:
        for c in closers:
            c()
    if "error" in result:
        raise result["error"]
    summary = result.get("summary", {})
    _print_summary(console, summary, state, as_json=args.json)
    if args.report:
        assert report_jsonl is not None and opts.truth is not None  # made with --report above
        _write_report(console, cfg, report_jsonl, opts.truth, args.report, args.units)
    return 0


def _truth_of(svc, key: str, payload: dict):
    """The simulator's true sample a hub-loads record estimates (None: not kept, or another
    record)."""
    if key != "hub_loads" or svc.sim is None:
        return None
    seq = payload["seq"]
    return next((s for s in reversed(svc.sim.recent_samples) if s.index == seq), None)


def _speed_words(speed: float | None) -> str:
    if speed is None:
        return "as fast as possible (lock-step)"
    return "real time" if speed == 1.0 else f"{speed:g}x real time (lock-step)"


def _show(console, th: threading.Thread, state, title: str, units: str, stop) -> None:
    """The view while the service thread ``th`` runs: live on a terminal, else a plain-text
    table every PLAIN_INTERVAL_S; Ctrl-C stops the service (``stop``) and waits for it. The
    last state stays on screen."""
    from rsra.daq.cli.demo_view import render, render_plain

    live = None
    last_line = 0.0
    try:
        if console.is_terminal:
            from rich.live import Live

            live = Live(render(state, title, units), console=console, refresh_per_second=4,
                        transient=False)
            live.start()
        while th.is_alive():
            th.join(timeout=0.25)
            if live is not None:
                live.update(render(state, title, units))
            elif time.monotonic() - last_line > PLAIN_INTERVAL_S and state.samples:
                # not a terminal: what the view shows, as a compact plain-text table
                last_line = time.monotonic()
                print(render_plain(state, title, units), flush=True)
    except KeyboardInterrupt:
        stop()
        th.join()
    finally:
        if live is not None:
            live.update(render(state, title, units))
            live.stop()
        elif state.samples:  # the last state, as the terminal view leaves it
            print(render_plain(state, title, units), flush=True)


def _write_report(console, cfg, records: Path, truth: str, folder: str, units: str) -> None:
    """``rsra report``'s report of the run into ``folder`` (the truth when the run kept it)."""
    from rsra.daq.analysis.report import write_report
    from rsra.sim_bus.truth import read_truth

    rep = write_report(cfg, records, truth if Path(truth).exists() else None,
                       folder, units=units, read_truth=read_truth)
    console.print(f"report written to {folder}: "
                  + ", ".join(p.name for p in rep.plots) + ", summary.md, summary.json")


def _print_summary(console, summary: dict, state, as_json: bool = False) -> None:
    """The final summary as readable text (the JSON behind --json)."""
    rej = summary.get("rejected") or {}
    lines = [f"samples {summary.get('samples', 0)}, lost {summary.get('lost', 0)}, "
             f"identification runs {summary.get('identification_runs', 0)} "
             f"(accepted {summary.get('accepted', 0)}"
             + (", rejected " + ", ".join(f"{v} {k}" for k, v in rej.items()) if rej else "")
             + ")"]
    with state.lock:
        bp = state.by_phase()
        ang, ta = state.angles, state.truth_alpha
    lines += _hub_error_lines(bp)
    if ta is not None:
        lines += _angle_error_lines(ang, ta, state.angle_names, summary.get("alpha_applied"))
    console.print("[bold]summary[/]: " + "\n  ".join(lines), highlight=False)
    if as_json:
        print(json.dumps({"summary": summary}, default=str), file=sys.stdout, flush=True)


def _hub_error_lines(bp: dict) -> list[str]:
    """The hub-load errors against truth by phase (none when no phase has a sample)."""
    from rsra.daq.analysis.accuracy import MEANING, phase_lines

    if not (any(bp["H"].values()) or any(bp["H_static"].values())):
        return []
    lines = ["hub-load error against truth by phase, each sample against the σ "
             "published for it (RMS error/σ and beyond 3σ per axis):"]
    for name in ("H", "H_static"):
        lines += [x for x in phase_lines(bp[name], name, "  ")
                  if not x.lstrip().startswith("(")]
    return lines + [f"  {p}: {m}" for p, m in MEANING.items() if bp["H"].get(p)
                    or bp["H_static"].get(p)]


def _angle_error_lines(ang: dict | None, ta, angle_names: tuple[str, ...],
                       alpha_applied: list | None) -> list[str]:
    """The identified angles' error against the true ones ``ta``, or the held starting
    angles' when no identification ran."""
    import numpy as np

    if ang and ang.get("alpha"):
        names = ang["names"]
        e = np.degrees([ang["alpha"][i] - ta[angle_names.index(n)]
                        for i, n in enumerate(names) if n in angle_names])
        s = np.degrees([np.sqrt(ang["P"][i][i]) for i in range(len(names))])
        return [f"angles: max |error| {np.abs(e).max():.3f} deg, max sigma {s.max():.3f} deg, "
                f"determined {ang.get('determined')}/{len(names)}"]
    if not ang and alpha_applied:
        # no identification run: the starting angles held for the whole run
        e = np.degrees(np.asarray(alpha_applied, float) - ta)
        return [f"angles (held, no identification run): max |error| {np.abs(e).max():.3f} deg"]
    return []
