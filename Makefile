# `make demo` and `make test` are the README's first two commands; both set everything up.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install --disable-pip-version-check -q -c constraints.txt
export PIP_CONSTRAINT := $(CURDIR)/constraints.txt

.PHONY: demo test lint typecheck pytest bench experiments experiments-quick clean setup setup-dev

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q --upgrade pip

$(VENV)/.core: $(PY) pyproject.toml constraints.txt
	$(PIP) -e .
	touch $@

$(VENV)/.dev: $(VENV)/.core
	$(PIP) -e ".[torch,dev]"
	touch $@

setup: $(VENV)/.core
setup-dev: $(VENV)/.dev

demo: $(VENV)/.core
	$(VENV)/bin/sinkjax demo

lint: $(VENV)/.dev
	$(VENV)/bin/ruff check src tests experiments calibration
	$(VENV)/bin/ruff format --check src tests experiments calibration

typecheck: $(VENV)/.dev
	$(VENV)/bin/mypy

pytest: $(VENV)/.dev
	$(VENV)/bin/pytest -n 2 -q

test: lint typecheck pytest

bench: $(VENV)/.dev
	$(PY) experiments/bench.py

experiments: $(VENV)/.dev
	$(PY) experiments/run_all.py

experiments-quick: $(VENV)/.dev
	$(PY) experiments/run_all.py --quick

clean:
	rm -rf $(VENV) sinkjax-demo .pytest_cache .mypy_cache .ruff_cache
