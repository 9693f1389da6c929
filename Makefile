# gctr — two commands do everything on a fresh machine:
#   make demo   set up, generate a small cross-source set from the shipped data, register it
#   make test   set up and run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DEMO   ?= demo_out

.PHONY: setup system-deps demo test bench-engine clean help

help:
	@echo "make demo          set up and run gctr batch on a small cross-source set (results in $(DEMO)/)"
	@echo "make test          set up and run the test suite"
	@echo "make bench-engine  full engine benchmark -> bench/ENGINE.md (tens of minutes)"

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

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# Reinstall when the project metadata changes.
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $@

setup: system-deps $(VENV)/.installed

demo: setup
	rm -rf $(DEMO)
	$(BIN)/python -m data_scripts.make_benchmark demo --out $(DEMO)/data
	$(BIN)/gctr batch $(DEMO)/data/pairs.csv -c configs/default.yaml -o $(DEMO)/results

test: setup
	$(BIN)/python -m pytest -q

bench-engine: setup
	$(BIN)/python -m data_scripts.bench_engine --levels easy,cross,hard,real --out bench/ENGINE.md

clean:
	rm -rf $(DEMO) .pytest_cache build *.egg-info
