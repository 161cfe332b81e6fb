"""C1 — `rsra campaign run` on N workers against 1 worker, the same campaign (docs/user-guide.md
"Campaigns").

A campaign of recordings of mixed length (full size: 16 recordings of 10 … 60 s, ``--recordings K --longest S``
for another; tiny: 2 of 1 s), run into a fresh dataset with ``--workers 1`` and with ``--workers N`` (N = the usable
cores), each on the default engine (a Dask local cluster, cluster start-up included),
interleaved. Figure: the speed-up t₁/t_N; target: an efficiency ≥ 0.8 per core
(≥ 1.6× on 2 cores). Ratios in one run are the figures to trust on a shared machine.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from bench.campaign_data import campaign_folder, campaign_setup, run_campaign
from bench.common import interleaved, ratio

BENCH = "c1_campaign_speedup"
EFFICIENCY = 0.8


def main(argv: list[str] | None = None) -> int:
    from rsra.daq.campaign.engine import cores

    args, w, lengths, rounds = campaign_setup(__doc__, BENCH, argv)
    n = cores()
    with tempfile.TemporaryDirectory(prefix="rsra-c1-") as tmp:
        recs = campaign_folder(Path(tmp), lengths)
        k = [0]

        def on(workers: int):
            def go() -> float:
                k[0] += 1
                ds = Path(tmp) / f"ds{k[0]}"
                rc, t = run_campaign(["--dataset", str(ds), "--workers", str(workers),
                                      str(recs)])
                shutil.rmtree(ds, ignore_errors=True)
                if rc != 0:
                    raise RuntimeError(f"campaign run exited {rc}")
                return t
            return go

        res = interleaved({"1": on(1), "N": on(n)}, rounds)
    t1, tn = min(res["1"]), min(res["N"])
    speedup = ratio(t1, tn)
    w.add(f"{n}_workers_vs_1", speedup, "x", peer="the same campaign on 1 worker",
          peer_figure=t1, ratio_value=speedup, ratio_is="peer/figure",
          target=f"≥ {EFFICIENCY * n:g}× on {n} cores (efficiency ≥ {EFFICIENCY:g})",
          met=speedup is not None and speedup >= EFFICIENCY * n, workers=n,
          recordings=len(lengths), seconds_recorded=sum(lengths), wall_1_s=t1, wall_n_s=tn,
          efficiency=None if speedup is None else speedup / n, rounds=rounds,
          all_rounds=res, statistic="best of rounds (cluster start-up included)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
