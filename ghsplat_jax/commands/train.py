"""`ghsplat train`: train 2DGS surfels on a dataset folder, then evaluate the run (a command
of its own, above train/ and eval/, because it uses both)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

HELP = "train 2D Gaussian surfels on a dataset (2DGS defaults; --recipe auto sizes the model and stops by itself)"
RECIPE_HELP = ("'auto': the model sizes itself and the run stops when held-out views stop improving, with images at "
               "reduced resolution early: use it for a new scene or to get a good model fast. Without --recipe: the "
               "2DGS defaults for a fixed 30k steps, the paper's Table 1 protocol: use it to reproduce published "
               "numbers")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="dataset folder (COLMAP, transforms.json or LLFF; a bare name is looked up "
                                  "under the shared datasets root)")
    p.add_argument("--out", required=True, help="run folder (config, stats, checkpoints, point_cloud.ply, metrics)")
    p.add_argument("--recipe", metavar="NAME", help=RECIPE_HELP)
    p.add_argument("--config", help="TOML (or JSON) file of TrainConfig overrides")
    p.add_argument("--steps", type=int, help="optimisation steps (default 30000)")
    p.add_argument("--downscale", type=float, help="image downscale factor")
    p.add_argument("--strategy", help="densification strategy: default, budget, mcmc or auto (train/strategies/); "
                                      "an unknown name is a config error that lists them")
    p.add_argument("--max-surfels", type=int, help="cap on the surfel count for --strategy budget or mcmc")
    p.add_argument("--seed", type=int)
    p.add_argument("--white", action="store_true", help="composite and render on a white background")
    p.add_argument("--pose-refine", action="store_true",
                   help="learn a pose correction per training view (pose_refine; rates: --set pose_lr_rot=..., "
                        "pose_lr_trans=..., pose_refine_from=...); writes OUT/pose_corrections.json")
    p.add_argument("--exposure-compensation", action="store_true",
                   help="learn a colour gain and offset per training view, for photos exposed unlike the rest "
                        "(exposure_compensation; the model keeps the exposure they share); writes "
                        "OUT/exposure_corrections.json")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any TrainConfig field, e.g. --set lambda_dist=100 (TOML value syntax)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz with OUT/config.toml")
    p.add_argument("--until", type=int, help="stop after this step with a checkpoint (continue with --resume)")
    p.add_argument("--no-eval", action="store_true", help="skip the evaluation after training")
    p.add_argument("--no-triangulate", action="store_true",
                   help="a dataset with cameras but fewer SfM points than init_min_points starts from random points "
                        "(by default its points are first triangulated from the known cameras into "
                        "OUT/triangulated.ply, with pycolmap)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def resolve_config(args):
    from ghsplat_jax.train.config import ConfigError, TrainConfig, apply_overrides, load_config, settings_missing_from
    from ghsplat_jax.train.run_dir import CONFIG_NAME

    out = Path(args.out)
    config, missing = TrainConfig(), []
    if args.recipe:  # under the config file and the other options
        config = apply_overrides(config, {"recipe": args.recipe}, "--recipe")
    if args.resume and (out / CONFIG_NAME).is_file():
        config = load_config(out / CONFIG_NAME)
        missing = settings_missing_from(out / CONFIG_NAME)
    if args.config:
        config = load_config(args.config, config)
    overrides = {}
    for item in args.set:
        import tomllib

        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        try:
            overrides[key.strip()] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            overrides[key.strip()] = value  # a bare string
    for key in ("data", "steps", "downscale", "strategy", "seed"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    if args.max_surfels is not None:
        overrides["strategy.max_surfels"] = args.max_surfels
    if args.white:
        overrides["background"] = (1.0, 1.0, 1.0)
    if args.pose_refine:
        overrides["pose_refine"] = True
    if args.exposure_compensation:
        overrides["exposure_compensation"] = True
    if args.no_progress:
        overrides["progress"] = False
    missing = [name for name in missing if name not in overrides]
    if missing:
        logging.getLogger("ghsplat.train").warning(
            "%s predates the settings %s: the resumed run takes their defaults (--set NAME=VALUE keeps an "
            "earlier behaviour)", out / CONFIG_NAME, ", ".join(missing))
    return apply_overrides(config, overrides, "command line")


def dataset_with_points(config, out):
    """The run's dataset, with points triangulated from its cameras when it has too few SfM
    points (sfm/triangulate.py; the points go to OUT/triangulated.ply)."""
    from ghsplat_jax.sfm.triangulate import with_triangulated_points
    from ghsplat_jax.train.run_dir import load_training_data

    return with_triangulated_points(load_training_data(config), config.init_min_points, out)


def main(args) -> int:
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.train import ConfigError, TrainingDivergedError

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        config = resolve_config(args)
        from ghsplat_jax.train.run_dir import has_checkpoint

        resuming = args.resume and has_checkpoint(args.out)  # the checkpoint holds the surfels
        dataset = None if resuming or args.no_triangulate else dataset_with_points(config, args.out)
        metrics = train_and_evaluate(config, args.out, resume=args.resume, evaluate=not args.no_eval,
                                     until=args.until, dataset=dataset)
    except (ConfigError, TrainingDivergedError, FileNotFoundError) as exc:
        print(f"ghsplat train: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # DatasetError and bad inputs are ValueErrors with a clear message
        print(f"ghsplat train: {exc}", file=sys.stderr)
        return 2
    if not metrics["finished"]:
        print(f"{args.out}: paused at step {metrics['steps']} of {config.steps}; continue with --resume")
        return 0
    stop = metrics.get("stop")
    if stop:
        print(f"{args.out}: stopped at step {stop['stopped_at']}: {stop['reason']}; kept the model of step "
              f"{stop['best_step']} (validation PSNR {stop['best_val_psnr']:.2f} dB)")
    test = metrics.get("test") or {}
    psnr = test.get("psnr")
    print(f"{args.out}: {metrics['num_gaussians']} surfels, {metrics['steps']} steps, "
          f"{metrics['train_seconds']:.1f} s" + (f", test PSNR {psnr:.2f} dB" if psnr is not None else ""))
    return 0
