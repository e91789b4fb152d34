# Every user-facing target sets itself up: a fresh machine needs only python3 (>= 3.10) and make.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
RUNS ?= 200

.PHONY: demo test bench clean

# (Re)create the virtual environment whenever pyproject.toml changes.
$(VENV): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e '.[dev]'
	touch $(VENV)

# Main job: fly quad_approach in JSBSim with the companion in the loop (lockstep SITL over MAVLink on
# free loopback ports), score its messages against truth and print the score table.
demo: $(VENV)
	$(BIN)/flightsim sitl configs/scenarios/quad_approach.toml --out out/demo --mavlink-port 0 --camera-port 0

test: $(VENV)
	$(BIN)/python -m pytest -q

# All benchmarks; rewrites docs/BENCHMARKS.md with the figures and the commands behind them.
bench: $(VENV)
	$(BIN)/python -m companion.bench all --runs $(RUNS) --write docs/BENCHMARKS.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
