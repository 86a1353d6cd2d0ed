"""Image losses and metrics (L1, SSIM, PSNR) and the 2DGS geometry regularisers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32

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
    block) band matrix. XLA:CPU runs this about 10x faster than a 1-channel convolution."""
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
    return jnp.matmul(window, jnp.asarray(band), precision=FLOAT32).reshape(lead + (nb * block,))[..., :n]


def _blur_rows(x: jax.Array) -> jax.Array:
    """1D Gaussian blur along the second-to-last axis with zero padding, as a sum of shifted
    row slices: each slice is contiguous, so this needs no transpose."""
    kernel = _gaussian_kernel()
    r = len(kernel) // 2
    n, axis = x.shape[-2], x.ndim - 2
    xp = jnp.pad(x, [(0, 0)] * axis + [(r, r), (0, 0)])
    return sum(float(w) * jax.lax.slice_in_dim(xp, k, k + n, axis=axis) for k, w in enumerate(kernel))


@jax.custom_vjp
def _blur(x: jax.Array) -> jax.Array:
    """Separable Gaussian blur of (..., H, W) planes with zero padding (as the 3DGS SSIM).
    The kernel is symmetric and the padding zero, so the blur is self-adjoint: its gradient is
    the blur of the cotangent, which costs what the forward does (autodiff's transposed
    windows and slices cost about twice that, measured)."""
    return _blur_rows(_blur_last_axis(x))


_blur.defvjp(lambda x: (_blur(x), None), lambda _, g: (_blur(g),))


def ssim_map(a: jax.Array, b: jax.Array) -> jax.Array:
    """Per-pixel SSIM (H,W,C) of (H,W,C) images; 11x11 Gaussian window, sigma 1.5."""
    a = jnp.moveaxis(a, -1, 0)
    b = jnp.moveaxis(b, -1, 0)
    # The statistics of each image blurred apart: when only `a` is differentiated (a render
    # against its photo), the gradient blurs 9 planes instead of 15.
    mu_a, aa, ab = jnp.split(_blur(jnp.concatenate([a, a * a, a * b])), 3)
    mu_b, bb = jnp.split(_blur(jnp.concatenate([b, b * b])), 2)
    var_a = aa - mu_a**2
    var_b = bb - mu_b**2
    cov = ab - mu_a * mu_b
    num = (2 * mu_a * mu_b + _C1) * (2 * cov + _C2)
    den = (mu_a**2 + mu_b**2 + _C1) * (var_a + var_b + _C2)
    return jnp.moveaxis(num / den, 0, -1)


def ssim(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.mean(ssim_map(a, b))


def _point_planes(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> list[jax.Array]:
    """World x, y, z planes (H,W each) of a z-depth map, through pixel centres (j + 0.5, i + 0.5).
    Plane by plane: XLA:CPU runs (H,W,3) arrays' 3-wide products, slices and their gradients'
    pads as separate strided passes (about 50 thread-ms of a fern step, measured)."""
    h, w = depth.shape
    x = jnp.arange(w, dtype=jnp.float32)[None] + 0.5
    y = jnp.arange(h, dtype=jnp.float32)[:, None] + 0.5
    k_inv = jnp.linalg.inv(K)
    cam = [(k_inv[c, 0] * x + k_inv[c, 1] * y + k_inv[c, 2]) * depth for c in range(3)]  # rays at z = 1
    R, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    return [sum(R[k, c] * (cam[k] - t[k]) for k in range(3)) for c in range(3)]  # R^T (p - t)


def depth_to_points(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> jax.Array:
    """World points (H,W,3) of a z-depth map, through pixel centres (j + 0.5, i + 0.5)."""
    return jnp.stack(_point_planes(depth, K, world_to_cam), axis=-1)


def _normal_planes(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> list[jax.Array]:
    """World normal planes (H,W each) of `depth_to_normal`."""
    p = _point_planes(depth, K, world_to_cam)
    d_row = [c[2:, 1:-1] - c[:-2, 1:-1] for c in p]
    d_col = [c[1:-1, 2:] - c[1:-1, :-2] for c in p]
    n = [d_row[(i + 1) % 3] * d_col[(i + 2) % 3] - d_row[(i + 2) % 3] * d_col[(i + 1) % 3]
         for i in range(3)]  # (down x right) = toward the camera
    sq = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    ok = sq > 1e-20
    scale = jax.lax.rsqrt(jnp.where(ok, sq, 1.0))  # double where: finite gradients
    return [jnp.pad(jnp.where(ok, c * scale, 0.0), 1) for c in n]


def depth_to_normal(depth: jax.Array, K: jax.Array, world_to_cam: jax.Array) -> jax.Array:
    """World normals (H,W,3) from finite differences of back-projected points, facing the
    camera; zero on the one-pixel border and where the differences vanish."""
    return jnp.stack(_normal_planes(depth, K, world_to_cam), axis=-1)


def normal_consistency(rendered_normal: jax.Array, depth_normal: jax.Array, alpha: jax.Array,
                       coverage: jax.Array | None = None) -> jax.Array:
    """2DGS normal loss: mean over pixels of 1 - <rendered, depth normal x alpha>, the alpha of
    the target held constant.

    `coverage` (H,W), the image's own alpha where it has one, weighs each pixel's term. The
    rendered normal's length is the rendered alpha, so unweighted the term rewards any opacity
    at all: on an object photographed against an empty background it grows opaque sheets of
    background colour, which then hide the object from new viewpoints (hbb1/2d-gaussian-splatting
    issue 85). The pixel count stays the divisor, so covered pixels keep the 2DGS gradient."""
    target = depth_normal * jax.lax.stop_gradient(alpha)[..., None]
    error = 1.0 - jnp.sum(rendered_normal * target, axis=-1)
    return jnp.mean(error if coverage is None else coverage * error)
