"""SfM stage timings (extraction, matching, mapping) against image count and image size,
and pose accuracy on lund_door against its reference model, per mapper.

    JAX_PLATFORMS=cpu .venv/bin/python benchmarks/speed/sfm_speed.py [--repeats 3] [--quick]

Uses the shared datasets (never copied): llff_fern/images_4 (20 photos, 1008x756) for
the sweeps, lund_door (12 photos, 1296x1936) for accuracy. Each configuration runs
`--repeats` times in a fresh database; the median per stage is reported. Writes
benchmarks/results/sfm_speed.json and sfm_speed.png.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: record.py and the other kinds' scripts
from record import RESULTS, machine_record  # noqa: E402

from ghsplat_jax.io_utils import atomic_write, json_safe, write_json  # noqa: E402
from ghsplat_jax.paths import datasets_root  # noqa: E402
from ghsplat_jax.sfm import pipeline  # noqa: E402
from ghsplat_jax.sfm.evaluate import compare_models  # noqa: E402
from ghsplat_jax.sfm.frames import list_images  # noqa: E402

STAGES = ("extraction", "matching", "mapping")


def run_stages(root: Path, names: list[str], options: pipeline.SfmOptions) -> dict:
    """Time extraction, matching and mapping once in a fresh database."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        db = tmp / "database.db"
        times = {}
        start = time.perf_counter()
        pipeline.extract(db, root, names, options)
        times["extraction"] = time.perf_counter() - start
        start = time.perf_counter()
        pipeline.match(db, options)
        times["matching"] = time.perf_counter() - start
        start = time.perf_counter()
        models = pipeline.map_images(db, root, tmp / "models", options)
        times["mapping"] = time.perf_counter() - start
        best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
        return {
            **times,
            "registered": 0 if best is None else best.num_reg_images(),
            "reprojection_error_px": None if best is None else best.compute_mean_reprojection_error(),
            "model": best,
        }


def measure(root: Path, names: list[str], options: pipeline.SfmOptions, repeats: int) -> dict:
    runs = [run_stages(root, names, options) for _ in range(repeats)]
    row = {stage: statistics.median(r[stage] for r in runs) for stage in STAGES}
    row["total"] = sum(row[s] for s in STAGES)
    row["registered"] = min(r["registered"] for r in runs)
    errors = [r["reprojection_error_px"] for r in runs if r["reprojection_error_px"] is not None]
    row["reprojection_error_px"] = statistics.median(errors) if errors else None
    row["all_runs"] = [{s: r[s] for s in STAGES} for r in runs]
    return row, runs[-1]["model"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="fewer points in each sweep")
    args = parser.parse_args()

    import pycolmap

    pycolmap.logging.minloglevel = 2
    fern = datasets_root() / "llff_fern" / "images_4"
    lund = datasets_root() / "lund_door"
    if not fern.exists() or not lund.exists():
        print(f"shared datasets not found under {datasets_root()} (set GHSPLAT_DATASETS)")
        return 1
    fern_names = list_images(fern)
    base = dict(align="none", progress=False, seed=0)

    counts = [5, 10, 20] if args.quick else [5, 10, 15, 20]
    sizes = [252, 504, 1008] if args.quick else [252, 378, 504, 756, 1008]
    by_count, by_size, accuracy = [], [], []
    for n in counts:
        row, _ = measure(fern, fern_names[:n], pipeline.SfmOptions(max_size=504, **base), args.repeats)
        by_count.append({"num_images": n, "max_size": 504, **row})
        print(f"fern {n:2d} images @504: " + ", ".join(f"{s} {row[s]:.2f}s" for s in STAGES)
              + f", registered {row['registered']}")
    for size in sizes:
        row, _ = measure(fern, fern_names, pipeline.SfmOptions(max_size=size, **base), args.repeats)
        by_size.append({"num_images": len(fern_names), "max_size": size, **row})
        print(f"fern 20 images @{size}: " + ", ".join(f"{s} {row[s]:.2f}s" for s in STAGES)
              + f", registered {row['registered']}")

    reference = pycolmap.Reconstruction(str(lund / "colmap_ground_truth"))
    lund_names = list_images(lund / "images")
    for mapper in pipeline.MAPPERS:
        for size in ([400, 1000] if args.quick else [400, 700, 1000, 1936]):
            options = pipeline.SfmOptions(max_size=size, mapper=mapper, **base)
            row, model = measure(lund / "images", lund_names, options, 1)
            result = compare_models(model, reference) if model is not None else {}
            accuracy.append({"dataset": "lund_door", "mapper": mapper, "max_size": size, **row, **result})
            print(f"lund_door {mapper} @{size}: registered {row['registered']}/12, centre error max "
                  f"{100 * result.get('centre_error_max_rel', float('nan')):.3f}% of extent, rotation "
                  f"error max {result.get('rotation_error_max_deg', float('nan')):.3f} deg, "
                  f"total {row['total']:.1f}s")

    report = {
        "benchmark": "sfm_speed",
        "machine": machine_record(),
        "versions": {"pycolmap": pycolmap.__version__, "colmap": pycolmap.COLMAP_version},
        "repeats": args.repeats,
        "note": "median seconds per stage over repeats (CPU SIFT, exhaustive matching, "
                "incremental mapping unless named); the machine may be shared, so compare "
                "rows within one run only",
        "fern_by_count": by_count,
        "fern_by_size": by_size,
        "lund_door_accuracy": accuracy,
    }
    write_json(RESULTS / "sfm_speed.json", json_safe(report))
    plot(report, RESULTS / "sfm_speed.png")
    print(f"wrote {RESULTS / 'sfm_speed.json'} and sfm_speed.png")
    return 0


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, key, xname, title in (
        (axes[0], "fern_by_count", "num_images", "llff_fern @ 504 px: time vs image count"),
        (axes[1], "fern_by_size", "max_size", "llff_fern, 20 images: time vs image size"),
    ):
        rows = report[key]
        x = [r[xname] for r in rows]
        bottom = np.zeros(len(rows))
        for stage in STAGES:
            values = np.array([r[stage] for r in rows])
            ax.bar([str(v) for v in x], values, bottom=bottom, label=stage)
            bottom += values
        ax.set_xlabel("images" if xname == "num_images" else "longest side (px)")
        ax.set_ylabel("seconds (median)")
        ax.set_title(title, fontsize=10)
        ax.legend()
    ax = axes[2]
    for mapper in ("incremental", "global"):
        rows = [r for r in report["lund_door_accuracy"]
                if r["mapper"] == mapper and r.get("centre_error_max_rel") is not None]
        ax.plot([r["max_size"] for r in rows], [100 * r["centre_error_max_rel"] for r in rows],
                "o-", label=mapper)
    ax.set_xlabel("longest side (px)")
    ax.set_ylabel("max centre error (% of extent)")
    ax.set_title("lund_door vs reference model (Umeyama-aligned)", fontsize=10)
    ax.axhline(1.0, color="grey", linestyle=":", label="1% target")
    ax.legend()
    fig.suptitle(f"SfM on {report['machine']['cpu_count']} CPU cores, "
                 f"pycolmap {report['versions']['pycolmap']}")
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
