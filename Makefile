# The README's commands. Every target builds .venv itself, so a fresh clone needs only python3 (>= 3.11).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench chaos load lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/colony demo

# Two test processes: most tests wait on processes and sockets (docs/architecture.md).
test: $(STAMP)
	$(BIN)/pytest -n 2

bench: $(STAMP)
	@for f in bench/[!_]*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

chaos: $(STAMP)
	$(BIN)/python chaos/chaos.py

load: $(STAMP)
	$(BIN)/python chaos/load.py $(if $(SECONDS),--seconds $(SECONDS))

# bench/ gets its own mypy run: bench/colony.py would clash with the colony package.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/mypy bench

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build *.egg-info
