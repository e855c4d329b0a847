# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: demo test bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

# Each command writes its folder atomically and replaces it whole with --overwrite: the demo
# replaces out/ (the previous out/center_out with it), then center-out writes out/center_out.
# The command line keeps its compiled solvers in a persistent cache (~/.cache/delayed-ilqr/jax,
# or $DELAYED_ILQR_CACHE_DIR), so a second `make demo` does not compile them again;
# DELAYED_ILQR_NO_CACHE=1 turns that off.
# The demo's center-out study is the small one: the noise-aware and deterministic designs at 0 and
# 100 ms. The full study (also the statistical re-design, which is most of its time, and 0, 50, 100,
# 150 ms) is `delayed-ilqr center-out --allow-unconverged --out center_out_full`
# (docs/guide/delay_sweeps.md).
# Last, the gallery's mid-reach kick on the six-muscle arm with its defaults, small (20 trials); the
# full size is `delayed-ilqr kick --trials 200 --out kick` (docs/gallery/kick.md).
demo: $(STAMP)
	$(BIN)/delayed-ilqr demo --overwrite --out out
	$(BIN)/delayed-ilqr center-out --design noise-aware --design deterministic --delays 0,0.1 \
		--allow-unconverged --overwrite --out out/center_out
	$(BIN)/delayed-ilqr kick --trials 20 --overwrite --out out/kick

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=30 tests

$(BENCH_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e '.[bench]'
	touch $(BENCH_STAMP)

# last, the full-size studies whose smaller versions `make test` runs (the tests marked `full`)
bench: $(BENCH_STAMP)
	$(BIN)/python benchmarks/run.py
	$(BIN)/python benchmarks/solve_p1_p2.py
	$(BIN)/python benchmarks/bounded.py
	$(BIN)/python -m pytest -q -m full tests

# the documentation site into site/ (strict: a broken reference fails); the test extra installs
# the docs extra, so the stamp of `make test` covers it
docs: $(STAMP)
	$(BIN)/python -m mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) out site .pytest_cache .hypothesis
