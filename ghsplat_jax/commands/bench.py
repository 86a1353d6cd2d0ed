"""`ghsplat bench NAME [ARGS...]`: run one of the repository's benchmarks/NAME.py scripts."""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

HELP = "run a benchmark script (raster_speed, sfm_speed, sim_speed, synth_speed, train_accuracy)"

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="benchmark name, e.g. raster_speed")
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script (see its --help)")


def main(args) -> int:
    script = BENCHMARKS / f"{args.name}.py"
    if not script.is_file():
        known = sorted(p.stem for p in BENCHMARKS.glob("*.py")) if BENCHMARKS.is_dir() else []
        print(f"ghsplat bench: no benchmark {script} (available: {', '.join(known) or 'none'})", file=sys.stderr)
        return 2
    sys.argv = [str(script), *args.args]
    runpy.run_path(str(script), run_name="__main__")
    return 0
