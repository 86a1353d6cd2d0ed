"""Evaluate trained surfels on a dataset's views: metrics per view and split, render time,
renders with depth and normal maps, and the run's metrics.json."""

from __future__ import annotations

import dataclasses

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from ghsplat_jax.eval.metrics import image_metrics, summarize
from ghsplat_jax.io_utils import write_json

log = logging.getLogger("ghsplat.eval")

METRICS_NAME = "metrics.json"
PER_VIEW_NAME = "per_view.json"


def _even_subset(views, k: int):
    if not k or len(views) <= k:
        return list(views)
    idx = np.unique(np.linspace(0, len(views) - 1, k).round().astype(int))
    return [views[i] for i in idx]


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
             train_peak_rss_mb: float | None = None) -> dict:
    """Render every test view and (up to config.eval_max_train_views) training view; write
    OUT/metrics.json and OUT/per_view.json (and renders under OUT/renders/test/); return metrics.
    peak_rss_mb is this process's peak, or the training process's when that was larger."""
    import jax
    from tqdm.auto import tqdm

    import ghsplat_jax as gs
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_renders = config.save_test_renders if save_renders is None else save_renders
    progress = config.progress if progress is None else progress
    rcfg = dataclasses.replace(config.raster, pair_capacity=None)  # eager renders: exact pair counts, nothing dropped
    surfels = jax.tree_util.tree_map(jax.numpy.asarray, surfels)
    splits = {"train": _even_subset(dataset.train, config.eval_max_train_views), "test": list(dataset.test)}
    rows, times = [], []
    warm = False
    for split, views in splits.items():
        for v in tqdm(views, desc=f"eval {split}", disable=not progress, leave=False):
            if not warm:  # compile outside the timing
                jax.block_until_ready(gs.render(surfels, v.camera, rcfg).rgb)
                warm = True
            t = time.perf_counter()
            out = gs.render(surfels, v.camera, rcfg)
            jax.block_until_ready(out.rgb)
            dt = time.perf_counter() - t
            times.append(dt)
            m = image_metrics(out.rgb, v.image)
            if not all(math.isfinite(x) for x in m.values()):
                raise FloatingPointError(f"view {v.name}: non-finite metrics {m}")
            rows.append(dict(split=split, name=v.name, render_seconds=dt, **m))
            if save_renders and split == "test":
                save_view_maps(out_dir / "renders" / "test", v.name, out)
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
        "peak_rss_mb": max(peak_rss_mb(), train_peak_rss_mb or 0.0),
        "strategy": config.strategy,
    }
    write_json(out_dir / PER_VIEW_NAME, rows)
    write_json(out_dir / METRICS_NAME, metrics)
    return metrics


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (training and evaluation), in MiB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def snapshot_dir(run_dir, step: int) -> Path:
    """Where the evaluation of an unfinished run's checkpoint at `step` goes."""
    return Path(run_dir) / "snapshots" / f"step_{int(step):06d}"


def load_run(run_dir):
    """(config, surfels, checkpoint metadata or {}, finished) of a training run folder: the
    surfels of point_cloud.ply, or of the checkpoint while the run is unfinished."""
    from ghsplat_jax.scene.ply import load_ply
    from ghsplat_jax.train import checkpoint as ckpt
    from ghsplat_jax.train import optim
    from ghsplat_jax.train.config import load_config
    from ghsplat_jax.train.trainer import CONFIG_NAME, PLY_NAME, load_run_checkpoint

    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG_NAME
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{run_dir}: not a training run (no {CONFIG_NAME})")
    config = load_config(cfg_path)
    ply = run_dir / PLY_NAME
    checkpoint = run_dir / ckpt.CHECKPOINT_NAME
    meta = ckpt.read_meta(checkpoint) if checkpoint.is_file() else {}
    if ply.is_file():
        return config, load_ply(ply), meta, True
    if not meta:
        raise FileNotFoundError(f"{ply}: missing and no {ckpt.CHECKPOINT_NAME} to evaluate; the run has not started")
    state, _ = load_run_checkpoint(checkpoint, optim.make_optimizers(config))
    return config, state.active_surfels(), meta, False


def evaluate_run(run_dir, progress: bool = True) -> dict:
    """Re-evaluate a run folder from its config and point_cloud.ply. An unfinished run (a
    checkpoint but no point_cloud.ply, e.g. stopped with --until) is evaluated at its
    checkpoint into RUN_DIR/snapshots/step_NNNNNN/ so the run's own metrics.json stays absent."""
    from ghsplat_jax.train.trainer import load_training_data

    run_dir = Path(run_dir)
    config, surfels, meta, finished = load_run(run_dir)
    seconds, steps = meta.get("train_seconds"), meta.get("step")
    out_dir = run_dir
    if not finished:
        out_dir = snapshot_dir(run_dir, steps)
        log.info("%s: unfinished; evaluating the checkpoint at step %d into %s", run_dir, steps, out_dir)
    if not meta and (run_dir / METRICS_NAME).is_file():
        old = json.loads((run_dir / METRICS_NAME).read_text())
        seconds, steps = old.get("train_seconds"), old.get("steps")
    dataset = load_training_data(config)
    return evaluate(surfels, dataset, config, out_dir, seconds, steps, progress=progress,
                    train_peak_rss_mb=meta.get("peak_rss_mb"))
