"""Run every benchmark, then regenerate bench/RESULTS.md and the README table
(``python -m bench.run_all``).

Each benchmark runs in its own process (``python -m bench.<module>``) with single-threaded
BLAS, so one benchmark's threads, buses and imports cannot disturb the next; all lines of
one ``run_all`` share a run id and name this command. Meant to finish in < 45 min on 2 cores
(the shared-bus rate search, P6a, takes up to 15 of them).
A benchmark that fails is reported and the others still run; the exit status is 1 then.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import os
import subprocess
import sys
import time

from bench.common import (
    BLAS_ENV,
    COMMAND_ENV,
    MODULES,
    RESULTS_DIR,
    RESULTS_MD,
    RUN_ID_ENV,
    render_results,
)

MODULE_TIMEOUT_S = 1800.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tiny", action="store_true", help="every benchmark in its tiny form "
                   "(RESULTS.md then ignores them)")
    p.add_argument("--only", nargs="+", choices=MODULES, metavar="MODULE",
                   help=f"run only these ({', '.join(MODULES)})")
    p.add_argument("--out", default=None, help=f"results directory (default {RESULTS_DIR})")
    p.add_argument("--no-table", action="store_true", help="do not regenerate RESULTS.md")
    args = p.parse_args(argv)
    command = "python -m bench.run_all" + (" " + " ".join(argv if argv is not None
                                                          else sys.argv[1:])).rstrip()
    run_id = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ") + f"-all{os.getpid()}"
    env = {**os.environ, **BLAS_ENV, RUN_ID_ENV: run_id, COMMAND_ENV: command}
    failed = []
    t_all = time.perf_counter()
    for mod in args.only or MODULES:
        cmd = [sys.executable, "-m", f"bench.{mod}"]
        if args.tiny:
            cmd.append("--tiny")
        if args.out:
            cmd += ["--out", args.out]
        t0 = time.perf_counter()
        print(f"== bench.{mod}", flush=True)
        try:
            rc = subprocess.run(cmd, env=env, timeout=MODULE_TIMEOUT_S, check=False).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
        print(f"== bench.{mod}: {'ok' if rc == 0 else f'FAILED ({rc})'} in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(mod)
    print(f"== all benchmarks in {time.perf_counter() - t_all:.0f} s"
          + (f"; failed: {', '.join(failed)}" if failed else ""), flush=True)
    if not args.no_table and not args.tiny:
        out_dir = args.out or RESULTS_DIR
        md = RESULTS_MD if args.out is None else os.path.join(args.out, "RESULTS.md")
        print(render_results(out_dir, md, command="python -m bench.run_all"))
        if args.out is None:
            from bench.readme import update_readme

            update_readme()  # the README's short table, from the same lines
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
