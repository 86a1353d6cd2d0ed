"""The public renderer: `render(surfels, camera, config)`.

`rasterize` is the pure, jit-able function with a static pair capacity. `render` picks that
capacity: eagerly it counts the pairs first and uses the smallest capacity bucket that fits
(so nothing is dropped and recompilation happens only when a bucket grows); under a trace it
uses `config.pair_capacity` and reports (or raises on) overflow.
"""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp

from ghsplat_jax.core.camera import Camera
from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.raster import binning, carried, composite, naive
from ghsplat_jax.raster.config import RasterConfig, RasterOverflowError, RasterStats, RenderOutput
from ghsplat_jax.raster.project import Projected, project
from ghsplat_jax.raster.samples import PixelSamples

log = logging.getLogger("ghsplat.raster")

MIN_CAPACITY = 1 << 12


def capacity_bucket(pairs: int) -> int:
    """Smallest of 1, 1.25, 1.5, 1.75 x 2^k at or above `pairs` (wastes at most 25%)."""
    pairs = max(int(pairs), MIN_CAPACITY)
    base = 1 << (pairs.bit_length() - 1)
    for step in (4, 5, 6, 7, 8):
        if base * step // 4 >= pairs:
            return base * step // 4
    raise AssertionError("unreachable")


def _as_surfels(s: Surfels) -> Surfels:
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), s)


def _sh_degree(s: Surfels, cfg: RasterConfig) -> int:
    return s.sh_degree if cfg.sh_degree is None else min(cfg.sh_degree, s.sh_degree)


def _chunk_params(p: Projected, index) -> composite.ChunkParams:
    return composite.ChunkParams(M=p.M[index], center=p.center[index], opacity=p.opacity[index],
                                 color=p.color[index], normal=p.normal[index], depth=p.depth[index])


