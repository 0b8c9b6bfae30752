# Two entry points for a fresh machine: `make demo` and `make test`.
# Both bootstrap .venv from requirements.lock (exact pins) on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp-installed

.PHONY: demo test test-all lint nets bench clean venv

$(STAMP): requirements.lock pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/v2v demo --out runs/demo

test: $(STAMP)
	$(PY) -m pytest -q

test-all: $(STAMP)
	$(PY) -m pytest -q -m "slow or not slow"

lint: $(STAMP)
	$(VENV)/bin/ruff check v2v tests experiments benchmarks
	$(VENV)/bin/mypy v2v

nets: $(STAMP)
	$(VENV)/bin/v2v nets build

bench: $(STAMP)
	$(PY) benchmarks/bench_run.py
	$(PY) benchmarks/bench_filter.py
	$(PY) benchmarks/bench_synthesis.py

clean:
	rm -rf $(VENV) runs .pytest_cache
