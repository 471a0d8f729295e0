# Each target creates .venv on first use; `make test` is what CI runs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test test-all bench bench-s1 reproduce reproduce-s1 reproduce-s2 reproduce-s3 reproduce-s4 results clean catalog

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/activate
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $@

# The demo needs opnav alone, not the test and benchmark extras. Its first run compiles opnav's numba
# kernels (about half a minute on 2 cores, saying so before the progress bars start); later runs load them.
$(VENV)/.installed-demo: pyproject.toml | $(BIN)/activate
	$(BIN)/python -m pip install --quiet -e .
	touch $@

demo: $(VENV)/.installed-demo
	$(BIN)/opnav --help
	$(BIN)/opnav demo

# `make test`: the suite without the long statistical and end-to-end runs (pyproject's addopts
# deselect -m slow; each has a fast sibling at small size that runs here). `make test-all`: everything.
# Both compile the numba kernels numba's cache lacks first, in one process per core, so that the tests
# and the processes they start load them instead of each compiling them (a second or two when cached),
# then run the tests in one pytest-xdist worker per core (-n auto). --dist worksteal: a worker that runs
# out of tests takes half of the other's queue (with the default, one worker ran the long study tests
# at the end for ~30 % of the wall while the other had finished).
test: $(VENV)/.installed
	$(BIN)/opnav compile
	$(BIN)/python -m pytest -q -n auto --dist worksteal

test-all: $(VENV)/.installed
	$(BIN)/opnav compile
	$(BIN)/python -m pytest -q -n auto --dist worksteal -m 'slow or not slow'

# Each benchmark prints its figures; figures quoted in issue notes come from these runs.
BENCHMARKS := propagate render centroid starid image_stage filters s2_observability s4_registration

bench: $(VENV)/.installed
	@for name in $(BENCHMARKS); do echo "== benchmarks/$$name.py"; $(BIN)/python benchmarks/$$name.py || exit 1; done

# The S1 Monte Carlo campaign (50 runs x 43,200 updates; about half an hour on 2 cores, resumable).
bench-s1: $(VENV)/.installed
	$(BIN)/python benchmarks/s1_filters.py --runs 50 --month jul --targets both --noise-arcsec 0.1 --workers 2

# S1 Tables 2 and 3: 4 months x 3 target sets x 2 noise levels, EKF and UKF, 50 seeds each, every row its
# own seeds (1,200 runs of 30 days; 45 min on 2 cores at load 16-28; resumable). Table in out/reproduce/s1/sweep.md; the README's
# (make results) holds each row's RMS over seeds against the posterior Cramér-Rao bound with its interval.
reproduce-s1: $(VENV)/.installed
	$(BIN)/opnav montecarlo samples/s1_jul_both_0.1.toml --runs 50 --workers 2 --filters ekf,ukf \
		--out out/reproduce/s1 --sweep month=may,jun,jul,aug --sweep targets=phobos,deimos,both \
		--sweep noise_arcsec=0.1,1 --no-progress

# S2 Tables 1-3 (observability per measurement set; switching EKF error after convergence), 10 seeds.
reproduce-s2: $(VENV)/.installed
	$(BIN)/opnav montecarlo samples/s2_capture.toml --runs 10 --out out/reproduce/s2 --no-progress

# S3 Table 4: EKF, UKF and MCMC-UPF (150 particles), 24 h at 10 s, 5 seeds, with the study's noise and
# with the sensors' (about 10 min each on 2 cores).
reproduce-s3: $(VENV)/.installed
	$(BIN)/opnav montecarlo samples/s3_geo.toml --runs 5 --workers 2 --filters ekf,ukf,mcmc-upf \
		--out out/reproduce/s3 --no-progress
	$(BIN)/opnav montecarlo samples/s3_geo.toml --runs 5 --workers 2 --filters ekf,ukf,mcmc-upf \
		--set noise_model=sensors --out out/reproduce/s3_sensors --no-progress

# S4: federated filter with and without time registration (and the exact reference), 5 seeds.
reproduce-s4: $(VENV)/.installed
	$(BIN)/opnav montecarlo samples/s4_approach.toml --runs 5 --out out/reproduce/s4 --no-progress

reproduce: reproduce-s1 reproduce-s2 reproduce-s3 reproduce-s4 results

# The README's results section, generated from out/reproduce (whatever campaigns are there).
results: $(VENV)/.installed
	$(BIN)/python benchmarks/results.py --reproduce out/reproduce --readme README.md

# The default star catalog is package data (opnav/data/stars.npz, described in opnav/data/stars.README.md).
catalog: $(VENV)/.installed
	$(BIN)/python -m pip install --quiet -e '.[catalog]'
	$(BIN)/python catalogs/build_catalog.py --output opnav/data/stars.npz

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
