# Two entry points, each creating its own virtual environment on a fresh machine.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test bench clean

$(BIN)/lensforge: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[test,bench]"
	touch $(BIN)/lensforge

demo: $(BIN)/lensforge
	$(BIN)/lensforge demo

test: $(BIN)/lensforge
	$(BIN)/python -m pytest -q -n 2

bench: $(BIN)/lensforge
	$(BIN)/python benchmarks/bench_optics.py

clean:
	rm -rf $(VENV)
