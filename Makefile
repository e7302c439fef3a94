# Quick start: `make demo` and `make test` each work on a fresh machine with Python >= 3.11.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint format typecheck install bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[test,dev,phiflow]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/physgrad demo

test: $(STAMP)
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check src tests
	$(BIN)/ruff format --check src tests

format: $(STAMP)  # rewrites files: ruff's safe fixes (import order, unused imports), then the formatter
	$(BIN)/ruff check --fix src tests
	$(BIN)/ruff format src tests

# pyright's PyPI wrapper runs the pyright it bundles on the `node` on PATH (none: it would
# download one); IGNORE_WARNINGS skips its check for a newer release.
typecheck: $(STAMP)
	PYRIGHT_PYTHON_IGNORE_WARNINGS=1 $(BIN)/pyright --pythonpath $(BIN)/python

bench: $(STAMP)
	$(BIN)/python benchmarks/hig_step.py

clean:
	rm -rf $(VENV) runs studies
