"""A second, independent estimate of every view's pose: the global mapper, held against the
incremental model view by view.

The incremental mapper adds views one after another, so a small error made early is carried
along a walk: a 60-view row segment mapped with every thread came out bent, 1.19% of the extent
and 2.3 degrees off at both ends, while each view agreed with its neighbours' points (the
leave-one-out check of crosscheck.py cannot see a bend that moves a view with its points). The
global mapper (GLOMAP in pycolmap) estimates every rotation at once, then every position, so it
carries no drift along the capture. Given every verified pair it ended more than 5% of the
extent off on 13 of 38 maps of the Table 1 segments (up to 84%: look-alike plants); given only
the pairs the model confirms (pairs that share at least `min_shared_points` of the model's 3D
points: a look-alike pair the mapper rejected shares none) it came within 0.17-0.80% of the
extent and 0.30-1.22 degrees of the exact cameras on all 38 (benchmarks/results/sfm_crosscheck/).
The pairs come from the model; the poses do not: each pair's matches are the database's, and the
global mapper estimates its own geometry from them.

Centre deviations are measured in the model's frame against the same scale as the cross-check
(crosscheck.model_scale), rotations against the mean rotation between the two models, so that a
bend shows as a spread and a rigid offset does not.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from ghsplat_jax.sfm.crosscheck import model_scale, rotation_angle_deg
from ghsplat_jax.sfm.evaluate import model_w2c, umeyama


@dataclasses.dataclass
class SecondEstimateOptions:
    # A view disagrees when the two estimates of its centre lie farther apart than this share of
    # the scale, or its rotations differ by more than max_rotation_deg beyond their mean offset.
    # Of 40 multithreaded maps of the Table 1 segments, the 37 within 0.95% and 1.68 degrees of
    # the exact cameras disagreed by at most 0.51% and 1.08 degrees; the three bent ones (0.92-1.19%
    # and 1.86-2.27 degrees) by 1.50-1.96 degrees (benchmarks/results/sfm_crosscheck/).
    max_centre_rel: float = 0.007
    max_rotation_deg: float = 1.3
    min_shared_points: int = 15  # a pair is given to the global mapper when it shares this many points
    min_common_views: int = 3    # fewer views in both models: no verdict


def shared_point_counts(reconstruction) -> Counter:
    """{(image id a, image id b), a < b: how many of the model's 3D points both observe}."""
    counts: Counter = Counter()
    for point in reconstruction.points3D.values():
        ids = sorted({element.image_id for element in point.track.elements})
        counts.update(itertools.combinations(ids, 2))
    return counts


def confirmed_pairs_database(database: Path, target: Path, reconstruction, min_shared_points: int) -> tuple[int, int]:
    """Copy `database` to `target` keeping only the verified pairs of registered views that share
    at least `min_shared_points` of the model's points; (pairs kept, pairs removed)."""
    import pycolmap

    shared = shared_point_counts(reconstruction)
    for suffix in ("", "-wal", "-shm"):
        Path(f"{target}{suffix}").unlink(missing_ok=True)
    shutil.copyfile(database, target)
    db = pycolmap.Database.open(str(target))
    kept = removed = 0
    try:
        pair_ids, _ = db.read_two_view_geometries()
        for pair_id in pair_ids:
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if shared.get((min(a, b), max(a, b)), 0) >= min_shared_points:
                kept += 1
            else:
                db.delete_two_view_geometry(a, b)
                removed += 1
    finally:
        db.close()
    return kept, removed


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest (in the chordal sense) to the mean of `rotations` (N,3,3)."""
    u, _, vt = np.linalg.svd(rotations.sum(0))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ d @ vt


def view_deviations(model: dict[str, np.ndarray], estimate: dict[str, np.ndarray],
                    scale: float) -> dict[str, tuple[float, float]]:
    """{name: (centre deviation / scale, rotation deviation in degrees)} of the views in both
    {name: world_to_cam (4,4)} sets: the estimate's centres carried into the model's frame by a
    similarity, its rotations by the mean rotation between the two."""
    names = sorted(set(model) & set(estimate))
    a = np.stack([model[n] for n in names])
    b = np.stack([estimate[n] for n in names])
    centres_a = -np.einsum("nji,nj->ni", a[:, :3, :3], a[:, :3, 3])
    centres_b = -np.einsum("nji,nj->ni", b[:, :3, :3], b[:, :3, 3])
    s, rot, t = umeyama(centres_b, centres_a)
    centre_dev = np.linalg.norm(s * centres_b @ rot.T + t - centres_a, axis=1) / max(scale, 1e-12)
    offsets = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])  # R_model^T R_estimate
    mean = mean_rotation(offsets)
    rotation_dev = [rotation_angle_deg(o @ mean.T) for o in offsets]
    return {n: (float(c), float(r)) for n, c, r in zip(names, centre_dev, rotation_dev, strict=True)}


def global_estimate(database: Path, image_root: Path, reconstruction, work: Path,
                    options: SecondEstimateOptions, num_threads: int = 1, seed: int = 0):
    """(the global mapper's largest model from the pairs `reconstruction` confirms, or None,
    {"pairs_kept", "pairs_removed"}); its database and models are written under `work`."""
    import pycolmap

    shutil.rmtree(work, ignore_errors=True)
    (work / "models").mkdir(parents=True)
    kept, removed = confirmed_pairs_database(database, work / "database.db", reconstruction,
                                             options.min_shared_points)
    pipeline = pycolmap.GlobalPipelineOptions()
    pipeline.num_threads = num_threads
    pipeline.random_seed = seed
    pipeline.mapper.global_positioning.use_gpu = False
    pipeline.mapper.bundle_adjustment.ceres.use_gpu = False
    pycolmap.set_random_seed(seed)
    try:
        models = pycolmap.global_mapping(work / "database.db", image_root, work / "models", options=pipeline)
    except (RuntimeError, ValueError):  # no usable pair left: no second estimate, no verdict
        models = {}
    best = max(models.values(), key=lambda m: m.num_reg_images(), default=None)
    return best, {"pairs_kept": kept, "pairs_removed": removed}


def compare(reconstruction, estimate, options: SecondEstimateOptions, extra: dict | None = None) -> dict:
    """The verdict of `estimate` on `reconstruction`, JSON-ready: per-view deviations ("views"),
    the views beyond the bounds ("disagree", worst first), those the estimate left out
    ("unconfirmed") and "verdict": "agree", "disagree" or "none" (too few views in common)."""
    ours = model_w2c(reconstruction)
    theirs = model_w2c(estimate) if estimate is not None else {}
    report = {"method": "global_mapper_on_confirmed_pairs", **(extra or {}),
              "max_centre_rel": options.max_centre_rel, "max_rotation_deg": options.max_rotation_deg,
              "num_views": len(ours), "num_common": len(set(ours) & set(theirs)),
              "unconfirmed": sorted(set(ours) - set(theirs))}
    if report["num_common"] < options.min_common_views:
        return report | {"verdict": "none", "disagree": [], "views": []}
    deviations = view_deviations(ours, theirs, model_scale(reconstruction))
    views = [{"name": n, "centre_rel": round(c, 5), "rotation_deg": round(r, 3)} for n, (c, r) in deviations.items()]
    disagree = sorted((v for v in views if v["centre_rel"] > options.max_centre_rel
                       or v["rotation_deg"] > options.max_rotation_deg),
                      key=lambda v: max(v["centre_rel"] / options.max_centre_rel,
                                        v["rotation_deg"] / options.max_rotation_deg), reverse=True)
    return report | {
        "verdict": "disagree" if disagree else "agree",
        "largest_centre_rel": max(v["centre_rel"] for v in views),
        "largest_rotation_deg": max(v["rotation_deg"] for v in views),
        "disagree": disagree, "views": views,
    }


def check(database: Path, image_root: Path, reconstruction, work: Path,
          options: SecondEstimateOptions = SecondEstimateOptions(), num_threads: int = 1, seed: int = 0) -> dict:
    """global_estimate, then compare; the work folder is kept only when the two disagree (for
    inspection: work/models/0 is the second estimate)."""
    estimate, pairs = global_estimate(database, image_root, reconstruction, work, options, num_threads, seed)
    report = compare(reconstruction, estimate, options, pairs)
    if report["verdict"] != "disagree":
        shutil.rmtree(work, ignore_errors=True)
    else:
        report["estimate_model"] = str(work / "models" / "0")
    return report


def summary(report: dict) -> str:
    """One line for the terminal and the refusal message."""
    if report["verdict"] == "none":
        return (f"the global mapper's second estimate shares only {report['num_common']} views with the model: "
                "no verdict")
    worst = report["disagree"][:6]
    if not worst:
        return (f"the global mapper's second estimate agrees on {report['num_common']} views (largest differences "
                f"{100 * report['largest_centre_rel']:.2f}% of the extent, "
                f"{report['largest_rotation_deg']:.2f} degrees)")
    shown = ", ".join(f"{v['name']} ({100 * v['centre_rel']:.2f}%, {v['rotation_deg']:.2f} deg)" for v in worst)
    return (f"{len(report['disagree'])} of {report['num_common']} views lie elsewhere in the global mapper's "
            f"second estimate, beyond {100 * report['max_centre_rel']:g}% of the extent or "
            f"{report['max_rotation_deg']:g} degrees: {shown}"
            + (", ..." if len(report["disagree"]) > len(worst) else ""))


ADVICE = [
    "the incremental model and the global mapper's estimate from the same confirmed pairs place some views "
    "differently: the incremental model is likely bent along the capture (drift carried from view to view). "
    "Both are written (the second under distorted/second_estimate/models/0); do not train on the model as it is",
    "re-run with --threads 1 (the multithreaded mapper differs from run to run), or add photos where the "
    "capture turns or ends so that more views overlap",
    "to accept the incremental model anyway: --no-second-estimate",
]
