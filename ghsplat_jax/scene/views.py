"""Rendering helpers for scene tools: shape-stable renders and camera rings.

raster.render compiles once per (surfel count, SH degree, pair capacity, image size, config).
Scene tools render many different edits (markers, crops, fused views); padding the count
to a power of two and the SH degree to a fixed value lets them share one compiled program.
Padding surfels sit at the camera centre, so the near-plane cull drops them.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core.surfels import Surfels


def pad_for_render(s: Surfels, camera_center, num: int | None = None, sh_degree: int = 3) -> Surfels:
    """Surfels padded to `num` (default: next power of two >= 4096) and to `sh_degree`."""
    from ghsplat_jax.scene.merge import set_sh_degree

    s = set_sh_degree(s, max(sh_degree, s.sh_degree))
    num = num or max(4096, 1 << max(s.num - 1, 0).bit_length())
    extra = num - s.num
    if extra < 0:
        raise ValueError(f"cannot pad {s.num} surfels to {num}")
    if extra == 0:
        return s
    k = s.sh_rest.shape[1]
    pad = Surfels(
        means=np.broadcast_to(np.asarray(camera_center, np.float32), (extra, 3)),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (extra, 1)),
        log_scales=np.full((extra, 2), -10.0, np.float32),
        opacity_logits=np.full(extra, -30.0, np.float32),
        sh_dc=np.zeros((extra, 3), np.float32), sh_rest=np.zeros((extra, k, 3), np.float32))
    return Surfels(*(np.concatenate([getattr(s, f), getattr(pad, f)]) for f in
                     ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))


def render_stable(s: Surfels, camera, config=None, num: int | None = None, sh_degree: int = 3):
    """raster.render on padded surfels (same image as unpadded; see the module docstring).
    Give `config.pair_capacity` too, or the capacity bucket may still vary between views."""
    from ghsplat_jax.raster import render

    center = np.asarray(camera.center, np.float64)
    return render(pad_for_render(s.to_numpy(), center, num, sh_degree), camera, config)


def orbit_cameras(target, radius: float, heights, count: int, width: int, height: int,
                  fov_x_deg: float = 60.0, up=(0.0, 0.0, 1.0)) -> list:
    """Cameras on circles around `target` (one ring per height offset), looking at it."""
    from ghsplat_jax.core.camera import Camera, intrinsics, look_at

    target = np.asarray(target, np.float64)
    K = intrinsics(width, height, fov_x_deg)
    cams = []
    for h in np.atleast_1d(heights):
        for a in np.linspace(0.0, 2 * np.pi, count, endpoint=False):
            eye = target + np.array([radius * np.cos(a), radius * np.sin(a), h])
            cams.append(Camera(K, look_at(eye, target, up), width, height))
    return cams