def _num_chunks(capacity: int, grid: binning.TileGrid, cfg: RasterConfig) -> int:
    chunks = capacity // cfg.chunk_size + grid.num_tiles
    return -(-chunks // cfg.batch_chunks) * cfg.batch_chunks


def _image(tiles: jax.Array, grid: binning.TileGrid, width: int, height: int) -> jax.Array:
    ts = grid.tile_size
    x = tiles.reshape((grid.tiles_y, grid.tiles_x, ts, ts) + tiles.shape[2:])
    x = jnp.swapaxes(x, 1, 2).reshape((grid.tiles_y * ts, grid.tiles_x * ts) + tiles.shape[2:])
    return x[:height, :width]


def _safe_divide(num, den):
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def render_outputs(totals, median, cfg: RasterConfig, grid, cam: Camera, p: Projected, layout,
                   capacity: int, samples: PixelSamples | None) -> RenderOutput:
    if samples is None:
        to_pixels = lambda tiles: _image(tiles, grid, cam.width, cam.height)
    else:
        to_pixels = lambda tiles: tiles.reshape((-1,) + tiles.shape[2:])[samples.index]
    img = to_pixels(totals)
    a = img[..., composite.A]
    background = jnp.asarray(cfg.background, jnp.float32)
    d1, d2 = img[..., composite.M1], img[..., composite.M2]
    radii = jnp.where(p.visible, jnp.max(p.box_max - p.box_min, axis=1) / 2, 0.0)
    stats = RasterStats(
        num_pairs=layout.num_pairs, capacity=jnp.int32(capacity),
        overflow=jnp.maximum(layout.num_pairs - capacity, 0),
        num_visible=jnp.sum(p.visible).astype(jnp.int32),
        num_invalid=jnp.sum(p.invalid).astype(jnp.int32),
        num_culled_near=jnp.sum(p.culled_near).astype(jnp.int32),
        max_tile_pairs=jnp.max(layout.tile_count), num_kept=layout.num_kept.astype(jnp.int32))
    # sum_{i<j} w_i w_j (m_i - m_j)^2 = A D2 - D1^2; rounding can make it slightly negative.
    distortion = jnp.maximum(a * d2 - d1 * d1, 0.0) if cfg.distortion else jnp.zeros_like(a)
    median = to_pixels(median) if cfg.median else jnp.zeros_like(a)
    return RenderOutput(
        rgb=img[..., composite.RGB] + (1.0 - a[..., None]) * background, alpha=a,
        depth=_safe_divide(img[..., composite.Z], a) if cfg.depth_normal else jnp.zeros_like(a),
        median_depth=median, normal=img[..., composite.NORMAL] if cfg.depth_normal else jnp.zeros(a.shape + (3,)),
        distortion=distortion,
        visible=p.visible, radii=radii, stats=stats)


def _empty(cam: Camera, cfg: RasterConfig, samples: PixelSamples | None = None) -> RenderOutput:
    shape = (cam.height, cam.width) if samples is None else samples.index.shape
    zero = jnp.int32(0)
    return RenderOutput(
        rgb=jnp.broadcast_to(jnp.asarray(cfg.background, jnp.float32), shape + (3,)),
        alpha=jnp.zeros(shape), depth=jnp.zeros(shape), median_depth=jnp.zeros(shape),
        normal=jnp.zeros(shape + (3,)), distortion=jnp.zeros(shape), visible=jnp.zeros((0,), bool),
        radii=jnp.zeros((0,)), stats=RasterStats(zero, zero, zero, zero, zero, zero, zero, zero))


def project_surfels(s: Surfels, cam: Camera, cfg: RasterConfig, means2d_probe: jax.Array | None = None) -> Projected:
    """The surfels projected as a render projects them (float32, the config's near plane, SH bands
    and low-pass filter)."""
    s = _as_surfels(s)
    return project(s, cam, cfg.near, _sh_degree(s, cfg), cfg.lowpass_filter, means2d_probe)


def compositor_static(cfg: RasterConfig, width: int, height: int, samples: PixelSamples | None = None):
    """The tile grid and the compositor's static settings of a render."""
    grid = binning.TileGrid.for_image(width, height, cfg.tile_size)
    return grid, composite.Static(grid.tiles_x, grid.tile_size, grid.num_tiles, cfg.near, cfg.far,
                                  cfg.lowpass_filter, cfg.batch_chunks, cfg.median, cfg.distortion,
                                  cfg.depth_normal, 0 if samples is None else samples.slots, cfg.backward_skip)


def bin_projected(p: Projected, cam: Camera, cfg: RasterConfig, capacity: int,
                  samples: PixelSamples | None = None):
    """The tile grid, the compositor's static settings and the binned pairs of a projection."""
    grid, st = compositor_static(cfg, cam.width, cam.height, samples)
    layout = binning.bin_pairs(p, cam.width, cam.height, grid, capacity, cfg.chunk_size,
                               _num_chunks(capacity, grid, cfg), cfg.bounds == "tight",
                               None if samples is None else samples.boxes, cfg.sort)
    return grid, st, layout


def chunk_surfels(layout: binning.Layout, cfg: RasterConfig, capacity: int):
    """Each chunk's surfels and which of its slots hold a pair, (W, K) both."""
    pair = layout.chunk_start[:, None] + jnp.arange(cfg.chunk_size)[None]
    valid = jnp.arange(cfg.chunk_size)[None] < layout.chunk_count[:, None]
    return layout.pair_surfel[jnp.clip(pair, 0, capacity - 1)], valid


def rasterize(s: Surfels, cam: Camera, cfg: RasterConfig, capacity: int,
              means2d_probe: jax.Array | None = None, tile_slots: int | None = None,
              samples: PixelSamples | None = None) -> RenderOutput:
    """Render with a static pair capacity; pairs beyond it are counted in stats.overflow.

    `tile_slots` is the dense baseline's per-tile capacity (default: enough for any tile).
    With `samples`, every per-pixel output is per sample point instead, (N,) or (N, 3).
    """
    if samples is not None:
        if cfg.backend != "tiled" or cfg.compositor != "carried":
            raise ValueError("sample-point renders need the tiled backend's carried compositor")
        if samples.grid != (cam.width, cam.height, cfg.tile_size):
            raise ValueError(f"the samples were grouped for (width, height, tile size) {samples.grid}, "
                             f"the render is {(cam.width, cam.height, cfg.tile_size)}")
    if s.means.shape[0] == 0:
        return _empty(cam, cfg, samples)
    if samples is not None:
        samples = jax.tree_util.tree_map(jnp.asarray, samples)
    p = project_surfels(s, cam, cfg, means2d_probe)
    grid, st, layout = bin_projected(p, cam, cfg, capacity, samples)
    if cfg.backend == "dense":
        slots = tile_slots or min(s.means.shape[0], capacity)
        starts = jnp.cumsum(layout.tile_count) - layout.tile_count
        pair_valid = jnp.arange(capacity) < layout.num_pairs
        totals, median = naive.composite_dense(st, _chunk_params(p, layout.pair_surfel), pair_valid,
                                               slots, starts, layout.tile_count)
    else:
        surfel, valid = chunk_surfels(layout, cfg, capacity)
        if cfg.compositor == "carried":
            totals, median = carried.composite_carried(st, carried.pair_table(p), surfel, valid, layout.chunk_tile,
                                                       layout.chunk_first, None if samples is None else samples.offsets)
        else:
            totals, median = composite.composite(st, _chunk_params(p, surfel), valid, layout.chunk_tile,
                                                 layout.chunk_first, cfg.backward)
    out = render_outputs(totals, median, cfg, grid, cam, p, layout, capacity, samples)
    if cfg.on_overflow == "raise" and isinstance(out.stats.num_pairs, jax.core.Tracer):
        jax.debug.callback(_raise_on_overflow, out.stats.num_pairs, capacity)
    return out


def _raise_on_overflow(num_pairs, capacity):
    if int(num_pairs) > capacity:
        raise RasterOverflowError(
            f"the render needs {int(num_pairs)} tile-surfel pairs but the pair capacity is {capacity}; "
            f"pass RasterConfig(pair_capacity={capacity_bucket(int(num_pairs))}) or more, or render "
            f"eagerly with pair_capacity=None to size it automatically")


rasterize_jit = jax.jit(rasterize, static_argnames=("cfg", "capacity", "tile_slots"))  # render's compiled rasterizer


def _count_pairs(s: Surfels, cam: Camera, cfg: RasterConfig, points: bool = False) -> tuple[jax.Array, jax.Array]:
    """Exact (total pairs, pairs in the fullest tile), without building the pair list; `points`
    for a sample-point render."""
    grid = binning.TileGrid.for_image(cam.width, cam.height, cfg.tile_size)
    p = project(s, cam, cfg.near, 0, cfg.lowpass_filter)
    return binning.count_pairs(p, cam.width, cam.height, grid, cfg.bounds == "tight", points)


count_pairs = jax.jit(_count_pairs, static_argnames=("cfg", "points"))


def _is_traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def render(s: Surfels, cam: Camera, cfg: RasterConfig | None = None, *,
           means2d_probe: jax.Array | None = None, samples: PixelSamples | None = None) -> RenderOutput:
    """Render surfels from a camera: rgb, alpha, depths, normals, distortion and binning stats.

    Differentiable in every Surfels field; works under jax.jit and jax.vmap (there give
    `cfg.pair_capacity`, or a default guess is used and an overflow raises or is reported
    per `cfg.on_overflow`). Eagerly, the capacity is sized from an exact pair count, so a
    render never loses a pair and recompiles only when a capacity bucket grows.
    `samples` (`samples.pixel_samples`): render only those image points, (N,) outputs.

    Args:
        s: the surfels (host or device arrays; cast to float32).
        cam: the camera (its width and height size the image).
        cfg: rasterizer settings; None uses `RasterConfig()`.
        means2d_probe: optional (N,2) zeros added to the projected centres, so that a
            gradient with respect to it gives the screen-space gradients densification uses.
        samples: optional sample points to render instead of the full image.

    Returns:
        RenderOutput: (H,W,...) images (or (N,...) per sample point) of rgb, alpha, depth,
        median_depth, normal and distortion, the (N,) visible mask and radii, and the
        binning stats.

    Raises:
        RasterOverflowError: when more tile-surfel pairs are needed than the capacity allows
            (under jit with `on_overflow="raise"`).
    """
    cfg = RasterConfig() if cfg is None else cfg
    s = _as_surfels(s)
    if _is_traced((s, cam, means2d_probe, samples)):
        capacity = cfg.pair_capacity or default_capacity(s.means.shape[0], cam, cfg)
        return rasterize(s, cam, cfg, capacity, means2d_probe, samples=samples)
    if s.means.shape[0] == 0:
        return _empty(cam, cfg, samples)
    needed, fullest = (int(x) for x in count_pairs(s, cam, binning_config(cfg), samples is not None))
    capacity = eager_capacity(max(needed, cfg.pair_capacity or 0),
                              (s.means.shape[0], s.sh_degree, cam.width, cam.height, cfg, samples is not None))
    slots = max(32, 1 << max(fullest - 1, 0).bit_length()) if cfg.backend == "dense" else None
    out = rasterize_jit(s, cam, cfg, capacity, means2d_probe, slots, samples)
    if int(out.stats.overflow):  # the count is exact, so this is a bug: never return a partial image
        raise RasterOverflowError(f"pair count {needed} disagreed with the render ({int(out.stats.num_pairs)})")
    return out


# The pair capacity eager renders of one scene, size and setting last compiled for: a camera moving
# through a scene needs a different count every frame, and a capacity per frame's bucket would
# compile again each time the count crosses one (100k surfels at 640x480: 7 s a stall).
_EAGER_CAPACITY: dict[tuple, int] = {}


def eager_capacity(needed: int, key: tuple) -> int:
    """The capacity an eager render uses for `needed` pairs: the one already compiled for `key`
    when it fits (and is at most 4x the need), else the bucket of 1.5x the need, so a count that
    keeps growing recompiles a few times, not at every bucket; each recompile is logged."""
    have = _EAGER_CAPACITY.get(key)
    if have is not None and needed <= have <= 4 * max(needed, MIN_CAPACITY):
        return have
    capacity = capacity_bucket(needed if have is None else int(1.5 * needed))
    if have is not None:
        log.info("render: %d tile-surfel pairs needed, the compiled buffer holds %d; compiling for %d", needed, have,
                 capacity)
    _EAGER_CAPACITY[key] = capacity
    return capacity


def capacity_for_views(s: Surfels, cameras, cfg: RasterConfig | None = None) -> int | None:
    """One pair capacity that fits every camera's exact pair count (None without cameras or
    surfels): eager renders of many views with it compile once, where sizing each view alone
    compiles again whenever a view needs a larger capacity bucket."""
    cfg = RasterConfig() if cfg is None else cfg
    s = _as_surfels(s)
    if s.means.shape[0] == 0:
        return None
    counts = [int(count_pairs(s, cam, binning_config(cfg))[0]) for cam in cameras]
    return capacity_bucket(max(counts)) if counts else None


def binning_config(cfg: RasterConfig) -> RasterConfig:
    """The part of `cfg` that binning depends on (count_pairs takes it): only the fields that
    change binning matter, so one compiled counter serves all variants."""
    return RasterConfig(near=cfg.near, far=cfg.far, tile_size=cfg.tile_size, lowpass_filter=cfg.lowpass_filter,
                        bounds=cfg.bounds)


def default_capacity(num_surfels: int, cam: Camera, cfg: RasterConfig) -> int:
    """A guess for traced renders without an explicit capacity: 8 tiles per surfel."""
    grid = binning.TileGrid.for_image(cam.width, cam.height, cfg.tile_size)
    return capacity_bucket(min(8 * num_surfels + grid.num_tiles, num_surfels * grid.num_tiles))
