"""Dense float64 reference renderer in NumPy: every pixel evaluates every surfel.

No tiles, no chunks, no log-space tricks: a straight transcription of the 2DGS rules that the
tiled rasterizer is tested against (see docs/design.md). Slow; for small tests only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ghsplat_jax.core.camera import Camera
from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.raster.config import RasterConfig

_C0 = 0.28209479177387814


# Its own copy of core.quaternions' matrix formula, on purpose: the reference is the
# independent float64 oracle the tiled rasterizer is tested against, so it shares no
# rotation code with it (tests/test_rotations.py checks core's copy against scipy).
def _quat_to_matrix(q):
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _sh_color(s: Surfels, dirs, degree):
    x, y, z = dirs.T
    basis: Any = [np.full_like(x, _C0)]  # the columns, then their stack
    if degree >= 1:
        c1 = 0.4886025119029199
        basis += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [1.0925484305920792 * xy, -1.0925484305920792 * yz, 0.31539156525252005 * (2 * zz - xx - yy),
                  -1.0925484305920792 * xz, 0.5462742152960396 * (xx - yy)]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        basis += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z,
                  -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                  -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
                  -0.5900435899266435 * x * (xx - 3 * yy)]
    basis = np.stack(basis, -1)
    k = (degree + 1) ** 2
    coeffs = np.concatenate([s.sh_dc[:, None], s.sh_rest[:, : k - 1]], 1)
    return np.maximum(np.einsum("nk,nkc->nc", basis, coeffs) + 0.5, 0.0)


def render_reference(s: Surfels, cam: Camera, cfg: RasterConfig | None = None) -> dict[str, np.ndarray]:
    """rgb, alpha, depth, median_depth, normal, distortion as float64 arrays.

    Surfels must be finite with non-zero quaternions (the reference does no culling of bad input).
    """
    cfg = RasterConfig() if cfg is None else cfg
    f64 = lambda a: np.asarray(a, np.float64)
    s = Surfels(*(f64(getattr(s, f)) for f in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")))
    K, w2c = f64(cam.K), f64(cam.world_to_cam)
    H, W = cam.height, cam.width
    degree = s.sh_rest.shape[1] and int(round(np.sqrt(s.sh_rest.shape[1] + 1))) - 1
    if cfg.sh_degree is not None:
        degree = min(degree, cfg.sh_degree)

    q = s.quats / np.linalg.norm(s.quats, axis=1, keepdims=True)
    R = _quat_to_matrix(q)
    scales = np.exp(s.log_scales)
    opacity = 1 / (1 + np.exp(-s.opacity_logits))
    mu_c = s.means @ w2c[:3, :3].T + w2c[:3, 3]
    local = np.concatenate([np.einsum("ij,njk->nik", w2c[:3, :3], R[:, :, :2]) * scales[:, None, :],
                            mu_c[:, :, None]], 2)
    M = np.einsum("ij,njk->nik", K, local)
    f = np.array([9.0, 9.0, -1.0])
    dist = np.sum(f * M[:, 2] ** 2, 1)
    # The filter centre is the dual-conic centre of the 3-sigma ellipse where that ellipse lies in
    # front of the camera; one that crosses the camera plane projects to a hyperbola, whose
    # "centre" can lie anywhere, so there the projected mean is used (as `project` does; 2DGS's
    # CUDA code takes the hyperbola's centre and a box around it, clipping such a surfel).
    bounded = dist < -1e-12 * np.maximum(mu_c[:, 2] ** 2, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        dual_center = np.stack([np.sum(f * M[:, 0] * M[:, 2], 1), np.sum(f * M[:, 1] * M[:, 2], 1)], 1) / dist[:, None]
        center = np.where(bounded[:, None], dual_center, M[:, :2, 2] / M[:, 2, 2:3])
    cam_center = -w2c[:3, :3].T @ w2c[:3, 3]
    view = s.means - cam_center
    color = _sh_color(s, view / np.linalg.norm(view, axis=1, keepdims=True), degree)
    normal = R[:, :, 2] * np.where(np.sum(R[:, :, 2] * view, 1) > 0, -1.0, 1.0)[:, None]

    keep = np.nonzero(mu_c[:, 2] > cfg.near)[0]
    keep = keep[np.argsort(mu_c[keep, 2], kind="stable")]
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    xy = np.stack([xs, ys], -1).reshape(-1, 2)
    T = np.ones(len(xy))
    out = {k: np.zeros((len(xy),) + sh) for k, sh in
           [("rgb", (3,)), ("depth", ()), ("normal", (3,)), ("median_depth", ()), ("distortion", ())]}
    acc_w, acc_m, acc_m2 = (np.zeros(len(xy)) for _ in range(3))
    done = np.zeros(len(xy), bool)
    for i in keep:
        k = xy[:, :1] * M[i, 2] - M[i, 0]
        l = xy[:, 1:] * M[i, 2] - M[i, 1]
        p = np.cross(k, l)
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
            rho3 = np.where(p[:, 2] != 0, u * u + v * v, np.inf)
        rho2 = 2 * np.sum((xy - center[i]) ** 2, 1) if cfg.lowpass_filter else np.full(len(xy), np.inf)
        use_hit = rho3 <= rho2
        rho = np.minimum(rho3, rho2)
        z = np.where(use_hit, np.nan_to_num(u * M[i, 2, 0] + v * M[i, 2, 1]) + M[i, 2, 2], mu_c[i, 2])
        alpha = np.minimum(0.99, opacity[i] * np.exp(-0.5 * rho))
        ok = ~done & (alpha >= 1 / 255) & (z >= cfg.near)
        t_next = T * (1 - alpha)
        stop = ok & (t_next < 1e-4)
        done |= stop
        ok &= ~stop
        w = np.where(ok, alpha * T, 0.0)
        m = cfg.far / (cfg.far - cfg.near) * (1 - cfg.near / np.where(ok, z, cfg.near))
        out["distortion"] += w * (m * m * acc_w + acc_m2 - 2 * m * acc_m)
        acc_w, acc_m, acc_m2 = acc_w + w, acc_m + w * m, acc_m2 + w * m * m
        out["median_depth"] = np.where(ok & (T > 0.5), z, out["median_depth"])
        out["rgb"] += w[:, None] * color[i]
        out["depth"] += w * np.where(ok, z, 0.0)
        out["normal"] += w[:, None] * normal[i]
        T = np.where(ok, t_next, T)
    alpha = 1 - T
    out["rgb"] += T[:, None] * np.asarray(cfg.background)
    out["depth"] = np.where(alpha > 0, out["depth"] / np.where(alpha > 0, alpha, 1), 0.0)
    out["alpha"] = alpha
    return {k: v.reshape((H, W) + v.shape[1:]) for k, v in out.items()}
