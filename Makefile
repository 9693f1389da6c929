# gctr — two commands do everything on a fresh machine:
#   make demo   set up, generate a small cross-source set from the shipped data, register it
#   make test   set up and run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DEMO   ?= demo_out
# Benchmark data (issue 9): every level; the engine is tuned on seed 1 and reported on seed 0.
BENCH_LEVELS ?= easy,cross,hard,real,part,lowoverlap,sfm,scene
SHARED       ?= ../shared/data

.PHONY: setup system-deps browser-deps demo test test-fast lint typecheck bench-engine bench-engine-tune clean help

help:
	@echo "make demo          set up and run gctr batch on a small cross-source set (results in $(DEMO)/)"
	@echo "make test          set up and run the test suite (2 processes; TEST_JOBS=0 for one)"
	@echo "make setup         only set up: libusb-1.0-0 and .venv with gctr[dev] (tests, benchmarks, dask)"
	@echo "make test-fast     the test suite without the tests marked slow (pytest -n 2 -m 'not slow')"
	@echo "make lint          ruff check (rules in pyproject.toml)"
	@echo "make typecheck     mypy with the pydantic plugin (packages in pyproject.toml)"
	@echo "make bench-engine  full engine benchmark on the report set (seed 0) -> bench/ENGINE.md (tens of minutes),"
	@echo "                   per-stage times compared with bench/stages-before-speed.md (before the speed work)"
	@echo "make bench-engine-tune  the same on the tuning set (seed 1) -> bench/work/ENGINE-seed1.md"
	@echo "make bench         gctr vs icp, fpfh_ransac, fgr, cpd, kiss_matcher on the report set -> bench/RESULTS.md (long)"
	@echo "make bench-quick   the same on 26 pairs, < 5 min -> bench/work/compare-quick/RESULTS.md"
	@echo "make bench-process whole-process time of gctr register (engine + comparison methods) vs an Open3D script,"
	@echo "                   one core -> bench/PROCESS.md"
	@echo "make bench-probes  pairs outside the benchmark: sparse (300-1200 points), unrelated (wrong files paired) and"
	@echo "                   mirrored (a flipped axis) from the shipped models -> bench/SPARSE.md, bench/UNRELATED.md,"
	@echo "                   bench/MIRRORED.md (about 13 min)"
	@echo "make bench-data       generate the REPORT set (--seed 0, all levels) -> bench/work/data"
	@echo "make bench-data-tune  generate the TUNING set (--seed 1, all levels) -> bench/work/data-seed1"
	@echo "                      (tune the engine on seed 1, report on seed 0; level scene reads SHARED=$(SHARED))"

# Open3D's wheel links against libusb-1.0; install it from Debian's packages when it is missing.
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "libusb-1.0-0: present"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing libusb-1.0-0 (needed by Open3D)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	else \
		echo "error: the system library libusb-1.0-0 is missing (Open3D needs it);"; \
		echo "       install it, e.g. 'sudo apt-get install libusb-1.0-0', then run make again"; exit 1; \
	fi

# Chromium renders OUTDIR/report.html in the report test (headless); skipped there when missing.
browser-deps:
	@if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then \
		echo "chromium: present"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing chromium (headless browser for the report test)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium fonts-liberation >/dev/null \
			|| echo "warning: could not install chromium; the browser test will be skipped"; \
	else \
		echo "note: chromium is not installed; the browser test of report.html will be skipped"; \
	fi

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# Reinstall when the project metadata changes (the version is read from gctr_cli/__init__.py).
$(VENV)/.installed: pyproject.toml gctr_cli/__init__.py | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $@

setup: system-deps $(VENV)/.installed

demo: setup
	rm -rf $(DEMO)
	$(BIN)/python -m data_scripts.make_benchmark demo --out $(DEMO)/data
	$(BIN)/gctr batch $(DEMO)/data/pairs.csv -c configs/default.yaml -o $(DEMO)/results

# two test processes (pytest-xdist): about 6 min instead of 8.5 on a 2-core machine; TEST_JOBS=0 runs in one
TEST_JOBS ?= 2
test: setup browser-deps
	$(BIN)/python -m pytest -q -n $(TEST_JOBS)

test-fast: setup
	$(BIN)/python -m pytest -q -n $(TEST_JOBS) -m "not slow"

lint: setup
	$(BIN)/ruff check .

typecheck: setup
	$(BIN)/mypy

# Report set (--seed 0) -> bench/ENGINE.md + bench/confidence_tradeoff.png; tuning set (--seed 1) -> bench/work/.
bench-engine: bench-data
	$(BIN)/python -m data_scripts.bench_engine --seed 0 --data bench/work/data --levels $(BENCH_LEVELS) --out bench/ENGINE.md \
		--stages-before bench/stages-before-speed.md

bench-engine-tune: bench-data-tune
	$(BIN)/python -m data_scripts.bench_engine --seed 1 --data bench/work/data-seed1 --levels $(BENCH_LEVELS) \
		--out bench/work/ENGINE-seed1.md --csv bench/work/seed1_pairs.csv

clean:
	rm -rf $(DEMO) .pytest_cache build *.egg-info

# Side-by-side benchmark of gctr and the comparison methods (issue 4): bench/RESULTS.md + bench/*.png.
.PHONY: bench bench-deps bench-quick bench-data bench-data-tune
bench-data: setup
	$(BIN)/python -m data_scripts.make_benchmark generate --levels $(BENCH_LEVELS) --pairs-per-model 10 \
		--seed 0 --shared $(SHARED) --out bench/work/data

bench-data-tune: setup
	$(BIN)/python -m data_scripts.make_benchmark generate --levels $(BENCH_LEVELS) --pairs-per-model 10 \
		--seed 1 --shared $(SHARED) --out bench/work/data-seed1

# KISS-Matcher (method kiss_matcher) for the comparison only: its wheel links the GPL-3.0 max-clique library
# PMC, so gctr does not depend on it; the benchmark installs it into the local venv.
bench-deps: setup
	@$(BIN)/python -c "import kiss_matcher" 2>/dev/null || $(BIN)/python -m pip install -q kiss-matcher==1.0.2

bench: setup bench-deps
	$(BIN)/python -m data_scripts.bench_compare --out bench/RESULTS.md

# Day-to-day variant (< 5 min on 2 cores): report in bench/work/compare-quick/RESULTS.md.
bench-quick: setup bench-deps
	$(BIN)/python -m data_scripts.bench_compare --quick

# Pairs outside the benchmark, from the shipped models: sparse clouds (300-1200 points) -> bench/SPARSE.md, and
# unrelated clouds (a manifest pairing the wrong files) -> bench/UNRELATED.md. Offsets 0 and 1000 were used for
# tuning; the reports use 50000.
.PHONY: bench-probes
bench-probes: setup
	$(BIN)/python -m data_scripts.probe_pairs --kind sparse --offset 50000 -j 2 --out bench/SPARSE.md
	$(BIN)/python -m data_scripts.probe_pairs --kind unrelated --offset 50000 -j 2 --out bench/UNRELATED.md
	$(BIN)/python -m data_scripts.probe_pairs --kind mirrored --offset 50000 --reps 4 -j 2 --out bench/MIRRORED.md

# Whole-process time of gctr register (GCTR engine and every comparison method, -c with method: X) vs the
# equivalent Open3D script, one core (issue 10): bench/PROCESS.md. kiss_matcher needs bench-deps.
.PHONY: bench-process
bench-process: setup bench-deps
	$(BIN)/python -m data_scripts.bench_process --out bench/PROCESS.md
