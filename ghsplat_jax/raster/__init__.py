"""The 2DGS tile rasterizer: project -> bin -> sort -> composite, with a custom VJP,
a checkpointed-autodiff alternative, a naive dense baseline and a float64 reference."""

from ghsplat_jax.raster.config import RasterConfig, RasterOverflowError, RasterStats, RenderOutput
from ghsplat_jax.raster.render import capacity_bucket, rasterize, render

__all__ = ["RasterConfig", "RasterOverflowError", "RasterStats", "RenderOutput", "capacity_bucket",
           "rasterize", "render"]
