"""Drive the robot along a trajectory in simulated time and produce time-stamped sensor
messages: tf, camera (rgb, optional depth and normals) with CameraInfo, LiDAR, and the
ground-truth robot pose. Sinks (a bag recorder, the live DDS node, the viewer) consume them.

Topics: /tf_static (once), /tf (map -> base_link at every event), /render and /camera_info
(the robot camera, frame camera_optical_frame), /render_depth, /render_normals (on
request), /lidar (frame lidar_link), /robot_pose (geometry_msgs/PoseStamped, ground truth).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Iterator

import numpy as np

from ghsplat_jax.sim import messages
from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
from ghsplat_jax.sim.lidar import Lidar
from ghsplat_jax.sim.robot import Robot
from ghsplat_jax.sim.trajectory import Trajectory


@dataclasses.dataclass
class SimConfig:
    camera_rate: float = 10.0       # Hz of simulated time; 0 disables the camera
    lidar_rate: float = 10.0        # Hz; 0 disables the LiDAR
    clock_start: float = 1.0        # simulated time of the trajectory's start (s); >0 keeps stamps non-zero
    duration: float | None = None   # cap on simulated seconds
    max_events: int | None = None   # cap on sensor events (quick runs)
    depth: bool = False
    normals: bool = False
    organised_cloud: bool = False


@dataclasses.dataclass
class Event:
    t: float                 # simulated time (stamp)
    pose: np.ndarray         # (x, y, yaw) of base_link in map
    kind: str                # "camera" or "lidar"


def schedule(traj: Trajectory, cfg: SimConfig) -> list[Event]:
    end = traj.duration if cfg.duration is None else min(traj.duration, cfg.duration)
    events = []
    for kind, rate in (("camera", cfg.camera_rate), ("lidar", cfg.lidar_rate)):
        if rate > 0:
            times = np.arange(int(np.floor(end * rate + 1e-9)) + 1) / rate
            events += [(float(t), kind) for t in times]
    events.sort(key=lambda e: (e[0], e[1]))
    if cfg.max_events is not None:
        events = events[:cfg.max_events]
    return [Event(cfg.clock_start + t, traj.at(traj.t[0] + t), kind) for t, kind in events]


def run(surfels, robot: Robot, traj: Trajectory, cfg: SimConfig, camera: CameraModel, lidar: Lidar | None,
        renderer: CameraRenderer | None = None, progress: Callable[[int, int], None] | None = None
        ) -> Iterator[tuple[str, object, float, object]]:
    """Yields (topic, rosbags message, stamp, payload) in time order; payload is the
    CameraFrame / LidarScan / pose for sinks that want arrays (viewer, live node)."""
    renderer = renderer or CameraRenderer()
    if camera.frame_id != robot.optical_frame:
        raise ValueError(f"the robot camera must render in {robot.optical_frame!r}")
    events = schedule(traj, cfg)
    static = robot.static_transforms()
    yield "/tf_static", messages.tf_message(static, cfg.clock_start), cfg.clock_start, static
    last_tf = None
    for i, ev in enumerate(events):
        x, y, yaw = ev.pose
        if last_tf != ev.t:
            base = robot.base_transform(x, y, yaw, ev.t)
            yield "/tf", messages.tf_message([base]), ev.t, base
            yield "/robot_pose", messages.pose_stamped(base.matrix, ev.t, robot.map_frame), ev.t, base.matrix
            last_tf = ev.t
        if ev.kind == "camera":
            frame = renderer.render(surfels, camera, robot.map_from_optical(x, y, yaw), ev.t)
            yield "/render", messages.image(frame.rgb, ev.t, camera.frame_id, "rgb8"), ev.t, frame
            yield "/camera_info", camera.info(ev.t), ev.t, camera
            if cfg.depth:  # REP-118 would allow NaN; we write 0 = no surface (no NaN on disk)
                yield "/render_depth", messages.image(np.nan_to_num(frame.depth, nan=0.0), ev.t, camera.frame_id,
                                                      "32FC1"), ev.t, frame
            if cfg.normals:
                yield "/render_normals", messages.image(np.nan_to_num(frame.normal, nan=0.0), ev.t, camera.frame_id,
                                                        "32FC3"), ev.t, frame
        elif lidar is not None:
            scan = lidar.scan(surfels, robot.map_from_lidar(x, y, yaw), ev.t, seed=i)
            f = scan.fields(cfg.organised_cloud)
            shape = scan.ranges.shape if cfg.organised_cloud else None
            yield "/lidar", messages.point_cloud2(f, ev.t, robot.lidar_frame, shape), ev.t, scan
        if progress:
            progress(i + 1, len(events))


def pace(start_wall: float, start_sim: float, t: float, speed: float = 1.0) -> None:
    """Sleep until simulated time t is due on the wall clock (live mode)."""
    delay = start_wall + (t - start_sim) / speed - time.monotonic()
    if delay > 0:
        time.sleep(delay)
