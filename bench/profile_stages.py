"""The CPU budget per sample, per stage (docs/performance.md "Where the time goes").

Each configuration runs as users start it; after a warm-up, py-spy (a sampling profiler,
``--nonblocking``: the process is never paused) records every thread of the process for
``--seconds``, while the process's CPU time (``/proc/<pid>/stat``) and the samples it
published (a Zenoh subscriber here) are counted over the same window. A stage's CPU µs per
sample = the process's CPU time × the stage's share of py-spy's active stacks ÷ samples.

Configurations:

* ``shared-200`` / ``shared-limit``: ``rsra bus``; ``rsra sim --scenario ground-test`` and
  ``rsra run`` in their own processes on it (the bench rig), at 200 samples/s and at the
  1 Mbit/s bus limit — the service alone and the simulator alone, each its own process;
* ``inproc-200``: ``rsra run --sim ground-test`` in real time (one process; the simulator's
  stacks told apart from the service's by their frames);
* ``lockstep``: ``rsra run --sim ground-test --speed max`` (both, one thread, no waiting).

Output: one JSON line per configuration and process, and a Markdown table (``--markdown``).
``--quick`` runs 2 s of ``inproc-200`` only, after a 1 s warm-up (the smoke test).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from bench.rig import start_sim_and_service, Receiver, cpu_seconds, free_tcp_port, rate_config, spawn, start_bus, stop, wait_listening

WARMUP_S = 8.0
QUICK_WARMUP_S, QUICK_S = 1.0, 2.0  # --quick: the smoke test (every path once, no figure)

# stage of a stack: the innermost frame that matches, on the side (simulator or service) the
# stack belongs to (a stack with a sim_bus/ frame is the simulator's)
SIM_RULES = (
    ("sim: physics (loads, noise)", ("sim_bus/physics.py", "sim_bus/offline.py", "sim_bus/truth.py")),
    ("sim: node PDO packing", ("sim_bus/nodes.py",)),
    ("sim: frames out (python-can send)", ("can/", "can_remote/", "_transmit (sim_bus", "_emit (sim_bus",
                                           "_send_frame (sim_bus", "_build (sim_bus")),
    ("sim: scheduling, other", ("sim_bus/", "daq/cli/commands/sim.py")),
)
SERVER_RULES = (
    ("bus server: WebSocket + JSON (python-can-remote)", ("can_remote/", "json/", "socket")),
    ("bus server: virtual bus", ("can/",)),
)
SERVICE_RULES = (
    ("JSON encoding", ("json/", "daq/jsonout.py")),
    ("Zenoh put", ("publish (daq/runtime/telemetry.py",)),
    ("estimator (filter, balance, stuck test, records)", ("estimator/", "daq/runtime/pipeline.py", "daq/runtime/stuck.py")),
    ("assembly + decode", ("daq/bus/assembler.py", "daq/bus/decoder.py")),
    ("frame tap + clock", ("daq/bus/reader.py:1", "on_message_received (daq/bus/reader.py", "stamp",
                           "daq/timebase", "daq/bus/recorder.py")),
    ("SYNC producer", ("daq/bus/master.py",)),
    ("frames in (python-can recv, notifier)", ("can/", "can_remote/", "canopen/", "queue.py",
                                               "threading.py")),
    ("service loop, publishing, other", ("daq/",)),
)


IDLE = ("Condition.wait ", "Event.wait ", "sleep ", "select ", "poll ", "_wait_for_tstate_lock ",
        "recv_into ", "accept ")


def idle(frames: list[str]) -> bool:
    """A thread waiting (py-spy --nonblocking cannot tell a waiting thread from a running one:
    its innermost Python frame says so)."""
    return frames[-1].startswith(IDLE)


def classify(frames: list[str]) -> str:
    if any("can_remote/server.py" in f for f in frames):
        for f in reversed(frames):
            for name, pats in SERVER_RULES:
                if any(p in f for p in pats):
                    return name
        return "bus server: other"
    side_sim = any("sim_bus/" in f for f in frames)
    if any("can_remote/" in f for f in frames):  # the shared bus's client (its JSON included)
        return "sim: frames out (python-can send)" if side_sim else "frames in (python-can recv, notifier)"
    rules = SIM_RULES if side_sim else SERVICE_RULES
    for f in reversed(frames):  # innermost first
        for name, pats in rules:
            if any(p in f for p in pats):
                return name
    return "sim: other" if side_sim else "other (interpreter, libraries)"


def read_raw(path: str | Path) -> Counter:
    """py-spy's raw (collapsed) output → samples per stage; start-up stacks dropped."""
    c: Counter = Counter()
    for line in Path(path).read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack or not n.isdigit():
            continue
        frames = stack.split(";")
        if any("<module>" in f and "importlib" in ";".join(frames) for f in frames[:3]):
            continue  # imports (start-up)
        if not idle(frames):
            c[classify(frames)] += int(n)
    return c


