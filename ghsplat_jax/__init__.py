"""GreenhouseSplat-JAX: 2D Gaussian surfels for greenhouse rows, in JAX.

    import ghsplat_jax as gs
    s = gs.load_ply("point_cloud.ply")
    out = gs.render(s, gs.Camera(K=K, world_to_cam=w2c, width=W, height=H), gs.RasterConfig())
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what type checkers see; at run time __getattr__ loads each on first use
    from ghsplat_jax.core import Camera as Camera
    from ghsplat_jax.core import Surfels as Surfels
    from ghsplat_jax.core import concatenate as concatenate
    from ghsplat_jax.core import intrinsics as intrinsics
    from ghsplat_jax.core import look_at as look_at
    from ghsplat_jax.core import make_surfels as make_surfels
    from ghsplat_jax.data.ply import PlyError as PlyError
    from ghsplat_jax.data.ply import load_ply as load_ply
    from ghsplat_jax.data.ply import save_ply as save_ply
    from ghsplat_jax.raster import RasterConfig as RasterConfig
    from ghsplat_jax.raster import RasterOverflowError as RasterOverflowError
    from ghsplat_jax.raster import RenderOutput as RenderOutput
    from ghsplat_jax.raster import render as render

# The public API, loaded on first use (PEP 562): importing a JAX-free module of the package
# (io_utils, curves, config_values) does not start JAX, so report scripts and `--check`s run without it.
_EXPORTS = {
    "Camera": "ghsplat_jax.core", "Surfels": "ghsplat_jax.core", "concatenate": "ghsplat_jax.core",
    "intrinsics": "ghsplat_jax.core", "look_at": "ghsplat_jax.core", "make_surfels": "ghsplat_jax.core",
    "PlyError": "ghsplat_jax.data.ply", "load_ply": "ghsplat_jax.data.ply", "save_ply": "ghsplat_jax.data.ply",
    "RasterConfig": "ghsplat_jax.raster", "RasterOverflowError": "ghsplat_jax.raster",
    "RenderOutput": "ghsplat_jax.raster", "render": "ghsplat_jax.raster",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ghsplat_jax' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
