"""Evaluate trained surfels on a dataset's views: metrics per view and split, render time,
renders with depth and normal maps, and the run's metrics.json (train/run_dir.py: where);
train_and_evaluate: one run trained and evaluated (`ghsplat train`, the experiment runner)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from ghsplat_jax.data.splits import subsample
from ghsplat_jax.eval.geometry import geometry_errors, ground_truth, truth_source
from ghsplat_jax.eval.metrics import (
    TRAIN_TEST_GAP_DB,
    background_cover,
    colour_corrected_metrics,
    image_metrics,
    lpips_metrics,
    missing_structure,
    psnr_outliers,
    structure_metrics,
    summarize,
)
from ghsplat_jax.io_utils import code_revision, device_name, machine_info
from ghsplat_jax.train import exposure as exposure_mod
from ghsplat_jax.train import run_dir as rd

log = logging.getLogger("ghsplat.eval")


def depth_colormap(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Turbo-coloured depth (near = red), robust range over covered pixels, black where empty."""
    from matplotlib import colormaps

    covered = alpha > 0.5
    if covered.any():
        lo, hi = np.percentile(depth[covered], [1, 99])
    else:
        lo, hi = 0.0, 1.0
    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = colormaps["turbo"](1.0 - t)[..., :3].astype(np.float32)
    return rgb * covered[..., None]


