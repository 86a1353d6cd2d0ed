"""Stability where methods fail (`ghsplat run experiments/stability.toml`, kind = "stability").

One table, a row per (case, method): pass or fail by a stated criterion, the measured error
against ground truth, how the tool detects the failure and the exact message it gives the
user. Case families (`[[cases]]` entries, each with `family` and `name`):

    sfm_recorded  a row of the recorded SfM benchmark results the experiment file names in
                  `sfm_recorded` (benchmarks/results/sfm_disambiguation/results.json: identical
                  vs varied plants, video-rate frames at 480x360): too slow to redo in minutes
    sfm           a live SfM run on a procedural row: few views, low texture (blurred,
                  low-contrast images), ... scored by camera-centre RMSE in % of the extent
    train         training on a synthetic row ([prepare]) from noisy poses (pose_noise, a
                  fraction of the extent), few views (views), a bad initialisation (init)
                  or a corrupt view; scored by the median test-view PSNR against the baseline
    divergence    training that cannot stay finite (e.g. an overflowing learning rate): the
                  NaN guard must stop it with an error and leave nothing non-finite on disk
    raster        a render (compositor: carried = early-terminating, logspace) of an opaque,
                  a sparse or a degenerate scene, scored by max |render - float64 reference|

Same seeds for every variant; medians over test views; the machine is recorded. Each case's
result is cached under OUTPUT/cases/NAME.json (keyed by its settings), so a rerun only
computes what changed. Reports: RESULTS/stability.{md,csv,json} and stability.png.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import logging
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ghsplat_jax.data.splits import subsample
from ghsplat_jax.host_memory import release_compiled_programs
from ghsplat_jax.io_utils import atomic_write, code_revision, json_safe, machine_info, save_figure, write_json

log = logging.getLogger("ghsplat.stability")

FAMILIES = ("sfm_recorded", "sfm", "train", "divergence", "raster")
SFM_GOAL_PCT = 2.0       # SfM passes when the tool says ok and the centre RMSE is within this % of the extent
PSNR_DROP_DB = 1.0       # training passes when its median test PSNR is within this of the baseline's
RASTER_TOL = 1e-3        # rendering passes when finite and within this of the float64 reference (tests' bound)
COLUMNS = ("family", "case", "method", "result", "error", "detection", "message", "source")


class StudyError(ValueError):
    """A case entry that cannot be run; the message names the case and key."""


# ----------------------------------------------------------------------------------- spec
_KEYS = {
    "sfm_recorded": {"recorded", "methods"},
    "sfm": {"plants", "identical", "views", "width", "height", "seed", "path", "blur_px", "contrast", "methods"},
    "train": {"pose_noise", "views", "init", "init_jitter", "corrupt_views", "baseline", "train", "seeds", "dataset",
              "triangulate", "goal_plant_psnr"},
    "divergence": {"train"},
    "raster": {"scene", "compositor", "width", "height", "seed"},
}
_PREPARE = {"plants": 3, "views": 24, "width": 128, "height": 96, "seed": 0, "points": 3000, "test_every": 6}


def check_cases(cases) -> list[dict]:
    if not isinstance(cases, list) or not cases:
        raise StudyError("a stability experiment needs [[cases]] entries")
    seen = set()
    for i, c in enumerate(cases):
        if not isinstance(c, dict) or not isinstance(c.get("name"), str):
            raise StudyError(f"cases[{i}] needs a 'name'")
        fam = c.get("family")
        if fam not in FAMILIES:
            raise StudyError(f"case {c['name']!r}: family must be one of {FAMILIES}, got {fam!r}")
        unknown = set(c) - {"name", "family"} - _KEYS[fam]
        if unknown:
            raise StudyError(f"case {c['name']!r}: unknown keys {sorted(unknown)} for family {fam!r} "
                             f"(known: {sorted(_KEYS[fam])})")
        if c["name"] in seen:
            raise StudyError(f"case {c['name']!r} appears twice")
        seen.add(c["name"])
    if sum(bool(c.get("baseline")) for c in cases if c["family"] == "train") > 1:
        raise StudyError("at most one train case may be the baseline")
    return cases


def _row(case: dict, method: str, ok: bool, error: str, detection: str, message: str, source: str = "run",
         **measured) -> dict:
    return {"family": case["family"], "case": case["name"], "method": method, "result": "pass" if ok else "fail",
            "error": error, "detection": detection, "message": message, "source": source, **measured}


# ------------------------------------------------------------------------------------ SfM
def _sfm_row(case: dict, r: dict, source: str) -> dict:
    from ghsplat_jax.sfm.report import verdict

    rmse = r.get("centre_rmse_pct")
    diagnosis = r.get("diagnosis") or []
    code, message = verdict(r["status"], r.get("fold_reasons", []), r["registered"], r["views"], 0.9, "OUT",
                            diagnosis, r.get("second_estimate"))
    ok = r["status"] == "ok" and rmse is not None and rmse <= SFM_GOAL_PCT
    if r["status"] == "folded":
        detection = "fold check: status folded, exit 4"
    elif r["status"] == "inconsistent":
        detection = "second estimate (global mapper): status inconsistent, exit 5"
    elif r["status"] in ("partial", "failed"):
        detection = f"registered-fraction check (< 0.9): status {r['status']}, exit 3" + (
            f"; diagnosed: {', '.join(dict.fromkeys(d['cause'] for d in diagnosis))}" if diagnosis else "")
    elif ok:
        detection = "none needed: status ok, exit 0"
    else:
        detection = "NOT DETECTED: status ok, exit 0"
    if message is None:
        message = f"(exit 0) {r['registered']} of {r['views']} images registered"
    error = (f"{r['registered']}/{r['views']} registered; centre RMSE "
             + (f"{rmse:.2f}% of extent" if rmse is not None
                else "n/a (no model)" if not r["registered"] else "n/a (fewer than 3 cameras to align)"))
    return _row(case, f"--disambiguate {r['method']}", ok, error, detection, message, source,
                status=r["status"], exit_code=code, registered=r["registered"], views=r["views"],
                centre_rmse_pct=rmse, rotation_max_deg=r.get("rotation_max_deg"),
                image_size=r.get("image_size"), seconds=r.get("total_s"),
                causes=[d["cause"] for d in diagnosis])


def _recorded(ctx) -> Path:
    """The recorded SfM results file the experiment names (`sfm_recorded`)."""
    if ctx is None or ctx.recorded is None:
        raise StudyError("sfm_recorded cases need `sfm_recorded = \"PATH/results.json\"` in the experiment file")
    return ctx.recorded


def run_sfm_recorded(case: dict, ctx) -> list[dict]:
    recorded = _recorded(ctx)
    data = json.loads(recorded.read_text())
    rows = [r for r in data["rows"] if r["case"] == case["recorded"]]
    if not rows:
        raise StudyError(f"case {case['name']!r}: no rows for {case['recorded']!r} in {recorded}")
    methods = case.get("methods", ["none", "auto"])
    src = (f"recorded: {recorded.as_posix()} ({data['image_size'][0]}x"
           f"{data['image_size'][1]}, case {case['recorded']})")
    return [_sfm_row(case, r, src) for m in methods for r in rows if r["method"] == m]


def _degrade(blur_px: float, contrast: float):
    """Low texture: blur each image (Gaussian, sigma in px) and pull it toward its mean colour."""
    def apply(folder: Path):
        import cv2

        from ghsplat_jax.data.images import read_image, write_image

        for p in sorted(folder.glob("*.png")):
            img = np.ascontiguousarray(read_image(p)[0][..., :3], np.float32)
            if blur_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), blur_px)
            mean = img.mean(axis=(0, 1), keepdims=True)
            write_image(p, np.clip(mean + contrast * (img - mean), 0, 1))
    return apply


def run_sfm(case: dict, ctx) -> list[dict]:
    import pycolmap

    from ghsplat_jax.experiments.sfm_rows import Case, run_case

    pycolmap.logging.minloglevel = 2
    c = Case(case["name"], int(case.get("plants", 5)), bool(case.get("identical", False)),
             case.get("path", "handheld"), int(case.get("views", 40)), int(case.get("seed", 0)))
    w, h = int(case.get("width", 480)), int(case.get("height", 360))
    blur, contrast = float(case.get("blur_px", 0.0)), float(case.get("contrast", 1.0))
    degrade = _degrade(blur, contrast) if (blur > 0 or contrast != 1.0) else None
    with tempfile.TemporaryDirectory(prefix="stability_sfm_", dir=ctx.scratch) as tmp:
        rows = run_case(c, Path(tmp), w, h, case.get("methods", ["auto"]), degrade, log=log.info)
    src = f"run: {w}x{h}, {c.views} views" + (f", blur {blur:g} px, contrast x{contrast:g}" if degrade else "")
    return [_sfm_row(case, r, src) for r in rows]


# ------------------------------------------------------------------------------ training
def prepare_row(prepare: dict, folder: Path) -> Path:
    """The synthetic row the training cases share (rendered once, kept while its settings hold)."""
    from ghsplat_jax.synth import capture, config, dataset, scene

    p = dict(_PREPARE, **prepare)
    unknown = set(p) - set(_PREPARE)
    if unknown:
        raise StudyError(f"[prepare]: unknown keys {sorted(unknown)} (known: {sorted(_PREPARE)})")
    stamp = folder / "prepare.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == p:
        return folder
    cfg = config.SceneConfig(seed=int(p["seed"]))
    cfg = cfg.replace(layout=dataclasses.replace(cfg.layout, rows=1, plants_per_row=int(p["plants"])),
                      ground=dataclasses.replace(cfg.ground, margin=1.0))
    world = scene.generate_scene(cfg)
    cams = capture.capture_path(world, "handheld", int(p["views"]), row=0, width=int(p["width"]),
                                height=int(p["height"]), seed=int(p["seed"]))
    dataset.write_dataset(world, cams, folder, n_points=int(p["points"]), meshes=False, overwrite=True)
    write_json(stamp, p)
    return folder


def _median_test(out_dir: Path) -> dict:
    from ghsplat_jax.train.run_dir import PER_VIEW_NAME

    rows = json.loads((out_dir / PER_VIEW_NAME).read_text())
    out = {}
    for split in ("train", "test"):
        mine = [r for r in rows if r["split"] == split]
        for k in ("psnr", "l1"):
            out[f"{split}_{k}"] = float(np.median([r[k] for r in mine])) if mine else None
    return out


def _train_config(case: dict, ctx):
    from ghsplat_jax.train.config import apply_overrides

    cfg = apply_overrides(ctx.train_base, {"data": str(ctx.row), "progress": False, "save_test_renders": False,
                                               "checkpoint_every": 0}, "stability study")
    return apply_overrides(cfg, case.get("train", {}), f"case {case['name']!r} train")


def _finite_on_disk(out_dir: Path) -> bool:
    """Every stored parameter of the run's checkpoint and PLY (where written) is finite."""
    from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, PLY_NAME

    ok = True
    ck = out_dir / CHECKPOINT_NAME
    if ck.exists():
        with np.load(ck, allow_pickle=False) as z:
            ok &= all(np.all(np.isfinite(z[k])) for k in z.files if np.issubdtype(z[k].dtype, np.floating))
    if (out_dir / PLY_NAME).exists():
        from ghsplat_jax.data.ply import read_vertices

        v = read_vertices(out_dir / PLY_NAME)
        ok &= all(np.all(np.isfinite(v[name])) for name in v.dtype.names)
    return bool(ok)


