"""A live web viewer (viser): the scene as Gaussian splats, the robot and its frames, the
camera frustum with the latest rendered image, and the latest LiDAR cloud.

Listens on 127.0.0.1 unless told otherwise. `sink(topic, msg, t, payload)` consumes the
stream of sim/simulate.py.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.core import quaternions
from ghsplat_jax.sim import frames


def _wxyz(T: np.ndarray) -> np.ndarray:
    """viser's w-x-y-z orientation of a pose."""
    return quaternions.from_rotation_matrix(np.asarray(T)[:3, :3])


def surfel_splats(surfels, max_count: int = 200_000, seed: int = 0) -> dict:
    """centers, covariances (flat: third axis 1 mm), rgbs, opacities for viser, subsampled."""
    import jax

    s = jax.tree_util.tree_map(np.asarray, surfels)
    n = s.means.shape[0]
    idx = np.sort(np.random.default_rng(seed).choice(n, max_count, replace=False)) if n > max_count else np.arange(n)
    R = quaternions.to_rotation_matrix_np(s.quats[idx])
    scales = np.exp(np.c_[s.log_scales[idx], np.full(len(idx), np.log(1e-3))])
    cov = np.einsum("nij,nj,nkj->nik", R, scales ** 2, R)
    rgb = np.clip(s.sh_dc[idx] * 0.28209479177387814 + 0.5, 0, 1)
    opacity = 1 / (1 + np.exp(-s.opacity_logits[idx]))
    return {"centers": s.means[idx].astype(np.float32), "covariances": cov.astype(np.float32),
            "rgbs": rgb.astype(np.float32), "opacities": opacity[:, None].astype(np.float32)}


class SimViewer:
    def __init__(self, scene, robot, host: str = "127.0.0.1", port: int = 8080, max_splats: int = 200_000):
        import viser

        self.robot = robot
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.add_gaussian_splats("/scene", **surfel_splats(scene.surfels, max_splats))
        self.base = self.server.scene.add_frame("/base_link", axes_length=0.3, axes_radius=0.01)
        self.server.scene.add_box("/base_link/body", color=(200, 160, 40),
                                  dimensions=(robot.length, robot.width, robot.height),
                                  position=(0.0, 0.0, robot.height / 2 + 0.05))
        cam_T = robot.camera.matrix() @ frames.make_transform(frames.LINK_FROM_OPTICAL_R)
        self.frustum = None
        self._cam_T = cam_T
        self.lidar_frame = self.server.scene.add_frame("/base_link/lidar_link", axes_length=0.15, axes_radius=0.005,
                                                       position=robot.lidar.matrix()[:3, 3],
                                                       wxyz=_wxyz(robot.lidar.matrix()))
        for tag in getattr(scene, "tags", []):
            self.server.scene.add_frame(f"/tags/{tag.id}", axes_length=tag.size, axes_radius=0.005,
                                        position=tag.world_from_tag[:3, 3], wxyz=_wxyz(tag.world_from_tag))
        self.counts = {"images": 0, "clouds": 0, "poses": 0}

    def set_pose(self, map_from_base: np.ndarray) -> None:
        self.base.position = map_from_base[:3, 3]
        self.base.wxyz = _wxyz(map_from_base)
        self.counts["poses"] += 1

    def set_image(self, rgb: np.ndarray, K: np.ndarray, width: int, height: int) -> None:
        fov_y = 2 * np.arctan(height / 2 / K[1, 1])
        img = np.clip(np.nan_to_num(rgb) * 255, 0, 255).astype(np.uint8)
        self.frustum = self.server.scene.add_camera_frustum(
            "/base_link/camera_optical_frame", fov=float(fov_y), aspect=width / height, scale=0.25, image=img,
            position=self._cam_T[:3, 3], wxyz=_wxyz(self._cam_T))
        self.counts["images"] += 1

    def set_cloud(self, points_lidar: np.ndarray) -> None:
        p = points_lidar[np.isfinite(points_lidar).all(1)]
        z = p[:, 2] if len(p) else np.zeros(0)
        t = (z - z.min()) / max(float(np.ptp(z)), 1e-6) if len(p) else z
        colours = np.stack([255 * t, 80 + 100 * (1 - t), 255 * (1 - t)], 1).astype(np.uint8)
        self.server.scene.add_point_cloud("/base_link/lidar_link/points", p.astype(np.float32), colours,
                                          point_size=0.03)
        self.counts["clouds"] += 1

    def sink(self, topic: str, msg, t: float, payload) -> None:
        if topic == "/tf":
            self.set_pose(payload.matrix)
        elif topic == "/render":
            self.set_image(payload.rgb, payload.model.matrix, payload.model.width, payload.model.height)
        elif topic == "/lidar":
            self.set_cloud(payload.points().reshape(-1, 3))

    def close(self) -> None:
        self.server.stop()
