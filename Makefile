# The two entry points of the README: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test test-slow test-shared test-all lint format bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-dev: $(VENV)/.installed pyproject.toml
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/symbio demo --out demo_out

# The self-contained suite (a few minutes): tests that need ../shared are left to `make test-shared`,
# pipeline-scale tests marked `slow` to `make test-slow`.
test: $(VENV)/.installed-dev
	$(PY) -m pytest -q -m "not shared"

# The self-contained tests marked slow (whole pipeline runs, long scenes); CI runs them after `make test`.
test-slow: $(VENV)/.installed-dev
	$(PY) -m pytest -q -m "slow and not shared" --runslow

# Every test that needs ../shared, slow ones included (CI runs it when the data is there).
test-shared: $(VENV)/.installed-dev
	$(PY) -m pytest -q -m shared --runslow

test-all: $(VENV)/.installed-dev
	$(PY) -m pytest -q --runslow

lint: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

format: $(VENV)/.installed-dev
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

# Every speed and accuracy benchmark (about 40 minutes on 2 cores; each prints its ratios and tables).
bench: $(VENV)/.installed-dev
	$(PY) -m eval.bench.synth
	$(PY) -m eval.bench.vbow
	$(PY) -m eval.bench.wl --keyframes 2000
	$(PY) -m eval.bench.objects
	$(PY) -m eval.bench.backend
	$(PY) -m eval.bench.lcd
	$(PY) -m eval.bench.frontend
	$(PY) -m eval.bench.pipeline
	$(PY) -m eval.bench.sweep

clean:
	rm -rf $(VENV) demo_out .pytest_cache .mypy_cache .ruff_cache
