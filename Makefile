# Two entry points for a fresh machine: `make demo` and `make test`.
# Both bootstrap .venv from requirements.lock (exact pins) on first use.
# The venv's interpreter (`make PYTHON=... venv` to choose): the first Python 3.11 of
# PY_CANDIDATES that can make a venv and has libpython linked into its executable (a
# distribution's build, compiled with PGO + LTO: v2v runs ~14 % faster on Debian's python3.11
# than on pyenv's default --enable-shared build, README "Speed"), else python3.
PY_CANDIDATES := /usr/bin/python3.11 python3.11 python3
PY_PICK = import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 11) or any("libpython" in l for l in open("/proc/self/maps")))
PYTHON ?= $(or $(firstword $(foreach p,$(PY_CANDIDATES),$(shell $(p) -c '$(PY_PICK)' 2>/dev/null && echo $(p)))),python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamp-installed

.PHONY: demo test test-all lint nets bench clean venv which-python

$(STAMP): requirements.lock pyproject.toml
	@test -x $(PY) || { py="$(PYTHON)"; echo "creating $(VENV) with $$py"; "$$py" -m venv $(VENV); }
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

which-python:
	@echo $(PYTHON)
