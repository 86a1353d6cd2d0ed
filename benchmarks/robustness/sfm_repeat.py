"""Run-to-run spread of `ghsplat sfm`: the same photos, the same options and seed, run again.

    python benchmarks/robustness/sfm_repeat.py runs/greenhouse4/row0_x0/photos runs/greenhouse4/row3_x1/photos \
        --repeats 3 --single-threaded 2

Each folder holds images/ and the generator's exact model in sparse/0. Every run is the command a
user types (`ghsplat sfm --images F/images --max-size 384 --seed 0`, all CPU threads, then with
--threads 1) and is scored against the exact cameras with compare_model_dirs. Writes
benchmarks/results/sfm_disambiguation/repeatability.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.experiments.report import markdown_table
from ghsplat_jax.io_utils import atomic_write, write_json
from ghsplat_jax.sfm.evaluate import compare_model_dirs

RESULTS = RESULTS / "sfm_disambiguation"


def run_once(folder: Path, threads: int, max_size: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sfm"
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "ghsplat_jax.cli", "sfm", "--images", str(folder / "images"),
                               "--out", str(out), "--max-size", str(max_size), "--seed", "0",
                               "--threads", str(threads)],
                              capture_output=True, text=True)
        seconds = time.perf_counter() - start
        report = json.loads((out / "sfm_report.json").read_text()) if (out / "sfm_report.json").is_file() else {}
        model = out / "sparse" / "0"
        acc = compare_model_dirs(model, folder / "sparse" / "0") if model.is_dir() else None
    return dict(folder=folder.parent.name, threads=threads, exit=proc.returncode, status=report.get("status"),
                registered=report.get("num_registered"), images=report.get("num_images"), seconds=round(seconds, 1),
                centre_error_max_pct=None if acc is None else round(100 * acc["centre_error_max_rel"], 3),
                rotation_error_max_deg=None if acc is None else round(acc["rotation_error_max_deg"], 3),
                dropped_spikes=len(report.get("dropped_spikes") or []))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", type=Path, nargs="+")
    ap.add_argument("--repeats", type=int, default=3, help="runs with all threads")
    ap.add_argument("--single-threaded", type=int, default=2, help="runs with --threads 1")
    ap.add_argument("--max-size", type=int, default=384)
    args = ap.parse_args(argv)
    rows = []
    for folder in args.folders:
        for threads in [-1] * args.repeats + [1] * args.single_threaded:
            rows.append(run_once(folder, threads, args.max_size))
            print(rows[-1], flush=True)
    write_json(RESULTS / "repeatability.json", {"machine": machine_record(start_backend=False), "rows": rows})
    cols = ("folder", "threads", "exit", "status", "registered", "images", "centre_error_max_pct",
            "rotation_error_max_deg", "dropped_spikes", "seconds")
    with atomic_write(RESULTS / "repeatability.md", "w") as fh:
        fh.write("# Run-to-run spread of `ghsplat sfm` (same photos, options and seed)\n\n"
                 "Made by `benchmarks/robustness/sfm_repeat.py`; errors against the generator's exact cameras "
                 "(similarity-aligned), in % of the extent.\n\n" + markdown_table(rows, cols))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
