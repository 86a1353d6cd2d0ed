"""Load a script of benchmarks/KIND/ as a module, for the tests of its functions."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"


def load_benchmark(name: str):
    """benchmarks/KIND/NAME.py (whatever its KIND) as the module NAME."""
    (path,) = [p for p in BENCHMARKS.glob(f"*/{name}.py") if p.parent.name != "results"]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    sys.path.insert(0, str(BENCHMARKS))  # record.py and the scripts they import from other kinds
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module
