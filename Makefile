# Each target creates .venv on first use; `make test` is what CI runs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test bench clean catalog

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/activate
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $@

demo: $(VENV)/.installed
	$(BIN)/opnav --help
	$(BIN)/opnav demo

test: $(VENV)/.installed
	$(BIN)/python -m pytest -q

bench: $(VENV)/.installed
	$(BIN)/python benchmarks/propagate.py

catalog: $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e '.[catalog]'
	$(BIN)/python catalogs/build_catalog.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
