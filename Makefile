# Two commands do all the set-up on a fresh machine (see README.md):
#   make run    create .venv, install mcrs (without the dev extra), train CNN-SEMU on map10 for a few
#               minutes (budget=quickstart), then evaluate it against the heuristics: table, learning curve and GIF in <run dir>/report/.
#               make run ARGS="seed=1"; the paper's 2M-step run: make run ARGS="budget=paper"
#   make test   create .venv, install mcrs with the dev extra and run the fast tests (make test-slow: the
#               rest; CI runs both, see .ci/run). Tests run in TEST_WORKERS=2 processes (make test TEST_WORKERS=0: one)
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: install run test test-slow test-all lint bench clean

# The dev extra (pytest, ruff, the launchers the tests run: Ray's is large) is for `make test`;
# `make run` needs only the package, so a first run does not wait for it.
$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $@ $(BIN)/.installed-run

$(BIN)/.installed-run: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -e .
	touch $@

install: $(BIN)/.installed

ARGS ?=
# pytest-xdist workers for the test targets: the tests run one torch thread each, so one per core.
TEST_WORKERS ?= 2

run: $(BIN)/.installed-run
	$(BIN)/mcrs-train budget=quickstart $(ARGS)

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: install
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m "not slow"

test-slow: install
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m slow

test-all: install
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

bench: install
	$(BIN)/mcrs-bench-env
	$(BIN)/mcrs-bench-learner

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
