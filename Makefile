# sb3-pearl: two set-up commands, `make demo` and `make test`, both install from scratch.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup test test-slow demo docs lint type bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch first: a local CPU wheel; letting pip choose torch pulls a multi-GB CUDA build.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[dev]" -c constraints.txt
	touch $(STAMP)

setup: $(STAMP)

test: setup docs
	# one module per worker at a time, dealt longest first (tests/conftest.py) instead of by test count; a test that
	# hangs (an in-process command, a child process) fails after 10 minutes instead of blocking its worker
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --timeout 600

test-slow: setup
	$(BIN)/python -m pytest -q -m slow

demo: setup
	$(BIN)/python -m pearl_paper.demo

docs: setup
	# the documentation site (Sphinx + MyST, API pages from the docstrings); a warning fails the build
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

type: setup
	$(BIN)/mypy sb3_pearl pearl_paper

bench: setup
	$(BIN)/python benchmarks/throughput.py

clean:
	rm -rf $(VENV) build *.egg-info docs/_build
