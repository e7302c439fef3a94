# Quick start: `make demo` and `make test` each work on a fresh machine with Python >= 3.11.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-typed test-slow test-all lint format typecheck docs install bench dist clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[all,test,dev,docs]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/physgrad demo

# `make test`: every test but the slow tier, on every core (pytest-xdist), in under 7 minutes
# on 2 cores (a fast-tier test over 5 s of CPU says why, @pytest.mark.costly("..."), or is slow:
# the run ends with a list of those that do neither, tests/conftest.py); `make test-slow`: the
# end-to-end command-line studies and paper-size builds; `make test-all`: both. CI (.ci/run) runs make test, then make test-slow.
# --dist loadfile: a module's tests run in one worker, so its module fixtures (generated
# data, reference rollouts) are built once, not once per worker
PYTEST := $(BIN)/python -m pytest -n auto --dist loadfile --durations=30

test: $(STAMP)
	$(PYTEST) -m "not slow"

# the fast tier again with physgrad's jaxtyping annotations checked at run time (beartype
# through jaxtyping's import hook, tests/conftest.py); a test that passes a wrong type on
# purpose, to check physgrad's own one-line error, is marked unchecked. CI runs it.
test-typed: $(STAMP)
	$(PYTEST) -m "not slow" --jaxtyping

test-slow: $(STAMP)
	$(PYTEST) -m slow

test-all: $(STAMP)
	$(PYTEST)

# the library, the tests and the scripts beside them (pyproject.toml's [tool.ruff] leaves out the
# notebooks and the Markdown pages)
LINT_PATHS := src tests examples benchmarks docs

lint: $(STAMP)
	$(BIN)/ruff check $(LINT_PATHS)
	$(BIN)/ruff format --check $(LINT_PATHS)

format: $(STAMP)  # rewrites files: ruff's safe fixes (import order, unused imports), then the formatter
	$(BIN)/ruff check --fix $(LINT_PATHS)
	$(BIN)/ruff format $(LINT_PATHS)

# pyright's PyPI wrapper runs the pyright it bundles on the `node` on PATH (none: it would
# download one); IGNORE_WARNINGS skips its check for a newer release.
typecheck: $(STAMP)
	PYRIGHT_PYTHON_IGNORE_WARNINGS=1 $(BIN)/pyright --pythonpath $(BIN)/python

# The API reference site (mkdocs.yml: docs/ and the docstrings) into site/; --strict: any
# warning (a broken link, an unknown cross-reference) fails. Open site/index.html.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

# The sdist and the wheel into dist/ (python -m build: hatchling in an isolated environment).
# Neither carries the studies' data: pyproject.toml's [tool.hatch.build.targets.sdist] leaves
# out docs/reproductions/data and figures and the benches' run directories; the wheel is
# src/physgrad alone. `pip install dist/physgrad-*.whl` installs it (.ci/smoke.sh checks that).
dist: $(STAMP)
	rm -rf dist
	$(BIN)/python -m build --outdir dist .

bench: $(STAMP)
	$(BIN)/python benchmarks/hig_step.py

# The lowest versions pyproject.toml allows, pinned exactly (core and every extra): the suite
# runs against them in a venv of its own, so the declared floors stay tested. A floor changes
# here and in pyproject.toml together (tests/test_packaging.py checks that they agree).
FLOORS := jax==0.8.2 jaxlib==0.8.2 equinox==0.13.2 jaxtyping==0.2.34 optax==0.2.5 optimistix==0.0.11 \
          lineax==0.1.0 numpy==2.0.0 matplotlib==3.8.4 rich==13.0.0 scipy==1.13.0 threadpoolctl==3.8.0 \
          kfac-jax==0.0.8 exponax==0.2.0 phiflow==3.4.0 phiml==1.16.0 tensorboardX==2.6.5 \
          optuna==4.0.0 distributed==2024.8.0 psycopg2-binary==2.9.9
FLOORS_VENV ?= .venv-floors

.PHONY: test-floors
test-floors:
	rm -rf $(FLOORS_VENV)
	$(PYTHON) -m venv $(FLOORS_VENV)
	$(FLOORS_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(FLOORS_VENV)/bin/python -m pip install --quiet -e ".[all,test]" $(FLOORS)
	$(FLOORS_VENV)/bin/python -m pytest -n auto --dist loadfile -m "not slow"

clean:
	rm -rf $(VENV) $(FLOORS_VENV) runs studies site dist
