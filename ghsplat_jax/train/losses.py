"""Image losses and metrics (L1, SSIM, PSNR) and the 2DGS geometry regularisers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_C1 = 0.01**2
_C2 = 0.03**2


def l1(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.mean(jnp.abs(a - b))


def psnr(a: jax.Array, b: jax.Array) -> jax.Array:
    """PSNR in dB of images in [0, 1]."""
    return -10.0 * jnp.log10(jnp.maximum(jnp.mean((a - b) ** 2), 1e-20))


def _gaussian_kernel(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    x = np.arange(size) - size // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


def _blur_last_axis(x: jax.Array, block: int = 32) -> jax.Array:
    """1D Gaussian blur along the last axis with zero padding, as a banded matmul: the axis is
    cut into blocks, each with its window of neighbours (block + 2r), times one (block + 2r,
    block) band matrix. XLA:CPU runs this about 10x faster than a 1-channel convolution and its
    gradient is matmuls too (a chain of shifted adds gets re-fused into every consumer)."""
    kernel = _gaussian_kernel()
    r = len(kernel) // 2
    n = x.shape[-1]
    nb = -(-n // block)
    lead = x.shape[:-1]
    xp = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(r, nb * block - n + block + r)])
    blocks = lambda start: xp[..., start:start + nb * block].reshape(lead + (nb, block))
    window = jnp.concatenate([blocks(0)[..., :r], blocks(r), blocks(block + r)[..., :r]], axis=-1)
    offset = np.arange(block + 2 * r)[:, None] - np.arange(block)[None] - r
    band = np.where(np.abs(offset) <= r, kernel[np.clip(offset + r, 0, 2 * r)], 0.0).astype(np.float32)
    return (window @ jnp.asarray(band)).reshape(lead + (nb * block,))[..., :n]


def _blur(x: jax.Array) -> jax.Array:
    """Separable Gaussian blur of (..., H, W) planes with zero padding (as the 3DGS SSIM)."""
    x = _blur_last_axis(x)
    return jnp.swapaxes(_blur_last_axis(jnp.swapaxes(x, -1, -2)), -1, -2)


def ssim_map(a: jax.Array, b: jax.Array) -> jax.Array:
    """Per-pixel SSIM (H,W,C) of (H,W,C) images; 11x11 Gaussian window, sigma 1.5."""
    a = jnp.moveaxis(a, -1, 0)
    b = jnp.moveaxis(b, -1, 0)
    blurred = _blur(jnp.concatenate([a, b, a * a, b * b, a * b]))
    mu_a, mu_b, aa, bb, ab = jnp.split(blurred, 5)
    var_a = aa - mu_a**2
    var_b = bb - mu_b**2
    cov = ab - mu_a * mu_b
    num = (2 * mu_a * mu_b + _C1) * (2 * cov + _C2)
    den = (mu_a**2 + mu_b**2 + _C1) * (var_a + var_b + _C2)
    return jnp.moveaxis(num / den, 0, -1)


def ssim(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.mean(ssim_map(a, b))


def depth_to_points(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> jax.Array:
    """World points (H,W,3) of a z-depth map, through pixel centres (j + 0.5, i + 0.5)."""
    h, w = depth.shape
    jj, ii = jnp.meshgrid(jnp.arange(w, dtype=jnp.float32) + 0.5, jnp.arange(h, dtype=jnp.float32) + 0.5)
    pix = jnp.stack([jj, ii, jnp.ones_like(jj)], axis=-1)
    rays = pix @ jnp.linalg.inv(K).T  # z = 1
    cam = rays * depth[..., None]
    R, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    return (cam - t) @ R  # R^T (p - t), row-vector form


def depth_to_normal(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> jax.Array:
    """World normals (H,W,3) from finite differences of back-projected points, facing the
    camera; zero on the one-pixel border and where the differences vanish."""
    p = depth_to_points(depth, K, world_to_cam)
    d_row = p[2:, 1:-1] - p[:-2, 1:-1]
    d_col = p[1:-1, 2:] - p[1:-1, :-2]
    n = jnp.cross(d_row, d_col)  # (down x right) = toward the camera
    sq = jnp.sum(n * n, axis=-1, keepdims=True)
    ok = sq > 1e-20
    n = jnp.where(ok, n, 0.0) / jnp.sqrt(jnp.where(ok, sq, 1.0))  # double where: finite gradients
    return jnp.pad(n, ((1, 1), (1, 1), (0, 0)))


def normal_consistency(rendered_normal: jax.Array, depth_normal: jax.Array, alpha: jax.Array) -> jax.Array:
    """2DGS normal loss: mean over pixels of 1 - <rendered, depth normal x alpha>; alpha is
    not differentiated (the prior must not push coverage)."""
    target = depth_normal * jax.lax.stop_gradient(alpha)[..., None]
    return jnp.mean(1.0 - jnp.sum(rendered_normal * target, axis=-1))
