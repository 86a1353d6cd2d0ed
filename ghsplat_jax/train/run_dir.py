"""A training run's folder: its layout, loading a run, and writing its metrics.

    RUN/config.toml         the resolved TrainConfig (`ghsplat train --config` reproduces it)
    RUN/stats.jsonl         one JSON line per training step
    RUN/checkpoint.npz      the training state, resumable (train/checkpoint.py)
    RUN/point_cloud.ply     the final surfels (present once the run has finished training)
    RUN/pose_corrections.json  per training view, the pose correction learnt (runs with pose_refine)
    RUN/metrics.json        evaluation summary: per split psnr/l1/ssim, num_gaussians, ...
    RUN/per_view.json       evaluation of every view
    RUN/renders/test/       rgb, depth and normal images of the test views
    RUN/snapshots/step_N/   the same evaluation files for an unfinished run's checkpoint

The trainer writes the first four (five with pose refinement); evaluation (eval/) reads a run through `load_run` and
writes the rest through `write_metrics`, so neither needs the other.
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path

import numpy as np

CONFIG_NAME = "config.toml"
STATS_NAME = "stats.jsonl"
TEST_CURVE_NAME = "test_curve.jsonl"
CHECKPOINT_NAME = "checkpoint.npz"
PLY_NAME = "point_cloud.ply"
POSE_NAME = "pose_corrections.json"
EXPOSURE_NAME = "exposure_corrections.json"
METRICS_NAME = "metrics.json"
PER_VIEW_NAME = "per_view.json"
TEST_RENDERS = Path("renders") / "test"


def snapshot_dir(run_dir, step: int) -> Path:
    """Where the evaluation of an unfinished run's checkpoint at `step` goes."""
    return Path(run_dir) / "snapshots" / f"step_{int(step):06d}"


def is_evaluated(run_dir) -> bool:
    """A finished run has been evaluated: its metrics.json exists."""
    return (Path(run_dir) / METRICS_NAME).is_file()


def has_checkpoint(run_dir) -> bool:
    return (Path(run_dir) / CHECKPOINT_NAME).is_file()


def read_metrics(run_dir) -> dict | None:
    """RUN/metrics.json, or None when the run has not been evaluated."""
    path = Path(run_dir) / METRICS_NAME
    return json.loads(path.read_text()) if path.is_file() else None


def kept_step(metrics: dict) -> int | None:
    """The step of the model a run's metrics describe: a self-stopped run's best validation
    check, else its last step."""
    return (metrics.get("stop") or {}).get("best_step", metrics.get("steps"))


def normal_loss_steps(run_dir, kept: int | None) -> int | None:
    """How many steps of the normal-consistency loss the model kept at step `kept` trained with:
    from the config's `normal_from` on. A run that stops itself before `normal_from` has none, and
    its normals are those of a model without the prior (34 against 20 degrees of mean error on
    row2_x1: train/recipes.py), so geometry errors compare only between runs alike in this. None
    where RUN/config.toml does not say."""
    path = Path(run_dir) / CONFIG_NAME
    config = tomllib.loads(path.read_text()) if path.is_file() else {}
    if kept is None or "normal_from" not in config or "lambda_normal" not in config:
        return None
    return max(0, int(kept) - int(config["normal_from"])) if config["lambda_normal"] > 0 else 0


def median_step_seconds(run_dir, last_fraction: float = 1.0) -> float | None:
    """Median wall time of one training step from the run's stats.jsonl, over the last
    `last_fraction` of the logged steps: the step cost without the compiles that dominate the
    total of short runs (None without stats). A resume restarts the clock at the checkpoint's
    time, so intervals that go backwards are left out."""
    path = Path(run_dir) / STATS_NAME
    if not path.is_file():
        return None
    logged = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
            logged.append((int(record["step"]), float(record["elapsed_s"])))
        except (ValueError, KeyError, TypeError):
            continue
    logged = logged[int(len(logged) * (1.0 - last_fraction)):]
    per_step = [(t1 - t0) / (s1 - s0) for (s0, t0), (s1, t1) in zip(logged, logged[1:]) if s1 > s0 and t1 > t0]
    return float(np.median(per_step)) if per_step else None


