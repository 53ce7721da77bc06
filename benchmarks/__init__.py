"""Benchmark commands (``mcrs-bench-*``), run by hand and in smoke tests; each prints its figures and writes
them as JSON through :mod:`mcrs_benchmarks.harness`."""
