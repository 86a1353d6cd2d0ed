"""Tile binning into a static pair buffer, and the per-tile chunk layout.

Surfels are sorted by centre depth first; pairs are generated in that order and then stably
sorted by tile id, so each tile's list is front to back without a second sort key.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.raster.project import Projected

TILE_MARGIN = 1e-2        # pixels added around a tile's rectangle of pixel centres (float32 slack)
CONIC_TOLERANCE = 1e-5    # the normalised conic's value still counted as inside (likewise)
PACKED_KEYS_MAX = int(np.iinfo(np.uint32).max)  # (tile, depth rank) keys up to this sort as one uint32
HOST_SORT_MIN_KEYS = 1 << 16  # "auto" sorts this many keys or more with NumPy (see host_sorts)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TileGrid:
    tiles_x: int = dataclasses.field(metadata=dict(static=True))
    tiles_y: int = dataclasses.field(metadata=dict(static=True))
    tile_size: int = dataclasses.field(metadata=dict(static=True))

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @staticmethod
    def for_image(width: int, height: int, tile_size: int) -> "TileGrid":
        return TileGrid(-(-width // tile_size), -(-height // tile_size), tile_size)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Layout:
    """Sorted pairs cut into chunks of `chunk_size` pairs that never span two tiles."""

    pair_surfel: jax.Array    # (C,) surfel id of each sorted pair
    chunk_tile: jax.Array     # (W,) tile of each chunk (num_tiles for unused chunks)
    chunk_start: jax.Array    # (W,) first pair of the chunk
    chunk_count: jax.Array    # (W,) pairs in the chunk (0 for unused chunks)
    chunk_first: jax.Array    # (W,) bool: first chunk of its tile
    tile_count: jax.Array     # (T,) pairs per tile
    num_pairs: jax.Array      # () candidate pairs needed (may exceed C: overflow)
    num_kept: jax.Array       # () pairs whose tile the surfel's alpha can reach 1/255 in


def tile_corner(tile: jax.Array, tiles_x: int, tile_size: int) -> tuple[jax.Array, jax.Array]:
    """Pixel coordinates (x0, y0) of tile ids' top-left corners, float32. Truncating division:
    tile ids are non-negative, and floor division's sign fix-ups cost XLA:CPU 3.6x as much."""
    x0 = jax.lax.rem(tile, tiles_x) * tile_size
    y0 = jax.lax.div(tile, tiles_x) * tile_size
    return x0.astype(jnp.float32), y0.astype(jnp.float32)


def tile_ranges(p: Projected, width: int, height: int, grid: TileGrid, tight: bool = True,
                points: bool = False):
    """Inclusive tile rectangles (x0, y0, x1, y1) and candidate pair counts per surfel, from the
    opacity-aware box (tight) or the 3-sigma box: the tiles of the pixel centres inside it, or
    with `points` (sample points anywhere in the image) every tile the box overlaps."""
    ts = grid.tile_size
    box_min, box_max = (p.bin_min, p.bin_max) if tight else (p.box_min, p.box_max)
    size = jnp.array([width, height], jnp.float32)
    if points:
        lo, hi, last = box_min, box_max, size
    else:  # pixel centres j + 0.5 inside the box
        lo, hi, last = jnp.ceil(box_min - 0.5), jnp.floor(box_max - 0.5), size - 1
    hits = p.visible & jnp.all((hi >= 0) & (lo <= last) & (lo <= hi), axis=1)
    lo = jnp.clip(lo, 0, last).astype(jnp.int32) // ts
    hi = jnp.clip(hi, 0, last).astype(jnp.int32) // ts
    if points:  # a point on the image's right or bottom edge belongs to the last tile
        last_tile = jnp.array([grid.tiles_x - 1, grid.tiles_y - 1], jnp.int32)
        lo, hi = jnp.minimum(lo, last_tile), jnp.minimum(hi, last_tile)
    extent = hi - lo + 1
    counts = jnp.where(hits, extent[:, 0] * extent[:, 1], 0)
    return lo, hi, counts


def cumsum(x: jax.Array, axis: int = 0) -> jax.Array:
    """Inclusive cumulative sum. jnp.cumsum lowers to a reduce-window that XLA:CPU runs about
    3x slower than this log-depth scan (9.7 against 3.0 ms for 655k int32, measured)."""
    return jax.lax.associative_scan(jnp.add, x, axis=axis)


