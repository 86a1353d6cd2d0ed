"""The carried compositor: each tile-surfel pair is evaluated once, transmittance is carried.

Chunks (`chunk_size` pairs of one tile, front to back, tile-major) are walked in batches of
`batch_chunks` by a loop over the used batches only. A batch's per-pixel planes are sized to
stay in cache, which is what XLA:CPU needs: it materialises every multi-use intermediate of a
fused expression, so throughput follows the cache level those planes live in. Inside a batch:
  - every pair is evaluated once (alpha and hit depth on its tile's pixels);
  - log(1 - alpha) is summed within each chunk by one small matmul with a triangular matrix;
  - chunk sums are scanned across the batch, restarting at each tile's first chunk, and the
    transmittance of the tile that straddles the batch boundary is carried into the next batch.
The forward also marks the pairs that can change an output: those with alpha > 0 at a pixel
still open (T >= T_MIN) before them. The others (mostly pairs behind a tile's saturated pixels,
or whose alpha stays under 1/255 at the tile's pixel centres) add zero weight everywhere and
leave every open pixel's transmittance as it was, so the backward pass skips them exactly: it
walks the marked pairs only, in layout order, cut again into chunks (`live_pairs`;
`RasterConfig.backward_skip` "chunks" marks whole chunks instead, "none" every pair). It
recomputes the forward blend with the same carry, carries g . (prefix of w f) the same way
(d/dalpha_i sum_j w_j f_j = T_i f_i - S_i / (1 - alpha_i) with S_i = total - inclusive prefix),
and pulls back through the per-pixel evaluation by hand: no autodiff inside the loop, and no
residuals but the marks and the median's (per pixel, the layout index of its pair).

Each surfel is stored (and gathered per pair, batch by batch) as the homography of its ray
transform about the filter centre c: the pixel-plane cross product k x l is linear in the pixel,
p(x) = a x + b y + c0 with
a = M1 x M2, b = M2 x M0, c0 = M0 x M1 (M's rows), so p = pc + a dx + b dy with (dx, dy) = x - c
and pc = p(c). Then (u, v) = (p0, p1) / p2 and, since M2 . a = M2 . b = 0, the hit depth
u M20 + v M21 + M22 is det(M) / p2. Same contract as `project.evaluate_pixels`, fewer flops.
`project` computes pc, a, b and det(M) per surfel (`Projected.p_center`, `p_dx`, `p_dy`, `det`).

With `offsets` (T, S, 2) (`samples.PixelSamples`), a tile's S sample points stand in for its
pixels: the same math, with each batch gathering its tiles' points instead of a constant grid.

Both walks also run in parts: `split_chunks` cuts the used chunks into ranges of whole tiles,
`forward_part` and `backward_part` walk one range each (other chunks count as empty), and the
parts add up (`join_forward`; the table gradients by plain sums). The training step on a CPU
walks two parts from two threads (`train/parted_step.py`), since XLA:CPU runs one loop at a time.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.raster.binning import chunk_layout, cumsum, tile_corner
from ghsplat_jax.raster.composite import (
    LOG_T_FLOOR,
    NUM_FEATURES,
    T_MIN,
    Static,
    Z,
    feature_columns,
    local_pixels,
    ndc_depth,
    segmented_exclusive_cumsum,
)
from ghsplat_jax.raster.project import Projected

# Columns of the per-surfel table (gathered per pair): homography about the centre, det(M),
# filter centre, opacity, centre depth (the filter branch's depth), colour and normal.
PC, A, B, DET, CX, CY, OPACITY, DEPTH = slice(0, 3), slice(3, 6), slice(6, 9), 9, 10, 11, 12, 13
COLOR_NORMAL = slice(14, 20)
NUM_FIELDS = 20
LOG_T_MIN = math.log(T_MIN)
LOG_HALF = math.log(0.5)
EDGE_ON = 1e6  # |p0|, |p1| >= 1e6 |p2|: the hit would lie at infinity; the filter branch decides


def pair_table(p: Projected) -> jax.Array:
    """(N, NUM_FIELDS) per-surfel rows the compositor gathers per pair (differentiable)."""
    return jnp.concatenate([p.p_center, p.p_dx, p.p_dy, p.det[:, None], p.center, p.opacity[:, None],
                            p.depth[:, None], p.color, p.normal], axis=1)


def _corner_offsets(f, tile, st: Static):
    """(K, B) offsets of each chunk's tile corner from each pair's filter centre."""
    x0, y0 = tile_corner(tile, st.tiles_x, st.tile_size)
    return x0[None] - f[CX], y0[None] - f[CY]


def _evaluate(f, dx, dy, valid, st: Static):
    """alpha, hit depth and what the hand-written pullback needs, all (K, B, P)."""
    g = lambda i: f[i][..., None]
    pc, a, b = f[PC][..., None], f[A][..., None], f[B][..., None]   # (3, K, B, 1) each
    p0, p1, p2 = (pc[i] + a[i] * dx + b[i] * dy for i in range(3))
    ok = (jnp.abs(p0) < EDGE_ON * jnp.abs(p2)) & (jnp.abs(p1) < EDGE_ON * jnp.abs(p2))
    inv = 1.0 / jnp.where(ok, p2, 1.0)
    u, v = p0 * inv, p1 * inv
    rho3 = jnp.where(ok, u * u + v * v, jnp.inf)
    rho2 = 2.0 * (dx * dx + dy * dy) if st.lowpass_filter else jnp.inf
    hit = rho3 <= rho2
    rho = jnp.where(hit, rho3, rho2)
    z = jnp.where(hit, g(DET) * inv, g(DEPTH))
    rho = jnp.where(jnp.isfinite(rho), rho, 1e10)  # no filter and no hit: alpha 0, finite pullback
    e = jnp.exp(-0.5 * rho)
    oe = g(OPACITY) * e
    keep = (oe >= 1.0 / 255.0) & (z >= st.near) & valid[..., None]
    alpha = jnp.where(keep, jnp.minimum(0.99, oe), 0.0)
    z = jnp.where(keep, z, st.near)                # keep is alpha > 0
    return alpha, z, (u, v, inv, rho, hit, e, oe)


def _cumsum_k(x: jax.Array) -> jax.Array:
    """Inclusive cumulative sum over the leading (chunk) axis as one matmul."""
    k = x.shape[0]
    tri = jnp.tril(jnp.ones((k, k), x.dtype))
    return jnp.matmul(tri, x.reshape(k, -1), precision=FLOAT32).reshape(x.shape)


def _lead(first: jax.Array) -> jax.Array:
    """Chunks of the batch that continue the tile open at the batch's start."""
    return jnp.cumsum(first.astype(jnp.int32)) == 0


