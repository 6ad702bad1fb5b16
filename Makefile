# Two entry points, each creating its own virtual environment on a fresh machine.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test test-all bench clean

$(BIN)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[export,test,bench]"
	touch $@

demo: $(BIN)/.installed
	$(BIN)/lensforge demo

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n 2 -m "not slow"

test-all: $(BIN)/.installed
	$(BIN)/python -m pytest -q -n 2

bench: $(BIN)/.installed
	for f in benchmarks/bench_*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV)