def _owner(starts: jax.Array, counts: jax.Array, size: int) -> jax.Array:
    """For each slot in [0, size), the index of the segment (starts, counts) covering it.

    Segments are consecutive; the owner of slot p is (number of starts <= p) - 1, counted by a
    scatter-add and a cumulative sum (linear, unlike a binary search per slot).
    """
    hist = jnp.zeros(size + 1, jnp.int32).at[jnp.minimum(starts, size)].add(1)
    return cumsum(hist[:size]) - 1


def bin_pairs(p: Projected, width: int, height: int, grid: TileGrid, capacity: int,
              chunk_size: int, num_chunks: int, tight: bool = True, boxes: jax.Array | np.ndarray | None = None,
              sort: str = "auto") -> Layout:
    """`boxes` (T, 4): render only points inside these per-tile boxes (`samples.PixelSamples`):
    tiles with an empty box get no pairs, and the exact test uses the box, not the tile.
    `sort`: `RasterConfig.sort` (see `host_sorts`)."""
    n = p.depth.shape[0]
    lo, hi, counts = tile_ranges(p, width, height, grid, tight, boxes is not None)
    order = stable_argsort(p.depth, host_sorts(sort, n))
    sorted_counts = counts[order]
    ends = cumsum(sorted_counts)
    starts = ends - sorted_counts
    num_pairs = ends[-1] if n else jnp.int32(0)

    slot = jnp.arange(capacity, dtype=jnp.int32)
    owner = jnp.clip(_owner(starts, sorted_counts, capacity), 0, max(n - 1, 0))
    surfel = order[owner]
    local = slot - starts[owner]
    row_len = (hi[surfel, 0] - lo[surfel, 0] + 1)
    # Truncating division (exact here: both are non-negative): with floor division's sign
    # fix-ups, XLA:CPU takes 3.6x as long for this divide and remainder (524k pairs, measured).
    row, col = jax.lax.div(local, row_len), jax.lax.rem(local, row_len)
    tile_xy = (lo[surfel, 0] + col, lo[surfel, 1] + row)
    tile = tile_xy[1] * grid.tiles_x + tile_xy[0]
    keep = slot < num_pairs
    if boxes is not None:
        keep &= boxes[tile, 0] <= boxes[tile, 2]
    if tight:
        keep &= tile_touched(p, surfel, tile, tile_xy, grid, boxes)
    tile = jnp.where(keep, tile, grid.num_tiles)
    tile, pair_surfel = _tile_major(tile, owner, order, grid.num_tiles, n, host_sorts(sort, capacity))

    tile_count = jnp.zeros(grid.num_tiles + 1, jnp.int32).at[tile].add(1)[:-1]
    chunk_tile, chunk_start, chunk_count, chunk_first = chunk_layout(tile_count, chunk_size, num_chunks)
    return Layout(pair_surfel=pair_surfel, chunk_tile=chunk_tile, chunk_start=chunk_start, chunk_count=chunk_count,
                  chunk_first=chunk_first, tile_count=tile_count, num_pairs=num_pairs, num_kept=jnp.sum(keep))


