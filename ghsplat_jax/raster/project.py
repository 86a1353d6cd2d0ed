"""Per-surfel projection: ray transform, screen box, filter centre, colour and normal.

Follows the 2DGS reference: M = K [s_u t_u | s_v t_v | mu] in camera space; the screen box
and the filter centre come from the dual conic of the 3-sigma ellipse.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ghsplat_jax.core import quaternions, sh
from ghsplat_jax.core.camera import Camera
from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.core.surfels import Surfels

CUTOFF = 3.0                       # box and ellipse at 3 sigma
FILTER_REACH = 3.0 * 0.7071067811865476  # the low-pass filter's reach in pixels (3 sqrt(2)/2)
LOG_SCALE_RANGE = (-25.0, 15.0)    # beyond this scales overflow float32 products


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Projected:
    """What the compositor needs per surfel (all differentiable except the masks)."""

    M: jax.Array          # (N,3,3) ray transform, rows
    center: jax.Array     # (N,2) low-pass filter centre (pixels)
    opacity: jax.Array    # (N,)
    color: jax.Array      # (N,3)
    normal: jax.Array     # (N,3) world frame, facing the camera
    depth: jax.Array      # (N,) view depth of the centre (sort key, filter-branch depth)
    box_min: jax.Array    # (N,2) screen box of the 3-sigma ellipse, pixels (visibility and radii)
    box_max: jax.Array    # (N,2)
    bin_min: jax.Array    # (N,2) opacity-aware box: where alpha can reach 1/255 (binning)
    bin_max: jax.Array    # (N,2)
    conic: jax.Array      # (N,6) the ellipse where alpha >= 1/255: q(d) <= 0, d the offset from `center`
    reach: jax.Array      # (N,) radius of the low-pass filter's disc around `center` where alpha >= 1/255
    bounded: jax.Array    # (N,) bool: the ellipse lies in front of the camera (else no tile test)
    visible: jax.Array    # (N,) bool: valid, in front of near, box on screen
    invalid: jax.Array    # (N,) bool: non-finite parameters or zero quaternion
    culled_near: jax.Array  # (N,) bool


def _finite_rows(x: jax.Array) -> jax.Array:
    return jnp.all(jnp.isfinite(x.reshape(x.shape[0], -1)), axis=1)


def _sum3(x: jax.Array) -> jax.Array:
    """x[:, 0] + x[:, 1] + x[:, 2] of an (N, 3) product: it fuses with the product, where
    jnp.sum over the small axis is a YNN reduction of its own (about 1.3 ms at 100k surfels)."""
    return x[:, 0] + x[:, 1] + x[:, 2]


def _times(A: jax.Array, B: jax.Array) -> jax.Array:
    """A @ B[n] for every n: (3, 3) x (N, 3, k) -> (N, 3, k), written out row by row as scalar
    times (N, k) planes. As an einsum, XLA:CPU runs 100k of these 3x3 products as a batched dot at
    about 3 ms; as broadcast (N, 3, k) products, their transpose sums over the size-3 axis, six
    YNN reductions of 8 ms each in a training step's pull-back (fern, 82k surfels)."""
    return jnp.stack([sum(A[i, j] * B[:, j, :] for j in range(3)) for i in range(3)], axis=1)


