"""GreenhouseSplat-JAX: 2D Gaussian surfels for greenhouse rows, in JAX.

    import ghsplat_jax as gs
    s = gs.load_ply("point_cloud.ply")
    out = gs.render(s, gs.Camera(K=K, world_to_cam=w2c, width=W, height=H), gs.RasterConfig())
"""

from ghsplat_jax.core import Camera, Surfels, concatenate, intrinsics, look_at, make_surfels
from ghsplat_jax.data.ply import PlyError, load_ply, save_ply
from ghsplat_jax.raster import RasterConfig, RasterOverflowError, RenderOutput, render

__all__ = [
    "Camera", "PlyError", "RasterConfig", "RasterOverflowError", "RenderOutput", "Surfels",
    "concatenate", "intrinsics", "load_ply", "look_at", "make_surfels", "render", "save_ply",
]
