# Quick start: `make demo` (the tiny job) and `make test` (the test suite).
# Both create .venv and install the package with its test extras on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= out/demo

.PHONY: demo test test-all data bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $@

demo: $(VENV)/.installed
	$(PY) -m ppdjax.demo --config=ppdjax/configs/tiny.py --out=$(OUT)

# two pytest workers, each taking whole test modules (a module's fixtures are made once;
# the tiny dataset and run once per test run, shared through a file lock) in the order
# tests/conftest.py gives them (the module that makes the tiny run first, the modules that
# read it last): README gives the time from a fresh clone with empty caches
test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 --dist loadscope --no-loadscope-reorder

test-all: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 --dist loadscope --no-loadscope-reorder -m ""

data: $(VENV)/.installed
	$(PY) -m ppdjax.generate --config=ppdjax/configs/tiny.py --out=out/blocks_tiny

bench: $(VENV)/.installed
	$(PY) experiments/benchmarks/bench_physics.py

clean:
	rm -rf $(VENV) out .jax_cache
