"""SfM on self-similar rows: pair filters (--disambiguate) and the fold check, against ground truth.

Each case is a procedural row (ghsplat_jax.synth) with identical or varied plants, shot
by a hand-held loop, a robot aisle drive, or a video-rate walk (many frames, thinned by
the frame selector). Features and exhaustive matches are computed once per case; each
method then filters pairs, maps (incremental), and runs the fold diagnostics, exactly
as `ghsplat sfm` does. Per case and method: registered views, camera-centre RMSE and
max as % of the extent (Umeyama similarity to the true cameras), rotation error,
whether the fold check flagged the model, the resulting status, and seconds.

    JAX_PLATFORMS=cpu nice -n 10 .venv/bin/python benchmarks/robustness/sfm_disambiguation.py [--quick]

Writes benchmarks/results/sfm_disambiguation/{results.json, results.csv, table.md,
errors.png}. Rows of results.json carry "case", "method", "centre_rmse_pct",
"fold_suspected" and "status" for the stability table of the research results.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.experiments.sfm_rows import Case
from ghsplat_jax.experiments.sfm_rows import run_case as _run_case
from ghsplat_jax.io_utils import atomic_write, json_safe, save_figure, write_json

RESULTS = RESULTS / "sfm_disambiguation"


CASES = [  # hand-held views: about 0.22 m apart at an even pace unless named "sparse"
    Case("varied-5-handheld-s0", 5, False, views=40, seed=0),
    Case("identical-5-handheld-s0", 5, True, views=40, seed=0),
    Case("identical-8-handheld-s1", 8, True, views=52, seed=1),
    Case("identical-8-handheld-sparse-s0", 8, True, views=36, seed=0, slowdown=0.4),
    Case("identical-5-video-s3", 5, True, views=120, seed=3, video=True),
    Case("identical-8-robot-s1", 8, True, "robot", views=36, seed=1),
    Case("varied-8-robot-s1", 8, False, "robot", views=36, seed=1),
    Case("identical-12-robot-s2", 12, True, "robot", views=40, seed=2),
    Case("identical-20-robot-s0", 20, True, "robot", views=44, seed=0),
]
QUICK = CASES[:2]

METHODS = ("none", "auto", "order", "tracks")  # --disambiguate values, default windows


def run_case(case: Case, tmp: Path, width: int, height: int) -> list[dict]:
    return _run_case(case, tmp, width, height, METHODS, log=lambda line: print(line, flush=True))


COLUMNS = ("case", "method", "views", "registered", "centre_rmse_pct", "centre_max_pct",
           "rotation_max_deg", "fold_suspected", "status", "total_s")


def table(rows: list[dict], width: int, height: int) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.2f}"
        return "" if v is None else str(v)

    lines = [f"SfM on procedural rows, {width}x{height} px, exhaustive SIFT matching, incremental "
             "mapping; centre errors in % of the extent after a similarity alignment to the true "
             "cameras; `silent` = status ok with RMSE above 5%.", "",
             "| " + " | ".join(COLUMNS) + " | silent |", "|" + "---|" * (len(COLUMNS) + 1)]
    for row in rows:
        silent = row["status"] == "ok" and (row.get("centre_rmse_pct") or 0) > 5
        lines.append("| " + " | ".join(fmt(row.get(c)) for c in COLUMNS) + f" | {'YES' if silent else ''} |")
    return "\n".join(lines) + "\n"


def summary(rows: list[dict]) -> dict:
    out = {}
    for label in METHODS:
        mine = [r for r in rows if r["method"] == label]
        good = [r for r in mine if r["status"] == "ok" and (r.get("centre_rmse_pct") or 1e9) <= 2.0]
        silent = [r["case"] for r in mine if r["status"] == "ok" and (r.get("centre_rmse_pct") or 0) > 5]
        out[label] = {"cases": len(mine), "ok_within_2pct": len(good), "silent_wrong": silent,
                      "refused": sum(r["status"] != "ok" for r in mine),
                      "total_s": float(sum(r["total_s"] for r in mine))}
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r["case"] for r in rows))
    fig, ax = plt.subplots(figsize=(max(8, 1.1 * len(cases)), 4.5))
    width = 0.8 / len(METHODS)
    for k, label in enumerate(METHODS):
        for c, case in enumerate(cases):
            row = next((r for r in rows if r["case"] == case and r["method"] == label), None)
            if row is None or row.get("centre_rmse_pct") is None:
                continue
            x = c + (k - (len(METHODS) - 1) / 2) * width
            ax.bar(x, max(row["centre_rmse_pct"], 0.01), width, color=f"C{k}",
                   hatch="//" if row["status"] != "ok" else None, edgecolor="k" if row["status"] != "ok" else None,
                   label=label if c == 0 else None)
    ax.set_yscale("log")
    ax.axhline(2.0, color="grey", linestyle=":", label="2% goal")
    ax.axhline(5.0, color="red", linestyle=":", label="5%: must be flagged")
    ax.set_xticks(range(len(cases)), [c.replace("-", "\n", 2) for c in cases], fontsize=7)
    ax.set_ylabel("camera-centre RMSE (% of extent)")
    ax.set_title("SfM pair filters on procedural rows (hatched: refused, i.e. folded or partial)", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two cases only")
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--cases", nargs="*", default=None, help="case names (default: all)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the other cases' rows of the existing results.json (rerun some cases)")
    args = parser.parse_args()

    import pycolmap

    pycolmap.logging.minloglevel = 2
    cases = QUICK if args.quick else CASES
    if args.cases:
        cases = [c for c in CASES if c.name in args.cases]
    load_start = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(prefix="sfm_disambiguation_") as tmp:
        for case in cases:
            rows.extend(run_case(case, Path(tmp), args.width, args.height))
    if args.merge and (RESULTS / "results.json").is_file():
        import json

        previous = json.loads((RESULTS / "results.json").read_text())
        rerun = {c.name for c in cases}
        kept = [r for r in previous["rows"] if r["case"] not in rerun]
        order = [c.name for c in CASES]
        rows = sorted(kept + rows, key=lambda r: (order.index(r["case"]) if r["case"] in order else 99,
                                                  METHODS.index(r["method"])))
        cases = [c for c in CASES if c.name in {r["case"] for r in rows}]
    report = {
        "benchmark": "sfm_disambiguation",
        "machine": machine_record(load_average_at_start=list(load_start)),
        "versions": {"pycolmap": pycolmap.__version__, "colmap": pycolmap.COLMAP_version},
        "image_size": [args.width, args.height],
        "cases": [dataclasses.asdict(c) for c in cases],
        "methods": list(METHODS),
        "note": "seconds on a shared 2-core CPU (other jobs running): compare methods within a case; "
                "extraction and matching are shared by the methods of a case and counted in each total",
        "summary": summary(rows),
        "rows": rows,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "results.json", json_safe(report))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=[c for c in (*COLUMNS, "rotation_mean_deg",
                            "identical", "path", "video", "seed", "plants", "image_size",
                            "extraction_s", "matching_s", "filter_and_map_s")], extrasaction="ignore")
    writer.writeheader()
    writer.writerows(json_safe(rows))
    with atomic_write(RESULTS / "results.csv", "w") as fh:
        fh.write(buffer.getvalue())
    with atomic_write(RESULTS / "table.md", "w") as fh:
        fh.write(table(rows, args.width, args.height))
    plot(rows, RESULTS / "errors.png")
    print(table(rows, args.width, args.height))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