def _load(case: dict, cfg):
    from ghsplat_jax.train.run_dir import load_training_data

    ds = load_training_data(cfg)  # pose_noise is applied here (TrainConfig.pose_noise)
    train = subsample(list(ds.train), int(case.get("views", 0)) or None)
    changes = {"train": train}
    if case.get("init") == "random":
        changes.update(points=np.zeros((0, 3), np.float32), point_colors=None)
    elif case.get("init_jitter"):
        rng = np.random.default_rng([cfg.seed, 31])
        changes["points"] = (ds.points + rng.normal(0, float(case["init_jitter"]) * ds.scene_extent,
                                                     ds.points.shape)).astype(np.float32)
    if case.get("corrupt_views"):
        k = int(case["corrupt_views"])
        changes["train"] = [dataclasses.replace(v, image=np.full_like(v.image, np.nan)) if i < k else v
                            for i, v in enumerate(train)]
    return dataclasses.replace(ds, **changes)


# ---------------------------------------------------------------- what flagged a run
DETECTORS = ("input check", "NaN guard", "outlier views", "train-test gap", "missing structure")


def _eval_warning(metrics: dict, starts: str) -> str | None:
    """The evaluation's logged warning (metrics.json `warnings`) that begins with `starts`, as
    the console shows it (`ghsplat train --out OUT`)."""
    for text in metrics.get("warnings") or []:
        if text.startswith(starts):
            return f"WARNING ghsplat.eval: OUT: {text}"
    return None


