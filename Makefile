# hilcal: `make demo` and `make test` set up .venv themselves (idempotent; quick when nothing changed).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: venv demo test bench screenshot lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: venv
	$(BIN)/hilcal run --sim --yes --out runs/demo-$$(date +%Y%m%d-%H%M%S) --records runs/records.sqlite

lint: venv
	$(BIN)/ruff check .

test: lint
	$(BIN)/pytest -n auto --dist loadfile --no-loadscope-reorder --durations=25

bench: venv
	MPLBACKEND=Agg $(BIN)/python benchmarks/run_all.py

screenshot: venv
	$(BIN)/python benchmarks/bench_panel.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
