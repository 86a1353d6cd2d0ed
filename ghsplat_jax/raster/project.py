"""Per-surfel projection: ray transform, screen box, filter centre, colour and normal.

Follows the 2DGS reference: M = K [s_u t_u | s_v t_v | mu] in camera space; the screen box
and the filter centre come from the dual conic of the 3-sigma ellipse.

Written on (N,) planes, one per vector or matrix entry, and stacked only into the outputs. On
XLA:CPU the gradient of every slice of an (N, 3) or (N, 3, 3) intermediate is a full-size pad,
and that of every broadcast against a small axis a YNN reduction, each an op of its own. On
such arrays, pads, YNN reductions and concatenations took 232 ms of thread time in a Table 1
training step (164k surfels, 192x144), and 122 ms on planes; with the SH colour's written-out
gradient (`core.sh`), that step ran 1.25x faster.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core import quaternions, sh
from ghsplat_jax.core.camera import Camera
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
    # M as a homography about `center` (`carried`): the pixel-plane cross product p(center + d) =
    # p_center + p_dx d_x + p_dy d_y, with p(x) = (x M2 - M0) x (y M2 - M1) = a x + b y + c0 for M's
    # rows, a = M1 x M2, b = M2 x M0, c0 = M0 x M1; and det(M) = M2 . c0 (the hit depth's numerator).
    p_center: jax.Array   # (N,3)
    p_dx: jax.Array       # (N,3) a
    p_dy: jax.Array       # (N,3) b
    det: jax.Array        # (N,)
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


def _finite_rows(x: jax.Array | np.ndarray) -> jax.Array:
    return jnp.all(jnp.isfinite(x.reshape(x.shape[0], -1)), axis=1)


def _planes(x: jax.Array) -> list[jax.Array]:
    """x's last axis as planes, taken as rows of its transpose: the gradient of a row is a pad
    along the major axis, which XLA:CPU runs as a cheap loop. Columns x[:, i] gave pads along
    the minor axis, fused with their cotangents' computation: four of them took 84 ms of a
    Table 1 step's thread time (row1_x1 at step 10,000, profiled 2026-11-27)."""
    return list(jnp.moveaxis(x, -1, 0))


def _stack(planes) -> jax.Array:
    return jnp.stack(planes, axis=1)


def _matvec(A: jax.Array, v: list) -> list:
    """A (3, 3) times a vector of planes."""
    return [sum(A[i, j] * v[j] for j in range(3)) for i in range(3)]


def _cross(u: list, v: list) -> list:
    return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]


def project(s: Surfels, cam: Camera, near: float, sh_degree: int, lowpass_filter: bool,
            means2d_probe: jax.Array | None = None) -> Projected:
    n = s.means.shape[0]
    finite = (_finite_rows(s.means) & _finite_rows(s.quats) & _finite_rows(s.log_scales)
              & jnp.isfinite(s.opacity_logits) & _finite_rows(s.sh_dc) & _finite_rows(s.sh_rest))
    # Non-finite inputs are replaced before any arithmetic so no NaN reaches gradients.
    clean = lambda x, fill=0.0: jnp.where(finite.reshape((n,) + (1,) * (x.ndim - 1)), x, fill)
    means = _planes(clean(s.means))
    R_world, quat_ok = quaternions.rotation_planes(clean(s.quats))  # columns t_u, t_v, n
    scales = [jnp.exp(jnp.clip(x, *LOG_SCALE_RANGE)) for x in _planes(clean(s.log_scales))]
    opacity = jax.nn.sigmoid(clean(s.opacity_logits, -20.0))
    invalid = ~(finite & quat_ok)

    R_wc, t_wc = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
    mu_c = [m + t_wc[i] for i, m in enumerate(_matvec(R_wc, means))]
    tangents_c = [[t * scales[j] for t in _matvec(R_wc, [R_world[k][j] for k in range(3)])] for j in range(2)]
    columns = [_matvec(cam.K, c) for c in (*tangents_c, mu_c)]      # of K [s_u t_u | s_v t_v | mu]
    M = [[columns[j][i] for j in range(3)] for i in range(3)]       # rows
    depth = mu_c[2]

    # Dual conic of u^2 + v^2 = CUTOFF^2: C* = M diag(c^2, c^2, -1) M^T.
    center, half, bounded = _ellipse_box(M, CUTOFF**2, depth)
    reach = FILTER_REACH if lowpass_filter else 0.5
    half = [jnp.maximum(h, reach) for h in half]

    safe_depth = jnp.where(jnp.abs(depth) > 1e-12, depth, 1.0)
    # Where the ellipse is unbounded, the projected mean (the reference does the same).
    center = [jnp.where(bounded, c, M[i][2] / safe_depth) for i, c in enumerate(center)]
    # An ellipse that crosses the camera plane projects to an unbounded conic: whole screen.
    big = jnp.float32(1e9)
    box_min = [jnp.where(bounded, c - h, -big) for c, h in zip(center, half)]
    box_max = [jnp.where(bounded, c + h, big) for c, h in zip(center, half)]

    # Where alpha = opacity exp(-rho / 2) can reach 1/255: rho <= rho_max = 2 ln(255 opacity). As
    # rho = min(rho3, rho2), that region is the ellipse u^2 + v^2 <= rho_max joined with the
    # filter's disc 2 |x - c|^2 <= rho_max. Candidate tiles come from its box capped at the
    # 3-sigma ellipse (the reference's extent); the tile test then drops a candidate only where
    # alpha stays below 1/255 at every pixel, so the image equals the 3-sigma binning's.
    rho_max = jnp.maximum(2.0 * jnp.log(jnp.maximum(255.0 * opacity, 1e-30)), 0.0)
    cut2 = jnp.minimum(rho_max, CUTOFF**2)
    tight_center, tight_half, tight_bounded = _ellipse_box(M, cut2, depth)
    disc = (lambda r2: jnp.sqrt(0.5 * r2)) if lowpass_filter else (lambda r2: jnp.zeros_like(r2))
    faint = rho_max <= 0.0  # alpha < 1/255 everywhere: no pixel at all
    box_disc = disc(cut2)
    bin_min, bin_max = [], []
    for c, tc, th in zip(center, tight_center, tight_half):
        th = jnp.maximum(th, 0.5)
        bin_min.append(jnp.where(faint, big, jnp.where(tight_bounded, jnp.minimum(tc - th, c - box_disc), -big)))
        bin_max.append(jnp.where(faint, -big, jnp.where(tight_bounded, jnp.maximum(tc + th, c + box_disc), big)))
    conic = _pixel_conic(M, rho_max, center)

    if means2d_probe is not None:
        # Shifts the projected centre column only; the filter centre keeps its value, so the
        # probe's gradient excludes the filter branch like the reference's densification signal.
        probe = _planes(means2d_probe)
        M[0][2] = M[0][2] + probe[0] * M[2][2]
        M[1][2] = M[1][2] + probe[1] * M[2][2]

    culled_near = ~invalid & (depth <= near)
    on_screen = (box_max[0] > 0) & (box_min[0] < cam.width) & (box_max[1] > 0) & (box_min[1] < cam.height)
    visible = ~invalid & ~culled_near & on_screen
    for m in (m for row in M for m in row):
        visible &= jnp.isfinite(m)

    view_dir = [m - cam.center[i] for i, m in enumerate(means)]
    dir_norm2 = sum(v * v for v in view_dir)
    dir_norm = jnp.sqrt(jnp.where(dir_norm2 > 0, dir_norm2, 1.0))
    color = sh.evaluate(clean(s.sh_dc), clean(s.sh_rest), _stack([v / dir_norm for v in view_dir]), sh_degree)
    normal = [R_world[k][2] for k in range(3)]
    away = sum(nk * vk for nk, vk in zip(normal, view_dir)) > 0
    normal = [jnp.where(away, -x, x) for x in normal]

    hide = lambda x, fill=0.0: jnp.where(visible, x, fill)
    M = [[hide(M[i][j], float(i == j)) for j in range(3)] for i in range(3)]
    center = [hide(c) for c in center]
    return Projected(
        M=jnp.stack([_stack(row) for row in M], axis=1), center=_stack(center), opacity=hide(opacity),
        color=jnp.where(visible[:, None], color, 0.0), normal=_stack([hide(x) for x in normal]),
        depth=hide(depth, jnp.inf), **_homography(M, center), box_min=_stack(box_min), box_max=_stack(box_max),
        bin_min=_stack(bin_min), bin_max=_stack(bin_max), conic=conic, reach=disc(rho_max), bounded=tight_bounded,
        visible=visible, invalid=invalid, culled_near=culled_near)


