# jaxland: two commands on a fresh machine with Python 3.11.
#   make demo   simulate the paper's 0.2 m drop: out/paper-drop/{trajectory.csv, summary.json,
#               scene.toml, vehicle.toml, effective_vehicle.toml, figures/}
#   make test   run the test suite (17 to 19 minutes on 2 cores)
# Both create .venv and install jaxland from pyproject.toml on first use.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
ifeq ($(strip $(PYTHON)),)
$(error no python3.11 or python3 on PATH: install Python 3.11 (with venv), or run make PYTHON=/path/to/python)
endif
VENV := .venv
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test bench bench-integrators paper docs notebooks lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/jaxland simulate --out out/paper-drop

# The suite is mostly XLA compilation, which runs on one core: two worker processes (pytest-xdist),
# each test file whole on one worker so that its module fixtures compile once.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# Measurements: write benchmarks/results/ (summaries, tracked) and benchmarks/results/raw/
# (full dumps, ignored). Add --quick by hand for a smoke run; it writes out/bench-quick/.
bench: $(STAMP)
	$(VENV)/bin/python benchmarks/bench_landing.py

bench-integrators: $(STAMP)
	$(VENV)/bin/python benchmarks/bench_integrators.py

paper: $(STAMP)
	$(VENV)/bin/python benchmarks/paper_reproduction.py

# the measured tables in docs/ from benchmarks/results/*.json (the tests run it with --check)
docs: $(STAMP)
	$(VENV)/bin/python benchmarks/docs_tables.py

# execute the notebooks at small size and store their outputs and figures
notebooks: $(STAMP)
	$(VENV)/bin/python notebooks/execute.py --write

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) out .pytest_cache
