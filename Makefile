# Quick start: `make demo` (simulate the default scene into ./out) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[test]"
	# the package's bytecode now, not in the first run's imports (an editable install
	# leaves it to them: ~0.4 s of a first `clumpylen simulate`)
	$(BIN)/python -m compileall -q clumpylen_jax
	touch $(STAMP)

.PHONY: setup demo test bench
setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/clumpylen simulate cosmic-archipelago --out out

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist worksteal tests

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py
