# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Each creates the virtual environment .venv in the repository and installs robotd into it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo docs test lint clean readme test-broker

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,plot]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/robotd demo --out out/demo

# The libRSF Labyrinth UWB dataset beside the repository: real odometry for the experiment and the scorecards.
LIBRSF := ../shared/datasets/librsf_labyrinth_uwb

# Regenerates the README's figures: the offline experiment, the scorecards, the benchmarks, then the README's generated
# blocks.
docs: $(STAMP)
	$(BIN)/robotd experiment square --loops 3 --seeds 10 --out docs/results --librsf $(LIBRSF)
	$(BIN)/robotd scorecard --out docs/scorecard/sim --librsf $(LIBRSF)
	$(BIN)/robotd scorecard --out docs/scorecard/sim-lab --config config/sim-lab.yaml
	$(BIN)/robotd scorecard --out docs/scorecard/sim-heldout --seeds 6 --first-seed 4 --librsf $(LIBRSF)
	$(BIN)/robotd scorecard --out docs/scorecard/sim-lab-heldout --seeds 6 --first-seed 4 --config config/sim-lab.yaml
	$(BIN)/robotd scorecard --out docs/scorecard/sim-other --seeds 6 --first-seed 4 --config config/sim-other.yaml
	$(BIN)/robotd bench --report docs/bench.md --json docs/bench.json
	$(BIN)/robotd readme README.md

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# Two worker processes: about half of the suite waits on real time (daemons, sockets, the virtual robot), so two run it
# in a little over half the time on a two-core machine. `pytest` alone runs it in one process.
test: lint test-broker
	$(BIN)/pytest -n 2

# The fleet tests' MQTT broker: installed when missing and the machine allows it (root with apt, as in CI); never
# fails the build (without it those tests skip, and CI=true turns that skip into a failure).
test-broker:
	@if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ] && [ "$$(id -u)" = 0 ] \
		&& command -v apt-get >/dev/null 2>&1; then \
		echo "installing mosquitto (apt-get) for the fleet tests"; \
		{ DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto >/dev/null 2>&1 \
		|| { apt-get update -qq >/dev/null 2>&1 \
		&& DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mosquitto >/dev/null 2>&1; }; } \
		|| echo "could not install mosquitto: the fleet tests will skip"; \
	fi

readme: $(STAMP)
	$(BIN)/robotd readme README.md

clean:
	rm -rf $(VENV)
