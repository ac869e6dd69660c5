"""Benchmarks: `python -m eval.bench <name>` (or `all`). Each writes tables to reports/."""
