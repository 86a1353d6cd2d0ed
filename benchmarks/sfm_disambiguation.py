"""SfM on self-similar rows: pair filters (--disambiguate) and the fold check, against ground truth.

Each case is a procedural row (ghsplat_jax.synth) with identical or varied plants, shot
by a hand-held loop, a robot aisle drive, or a video-rate walk (many frames, thinned by
the frame selector). Features and exhaustive matches are computed once per case; each
method then filters pairs, maps (incremental), and runs the fold diagnostics, exactly
as `ghsplat sfm` does. Per case and method: registered views, camera-centre RMSE and
max as % of the extent (Umeyama similarity to the true cameras), rotation error,
whether the fold check flagged the model, the resulting status, and seconds.

    JAX_PLATFORMS=cpu nice -n 10 .venv/bin/python benchmarks/sfm_disambiguation.py [--quick]

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
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ghsplat_jax.io_utils import atomic_write, save_figure, write_json  # noqa: E402
from ghsplat_jax.sfm import pipeline  # noqa: E402
from ghsplat_jax.sfm.align import camera_centres  # noqa: E402
from ghsplat_jax.sfm.evaluate import compare_poses, model_w2c  # noqa: E402
from sfm_speed import _clean  # noqa: E402  (benchmarks/ is the script's folder)

RESULTS = Path(__file__).resolve().parent / "results" / "sfm_disambiguation"


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    plants: int
    identical: bool
    path: str = "handheld"   # handheld | robot
    views: int = 36          # rendered views (video: frames before selection)
    seed: int = 0
    video: bool = False      # thin the frames with the frame selector, like a video
    slowdown: float = 1.0    # hand-held walking speed at the row ends relative to the aisles


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


def make_case(case: Case, out: Path, width: int, height: int) -> Path:
    from ghsplat_jax.synth import capture, config, dataset, scene

    cfg = config.SceneConfig(seed=case.seed)
    cfg = cfg.replace(
        layout=dataclasses.replace(cfg.layout, rows=1, plants_per_row=case.plants,
                                   identical_plants=case.identical),
        ground=dataclasses.replace(cfg.ground, margin=1.5, texture_tile=3.0),
        render=dataclasses.replace(cfg.render, texture_size=512),
    )
    world = scene.generate_scene(cfg)
    cams = capture.capture_path(world, case.path, case.views, row=0, width=width, height=height,
                                seed=case.seed, config=capture.PathConfig(end_slowdown=case.slowdown))
    return dataset.write_dataset(world, cams, out, n_points=300, meshes=False, overwrite=True)


def evaluate(best, truth) -> dict:
    est, ref = model_w2c(best), model_w2c(truth)
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        return {}
    e, r = np.stack([est[n] for n in names]), np.stack([ref[n] for n in names])
    result = compare_poses(e, r)
    return {
        "centre_rmse_pct": 100 * result["centre_error_rmse"] / result["extent"],
        "centre_max_pct": 100 * result["centre_error_max_rel"],
        "rotation_mean_deg": result["rotation_error_mean_deg"],
        "rotation_max_deg": result["rotation_error_max_deg"],
        "extent_m": result["extent"],
        "num_compared": len(names),
        "true_centres_span_m": float(np.ptp(camera_centres(r), axis=0).max()),
    }


def run_method(method: str, base_db: Path, root: Path, names: list[str], work: Path, truth,
               min_fraction: float) -> dict:
    """One `--disambiguate` method through the pipeline's own mapping stage (pipeline.reconstruct)."""
    options = pipeline.SfmOptions(disambiguate=method, progress=False, seed=0)
    work.mkdir(parents=True)
    database = work / "database.db"
    shutil.copyfile(base_db, database)
    timings: dict = {}
    start = time.perf_counter()
    result = pipeline.reconstruct(database, root, names, options, work, timings)
    seconds = time.perf_counter() - start
    best, diag = result.best, result.diagnostics
    row = {"method": method, "filter_and_map_s": seconds, "num_models": len(result.models),
           "registered": 0 if best is None else best.num_reg_images(), "num_images": len(names),
           "disambiguation": result.disambiguation}
    if best is None:
        row.update(status="failed", fold_suspected=False)
        return row
    row["fold_suspected"] = diag["fold_suspected"]
    row["fold_reasons"] = diag["reasons"]
    row["neighbour_pairs_contradicted"] = diag["neighbour_pairs"]["fraction_contradicted"]
    row["rotation_chain_max_drift_deg"] = diag["rotation_chain"]["max_drift_deg"]
    if diag["fold_suspected"]:
        row["status"] = "folded"
    elif row["registered"] < min_fraction * len(names):
        row["status"] = "partial"
    else:
        row["status"] = "ok"
    row.update(evaluate(best, truth))
    return row


def run_case(case: Case, tmp: Path, width: int, height: int) -> list[dict]:
    import pycolmap

    data = make_case(case, tmp / case.name / "data", width, height)
    truth = pycolmap.Reconstruction(str(data / "sparse" / "0"))
    options = pipeline.SfmOptions(progress=False, select_frames=case.video, max_size=max(width, height))
    out = tmp / case.name / "sfm"
    out.mkdir(parents=True)
    timings: dict = {}
    root, names, frame_info = pipeline.resolve_input(data / "images", out, options, timings)
    base_db = out / "database.db"
    start = time.perf_counter()
    pipeline.extract(base_db, root, names, options)
    extraction = time.perf_counter() - start
    start = time.perf_counter()
    pipeline.match(base_db, options)
    matching = time.perf_counter() - start
    rows = []
    for label in METHODS:
        row = run_method(label, base_db, root, names, out / label, truth, options.min_registered_fraction)
        row.update(case=case.name, plants=case.plants, identical=case.identical, path=case.path,
                   video=case.video, seed=case.seed, rendered_views=case.views, views=len(names),
                   image_size=f"{width}x{height}", extraction_s=extraction, matching_s=matching,
                   total_s=extraction + matching + row["filter_and_map_s"])
        rows.append(row)
        print(f"{case.name:28s} {label:9s} reg {row['registered']:3d}/{len(names):<3d} "
              f"rmse {row.get('centre_rmse_pct', float('nan')):7.2f}% rot max "
              f"{row.get('rotation_max_deg', float('nan')):6.1f} deg fold {row['fold_suspected']!s:5s} "
              f"{row['status']:7s} {row['total_s']:6.1f}s {'; '.join(row.get('fold_reasons', []))[:160]}",
              flush=True)
    shutil.rmtree(tmp / case.name, ignore_errors=True)
    return rows


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
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpu_count": os.cpu_count(), "python": platform.python_version(),
                    "load_average_at_start": list(load_start), "load_average_at_end": list(os.getloadavg())},
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
    write_json(RESULTS / "results.json", _clean(report))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=[c for c in (*COLUMNS, "rotation_mean_deg",
                            "identical", "path", "video", "seed", "plants", "image_size",
                            "extraction_s", "matching_s", "filter_and_map_s")], extrasaction="ignore")
    writer.writeheader()
    writer.writerows(_clean(rows))
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
