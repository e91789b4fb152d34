# Every user-facing target sets itself up: a fresh machine needs only python3 (>= 3.10) and make.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
RUNS ?= 200

.PHONY: demo test bench clean

# (Re)create the virtual environment whenever pyproject.toml changes.
$(VENV): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e '.[dev,sim,gcs]'
	# compile the companion's kernels once (numba caches them; the first start would otherwise pay it)
	$(BIN)/companion kernels
	touch $(VENV)

# Main job, the closed loop: the quad is commanded at 6 m/s through a textured wall in JSBSim; the
# companion (lockstep SITL over MAVLink on free loopback ports) ranges it and the simulated
# autopilot's ArduPilot avoidance stops the quad short on those ranges. Prints where it stopped, the
# clearance and the message scores; the top-down plot is out/demo/avoidance.png.
demo: $(VENV)
	$(BIN)/flightsim sitl configs/scenarios/quad_avoid_wall_6.toml --avoidance ardupilot --out out/demo --mavlink-port 0 --camera-port 0

test: $(VENV)
	$(BIN)/python -m pytest -q

# All benchmarks; rewrites docs/BENCHMARKS.md with the figures and the commands behind them.
bench: $(VENV)
	$(BIN)/python -m bench all --runs $(RUNS) --write docs/BENCHMARKS.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
