"""C4 — a re-run of an unchanged campaign of 200 recordings of 300 s: no task, ≤ 5 s
(docs/user-guide.md "Campaigns").

The campaign is made of cheap fakes, which is only fair because the re-run never reads an
unchanged recording: 200 recording folders (tiny: 5), each with a real recording's
config.json and EDS files and a sparse frames.log of the size a 300-s recording has
(bytes/s of a real one × 300). The dataset is left as a finished campaign leaves it: a
manifest row per recording with its output key, and the content-hash cache holding each
file's (path, size, mtime_ns, inode). Timed: ``rsra campaign run`` over the folder, in this
process, with the engine made to fail if it is opened. Checked besides the time: no task
submitted, no recording read, nothing in the dataset written.
"""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import tempfile
import time
from pathlib import Path

from bench.campaign_data import source_recording
from bench.common import arg_parser, writer_from_args

BENCH = "c4_rerun_unchanged"
LIMIT_S = 5.0
SECONDS = 300.0


def _fake_campaign(root: Path, n: int) -> tuple[Path, Path, int]:
    from rsra.daq.campaign import keys
    from rsra.daq.campaign.dataset import CACHE, write_manifest
    from rsra.daq.campaign.runner import _row, make_plan

    real = source_recording(1.0)
    frames = real / "frames.log"
    first, last = (float(ln[1:ln.index(")")]) for ln in (
        frames.read_text().splitlines()[i] for i in (0, -1)))
    size = int(frames.stat().st_size / max(last - first, 1e-3) * SECONDS)
    recs = root / "recordings"
    recs.mkdir()
    for i in range(n):
        d = recs / f"flight{i:03d}"
        shutil.copytree(real, d, ignore=shutil.ignore_patterns("frames.log", "truth.npz",
                                                               ".complete"))
        with open(d / "frames.log", "wb") as f:
            f.truncate(size)  # sparse: never read
    ds = root / "ds"
    ds.mkdir()
    write_manifest(ds, [])
    # what a finished campaign leaves: the cache (stat and hash of every file) and the rows
    cache = keys.HashCache(ds / CACHE)
    for p in recs.rglob("*"):
        if p.is_file():
            st = p.stat()
            fake = "0" * 64 if p.name == "frames.log" else None
            cache.entries[os.path.realpath(p)] = [st.st_size, st.st_mtime_ns, st.st_ino,
                                                  fake or keys.HashCache(None).file(p)]
    cache._changed = True
    cache.save()
    plan = make_plan([str(recs)], ds, None, {"recompute": False, "no_identification": False})
    assert plan.cache.read == 0 and len(plan.of("run")) == n
    rows = []
    for item in plan.items:
        row = _row(plan, item, {"status": "ok", "samples": int(SECONDS * 200)})
        rows.append(row)
    write_manifest(ds, rows)
    return recs, ds, size


def main(argv: list[str] | None = None) -> int:
    import rsra.daq.campaign.engine as engine
    from rsra.daq.campaign.runner import make_plan
    from rsra.daq.cli import main as cli

    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    n = 5 if args.tiny else 200
    with tempfile.TemporaryDirectory(prefix="rsra-c4-") as tmp:
        recs, ds, size = _fake_campaign(Path(tmp), n)
        before = {p: p.stat().st_mtime_ns for p in ds.rglob("*") if p.is_file()}
        opened = []

        def refuse(*a, **k):
            opened.append(1)
            raise RuntimeError("the engine was opened: a task would run")

        real_open, engine.open_engine = engine.open_engine, refuse
        try:
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()) as out:
                rc = cli(["campaign", "run", "--dataset", str(ds), str(recs)])
            t = time.perf_counter() - t0
        finally:
            engine.open_engine = real_open
        after = {p: p.stat().st_mtime_ns for p in ds.rglob("*") if p.is_file()}
        plan = make_plan([str(recs)], ds, None, {"recompute": False,
                                                 "no_identification": False})
        ok = (rc == 0 and not opened and after == before and plan.cache.read == 0
              and "nothing to do" in out.getvalue())
    w.add(f"{n}_recordings_of_{SECONDS:g}s", t, "s", target=f"no task, ≤ {LIMIT_S:g} s",
          met=ok and t <= LIMIT_S, exit_status=rc, engine_opened=bool(opened),
          dataset_unchanged=after == before, files_read=plan.cache.read,
          recordings=n, frames_bytes_each=size)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