def project(s: Surfels, cam: Camera, near: float, sh_degree: int, lowpass_filter: bool,
            means2d_probe: jax.Array | None = None) -> Projected:
    n = s.means.shape[0]
    finite = (_finite_rows(s.means) & _finite_rows(s.quats) & _finite_rows(s.log_scales)
              & jnp.isfinite(s.opacity_logits) & _finite_rows(s.sh_dc) & _finite_rows(s.sh_rest))
    # Non-finite inputs are replaced before any arithmetic so no NaN reaches gradients.
    clean = lambda x, fill=0.0: jnp.where(finite.reshape((n,) + (1,) * (x.ndim - 1)), x, fill)
    means = clean(s.means)
    quat, quat_ok = quaternions.safe_normalize(clean(s.quats))
    scales = jnp.exp(jnp.clip(clean(s.log_scales), *LOG_SCALE_RANGE))
    opacity = jax.nn.sigmoid(clean(s.opacity_logits, -20.0))
    invalid = ~(finite & quat_ok)

    R_world = quaternions.to_rotation_matrix(quat)                 # columns t_u, t_v, n
    R_wc, t_wc = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
    mu_c = jnp.matmul(means, R_wc.T, precision=FLOAT32) + t_wc
    tangents_c = _times(R_wc, R_world[:, :, :2]) * scales[:, None, :]
    local = jnp.concatenate([tangents_c, mu_c[:, :, None]], axis=2)  # [s_u t_u | s_v t_v | mu]
    M = _times(cam.K, local)
    depth = mu_c[:, 2]

    # Dual conic of u^2 + v^2 = CUTOFF^2: C* = M diag(c^2, c^2, -1) M^T.
    center, half, bounded = _ellipse_box(M, jnp.full((n,), CUTOFF**2), depth)
    reach = FILTER_REACH if lowpass_filter else 0.5
    half = jnp.maximum(half, reach)

    safe_depth = jnp.where(jnp.abs(depth) > 1e-12, depth, 1.0)
    projected_mean = M[:, :2, 2] / safe_depth[:, None]
    center = jnp.where(bounded[:, None], center, projected_mean)  # the reference does the same
    # An ellipse that crosses the camera plane projects to an unbounded conic: whole screen.
    big = jnp.float32(1e9)
    box_min = jnp.where(bounded[:, None], center - half, -big)
    box_max = jnp.where(bounded[:, None], center + half, big)

    # Where alpha = opacity exp(-rho / 2) can reach 1/255: rho <= rho_max = 2 ln(255 opacity). As
    # rho = min(rho3, rho2), that region is the ellipse u^2 + v^2 <= rho_max joined with the
    # filter's disc 2 |x - c|^2 <= rho_max. Candidate tiles come from its box capped at the
    # 3-sigma ellipse (the reference's extent); the tile test then drops a candidate only where
    # alpha stays below 1/255 at every pixel, so the image equals the 3-sigma binning's.
    rho_max = jnp.maximum(2.0 * jnp.log(jnp.maximum(255.0 * opacity, 1e-30)), 0.0)
    cut2 = jnp.minimum(rho_max, CUTOFF**2)
    tight_center, tight_half, tight_bounded = _ellipse_box(M, cut2, depth)
    tight_half = jnp.maximum(tight_half, 0.5)
    disc = (lambda r2: jnp.sqrt(0.5 * r2)) if lowpass_filter else (lambda r2: jnp.zeros_like(r2))
    faint = rho_max <= 0.0  # alpha < 1/255 everywhere: no pixel at all
    box_disc = disc(cut2)[:, None]
    bin_min = jnp.where(tight_bounded[:, None], jnp.minimum(tight_center - tight_half, center - box_disc), -big)
    bin_max = jnp.where(tight_bounded[:, None], jnp.maximum(tight_center + tight_half, center + box_disc), big)
    bin_min, bin_max = jnp.where(faint[:, None], big, bin_min), jnp.where(faint[:, None], -big, bin_max)
    conic = _pixel_conic(M, rho_max, center)

    if means2d_probe is not None:
        # Shifts the projected centre column only; the filter centre keeps its value, so the
        # probe's gradient excludes the filter branch like the reference's densification signal.
        shift = means2d_probe * M[:, 2, 2][:, None]
        M = M.at[:, 0, 2].add(shift[:, 0]).at[:, 1, 2].add(shift[:, 1])

    culled_near = ~invalid & (depth <= near)
    on_screen = (box_max[:, 0] > 0) & (box_min[:, 0] < cam.width) & (box_max[:, 1] > 0) & (box_min[:, 1] < cam.height)
    visible = ~invalid & ~culled_near & on_screen & jnp.all(jnp.isfinite(M.reshape(n, 9)), 1)

    cam_center = cam.center
    view_dir = means - cam_center
    dir_norm2 = _sum3(view_dir**2)[:, None]
    dirs = view_dir / jnp.sqrt(jnp.where(dir_norm2 > 0, dir_norm2, 1.0))
    color = sh.evaluate(clean(s.sh_dc), clean(s.sh_rest), dirs, sh_degree)
    normal = R_world[:, :, 2]
    normal = jnp.where(_sum3(normal * view_dir)[:, None] > 0, -normal, normal)

    zero_if_hidden = lambda x: jnp.where(visible.reshape((n,) + (1,) * (x.ndim - 1)), x, 0.0)
    return Projected(
        M=jnp.where(visible[:, None, None], M, jnp.eye(3)), center=zero_if_hidden(center),
        opacity=zero_if_hidden(opacity), color=zero_if_hidden(color), normal=zero_if_hidden(normal),
        depth=jnp.where(visible, depth, jnp.inf), box_min=box_min, box_max=box_max, bin_min=bin_min,
        bin_max=bin_max, conic=conic, reach=disc(rho_max), bounded=tight_bounded, visible=visible, invalid=invalid,
        culled_near=culled_near)