def normal_colormap(normal: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Alpha-weighted world normals shown as (n + 1) / 2 over alpha."""
    return np.clip(np.asarray(normal) * 0.5 + 0.5 * np.asarray(alpha)[..., None], 0, 1).astype(np.float32)


def save_view_maps(folder: Path, name: str, out) -> None:
    """rgb PNG, colour-mapped depth PNG + raw depth EXR, normal PNG ((n + 1) / 2 over alpha)."""
    from ghsplat_jax.data.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    stem = name.replace("/", "_").rsplit(".", 1)[0]
    rgb = np.clip(np.asarray(out.rgb), 0, 1)
    alpha = np.asarray(out.alpha)
    depth = np.nan_to_num(np.asarray(out.depth), nan=0.0, posinf=0.0, neginf=0.0)
    normal = np.nan_to_num(np.asarray(out.normal))
    write_image(folder / f"{stem}.png", rgb)
    write_image(folder / f"{stem}_depth.png", depth_colormap(depth, alpha))
    write_image(folder / f"{stem}_depth.exr", depth[..., None], dtype="float")
    write_image(folder / f"{stem}_normal.png", normal_colormap(normal, alpha))


def evaluate(surfels, dataset, config, out_dir, train_seconds: float | None = None, steps: int | None = None,
             save_renders: bool | None = None, progress: bool | None = None,
             train_peak_rss_mb: float | None = None, extra: dict | None = None,
             train_exposure: dict | None = None) -> dict:
    """Render every test view and (up to config.eval_max_train_views) training view, with LPIPS on
    the test views when config.eval_lpips and its weights are installed, and depth and normal
    error where the dataset is a synth scene with ground truth (eval/geometry.py); write
    OUT/metrics.json and OUT/per_view.json (and renders under OUT/renders/test/); return metrics.
    peak_rss_mb is this process's peak, or the training process's when that was larger.
    `extra`: more facts of the run for metrics.json (e.g. why a self-stopping run stopped).
    `train_exposure`: {training view name: its learnt exposure correction (exposure_corrections.json's
    row)}, applied to that view's render before it is scored, as training scored it; every other
    render is scored as it is."""
    import jax
    from tqdm.auto import tqdm

    from ghsplat_jax.raster.render import capacity_for_views, render

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_renders = config.save_test_renders if save_renders is None else save_renders
    progress = config.progress if progress is None else progress
    surfels = jax.tree_util.tree_map(jax.numpy.asarray, surfels)
    splits = {"train": subsample(list(dataset.train), config.eval_max_train_views or None), "test": list(dataset.test)}
    # Eager renders from exact pair counts (nothing dropped), all at one capacity: one compile.
    capacity = capacity_for_views(surfels, [v.camera for views in splits.values() for v in views], config.raster)
    rcfg = dataclasses.replace(config.raster, pair_capacity=capacity)
    rows, times = [], []
    warm = False
    # Where ground truth exists: its synth folder, and the similarity of the dataset's frame onto the scene's.
    frame = truth_source(getattr(dataset, "root", None))
    for split, views in splits.items():
        for v in tqdm(views, desc=f"eval {split}", disable=not progress, leave=False):
            if not warm:  # compile outside the timing
                jax.block_until_ready(render(surfels, v.camera, rcfg).rgb)
                warm = True
            t = time.perf_counter()
            out = render(surfels, v.camera, rcfg)
            jax.block_until_ready(out.rgb)
            dt = time.perf_counter() - t
            times.append(dt)
            rgb = out.rgb
            if split == "train" and v.name in (train_exposure or {}):
                rgb = exposure_mod.apply(rgb, exposure_mod.tone_of(train_exposure[v.name]))
            m = (image_metrics(rgb, v.image) | structure_metrics(rgb, v.image, v.alpha)
                 | background_cover(out.alpha, v.alpha))
            if split == "test":
                m |= colour_corrected_metrics(out.rgb, v.image)
            if split == "test" and config.eval_lpips:  # the papers report it on test views; a VGG pass is costly
                m |= lpips_metrics(out.rgb, v.image)
            truth = None if frame is None else ground_truth(frame[0], v.name, v.camera.width, v.camera.height)
            if truth is not None:  # a synth scene: depth and normal error against its ray-cast geometry
                m |= geometry_errors(out.median_depth if rcfg.median else None, out.normal, out.alpha, *truth,
                                     scale=frame[1], rotation=frame[2])
            if not all(math.isfinite(x) for x in m.values()):
                raise FloatingPointError(f"view {v.name}: non-finite metrics {m}")
            rows.append(dict(split=split, name=v.name, render_seconds=dt, **m))
            if save_renders and split == "test":
                save_view_maps(out_dir / rd.TEST_RENDERS, v.name, out)
    metrics = {
        "train": summarize([r for r in rows if r["split"] == "train"]),
        "test": summarize([r for r in rows if r["split"] == "test"]),
        "num_gaussians": int(surfels.num),
        "train_seconds": None if train_seconds is None else float(train_seconds),
        "steps": None if steps is None else int(steps),
        "render_seconds_per_view": float(np.median(times)) if times else None,
        "image_size": ([int(dataset.train[0].camera.width), int(dataset.train[0].camera.height)]
                       if dataset.train else None),
        "data": str(config.data),
        "peak_rss_mb": max(rd.peak_rss_mb(), train_peak_rss_mb or 0.0),
        "strategy": config.strategy.name,
        "recipe": config.recipe,
        "device": device_name(),  # where it trained and rendered (the timings above depend on it)
    }
    metrics.update(extra or {})
    metrics.update(diagnose(metrics, rows, where=out_dir))
    rd.write_metrics(out_dir, metrics, rows)
    return metrics


def diagnose(metrics: dict, rows: list[dict], where="", gap_db: float = TRAIN_TEST_GAP_DB) -> dict:
    """What evaluation must not leave silent, as metrics.json entries, each also logged as a
    warning that says what it hints at and what to do:
    `outlier_views` {split: [{name, psnr, below_median_db}]} (views far below their split's
    median: metrics.psnr_outliers), `train_test_gap_db` (training minus test PSNR; over
    `gap_db` is over-fitting), `missing_structure_db` {split: dB} (the structure gain, when the render
    does barely better than an empty one where the photos show structure: the model misses the
    subject), and `warnings`, the logged texts."""
    warnings = []

    def warn(text: str) -> None:
        log.warning("%s: %s", where, text) if where else log.warning("%s", text)
        warnings.append(text)

    outliers = {}
    for split in ("train", "test"):
        views = [r for r in rows if r["split"] == split]
        found = psnr_outliers(views)
        outliers[split] = found
        if found:
            median = float(np.median([r["psnr"] for r in views]))
            listed = ", ".join(f"{o['name']} ({o['psnr']:.2f} dB)" for o in found)
            warn(f"{len(found)} {split} view(s) far below the split's median PSNR ({median:.2f} dB): {listed}. "
                 "A view much worse than its neighbours hints at a bad pose (the SfM registered it wrongly) or a "
                 "bad image (blur, exposure, a moving object), or, at the ends of a capture, at parts of the scene "
                 "no other view covers: look at its render beside the photo, and drop or re-register a bad one")
    out = {"outlier_views": outliers}
    train, test = (metrics.get("train") or {}).get("psnr"), (metrics.get("test") or {}).get("psnr")
    gap = None if train is None or test is None else float(train - test)
    out["train_test_gap_db"] = gap
    if gap is not None and gap > gap_db:
        found = (f"the training views' PSNR ({train:.2f} dB) exceeds the test views' ({test:.2f} dB) by {gap:.1f} dB "
                 f"(more than {gap_db:g}): the model over-fits the training views. ")
        stop = metrics.get("stop") or {}
        val = stop.get("best_val_psnr")
        if val is not None and stop.get("validation_views") == []:  # nothing held out: blind to over-fitting
            from ghsplat_jax.train.trainer import MIN_HELD_OUT, MIN_LEFT_TO_TRAIN

            warn(found + f"The run had too few training views to hold some out, so its stop rule read the "
                 f"training views ({val:.2f} dB at its best) and could not see the over-fitting: capture more "
                 f"views (the checks hold out every val_hold_every-th training view once {MIN_HELD_OUT} can be "
                 f"spared with {MIN_LEFT_TO_TRAIN} left to train)")
        elif val is not None:  # a self-stopping run: its held-out views did not see the over-fitting
            warn(found + f"The views held out to stop the run scored {val:.2f} dB, so they lie closer to the "
                 "training views than the test views do: capture more views between, or around, where the test "
                 "views look from")
        else:
            warn(found + "Use fewer surfels (--strategy budget or mcmc with --max-surfels), more views, or "
                 "`--recipe auto`, which stops when held-out views stop improving")
    missing = {}
    for split in ("train", "test"):
        s = metrics.get(split) or {}
        g = missing_structure(s)
        if g is not None:
            missing[split] = g
            warn(f"{split} views: where the photos show structure the render is only {g:.1f} dB better than an "
                 f"empty one (the photos' background colour): {s['structure_psnr']:.2f} dB there, against "
                 f"{s['psnr']:.2f} dB over the whole image. The model misses what the photos show (e.g. a thin "
                 "plant on a plain background) and the whole-image score hides it. Look at the test renders; check "
                 "the initial points cover the subject, and train longer or at full resolution")
    out["missing_structure_db"] = missing
    out["warnings"] = warnings
    return out


def test_curve_metrics(dataset, config):
    """`measure(params, active, pair_capacity)`: the test views' mean metrics (as metrics.json's
    "test") of a training pool, for the test curve that training writes every
    `config.test_curve_every` steps. It renders the padded pool (free slots hidden behind each
    camera, so the image is that of the live surfels) with only colour and alpha, from the
    training's pair buffer at least: it compiles again only when the pool or a buffer grows."""
    from ghsplat_jax.raster.render import render
    from ghsplat_jax.train.state import render_params

    views = list(dataset.test)
    lean = dataclasses.replace(config.raster, median=False, distortion=False, depth_normal=False)

    def measure(params, active, pair_capacity: int) -> dict:
        rcfg = dataclasses.replace(lean, pair_capacity=pair_capacity)
        rows = []
        for v in views:
            out = render(render_params(params, active, v.camera.world_to_cam), v.camera, rcfg)
            rows.append(image_metrics(out.rgb, v.image) | background_cover(out.alpha, v.alpha))
        return summarize(rows)

    return measure


