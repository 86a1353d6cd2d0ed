"""A Jackal-sized ground robot with configurable sensor mounts, and its tf tree.

Frames: map -> base_link -> camera_link -> camera_optical_frame, base_link -> lidar_link.
base_link sits on the ground under the robot's centre (heights below are above the
floor), x forward, y left, z up (REP-103). Defaults follow Clearpath Jackal: body
0.508 x 0.430 x 0.250 m, track 0.376 m, wheel radius 0.098 m, top plate at 0.25 m.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ghsplat_jax.sim import frames


@dataclasses.dataclass(frozen=True)
class Mount:
    """Pose of a sensor link in base_link: position (m) and roll-pitch-yaw (rad)."""

    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        return frames.from_xyz_rpy(self.xyz, self.rpy)


@dataclasses.dataclass(frozen=True)
class Robot:
    length: float = 0.508
    width: float = 0.430
    height: float = 0.250
    track: float = 0.376          # wheel separation (differential drive)
    wheel_radius: float = 0.098
    max_speed: float = 2.0        # m/s
    max_yaw_rate: float = 4.0     # rad/s
    camera: Mount = Mount((0.20, 0.0, 0.45))      # forward-looking, on a short mast
    lidar: Mount = Mount((0.0, 0.0, 0.55))
    map_frame: str = "map"
    base_frame: str = "base_link"
    camera_frame: str = "camera_link"
    optical_frame: str = "camera_optical_frame"
    lidar_frame: str = "lidar_link"

    def static_transforms(self) -> list[frames.Transform]:
        return [
            frames.Transform(self.base_frame, self.camera_frame, self.camera.matrix()),
            frames.Transform(self.camera_frame, self.optical_frame,
                             frames.make_transform(frames.LINK_FROM_OPTICAL_R)),
            frames.Transform(self.base_frame, self.lidar_frame, self.lidar.matrix()),
        ]

    def base_transform(self, x: float, y: float, yaw: float, stamp: float) -> frames.Transform:
        return frames.Transform(self.map_frame, self.base_frame, frames.planar(x, y, yaw), stamp)

    def tf_tree(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> frames.TfTree:
        return frames.TfTree([self.base_transform(x, y, yaw, 0.0), *self.static_transforms()])

    def map_from_optical(self, x: float, y: float, yaw: float) -> np.ndarray:
        return frames.planar(x, y, yaw) @ self.camera.matrix() @ frames.make_transform(frames.LINK_FROM_OPTICAL_R)

    def map_from_lidar(self, x: float, y: float, yaw: float) -> np.ndarray:
        return frames.planar(x, y, yaw) @ self.lidar.matrix()


def robot_from_config(cfg: dict | None) -> Robot:
    """Robot from a dict (e.g. a TOML table): scalar fields plus `camera`/`lidar` tables
    with `xyz` and `rpy_deg`; unknown keys raise."""
    cfg = dict(cfg or {})
    kwargs = {}
    for mount in ("camera", "lidar"):
        if mount in cfg:
            m = dict(cfg.pop(mount))
            xyz = tuple(float(v) for v in m.pop("xyz"))
            rpy = tuple(np.deg2rad(float(v)) for v in m.pop("rpy_deg", (0, 0, 0)))
            if m or len(xyz) != 3 or len(rpy) != 3:
                raise ValueError(f"robot.{mount}: expected xyz=[x,y,z] and rpy_deg=[r,p,y], got extra {sorted(m)}")
            kwargs[mount] = Mount(xyz, rpy)
    names = {f.name for f in dataclasses.fields(Robot)}
    unknown = set(cfg) - names
    if unknown:
        raise ValueError(f"robot: unknown keys {sorted(unknown)}")
    kwargs.update(cfg)
    return Robot(**kwargs)
