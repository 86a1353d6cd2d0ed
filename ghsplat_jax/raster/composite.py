"""Front-to-back compositing of binned surfels, tile by tile, with static shapes.

Transmittance is carried in log space, so a tile's list can be cut into fixed-size chunks
that are evaluated in parallel:
  pass 1: per chunk, the sum of log(1 - alpha) per pixel; a segmented scan over the chunks
          of each tile gives the log-transmittance at every chunk's start;
  pass 2: per chunk, weights w = alpha T and their sums against the features.
Every output is then a plain sum over surfels, sum_i w_i f_i, with features
f = [1, r, g, b, z, nx, ny, nz, m, m^2] (m the NDC depth of the distortion term), plus the
median depth, which picks one surfel per pixel. Colour and normal are constant per surfel, so
their sums are one matmul w^T [colour | normal]; only 1, z, m, m^2 vary per pixel.

Backward ("custom_vjp"): d/dalpha_i sum_j w_j f_j = T_i f_i - S_i / (1 - alpha_i), with
S_i = sum_{j>i} w_j f_j = total - inclusive prefix. Contracted with the output cotangent g
this needs one (B, P) plane per chunk: g.S_i = g.(total - prefix) - cumsum(w h), h = g.f,
where g.prefix at each chunk's start is a segmented scan of g.(chunk sums kept from the
forward pass). The backward is then one more parallel pass over the chunks that recomputes
alpha and differentiates only the per-chunk evaluation.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.raster.binning import tile_corner
from ghsplat_jax.raster.project import evaluate_pixels

# Columns of the per-tile sums: weight, colour, depth, normal, NDC depth and its square.
A, RGB, Z, NORMAL, M1, M2 = 0, slice(1, 4), 4, slice(5, 8), 8, 9
NUM_FEATURES = 10
T_MIN = 1e-4          # stop before a surfel would take transmittance below this
LOG_T_FLOOR = -60.0   # transmittance far below T_MIN: keeps sums finite in float32


@dataclasses.dataclass(frozen=True)
class Static:
    """Static settings of one compositing call (hashable)."""

    tiles_x: int
    tile_size: int
    num_tiles: int
    near: float
    far: float
    lowpass_filter: bool
    batch_chunks: int
    median: bool = True       # the median depth is wanted (the carried compositor skips it otherwise)
    distortion: bool = True   # the NDC depth sums of the distortion term are wanted (likewise)
    depth_normal: bool = True  # the depth and normal sums are wanted (likewise)
    samples: int = 0          # sample slots per tile (`samples.PixelSamples`); 0: every pixel of the tile
    backward_skip: str = "pairs"  # `RasterConfig.backward_skip` (the carried compositor's)

    @property
    def pixels(self) -> int:
        """Points evaluated per tile."""
        return self.samples or self.tile_size ** 2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ChunkParams:
    """Per-pair surfel parameters laid out as (chunks, chunk_size, ...)."""

    M: jax.Array
    center: jax.Array
    opacity: jax.Array
    color: jax.Array
    normal: jax.Array
    depth: jax.Array


def feature_columns(st: Static) -> list[int]:
    """The feature columns a render sums: weight and colour always; depth and normal, and the
    distortion moments, only where they are read (`Static.depth_normal`, `Static.distortion`)."""
    return ([A, *range(RGB.start, RGB.stop)] + ([Z, *range(NORMAL.start, NORMAL.stop)] if st.depth_normal else [])
            + ([M1, M2] if st.distortion else []))


def local_pixels(ts: int) -> tuple[np.ndarray, np.ndarray]:
    """(P,) x and y of a tile's pixel centres relative to its corner, row-major. NumPy, so they
    enter the program as literal arrays: built with jnp, XLA:CPU fuses the broadcast into every
    per-pixel fusion as index arithmetic, which stops it vectorising them (about 6x slower)."""
    local = np.arange(ts, dtype=np.float32) + 0.5
    return np.tile(local, ts), np.repeat(local, ts)


def tile_pixels(tile: jax.Array, st: Static) -> jax.Array:
    """(ts*ts, 2) pixel-centre coordinates of a tile, row-major."""
    xl, yl = local_pixels(st.tile_size)
    x0, y0 = tile_corner(tile, st.tiles_x, st.tile_size)
    return jnp.stack([x0[..., None] + xl, y0[..., None] + yl], axis=-1)


def evaluate_chunk(cp: ChunkParams, valid: jax.Array, tile: jax.Array, st: Static):
    """alpha (B,P) and hit depth (B,P) of one chunk on its tile's pixels (z = near where no hit)."""
    xy = tile_pixels(tile, st)[None]
    alpha, z = evaluate_pixels(cp.M[:, None], cp.center[:, None], cp.opacity[:, None],
                               cp.depth[:, None], xy, st.near, st.lowpass_filter)
    alpha = jnp.where(valid[:, None], alpha, 0.0)
    return alpha, jnp.where(alpha > 0, z, st.near)