def write_metrics(out_dir, metrics: dict, per_view: list[dict]) -> Path:
    """metrics.json and per_view.json (atomically, NaN refused); returns metrics.json's path."""
    from ghsplat_jax.io_utils import write_json

    write_json(Path(out_dir) / PER_VIEW_NAME, per_view)
    return write_json(Path(out_dir) / METRICS_NAME, metrics)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (checkpoints and metrics record it)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------- loading

def resolve_data_path(data: str | os.PathLike) -> Path:
    """An existing path as given, else the same name under the shared datasets root."""
    from ghsplat_jax.paths import datasets_root

    p = Path(data).expanduser()
    if p.exists() or p.is_absolute():
        return p
    return datasets_root() / data


def load_training_data(config):
    """The dataset a TrainConfig names, read with its downscale, background and split."""
    from ghsplat_jax.data import load_dataset

    if not config.data:
        raise ValueError("no dataset given: set --data (or `data` in the config)")
    dataset = load_dataset(resolve_data_path(config.data), downscale=config.downscale,
                           background=config.raster.background, split="auto", test_every=config.test_every,
                           max_views=config.max_views or None)
    if config.pose_noise:
        from ghsplat_jax.data.perturb import perturb_poses

        dataset = perturb_poses(dataset, config.pose_noise, config.seed)
    return dataset


def load_run_checkpoint(path, optimizers: dict):
    """(TrainState, metadata) of a run's checkpoint (the pool size, and the numbers of views with
    pose and exposure corrections, from the file)."""
    from ghsplat_jax.train import checkpoint as ckpt
    from ghsplat_jax.train.exposure import init_exposure
    from ghsplat_jax.train.pose import init_pose
    from ghsplat_jax.train.state import empty_params, new_state

    meta = ckpt.read_meta(path)
    pose = init_pose(meta["pose_views"], 1.0) if meta.get("pose_views") else None
    exposure = init_exposure(meta["exposure_views"]) if meta.get("exposure_views") else None
    template = new_state(empty_params(meta["capacity"], meta["sh_degree"]), np.zeros(meta["capacity"], bool),
                         optimizers, pose, exposure)
    return ckpt.load_checkpoint(path, template)


def raster_settings(ply_or_config):
    """The RasterConfig of the run a PLY belongs to (its folder's config.toml) or of a config.toml
    given directly; None when there is no run config."""
    from ghsplat_jax.train.config import load_config

    path = Path(ply_or_config)
    config = path if path.suffix == ".toml" else path.parent / CONFIG_NAME
    return load_config(config).raster if config.is_file() else None


def load_run(run_dir):
    """(config, surfels, checkpoint metadata or {}, finished) of a training run folder: the
    surfels of point_cloud.ply, or of the checkpoint while the run is unfinished."""
    from ghsplat_jax.data.ply import load_ply
    from ghsplat_jax.train import checkpoint as ckpt
    from ghsplat_jax.train import optim
    from ghsplat_jax.train.config import load_config

    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG_NAME
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{run_dir}: not a training run (no {CONFIG_NAME})")
    config = load_config(cfg_path)
    ply = run_dir / PLY_NAME
    checkpoint = run_dir / CHECKPOINT_NAME
    meta = ckpt.read_meta(checkpoint) if checkpoint.is_file() else {}
    if ply.is_file():
        return config, load_ply(ply), meta, True
    if not meta:
        raise FileNotFoundError(f"{ply}: missing and no {CHECKPOINT_NAME} to evaluate; the run has not started")
    state, _ = load_run_checkpoint(checkpoint, optim.make_optimizers(config))
    return config, state.active_surfels(), meta, False