TRAINING_RECORD = ("stop", "compaction", "machine", "code_revision")  # facts of the training a re-evaluation keeps


def evaluate_run(run_dir, progress: bool = True) -> dict:
    """Re-evaluate a run folder from its config and point_cloud.ply. An unfinished run (a
    checkpoint but no point_cloud.ply, e.g. stopped with --until) is evaluated at its
    checkpoint into RUN_DIR/snapshots/step_NNNNNN/ so the run's own metrics.json stays absent.
    A finished run's metrics.json keeps what its training recorded (why it stopped, the machine
    and code revision it trained with); `evaluated` names this evaluation's."""
    run_dir = Path(run_dir)
    config, surfels, meta, finished = rd.load_run(run_dir)
    seconds, steps = meta.get("train_seconds"), meta.get("step")
    out_dir = run_dir
    if not finished:
        out_dir = rd.snapshot_dir(run_dir, steps)
        log.info("%s: unfinished; evaluating the checkpoint at step %d into %s", run_dir, steps, out_dir)
    previous = (rd.read_metrics(run_dir) or {}) if finished else {}
    if previous:  # the training's own record (a self-stopped run's checkpoint holds its best step, not its last)
        seconds, steps = previous.get("train_seconds", seconds), previous.get("steps", steps)
    dataset = rd.load_training_data(config)
    extra = {k: previous[k] for k in TRAINING_RECORD if k in previous} | {
        "evaluated": {"machine": machine_info(), "code_revision": code_revision()}}
    pose_file = run_dir / rd.POSE_NAME
    if pose_file.is_file():  # as train_and_evaluate: training views at their refined poses
        from ghsplat_jax.train.pose import refine_views

        pose = json.loads(pose_file.read_text())
        extra["pose_refinement"] = pose["summary"]
        dataset = dataclasses.replace(dataset, train=refine_views(dataset.train, pose["views"], pose["scene_extent"]))
    exposure_file = run_dir / rd.EXPOSURE_NAME
    exposure = None
    if exposure_file.is_file():  # as train_and_evaluate: training views scored under their corrections
        exposure = json.loads(exposure_file.read_text())
        extra["exposure_compensation"] = exposure["summary"]
    return evaluate(surfels, dataset, config, out_dir, seconds, steps, progress=progress,
                    train_peak_rss_mb=meta.get("peak_rss_mb"), extra=extra, train_exposure=by_view(exposure))


