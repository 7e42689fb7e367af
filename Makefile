# gpg: the two commands of the README.
#   make test       create .venv, install gpg with its dev extra, run ruff and pytest (fast set)
#   make test-slow  the slow tests too: whole experiments and subprocess runs (minutes)
#   make compare    create .venv, install gpg, run every model on data=default
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test test-slow compare lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Two workers, one test file each at a time: the suite is bound by XLA compilation, which runs
# on one core per process, so two processes use both cores of the CI machine. The 15 slowest
# tests are listed at the end: the fast set has an 8-minute budget on the CI machine.
test: lint
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=15

test-slow: lint
	$(PY) -m pytest -q -n 2 --dist loadfile -m slow

compare: $(STAMP)
	$(PY) -m experiments.compare

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache .ruff_cache
