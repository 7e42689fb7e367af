# gpg: the two commands of the README.
#   make test       create .venv, install gpg with its dev extra, run ruff and pytest (fast set)
#   make test-slow  the slow tests too: whole experiments and subprocess runs (minutes)
#   make test-xla   the fast set under another XLA CPU configuration (XLA_ALT), optimised
#   make compare    create .venv, install gpg, run every model on data=default
#   make docs       the documentation site into site/ (warnings are errors; notebooks executed)
#   make api        docs/api.md written again from the packages' __all__ (a test checks it)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DOCS_STAMP := $(VENV)/.installed-docs

# The other compiler configuration of `make test-xla`: SSE4.2 code instead of AVX2, and float32
# products in XLA's own kernels instead of YNNPACK's, which choose their blocking from the CPU
# they find (what made a float32 variance differ between two machines of the same kind).
XLA_ALT ?= --xla_cpu_max_isa=SSE4_2 --xla_cpu_experimental_ynn_fusion_type=

.PHONY: test test-slow test-xla compare docs api lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $(DOCS_STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Two workers, one test file each at a time: the suite is bound by XLA compilation, which runs
# on one core per process, so two processes use both cores of the CI machine. The 15 slowest
# tests are listed at the end: the fast set has a 5-minute budget on the development machine.
test: lint
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=15

# Machine dependence before CI sees it: the same tests with the users' compiler settings (the
# fast set compiles for speed of compilation, tests/conftest.py) under XLA_ALT; a test that
# passes one and fails the other pins one configuration's bits.
test-xla: lint
	GPG_FAST_COMPILE=0 XLA_FLAGS="$(XLA_ALT)" $(PY) -m pytest -q -n 2 --dist loadfile

test-slow: lint
	$(PY) -m pytest -q -n 2 --dist loadfile -m slow

compare: $(STAMP)
	$(PY) -m experiments.compare

# The notebooks run on the first build (about 4 minutes) and are cached under build/docs/ by
# their bytes; --strict fails on any warning: a broken link or anchor, a reference target that
# does not exist, a docstring that does not parse.
docs: $(DOCS_STAMP)
	$(VENV)/bin/mkdocs build --strict

api: $(STAMP)
	$(PY) docs/_site/hooks.py

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache .ruff_cache site build/docs
