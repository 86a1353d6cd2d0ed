"""The Camera pytree: a pinhole camera in the OpenCV convention."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole camera: x right, y down, z forward; pixel (row i, col j) centre at (j+.5, i+.5).

    K (3,3) intrinsics in pixels; world_to_cam (4,4); width and height are static, so
    cameras of one size can be stacked and vmapped.

    Args:
        K: (3,3) intrinsics in pixels (or (..., 3, 3) for a stack); host arrays and lists
            become float32 device arrays.
        world_to_cam: (4,4) rigid transform from world to camera coordinates (OpenCV axes).
        width: image width in pixels (static: part of the pytree's structure).
        height: image height in pixels (static).

    Returns:
        A frozen, jit- and vmap-able camera pytree; `scaled` returns the same view at
        another resolution, `center` the camera centre in world coordinates.
    """

    K: jax.Array
    world_to_cam: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True), default=0)
    height: int = dataclasses.field(metadata=dict(static=True), default=0)

    def __post_init__(self):
        # Coerce host inputs; leave tracers and jax arrays alone.
        for name in ("K", "world_to_cam"):
            value = getattr(self, name)
            if isinstance(value, (list, tuple, np.ndarray)):
                object.__setattr__(self, name, jnp.asarray(value, jnp.float32))

    @property
    def rotation(self) -> jax.Array:
        return self.world_to_cam[..., :3, :3]

    @property
    def translation(self) -> jax.Array:
        return self.world_to_cam[..., :3, 3]

    @property
    def center(self) -> jax.Array:
        """Camera centre in world coordinates."""
        return -jnp.einsum("...ji,...j->...i", self.rotation, self.translation, precision=FLOAT32)

    def scaled(self, factor: float) -> "Camera":
        """The same view at `factor` times the resolution (pixel-centre convention kept)."""
        width, height = int(round(self.width * factor)), int(round(self.height * factor))
        sx, sy = width / self.width, height / self.height
        scale = jnp.diag(jnp.array([sx, sy, 1.0], jnp.float32))
        return Camera(jnp.matmul(scale, self.K, precision=FLOAT32), self.world_to_cam, width, height)


def project_points(points, K, world_to_cam) -> tuple[np.ndarray, np.ndarray]:
    """Host-side pinhole projection in float64: (xy (N,2) pixel coordinates, z (N,) depth along the
    optical axis) of world points (N,3). A point at z = 0 gets the xy of z = 1 (finite, never
    NaN); callers keep the depths they trust (z > 0, or a near plane). Pixel (row i, col j)
    covers [j, j+1) x [i, i+1), so floor(xy) is its pixel."""
    K, w2c = np.asarray(K, np.float64), np.asarray(world_to_cam, np.float64)
    cam = np.asarray(points, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    xy = (cam @ K.T)[:, :2] / np.where(z == 0, 1.0, z)[:, None]
    return xy, z


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_to_cam (4,4) of an OpenCV camera at `eye` looking at `target`.

    Args:
        eye: (3,) camera centre in world coordinates.
        target: (3,) world point the camera looks at (the image centre).
        up: (3,) world direction that appears upward in the image; any perpendicular is
            used when the camera looks along it.

    Returns:
        A (4,4) float32 world-to-camera matrix (x right, y down, z forward).
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ eye
    return w2c.astype(np.float32)


def intrinsics(width: int, height: int, fov_x_deg: float = 60.0) -> np.ndarray:
    """K for a centred principal point and the given horizontal field of view.

    Args:
        width: image width in pixels.
        height: image height in pixels.
        fov_x_deg: horizontal field of view in degrees (square pixels: fx = fy).

    Returns:
        A (3,3) float32 intrinsics matrix with the principal point at (width/2, height/2).
    """
    f = 0.5 * width / np.tan(np.deg2rad(fov_x_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