def detect(metrics: dict | None, warnings: list[str]) -> list[dict]:
    """What flagged one training run, in DETECTORS order: [{kind, detail, message}], `message`
    being the exact warning text the user sees. `warnings`: the lines logged while it trained
    (the trainer's and the triangulation's: `_capture_warnings`); `metrics`: its metrics.json
    (the evaluation's checks: eval.evaluate.diagnose), None when it was not evaluated."""
    from ghsplat_jax.eval.metrics import TRAIN_TEST_GAP_DB

    found = []
    guard = [w for w in warnings if "rolled back" in w]
    inputs = [w for w in warnings if w not in guard]
    if inputs:  # trainer.warn_about_inputs (random init, few views), triangulation giving too few points
        found.append({"kind": "input check", "detail": "warned when training starts",
                      "message": "\n".join(inputs)})
    if guard:
        found.append({"kind": "NaN guard", "detail": f"{len(guard)} step(s) rolled back",
                      "message": guard[0] + (f" (and {len(guard) - 1} more)" if len(guard) > 1 else "")})
    metrics = metrics or {}
    outliers = metrics.get("outlier_views") or {}
    for split in ("train", "test"):
        views = outliers.get(split) or []
        if views:
            found.append({"kind": "outlier views",
                          "detail": f"{split}: " + ", ".join(v["name"] for v in views),
                          "message": _eval_warning(metrics, f"{len(views)} {split} view(s) far below")
                          or f"{split} outlier views: " + ", ".join(v["name"] for v in views)})
    gap = metrics.get("train_test_gap_db")
    if gap is not None and gap > TRAIN_TEST_GAP_DB:
        found.append({"kind": "train-test gap", "detail": f"{gap:.1f} dB",
                      "message": _eval_warning(metrics, "the training views' PSNR") or f"train-test gap {gap:.1f} dB"})
    missing = metrics.get("missing_structure_db") or {}
    if missing:
        found.append({"kind": "missing structure",
                      "detail": ", ".join(f"{k} gain {v:.1f} dB" for k, v in missing.items()),
                      "message": "\n".join(_eval_warning(metrics, f"{k} views: where the photos show structure")
                                           or f"{k} structure gain {v:.1f} dB" for k, v in missing.items())})
    return found


def describe_detection(ok: bool, per_seed: list[list[dict]], seeds: list[int],
                       baseline_kinds: set[str] = frozenset()) -> tuple[str, str | None]:
    """(detection, message) of a row from the detectors that fired on each seed's run. A
    failing row counts as detected only by a detector that does not also fire on the baseline
    (`baseline_kinds`); one whose failure none reports is "NOT DETECTED". The message is the
    fired detectors' warnings (the first seed's that raised each), one per line; None when
    nothing fired."""
    kinds = {}
    for seed, found in zip(seeds, per_seed):
        for f in found:
            entry = kinds.setdefault(f["kind"], {"seeds": [], "first": f})
            entry["seeds"].append(seed)
    order = [k for k in DETECTORS if k in kinds] + [k for k in kinds if k not in DETECTORS]
    n = len(seeds)

    def label(k):
        e = kinds[k]
        return f"{k} ({e['first']['detail']}; {len(e['seeds'])} of {n} seed(s))"

    message = "\n".join(kinds[k]["first"]["message"] for k in order) or None
    if ok:
        return ("none needed" if not order else "passes; warned: " + "; ".join(label(k) for k in order)), message
    telling = [k for k in order if k not in baseline_kinds]
    if not telling:
        also = [k for k in order if k in baseline_kinds]
        return ("NOT DETECTED: training ends normally" + (
            f" (the {', '.join(also)} warning also fires on the baseline)" if also else "")), message
    return "; ".join(label(k) for k in telling), message


# ------------------------------------------------------------------------ over seeds
def seed_stats(values: list[float]) -> dict:
    """mean, sd (sample, 0 for one seed), min, max and n of one number over seeds."""
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max()), "n": int(len(v))}


def verdict_spread(values: list[float], line: float, paired_with: list[float] | None = None) -> dict:
    """How far a row's mean stands from its pass line, against the seed spread. With
    `paired_with` (the baseline's values for the same seeds) the criterion is relative: margin
    = mean(value - baseline) - line, spread = sd of those per-seed differences; else margin =
    mean(value) - line, spread = sd(values). `outside` is true when |margin| > spread (the
    verdict does not hinge on the seed), false when within it; None for one seed."""
    v = np.asarray(values, np.float64)
    if paired_with is not None:
        b = np.asarray(paired_with, np.float64)
        v = v - b if len(b) == len(v) else v - b.mean()
    margin = float(v.mean() - line)
    spread = float(v.std(ddof=1)) if len(v) > 1 else 0.0
    return {"margin_db": margin, "spread_db": spread, "outside": (abs(margin) > spread) if len(v) > 1 else None}


def _fmt_seeds(name: str, values: list[float], seeds: list[int]) -> str:
    st = seed_stats(values)
    return (f"{name} {st['mean']:.2f} ± {st['sd']:.2f} dB (seeds " + ", ".join(
        f"{s}: {x:.2f}" for s, x in zip(seeds, values)) + ")")


# --------------------------------------------------------------------- a thin object
_DATASET = {"preset": "thin-plant", "capture": "orbit", "views": 18, "width": 128, "height": 96, "seed": 0,
            "points": 0, "orbit_radius": 0.5, "camera_height": 0.8, "target_height": 0.3}


def scene_settings(spec: dict) -> tuple[dict, object, dict]:
    """A case's `dataset` with its defaults filled in, the scene config its preset resolves to,
    and that config as JSON values (the preset as the code has it now: a changed preset renders
    the scene, and runs the case, again)."""
    from ghsplat_jax.synth import config

    p = _DATASET | dict(spec)
    cfg = config.preset_config(p["preset"], {"seed": int(p["seed"])})
    return p, cfg, json.loads(json.dumps(dataclasses.asdict(cfg)))


def prepare_scene(spec: dict, folder: Path) -> Path:
    """A synth preset scene (`dataset = {preset, capture, views, width, height, ...}` of a train
    case) rendered into `folder`, kept while its settings hold. `points = 0`: cameras only."""
    from ghsplat_jax.synth import capture, dataset, scene

    p, cfg, resolved = scene_settings(spec)
    p["scene"] = resolved
    stamp = folder / "prepare.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == p:
        return folder
    world = scene.generate_scene(cfg)
    path = capture.PathConfig(orbit_radius=float(p["orbit_radius"]), height=float(p["camera_height"]),
                              target_height=float(p["target_height"]))
    cams = capture.capture_path(world, p["capture"], int(p["views"]), width=int(p["width"]),
                                height=int(p["height"]), seed=int(p["seed"]), config=path)
    dataset.write_dataset(world, cams, folder, n_points=int(p["points"]), meshes=False, overwrite=True)
    write_json(stamp, p)
    return folder


