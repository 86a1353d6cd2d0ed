"""SfM on procedural rows against ground truth: make a row (ghsplat_jax.synth), run the pipeline's
own stages (extract, match, then per `--disambiguate` method filter, map and fold-check, exactly as
`ghsplat sfm` does) and score the best model against the true cameras.

Used by benchmarks/robustness/sfm_disambiguation.py and the stability study (experiments/stability.py).
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from ghsplat_jax.sfm import diagnose, pipeline
from ghsplat_jax.sfm.align import camera_centres
from ghsplat_jax.sfm.evaluate import compare_poses, model_w2c


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


def make_case(case: Case, out: Path, width: int, height: int) -> Path:
    """Render the case's row and cameras into a dataset folder (images/, sparse/0 = the truth)."""
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
    """Camera-centre RMSE and max (% of the extent) and rotation errors after a similarity
    alignment of the model's cameras to the true ones (empty when fewer than 3 match)."""
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
        row.update(status="failed", fold_suspected=False,
                   diagnosis=diagnose.diagnose_run(database, names, None, refused=True))
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
    if row["status"] == "partial" or row["registered"] < len(names):
        row["diagnosis"] = diagnose.diagnose_run(database, names, best, refused=row["status"] == "partial")
    row.update(evaluate(best, truth))
    return row


def run_case(case: Case, tmp: Path, width: int, height: int, methods, degrade=None, log=print) -> list[dict]:
    """Every method on one case: the row is rendered once, features and matches are computed
    once and shared. `degrade(images_folder)` may alter the rendered images first (e.g. blur)."""
    import pycolmap

    data = make_case(case, tmp / case.name / "data", width, height)
    if degrade is not None:
        degrade(data / "images")
    truth = pycolmap.Reconstruction(str(data / "sparse" / "0"))
    options = pipeline.SfmOptions(progress=False, select_frames=case.video, max_size=max(width, height))
    out = tmp / case.name / "sfm"
    out.mkdir(parents=True)
    timings: dict = {}
    root, names, _frame_info = pipeline.resolve_input(data / "images", out, options, timings)
    base_db = out / "database.db"
    start = time.perf_counter()
    pipeline.extract(base_db, root, names, options)
    extraction = time.perf_counter() - start
    start = time.perf_counter()
    pipeline.match(base_db, options)
    matching = time.perf_counter() - start
    rows = []
    for label in methods:
        row = run_method(label, base_db, root, names, out / label, truth, options.min_registered_fraction)
        row.update(case=case.name, plants=case.plants, identical=case.identical, path=case.path,
                   video=case.video, seed=case.seed, rendered_views=case.views, views=len(names),
                   image_size=f"{width}x{height}", extraction_s=extraction, matching_s=matching,
                   total_s=extraction + matching + row["filter_and_map_s"])
        rows.append(row)
        log(f"{case.name:28s} {label:9s} reg {row['registered']:3d}/{len(names):<3d} "
            f"rmse {row.get('centre_rmse_pct', float('nan')):7.2f}% rot max "
            f"{row.get('rotation_max_deg', float('nan')):6.1f} deg fold {row['fold_suspected']!s:5s} "
            f"{row['status']:7s} {row['total_s']:6.1f}s {'; '.join(row.get('fold_reasons', []))[:160]}")
    shutil.rmtree(tmp / case.name, ignore_errors=True)
    return rows
