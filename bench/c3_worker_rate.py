"""C3 — one campaign task's samples/s against `rsra replay` alone (docs/user-guide.md
"Campaigns").

One recording (full size: 60 s, 12 000 samples; tiny: 1 s), in this process, interleaved:
the campaign's per-recording task (``rsra.daq.campaign.task.run_recording``: the replay
through its seam, the Parquet tables of every key, the information product from the same
replay's samples, the manifest summary) against
``rsra replay REC --out /dev/null`` (the same replay, JSON lines thrown away). Target: the
task ≥ 0.9 × replay's samples/s.
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
from bench.common import arg_parser, interleaved, ratio, writer_from_args

BENCH = "c3_worker_rate"
TARGET = 0.9


def main(argv: list[str] | None = None) -> int:
    from rsra.daq.campaign.task import run_recording
    from rsra.daq.cli import main as cli

    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    rec = source_recording(1.0 if args.tiny else 60.0)
    rounds = 1 if args.tiny else 3
    samples = [0]
    with tempfile.TemporaryDirectory(prefix="rsra-c3-") as tmp:
        def task() -> float:
            ds = Path(tmp) / "ds"
            ds.mkdir()
            out = run_recording({"recording": "c3", "source": str(rec), "dataset": str(ds),
                                 "config": None, "options": {"recompute": False,
                                                             "no_identification": False},
                                 "provenance": {}})
            shutil.rmtree(ds)
            if out["status"] != "ok":
                raise RuntimeError(out["reason"])
            samples[0] = out["samples"]
            return out["samples"] / out["wall_s"]

        def replay() -> float:
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                rc = cli(["replay", str(rec), "--out", os.devnull])
            if rc != 0:
                raise RuntimeError(f"rsra replay exited {rc}")
            return samples[0] / (time.perf_counter() - t0)

        task()  # warm: imports, and the sample count replay's rate is taken with
        res = interleaved({"task": task, "replay": replay}, rounds)
    bt, br = max(res["task"]), max(res["replay"])
    r = ratio(bt, br)
    w.add("task_vs_replay", bt, "samples/s", peer="rsra replay --out /dev/null",
          peer_figure=br, ratio_value=r, ratio_is="figure/peer",
          target=f"≥ {TARGET:g} × replay's samples/s", met=r is not None and r >= TARGET,
          samples=samples[0], rounds=rounds, all_rounds=res, statistic="best of rounds")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