def _segmented_carry(chunk_totals, first, carry):
    """Exclusive per-tile prefix of chunk totals (B, P), continuing `carry` for the open tile;
    and the inclusive total at the batch's end (the next batch's carry)."""
    before = segmented_exclusive_cumsum(chunk_totals, first) + jnp.where(_lead(first)[:, None], carry, 0.0)
    return before, before[-1] + chunk_totals[-1]


def _blend(alpha, log_t_carry, first, skip: str = "none"):
    """Transmittance before each pair, inclusion and weights (K, B, P); the next carry; and the
    backward's marks (K, B) (`Static.backward_skip`): "pairs", whether each pair can change an
    output (alpha > 0 at a pixel still open before it); "chunks", whether its chunk holds alpha > 0
    at a pixel open at the chunk's start; "none", all True."""
    log1m = jnp.log(1.0 - alpha)  # log1p costs twice as much on XLA:CPU; alpha <= 0.99 keeps this exact enough
    within = _cumsum_k(log1m)
    log_t0, carry = _segmented_carry(within[-1], first, log_t_carry)
    log_t0 = jnp.maximum(log_t0, LOG_T_FLOOR)
    log_after = log_t0[None] + within
    log_before = log_after - log1m
    t_before = jnp.exp(log_before)
    included = (alpha > 0) & (log_after >= LOG_T_MIN)
    weight = jnp.where(included, alpha * t_before, 0.0)
    # A pixel closed before a pair stays closed with or without it.
    if skip == "pairs":
        live = jnp.any((alpha > 0) & (log_before >= LOG_T_MIN), axis=-1)
    elif skip == "chunks":
        live = jnp.broadcast_to(jnp.any((log_t0 >= LOG_T_MIN) & (within[-1] < 0), axis=-1), alpha.shape[:2])
    else:
        live = jnp.ones(alpha.shape[:2], bool)
    return t_before, included, weight, log_before, jnp.maximum(carry, LOG_T_FLOOR), live


