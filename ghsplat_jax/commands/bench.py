"""`ghsplat bench NAME [ARGS...]`: run one of the repository's benchmarks/NAME.py scripts.

The benchmarks are scripts of the source checkout, not modules of the installed package:
they run as `python benchmarks/NAME.py` would, with benchmarks/ first on sys.path so they
can import each other (raster_ablation uses raster_speed's timer).
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

HELP = "run a benchmark script of the source checkout (raster_speed, raster_ablation, sfm_speed, ...)"

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="benchmark name, e.g. raster_speed")
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script (see its --help)")


def main(args) -> int:
    if not BENCHMARKS.is_dir():
        print(f"ghsplat bench: no benchmarks/ folder beside this package ({BENCHMARKS.parent}); the benchmarks "
              "are scripts of the source checkout: clone the repository and install it with `pip install -e .`",
              file=sys.stderr)
        return 2
    script = BENCHMARKS / f"{args.name}.py"
    if not script.is_file():
        known = sorted(p.stem for p in BENCHMARKS.glob("*.py"))
        print(f"ghsplat bench: no benchmark {script} (available: {', '.join(known) or 'none'})", file=sys.stderr)
        return 2
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [str(script), *args.args]
    sys.path.insert(0, str(BENCHMARKS))
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:  # the scripts end with `raise SystemExit(main())`
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(exc.code, file=sys.stderr)  # SystemExit("message"), as Python itself would
        return 1
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
    return 0
