# `make demo` and `make test` are the README's first two commands; both set everything up.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install --disable-pip-version-check -q -c constraints.txt
export PIP_CONSTRAINT := $(CURDIR)/constraints.txt

.PHONY: demo test test-heavy test-all lint typecheck pytest pytest-heavy bench experiments experiments-quick clean setup setup-dev chromium

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q --upgrade pip

$(VENV)/.core: $(PY) pyproject.toml constraints.txt
	$(PIP) -e .
	touch $@

$(VENV)/.dev: $(VENV)/.core
	$(PIP) -e ".[torch,dev,review,parallel]"
	touch $@

# The review page's browser tests drive Debian's chromium. Installed here when missing and we
# are root with apt; otherwise (or if apt fails) those tests skip, saying how to install it.
chromium:
	@if [ ! -x /usr/bin/chromium ] && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
			>/dev/null) || echo "warning: could not install chromium; browser tests will skip"; \
	fi

setup: $(VENV)/.core
setup-dev: $(VENV)/.dev

demo: $(VENV)/.core
	$(VENV)/bin/sinkjax demo

lint: $(VENV)/.dev
	$(VENV)/bin/ruff check src tests experiments calibration
	$(VENV)/bin/ruff format --check src tests experiments calibration

typecheck: $(VENV)/.dev
	$(VENV)/bin/mypy

# worksteal: a worker with nothing left takes queued tests from the other (conftest puts the
# slow ones first). `make test` (under 15 minutes on 2 cores) leaves out the tests marked
# heavy: the end-to-end compiles of the whole method (a calibration, a training run, the
# experiments' smoke run, finite-difference gradients through the fit), about 35 CPU-minutes
# between them; `make test-heavy` runs those, `make test-all` both; CI (.ci/run) runs both.
pytest: $(VENV)/.dev chromium
	$(VENV)/bin/pytest -n 2 --dist worksteal -q --durations=15 -m "not heavy"

pytest-heavy: $(VENV)/.dev chromium
	$(VENV)/bin/pytest -n 2 --dist worksteal -q --durations=15 -m heavy

test: lint typecheck pytest

test-heavy: pytest-heavy

test-all: test pytest-heavy

bench: $(VENV)/.dev
	$(PY) experiments/bench.py

experiments: $(VENV)/.dev
	$(PY) experiments/run_all.py

experiments-quick: $(VENV)/.dev
	$(PY) experiments/run_all.py --quick

clean:
	rm -rf $(VENV) sinkjax-demo .pytest_cache .mypy_cache .ruff_cache