def _last_median(included, log_before):
    """Index within its chunk (B, P) of the last pair with T > 0.5 at each pixel, -1 for none."""
    k = jnp.arange(included.shape[0])[:, None, None]
    return jnp.max(jnp.where(included & (log_before > LOG_HALF), k, -1), axis=0)


def _slice(x, i, batch):
    return jax.lax.dynamic_slice_in_dim(x, i * batch, batch)


def _batch_inputs(table, surfel, valid, tile, first, i, st: Static, lo, hi):
    """Batch i: fields (F, K, B), valid (K, B), tile (B,), first (B,), corner offsets (K, B);
    chunks outside [lo, hi) count as empty (another part's, `split_chunks`)."""
    rows = table[_slice(surfel, i, st.batch_chunks)]                    # (B, K, F)
    f = jnp.moveaxis(rows, 2, 0).swapaxes(1, 2)
    t = _slice(tile, i, st.batch_chunks)
    chunk = i * st.batch_chunks + jnp.arange(st.batch_chunks)
    v = _slice(valid, i, st.batch_chunks).T & ((chunk >= lo) & (chunk < hi))[None]
    return f, v, t, _slice(first, i, st.batch_chunks), _corner_offsets(f, t, st)


def split_chunks(first, used, parts: int):
    """(parts + 1,) chunk indices: part j walks chunks [b[j], b[j + 1]) of the `used` ones,
    about used / parts of them, each part starting at a tile's first chunk, so no transmittance
    crosses parts and the parts' walks are independent."""
    index = jnp.arange(first.shape[0], dtype=jnp.int32)
    used = jnp.asarray(used, jnp.int32)
    targets = (jnp.arange(1, parts, dtype=jnp.int32) * used) // parts
    starts = jnp.min(jnp.where(first[None] & (index[None] >= targets[:, None]) & (index[None] < used),
                               index[None], used), axis=1)
    return jnp.concatenate([jnp.zeros(1, jnp.int32), starts, used[None]])


def _batches(lo, hi, batch: int) -> tuple[Any, Any]:
    """The loop range over batches that hold chunks [lo, hi)."""
    return lo // batch, (hi + batch - 1) // batch


def _local_points(offsets, t, st: Static):
    """x and y of the points evaluated in each chunk's tile, relative to its corner: the pixel
    centres as NumPy literals (P,), or the tiles' sample points (B, S)."""
    if offsets is None:
        return local_pixels(st.tile_size)
    xy = jnp.take(offsets, t, axis=0, mode="clip")
    return xy[..., 0], xy[..., 1]


def _offsets(corner, local):
    """(dx, dy) of every evaluated point from each pair's filter centre, (K, B, P)."""
    return corner[0][..., None] + local[0], corner[1][..., None] + local[1]


def used_chunks(valid):
    """How many chunks of the layout hold pairs (they come first)."""
    return jnp.sum(valid[:, 0].astype(jnp.int32))


