# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Each creates the virtual environment .venv in the repository and installs robotd into it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo docs test lint clean readme

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,plot]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/robotd demo --out out/demo

# Regenerates the README's figures: the offline experiment, the benchmarks, then the README's generated blocks.
docs: $(STAMP)
	$(BIN)/robotd experiment square --loops 3 --seeds 10 --out docs/results --librsf ../shared/datasets/librsf_labyrinth_uwb
	$(BIN)/robotd bench --report docs/bench.md --json docs/bench.json
	$(BIN)/robotd readme README.md

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
