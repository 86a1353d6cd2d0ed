"""The naive pure-JAX baseline: one dense (tiles, K, pixels) block per render.

Every tile holds K surfel slots (K >= the fullest tile), all alphas are evaluated at once,
transmittance is an exclusive cumulative product and gradients are plain autodiff. Kept as a
selectable backend ("dense") so benchmarks and ablations compare against it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ghsplat_jax.raster.composite import T_MIN, ChunkParams, Static, evaluate_chunk, last_median, pixel_sums


def composite_dense(st: Static, pair_params: ChunkParams, pair_valid, tile_slots: int,
                    tile_start, tile_count):
    """pair_params: (C, ...) per sorted pair; returns (T,P,F) sums and (T,P) median."""
    capacity = pair_params.depth.shape[0]
    slot = tile_start[:, None] + jnp.arange(tile_slots)[None]          # (T, K)
    valid = (jnp.arange(tile_slots)[None] < tile_count[:, None]) & pair_valid[jnp.clip(slot, 0, capacity - 1)]
    params = jax.tree_util.tree_map(lambda a: a[jnp.clip(slot, 0, capacity - 1)], pair_params)
    tiles = jnp.arange(st.num_tiles)
    alpha, z = jax.vmap(lambda c, v, t: evaluate_chunk(c, v, t, st))(params, valid, tiles)
    one_minus = 1.0 - alpha
    t_before = jnp.cumprod(one_minus, axis=1) / one_minus            # exclusive cumprod
    included = (alpha > 0) & (t_before * one_minus >= T_MIN)
    weight = jnp.where(included, alpha * t_before, 0.0)
    sums = jax.vmap(lambda w, z, c, n: pixel_sums(w, z, c, n, st))(weight, z, params.color, params.normal)
    last, _ = jax.vmap(last_median)(included, t_before)
    median = jnp.sum(jnp.where(last, z, 0.0), axis=1)
    return sums, median