def _pixel_sums(weight, z, f, st: Static):
    """(B, len(feature_columns(st)), P) sums of w f over each chunk, field-major.
    Written out as a sum over the chunk's pairs of broadcast products, which XLA:CPU fuses into
    one vectorised loop per feature: as an einsum and reductions over the chunk axis it ran YNN
    batched dots of (P, K) x (K, 6) blocks and small-axis reductions, 2.5x the cost (and a
    (B, P, F) result is strided along P)."""
    cn = f[COLOR_NORMAL][..., None]                                      # (6, K, B, 1)
    factors = [None, cn[0], cn[1], cn[2]]                               # A, rgb
    if st.depth_normal:
        factors += [z, cn[3], cn[4], cn[5]]
    if st.distortion:
        m = ndc_depth(z, st)
        factors += [m, m * m]
    sums = [sum(weight[k] if x is None else weight[k] * x[k] for k in range(weight.shape[0])) for x in factors]
    return jnp.stack(sums, axis=1)


def _all_features(sums, st: Static):
    """(T, P, NUM_FEATURES) from the (T, P, len(feature_columns(st))) sums, zeros in the other
    columns (filled once after the loop, not scattered batch by batch)."""
    columns = dict(zip(feature_columns(st), jnp.moveaxis(sums, -1, 0)))
    zero = jnp.zeros(sums.shape[:-1], sums.dtype)
    return jnp.stack([columns.get(c, zero) for c in range(NUM_FEATURES)], axis=-1)


def forward_part(st: Static, table, surfel, valid, tile, first, offsets, lo, hi):
    """The forward walk of chunks [lo, hi) (`split_chunks`): per-tile sums (T, F', P), the median
    pairs' depths (chunks, P), their layout indices (T, P) and the backward's marks (W, K), each
    zero (-1, False) outside the part; `join_forward` adds the parts up."""
    num_chunks, pixels = tile.shape[0], st.pixels
    batch = st.batch_chunks

    def body(i, state):
        log_t, totals, z_last, selected, live = state
        f, v, t, fst, corner = _batch_inputs(table, surfel, valid, tile, first, i, st, lo, hi)
        alpha, z, _ = _evaluate(f, *_offsets(corner, _local_points(offsets, t, st)), v, st)
        _, included, weight, log_before, log_t, batch_live = _blend(alpha, log_t, fst, st.backward_skip)
        live = jax.lax.dynamic_update_slice_in_dim(live, batch_live.T, i * batch, 0)
        totals = totals.at[t].add(_pixel_sums(weight, z, f, st), mode="drop")
        if st.median:  # per pixel, the layout index (chunk x K + k) of the last pair with T > 0.5
            k_last = _last_median(included, log_before)
            z_here = jnp.sum(jnp.where(jnp.arange(z.shape[0])[:, None, None] == k_last[None], z, 0.0), 0)
            z_last = jax.lax.dynamic_update_slice_in_dim(z_last, z_here, i * batch, 0)
            pair_id = (i * batch + jnp.arange(batch, dtype=jnp.int32))[:, None] * z.shape[0] + k_last
            selected = selected.at[t].max(jnp.where(k_last >= 0, pair_id, -1), mode="drop")
        return log_t, totals, z_last, selected, live

    median_rows = num_chunks if st.median else 1
    init = (jnp.zeros(pixels), jnp.zeros((st.num_tiles, len(feature_columns(st)), pixels)),
            jnp.zeros((median_rows, pixels)), jnp.full((st.num_tiles, pixels), -1, jnp.int32),
            jnp.zeros(tile.shape + (surfel.shape[1],), bool))
    return jax.lax.fori_loop(*_batches(lo, hi, batch), body, init)[1:]


