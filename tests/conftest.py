import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Reuse compiled XLA programs across runs and clones (the Makefile sets the same default).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.expanduser("~/.cache/ghsplat-jax/xla"))