def profile_pid(pid: int, seconds: float, out: str, rate: int = 200) -> subprocess.Popen:
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    return subprocess.Popen([spy, "record", "--pid", str(pid), "-d", str(int(seconds)), "-r",
                             str(rate), "-f", "raw", "--nonblocking", "--gil", "-o", out],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def budget(counts: Counter, cpu_s: float, samples: int) -> dict:
    total = sum(counts.values()) or 1
    per = cpu_s / max(1, samples) * 1e6
    return {"cpu_us_per_sample": round(per, 1),
            "stages_us": {k: round(per * v / total, 1) for k, v in counts.most_common()},
            "profile_samples": total}


def measure(procs: dict[str, subprocess.Popen], rx: Receiver, seconds: float, tmp: Path) -> dict:
    spies, cpu0 = {}, {}
    for name, p in procs.items():
        cpu0[name] = cpu_seconds(p.pid)
        spies[name] = profile_pid(p.pid, seconds, str(tmp / f"{name}.txt"))
    n0, t0 = rx.count(), time.monotonic()
    time.sleep(seconds)
    n1, t1 = rx.count(), time.monotonic()
    cpu1 = {name: cpu_seconds(p.pid) for name, p in procs.items()}
    for s in spies.values():
        s.wait(60)
    samples = n1 - n0
    res = {"samples": samples, "window_s": round(t1 - t0, 2),
           "rate_achieved": round(samples / (t1 - t0), 1), "load_average": os.getloadavg()[0]}
    for name in procs:
        res[name] = budget(read_raw(tmp / f"{name}.txt"), cpu1[name] - cpu0[name], samples)
        res[name]["cpu_share_of_core"] = round((cpu1[name] - cpu0[name]) / (t1 - t0), 3)
    return res


def run_shared(rate: float, seconds: float, tmp: Path, warmup: float = WARMUP_S) -> dict:
    from rsra.config.rig import load_config

    cfg_path = rate_config(rate, tmp)
    bus, channel = start_bus()
    sim = svc = rx = None
    try:
        sim, svc, ep = start_sim_and_service(channel, cfg_path)
        rx = Receiver(ep, load_config().telemetry.prefix, int(rate * (seconds + warmup + 60)))
        time.sleep(warmup)
        return measure({"service": svc, "simulator": sim, "bus server": bus}, rx, seconds, tmp)
    finally:
        if rx is not None:
            rx.close()
        for p in (svc, sim, bus):
            stop(p)


def run_inproc(extra: list[str], seconds: float, tmp: Path, rate_hint: float,
               warmup: float = WARMUP_S) -> dict:
    from rsra.config.rig import load_config

    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    svc = spawn(["-m", "rsra", "run", "--sim", "ground-test", *extra, "--zenoh-listen", ep,
                 "--log-level", "warning"])
    rx = None
    try:
        wait_listening(port, svc)
        rx = Receiver(ep, load_config().telemetry.prefix, int(rate_hint * (seconds + warmup + 60)))
        time.sleep(warmup)
        return measure({"process": svc}, rx, seconds, tmp)
    finally:
        if rx is not None:
            rx.close()
        stop(svc)


def markdown(results: dict) -> str:
    stages: list[str] = []
    cols = []
    for conf, r in results.items():
        for name in ("service", "simulator", "bus server", "process"):
            if name in r:
                cols.append((f"{conf} {name}", r[name], r))
                for s in r[name]["stages_us"]:
                    if s not in stages:
                        stages.append(s)
    stages.sort(key=lambda s: (s.startswith("sim:"), s))
    head = "| stage (CPU µs per sample) | " + " | ".join(c[0] for c in cols) + " |"
    lines = [head, "|---" * (len(cols) + 1) + "|"]
    for s in stages:
        lines.append(f"| {s} | " + " | ".join(
            str(c[1]["stages_us"].get(s, "—")) for c in cols) + " |")
    lines.append("| **total** | " + " | ".join(f"**{c[1]['cpu_us_per_sample']}**" for c in cols) + " |")
    lines.append("| share of one core | " + " | ".join(str(c[1]["cpu_share_of_core"]) for c in cols) + " |")
    lines.append("| samples/s achieved | " + " | ".join(str(c[2]["rate_achieved"]) for c in cols) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0, help="profiled window per configuration")
    p.add_argument("--only", nargs="+", default=None,
                   choices=("shared-200", "shared-limit", "inproc-200", "lockstep"))
    p.add_argument("--quick", action="store_true", help="2 s of inproc-200 after a 1 s warm-up (smoke test)")
    p.add_argument("--markdown", action="store_true", help="also print the Markdown table")
    p.add_argument("--keep", default=None, metavar="DIR",
                   help="keep py-spy's raw stacks here (one file per configuration and process)")
    args = p.parse_args(argv)
    from bench.p6_max_rate import bus_limit_samples_per_s
    from rsra.config.rig import load_config

    limit = math.floor(bus_limit_samples_per_s(load_config())[0])
    confs = ["inproc-200"] if args.quick else (args.only or ["shared-200", "shared-limit",
                                                             "inproc-200", "lockstep"])
    seconds = QUICK_S if args.quick else args.seconds
    warmup = QUICK_WARMUP_S if args.quick else WARMUP_S
    results = {}
    with tempfile.TemporaryDirectory(prefix="rsra-profile-") as d:
        tmp = Path(d)
        for conf in confs:
            if conf == "shared-200":
                r = run_shared(200.0, seconds, tmp, warmup)
            elif conf == "shared-limit":
                r = run_shared(float(limit), seconds, tmp, warmup)
            elif conf == "inproc-200":
                r = run_inproc(["--speed", "1"], seconds, tmp, 200.0, warmup)
            else:
                r = run_inproc(["--speed", "max", "--no-identification"], seconds, tmp, 5000.0,
                               warmup)
            results[conf] = r
            if args.keep:
                Path(args.keep).mkdir(parents=True, exist_ok=True)
                for f in tmp.glob("*.txt"):
                    shutil.copy(f, Path(args.keep) / f"{conf}-{f.name}")
            print(json.dumps({"configuration": conf, **r}), flush=True)
    if args.markdown:
        print(markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
