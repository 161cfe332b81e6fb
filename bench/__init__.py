"""Benchmarks against the peers a user would pick instead (spec performance.md).

Every benchmark is a module runnable as ``python -m bench.<module> [--tiny]``; each prints
and appends JSON lines to ``bench/results/<module>.jsonl`` (``bench.common.write_result``).
``python -m bench.run_all`` runs them all and regenerates ``bench/RESULTS.md``.

Benchmarks are not tests: the test suite only checks that each one runs in its tiny
configuration and writes well-formed lines (tests/test_bench.py), never a timing.
"""