def object_psnr(surfels, views, folder: Path, cfg) -> float | None:
    """Mean over `views` of the PSNR over the pixels the dataset's instance masks mark as a
    plant (synth's masks/STEM.png, instances.json), the render clipped to [0, 1]; None when no
    view has such a pixel."""
    import jax

    from ghsplat_jax.data.images import read_pixels
    from ghsplat_jax.raster.render import capacity_for_views, render

    plants = [i["id"] for i in json.loads((folder / "instances.json").read_text())["instances"]
              if i["class"] == "plant"]
    surfels = jax.tree_util.tree_map(jax.numpy.asarray, surfels)
    rcfg = dataclasses.replace(cfg.raster, pair_capacity=capacity_for_views(surfels, [v.camera for v in views],
                                                                             cfg.raster))
    out = []
    for v in views:
        mask = np.isin(read_pixels(folder / "masks" / (Path(v.name).stem + ".png")), plants)
        mask = mask.reshape(mask.shape[:2])
        h, w = v.image.shape[:2]
        if mask.shape != (h, w):  # a downscaled run: the mask's nearest pixels
            mask = mask[(np.arange(h) * mask.shape[0] // h)[:, None], np.arange(w) * mask.shape[1] // w]
        if not mask.any():
            continue
        rgb = np.clip(np.asarray(render(surfels, v.camera, rcfg).rgb, np.float64), 0, 1)
        mse = max(float(np.mean((rgb[mask] - v.image[mask]) ** 2)), 1e-20)
        out.append(-10 * np.log10(mse))
    return float(np.mean(out)) if out else None


# ------------------------------------------------------------------------- a training case
def case_seeds(case: dict, ctx) -> list[int]:
    seeds = case.get("seeds", ctx.seeds if ctx is not None else None) or [int(ctx.train_base.seed)]
    if not isinstance(seeds, list) or not all(isinstance(x, int) for x in seeds):
        raise StudyError(f"case {case['name']!r}: seeds must be a list of integers, got {seeds!r}")
    return seeds


def _train_seed(case: dict, ctx, seed: int) -> dict:
    from ghsplat_jax.eval.evaluate import evaluate
    from ghsplat_jax.sfm.triangulate import with_triangulated_points
    from ghsplat_jax.train.trainer import train

    release_compiled_programs()
    cfg = _train_config(case, ctx)
    if case.get("dataset"):
        cfg = cfg.replace(data=str(ctx.scenes[case["name"]]))
    noise = float(case.get("pose_noise", 0.0))
    cfg = cfg.replace(pose_noise=noise, seed=int(seed))
    ds = _load(case, cfg)
    out = ctx.output / "train" / case["name"] / f"seed{seed}"
    shutil.rmtree(out, ignore_errors=True)
    with _capture_warnings() as warnings:
        start = time.perf_counter()
        if case.get("triangulate", True) and case.get("init") != "random":  # as `ghsplat train` does
            ds = with_triangulated_points(ds, cfg.init_min_points, out)
        result = train(cfg, out, dataset=ds)
        seconds = time.perf_counter() - start
    # scored on the intact images (a corrupt training view is the input's fault, not the model's)
    clean = _load(dict(case, corrupt_views=0), cfg) if case.get("corrupt_views") else ds
    metrics = evaluate(result.surfels, clean, cfg, out, result.train_seconds, result.steps)
    med = _median_test(out)
    plant = object_psnr(result.surfels, clean.test, Path(cfg.data), cfg) if case.get("goal_plant_psnr") else None
    points = 0 if ds.points is None else int(len(ds.points))
    return {"seed": int(seed), **med, "test_psnr_mean": metrics["test"]["psnr"], "plant_psnr": plant,
            "finite": _finite_on_disk(out), "rollbacks": result.rollbacks, "num_gaussians": metrics["num_gaussians"],
            "steps": metrics["steps"], "train_seconds": metrics["train_seconds"], "seconds": seconds,
            "found": detect(metrics, warnings), "init_points": points, "train_views": len(ds.train),
            "test_views": len(ds.test), "image_size": f"{ds.train[0].camera.width}x{ds.train[0].camera.height}",
            "structure_psnr": metrics["test"].get("structure_psnr"), "cfg_steps": cfg.steps}


def run_train(case: dict, ctx) -> list[dict]:
    seeds = case_seeds(case, ctx)
    if case.get("dataset"):
        ctx.scenes[case["name"]] = prepare_scene(
            case["dataset"], ctx.output / "scenes" / hashlib.sha256(
                json.dumps(case["dataset"], sort_keys=True).encode()).hexdigest()[:12])
    runs = [_train_seed(case, ctx, s) for s in seeds]
    r0 = runs[0]
    noise = float(case.get("pose_noise", 0.0))
    what = [f"pose noise {100 * noise:g}% of extent" if noise else "",
            f"{r0['train_views']} training views" if case.get("views") else "",
            "random init (no SfM points)" if case.get("init") == "random" else "",
            f"SfM points jittered {100 * float(case['init_jitter']):g}% of extent" if case.get("init_jitter") else "",
            f"{case['corrupt_views']} NaN view(s)" if case.get("corrupt_views") else "",
            (f"{case['dataset'].get('preset', 'thin-plant')} scene, cameras without points, "
             + (f"{r0['init_points']} triangulated points" if r0["init_points"] else "random init (no points)")
             + ("" if case.get("triangulate", True) else " (--no-triangulate)")) if case.get("dataset") else ""]
    method = "; ".join(w for w in what if w) or "exact poses, all views, SfM-point init (baseline)"
    psnrs = [r["test_psnr"] for r in runs]
    st = seed_stats(psnrs)
    finite = all(r["finite"] for r in runs)
    base = ctx.baseline  # {seed: test PSNR} of the baseline case
    goal = case.get("goal_plant_psnr")
    spread = None
    if goal is not None:  # an absolute criterion on the object's own pixels
        plant = [r["plant_psnr"] if r["plant_psnr"] is not None else float("nan") for r in runs]
        pst = seed_stats(plant)
        ok = finite and pst["mean"] >= float(goal)
        spread = verdict_spread(plant, float(goal))
        error = (_fmt_seeds("plant-pixel PSNR", plant, seeds) + f" (goal >= {float(goal):g} dB, "
                 f"{spread['margin_db']:+.2f} dB); whole-image test PSNR "
                 f"{np.mean([r['test_psnr_mean'] for r in runs]):.2f} dB (median "
                 f"{st['mean']:.2f}); train PSNR {np.mean([r['train_psnr'] for r in runs]):.2f} dB")
    elif case.get("baseline") or not base:
        ok = finite and all(math.isfinite(x) for x in psnrs)
        error = _fmt_seeds("test PSNR", psnrs, seeds) + " (baseline)"
    else:
        paired = [base.get(s, float("nan")) for s in seeds]
        if not all(math.isfinite(x) for x in paired):
            paired = list(base.values())
        spread = verdict_spread(psnrs, -PSNR_DROP_DB, paired)
        ok = finite and spread["margin_db"] >= 0  # mean(psnr - baseline) >= -PSNR_DROP_DB
        error = (_fmt_seeds("test PSNR", psnrs, seeds)
                 + f" ({spread['margin_db'] - PSNR_DROP_DB:+.2f} dB vs baseline mean)")
    if spread is not None and spread["outside"] is not None:
        error += (f"; {'pass' if ok else 'fail'} {'stands outside' if spread['outside'] else 'is WITHIN'} the seed "
                  f"spread (|margin| {abs(spread['margin_db']):.2f} vs sd {spread['spread_db']:.2f} dB)")
    base_kinds = set(ctx.baseline_kinds) if not case.get("baseline") and goal is None else set()
    detection, message = describe_detection(ok, [r["found"] for r in runs], seeds, base_kinds)
    if message is None:  # what `ghsplat train` prints at the end (first seed)
        message = (f"OUT: {r0['num_gaussians']} surfels, {r0['steps']} steps, {r0['train_seconds']:.1f} s, "
                   f"test PSNR {r0['test_psnr_mean']:.2f} dB")
    if case.get("baseline"):
        ctx.baseline = {r["seed"]: r["test_psnr"] for r in runs}
        ctx.baseline_kinds = {f["kind"] for r in runs for f in r["found"]}
    per_seed = [{k: r[k] for k in ("seed", "test_psnr", "test_psnr_mean", "train_psnr", "plant_psnr",
                                   "structure_psnr", "rollbacks", "num_gaussians", "init_points", "seconds")}
                | {"detected": [f["kind"] for f in r["found"]]} for r in runs]
    return [_row(case, method, ok, error, detection, message,
                 f"run: {r0['image_size']}, {r0['cfg_steps']} steps, seeds {', '.join(map(str, seeds))}",
                 test_psnr=st["mean"], test_psnr_sd=st["sd"], test_psnrs=psnrs, seeds=seeds,
                 plant_psnr=None if goal is None else seed_stats(plant)["mean"],
                 test_psnr_whole_mean=float(np.mean([r["test_psnr_mean"] for r in runs])),
                 test_l1=float(np.mean([r["test_l1"] for r in runs])),
                 train_psnr=float(np.mean([r["train_psnr"] for r in runs])), pose_noise=noise,
                 train_views=r0["train_views"], test_views=r0["test_views"], steps=r0["cfg_steps"],
                 rollbacks=sum(r["rollbacks"] for r in runs), finite_on_disk=finite,
                 num_gaussians=r0["num_gaussians"], seconds=sum(r["seconds"] for r in runs),
                 baseline_psnr=None if case.get("baseline") or not base else float(np.mean(list(base.values()))),
                 margin_db=None if spread is None else spread["margin_db"],
                 spread_db=None if spread is None else spread["spread_db"],
                 outside_spread=None if spread is None else spread["outside"], per_seed=per_seed)]


class _capture_warnings:
    """Collect the warning lines of training and of its triangulation (what the user sees on
    the console)."""

    LOGGERS = ("ghsplat.train", "ghsplat.sfm")

    def __enter__(self):
        self.lines: list[str] = []
        self.handler = logging.Handler(logging.WARNING)
        self.handler.emit = lambda record: self.lines.append(f"WARNING {record.name}: {record.getMessage()}")
        for name in self.LOGGERS:
            logging.getLogger(name).addHandler(self.handler)
        return self.lines

    def __exit__(self, *exc):
        for name in self.LOGGERS:
            logging.getLogger(name).removeHandler(self.handler)
        return False


def run_divergence(case: dict, ctx) -> list[dict]:
    from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, PLY_NAME
    from ghsplat_jax.train.trainer import TrainingDivergedError, train

    cfg = _train_config(case, ctx)
    ds = _load(case, cfg)
    out = ctx.output / "divergence" / case["name"]
    shutil.rmtree(out, ignore_errors=True)
    raised, steps = None, None
    with _capture_warnings() as warnings:
        try:
            steps = train(cfg, out, dataset=ds).steps
        except TrainingDivergedError as exc:
            raised = exc
    finite = _finite_on_disk(out)
    stopped = raised is not None
    ok = stopped and finite and not (out / PLY_NAME).exists()
    overrides = ", ".join(f"{k} = {v}" for k, v in case.get("train", {}).items())
    error = (f"stopped with TrainingDivergedError after {len(warnings)} rolled-back step(s); "
             if stopped else f"ran {steps} steps without stopping; ") + \
        f"non-finite values on disk: {'none' if finite else 'YES'}; point_cloud.ply written: " \
        f"{'yes' if (out / PLY_NAME).exists() else 'no'}; " \
        f"checkpoint kept: {'yes' if (out / CHECKPOINT_NAME).exists() else 'no'}"
    detection = ("NaN guard: non-finite loss or parameters -> roll back; after max_consecutive_rollbacks "
                 "(or max_total_rollbacks) stop, exit 2" if stopped else "NOT DETECTED")
    message = f"ghsplat train: {raised}" if stopped else "(none)"
    return [_row(case, overrides, ok, error, detection, message, f"run: {cfg.steps} steps max",
                 rollbacks=len(warnings), finite_on_disk=finite, first_warning=warnings[0] if warnings else None)]


# ----------------------------------------------------------------------------- rendering
def _random_surfels(rng: np.random.Generator, n: int, opacity: tuple[float, float], scale: tuple[float, float]):
    """n random surfels in a 2.4 x 1.6 x 1.6 m box, opacities and scales uniform in the given ranges."""
    from ghsplat_jax.core.surfels import make_surfels

    means = rng.uniform(-1, 1, (n, 3)) * [1.2, 0.8, 0.8]
    op = rng.uniform(*opacity, n)
    return make_surfels(means, rng.normal(size=(n, 4)), np.log(rng.uniform(*scale, (n, 2))),
                        np.log(op / (1 - op)), rng.normal(0, 0.6, (n, 3)), rng.normal(0, 0.2, (n, 3, 3)), 1)


def raster_scene(kind: str, seed: int = 0):
    """(surfels, camera, indices the renderer must cull as invalid) for an opaque, a sparse or a
    degenerate scene; the camera looks along +y at the origin from 3.5 m."""
    from ghsplat_jax.core.camera import Camera, intrinsics, look_at
    from ghsplat_jax.core.surfels import make_surfels

    rng = np.random.default_rng(seed)
    cam = lambda w, h: Camera(intrinsics(w, h, 60.0), look_at([0.0, -3.5, 0.6], [0, 0, 0]), w, h)
    if kind == "opaque":  # many layers of nearly opaque surfels: transmittance reaches 1e-4 early
        return _random_surfels(rng, 400, (0.9, 0.99), (0.15, 0.4)), cam, []
    if kind == "sparse":  # a few faint surfels: most pixels never saturate
        return _random_surfels(rng, 24, (0.03, 0.3), (0.05, 0.2)), cam, []
    if kind != "degenerate":
        raise StudyError(f"raster scene must be opaque, sparse or degenerate, got {kind!r}")
    # ordinary surfels plus one of every awkward kind (as tests/test_raster_robustness.py's bad_scene)
    awkward = [[0, 0, 0.2],          # edge-on (plane normal z, seen from -y)
               [0, -5, 0],           # behind the camera
               [0, -2.9, 0.5],       # centre 0.6 m ahead, plane reaching behind the camera
               [0.2, 0, 0],          # near-zero scale
               [0.1, 0, 0],          # huge scale
               [0, 2, 0],            # covers the whole screen
               [0.1, 0.1, 0],        # unnormalised quaternion
               [0.2, 0.1, 0],        # zero quaternion (invalid)
               [np.nan, 0, 0],       # NaN mean (invalid)
               [0, 0, np.inf]]       # Inf mean (invalid)
    n0 = 40
    means = np.concatenate([rng.uniform(-1, 1, (n0, 3)) * [1.0, 0.5, 0.6], np.array(awkward, float)])
    n = len(means)
    quats = np.concatenate([rng.normal(size=(n0, 4)), np.tile([1.0, 0, 0, 0], (n - n0, 1))])
    quats[n0 + 2] = [0.7071, 0.7071, 0, 0]
    quats[n0 + 6] = [5.0, 3.0, -2.0, 1.0]
    quats[n0 + 7] = [0, 0, 0, 0]
    ls = np.concatenate([np.log(rng.uniform(0.05, 0.2, (n0, 2))), np.full((n - n0, 2), np.log(0.1))])
    ls[n0 + 2] = np.log(0.5)
    ls[n0 + 3] = -80.0
    ls[n0 + 4] = 60.0
    ls[n0 + 5] = np.log(50.0)
    op = np.concatenate([rng.uniform(0.2, 0.9, n0), np.full(n - n0, 0.6)])
    s = make_surfels(means, quats, ls, np.log(op / (1 - op)), rng.normal(0, 0.6, (n, 3)), rng.normal(0, 0.2, (n, 3, 3)),
                     1)
    return s, cam, [n0 + 7, n0 + 8, n0 + 9]


def run_raster(case: dict, ctx) -> list[dict]:
    import jax

    from ghsplat_jax.raster.config import RasterConfig
    from ghsplat_jax.raster.reference import render_reference
    from ghsplat_jax.raster.render import render

    kind, comp = case.get("scene", "opaque"), case.get("compositor", "carried")
    s, cam_fn, invalid = raster_scene(kind, int(case.get("seed", 0)))
    cam = cam_fn(int(case.get("width", 64)), int(case.get("height", 48)))
    cfg = RasterConfig(compositor=comp, background=(0.2, 0.3, 0.4))
    out = render(s, cam, cfg)
    keep = np.setdiff1d(np.arange(s.means.shape[0]), invalid)
    ref = render_reference(jax.tree_util.tree_map(lambda a: np.asarray(a)[keep], s), cam, cfg)
    finite = all(bool(np.all(np.isfinite(np.asarray(getattr(out, k))))) for k in
                 ("rgb", "alpha", "depth", "median_depth", "normal", "distortion"))
    err = {k: float(np.max(np.abs(np.asarray(getattr(out, k), np.float64) - ref[k]))) for k in ("rgb", "alpha")}
    worst = max(err.values())
    # The rasterizer bins each surfel over its 3-sigma ellipse, as 2DGS does (docs/design.md, "Bounds");
    # the dense reference does not, so each pixel may lose up to opacity * exp(-9/2) per surfel.
    opacity = 1 / (1 + np.exp(-np.asarray(s.opacity_logits, np.float64)[keep]))
    truncation = float(opacity.max() * np.exp(-4.5)) if opacity.max() * np.exp(-4.5) >= 1 / 255 else 0.0
    ok = finite and worst <= RASTER_TOL + truncation
    other = render(s, cam, dataclasses.replace(cfg, compositor="logspace" if comp == "carried" else "carried"))
    between = float(np.max(np.abs(np.asarray(out.rgb, np.float64) - np.asarray(other.rgb, np.float64))))
    st = out.stats
    n_invalid, n_near = int(st.num_invalid), int(st.num_culled_near)
    label = {"carried": "carried (early-terminating, T < 1e-4)", "logspace": "logspace (two-pass log transmittance)"}
    alpha = np.asarray(out.alpha)
    error = (f"max |rgb - ref| {err['rgb']:.2e}, max |alpha - ref| {err['alpha']:.2e} (allowed "
             f"{RASTER_TOL + truncation:.1e}); max |rgb - other compositor| {between:.1e}; outputs finite: "
             f"{'yes' if finite else 'NO'}; median alpha {float(np.median(alpha)):.3f}")
    if kind == "degenerate":
        detection = (f"culled before binning: RasterStats.num_invalid = {n_invalid} (NaN, Inf, zero quaternion), "
                     f"num_culled_near = {n_near}")
        message = "(none: culled quietly, counted in the render's stats)"
    else:
        detection = "none needed" if ok else "NOT DETECTED"
        message = "(none)"
    return [_row(case, f"compositor {label.get(comp, comp)}", ok, error, detection, message,
                 f"run: {cam.width}x{cam.height}, {s.means.shape[0]} surfels", max_abs_rgb=err["rgb"],
                 max_abs_alpha=err["alpha"], allowed=RASTER_TOL + truncation, max_abs_vs_other_compositor=between,
                 finite=finite, num_invalid=n_invalid, num_culled_near=n_near,
                 median_alpha=float(np.median(alpha)))]


RUNNERS = {"sfm_recorded": run_sfm_recorded, "sfm": run_sfm, "train": run_train, "divergence": run_divergence,
           "raster": run_raster}


# ---------------------------------------------------------------------------- the study
@dataclasses.dataclass
class Context:
    output: Path
    scratch: Path
    train_base: object
    row: Path | None = None
    baseline: dict = dataclasses.field(default_factory=dict)  # {seed: test PSNR} of the baseline case
    baseline_kinds: set = dataclasses.field(default_factory=set)  # detectors that fire on the baseline
    seeds: list | None = None  # the study file's `seeds` (a case's own `seeds` wins)
    scenes: dict = dataclasses.field(default_factory=dict)  # case name -> its rendered `dataset` scene
    prepare: dict = dataclasses.field(default_factory=dict)
    recorded: Path | None = None  # the file sfm_recorded cases read (the experiment's `sfm_recorded`)


def _key(case: dict, ctx) -> str:
    extra = {}
    if case["family"] in ("train", "divergence"):
        extra = {"train": ctx.train_base.to_dict(), "prepare": ctx.prepare, "seeds": case_seeds(case, ctx),
                 "baseline": {str(k): v for k, v in sorted(ctx.baseline.items())}}
        if case.get("dataset"):  # a preset scene: its settings as the code has them now
            extra["scene"] = scene_settings(case["dataset"])[2]
    elif case["family"] == "sfm_recorded":  # the rows it reads
        recorded = ctx.recorded if ctx is not None else None
        extra = {"recorded": hashlib.sha256(recorded.read_bytes()).hexdigest() if recorded and recorded.is_file()
                 else None}
    elif case["family"] == "sfm":  # the SfM defaults it runs with
        from ghsplat_jax.sfm.pipeline import SfmOptions

        extra = {"sfm": dataclasses.asdict(SfmOptions())}
    return json.dumps({"case": case, **extra}, sort_keys=True, default=str)


def run_study(exp, only: set[str] | None = None) -> dict:
    """Run every case of a loaded stability experiment (`experiments.runner.Experiment`, kind
    "stability") and write the reports; returns {"rows", "failed" (errors), "reports"}."""
    from ghsplat_jax.train.config import TrainConfig, apply_overrides

    spec = exp.spec
    cases = check_cases(spec.get("cases"))
    if only:  # the baseline stays in (reused from its cache when unchanged): the others are judged against it
        picked = [c for c in cases if c["name"] in only or c["family"] in only]
        trains = any(c["family"] == "train" for c in picked)
        cases = [c for c in cases if c in picked or (trains and c.get("baseline"))]
    base = apply_overrides(TrainConfig(), spec.get("train", {}), f"{exp.source} [train]")
    output = Path(exp.output)
    (output / "cases").mkdir(parents=True, exist_ok=True)
    recorded = spec.get("sfm_recorded")
    ctx = Context(output, output, base, prepare=dict(_PREPARE, **spec.get("prepare", {})),
                  recorded=Path(recorded) if recorded else None, seeds=spec.get("seeds"))
    # the baseline first: the other training cases are judged against it
    cases = sorted(cases, key=lambda c: not c.get("baseline"))
    rows, failed = [], []
    revision = code_revision()  # each row keeps the revision it ran at (cached rows: theirs, or none)
    for case in cases:
        if case["family"] in ("train", "divergence") and ctx.row is None:
            log.info("rendering the training row into %s", output / "row")
            ctx.row = prepare_row(spec.get("prepare", {}), output / "row")
        cache = output / "cases" / f"{case['name']}.json"
        key = _key(case, ctx)
        if cache.is_file() and (cached := json.loads(cache.read_text())).get("key") == key:
            log.info("%s: unchanged, reusing %s", case["name"], cache)
            got = cached["rows"]
        else:
            log.info("%s (%s): running", case["name"], case["family"])
            release_compiled_programs()  # many runs in one process: see host_memory
            start = time.perf_counter()
            try:
                got = RUNNERS[case["family"]](case, ctx)
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # noqa: BLE001  (one broken case must not lose the others)
                msg = f"{type(exc).__name__}: {exc}"
                log.error("%s failed: %s", case["name"], msg)
                failed.append((case["name"], msg))
                got = [_row(case, "-", False, f"the study could not run this case: {msg}",
                            "study error (not a tool check)", msg, "run") | {"code_revision": revision}]
                rows.extend(got)
                continue
            for r in got:
                r.setdefault("seconds", time.perf_counter() - start)
                r["code_revision"] = revision
            write_json(cache, {"key": key, "rows": json_safe(got)})
        if case.get("baseline") and got and got[0].get("test_psnrs"):  # a cached baseline: the seeds' values
            ctx.baseline = dict(zip(got[0]["seeds"], got[0]["test_psnrs"]))
            ctx.baseline_kinds = {k for p in got[0].get("per_seed", []) for k in p.get("detected", [])}
        rows.extend(got)
    order = {c["name"]: i for i, c in enumerate(check_cases(spec.get("cases")))}
    if only:  # a partial rerun: the other cases keep their rows from the last full report
        rerun = {c["name"] for c in cases}
        rows += [r for r in _reported_rows(exp) if r["case"] in order and r["case"] not in rerun]
    rows.sort(key=lambda r: order.get(r["case"], len(order)))  # the file's order (stable within a case)
    reports = write_reports(rows, exp, spec)
    return {"rows": rows, "failed": failed, "reports": reports}


def _revisions(rows: list[dict]) -> list[tuple[str, int]]:
    """(code revision, rows run at it) in first-seen order; rows run before rows kept it: "not recorded"."""
    counts: dict[str, int] = {}
    for r in rows:
        rev = r.get("code_revision") or "not recorded"
        counts[rev] = counts.get(rev, 0) + 1
    return list(counts.items())


def _reported_rows(exp) -> list[dict]:
    """Rows of the last written report (RESULTS/stability.json), [] without one."""
    path = Path(exp.results) / "stability.json"
    return json.loads(path.read_text())["rows"] if path.is_file() else []


# ------------------------------------------------------------------------------- reports
def _cell(v) -> str:
    return "" if v is None else str(v).replace("|", "\\|").replace("\n", "<br>")


def summary(rows: list[dict]) -> dict:
    fails = [r for r in rows if r["result"] == "fail"]
    silent = [f"{r['case']} ({r['method']})" for r in fails if r["detection"].startswith("NOT DETECTED")]
    return {"rows": len(rows), "pass": len(rows) - len(fails), "fail": len(fails),
            "fail_detected": len(fails) - len(silent), "fail_not_detected": silent}


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(c)) for c in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def write_reports(rows: list[dict], exp, spec: dict) -> list[Path]:
    results = Path(exp.results)
    results.mkdir(parents=True, exist_ok=True)
    s = summary(rows)
    train = spec.get("train", {})
    criteria = {"sfm": f"pass = status ok and camera-centre RMSE <= {SFM_GOAL_PCT}% of the extent (similarity-"
                       "aligned to the true cameras)",
                "train": f"pass = finite and median test-view PSNR within {PSNR_DROP_DB} dB of the baseline "
                         "(test views keep their true poses)",
                "divergence": "pass = the run stops with TrainingDivergedError, nothing non-finite on disk, "
                              "no point_cloud.ply",
                "raster": f"pass = every output finite and max |render - float64 reference| <= {RASTER_TOL} plus "
                          "the documented 3-sigma truncation (max opacity x e^-4.5 where that reaches 1/255) "
                          "(rgb and alpha; the dense reference gets the scene without the invalid surfels)"}
    report = {"experiment": exp.name, "preset": exp.preset, "source": str(exp.source), "machine": machine_info(),
              "code_revision": code_revision(),
              "criteria": criteria, "prepare": dict(_PREPARE, **spec.get("prepare", {})), "train": train,
              "summary": s, "rows": json_safe(rows)}
    paths = [write_json(results / "stability.json", report)]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS) + sorted({k for r in rows for k in r} - set(COLUMNS)))
    writer.writeheader()
    writer.writerows(json_safe(rows))
    with atomic_write(results / "stability.csv", "w") as fh:
        fh.write(buffer.getvalue())
    paths.append(results / "stability.csv")
    md = [f"# Stability where methods fail ({exp.name}, preset {exp.preset})", "",
          f"{exp.description}".strip(), "",
          f"Made by `ghsplat run {exp.source}" + (f" --preset {exp.preset}`" if exp.preset != "full" else "`")
          + f" on {report['machine']['platform']}, {report['machine']['cpu_count']} CPUs, jax "
          f"{report['machine']['jax']} ({report['machine']['jax_backend']}). Training row: "
          f"{report['prepare']['plants']} plants, {report['prepare']['views']} hand-held views at "
          f"{report['prepare']['width']}x{report['prepare']['height']}, every {report['prepare']['test_every']}th "
          "a test view" + (f"; {train.get('steps')} steps" if train.get("steps") else "") + ". Report at code "
          f"revision `{report['code_revision']}`; the code revision each case ran at: "
          + ", ".join(f"{rev} ({n} rows)" for rev, n in _revisions(rows)) + ".", "",
          "Criteria: " + "; ".join(f"**{k}**: {v}" for k, v in criteria.items()) + ".", "",
          table(rows),
          "## Reading", "",
          f"{s['rows']} rows: {s['pass']} pass, {s['fail']} fail, of which {s['fail_detected']} are detected by "
          f"the tool and {len(s['fail_not_detected'])} are not"
          + (f" ({'; '.join(s['fail_not_detected'])})" if s["fail_not_detected"] else "") + ".", ""]
    md += reading(rows)
    with atomic_write(results / "stability.md", "w") as fh:
        fh.write("\n".join(md) + "\n")
    paths.append(results / "stability.md")
    png = plot(rows, results / "stability.png")
    if png:
        paths.append(png)
    return paths


