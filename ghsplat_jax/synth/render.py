"""Ground-truth renderer: ray casting against the scene mesh (trimesh + embreex).

For each pixel centre (j + 0.5, i + 0.5) one camera ray; embree finds the first triangle,
then the hit is recomputed in float64 (Moller-Trumbore) for exact depth and barycentrics.

Outputs per view (H, W leading):
- rgb (3,) float32 in [0, 1]: texture x tint, lit by a sun (optional shadow rays, soft with
  several samples over the sun disc) and a sky dome; thin foliage is lit through from behind;
  misses show a sky gradient (render.background = "black": black).
- depth float32: z along the camera axis (OpenCV), 0 where nothing is hit.
- normal (3,) float32: world-frame unit geometric normal facing the camera, 0 where no hit.
- instance int32: scene instance id, 0 background; semantic uint8: index into scene.CLASSES.
- face int32: index of the hit mesh face, -1 background.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.synth.scene import Scene

SKY_HORIZON = np.array([0.78, 0.82, 0.86])
SKY_ZENITH = np.array([0.55, 0.68, 0.86])
SUN_COLOUR = np.array([1.0, 0.97, 0.90])
SKY_LIGHT = np.array([0.92, 0.96, 1.0])


def camera_arrays(camera) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(K, world_to_cam) float64 and (width, height) of any Camera-like object."""
    K = np.asarray(camera.K, np.float64)
    w2c = np.asarray(camera.world_to_cam, np.float64)
    width, height = int(camera.width), int(camera.height)
    if K.shape != (3, 3) or w2c.shape != (4, 4) or width <= 0 or height <= 0:
        raise ValueError(f"bad camera: K {K.shape}, world_to_cam {w2c.shape}, size {width}x{height}")
    return K, w2c, width, height


