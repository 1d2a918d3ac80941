# hilcal: `make demo` and `make test` set up .venv themselves (idempotent; quick when nothing changed).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# One pytest worker more than cores: many tests wait on simulated devices, subprocesses or a browser in real time, so
# a third worker keeps both cores busy (`pytest -m "not slow"` on 2 cores, back to back on 2026-12-03: 173 s with -n 3, 210 s with -n 2).
WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))

.PHONY: venv demo test test-slow test-all compile bench screenshot lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet 'uv>=0.5,<1'
	$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: venv
	$(BIN)/hilcal run --sim --yes --out runs/demo-$$(date +%Y%m%d-%H%M%S) --records runs/records.sqlite

lint: venv
	$(BIN)/ruff check .

# `make test` leaves out the tests marked slow (pyproject.toml): the whole simulated calibration runs, the
# headless-browser tests and the tests that take more than about 3.5 CPU seconds alone (their fixtures included),
# together about four fifths of the suite's CPU time (docs/benchmarks_tests.md). `make test-slow` runs those; CI
# (.ci/run) runs both, as does `make test-all`.
# Byte-compile first: with PYTHONDONTWRITEBYTECODE set (as on the machines this project is built on), every
# process the tests start would otherwise compile the project's sources again (~0.15 s per `hilcal` start).
# pytest may keep its assertion-rewritten test modules in __pycache__ (PYTHONDONTWRITEBYTECODE unset for it): a
# worker then collects in 8 s instead of 17 s once a run has written them (`pytest --co -p no:xdist`, 2026-12-03; `make test-slow` after
# `make test`, and every run after the first).
# One BLAS thread per process: the workers and the runs they start already share the cores, and OpenBLAS's own
# threads would only spin on them for matrices of a few hundred rows.
PYTEST := env -u PYTHONDONTWRITEBYTECODE OPENBLAS_NUM_THREADS=1 $(BIN)/pytest --dist loadfile --no-loadscope-reorder --durations=25

compile: venv
	$(BIN)/python -m compileall -q -j0 hilcal drivers procedures sim_devices benchmarks tests >/dev/null

test: lint compile
	$(PYTEST) -n $(WORKERS) -m "not slow"

test-slow: compile
	$(PYTEST) -n $(WORKERS) -m slow

test-all: test test-slow

bench: venv
	MPLBACKEND=Agg $(BIN)/python benchmarks/run_all.py

screenshot: venv
	$(BIN)/python benchmarks/bench_panel.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
