"""Camera sensors: a pinhole model with its CameraInfo, and a renderer that compiles
once per image size (cameras of one size share it and render in one call, one after another).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ghsplat_jax.sim import frames


@dataclasses.dataclass(frozen=True)
class CameraModel:
    """An undistorted pinhole camera whose images are in `frame_id` (an optical frame)."""

    frame_id: str
    width: int
    height: int
    K: tuple[float, ...]  # 3x3 row-major

    def __post_init__(self):
        K = np.asarray(self.K, np.float64).reshape(-1)
        if K.size != 9 or not np.all(np.isfinite(K)):
            raise ValueError("K must be 9 finite numbers")
        object.__setattr__(self, "K", tuple(float(v) for v in K))
        if not self.frame_id or not isinstance(self.frame_id, str):
            raise ValueError("camera needs a frame id")
        if not (8 <= self.width <= 8192 and 8 <= self.height <= 8192):
            raise ValueError(f"image size {self.width}x{self.height} out of range 8..8192")
        k = self.matrix
        if not (k[0, 0] > 0 and k[1, 1] > 0 and k[2, 2] == 1 and k[1, 0] == k[2, 0] == k[2, 1] == 0):
            raise ValueError("K must be upper triangular with positive focal lengths and K[2,2] = 1")

    @property
    def matrix(self) -> np.ndarray:
        return np.asarray(self.K, np.float64).reshape(3, 3)

    @classmethod
    def from_fov(cls, frame_id: str, width: int, height: int, fov_x_deg: float) -> "CameraModel":
        from ghsplat_jax.core.camera import intrinsics

        return cls(frame_id, int(width), int(height), tuple(intrinsics(width, height, fov_x_deg).reshape(-1)))

    @classmethod
    def from_camera_info(cls, msg) -> "CameraModel":
        if not all(abs(float(v)) <= 1e-12 for v in msg.d):  # NaN fails this test too
            raise ValueError("only undistorted cameras can be rendered (D must be zero)")
        return cls(msg.header.frame_id, int(msg.width), int(msg.height), tuple(float(v) for v in msg.k))

    def info(self, t: float):
        from ghsplat_jax.sim import messages

        return messages.camera_info(self.matrix, self.width, self.height, t, self.frame_id)


def counted_capacity(surfels, cameras, cfg, headroom: float = 1.25, points: bool = False) -> int:
    """Pair capacity from an exact count for these views (the rasterizer's cheap binning
    pass), with headroom for the next poses: the first compilation is usually the only one.
    `points`: the views render sample points (`raster.samples`), not whole images."""
    from ghsplat_jax.raster import capacity_bucket
    from ghsplat_jax.raster.render import binning_config, count_pairs

    needed = max(int(count_pairs(surfels, cam, binning_config(cfg), points)[0]) for cam in cameras)
    return capacity_bucket(int(needed * headroom))


def sensor_config(raster_config, pair_capacity, background=(0.0, 0.0, 0.0), median: bool = False):
    """The sensors' raster settings: a static pair capacity whose overflow is reported, not raised,
    and the forward-only fast path: no distortion sums, the median depth only when it is read."""
    from ghsplat_jax.raster import RasterConfig

    cfg = raster_config or RasterConfig(near=0.2, background=tuple(background))
    return dataclasses.replace(cfg, pair_capacity=pair_capacity, on_overflow="report", distortion=False,
                               median=median)


def sensor_render_fn(render_fn, cfg):
    """`render_fn` (a test fake) or the rasterizer with `cfg`."""
    if render_fn is not None:
        return render_fn
    from ghsplat_jax.raster import render

    return lambda surfels, cam: render(surfels, cam, cfg)


def initial_capacity(render_fn, surfels, cameras, cfg, points: bool = False) -> int:
    """First pair capacity: an exact count for the rasterizer; a fixed guess for a fake renderer."""
    return 1 << 14 if render_fn is not None else counted_capacity(surfels, cameras, cfg, points=points)


def grown_capacity(pairs: int) -> int:
    """Capacity after an overflow of `pairs` needed pairs (10% headroom)."""
    from ghsplat_jax.raster import capacity_bucket

    return capacity_bucket(int(pairs * 1.1))


def _frame_images(rgb, alpha, depth, normal):
    """The frame's published images from a render, inside the jitted call: rgb clipped to [0, 1];
    depth and unit normals NaN where alpha < 0.5 (float32 throughout). On the host, NumPy took
    about 17 ms per 640x480 frame for this (measured), 7% of the frame."""
    import jax.numpy as jnp

    hit = alpha >= 0.5
    norm = jnp.sqrt(normal[..., 0] ** 2 + normal[..., 1] ** 2 + normal[..., 2] ** 2)[..., None]
    unit = normal / jnp.maximum(norm, 1e-12)
    return (jnp.clip(rgb, 0.0, 1.0).astype(jnp.float32), alpha.astype(jnp.float32),
            jnp.where(hit, depth, jnp.nan).astype(jnp.float32),
            jnp.where(hit[..., None], unit, jnp.nan).astype(jnp.float32))


@dataclasses.dataclass
class CameraFrame:
    stamp: float
    model: CameraModel
    map_from_optical: np.ndarray
    rgb: np.ndarray          # (H,W,3) float32 in [0,1]
    alpha: np.ndarray        # (H,W)
    depth: np.ndarray        # (H,W) z-depth, NaN where alpha < 0.5
    normal: np.ndarray       # (H,W,3) world-frame unit normals, NaN where alpha < 0.5


class CameraRenderer:
    """Renders CameraModels at optical-frame poses; `traces` counts compilations.

    `pair_capacity=None` sizes the rasterizer's pair buffer from an exact count at the
    first frame; a later overflow grows it (one recompilation), never a partial image.
    """

    def __init__(self, render_fn: Callable | None = None, raster_config=None, pair_capacity: int | None = None,
                 background=(0.0, 0.0, 0.0)):
        self._render_fn = render_fn
        self._raster_config = raster_config
        self._background = tuple(background)
        self.pair_capacity = pair_capacity
        self.traces = 0
        self._fns: dict[tuple[int, int], Callable] = {}

    def _config(self):
        return sensor_config(self._raster_config, self.pair_capacity, self._background)

    def program(self, width: int, height: int):
        """The jit-compiled render of a batch of cameras of this image size: (surfels, Ks, w2cs) ->
        (rgb, alpha, depth, normal, overflow, pairs); one compilation per size."""
        key = (width, height)
        if key not in self._fns:
            import jax
            import jax.numpy as jnp

            from ghsplat_jax.core.camera import Camera

            render = sensor_render_fn(self._render_fn, self._config())

            def many(surfels, Ks, w2cs):
                self.traces += 1  # runs only while tracing
                # One camera after another: under vmap the compositor's batch slices become gathers
                # inside every per-pixel fusion, which made a 640x480 frame 3x slower on a CPU.
                out = jax.lax.map(lambda Kw: render(surfels, Camera(Kw[0], Kw[1], width, height)), (Ks, w2cs))
                stats = getattr(out, "stats", None)
                overflow = jnp.sum(stats.overflow) if stats is not None else jnp.int32(0)
                pairs = jnp.max(stats.num_pairs) if stats is not None else jnp.int32(0)
                return (*_frame_images(out.rgb, out.alpha, out.depth, out.normal), overflow, pairs)

            self._fns[key] = jax.jit(many)
        return self._fns[key]

    def render(self, surfels, model: CameraModel, map_from_optical: np.ndarray, stamp: float = 0.0) -> CameraFrame:
        return self.render_many(surfels, [model], [map_from_optical], stamp)[0]

    def render_many(self, surfels, models: list[CameraModel], poses: list[np.ndarray],
                    stamp: float = 0.0) -> list[CameraFrame]:
        """Cameras of one size render in one call; other sizes in their own."""
        out: list[CameraFrame | None] = [None] * len(models)
        groups: dict[tuple[int, int], list[int]] = {}
        for i, m in enumerate(models):
            groups.setdefault((m.width, m.height), []).append(i)
        for (W, H), idx in groups.items():
            Ks = np.stack([models[i].matrix for i in idx]).astype(np.float32)
            w2cs = np.stack([frames.world_to_cam(poses[i]) for i in idx])
            if self.pair_capacity is None:
                from ghsplat_jax.core.camera import Camera

                cams = [Camera(K, w, W, H) for K, w in zip(Ks, w2cs)]
                self.pair_capacity = initial_capacity(self._render_fn, surfels, cams, self._config())
            for _ in range(8):
                rgb, alpha, depth, normal, overflow, pairs = self.program(W, H)(surfels, Ks, w2cs)
                if int(overflow) == 0:
                    break
                self.pair_capacity = grown_capacity(int(pairs))
                self._fns.clear()  # grow the pair buffer: one recompilation, never a partial image
            else:
                raise RuntimeError("camera render kept overflowing its pair buffer")
            rgb, alpha, depth, normal = (np.asarray(a) for a in (rgb, alpha, depth, normal))
            for j, i in enumerate(idx):
                out[i] = CameraFrame(stamp, models[i], np.asarray(poses[i], np.float64), rgb[j], alpha[j], depth[j],
                                     normal[j])
        return out
