"""P9 — replay throughput: `rsra replay --out` against python-can's own reading of the log.

Side by side in one run, on recordings made by ``rsra run --sim S --speed max --record``
(300 s of a ground test and of a flight): python-can's ``can.LogReader`` iterating every
frame of the recording (the peer: reading the file and nothing else), ``rsra replay --out``
(the columnar path, the default: docs/cli.md §6) and ``rsra replay --out --streaming`` (every
frame one by one: the reference), each the whole command in its own process — start-up, the
identification (the recorded schedule, then ``--recompute``) and the JSON lines written
included. The ratio is python-can's time over the replay's (> 1: the replay is faster than
python-can reads the file). The columnar and streaming outputs are compared record for
record (the identification worker's process id aside).

Also: the same recording as BLF and ASC (python-can's Logger), against python-can's
iteration of that file; ``rsra replay --help`` (best of 5, target < 0.3 s); the peak
resident size of every replay process (the identification worker included) over a flight
hour (the 300-s flight recording repeated 12 times in one file, times shifted, 720 000
samples, ``--recompute``), the columnar block size said.

Targets: ≥ 1.0× python-can on both 300-s recordings (and ``--recompute``), ≥ 0.9× on BLF/ASC,
``--help`` < 0.3 s, a flight hour ≤ 300 MB.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.common import BLAS_ENV, arg_parser, ratio, writer_from_args

BENCH = "p9_replay"
DURATION_S = 300.0
HOUR_REPEATS = 12
RSS_LIMIT_MB = 300.0
HELP_LIMIT_S = 0.3
ENV = {**os.environ, **BLAS_ENV}
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rsra(*args: str, timeout: float = 3600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rsra", *args], capture_output=True,
                          text=True, timeout=timeout, env=ENV, check=True)


def record(folder: Path, scenario: str, duration: float) -> None:
    rsra("run", "--sim", scenario, "--seed", "1", "--speed", "max", "--duration",
         str(duration), "--record", str(folder), "--zenoh-listen", "tcp/127.0.0.1:0",
         "--log-level", "error")


def python_can_s(path: Path) -> tuple[float, int]:
    """python-can iterating every frame of ``path`` (in a fresh process, as the replay)."""
    code = ("import time, can, sys\nt0 = time.perf_counter()\nn = 0\n"
            "for _ in can.LogReader(sys.argv[1]):\n    n += 1\n"
            "print(time.perf_counter() - t0, n)")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                         text=True, timeout=3600, env=ENV, check=True).stdout.split()
    return float(out[0]), int(out[1])


def _tree_mb(pid: int) -> tuple[float, float]:
    """Resident size (RSS) and proportional set size (PSS: a page shared by n processes
    counted 1/n in each, so the libraries both processes map count once) of ``pid`` and
    every process below it (/proc), MB."""
    rss = pss = 0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/statm") as f:
                rss += int(f.read().split()[1]) * _PAGE
            with open(f"/proc/{p}/smaps_rollup") as f:
                for line in f:
                    if line.startswith("Pss:"):
                        pss += int(line.split()[1]) * 1024
                        break
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo.extend(int(c) for c in f.read().split())
        except (OSError, ValueError):
            continue
    return rss / 2**20, pss / 2**20


def replay_s(logs: list[Path], out: Path, *extra: str) -> tuple[float, tuple[float, float]]:
    """Wall time of ``rsra replay LOGS --out OUT EXTRA`` and the peak RSS and PSS of its
    process tree (sampled every 100 ms)."""
    cmd = [sys.executable, "-m", "rsra", "replay", *map(str, logs), "--out", str(out), *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    peak = [0.0, 0.0]

    def watch() -> None:
        while proc.poll() is None:
            rss, pss = _tree_mb(proc.pid)
            peak[0], peak[1] = max(peak[0], rss), max(peak[1], pss)
            time.sleep(0.1)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    try:
        _, err = proc.communicate(timeout=7200)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    th.join()
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"rsra replay {' '.join(extra)} failed: {err.decode()[-500:]}")
    return dt, (peak[0], peak[1])


def same_records(a: Path, b: Path) -> bool:
    """The two outputs hold the same lines (the identification worker's pid aside)."""
    pid = re.compile(rb'"pid":\d+')
    with open(a, "rb") as fa, open(b, "rb") as fb:
        for x, y in zip(fa, fb, strict=False):
            if x != y and pid.sub(b"", x) != pid.sub(b"", y):
                return False
        return fa.read(1) == fb.read(1) == b""


def help_s(rounds: int = 5) -> float:
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "rsra", "replay", "--help"], env=ENV,
                       stdout=subprocess.DEVNULL, check=True)
        best = min(best, time.perf_counter() - t0)
    return best


