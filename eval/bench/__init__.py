"""Benchmarks a user or a regression check needs: `python -m eval.bench <name>` (or `all`; `make bench` runs
`all --quick`). Each writes a table to reports/. One-off parameter studies live in studies/."""
