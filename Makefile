# The two commands of the README. Both bootstrap what they need (scripts/bootstrap.sh).
VENV ?= .venv
BIN := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: demo test bootstrap

bootstrap:
	@bash scripts/bootstrap.sh

demo: bootstrap
	$(BIN)/nerfpipe demo

test:
	@bash scripts/bootstrap.sh --test
	$(BIN)/python -m pytest -q -n 2 $(PYTEST_ARGS)