def ndc_depth(z: jax.Array, st: Static) -> jax.Array:
    """The distortion term's depth mapping m(z) (the reference's near/far NDC)."""
    return st.far / (st.far - st.near) * (1.0 - st.near / z)


def pixel_sums(weight, z, color, normal, st: Static) -> jax.Array:
    """(P, F) sums of w f over a chunk: [A, rgb, z, normal, m, m^2]."""
    m = ndc_depth(z, st)
    const = jnp.matmul(weight.T, jnp.concatenate([color, normal], axis=1), precision=FLOAT32)  # (P, 6)
    per_pixel = lambda f: jnp.sum(weight * f, axis=0)[:, None]
    return jnp.concatenate([per_pixel(1.0), const[:, :3], per_pixel(z), const[:, 3:],
                            per_pixel(m), per_pixel(m * m)], axis=1)


def _blend(alpha: jax.Array, log_t0: jax.Array):
    """Transmittance before each surfel, inclusion mask and weights within one chunk."""
    log1m = jnp.log1p(-alpha)
    log_before = log_t0[None] + jnp.cumsum(log1m, axis=0) - log1m
    t_before = jnp.exp(log_before)
    included = (alpha > 0) & (jnp.exp(log_before + log1m) >= T_MIN)
    weight = jnp.where(included, alpha * t_before, 0.0)
    return t_before, included, weight


def last_median(included, t_before):
    """Per pixel, a one-hot over the chunk marking the last surfel with T > 0.5, and whether any."""
    flag = included & (t_before > 0.5)
    later = jnp.cumsum(flag[::-1].astype(jnp.int32), axis=0)[::-1] - flag
    return flag & (later == 0), jnp.any(flag, axis=0)


def segmented_exclusive_cumsum(values: jax.Array, first: jax.Array) -> jax.Array:
    """Exclusive cumulative sum along axis 0 that restarts where `first` is set."""
    def combine(a, b):
        fa, va = a
        fb, vb = b
        fb_ = fb.reshape(fb.shape + (1,) * (vb.ndim - fb.ndim))
        return fa | fb, jnp.where(fb_, vb, va + vb)

    _, inclusive = jax.lax.associative_scan(combine, (first, values))
    previous = jnp.concatenate([jnp.zeros_like(inclusive[:1]), inclusive[:-1]])
    return jnp.where(first.reshape(first.shape + (1,) * (values.ndim - 1)), 0.0, previous)


def _map(fn, xs, st: Static, remat: bool, num_used: jax.Array):
    """fn over chunks, `batch_chunks` at a time, skipping batches past the used chunks.

    Used chunks come first, so a capacity with headroom costs memory but not compute: a batch
    beyond `num_used` returns zeros (what empty chunks produce) without evaluating anything.
    Under an outer vmap the cond becomes a select and nothing is skipped, but all stays exact.
    """
    fn = jax.checkpoint(fn) if remat else fn
    batch = st.batch_chunks
    num_batches = jax.tree_util.tree_leaves(xs)[0].shape[0] // batch
    xs = jax.tree_util.tree_map(lambda a: a.reshape((num_batches, batch) + a.shape[1:]), xs)
    run = jax.vmap(lambda x: fn(*x))
    out_shape = jax.eval_shape(run, jax.tree_util.tree_map(lambda a: a[0], xs))
    skip = lambda _: jax.tree_util.tree_map(lambda o: jnp.zeros(o.shape, o.dtype), out_shape)

    def body(carry, item):
        i, x = item
        return carry, jax.lax.cond(i * batch < num_used, run, skip, x)

    _, ys = jax.lax.scan(body, None, (jnp.arange(num_batches), xs))
    return jax.tree_util.tree_map(lambda a: a.reshape((num_batches * batch,) + a.shape[2:]), ys)