def chunk_layout(tile_count: jax.Array, chunk_size: int, num_chunks: int):
    """Chunks of `chunk_size` pairs that never span two tiles, over pairs stored tile after tile
    (`tile_count` (T,) pairs per tile): each chunk's tile (T for unused chunks), first pair, pair
    count (0 for unused chunks) and whether it is its tile's first. `num_chunks` must hold every
    tile's chunks."""
    num_tiles = tile_count.shape[0]
    tile_start = cumsum(tile_count) - tile_count
    chunks = -(-tile_count // chunk_size)
    chunk_offset = cumsum(chunks) - chunks
    w = jnp.arange(num_chunks, dtype=jnp.int32)
    chunk_tile = jnp.clip(_owner(chunk_offset, chunks, num_chunks), 0, num_tiles - 1)
    used = w < jnp.sum(chunks)
    k = w - chunk_offset[chunk_tile]
    chunk_start = tile_start[chunk_tile] + k * chunk_size
    chunk_count = jnp.where(used, jnp.clip(tile_count[chunk_tile] - k * chunk_size, 0, chunk_size), 0)
    return jnp.where(used, chunk_tile, num_tiles), chunk_start, chunk_count, used & (k == 0)


def _sortable_bits(x: jax.Array) -> jax.Array:
    """uint32 keys in the order of the float32 values: -0 sorts as 0, and NaNs last (as argsort)."""
    x = jnp.where(x == 0, 0.0, jnp.where(jnp.isnan(x), jnp.nan, x)).astype(jnp.float32)
    b = jax.lax.bitcast_convert_type(x, jnp.uint32)
    return jnp.where(b >> 31 == 1, ~b, b | np.uint32(1 << 31))


def host_sorts(mode: str, num_keys: int) -> bool:
    """Whether to sort `num_keys` keys on the host with NumPy (`RasterConfig.sort`). "auto" does
    on a CPU backend from HOST_SORT_MIN_KEYS keys: there NumPy's SIMD sort is about 16x faster
    than XLA:CPU's (2 ms against 33 ms for 655k uint32 keys, measured) and the data is already in
    host memory, while below it the gain is a few ms at most and not worth the host callback
    (XLA's persistent compilation cache skips programs that have one). "xla" never does."""
    return mode == "auto" and num_keys >= HOST_SORT_MIN_KEYS and jax.default_backend() == "cpu"


def _host_sort(x) -> np.ndarray:
    return np.sort(np.asarray(x), axis=-1)


def _host_stable_argsort(key) -> np.ndarray:
    """Stable argsort of uint32 keys along the last axis: one sort of (key, position) packed
    into uint64 (positions are unique, so any sort is stable)."""
    key = np.asarray(key)
    n = key.shape[-1]
    bits = max((n - 1).bit_length(), 1)
    packed = (key.astype(np.uint64) << np.uint64(bits)) | np.arange(n, dtype=np.uint64)
    return (np.sort(packed, axis=-1) & np.uint64((1 << bits) - 1)).astype(np.int32)


def sort_unsigned(x: jax.Array, host: bool) -> jax.Array:
    """Ascending sort of unsigned integer keys (no gradient: they are integers)."""
    if not host:
        return jnp.sort(x)
    return jax.pure_callback(_host_sort, jax.ShapeDtypeStruct(x.shape, x.dtype), x, vmap_method="broadcast_all")


def stable_argsort(x: jax.Array, host: bool) -> jax.Array:
    """jnp.argsort(x, stable=True) of a float vector. On the host, one NumPy sort; elsewhere an
    LSD radix sort whose passes are single-operand uint32 sorts of (digit, position): XLA:CPU
    sorts one uint32 operand about 7x faster than a (key, index) pair."""
    n = x.shape[0]
    key = _sortable_bits(x)
    if host:
        return jax.pure_callback(_host_stable_argsort, jax.ShapeDtypeStruct(x.shape, jnp.int32), key,
                                 vmap_method="broadcast_all")
    index_bits = max((n - 1).bit_length(), 1)
    digit_bits = 32 - index_bits
    position = jnp.arange(n, dtype=jnp.uint32)
    order = jnp.arange(n, dtype=jnp.int32)
    for shift in range(0, 32, digit_bits):
        digit = (key[order] >> shift) & np.uint32((1 << min(digit_bits, 32 - shift)) - 1)
        packed = jnp.sort((digit << index_bits) | position)   # positions are unique: a stable pass
        order = order[(packed & np.uint32((1 << index_bits) - 1)).astype(jnp.int32)]
    return order


def _tile_major(tile, owner, order, num_tiles: int, n: int, host: bool):
    """Pairs sorted by tile, front to back within a tile: (tile, surfel) of each.

    Slots are in depth order (by `owner`, the surfel's depth rank), so this is a stable sort by
    tile. Where (tile, owner) packs into one uint32 the sort has a single operand, which XLA:CPU
    sorts about 8x faster than a (key, payload) pair (measured on 600k pairs)."""
    if (num_tiles + 1) * max(n, 1) <= PACKED_KEYS_MAX:
        key = sort_unsigned(tile.astype(jnp.uint32) * np.uint32(n) + owner.astype(jnp.uint32), host)
        return (key // np.uint32(n)).astype(jnp.int32), order[(key % np.uint32(n)).astype(jnp.int32)]
    return jax.lax.sort((tile, order[owner]), num_keys=1, is_stable=True)


def _tile_test_table(p: Projected) -> jax.Array:
    """(N, 15) per-surfel terms of the exact tile test, computed once per surfel and read as one
    row per pair: the centre, the filter's reach, whether the ellipse is bounded, the conic's six
    coefficients, the reciprocals of its diagonal, and its minimum's offset from the centre and
    whether that minimum lies inside the ellipse. (Read as 15 separate gathers per pair, binning a
    fern view at 787k pair slots took 3-11 ms longer, 66-79 ms in all.)"""
    qxx, qxy, qyy, qx, qy, _ = (p.conic[:, i] for i in range(6))
    safe = lambda v: jnp.where(v > 0, v, 1.0)
    det = qxx * qyy - qxy * qxy
    mx, my = (qxy * qy - qyy * qx) / safe(det), (qxy * qx - qxx * qy) / safe(det)
    has_min = (det > 0) & (_conic(p.conic.T, mx, my) <= CONIC_TOLERANCE)
    return jnp.stack([p.center[:, 0], p.center[:, 1], p.reach, p.bounded.astype(jnp.float32), *p.conic.T,
                      1.0 / safe(qxx), 1.0 / safe(qyy), mx, my, has_min.astype(jnp.float32)], axis=1)


def _conic(q, dx, dy):
    """The normalised conic's value at offset (dx, dy) from the centre; q: its six rows."""
    qxx, qxy, qyy, qx, qy, q1 = q
    return qxx * dx * dx + 2 * qxy * dx * dy + qyy * dy * dy + 2 * qx * dx + 2 * qy * dy + q1


def tile_touched(p: Projected, surfel: jax.Array, tile: jax.Array, tile_xy: tuple[jax.Array, jax.Array],
                 grid: TileGrid, boxes: jax.Array | np.ndarray | None = None) -> jax.Array:
    """Whether a tile's pixel centres (or the box of its sample points) meet the region where
    the surfel's alpha can reach 1/255: its ellipse (the minimum of the conic over the
    rectangle is <= 0) or its filter disc. Exact up to float32 rounding, which a small margin
    covers; unbounded conics keep every tile. `tile_xy`: the tiles' column and row."""
    ts = grid.tile_size
    rows = _tile_test_table(p)[surfel]
    cx, cy, reach, bounded, *conic, inv_xx, inv_yy, mx, my, has_min = (rows[:, i] for i in range(15))
    bounded, has_min = bounded > 0, has_min > 0  # stored as 0/1 in the float table
    if boxes is None:
        x0 = (tile_xy[0] * ts).astype(jnp.float32) + (0.5 - TILE_MARGIN) - cx
        y0 = (tile_xy[1] * ts).astype(jnp.float32) + (0.5 - TILE_MARGIN) - cy
        x1, y1 = x0 + (ts - 1 + 2 * TILE_MARGIN), y0 + (ts - 1 + 2 * TILE_MARGIN)
    else:
        x0, y0 = boxes[tile, 0] - cx - TILE_MARGIN, boxes[tile, 1] - cy - TILE_MARGIN
        x1, y1 = boxes[tile, 2] - cx + TILE_MARGIN, boxes[tile, 3] - cy + TILE_MARGIN
    # Filter disc: the rectangle's closest point to the centre.
    nx, ny = jnp.clip(0.0, x0, x1), jnp.clip(0.0, y0, y1)
    in_disc = nx * nx + ny * ny <= reach * reach
    q = lambda dx, dy: _conic(conic, dx, dy) <= CONIC_TOLERANCE
    _, qxy, _, qx, qy, _ = conic
    # The conic's minimum: inside the rectangle, or on one of its edges (1D minima of a quadratic).
    inside = has_min & (mx >= x0) & (mx <= x1) & (my >= y0) & (my <= y1)
    on_edge = jnp.zeros_like(inside)
    for y in (y0, y1):
        on_edge |= q(jnp.clip(-(qxy * y + qx) * inv_xx, x0, x1), y)
    for x in (x0, x1):
        on_edge |= q(x, jnp.clip(-(qxy * x + qy) * inv_yy, y0, y1))
    return ~bounded | in_disc | inside | on_edge


def count_pairs(p: Projected, width: int, height: int, grid: TileGrid,
                tight: bool = True, points: bool = False) -> tuple[jax.Array, jax.Array]:
    """(candidate pairs, candidates of the fullest tile) from the tile rectangles via a 2D
    difference array (the buffer must hold every candidate; the exact test runs after)."""
    lo, hi, counts = tile_ranges(p, width, height, grid, tight, points)
    hit = counts > 0
    diff = jnp.zeros((grid.tiles_y + 1, grid.tiles_x + 1), jnp.int32)
    one = hit.astype(jnp.int32)
    diff = (diff.at[lo[:, 1], lo[:, 0]].add(one).at[lo[:, 1], hi[:, 0] + 1].add(-one)
            .at[hi[:, 1] + 1, lo[:, 0]].add(-one).at[hi[:, 1] + 1, hi[:, 0] + 1].add(one))
    per_tile = cumsum(cumsum(diff, axis=0), axis=1)
    return jnp.sum(counts), jnp.max(per_tile)
