"""Benchmark stage: `python -m stages.benchmark tracer ...` prints a table and writes JSON."""
