# o3drbf: `make demo` and `make test` set everything up, then do their job.
PY      := .venv/bin/python
SETUP   := .venv/.installed
BENCH   := .venv/.bench-installed
OUT     ?= out
TEMPLE  ?= ../shared/data/middlebury_templeSparseRing
export OMP_NUM_THREADS ?= 2

.PHONY: setup demo test test-fast samples bench bench-user bench-check bench-tiles bench-tiles-large bench-paper figures clean

setup: $(SETUP)

$(SETUP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh

# The benchmarks' peers beyond Open3D (ferreus_rbf: the extra "bench" of pyproject.toml).
$(BENCH): $(SETUP)
	$(PY) -m pip install -q -e ".[test,bench]" && touch $(BENCH)

demo: $(SETUP)
	$(PY) samples/demo.py --out $(OUT)

samples: $(SETUP)
	$(PY) samples/generate.py $(OUT)/samples

# The whole suite in TEST_WORKERS processes (pytest-xdist; the slowest tests, compiling and end to end, run beside the rest);
# a crash in a command the tests start prints its Python stack (PYTHONFAULTHANDLER).
TEST_WORKERS ?= 2
test: $(SETUP)
	PYTHONFAULTHANDLER=1 $(PY) -m pytest -q -rs -n $(TEST_WORKERS) --dist worksteal

# The tests not marked slow (tests/conftest.py lists them): under a minute on 2 cores.
test-fast: $(SETUP)
	$(PY) -m pytest -q -m "not slow" --durations=5

bench: $(BENCH)
	$(PY) benchmarks/run.py

# The user's path alone, recorded as data (benchmarks/recorded/) for docs/benchmarks.md; then check the page quotes it.
bench-user: $(BENCH)
	$(PY) benchmarks/user_path.py --record benchmarks/recorded/user_path.json
	$(PY) benchmarks/check_recorded.py

bench-check: $(SETUP)
	$(PY) benchmarks/check_recorded.py

# Tiled reconstruction from a file vs Open3D Poisson depth 10: 1M points with --tiles 17 (--tiles auto runs
# 1M untiled where it fits in memory), a few minutes on 2 cores.
bench-tiles: $(SETUP)
	$(PY) benchmarks/tiles.py --points 1000000 --tiles 17

# Opt-in, not part of `make bench`: 10,000,000 points with the command's defaults (--tiles auto), Poisson
# depth 10 and 11 (about 15 minutes on 2 cores).
bench-tiles-large: $(SETUP)
	$(PY) benchmarks/tiles.py --large --depth11

# The paper's figures, the robustness study and the settings sweep: long (start it and come back much later).
bench-paper: $(SETUP)
	$(PY) benchmarks/paper/run_all.py --out results/paper

figures: $(SETUP)
	$(PY) samples/demo.py --out $(OUT)/figures
	mkdir -p docs/images && cp $(OUT)/figures/demo.png docs/images/demo.png
	$(PY) scripts/run_notebook.py docs/quickstart.ipynb --figure docs/images/quickstart.png
	$(PY) -m o3drbf.viewers.sample_scan $(OUT)/figures/tori_scan.json
	$(PY) -m o3drbf.cli view $(OUT)/figures/tori_scan.json --screenshot docs/images/viewer.png --zoom 0.5
	$(PY) samples/generate.py $(OUT)/figures/samples
	$(PY) -m o3drbf.cli compare $(OUT)/figures/samples/scan.json --truth $(OUT)/figures/samples/reference.ply -o $(OUT)/figures/compare
	cp $(OUT)/figures/compare/comparison.png docs/images/compare.png
	@if [ -f results/paper/robustness.png ]; then cp results/paper/robustness.png docs/images/robustness.png; \
	else echo "figures: run make bench-paper for docs/images/robustness.png"; fi
	@if [ -d $(TEMPLE) ]; then \
	  .venv/bin/o3drbf photos $(TEMPLE) --calibration $(TEMPLE)/templeSR_par.txt -o $(OUT)/figures/temple.ply --picture docs/images/fig9_temple.png; \
	else echo "figures: skipping Fig. 9 (needs $(TEMPLE))"; fi

clean:
	rm -rf $(OUT) .pytest_cache