def _pixel_plane(M, origin):
    """p(x) = (x M2 - M0) x (y M2 - M1) = a x + b y + c0 for M's rows (planes): p at `origin`,
    a = M1 x M2, b = M2 x M0 and c0 = M0 x M1."""
    a, b, c0 = _cross(M[1], M[2]), _cross(M[2], M[0]), _cross(M[0], M[1])
    return [a[i] * origin[0] + b[i] * origin[1] + c0[i] for i in range(3)], a, b, c0


def _homography(M, center) -> dict:
    """`Projected`'s p_center, p_dx, p_dy and det from M's rows and the centre (planes)."""
    p_center, a, b, c0 = _pixel_plane(M, center)
    det = M[2][0] * c0[0] + M[2][1] * c0[1] + M[2][2] * c0[2]
    return dict(p_center=_stack(p_center), p_dx=_stack(a), p_dy=_stack(b), det=det)


def _ellipse_box(M, cut2, depth):
    """Centre, half-extent and boundedness of the projected ellipse u^2 + v^2 <= cut2 from its
    dual conic C* = M diag(cut2, cut2, -1) M^T (M as rows of planes)."""
    f = (cut2, cut2, -1.0)
    dual = lambda r, q: sum(f[k] * M[r][k] * M[q][k] for k in range(3))
    dist = dual(2, 2)
    bounded = dist < -1e-12 * jnp.maximum(depth**2, 1e-12)  # ellipse entirely in front of the camera
    safe_dist = jnp.where(bounded, dist, -1.0)
    center = [dual(0, 2) / safe_dist, dual(1, 2) / safe_dist]
    half = [jnp.sqrt(jnp.maximum(c * c - dual(i, i) / safe_dist, 1e-4)) for i, c in enumerate(center)]
    return center, half, bounded


def _pixel_conic(M, cut2, origin):
    """q(d) = p0^2 + p1^2 - cut2 p2^2 with p = adj(M) (origin + d, 1), as the coefficients
    (dxx, dxy, dyy, dx, dy, 1) of a quadratic in the pixel offset d: q <= 0 inside the ellipse.
    Normalised by its largest coefficient, so float32 comparisons stay meaningful."""
    pc, a, b, _ = _pixel_plane(M, origin)  # p at the origin
    w = (1.0, 1.0, -cut2)
    dot = lambda x, y: sum(w[k] * x[k] * y[k] for k in range(3))
    q = [dot(a, a), dot(a, b), dot(b, b), dot(a, pc), dot(b, pc), dot(pc, pc)]
    scale = jnp.maximum(jnp.maximum(jnp.abs(q[0]), jnp.abs(q[1])), jnp.abs(q[2]))
    scale = jnp.where(scale > 0, scale, 1.0)
    return jax.lax.stop_gradient(_stack([x / scale for x in q]))


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