def _ellipse_box(M, cut2, depth):
    """Centre, half-extent and boundedness of the projected ellipse u^2 + v^2 <= cut2 from its
    dual conic C* = M diag(cut2, cut2, -1) M^T."""
    f = jnp.stack([cut2, cut2, -jnp.ones_like(cut2)], axis=1)
    dist = _sum3(f * M[:, 2] ** 2)
    bounded = dist < -1e-12 * jnp.maximum(depth**2, 1e-12)  # ellipse entirely in front of the camera
    safe_dist = jnp.where(bounded, dist, -1.0)
    center = jnp.stack([_sum3(f * M[:, 0] * M[:, 2]), _sum3(f * M[:, 1] * M[:, 2])], 1)
    center = center / safe_dist[:, None]
    diag = jnp.stack([_sum3(f * M[:, 0] ** 2), _sum3(f * M[:, 1] ** 2)], 1) / safe_dist[:, None]
    half = jnp.sqrt(jnp.maximum(center**2 - diag, 1e-4))
    return center, half, bounded


def _pixel_conic(M, cut2, origin):
    """q(d) = p0^2 + p1^2 - cut2 p2^2 with p = adj(M) (origin + d, 1), as the coefficients
    (dxx, dxy, dyy, dx, dy, 1) of a quadratic in the pixel offset d: q <= 0 inside the ellipse.
    Normalised by its largest coefficient, so float32 comparisons stay meaningful."""
    a, b, c0 = jnp.cross(M[:, 1], M[:, 2]), jnp.cross(M[:, 2], M[:, 0]), jnp.cross(M[:, 0], M[:, 1])
    pc = a * origin[:, :1] + b * origin[:, 1:] + c0           # p at the origin
    w = jnp.stack([jnp.ones_like(cut2), jnp.ones_like(cut2), -cut2], axis=1)
    dot = lambda x, y: _sum3(w * x * y)
    q = jnp.stack([dot(a, a), dot(a, b), dot(b, b), dot(a, pc), dot(b, pc), dot(pc, pc)], axis=1)
    scale = jnp.max(jnp.abs(q[:, :3]), axis=1, keepdims=True)
    return jax.lax.stop_gradient(q / jnp.where(scale > 0, scale, 1.0))


def evaluate_pixels(M, center, opacity, depth, xy, near: float, lowpass_filter: bool):
    """alpha and hit depth of surfels at pixel centres; broadcasts over leading axes.

    M (...,3,3), center (...,2), opacity (...), depth (...) against xy (...,2).
    Returns (alpha, z), alpha already zero where the hit is invalid or below 1/255.
    Written on scalar planes (no (...,3) temporaries) so XLA fuses it into one loop.
    """
    x, y = xy[..., 0], xy[..., 1]
    m = lambda i, j: M[..., i, j]
    # Pixel planes k = x M[2] - M[0], l = y M[2] - M[1]; (u, v, 1) ~ k x l.
    k0, k1, k2 = x * m(2, 0) - m(0, 0), x * m(2, 1) - m(0, 1), x * m(2, 2) - m(0, 2)
    l0, l1, l2 = y * m(2, 0) - m(1, 0), y * m(2, 1) - m(1, 1), y * m(2, 2) - m(1, 2)
    p0, p1, p2 = k1 * l2 - k2 * l1, k2 * l0 - k0 * l2, k0 * l1 - k1 * l0
    # Edge-on surfels (p2 -> 0) would put the hit at infinity: take the filter branch instead.
    ok = (jnp.abs(p0) < 1e6 * jnp.abs(p2)) & (jnp.abs(p1) < 1e6 * jnp.abs(p2))
    inv = 1.0 / jnp.where(ok, p2, 1.0)
    u, v = jnp.where(ok, p0, 0.0) * inv, jnp.where(ok, p1, 0.0) * inv
    rho3 = jnp.where(ok, u * u + v * v, jnp.inf)
    if lowpass_filter:
        dx, dy = x - center[..., 0], y - center[..., 1]
        rho2 = 2.0 * (dx * dx + dy * dy)
    else:
        rho2 = jnp.full_like(rho3, jnp.inf)
    use_hit = rho3 <= rho2
    rho = jnp.where(use_hit, rho3, rho2)
    z = jnp.where(use_hit, u * m(2, 0) + v * m(2, 1) + m(2, 2), depth)
    alpha = jnp.minimum(0.99, opacity * jnp.exp(-0.5 * jnp.where(jnp.isfinite(rho), rho, 1e10)))
    keep = (alpha >= 1.0 / 255.0) & (z >= near)
    return jnp.where(keep, alpha, 0.0), z
