# The two commands: `make demo` and `make test`. Both set everything up on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint typecheck imports bench clean wheelhouse readers examples

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[hub,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fleetdaq demo --data data $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check edge hub ptp fleetdaq tests bench examples
	$(VENV)/bin/ruff format --check edge hub ptp fleetdaq tests bench examples

typecheck: $(STAMP) examples
	$(VENV)/bin/mypy
	$(VENV)/bin/mypy --strict $(EXAMPLE)/src $(EXAMPLE)/tests

imports: $(STAMP)
	$(VENV)/bin/lint-imports

# Readers nobody on this project wrote (tests/readers): their own venv, never the project's,
# and the npm Foxglove client. Unpinned, so a release that breaks compatibility fails a test.
READERS := .venv-readers
$(READERS)/.installed: tests/readers/requirements.txt
	test -x $(READERS)/bin/python || $(PYTHON) -m venv $(READERS)
	$(READERS)/bin/python -m pip install --quiet --upgrade pip
	$(READERS)/bin/python -m pip install --quiet -r tests/readers/requirements.txt
	touch $@
tests/readers/node/node_modules/.installed: tests/readers/node/package.json
	cd tests/readers/node && npm install --no-audit --no-fund --silent
	touch $@
readers: $(READERS)/.installed tests/readers/node/node_modules/.installed

# The example driver package (examples/): installed into the project's environment, so its
# entry point registers and its conformance tests run in the same pytest run (testpaths).
EXAMPLE := examples/fleetdaq-driver-example
$(VENV)/.examples: $(STAMP) $(EXAMPLE)/pyproject.toml
	$(PY) -m pip install --quiet --no-deps -e $(EXAMPLE)
	touch $@
examples: $(VENV)/.examples

test: lint typecheck imports readers examples
	$(PY) -m pytest -q --durations=15 -n 2

# What ansible/site.yml installs on every host (README "Deploying a site"): fleetdaq's wheel and
# the wheels of every dependency of the extras asked for, for the hosts' platform, e.g.
#   make wheelhouse                                       this machine's platform, [hub]
#   make wheelhouse EXTRAS=pi PLATFORM=manylinux_2_17_aarch64 PYVER=3.11   Raspberry Pi edges
# Run it once per platform into the same folder; the hosts install with pip --no-index.
WHEELHOUSE ?= build/wheelhouse
EXTRAS ?= hub
PLATFORM ?=
PYVER ?=
wheelhouse: $(STAMP)
	mkdir -p $(WHEELHOUSE)
	rm -f $(WHEELHOUSE)/fleetdaq-*.whl
	$(PY) -m pip wheel --quiet --no-deps --wheel-dir $(WHEELHOUSE) .
	$(PY) -m pip download --quiet --only-binary=:all: --dest $(WHEELHOUSE) \
	  $(if $(PLATFORM),--platform $(PLATFORM)) $(if $(PYVER),--python-version $(PYVER)) \
	  "$$(ls $(WHEELHOUSE)/fleetdaq-*.whl)[$(EXTRAS)]"

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
	$(PY) bench/web_floor.py
	$(PY) bench/fanin.py
	$(PY) bench/router_log.py

clean:
	rm -rf $(VENV) $(READERS) tests/readers/node/node_modules build *.egg-info .pytest_cache .mypy_cache .ruff_cache