def join_forward(st: Static, parts, chunk_size: int):
    """Outputs (totals (T, P, F), median (T, P)) and residuals from `forward_part`'s parts."""
    totals, z_last, selected, live = parts[0]
    for more in parts[1:]:
        totals, z_last = totals + more[0], z_last + more[1]
        selected, live = jnp.maximum(selected, more[2]), live | more[3]
    totals = _all_features(jnp.swapaxes(totals, 1, 2), st)              # (T, P, F)
    chunk = jnp.maximum(selected, 0) // chunk_size
    median = jnp.where(selected >= 0, z_last[chunk, jnp.arange(st.pixels)[None]], 0.0)
    return (totals, median), (totals, selected, live)


def _forward(st: Static, table, surfel, valid, tile, first, offsets):
    part = forward_part(st, table, surfel, valid, tile, first, offsets, 0, used_chunks(valid))
    return join_forward(st, [part], surfel.shape[1])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def composite_carried(st: Static, table, surfel, valid, tile, first, offsets=None):
    """Per-tile feature sums (T, P, F) and median depth (T, P) from the per-surfel table
    (N, NUM_FIELDS) and the chunked pairs' surfels (W, K); valid (W, K), tile (W,), first (W,)
    as `binning.Layout` lays them out; `offsets` (T, S, 2): sample points instead of pixels.
    Each batch gathers its own rows, and the backward scatter-adds into an (N, NUM_FIELDS)
    gradient: a (W, K, NUM_FIELDS) pair table and its zeroed gradient cost more than the
    compositor's gathers."""
    return _forward(st, table, surfel, valid, tile, first, offsets)[0]


def _fwd(st, table, surfel, valid, tile, first, offsets):
    outputs, (totals, selected, live) = _forward(st, table, surfel, valid, tile, first, offsets)
    return outputs, (table, surfel, valid, tile, offsets, totals, selected, live)


def live_pairs(live, surfel, valid, tile, num_tiles: int):
    """The pairs the backward walks: the marked ones (`live` (W, K)), in layout order, cut again
    into chunks of K that never span two tiles. Returns surfels, valid and each pair's layout
    index (W, K; W x K where unused), tile and first flags (W,), and how many chunks are used.
    A pair that cannot change an output (alpha > 0 only at pixels closed before it) adds no
    weight and moves no open pixel's transmittance, and a pixel is always closed by a pair that
    can, so walking the others alone gives each of their gradients; its own gradient is zero."""
    w, k = surfel.shape
    keep = live & valid
    tile_count = jnp.zeros(num_tiles + 1, jnp.int32).at[tile].add(jnp.sum(keep, 1, dtype=jnp.int32))[:-1]
    flat = keep.reshape(-1)
    slot = jnp.where(flat, cumsum(flat.astype(jnp.int32)) - 1, w * k)
    index = jnp.zeros(w * k, jnp.int32).at[slot].set(jnp.arange(w * k, dtype=jnp.int32), mode="drop")
    chunk_tile, chunk_start, chunk_count, first = chunk_layout(tile_count, k, w)
    index = index[jnp.clip(chunk_start[:, None] + jnp.arange(k), 0, w * k - 1)]
    used = jnp.arange(k)[None] < chunk_count[:, None]
    return (surfel.reshape(-1)[index], used, jnp.where(used, index, w * k), chunk_tile, first,
            jnp.sum((chunk_count > 0).astype(jnp.int32)))


