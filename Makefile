# The README's commands. Every target builds .venv itself, so a fresh clone needs only python3 (>= 3.11).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
RUNTIME := $(VENV)/.runtime-installed
DEV := $(VENV)/.dev-installed

.PHONY: demo test bench chaos load lint screenshots clean

# The product's dependencies only: enough for demo, bench and load.
$(RUNTIME): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e .
	touch $@

# The test and lint tools on top (pytest, hypothesis, playwright, mypy, ruff...).
$(DEV): $(RUNTIME)
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

demo: $(RUNTIME)
	$(BIN)/colony demo

# Two test processes: most tests wait on processes and sockets (docs/architecture.md).
test: $(DEV)
	$(BIN)/pytest -n 2

bench: $(RUNTIME)
	@for f in bench/[!_]*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

# The scheduler's interleaving properties with thousands of examples, then real processes killed.
chaos: $(DEV)
	$(BIN)/pytest -q tests/test_scheduler.py -k interleaving --hypothesis-profile=chaos
	$(BIN)/python chaos/chaos.py

load: $(RUNTIME)
	$(BIN)/python chaos/load.py $(if $(SECONDS),--seconds $(SECONDS))

# The dashboard's pictures in docs/img, retaken from a colony started for them (headless Chromium).
screenshots: $(DEV)
	$(BIN)/python tools/screenshots.py

# bench/ gets its own mypy run: bench/colony.py would clash with the colony package.
lint: $(DEV)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/mypy bench

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build *.egg-info
