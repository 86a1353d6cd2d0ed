# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export JAX_PLATFORMS ?= cpu
# Persistent XLA compilation cache: repeated test runs skip most compiles.
export JAX_COMPILATION_CACHE_DIR ?= $(HOME)/.cache/ghsplat-jax/xla

.PHONY: install test demo bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	@# A headless browser for the viewer's screenshot test (root with apt only; else that test skips).
	@command -v chromium-headless-shell >/dev/null || command -v chromium >/dev/null || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium-headless-shell >/dev/null; } || \
	  echo "note: no chromium-headless-shell; the viewer screenshot test will be skipped"
	touch $(STAMP)

# One pytest process per test file (tests/run_suite.py says why), then one summary.
test: install
	$(BIN)/python tests/run_suite.py

demo: install
	$(BIN)/ghsplat demo

bench: install
	$(BIN)/python benchmarks/speed/raster_speed.py

clean:
	rm -rf $(VENV) .cache build *.egg-info
