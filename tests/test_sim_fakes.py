"""Analytic stand-ins for the rasterizer used by the sim tests (no surfels needed)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class FakeOutput(NamedTuple):
    rgb: jax.Array
    alpha: jax.Array
    depth: jax.Array
    median_depth: jax.Array
    normal: jax.Array
    stats: object = None


def box_room_renderer(lo=(-4.0, -3.0, -1.0), hi=(5.0, 6.0, 3.0), hole=None):
    """render_fn(surfels, camera) for a camera inside an axis-aligned box: exact z-depth
    of the walls. `hole` = (axis, sign) makes that wall transparent (alpha 0)."""
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)

    def render(surfels, cam):
        H, W = cam.height, cam.width
        jj, ii = jnp.meshgrid(jnp.arange(W) + 0.5, jnp.arange(H) + 0.5)
        pix = jnp.stack([jj, ii, jnp.ones_like(jj)], -1)
        d_cam = pix @ jnp.linalg.inv(cam.K).T              # z = 1: t is the z-depth
        R, t = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
        origin = -R.T @ t
        d = d_cam @ R                                      # world directions (rows)
        safe = jnp.where(jnp.abs(d) < 1e-12, 1e-12, d)
        t_axis = jnp.where(d > 0, (hi - origin) / safe, (lo - origin) / safe)
        axis = jnp.argmin(t_axis, -1)
        z = jnp.min(t_axis, -1)
        alpha = jnp.ones_like(z)
        if hole is not None:
            ax, sign = hole
            hit_sign = jnp.take_along_axis(d, axis[..., None], -1)[..., 0] * sign > 0
            alpha = jnp.where((axis == ax) & hit_sign, 0.0, 1.0)
        rgb = jnp.broadcast_to((0.25 + 0.25 * axis)[..., None], (H, W, 3)).astype(jnp.float32)
        return FakeOutput(rgb * alpha[..., None], alpha, z * alpha, z * alpha, jnp.zeros((H, W, 3)))

    return render


def analytic_box_ranges(origin, dirs, lo, hi):
    import numpy as np

    lo, hi, o = (np.asarray(v, np.float64) for v in (lo, hi, origin))
    d = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    t = np.where(d > 0, (hi - o) / d, (lo - o) / d)
    return t.min(-1)
