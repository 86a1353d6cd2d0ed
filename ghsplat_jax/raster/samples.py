"""Render at arbitrary sample points of the image plane instead of every pixel centre.

A sensor that reads a few rays per tile (a LiDAR's beams on its faces) only needs the surfels
evaluated at those rays. Samples are grouped by the tile they fall in, each tile holding up to
`slots` of them: the compositor evaluates a tile's slots where it would evaluate its pixels,
binning drops tiles without samples, and the exact tile test uses the box around a tile's
samples rather than the whole tile. A sample at a pixel centre (j + 0.5, i + 0.5) renders
exactly what the image render gives at pixel (i, j).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from ghsplat_jax.raster.binning import TileGrid


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PixelSamples:
    """Sample points of one image, grouped by tile (NumPy or jax arrays; stackable per camera)."""

    offsets: np.ndarray   # (T, S, 2) sample x, y relative to its tile's corner; spare slots repeat slot 0
    boxes: np.ndarray     # (T, 4) min x, min y, max x, max y of a tile's samples (empty tile: max < min)
    index: np.ndarray     # (N,) int32 flat slot tile * S + slot of each sample
    grid: tuple[int, int, int] = dataclasses.field(metadata=dict(static=True))  # image width, height, tile size

    @property
    def slots(self) -> int:
        return self.offsets.shape[-2]


def pixel_samples(xy: np.ndarray, width: int, height: int, tile_size: int, slots: int | None = None) -> PixelSamples:
    """Group (N, 2) continuous image coordinates (pixel centres at j + 0.5) by tile.

    `slots` (per tile) defaults to the fullest tile's count rounded up to a multiple of 8; pass
    a larger one to stack layouts of several cameras. Samples must lie in [0, width] x [0, height].
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) == 0:
        raise ValueError("pixel_samples needs at least one sample point")
    if not np.all(np.isfinite(xy)) or xy[:, 0].min() < 0 or xy[:, 1].min() < 0 \
            or xy[:, 0].max() > width or xy[:, 1].max() > height:
        raise ValueError(f"sample points must be finite and inside the {width}x{height} image")
    grid = TileGrid.for_image(width, height, tile_size)
    col = np.minimum(xy[:, 0] // tile_size, grid.tiles_x - 1).astype(np.int64)
    row = np.minimum(xy[:, 1] // tile_size, grid.tiles_y - 1).astype(np.int64)
    tile = row * grid.tiles_x + col
    order = np.argsort(tile, kind="stable")
    counts = np.bincount(tile, minlength=grid.num_tiles)
    fullest = int(counts.max())
    slots = slots or -(-fullest // 8) * 8
    if slots < fullest:
        raise ValueError(f"a tile holds {fullest} samples but only {slots} slots were asked for")
    slot = np.empty(len(xy), np.int64)
    slot[order] = np.arange(len(xy)) - (np.cumsum(counts) - counts)[tile[order]]
    corner = np.stack([tile % grid.tiles_x, tile // grid.tiles_x], axis=1) * tile_size
    offsets = np.full((grid.num_tiles, slots, 2), tile_size / 2.0)
    offsets[tile, slot] = xy - corner
    first = np.flatnonzero(counts)
    offsets[first] = np.where(np.arange(slots)[None, :, None] < counts[first, None, None],
                              offsets[first], offsets[first, :1])        # spare slots repeat slot 0
    boxes = np.tile([np.inf, np.inf, -np.inf, -np.inf], (grid.num_tiles, 1))
    np.minimum.at(boxes[:, :2], tile, xy)
    np.maximum.at(boxes[:, 2:], tile, xy)
    boxes[counts == 0] = (0.0, 0.0, -1.0, -1.0)
    return PixelSamples(offsets.astype(np.float32), boxes.astype(np.float32), (tile * slots + slot).astype(np.int32),
                        (width, height, tile_size))


def stack(layouts: list[PixelSamples]) -> PixelSamples:
    """One layout per camera stacked along a new leading axis (same image size, tiles and slots);
    shorter index lists are padded with slot 0, whose values the caller ignores."""
    if len({(s.grid, s.slots) for s in layouts}) != 1:
        raise ValueError("stacked sample layouts need the same image size, tile size and slots")
    n = max(len(s.index) for s in layouts)
    return PixelSamples(np.stack([s.offsets for s in layouts]), np.stack([s.boxes for s in layouts]),
                        np.stack([np.pad(s.index, (0, n - len(s.index))) for s in layouts]), layouts[0].grid)