def _pullback(f, corner, local, aux, d_alpha, d_z):
    """Hand-derived gradients (NUM_FIELDS - 6, K, B) of the geometric per-pair fields (all but
    colour and normal) from d alpha and d z; `local` as `_local_points` gives it."""
    u, v, inv, rho, hit, e, oe = aux
    live = d_alpha != 0
    unclamped = live & (oe < 0.99)
    g_rho = jnp.where(unclamped, -0.5 * oe * d_alpha, 0.0)
    g_opacity = jnp.where(unclamped, e * d_alpha, 0.0)
    # Hit branch: rho = (p0^2 + p1^2) / p2^2, z = det / p2.
    g_hit_rho = jnp.where(hit, g_rho, 0.0)
    g_hit_z = jnp.where(hit, d_z, 0.0)
    g_p0, g_p1 = 2.0 * g_hit_rho * u * inv, 2.0 * g_hit_rho * v * inv
    g_p2 = -(2.0 * g_hit_rho * rho + g_hit_z * f[DET][..., None] * inv) * inv
    g_det = g_hit_z * inv
    # Filter branch: rho = 2 |x - c|^2, z = centre depth.
    g_filter = jnp.where(hit, 0.0, g_rho)
    g_depth = jnp.where(hit, 0.0, d_z)
    # Sums over pixels against [1, dx, dy]; dx = ox + x_local, so a matmul with the local basis.
    # One per plane: stacking the planes first makes XLA:CPU emit one unvectorised loop that
    # picks a plane per element, which cost more than all the rest of the backward.
    xl, yl = local
    basis = jnp.stack([jnp.ones_like(xl), xl, yl], axis=-1)             # (P, 3), or (B, S, 3) for samples
    if basis.ndim == 2:
        against = lambda plane: jnp.matmul(plane, basis, precision=FLOAT32)
    else:
        against = lambda plane: jnp.einsum("kbp,bpc->kbc", plane, basis, precision=FLOAT32)
    s = jnp.stack([against(plane) for plane in (g_p0, g_p1, g_p2, g_filter)])  # (4, K, B, 3)
    ox, oy = corner
    total, sx, sy = s[..., 0], s[..., 1] + ox * s[..., 0], s[..., 2] + oy * s[..., 0]
    d_pc, d_a, d_b = total[:3], sx[:3], sy[:3]
    # det, opacity and centre depth need only the plain sum over pixels.
    d_det, d_opacity, d_depth = (jnp.sum(plane, -1) for plane in (g_det, g_opacity, g_depth))
    a, b = f[A], f[B]
    d_cx = -jnp.sum(a * d_pc, 0) - 4.0 * sx[3]
    d_cy = -jnp.sum(b * d_pc, 0) - 4.0 * sy[3]
    return jnp.stack([*d_pc, *d_a, *d_b, d_det, d_cx, d_cy, d_opacity, d_depth])


class BackwardInputs(NamedTuple):
    """What every backward part reads: the table, the marked pairs cut into chunks (`live_pairs`),
    the median pairs' layout indices and the cotangents (padded with a row for the empty tile)."""

    table: jax.Array
    surfel: jax.Array
    valid: jax.Array
    tile: jax.Array
    first: jax.Array
    offsets: jax.Array | None
    pair_id: jax.Array
    selected: jax.Array
    g_median: jax.Array
    g_dot_total: jax.Array
    g_rows: jax.Array


def backward_inputs(st: Static, residuals, cotangents):
    """What every backward part reads, from the forward's residuals and the output cotangents;
    and how many chunks of marked pairs there are to walk (`split_chunks`)."""
    table, surfel, valid, tile, offsets, totals, selected, live = residuals
    surfel, valid, pair_id, tile, first, num_live = live_pairs(live, surfel, valid, tile, st.num_tiles)
    g_totals, g_median = cotangents
    pad = lambda a, fill: jnp.concatenate([a, jnp.full((1,) + a.shape[1:], fill, a.dtype)])
    g_totals, g_median, selected = pad(g_totals, 0.0), pad(g_median, 0.0), pad(selected, -1)
    g_dot_total = jnp.sum(g_totals * pad(totals, 0.0), axis=-1)          # (T + 1, P)
    # Pixels minor, so a batch gathers whole (F, P) rows and every per-pixel fusion reads its
    # (B, P) planes along P. Gathered as (B, P, F), XLA:CPU reads them with a stride; gathered
    # from (F, T + 1, P), it transposes them inside every fusion that reads them.
    g_rows = jnp.swapaxes(g_totals, 1, 2)                               # (T + 1, F, P)
    return BackwardInputs(table, surfel, valid, tile, first, offsets, pair_id, selected, g_median, g_dot_total,
                          g_rows), num_live


