# Two commands do all the set-up on a fresh machine with Python 3.11 and pip:
#   make demo   create .venv, install, simulate the T-handle scene (figures and GIF in out/)
#   make test   create .venv if missing, install, run the test suite
#   make lint   ruff's checks (CI runs them)
#   make docs   install the docs extra, build the API site into site/ (warnings fail)
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench docs clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

# The peers (diffrax, MuJoCo) only for benchmarks: tests and CI stay light.
BENCH_STAMP := $(VENV)/.bench-installed
$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	touch $(BENCH_STAMP)

# mkdocs-material and mkdocstrings only for the API site.
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[docs]"
	touch $(DOCS_STAMP)

demo: $(STAMP)
	$(BIN)/lierk simulate examples/tee_handle_a.toml --out out/
	$(BIN)/python -m lierk.app.demo --out out/report_cases

# One process per test module: a single process compiling the whole suite's
# programs (thousands of XLA executables) was killed mid-run by the native
# code's limits; each module alone is well within them.  Two modules at a
# time, one per core, largest files first (the suite took 15.5 min one after
# another on 2 cores, 11.7 min two at a time);
# each module's output is kept in .test-logs/ and shown whole if it fails.
#
# Most of the suite's time is XLA compiling small problems that then run for
# milliseconds.  XLA's quick settings (no LLVM optimisation passes, the older
# loop emitters) halve that (the suite on a fresh clone: 18.9 -> 11.3 min) and move
# results by a few units in the last place.  Modules whose claims are those
# last bits, or the numbers users see printed, keep XLA's defaults: the
# manual's pages and tests/test_last_bits.py.  Running pytest directly uses
# the defaults everywhere.
QUICK_XLA_FLAGS := --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false
AS_USERS_COMPILE := test_docs test_readme test_last_bits
test: $(STAMP)
	@mkdir -p .test-logs && rm -f .test-logs/*.log .test-logs/compilations.tsv
	@ls -S tests/test_*.py | xargs -P 2 -I{} sh -c 'name=$$(basename {} .py); log=.test-logs/$$name.log; \
	  case " $(AS_USERS_COMPILE) " in *" $$name "*) flags="";; *) flags="$(QUICK_XLA_FLAGS)";; esac; \
	  if XLA_FLAGS="$$(echo $${XLA_FLAGS:-} $$flags)" $(BIN)/python -m pytest -q --durations=10 {} > $$log 2>&1; then \
	  echo "== {}: $$(tail -n 1 $$log | tr -d =) | $$(grep -h "^compilations:" $$log | cut -d: -f3-)"; \
	  else echo "== {} FAILED:"; cat $$log; exit 1; fi'

# ruff's lint, configured in pyproject.toml (line length 120).
lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(BENCH_STAMP)
	$(BIN)/python -m benchmarks

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) out site
