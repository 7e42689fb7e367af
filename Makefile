# gpg: the two commands of the README.
#   make test     create .venv, install gpg with its dev extra, run ruff and pytest
#   make compare  create .venv, install gpg, run every baseline on data=default
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: test compare lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: lint
	$(PY) -m pytest -q

compare: $(STAMP)
	$(PY) -m experiments.compare

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache .ruff_cache