def backward_part(st: Static, inputs: BackwardInputs, lo, hi):
    """The gradient (N, NUM_FIELDS) of the per-surfel table from the marked chunks [lo, hi);
    the parts' gradients add up."""
    table, surfel, valid, tile, first, offsets, pair_id, selected, g_median, g_dot_total, g_rows = inputs
    batch = st.batch_chunks

    def body(i, state):
        log_t, prefix, d_table = state
        f, v, t, fst, corner = _batch_inputs(table, surfel, valid, tile, first, i, st, lo, hi)
        local = _local_points(offsets, t, st)
        alpha, z, aux = _evaluate(f, *_offsets(corner, local), v, st)
        t_before, included, weight, log_before, log_t, _ = _blend(alpha, log_t, fst)
        g = g_rows[t]                                                     # (B, F, P)
        plane = lambda c: g[:, c][None]                                   # (1, B, P)
        const_planes = (1, 2, 3, 5, 6, 7) if st.depth_normal else (1, 2, 3)  # rgb and normal
        # h = g . f for every (pair, pixel): the output change per unit weight. Written out, it
        # fuses; as an einsum, XLA:CPU ran batched (K, 6) x (6, P) dots and a transpose.
        h = plane(0) + sum(f[COLOR_NORMAL][j][..., None] * plane(c) for j, c in enumerate(const_planes))
        g_z = []                                                          # d(output)/dz per unit weight
        if st.depth_normal:
            h = h + plane(Z) * z
            g_z.append(plane(Z))
        if st.distortion:
            m = ndc_depth(z, st)
            h = h + (plane(8) + plane(9) * m) * m
            g_z.append((plane(8) + 2.0 * plane(9) * m) * (st.far / (st.far - st.near) * st.near / (z * z)))
        wh = weight * h
        within = _cumsum_k(wh)
        before, prefix = _segmented_carry(within[-1], fst, prefix)
        after = g_dot_total[t][None] - (before[None] + within)            # g . S_i
        # One divide last: XLA:CPU keeps an expensive op's result in memory, where it copies a
        # cheap expression into each of the pullback's seven consumers (gathers and all).
        one_minus = 1.0 - alpha
        d_alpha = jnp.where(included, (t_before * h * one_minus - after) / one_minus, 0.0)
        d_z = weight * sum(g_z) if g_z else jnp.zeros_like(weight)
        if st.median:  # the pixel's median pair, found by its layout index (never another part's)
            here = (_slice(pair_id, i, batch).T[..., None] == selected[t][None]) & v[..., None]
            d_z = d_z + jnp.where(here, g_median[t][None], 0.0)
        d_geometry = _pullback(f, corner, local, aux, d_alpha, d_z)     # (14, K, B)
        g_const = jnp.concatenate([g[:, c:c + 1] for c in const_planes], axis=1)  # (B, 6 or 3, P)
        d_const = jnp.einsum("kbp,bcp->kbc", weight, g_const, precision=FLOAT32)  # (K, B, 6 or 3)
        if not st.depth_normal:
            d_const = jnp.pad(d_const, ((0, 0), (0, 0), (0, 3)))           # no normal gradient
        d_rows = jnp.concatenate([jnp.moveaxis(d_geometry, 0, -1), d_const], axis=-1).swapaxes(0, 1)
        d_table = d_table.at[_slice(surfel, i, batch)].add(d_rows)         # padding pairs add zeros
        return log_t, prefix, d_table

    init = (jnp.zeros(st.pixels), jnp.zeros(st.pixels), jnp.zeros_like(table))
    return jax.lax.fori_loop(*_batches(lo, hi, batch), body, init)[2]


def _bwd(st: Static, residuals, cotangents):
    inputs, num_live = backward_inputs(st, residuals, cotangents)
    return backward_part(st, inputs, 0, num_live), None, None, None, None, None


composite_carried.defvjp(_fwd, _bwd)
