from ghsplat_jax.core.camera import Camera, intrinsics, look_at
from ghsplat_jax.core.surfels import Surfels, concatenate, make_surfels

__all__ = ["Camera", "Surfels", "concatenate", "intrinsics", "look_at", "make_surfels"]
