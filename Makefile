# Two commands for a newcomer: `make run` (service on the simulated rack) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

# on a terminal: the whole simulated system (rack, service, controller flying a demo path)
# with the operator console (q or Ctrl-C stops everything, outputs 0 V); else the plain line view
run: $(STAMP)
	@if [ -t 1 ]; then $(BIN)/pfma console --sim; else $(BIN)/pfma serve --rack fake --live --demo; fi

# two passes: the deterministic tests on two workers, then the real-time ones (marked
# realtime: they start processes or wait on wall-clock time) alone, so load cannot fail them
test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -m "not lab and not realtime"
	$(BIN)/python -m pytest -m "realtime and not lab"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/lint-imports --no-cache
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/pfma bench

clean:
	rm -rf $(VENV) build *.egg-info
