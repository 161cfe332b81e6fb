"""Recordings for the campaign benchmarks (C1–C4): one simulator recording, made once and
kept in a cache folder, cut into recordings of the lengths a benchmark asks for (a
recording folder whose frames.log stops at a line: a shorter recording of the same flight;
each copy is its own recording, by path)."""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import socket
import time
from pathlib import Path

CACHE = Path(os.environ.get("RSRA_BENCH_CACHE", Path.home() / ".cache" / "rsra-bench"))


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def source_recording(seconds: float) -> Path:
    """A ground-test recording of ``seconds`` (made once, then taken from the cache)."""
    from rsra.daq.cli import main

    folder = CACHE / f"ground-{seconds:g}s"
    if (folder / "frames.log").is_file() and (folder / ".complete").is_file():
        return folder
    shutil.rmtree(folder, ignore_errors=True)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["run", "--sim", "ground-test", "--speed", "max", "--duration",
                   f"{seconds:g}", "--seed", "7", "--record", str(folder),
                   "--zenoh-listen", f"tcp/127.0.0.1:{_port()}"])
    if rc != 0:
        raise RuntimeError(f"making the benchmark recording failed ({rc})")
    (folder / ".complete").write_text("")
    return folder


def cut(source: Path, dest: Path, seconds: float) -> Path:
    """A copy of ``source`` whose frames stop ``seconds`` after its first frame."""
    shutil.copytree(source, dest, ignore=shutil.ignore_patterns("frames.log", "truth.npz",
                                                                 ".complete"))
    with open(source / "frames.log", encoding="utf-8") as f, \
            open(dest / "frames.log", "w", encoding="utf-8") as out:
        t0 = None
        for line in f:
            t = float(line[1:line.index(")")])
            t0 = t if t0 is None else t0
            if t - t0 > seconds:
                break
            out.write(line)
    return dest


def campaign_folder(root: Path, lengths: list[float]) -> Path:
    """A folder of recordings of these lengths (s), cut from one cached recording."""
    src = source_recording(max(lengths))
    folder = root / "recordings"
    folder.mkdir(parents=True)
    for i, s in enumerate(lengths):
        cut(src, folder / f"rec{i:03d}", s)
    return folder


def run_campaign(argv: list[str]) -> tuple[int, float]:
    """`rsra campaign run ARGV` in this process: (exit status, wall time s)."""
    from rsra.daq.cli import main

    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["campaign", "run", *argv])
    return rc, time.perf_counter() - t0


def campaign_setup(doc: str, bench: str, argv: list[str] | None):
    """The options C1 and C2 share (``--recordings``, ``--longest``, the common ones) and what
    they give: (args, writer, the recordings' lengths in s, rounds)."""
    from bench.common import arg_parser, writer_from_args

    p = arg_parser(doc.splitlines()[0])
    p.add_argument("--recordings", type=int, default=16, help="recordings (default 16)")
    p.add_argument("--longest", type=float, default=60.0,
                   help="the longest recording, s (the shortest is a sixth of it; default 60)")
    args = p.parse_args(argv)
    k, top = args.recordings, args.longest
    lengths = [1.0, 1.0] if args.tiny else [top / 6 + top * 5 / 6 * i / max(k - 1, 1)
                                             for i in range(k)]
    return args, writer_from_args(bench, args), lengths, 1 if args.tiny else 2
