"""Performance benchmarks of the environment (``mcrs-bench-env``), run by hand and in CI smoke tests."""
