"""The training step cut into programs, so that the compositor's loops use two cores.

XLA:CPU runs one while loop at a time on one thread, even two independent loops in one
program, and the compositor's loops take most of a CPU step; two jitted calls made from two
threads do run side by side (`benchmarks/profiling/loop_threads.py`). So this step runs as:
  1. `front`: the step's surfels, projected and binned, and the vjp of the per-surfel table;
  2. the compositor's forward walk, one call per part of the used chunks (`carried.split_chunks`:
     whole tiles, about equal shares), each part from its own thread, in batches of
     `RasterConfig.part_batch_chunks` chunks;
  3. `middle`: the parts joined, the outputs, the loss and its cotangents for the compositor's
     outputs, and what the backward walk reads;
  4. the backward walk per part of the marked chunks, likewise;
  5. `finish`: the table's gradient pulled back to the parameters, Adam, densification statistics.
The math is `step.train_step`'s (tested against it); only the parts' table gradients add up in
another order. The trainer uses it for the carried compositor on a CPU with two or more cores
(`TrainConfig.step_threads`).
"""

from __future__ import annotations

import dataclasses
import functools
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp

from ghsplat_jax.core.camera import Camera
from ghsplat_jax.raster import carried
from ghsplat_jax.raster.render import (
    bin_projected,
    chunk_surfels,
    compositor_static,
    default_capacity,
    project_surfels,
    render_outputs,
)
from ghsplat_jax.train.step import (
    TRACE_COUNTS,
    apply_gradients,
    image_loss,
    regularisers,
    step_surfels,
    update_view_corrections,
    view_corrections,
)


# One program serves every part: the part's index is an argument, not a constant.
@functools.partial(jax.jit, static_argnums=0)
def _forward_part(st, j, bounds, *args):
    return carried.forward_part(st, *args, bounds[j], bounds[j + 1])


@functools.partial(jax.jit, static_argnums=0)
def _backward_part(st, j, bounds, inputs):
    return carried.backward_part(st, inputs, bounds[j], bounds[j + 1])


def make_parted_step(optimizers, weights, parts: int, exposure_rates=None):
    """A step with `step_builder.make_train_step`'s signature whose compositor runs in `parts` threads.
    It learns exposure corrections (a state with `exposure`), not pose ones: the camera's gradient
    is not carried through the parts."""
    pool = ThreadPoolExecutor(parts, thread_name_prefix="compositor")

    def in_parts(fn, *args):
        """fn(j, *args) for every part, each called (and waited for) in its own thread."""
        return list(pool.map(lambda j: jax.block_until_ready(fn(jnp.int32(j), *args)), range(parts)))

    @functools.partial(jax.jit, static_argnames=("raster_cfg", "width", "height"))
    def front(state, K, world_to_cam, raster_cfg, width, height):
        TRACE_COUNTS["train_step"] += 1
        camera = Camera(K, world_to_cam, width, height)

        def table_of(params, probe):
            p = project_surfels(step_surfels(params, state.active, camera, state.step, weights), camera, raster_cfg,
                                probe)
            return carried.pair_table(p), p

        probe = jnp.zeros((state.capacity, 2), jnp.float32)
        table, pull_back, p = jax.vjp(table_of, state.params, probe, has_aux=True)
        _, _, layout = bin_projected(p, camera, raster_cfg, raster_cfg.pair_capacity)
        surfel, valid = chunk_surfels(layout, raster_cfg, raster_cfg.pair_capacity)
        bounds = carried.split_chunks(layout.chunk_first, carried.used_chunks(valid), parts)
        return table, pull_back, p, layout, surfel, valid, bounds

    @functools.partial(jax.jit, static_argnames=("raster_cfg", "width", "height"))
    def middle(forward_parts, state, table, p, layout, surfel, valid, image, K, world_to_cam, raster_cfg, width,
               height, view):
        camera = Camera(K, world_to_cam, width, height)
        grid, st = compositor_static(raster_cfg, width, height)
        outputs, (totals, selected, live) = carried.join_forward(st, forward_parts, surfel.shape[1])

        def loss_of(totals, median, tone):
            out = render_outputs(totals, median, raster_cfg, grid, camera, p, layout, raster_cfg.pair_capacity, None)
            return image_loss(out, image, camera, state.step, weights, raster_cfg, tone)

        _, tone = view_corrections(state, view)
        loss, pull_back, aux = jax.vjp(loss_of, *outputs, tone, has_aux=True)
        *cotangents, tone_grad = pull_back(jnp.ones_like(loss))
        residuals = (table, surfel, valid, layout.chunk_tile, None, totals, selected, live)
        inputs, num_live = carried.backward_inputs(st, residuals, cotangents)
        return inputs, carried.split_chunks(inputs.first, num_live, parts), loss, aux, tone_grad

    @functools.partial(jax.jit, static_argnames=("width", "height"))
    def finish(state, pull_back, table_grads, loss, aux, means_lr, width, height, view, tone_grad):
        grads, probe_grad = pull_back(sum(table_grads[1:], table_grads[0]))
        if weights.opacity_reg > 0 or weights.scale_reg > 0:
            reg, reg_grads = jax.value_and_grad(regularisers)(state.params, state.active, weights)
            loss = loss + reg
            grads = jax.tree_util.tree_map(jnp.add, grads, reg_grads)
        new, metrics = apply_gradients(state, loss, aux, grads, probe_grad, means_lr, optimizers, width, height)
        return update_view_corrections(new, metrics, view, state.step, None, tone_grad, None, exposure_rates)

    def step(state, image, K, world_to_cam, means_lr, raster_cfg, width, height, view=None):
        raster_cfg = dataclasses.replace(raster_cfg, batch_chunks=raster_cfg.part_batch_chunks)
        if raster_cfg.pair_capacity is None:  # as `render` sizes a traced render's buffer
            camera = Camera(K, world_to_cam, width, height)
            raster_cfg = dataclasses.replace(raster_cfg, pair_capacity=default_capacity(state.capacity, camera,
                                                                                        raster_cfg))
        _, st = compositor_static(raster_cfg, width, height)
        table, pull_back, p, layout, surfel, valid, bounds = front(state, K, world_to_cam, raster_cfg, width, height)
        forward_parts = in_parts(lambda j: _forward_part(st, j, bounds, table, surfel, valid, layout.chunk_tile,
                                                         layout.chunk_first, None))
        inputs, bounds, loss, aux, tone_grad = middle(forward_parts, state, table, p, layout, surfel, valid, image, K,
                                                      world_to_cam, raster_cfg, width, height, view)
        table_grads = in_parts(lambda j: _backward_part(st, j, bounds, inputs))
        return finish(state, pull_back, table_grads, loss, aux, means_lr, width, height, view, tone_grad)

    return step
