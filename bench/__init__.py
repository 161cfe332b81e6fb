"""Benchmarks against the peers a user would pick instead (docs/performance.md).

Every benchmark is a module runnable as ``python -m bench.<module> [--tiny]``; each prints
and appends JSON lines to ``bench/results/<module>.jsonl`` (``bench.common.write_result``).
``python -m bench.run_all`` runs them all and regenerates ``bench/RESULTS.md``.

Benchmarks are not tests: the test suite only checks that each one runs in its tiny
configuration and writes well-formed lines (tests/test_bench.py), never a timing.
"""
import os

# Benchmarks run with the service's BLAS setting (daq/__init__.py: one thread). Without it a
# benchmark that imports only `estimator` let OpenBLAS start threads for long products, which
# cost 15-35 ms a call on the shared 2 cores (measured in P3). The user's environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
