# The two commands: `make demo` and `make test`. Both set everything up on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint typecheck imports bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[hub,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fleetdaq demo --data data $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check edge hub ptp fleetdaq tests bench
	$(VENV)/bin/ruff format --check edge hub ptp fleetdaq tests bench

typecheck: $(STAMP)
	$(VENV)/bin/mypy

imports: $(STAMP)
	$(VENV)/bin/lint-imports

test: lint typecheck imports
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/record.py
	$(PY) bench/edge.py
	$(PY) bench/t8.py
	$(PY) bench/timing.py
	$(PY) bench/outage.py
	$(PY) bench/read.py
	$(PY) bench/alarms.py
	$(PY) bench/control.py
	$(PY) bench/foxglove.py
	$(PY) bench/dashboard.py
	$(PY) bench/fanin.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
