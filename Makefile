# o3drbf: `make demo` and `make test` set everything up, then do their job.
PY      := .venv/bin/python
SETUP   := .venv/.installed
OUT     ?= out
export OMP_NUM_THREADS ?= 2

.PHONY: setup demo test bench bench-paper figures clean

setup: $(SETUP)

$(SETUP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh

demo: $(SETUP)
	$(PY) samples/demo.py --out $(OUT)

test: $(SETUP)
	$(PY) -m pytest -q -rs

bench: $(SETUP)
	$(PY) benchmarks/run.py

bench-paper: $(SETUP)
	$(PY) benchmarks/paper/run_all.py --out results/paper

figures: $(SETUP)
	$(PY) samples/demo.py --out $(OUT)/figures
	mkdir -p docs/images && cp $(OUT)/figures/demo.png docs/images/demo.png

clean:
	rm -rf $(OUT) .pytest_cache