def reading(rows: list[dict]) -> list[str]:
    """A few measured sentences per family (no adjectives the numbers do not carry)."""
    out = []
    sfm = [r for r in rows if r["family"].startswith("sfm")]
    if sfm:
        ok = [r for r in sfm if r["result"] == "pass"]
        sfm = [r for r in sfm if not r["detection"].startswith("study error")]
        out.append(f"- SfM: {len(ok)} of {len(sfm)} (case, method) rows pass; every failing row is "
                   + ("refused by the fold check or the registered-fraction check (exit 4 or 3)."
                      if all(not r["detection"].startswith("NOT") for r in sfm if r["result"] == "fail")
                      else "listed above with its detection; the NOT DETECTED ones return exit 0 with a wrong model."))
    tr = [r for r in rows if r["family"] == "train" and r.get("test_psnr") is not None]
    if tr:
        parts = [f"{r['case']} {r['test_psnr']:.2f}" + (f" ± {r['test_psnr_sd']:.2f}" if r.get("test_psnr_sd") else "")
                 + " dB" for r in tr]
        out.append("- Training (median test PSNR, mean ± sd over seeds): " + ", ".join(parts) + ".")
        close = [r["case"] for r in tr if r.get("outside_spread") is False]
        if close:
            out.append("- Verdicts within the seed spread (the pass line lies inside one sd of the seeds' "
                       "margins, so another seed could flip them): " + ", ".join(close) + ".")
        silent = [r["case"] for r in tr if r["result"] == "fail" and r["detection"].startswith("NOT DETECTED")]
        out.append("- Training failures no check reports: " + (", ".join(silent) if silent else "none") + ".")
    dv = [r for r in rows if r["family"] == "divergence"]
    if dv:
        out.append("- Divergence: " + "; ".join(f"{r['case']}: {r['result']} ({r['error']})" for r in dv) + ".")
    ra = [r for r in rows if r["family"] == "raster" and r.get("max_abs_rgb") is not None]
    if ra:
        between = max(r.get("max_abs_vs_other_compositor") or 0.0 for r in ra)
        out.append("- Rendering: largest error against the float64 reference "
                   f"{max(max(r['max_abs_rgb'], r['max_abs_alpha']) for r in ra):.1e} over {len(ra)} (scene, "
                   f"compositor) rows; the two compositors differ from each other by at most {between:.1e}"
                   + (" (below the 1e-4 transmittance at which the early-terminating one stops), so what differs "
                      "from the reference comes from binning (the 3-sigma truncation), not compositing"
                      if between <= 1e-4 else "") + "; outputs are finite in "
                   f"{sum(bool(r['finite']) for r in ra)} of {len(ra)} rows.")
    return out


