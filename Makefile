# Two commands do all the set-up on a fresh machine with Python 3.11 and pip:
#   make demo   create .venv, install, run the T-handle demo (writes figures to out/)
#   make test   create .venv if missing, install, run the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m lierk.demo --out out

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/convergence.py
	$(BIN)/python benchmarks/throughput.py
	$(BIN)/python benchmarks/work_precision.py

clean:
	rm -rf $(VENV) out