def by_view(corrections: dict | None) -> dict | None:
    """{view name: row} of a corrections file's `views` (None: none)."""
    return None if corrections is None else {r["name"]: r for r in corrections["views"]}


def train_and_evaluate(config, out_dir, resume: bool = False, dataset=None, evaluate: bool = True,
                       until: int | None = None) -> dict:
    """Train into `out_dir` and evaluate; returns the metrics (or a short summary without eval
    or when stopped early by `until`)."""
    from ghsplat_jax.train import train
    from ghsplat_jax.train.run_dir import load_training_data
    from ghsplat_jax.train.strategies import make_strategy

    if resume:  # a process killed mid-write leaves scratch folders beside the outputs
        from ghsplat_jax.io_utils import remove_scratch

        for p in remove_scratch(out_dir):
            log.info("removed %s, left by an interrupted write", p)
    revision = code_revision()  # the code this process trains with, read before training
    dataset = dataset if dataset is not None else load_training_data(config)
    test_eval = test_curve_metrics(dataset, config) if config.test_curve_every and dataset.test else None
    result = train(config, out_dir, dataset=dataset, resume=resume, until=until, test_eval=test_eval)
    summary = {"num_gaussians": result.num_surfels, "train_seconds": result.train_seconds, "steps": result.steps,
               "finished": result.finished}
    if result.stop is not None:
        summary["stop"] = stop_summary(result.stop, result.steps, config.resolved().steps, result.held_out)
    if not evaluate or not result.finished:
        return summary
    # Where and with what code it trained (the training seconds depend on both), from this process.
    extra = {k: summary[k] for k in ("stop",) if k in summary} | {"machine": machine_info(),
                                                                   "code_revision": revision}
    extra |= make_strategy(config).report(result.strategy_state)  # e.g. the auto strategy's compaction
    if result.exposure is not None:  # training views scored under their corrections, as training scored them
        extra["exposure_compensation"] = result.exposure["summary"]
    if result.pose is not None:  # the training views are evaluated at the poses the run refined them to
        from ghsplat_jax.train.pose import refine_views

        extra["pose_refinement"] = result.pose["summary"]
        dataset = dataclasses.replace(dataset, train=refine_views(dataset.train, result.pose["views"],
                                                                  result.pose["scene_extent"]))
    return _evaluate(result.surfels, dataset, config, out_dir, result.train_seconds, result.steps,
                     extra=extra, train_exposure=by_view(result.exposure)) | {"finished": True}


def stop_summary(rule: dict, steps: int, max_steps: int, held_out: list[str] | None = None) -> dict:
    """What metrics.json says of a run with validation: why and when it stopped, the step whose
    model it kept (`kept_from`: the first check that could be kept, where normal_settle sets one), and
    the views its checks held out (`held_out`; [] when they read the training
    views, as they do where too few train to spare some)."""
    stopped = rule.get("stopped_at") is not None
    return {"reason": rule["reason"] if stopped else f"the schedule ended at step {max_steps}",
            "stopped_at": int(rule["stopped_at"]) if stopped else int(steps), "best_step": int(rule["best_step"]),
            "best_val_psnr": rule["best_psnr"], "annealed_at": rule.get("annealed_at"),
            "kept_from": rule.get("kept_from"), "validation_views": held_out}


_evaluate = evaluate  # train_and_evaluate's `evaluate` flag shadows the function's name
