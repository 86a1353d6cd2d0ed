"""A spinning LiDAR from four 90-degree z-depth renders.

The four faces look along lidar azimuths 0, 90, 180 and 270 deg; they are rendered inside
one jit (one after another with lax.map by default, where the rasterizer skips unused work;
or as one jax.vmap over cameras of one size). With the project's rasterizer (`sampling=
"beams"`, the default) each face renders only its beams' rays, as sample points of the face
image (`raster.samples`): the exact z-depth along every beam, and (VLP-16) 32 evaluations per
tile-surfel pair where a 16-px tile of pixels takes 256.
With a given `render_fn` (or `sampling="faces"`) whole face images are rendered and
resampled onto the beam pattern in the same jit:

- every column's azimuth lies in exactly one face (half-open intervals
  [a_k - 45 deg, a_k + 45 deg)), so seams neither duplicate nor drop azimuths; the
  faces are rendered one pixel wider than 90 degrees so edge beams stay inside;
- z-depth is interpolated as inverse depth (exactly linear in the image for a plane),
  falling back to the nearest pixel at depth discontinuities (no ghost points between
  a leaf and the wall behind it), then range = z / (cos(elevation) cos(face azimuth));
- no return where the nearest pixel's alpha is below `min_alpha`, or the range is
  outside [min_range, max_range]; Gaussian range noise is added before that check.

Columns sweep clockwise seen from above (as Velodyne and Ouster sensors spin),
starting at +x; per-point `time` is the column's offset in the sweep, in seconds.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ghsplat_jax.sim.beams import BeamPattern

FACE_AZIMUTHS = np.deg2rad([0.0, 90.0, 180.0, 270.0])
# Beam rows lie about 10 px apart on a face, so 8-px tiles hold few beams and many tiles none;
# 16-px tiles halve the candidate pairs (VLP-16 at 100k surfels: 0.41 -> 0.31 s per scan).
BEAM_TILE_SIZE = 16


def lidar_from_face_optical() -> np.ndarray:
    """(4,4,4) poses of the four face cameras (OpenCV optical frames) in lidar_link."""
    out = np.tile(np.eye(4), (4, 1, 1))
    for k, a in enumerate(FACE_AZIMUTHS):
        c, s = np.cos(a), np.sin(a)
        out[k, :3, :3] = np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])  # columns x, y, z
    return out


@dataclasses.dataclass(frozen=True)
class FaceGeometry:
    width: int
    height: int
    K: np.ndarray  # (3,3) shared by the four faces


def face_geometry(pattern: BeamPattern, width: int | None = None, margin_px: float = 1.0) -> FaceGeometry:
    """Face size and intrinsics. Default width: about one pixel per column at the face
    centre (columns / 4 / (pi / 4) * ... = columns / pi), at least 64."""
    width = int(width or max(64, int(round(pattern.columns / np.pi))))
    f = width / 2.0 - margin_px          # +-45 deg land `margin_px` inside the image
    half = np.sqrt(2.0) * np.tan(np.deg2rad(pattern.max_abs_elevation_deg))
    height = 2 * int(np.ceil(f * half + margin_px + 1.0))
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return FaceGeometry(width, height, K)


@dataclasses.dataclass(frozen=True)
class ResampleTable:
    """Where each (ring, column) beam samples the faces; all (B, C) unless noted."""

    face: np.ndarray          # int32 face index
    u: np.ndarray             # continuous pixel x (pixel centres at j + 0.5)
    v: np.ndarray
    range_per_z: np.ndarray   # range / z-depth along the beam
    directions: np.ndarray    # (B, C, 3) unit beam directions in lidar_link
    azimuth: np.ndarray       # (C,) radians in lidar_link, in [0, 2 pi)
    time: np.ndarray          # (C,) seconds after the sweep start


def column_azimuths(columns: int) -> np.ndarray:
    """Clockwise sweep from +x, wrapped into [0, 2 pi)."""
    return np.mod(-2.0 * np.pi * np.arange(columns) / columns, 2.0 * np.pi)


def face_of_azimuth(az: np.ndarray) -> np.ndarray:
    """Face k owns [k*90 - 45, k*90 + 45) degrees: each azimuth in exactly one face."""
    return (np.floor((np.mod(az, 2 * np.pi) + np.pi / 4) / (np.pi / 2)).astype(np.int64) % 4).astype(np.int32)


def resample_table(pattern: BeamPattern, geom: FaceGeometry) -> ResampleTable:
    el = np.deg2rad(np.asarray(pattern.elevations_deg, np.float64))[:, None]   # (B,1)
    az = column_azimuths(pattern.columns)                                      # (C,)
    face = face_of_azimuth(az)
    local = np.mod(az - FACE_AZIMUTHS[face] + np.pi, 2 * np.pi) - np.pi        # in [-pi/4, pi/4)
    B, C = el.shape[0], az.shape[0]
    fx, fy, cx, cy = geom.K[0, 0], geom.K[1, 1], geom.K[0, 2], geom.K[1, 2]
    # Beam direction in the face's optical frame: (-cos e sin a', -sin e, cos e cos a').
    u = cx - fx * np.tan(local)[None, :] * np.ones((B, 1))
    v = cy - fy * np.tan(el) / np.cos(local)[None, :]
    range_per_z = 1.0 / (np.cos(el) * np.cos(local)[None, :])
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones((1, C))], -1)
    if u.min() < 0 or u.max() > geom.width or v.min() < 0 or v.max() > geom.height:
        raise ValueError("beam pattern does not fit in the LiDAR faces (vertical field too narrow)")
    return ResampleTable(np.broadcast_to(face, (B, C)).astype(np.int32), u, v, range_per_z, dirs,
                         az, np.arange(C) / (C * pattern.rate_hz))


def resample(depth, alpha, gray, table: ResampleTable, *, min_alpha: float = 0.5,
             edge_tolerance: float = 0.1):
    """Face maps (4,H,W) -> per-beam (range, intensity, hit) arrays (B,C), in jax.

    Inverse depth is bilinear between the four surrounding pixel centres when all four
    are hits within `edge_tolerance` (relative) of each other, or within 50% and locally
    planar; else the nearest pixel.
    """
    import jax.numpy as jnp

    _, H, W = depth.shape
    x = jnp.asarray(table.u - 0.5, jnp.float32)  # pixel-index coordinates
    y = jnp.asarray(table.v - 0.5, jnp.float32)
    f = jnp.asarray(table.face)
    x0 = jnp.clip(jnp.floor(x), 0, W - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, H - 2).astype(jnp.int32)
    tx = jnp.clip(x - x0, 0.0, 1.0)
    ty = jnp.clip(y - y0, 0.0, 1.0)
    xn = jnp.clip(jnp.round(x), 0, W - 1).astype(jnp.int32)
    yn = jnp.clip(jnp.round(y), 0, H - 1).astype(jnp.int32)

    def at(img, yy, xx):
        return img[f, yy, xx]

    hit = lambda yy, xx: (at(alpha, yy, xx) >= min_alpha) & (at(depth, yy, xx) > 0)
    corners = [(y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)]
    weights = [(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx]
    zs = [at(depth, yy, xx) for yy, xx in corners]
    all_hit = hit(*corners[0]) & hit(*corners[1]) & hit(*corners[2]) & hit(*corners[3])
    zmax = jnp.maximum(jnp.maximum(zs[0], zs[1]), jnp.maximum(zs[2], zs[3]))
    zmin = jnp.minimum(jnp.minimum(zs[0], zs[1]), jnp.minimum(zs[2], zs[3]))
    safe = [jnp.where(all_hit, z, 1.0) for z in zs]
    # A plane seen at a grazing angle changes depth fast between pixels but its inverse
    # depth stays affine (zero mixed second difference): interpolate that too, up to 50%.
    invs = [1.0 / z for z in safe]
    planar = jnp.abs(invs[0] + invs[3] - invs[1] - invs[2]) <= 0.01 * (invs[0] + invs[3]) / 2
    smooth = all_hit & ((zmax <= zmin * (1.0 + edge_tolerance)) | (planar & (zmax <= zmin * 1.5)))
    inv = sum(w / z for w, z in zip(weights, safe))
    z_near = at(depth, yn, xn)
    z = jnp.where(smooth, 1.0 / inv, z_near)
    ok = hit(yn, xn)
    rng = jnp.where(ok, z * jnp.asarray(table.range_per_z, jnp.float32), 0.0)
    return rng, at(gray, yn, xn), ok


@dataclasses.dataclass
class LidarScan:
    stamp: float
    pattern: BeamPattern
    ranges: np.ndarray      # (B, C) metres, NaN where no return
    intensity: np.ndarray   # (B, C) 0-255
    table: ResampleTable
    stats: dict

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.ranges)

    def points(self) -> np.ndarray:
        """(B, C, 3) in lidar_link, NaN where no return (an organised cloud)."""
        return self.ranges[..., None] * self.table.directions

    def fields(self, organised: bool = False) -> dict[str, np.ndarray]:
        """x, y, z, intensity (float32), ring (uint16), time (float32); flat arrays,
        dropping no-returns unless `organised` (then NaN coordinates, ring-major)."""
        B, C = self.ranges.shape
        pts = self.points()
        ring = np.broadcast_to(np.arange(B, dtype=np.uint16)[:, None], (B, C))
        time = np.broadcast_to(self.table.time.astype(np.float32)[None, :], (B, C))
        keep = np.ones((B, C), bool) if organised else self.valid
        return {"x": pts[..., 0][keep].astype(np.float32), "y": pts[..., 1][keep].astype(np.float32),
                "z": pts[..., 2][keep].astype(np.float32),
                "intensity": np.where(self.valid, self.intensity, np.nan)[keep].astype(np.float32),
                "ring": ring[keep], "time": time[keep]}


RenderFn = Callable  # (surfels, Camera) -> object with rgb, alpha, depth, median_depth, stats


class Lidar:
    """Rendered LiDAR; one compiled function per (pattern, face size, scene size).

    `render_fn(surfels, camera)` defaults to the project's rasterizer, sampled at the beams
    (`sampling="beams"`); tests pass an analytic one, whose face images are resampled
    (`sampling="faces"`, also selectable with the rasterizer). `traces` counts how often the
    scan function was traced (compiled). `pair_capacity=None` sizes the pair buffer from an
    exact count of the first scan's faces; an overflow later grows it (one recompilation),
    never a partial scan.
    """

    def __init__(self, pattern: BeamPattern, *, face_width: int | None = None, depth: str = "expected",
                 min_alpha: float = 0.5, render_fn: RenderFn | None = None, raster_config=None,
                 pair_capacity: int | None = None, batching: str = "map", sampling: str | None = None):
        if batching not in ("vmap", "map"):
            raise ValueError(f"batching must be 'vmap' or 'map', got {batching!r}")
        sampling = sampling or ("faces" if render_fn is not None else "beams")
        if sampling not in ("beams", "faces"):
            raise ValueError(f"sampling must be 'beams' or 'faces', got {sampling!r}")
        if sampling == "beams" and render_fn is not None:
            raise ValueError("sampling='beams' renders with the project's rasterizer; a render_fn needs 'faces'")
        self.batching, self.sampling = batching, sampling
        if depth not in ("expected", "median"):
            raise ValueError(f"depth must be 'expected' or 'median', got {depth!r}")
        self.pattern, self.depth_mode, self.min_alpha = pattern, depth, min_alpha
        self.geom = face_geometry(pattern, face_width)
        self.table = resample_table(pattern, self.geom)
        self.faces = lidar_from_face_optical()
        self._render_fn = render_fn
        self._raster_config = raster_config
        self.pair_capacity = pair_capacity
        self.traces = 0
        self._fn = None

    def _config(self):
        from ghsplat_jax.sim.camera_sensor import sensor_config

        cfg = sensor_config(self._raster_config, self.pair_capacity, median=self.depth_mode == "median")
        if self.sampling == "faces":
            return cfg
        # Sample points need the carried compositor; every compositor renders the same image.
        return dataclasses.replace(cfg, tile_size=BEAM_TILE_SIZE, compositor="carried", backward="custom_vjp",
                                   backend="tiled")

    def _beam_samples(self):
        """Each face's beams as sample points of its image, and where each (ring, column) beam's
        values land in the stacked (4, N) outputs."""
        from ghsplat_jax.raster import samples

        W, H, ts = self.geom.width, self.geom.height, self._config().tile_size
        xy = np.stack([self.table.u, self.table.v], axis=-1)
        faces = [np.flatnonzero(self.table.face.ravel() == k) for k in range(4)]
        points = [xy.reshape(-1, 2)[f] for f in faces]
        slots = max(samples.pixel_samples(q, W, H, ts).slots for q in points)
        stacked = samples.stack([samples.pixel_samples(q, W, H, ts, slots) for q in points])
        where = np.zeros(self.table.face.size, np.int64)
        for k, f in enumerate(faces):
            where[f] = k * stacked.index.shape[1] + np.arange(len(f))
        return stacked, where.reshape(self.table.face.shape)

    def _build(self):
        import jax
        import jax.numpy as jnp

        from ghsplat_jax.core.camera import Camera
        from ghsplat_jax.sim.camera_sensor import sensor_render_fn

        cfg = self._config()
        K = jnp.asarray(np.broadcast_to(self.geom.K, (4, 3, 3)), jnp.float32)
        W, H = self.geom.width, self.geom.height
        if self.sampling == "beams":
            from ghsplat_jax.raster import render as rasterizer

            points, where = self._beam_samples()
            points = jax.tree_util.tree_map(jnp.asarray, points)
            render = lambda surfels, cam, face_points: rasterizer(surfels, cam, cfg, samples=face_points)
        else:
            points = jnp.zeros(4)  # nothing per face: whole faces are rendered
            face_render = sensor_render_fn(self._render_fn, cfg)
            render = lambda surfels, cam, _: face_render(surfels, cam)

        def scan(surfels, w2cs, key):
            self.traces += 1  # runs only while tracing
            cams = Camera(K, w2cs, W, H)
            if self.batching == "vmap":
                out = jax.vmap(render, in_axes=(None, 0, 0))(surfels, cams, points)
            else:  # one face after another inside the same jit (lower peak memory)
                out = jax.lax.map(lambda c: render(surfels, *c), (cams, points))
            depth = out.median_depth if self.depth_mode == "median" else out.depth
            gray = jnp.clip(jnp.mean(out.rgb, -1) / jnp.maximum(out.alpha, 1e-6), 0.0, 1.0) * 255.0
            if self.sampling == "beams":  # exact values along every beam
                at = lambda x: x.reshape(-1)[where]
                ok = (at(out.alpha) >= self.min_alpha) & (at(depth) > 0)
                rng = jnp.where(ok, at(depth) * jnp.asarray(self.table.range_per_z, jnp.float32), 0.0)
                inten = at(gray)
            else:
                rng, inten, ok = resample(depth, out.alpha, gray, self.table, min_alpha=self.min_alpha)
            rng = rng + self.pattern.noise_std * jax.random.normal(key, rng.shape)
            ok = ok & (rng >= self.pattern.min_range) & (rng <= self.pattern.max_range)
            stats = getattr(out, "stats", None)
            overflow = jnp.sum(stats.overflow) if stats is not None else jnp.int32(0)
            pairs = jnp.max(stats.num_pairs) if stats is not None else jnp.int32(0)
            return jnp.where(ok, rng, jnp.nan), inten, overflow, pairs

        self._fn = jax.jit(scan)

    def world_to_cams(self, map_from_lidar: np.ndarray) -> np.ndarray:
        from ghsplat_jax.sim.frames import invert

        return invert(np.asarray(map_from_lidar, np.float64) @ self.faces).astype(np.float32)

    def scan(self, surfels, map_from_lidar: np.ndarray, stamp: float = 0.0, seed: int = 0) -> LidarScan:
        import jax

        w2cs = self.world_to_cams(map_from_lidar)
        from ghsplat_jax.sim.camera_sensor import grown_capacity, initial_capacity

        if self.pair_capacity is None:
            from ghsplat_jax.core.camera import Camera

            K = np.asarray(self.geom.K, np.float32)
            cams = [Camera(K, w, self.geom.width, self.geom.height) for w in w2cs]
            self.pair_capacity = initial_capacity(self._render_fn, surfels, cams, self._config(),
                                                  points=self.sampling == "beams")
        if self._fn is None:
            self._build()
        key = jax.random.PRNGKey(seed)
        for _ in range(8):
            rng, inten, overflow, pairs = self._fn(surfels, w2cs, key)
            if int(overflow) == 0:
                break
            # Grow the pair buffer and recompile once; never keep an incomplete render.
            self.pair_capacity = grown_capacity(int(pairs))
            self._build()
        else:
            raise RuntimeError("LiDAR render kept overflowing its pair buffer")
        return LidarScan(stamp, self.pattern, np.asarray(rng, np.float64), np.asarray(inten, np.float64),
                         self.table, {"pairs": int(pairs), "capacity": self.pair_capacity})
