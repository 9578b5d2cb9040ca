# terrastream: `make demo` and `make test` set everything up (venv, pip packages, headless GL libs).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.stamp-install

.PHONY: demo test setup gl-libs lint bench clean reliability

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "terrastream needs Python >= 3.11; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

gl-libs:   # with CI=true: fails when no headless EGL context can be created
	@PY=$(BIN)/python bash scripts/ensure-gl.sh

setup: $(STAMP) gl-libs

# pytest-xdist processes for `make test` (0: one process)
TEST_WORKERS ?= 2

test: setup   # ends with "GL tests: N ran (...), M skipped" (tests/conftest.py)
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

reliability: setup   # the long fault-injection series (24 kills, 24 Ctrl-Cs, 30,000-frame faulty session); counts in BENCHMARKS.md
	TERRASTREAM_RELIABILITY_LONG=1 $(BIN)/python -m pytest -s tests/reliability tests/streamer/test_session_faults.py
	TERRASTREAM_RELIABILITY_LONG=1 $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile -m long_series tests

demo: setup
	@bash scripts/demo.sh

lint: setup
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

bench: setup   # long: see BENCHMARKS.md for each command's run time
	$(BIN)/python bench/tiling.py
	$(BIN)/python bench/prefetch.py
	$(BIN)/python bench/render.py
	$(BIN)/python bench/lod_compare.py

clean:
	rm -rf demo-out bench/work .pytest_cache
