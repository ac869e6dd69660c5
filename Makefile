# DMesh harness. `make demo` and `make test` set themselves up first (Debian packages, .venv, native build).
PY := .venv/bin/python
export OMP_NUM_THREADS ?= 2

.PHONY: setup test test-slow demo bench readme reproduce-tables reproduce-recipes robustness clean

setup:
	@bash tools/setup.sh

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

demo: setup
	$(PY) -m eval.cli demo -o out

bench: setup
	$(PY) -m eval.bench all --quick --out out/bench

reproduce-tables: setup
	$(PY) -m eval.cli reproduce-tables --jobs 2 -o reports

reproduce-recipes: setup
	$(PY) -m eval.cli reproduce-tables --recipes -o reports

robustness: setup
	$(PY) -m eval.cli robustness --jobs 2 -o reports

clean:
	rm -rf build out .pytest_cache

readme:
	$(PY) -m eval.reports.readme
