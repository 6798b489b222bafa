# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Each creates the virtual environment .venv in the repository and installs robotd into it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint clean readme

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,plot]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/robotd check-config config/robot.yaml
	$(BIN)/robotd check-config config/sim.yaml

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test: lint
	$(BIN)/pytest

readme: $(STAMP)
	$(BIN)/robotd readme README.md

clean:
	rm -rf $(VENV)
