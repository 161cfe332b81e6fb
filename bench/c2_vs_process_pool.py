"""C2 — `rsra campaign run` on Dask against a plain ProcessPoolExecutor over the same tasks
(docs/user-guide.md "Campaigns").

The campaign of C1 (tiny: 2 recordings of 1 s) into a fresh dataset on N = the usable cores,
once on the default engine (a Dask local cluster) and once with ``--pool`` (the same tasks
through the engine seam on a ``concurrent.futures.ProcessPoolExecutor``), interleaved. Each
side's wall time is the whole `rsra campaign run` in this process: the plan (every recording
hashed into a fresh dataset's cache), the engine's start (Dask: importing distributed, the
scheduler, N nannies and their forked workers; the pool: its forked processes), the same
per-recording tasks, the manifest, the summary and the engine's close. Target: Dask's wall
time ≤ 1.05 × the pool's.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from bench.campaign_data import campaign_folder, campaign_setup, run_campaign
from bench.common import interleaved, ratio

BENCH = "c2_vs_process_pool"
LIMIT = 1.05


def main(argv: list[str] | None = None) -> int:
    from rsra.daq.campaign.engine import cores

    args, w, lengths, rounds = campaign_setup(__doc__, BENCH, argv)
    n = cores()
    with tempfile.TemporaryDirectory(prefix="rsra-c2-") as tmp:
        recs = campaign_folder(Path(tmp), lengths)
        k = [0]

        def on(*engine: str):
            def go() -> float:
                k[0] += 1
                ds = Path(tmp) / f"ds{k[0]}"
                rc, t = run_campaign(["--dataset", str(ds), "--workers", str(n), *engine,
                                      str(recs)])
                shutil.rmtree(ds, ignore_errors=True)
                if rc != 0:
                    raise RuntimeError(f"campaign run exited {rc}")
                return t
            return go

        res = interleaved({"dask": on(), "pool": on("--pool")}, rounds)
    td, tp = min(res["dask"]), min(res["pool"])
    r = ratio(tp, td)
    w.add(f"dask_vs_pool_{n}_workers", td, "s", peer="ProcessPoolExecutor, same tasks",
          peer_figure=tp, ratio_value=r, ratio_is="peer/figure",
          target=f"Dask wall ≤ {LIMIT:g} × the pool's (ratio ≥ {1 / LIMIT:.3f})",
          met=r is not None and r >= 1 / LIMIT, workers=n, recordings=len(lengths),
          rounds=rounds, all_rounds=res, statistic="best of rounds (start-up included)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