def plot(rows: list[dict], path: Path) -> Path | None:
    tr = [r for r in rows if r["family"] == "train" and r.get("test_psnr") is not None]
    noise = sorted((r for r in tr if r.get("train_views") and not r["case"].startswith(("views", "init", "corrupt"))
                    and (r.get("pose_noise") or r.get("baseline_psnr") is None)), key=lambda r: r["pose_noise"])
    views = sorted((r for r in tr if r["case"].startswith("views") or r.get("baseline_psnr") is None),
                   key=lambda r: r["train_views"])
    if len(noise) < 2 and len(views) < 2:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    base = next((r["test_psnr"] for r in tr if r.get("baseline_psnr") is None), None)
    for ax, sel, x, label in ((axes[0], noise, "pose_noise", "training pose noise (% of scene extent)"),
                              (axes[1], views, "train_views", "training views")):
        xs = [100 * r[x] if x == "pose_noise" else r[x] for r in sel]
        ax.plot(xs, [r["test_psnr"] for r in sel], "o-", label="median test PSNR")
        ax.plot(xs, [r["train_psnr"] for r in sel], "s--", alpha=0.6, label="median train PSNR")
        if base is not None:
            ax.axhline(base - PSNR_DROP_DB, color="red", linestyle=":", label=f"baseline - {PSNR_DROP_DB:g} dB (pass)")
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Training stability on a synthetic row (same seed for every variant)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path