def _forward(st: Static, cp: ChunkParams, valid, tile, first, remat: bool):
    def pass1(cp_w, valid_w, tile_w):
        alpha, _ = evaluate_chunk(cp_w, valid_w, tile_w, st)
        return jnp.sum(jnp.log1p(-alpha), axis=0)

    num_used = jnp.sum(valid[:, 0])
    log_sum = _map(pass1, (cp, valid, tile), st, remat, num_used)
    log_t0 = jnp.maximum(segmented_exclusive_cumsum(log_sum, first), LOG_T_FLOOR)

    def pass2(cp_w, valid_w, tile_w, log_t0_w):
        alpha, z = evaluate_chunk(cp_w, valid_w, tile_w, st)
        t_before, included, weight = _blend(alpha, log_t0_w)
        last, has = last_median(included, t_before)
        sums = pixel_sums(weight, z, cp_w.color, cp_w.normal, st)
        return sums, jnp.sum(jnp.where(last, z, 0.0), axis=0), has

    sums, z_last, has = _map(pass2, (cp, valid, tile, log_t0), st, remat, num_used)
    totals = jnp.zeros((st.num_tiles,) + sums.shape[1:]).at[tile].add(sums, mode="drop")
    chunk_id = jnp.arange(tile.shape[0], dtype=jnp.int32)[:, None]
    selected = jnp.full((st.num_tiles, sums.shape[1]), -1, jnp.int32).at[tile].max(
        jnp.where(has, chunk_id, -1), mode="drop")
    pixel = jnp.arange(sums.shape[1])[None]
    median = jnp.where(selected >= 0, z_last[jnp.maximum(selected, 0), pixel], 0.0)
    return (totals, median), (log_t0, sums, totals, selected)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def composite_custom(st: Static, cp: ChunkParams, valid, tile, first):
    return _forward(st, cp, valid, tile, first, remat=False)[0]


def _custom_fwd(st, cp, valid, tile, first):
    outputs, (log_t0, sums, totals, selected) = _forward(st, cp, valid, tile, first, remat=False)
    return outputs, (cp, valid, tile, first, log_t0, sums, totals, selected)


def _custom_bwd(st, residuals, cotangents):
    cp, valid, tile, first, log_t0, sums, totals, selected = residuals
    g_totals, g_median = cotangents
    pad = lambda a, fill: jnp.concatenate([a, jnp.full((1,) + a.shape[1:], fill, a.dtype)])
    g_totals, g_median = pad(g_totals, 0.0), pad(g_median, 0.0)
    totals, selected = pad(totals, 0.0), pad(selected, -1)
    # Only g . (total - prefix) is needed per chunk and pixel, so the segmented scan runs on
    # one plane instead of all features.
    g_chunk = g_totals[tile]                                               # (W, P, F)
    after_start = (jnp.sum(g_chunk * totals[tile], axis=-1)
                   - segmented_exclusive_cumsum(jnp.sum(g_chunk * sums, axis=-1), first))

    def chunk_grad(cp_w, valid_w, tile_w, log_t0_w, after_start_w, w):
        geometry = lambda M, center, opacity, depth: evaluate_chunk(
            dataclasses.replace(cp_w, M=M, center=center, opacity=opacity, depth=depth), valid_w, tile_w, st)
        (alpha, z), pullback = jax.vjp(geometry, cp_w.M, cp_w.center, cp_w.opacity, cp_w.depth)
        t_before, included, weight = _blend(alpha, log_t0_w)
        g = g_totals[tile_w]                                              # (P, F)
        g_a, g_rgb, g_z, g_n, g_m, g_m2 = g[:, 0], g[:, 1:4], g[:, 4], g[:, 5:8], g[:, 8], g[:, 9]
        m = ndc_depth(z, st)
        # h = g . f for every (surfel, pixel): the output change per unit weight.
        h = (g_a + g_z * z + g_m * m + g_m2 * m * m
             + jnp.matmul(cp_w.color, g_rgb.T, precision=FLOAT32)
             + jnp.matmul(cp_w.normal, g_n.T, precision=FLOAT32))
        after = after_start_w - jnp.cumsum(weight * h, axis=0)
        d_alpha = jnp.where(included, t_before * h - after / (1.0 - alpha), 0.0)
        dm_dz = st.far / (st.far - st.near) * st.near / (z * z)
        d_z = weight * (g_z + (g_m + 2.0 * g_m2 * m) * dm_dz)
        last, _ = last_median(included, t_before)
        d_z += jnp.where(last & (selected[tile_w] == w)[None], g_median[tile_w][None], 0.0)
        d_M, d_center, d_opacity, d_depth = pullback((d_alpha, d_z))
        return ChunkParams(M=d_M, center=d_center, opacity=d_opacity,
                           color=jnp.matmul(weight, g_rgb, precision=FLOAT32),
                           normal=jnp.matmul(weight, g_n, precision=FLOAT32), depth=d_depth)

    chunk_id = jnp.arange(tile.shape[0], dtype=jnp.int32)
    d_cp = _map(chunk_grad, (cp, valid, tile, log_t0, after_start, chunk_id), st, remat=False,
                num_used=jnp.sum(valid[:, 0]))
    return d_cp, None, None, None


composite_custom.defvjp(_custom_fwd, _custom_bwd)


def composite(st: Static, cp: ChunkParams, valid, tile, first, backward: str):
    """Per-tile feature sums (T, P, F) and median depth (T, P)."""
    if backward == "custom_vjp":
        return composite_custom(st, cp, valid, tile, first)
    return _forward(st, cp, valid, tile, first, remat=True)[0]
