# Two commands for a newcomer: `make run` (service on the simulated rack) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint bench soak flood chaos clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

# on a terminal: the whole simulated system (rack, service, controller flying a demo path)
# with the operator console (q or Ctrl-C stops everything, outputs 0 V); else the plain line view.
# Both on the buffer pfma (the console: and world model pfma_wm) that every tool reads by
# default; while another system runs there, on a private name said in one line
run: $(STAMP)
	@if [ -t 1 ]; then $(BIN)/pfma console --sim; else $(BIN)/pfma serve --rack fake --live --demo --private-if-busy; fi

# two passes: the deterministic tests on two workers, then the real-time ones (marked
# realtime: they start processes or wait on wall-clock time) alone, so load cannot fail them
test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -m "not lab and not realtime" --durations=20
	$(BIN)/python -m pytest -m "realtime and not lab and not chaos" --durations=15

# the kill matrix, CI-sized (tests/chaos/test_kill_matrix.py, ~2.5 min): real processes killed
# under the simulated stack, every check asserted; CI runs it after make test (a chaos run is a
# benchmark's length, so make test stays shorter); pfma bench chaos --trials 100 is the full one
chaos: $(STAMP)
	$(BIN)/python -m pytest -m chaos tests/chaos

# ruff (with the complexity gate, C901 over 20), the length gate (devtools/function_length.py),
# radon's grades (devtools/complexity_grades.py: at most 10 functions rate D or worse), the
# import contracts (the floors and no import circle), mypy
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python devtools/function_length.py
	$(BIN)/python devtools/complexity_grades.py
	$(BIN)/lint-imports --no-cache
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/pfma bench

# the soak, judged (issue 20; CI runs it after make test): the simulated stack for
# SOAK_MINUTES, exit 1 naming each failed criterion (docs/chaos.md). --realtime (the service
# and the controller SCHED_FIFO on pinned CPUs, as the kill matrix in make test runs them)
# where this user may set SCHED_FIFO, e.g. root; else without it, and it says so.
SOAK_MINUTES ?= 10
FIFO_OK = $(BIN)/python -c 'import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))' 2>/dev/null
soak: $(STAMP)
	@if $(FIFO_OK); \
	then rt=--realtime; else rt=; echo "make soak: SCHED_FIFO not permitted for this user: the soak runs without --realtime"; fi; \
	echo "$(BIN)/pfma bench soak --minutes $(SOAK_MINUTES) --check $$rt"; \
	$(BIN)/pfma bench soak --minutes $(SOAK_MINUTES) --check $$rt

# the Modbus flood, judged (issue 20: <= 5 extra dropped frames per 10 s under 2,000 reads/s;
# CI runs it after the soak): only with --realtime (SCHED_FIFO). A time-sharing service's
# dropped frames on a shared 2-core host are the host's (one quiet 10 s run dropped 204), so
# without SCHED_FIFO the figure is not judged and this says so (docs/reliability.md)
flood: $(STAMP)
	@if $(FIFO_OK); \
	then echo "$(BIN)/pfma bench flood --rounds 5 --realtime --check"; $(BIN)/pfma bench flood --rounds 5 --realtime --check; \
	else echo "make flood: SCHED_FIFO not permitted for this user: the Modbus flood is not judged (pfma bench flood --realtime --check)"; fi

clean:
	rm -rf $(VENV) build *.egg-info
