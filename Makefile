# racing-games: `make test` and `make demo` create .venv and install on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?= -m "not slow"

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

test-all: $(STAMP)
	$(BIN)/python -m pytest -m ""

demo: $(STAMP)
	$(BIN)/racing demo

bench: $(STAMP)
	$(BIN)/racing bench

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
