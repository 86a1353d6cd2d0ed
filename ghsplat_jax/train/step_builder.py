"""The training step a run uses: one jitted program (`step.train_step`), or on a CPU the
parted step whose compositor runs in threads (`parted_step`)."""

from __future__ import annotations

import os

import jax

from ghsplat_jax.train import optim
from ghsplat_jax.train.parted_step import make_parted_step
from ghsplat_jax.train.step import TRACE_COUNTS, ExposureRates, LossWeights, PoseRates, train_step


def step_threads(config) -> int:
    """How many threads walk the compositor in a training step (`TrainConfig.step_threads`)."""
    if config.step_threads:
        return config.step_threads
    if config.pose_refine:  # the parted step does not carry the camera's gradient
        return 1
    r = config.raster
    parted = r.backend == "tiled" and r.compositor == "carried" and jax.default_backend() == "cpu"
    return min(2, os.cpu_count() or 1) if parted else 1


def make_train_step(config, render_fn=None):
    """(optimizers, step(state, image, K, w2c, means_lr, raster_cfg, width, height)) built from
    `config` itself: every setting the step reads is baked into it, so no other run can reuse it
    by mistake. It is one jitted program, or with `step_threads(config)` > 1 (and the package's
    renderer) `parted_step`'s programs, whose compositor runs in that many threads (a Python
    function that calls jitted programs: not itself traceable by jit or make_jaxpr). It compiles
    once per pool capacity, image size and raster_cfg (static). Runs with identical settings
    still share the XLA binary through JAX's persistent compilation cache, which keys on the
    program. The state is not donated: a step that overflows its pair buffer or goes non-finite
    is redone or rolled back from it. With `config.pose_refine` or `config.exposure_compensation`
    the step also takes `view`, the training view's index into the state's per-view corrections;
    with `pose_refine` it is always the one program."""
    optimizers = optim.make_optimizers(config)
    weights = LossWeights.from_config(config)
    pose_rates = PoseRates.from_config(config)
    exposure_rates = ExposureRates.from_config(config)
    threads = step_threads(config)
    if render_fn is None and threads > 1:
        return optimizers, make_parted_step(optimizers, weights, threads, exposure_rates)
    if render_fn is None:
        from ghsplat_jax.raster.render import render as render_fn

    def step(state, image, K, world_to_cam, means_lr, raster_cfg, width, height, view=None):
        TRACE_COUNTS["train_step"] += 1
        return train_step(state, image, K, world_to_cam, means_lr, width=width, height=height,
                          optimizers=optimizers, weights=weights, raster_cfg=raster_cfg, render_fn=render_fn,
                          view=view, pose_rates=pose_rates, exposure_rates=exposure_rates)

    return optimizers, jax.jit(step, static_argnames=("raster_cfg", "width", "height"))
