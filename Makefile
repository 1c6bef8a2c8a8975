# racing-games: `make test` and `make demo` create .venv and install on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Tests run in one worker process per logical CPU, at most 4 (pytest-xdist): most of their
# time is XLA compilation, which keeps a process on one core most of the time. Each test
# file runs in one worker (--dist loadfile), so its module fixtures and the solvers its tests
# compile are built once, not once per worker.
# `make test WORKERS=` runs them in a single process (e.g. under a debugger).
WORKERS ?= -n logical --maxprocesses 4 --dist loadfile
PYTEST_ARGS ?= -m "not slow" $(WORKERS)

.PHONY: test test-all demo bench install clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	# torch pinned to the CPU build through constraints.txt (no CUDA packages)
	$(BIN)/python -m pip install -c constraints.txt -e ".[all]"
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# every test, slow ones included, with XLA's full optimisations (the default run compiles
# quickly: tests/conftest.py)
test-all: $(STAMP)
	RACING_TEST_OPTIMIZED=1 $(BIN)/python -m pytest -m "" $(WORKERS)

demo: $(STAMP)
	$(BIN)/racing demo

bench: $(STAMP)
	$(BIN)/racing bench

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