def hour_log(src: Path, dst: Path, repeats: int) -> None:
    """``src`` repeated ``repeats`` times in one file, each copy's times shifted on by the
    recording's length (a longer recording of the same aircraft; the SYNC counter jumps at
    each join: counted, as the reader counts it)."""
    data = src.read_bytes()
    first = float(data[1:data.index(b")")])
    last_line = data.rstrip(b"\n").rsplit(b"\n", 1)[-1]
    span = float(last_line[1:last_line.index(b")")]) - first + 0.005
    with open(dst, "wb") as f:
        for k in range(repeats):
            if k == 0:
                f.write(data)
                continue
            shift = k * span

            def moved(m: re.Match) -> bytes:
                return b"(%.6f)" % (float(m.group(1)) + shift)

            f.write(re.sub(rb"^\(([0-9.]+)\)", moved, data, flags=re.M))


def convert(src: Path, dst: Path) -> None:
    import can

    with can.LogReader(src) as r, can.Logger(dst) as w:
        for msg in r:
            w.on_message_received(msg)


def main(argv: list[str] | None = None) -> int:
    p = arg_parser(__doc__.splitlines()[0])
    p.add_argument("--keep", metavar="DIR", default=None,
                   help="make (or reuse) the recordings in DIR instead of a temporary folder")
    args = p.parse_args(argv)
    w = writer_from_args(BENCH, args)
    # tiny (the test suite's): 2 s of the ground test, no --recompute, BLF only
    duration = 2.0 if args.tiny else DURATION_S
    repeats = 2 if args.tiny else HOUR_REPEATS
    kinds = (("ground", "ground-test"),) if args.tiny else \
        (("ground", "ground-test"), ("flight", "flight"))
    extras: list[list[str]] = [[]] if args.tiny else [[], ["--recompute"]]
    formats = (".blf",) if args.tiny else (".blf", ".asc")
    tmp = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="rsra-bench-p9-"))
    tmp.mkdir(parents=True, exist_ok=True)
    from rsra.daq.bus.columnar import BLOCK_BYTES

    try:
        recs = {}
        for name, scenario in kinds:
            folder = tmp / f"{name}-{duration:g}s"
            if not (folder / "frames.log").is_file():
                shutil.rmtree(folder, ignore_errors=True)
                record(folder, scenario, duration)
            recs[name] = folder
        target = "≥ 1.0× python-can's LogReader iterating the same log (whole command, " \
                 "identification included)"
        for name, folder in recs.items():
            peer, frames = python_can_s(folder / "frames.log")
            for extra in extras:
                col, rss = replay_s([folder], tmp / "col.jsonl", *extra)
                ref, _ = replay_s([folder], tmp / "ref.jsonl", *extra, "--streaming")
                same = same_records(tmp / "col.jsonl", tmp / "ref.jsonl")
                samples = round(duration * 200)
                r = ratio(peer, col)
                w.add(f"{name}_{duration:g}s" + ("_recompute" if extra else ""), col, "s",
                      peer="python-can LogReader iteration", peer_figure=peer, ratio_value=r,
                      ratio_is="peer/figure", target=target, met=r is not None and r >= 1.0,
                      frames=frames, samples_per_s=samples / col, streaming_s=ref,
                      streaming_ratio=ratio(peer, ref), columnar_vs_streaming=ratio(ref, col),
                      same_records=same, peak_rss_mb=rss[0], peak_pss_mb=rss[1],
                      load_average=os.getloadavg()[0])
        for suffix in formats:
            f = tmp / f"ground{suffix}"
            if not f.is_file():
                convert(recs["ground"] / "frames.log", f)
            peer, frames = python_can_s(f)
            col, _ = replay_s([f], tmp / "col.jsonl", "--no-identification")
            ref, _ = replay_s([f], tmp / "ref.jsonl", "--no-identification", "--streaming")
            r = ratio(peer, col)
            w.add(f"ground_{suffix.lstrip('.')}", col, "s", peer="python-can LogReader "
                  "iteration", peer_figure=peer, ratio_value=r, ratio_is="peer/figure",
                  target="≥ 0.9× python-can iterating the same file (--no-identification: "
                  "a log without its folder's config and schedule)", met=r is not None
                  and r >= 0.9, frames=frames, streaming_s=ref,
                  same_records=same_records(tmp / "col.jsonl", tmp / "ref.jsonl"))
        h = help_s(1 if args.tiny else 5)
        w.add("replay_help", h, "s", target=f"rsra replay --help < {HELP_LIMIT_S} s (best of 5)",
              met=h < HELP_LIMIT_S)
        hour = tmp / f"{kinds[-1][0]}-x{repeats}.log"
        if not hour.is_file():
            hour_log(recs[kinds[-1][0]] / "frames.log", hour, repeats)
        t, (rss, pss) = replay_s([hour], tmp / "hour.jsonl", "--recompute")
        w.add("flight_hour_peak_rss", rss, "MB", target=f"≤ {RSS_LIMIT_MB:g} MB, every replay "
              "process (the identification worker included; RSS, shared libraries counted "
              "in each process)", met=rss <= RSS_LIMIT_MB, peak_pss_mb=pss,
              samples=round(duration * 200) * repeats, replay_s=t,
              load_average=os.getloadavg()[0],
              block_bytes=BLOCK_BYTES, output_mb=(tmp / "hour.jsonl").stat().st_size / 2**20)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
