"""P3 — batch filtering of a replay (no real time), samples/s (spec performance.md).

``estimator.filters.filter_batch`` against the per-sample loop of P2 (``LoadFilter.step``)
on the same simulator data (ground-test, true angles, every sample measured), for both
tunings of model.md §6. Both designs are six single-output filters in rotated whitened
coordinates y = M R⁻¹ (z − S T) (M = I for the time-constant gain; for the Riccati gain M
diagonalises W and the PSDs together): per component one IIR filter of the innovation,
run as second-order sections (``scipy.signal.sosfilt``), Ĥ from it without a second filter,
the x0 response and the final state by modes; the N × 30 state history is not made.

What is timed is what a replay consumes: Ĥ, the innovations and the final state (the
state history ``x_plus`` is computed on first access only). Both paths must give the same Ĥ
(the relative difference is in the result line). Target: ≥ 1 000 000 samples/s and ≥ 20×
the loop.
"""
from __future__ import annotations

import time

import numpy as np

from bench.common import arg_parser, interleaved, ratio, writer_from_args
from bench.p2_filter_step import filter_inputs, load_filter_cache
from rsra.config.rig import load_config
from rsra.estimator.filters import TUNINGS, LoadFilter, filter_batch

BENCH = "p3_batch"
TARGET_RATE = 1_000_000.0
TARGET_RATIO = 20.0


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
    n, rounds = (400, 1) if args.tiny else (40000, 5)
    T, z, run = filter_inputs(cfg, n)
    alpha = run.alpha_true[0]
    omega = cfg.rotor.omega_nominal_rad_s
    invalid_after = round(cfg.filter.invalid_after_s * cfg.sample_rate_hz)
    for tuning in TUNINGS:
        cache = load_filter_cache(cfg, tuning=tuning)
        d = cache.design_for(omega)
        H_loop = np.empty((n, 6))
        out: dict = {}

        def loop(cache=cache, H_loop=H_loop) -> float:
            lf = LoadFilter(cache, alpha, invalid_after, omega=omega)
            step = lf.step
            t0 = time.perf_counter()
            for i in range(n):
                H_loop[i] = step(T[i], z[i]).H
            return n / (time.perf_counter() - t0)

        def batch(d=d, out=out) -> float:
            t0 = time.perf_counter()
            res = filter_batch(d, alpha, T, z)
            H, _e, _x = res.H, res.e, res.x_last  # what a replay consumes
            rate = n / (time.perf_counter() - t0)
            out["H"] = H
            return rate

        res = interleaved({"loop": loop, "batch": batch}, rounds)
        best = {k: max(v) for k, v in res.items()}
        diff = float(np.max(np.abs(out["H"] - H_loop)) / np.max(np.abs(H_loop)))
        r = ratio(best["batch"], best["loop"])
        w.add(f"{tuning}", best["batch"], "samples/s", peer="per-sample LoadFilter.step loop",
              peer_figure=best["loop"], ratio_value=r, ratio_is="figure/peer",
              target="≥ 1 000 000 samples/s and ≥ 20 × the loop",
              met=best["batch"] >= TARGET_RATE and r is not None and r >= TARGET_RATIO,
              tuning=tuning, states=d.n_states, samples=n, rounds=rounds,
              all_rounds={k: [round(x) for x in v] for k, v in res.items()},
              rate_met=best["batch"] >= TARGET_RATE,
              ratio_met=r is not None and r >= TARGET_RATIO,
              max_relative_difference_batch_vs_loop=diff, statistic="best of rounds",
              path="second-order sections per rotated component"
              + (" (one call, one gain)" if d.component_gain is not None
                 else " (six gains, rotation M diagonalising W and the PSDs)"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