def pixel_rays(camera, offset=(0.5, 0.5)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World ray origins (N,3), unit directions (N,3) and each direction's camera-z component (N,),
    for pixels in row-major order at (j + offset[0], i + offset[1])."""
    K, w2c, width, height = camera_arrays(camera)
    jj, ii = np.meshgrid(np.arange(width) + offset[0], np.arange(height) + offset[1])
    Ki = np.linalg.inv(K)
    # elementwise products, not (N,3) @ (3,3): BLAS threads only slow this down on a busy CPU
    d_cam = [Ki[r, 0] * jj.ravel() + Ki[r, 1] * ii.ravel() + Ki[r, 2] for r in range(3)]
    norm = np.sqrt(d_cam[0] ** 2 + d_cam[1] ** 2 + d_cam[2] ** 2)
    d_cam = [c / norm for c in d_cam]
    R, t = w2c[:3, :3], w2c[:3, 3]
    dirs = np.stack([d_cam[0] * R[0, k] + d_cam[1] * R[1, k] + d_cam[2] * R[2, k] for k in range(3)], -1)
    origins = np.broadcast_to(-R.T @ t, dirs.shape)
    return np.ascontiguousarray(origins), dirs, d_cam[2]


def trace(scene: Scene, origins: np.ndarray, dirs: np.ndarray):
    """First hits: (tri (N,) int64, -1 for a miss; t (N,) float64 distance; bary (N,3))."""
    tri = np.asarray(scene.intersector.intersects_first(origins, dirs), np.int64)
    t = np.zeros(len(tri))
    bary = np.zeros((len(tri), 3))
    hit = np.flatnonzero(tri >= 0)
    if hit.size:
        v = scene.vertices[scene.faces[tri[hit]]]
        o, d = origins[hit], dirs[hit]
        e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-18
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - v[:, 0]
        b1 = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        b2 = np.einsum("ij,ij->i", d, q) * inv
        th = np.einsum("ij,ij->i", e2, q) * inv
        ok &= np.isfinite(th) & (th > 0)
        tri[hit[~ok]] = -1  # degenerate or behind: embree's float32 call was marginal
        t[hit] = np.where(ok, th, 0.0)
        bary[hit] = np.stack([1 - b1 - b2, b1, b2], -1) * ok[:, None]
    return tri, t, bary


def sample_texture(texture: np.ndarray, uv: np.ndarray, nearest: bool = False) -> np.ndarray:
    """Texels at uv (n,2), wrapping around; v up (row 0 is v = 1)."""
    h, w = texture.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = (1 - uv[:, 1]) * h - 0.5
    if nearest:
        return texture[np.floor(y + 0.5).astype(np.int64) % h, np.floor(x + 0.5).astype(np.int64) % w]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    return ((texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx) * (1 - fy)
            + (texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx) * fy)


def albedo(scene: Scene, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Surface colour (n,3) at hits on faces `tri` (all >= 0) with barycentrics `bary`."""
    uv = np.einsum("nk,nkj->nj", bary, scene.uv[scene.faces[tri]])
    out = np.empty((len(tri), 3))
    mats = scene.face_material[tri]
    for m in np.unique(mats):
        sel = mats == m
        material = scene.materials[m]
        out[sel] = sample_texture(material.texture, uv[sel], material.nearest)
    return out * scene.face_tint[tri]


def sun_direction(scene: Scene) -> np.ndarray:
    rc = scene.config.render
    el, az = np.deg2rad(rc.sun_elevation_deg), np.deg2rad(rc.sun_azimuth_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def sky_colour(dirs: np.ndarray) -> np.ndarray:
    up = np.sqrt(np.clip(dirs[:, 2:3], 0, 1))
    return SKY_HORIZON * (1 - up) + SKY_ZENITH * up


def _sun_visibility(scene: Scene, points, normals_sun_side, shadows: bool, samples: int, rng) -> np.ndarray:
    """Fraction of the sun disc visible from each point (1 without shadows)."""
    if not shadows or len(points) == 0:
        return np.ones(len(points))
    rc = scene.config.render
    sun = sun_direction(scene)
    origins = points + normals_sun_side * 1e-4 + sun * 1e-4
    a = np.cross(sun, [0.0, 0.0, 1.0] if abs(sun[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(sun, a)
    radius = np.tan(np.deg2rad(rc.sun_radius_deg))
    visible = np.zeros(len(points))
    for _k in range(samples):
        if samples == 1:
            dirs = np.broadcast_to(sun, points.shape)
        else:  # uniform points on the sun disc, a fresh pattern per sample
            r = radius * np.sqrt(rng.uniform(size=len(points)))[:, None]
            phi = rng.uniform(0, 2 * np.pi, len(points))[:, None]
            dirs = sun + r * (np.cos(phi) * a + np.sin(phi) * b)
            dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        visible += ~scene.intersector.intersects_any(origins, np.ascontiguousarray(dirs))
    return visible / samples


def shade(scene: Scene, origins, dirs, tri, t, bary, shadows: bool, samples: int, rng):
    """(rgb (N,3), camera-facing normals (N,3)) for traced rays."""
    rc = scene.config.render
    rgb = sky_colour(dirs) if rc.background == "sky" else np.zeros_like(dirs)
    normals = np.zeros_like(dirs)
    hit = np.flatnonzero(tri >= 0)
    if hit.size == 0:
        return rgb, normals
    n = scene.face_normals[tri[hit]]
    n = np.where((np.einsum("ij,ij->i", n, dirs[hit]) > 0)[:, None], -n, n)
    normals[hit] = n
    points = origins[hit] + dirs[hit] * t[hit, None]
    sun = sun_direction(scene)
    cos_sun = n @ sun
    translucent = np.array([m.translucent for m in scene.materials])[scene.face_material[tri[hit]]]
    lit = (cos_sun > 0) | translucent  # opaque surfaces facing away from the sun are self-shadowed
    vis = np.zeros(hit.size)
    side = np.where(cos_sun[:, None] >= 0, n, -n)
    vis[lit] = _sun_visibility(scene, points[lit], side[lit], shadows, samples, rng)
    direct = np.where(cos_sun > 0, cos_sun, 0.35 * -cos_sun * translucent) * vis
    ambient = rc.sky_strength * (0.55 + 0.45 * n[:, 2:3]) * SKY_LIGHT
    light = ambient + rc.sun_strength * direct[:, None] * SUN_COLOUR
    rgb[hit] = albedo(scene, tri[hit], bary[hit]) * light
    return np.clip(rgb, 0, 1), normals


def render_view(scene: Scene, camera, *, shadows: bool | None = None, supersample: int | None = None) -> dict:
    """Render one camera: dict of rgb, depth, normal, instance, semantic arrays (see module doc)."""
    rc = scene.config.render
    shadows = rc.shadows if shadows is None else shadows
    ss = rc.supersample if supersample is None else int(supersample)
    samples = rc.shadow_samples
    rng = np.random.default_rng(scene.config.seed)
    _, _, width, height = camera_arrays(camera)

    origins, dirs, dz = pixel_rays(camera)
    tri, t, bary = trace(scene, origins, dirs)
    rgb, normals = shade(scene, origins, dirs, tri, t, bary, shadows, samples, rng)
    if ss > 1:  # anti-aliased colour from an s x s grid of sub-pixel rays
        rgb = np.zeros_like(rgb)
        for a in range(ss):
            for b in range(ss):
                o2, d2, _ = pixel_rays(camera, ((a + 0.5) / ss, (b + 0.5) / ss))
                rgb += shade(scene, o2, d2, *trace(scene, o2, d2), shadows, samples, rng)[0]
        rgb /= ss * ss
    hit = tri >= 0
    instance = np.where(hit, scene.face_instance[np.maximum(tri, 0)], 0).astype(np.int32)
    shape = (height, width)
    return {
        "rgb": rgb.reshape(*shape, 3).astype(np.float32),
        "depth": np.where(hit, t * dz, 0.0).reshape(shape).astype(np.float32),
        "normal": normals.reshape(*shape, 3).astype(np.float32),
        "instance": instance.reshape(shape),
        "semantic": scene.instance_classes[instance].reshape(shape),
        "face": tri.reshape(shape).astype(np.int32),
    }


def render_views(scene: Scene, cameras, *, progress: bool = False, **kwargs) -> dict:
    """Render every camera; arrays stacked along a leading view axis (all cameras one size)."""
    from tqdm import tqdm

    views = [render_view(scene, cam, **kwargs) for cam in tqdm(cameras, disable=not progress, desc="render")]
    if len({v["rgb"].shape for v in views}) > 1:
        raise ValueError("render_views stacks views: all cameras must share one image size")
    return {key: np.stack([v[key] for v in views]) for key in views[0]}
