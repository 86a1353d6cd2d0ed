"""`ghsplat bench NAME [ARGS...]`: run one of the repository's benchmarks/KIND/NAME.py scripts
(KIND: speed, profiling, robustness, analysis; NAME alone finds it, KIND/NAME also works).

The benchmarks are scripts of the source checkout, not modules of the installed package:
they run as `python benchmarks/KIND/NAME.py` would, with benchmarks/ first on sys.path so they
find record.py (results folder, machine record) and each other (raster_ablation uses
speed/raster_speed's timer).
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

HELP = "run a benchmark script of the source checkout (raster_speed, raster_ablation, sfm_speed, ...)"

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="benchmark name, e.g. raster_speed or speed/raster_speed")
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script (see its --help)")


def scripts() -> list[Path]:
    """The benchmark scripts, benchmarks/KIND/NAME.py."""
    return sorted(p for p in BENCHMARKS.glob("*/*.py") if p.parent.name != "results")


def find_script(name: str) -> Path | None:
    """benchmarks/KIND/NAME.py for "NAME" or "KIND/NAME", None when there is no such script."""
    name = name.removesuffix(".py")
    found = [p for p in scripts() if name in (p.stem, f"{p.parent.name}/{p.stem}")]
    return found[0] if len(found) == 1 else None


def main(args) -> int:
    if not BENCHMARKS.is_dir():
        print(f"ghsplat bench: no benchmarks/ folder beside this package ({BENCHMARKS.parent}); the benchmarks "
              "are scripts of the source checkout: clone the repository and install it with `pip install -e .`",
              file=sys.stderr)
        return 2
    script = find_script(args.name)
    if script is None:
        known = sorted(f"{p.parent.name}/{p.stem}" for p in scripts())
        print(f"ghsplat bench: no benchmark {args.name!r} in {BENCHMARKS} (available: {', '.join(known) or 'none'})",
              file=sys.stderr)
        return 2
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [str(script), *args.args]
    sys.path[:0] = [str(script.parent), str(BENCHMARKS)]
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
