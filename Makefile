# Two commands set everything up: `make demo` and `make test`. Each creates .venv when missing
# and installs the project into it (compiling the C verifier kernel with the machine's cc, and
# the train extra: CI runs the training pipeline on a reduced size; the reference extra: the
# benchmark's independent solvers); nothing needs installing by hand.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test lint clean

$(STAMP): pyproject.toml setup.py $(wildcard rt_runtime/planning/kernel/*.c rt_runtime/planning/kernel/*.h)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,plot,train,reference]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/excavator-rt demo

# The checkers run first and fail the target on any finding: ruff, mypy strict, and the
# package boundaries as import-linter contracts (pyproject.toml, [tool.importlinter]).
# Bytecode is written even where the environment says not to (PYTHONDONTWRITEBYTECODE): the
# suite starts daemons, planner processes and CLIs by the dozen, and each would compile the
# package's sources again (~0.3 s a start). Two workers, each taking whole files: much of the
# suite waits on daemons, planner processes and the real-time HIL, and a file's module fixtures
# (the fault campaign) run once; 14-15 min on the 2-core machine against 24-25 min on one.
test: lint
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -n 2 --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check rt_runtime firmware_models hil_sim tests
	$(BIN)/mypy
	$(BIN)/lint-imports

clean:
	rm -rf $(VENV) build *.egg-info
