"""Rasterizer configuration and output pytrees."""

from __future__ import annotations

import dataclasses

import jax


class RasterOverflowError(RuntimeError):
    """More tile-surfel pairs than the static pair capacity; nothing is ever dropped quietly.

    Args:
        *args: the message, as for any exception (it gives the pair count and the capacity).

    Returns:
        The exception, raised by `render` (eagerly, or under jit with `on_overflow="raise"`).
    """


@dataclasses.dataclass(frozen=True)
class RasterConfig:
    """Static rasterizer settings (hashable, so they can be jit static arguments).

    Args:
        near, far, background, tile_size, bounds, lowpass_filter, chunk_size, batch_chunks,
            part_batch_chunks, compositor, backward, backward_skip, backend, median,
            distortion, depth_normal, sh_degree, sort, pair_capacity, on_overflow: the
            fields below, each described where it is declared; all keywords, all defaulted.

    Returns:
        A frozen, validated configuration (a bad value raises ValueError on construction).
    """

    near: float = 0.2                      # cull centres and skip hits nearer than this (metres)
    far: float = 100.0                     # far plane of the NDC depth used by the distortion term
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rgb behind the last surfel
    # Defaults are the fastest exact choice measured on a 2-core CPU (benchmarks/speed/raster_ablation.py):
    # 8-px tiles waste fewer pixel evaluations than 2DGS's 16; batches of 128 chunks beat 64 by 5%
    # per fern training step (loop overhead against the per-pixel planes' cache footprint) and tie
    # at the demo's 192x144.
    tile_size: int = 8                     # 8, 16 or 32 pixel tiles
    bounds: str = "tight"                  # "tight" (opacity-aware box and exact ellipse-tile test) or
                                           # "box3" (the 3-sigma box, as 2DGS: the ablation)
    lowpass_filter: bool = True            # 2DGS screen-space filter rho = min(rho3, 2|x - c|^2)
    chunk_size: int = 16                   # surfels blended per vectorised step within a tile
    batch_chunks: int = 128                # chunks evaluated together (cache footprint vs. loop overhead)
    # The batch of each part when the carried compositor walks in parts from threads (the CPU
    # training step, train/parted_step.py). Measured, not derived: 32 made a fern step at 1,250
    # 1.14x and a lego step at 30,000 1.08x faster than 128 (interleaved, `benchmarks/speed/train_speed.py
    # --compare partbatch`). Likely cause: with one core idle XLA spreads a large batch's ops over
    # both, and with both walking it cannot, so only the larger planes' cache cost is left.
    part_batch_chunks: int = 32
    compositor: str = "carried"            # "carried" (one evaluation per pair, transmittance carried
                                           # across batches) or "logspace" (two-pass, the ablation)
    backward: str = "custom_vjp"           # "custom_vjp" (analytic) or "autodiff" (checkpointed; logspace only)
    backward_skip: str = "pairs"           # what the carried backward leaves out, all exactly: "pairs" that
                                           # cannot change an output (alpha > 0 only at pixels closed before
                                           # them), whole "chunks" of such pairs, or "none"
    backend: str = "tiled"                 # "tiled" (this rasterizer) or "dense" (naive per-tile baseline)
    median: bool = True                    # compute median_depth (False: zeros, and faster)
    distortion: bool = True                # compute distortion (False: zeros, and faster)
    depth_normal: bool = True              # compute depth and normal (False: zeros, and faster)
    sh_degree: int | None = None           # active SH bands; None uses every band the data has
    sort: str = "auto"                     # binning's sorts: "auto" (NumPy's for large sorts on a CPU backend,
                                           # through a host callback: 16x faster than XLA:CPU's, but XLA's
                                           # persistent compilation cache skips such programs) or "xla"
    pair_capacity: int | None = None       # static tile-surfel pair buffer; None sizes it automatically
    on_overflow: str = "raise"             # under jit: "raise" a runtime error or "report" in stats only

    def __post_init__(self):
        if self.tile_size not in (8, 16, 32):
            raise ValueError(f"tile_size must be 8, 16 or 32, got {self.tile_size}")
        if self.backward not in ("custom_vjp", "autodiff"):
            raise ValueError(f"backward must be 'custom_vjp' or 'autodiff', got {self.backward!r}")
        if self.bounds not in ("tight", "box3"):
            raise ValueError(f"bounds must be 'tight' or 'box3', got {self.bounds!r}")
        if self.compositor not in ("carried", "logspace"):
            raise ValueError(f"compositor must be 'carried' or 'logspace', got {self.compositor!r}")
        if self.backward_skip not in ("pairs", "chunks", "none"):
            raise ValueError(f"backward_skip must be 'pairs', 'chunks' or 'none', got {self.backward_skip!r}")
        if self.backward == "autodiff" and self.compositor != "logspace":
            raise ValueError("backward='autodiff' differentiates the logspace compositor: "
                             "set compositor='logspace' with it")
        if self.backend not in ("tiled", "dense"):
            raise ValueError(f"backend must be 'tiled' or 'dense', got {self.backend!r}")
        if self.sort not in ("auto", "xla"):
            raise ValueError(f"sort must be 'auto' or 'xla', got {self.sort!r}")
        if self.on_overflow not in ("raise", "report"):
            raise ValueError(f"on_overflow must be 'raise' or 'report', got {self.on_overflow!r}")
        if self.chunk_size < 1 or self.batch_chunks < 1 or self.part_batch_chunks < 1:
            raise ValueError("chunk_size, batch_chunks and part_batch_chunks must be positive")
        if not self.near > 0 or not self.far > self.near:
            raise ValueError(f"need 0 < near < far, got near={self.near}, far={self.far}")
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RasterStats:
    """Binning statistics of one render (int32 scalars)."""

    num_pairs: jax.Array        # tile-surfel pairs needed (candidates from the opacity-aware boxes)
    capacity: jax.Array         # pairs the static buffer holds
    overflow: jax.Array         # pairs that did not fit (the render is incomplete when > 0)
    num_visible: jax.Array      # surfels touching at least one tile
    num_invalid: jax.Array      # non-finite parameters or zero quaternion: culled
    num_culled_near: jax.Array  # centre at or behind the near plane
    max_tile_pairs: jax.Array   # most surfels overlapping one tile
    num_kept: jax.Array         # pairs left after the exact tile test (the ones composited)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderOutput:
    """Per-pixel outputs (H,W,...), or per sample point (N,...) for a `samples` render.

    Args:
        rgb, alpha, depth, median_depth, normal, distortion, visible, radii, stats: the
            fields below, as `render` fills them.

    Returns:
        A pytree of arrays (jit and vmap carry it through); its fields are the render's outputs.
    """

    rgb: jax.Array           # (H,W,3) over the background
    alpha: jax.Array         # (H,W) accumulated opacity
    depth: jax.Array         # (H,W) expected z-depth sum(w z) / alpha (0 where alpha = 0)
    median_depth: jax.Array  # (H,W) depth of the surfel where accumulated opacity crosses 0.5
    normal: jax.Array        # (H,W,3) world-frame normals facing the camera, alpha-weighted
    distortion: jax.Array    # (H,W) sum_{i<j} w_i w_j (m_i - m_j)^2 of NDC depths m
    visible: jax.Array       # (N,) surfel touches at least one tile
    radii: jax.Array         # (N,) half-extent of the screen box in pixels (0 when culled)
    stats: RasterStats
