# The two commands of the README: `make run` and `make test`; `make docs` builds the documentation site.
# Both create the virtual environment .venv with Python 3.11+ on first use.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
CORES ?= 2

.PHONY: run test lint venv bench docs clean

# what the lint step checks: the import layers (pyproject.toml), the code, the rules' formatting
LINT_PATHS := src tests benchmarks workflow/scripts

$(BIN)/activate:
	$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "Python 3.11 or newer is needed"'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# constraints.txt: the tested version of every package (reproducible numbers; tests/regression/tiny.json)
$(VENV)/.installed: pyproject.toml constraints.txt | $(BIN)/activate
	$(BIN)/python -m pip install -c constraints.txt -e ".[test,docs]"
	touch $@

venv: $(VENV)/.installed

run: $(VENV)/.installed
	$(BIN)/snakemake --cores $(CORES)

lint: $(VENV)/.installed
	$(BIN)/lint-imports --no-cache
	$(BIN)/ruff check $(LINT_PATHS)
	$(BIN)/snakefmt --check Snakefile workflow/rules

# --dist loadfile: the tests of one file run on one worker, so a module's fixture (a simulated and
# calibrated dataset) is built once; --no-loadscope-reorder: the files go out in the order tests/conftest.py
# gives them (the longest first), not sorted by their number of tests; --durations: the slowest tests and fixtures of every run are
# printed at the end, so the suite's cost is on record where it is paid
test: lint
	$(BIN)/python -m pytest -n $(CORES) --dist loadfile --no-loadscope-reorder -q --durations=25

# the documentation site (docs/conf.py): every warning is an error (-q: only they are printed, so that the
# test run's summary stays the last lines of .ci/run); the pages open at docs/_build/html/index.html
docs: $(VENV)/.installed
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html

bench: $(VENV)/.installed
	$(BIN)/python benchmarks/bench_stages.py

clean:
	rm -rf results .snakemake docs/_build
