# Each target creates .venv on first use; `make test` is what CI runs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test bench bench-s1 reproduce-s1 clean catalog

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

# Each benchmark prints its figures; figures quoted in issue notes come from these runs.
BENCHMARKS := propagate render centroid starid image_stage filters s2_observability s4_registration

bench: $(VENV)/.installed
	@for name in $(BENCHMARKS); do echo "== benchmarks/$$name.py"; $(BIN)/python benchmarks/$$name.py || exit 1; done

# The S1 Monte Carlo campaign (50 runs x 43,200 updates; about half an hour on 2 cores, resumable).
bench-s1: $(VENV)/.installed
	$(BIN)/python benchmarks/s1_filters.py --runs 50 --month jul --targets both --noise-arcsec 0.1 --workers 2

# S1 Tables 2 and 3: 4 months x 3 target sets x 2 noise levels, EKF and UKF, 10 seeds each
# (240 runs of 30 days; about an hour on 2 cores; resumable). Table in out/reproduce/s1/sweep.md.
reproduce-s1: $(VENV)/.installed
	$(BIN)/opnav montecarlo samples/s1_jul_both_0.1.toml --runs 10 --workers 2 --filters ekf,ukf \
		--out out/reproduce/s1 --sweep month=may,jun,jul,aug --sweep targets=phobos,deimos,both \
		--sweep noise_arcsec=0.1,1 --no-progress

catalog: $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e '.[catalog]'
	$(BIN)/python catalogs/build_catalog.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
