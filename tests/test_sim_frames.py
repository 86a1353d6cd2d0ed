import json

import numpy as np
import pytest

from ghsplat_jax.sim import frames, robot
from ghsplat_jax.sim import trajectory as tj


def test_optical_frame_is_opencv_in_rep103_body():
    R = frames.LINK_FROM_OPTICAL_R
    assert np.allclose(R @ [0, 0, 1], [1, 0, 0])   # optical z = forward (body x)
    assert np.allclose(R @ [1, 0, 0], [0, -1, 0])  # optical x = right (body -y)
    assert np.allclose(R @ [0, 1, 0], [0, 0, -1])  # optical y = down (body -z)
    assert np.isclose(np.linalg.det(R), 1)


def test_tf_tree_chain_and_lookup():
    r = robot.Robot()
    tree = r.tf_tree(1.0, 2.0, np.pi / 2)
    assert tree.frames == {"map", "base_link", "camera_link", "camera_optical_frame", "lidar_link"}
    T = tree.lookup("map", "camera_optical_frame")
    assert np.allclose(T, r.map_from_optical(1.0, 2.0, np.pi / 2))
    # robot heading +y: the camera looks along +y, 0.2 m ahead of base_link
    assert np.allclose(T[:3, 2], [0, 1, 0], atol=1e-12) and np.allclose(T[:3, 3], [1.0, 2.2, 0.45])
    assert np.allclose(tree.lookup("lidar_link", "map") @ tree.lookup("map", "lidar_link"), np.eye(4))
    with pytest.raises(KeyError):
        tree.lookup("map", "nowhere")
    with pytest.raises(ValueError):
        tree.set(frames.Transform("camera_link", "base_link", np.eye(4)))  # second parent


def test_world_to_cam_matches_look_at():
    from ghsplat_jax.core.camera import look_at

    r = robot.Robot()
    T = r.map_from_optical(0.0, 0.0, 0.0)
    eye = T[:3, 3]
    assert np.allclose(frames.world_to_cam(T), look_at(eye, eye + [1, 0, 0]), atol=1e-6)


def test_pose_validation():
    with pytest.raises(ValueError):
        frames.from_pose([0, 0, np.nan], [0, 0, 0, 1])
    with pytest.raises(ValueError):
        frames.from_pose([0, 0, 0], [0, 0, 0, 2])
    T = frames.from_pose([1, 2, 3], frames.quat_xyzw(frames.rpy_matrix(0.1, 0.2, 0.3)))
    assert np.allclose(T[:3, :3], frames.rpy_matrix(0.1, 0.2, 0.3))


def test_robot_config_mounts():
    r = robot.robot_from_config({"camera": {"xyz": [0.1, 0, 0.6], "rpy_deg": [0, 10, 90]}, "track": 0.4})
    assert r.track == 0.4 and np.allclose(r.camera.rpy, np.deg2rad([0, 10, 90]))
    # yaw 90: camera looks left (+y), pitched down 10 deg
    z = r.map_from_optical(0, 0, 0)[:3, 2]
    assert np.allclose(z, [0, np.cos(np.deg2rad(10)), -np.sin(np.deg2rad(10))], atol=1e-9)
    with pytest.raises(ValueError):
        robot.robot_from_config({"wheels": 6})


def test_diff_drive_circle_and_straight():
    # v = 1, w = 1 for 2 pi seconds: a full unit circle back to the start
    traj = tj.integrate_twist(np.ones(100), np.ones(100), 2 * np.pi / 100)
    assert np.allclose([traj.x[-1], traj.y[-1]], [0, 0], atol=1e-9)
    assert np.allclose(np.hypot(traj.x, traj.y - 1), 1)  # centre (0, 1), radius v/w
    v, w = tj.wheels_to_twist(np.array([10.0]), np.array([10.0]), 0.376, 0.098)
    assert np.isclose(v[0], 0.98) and w[0] == 0
    straight = tj.integrate_twist(0.5, 0.0, 0.1, start=(1, 1, np.pi / 2), t0=0.0)
    assert np.allclose([straight.x[-1], straight.y[-1]], [1, 1.05])


def test_waypoints_constant_speed_and_turns(tmp_path):
    traj = tj.from_waypoints([[0, 0], [2, 0], [2, 1]], speed=0.5, turn_rate=1.0)
    v, _ = traj.velocities()
    assert np.allclose(v[v > 0], 0.5)
    assert np.isclose(traj.duration, 4 + np.pi / 2 + 2)
    x, y, yaw = traj.at(5.0)  # during the in-place turn at (2, 0)
    assert np.allclose([x, y], [2, 0]) and 0 < yaw < np.pi / 2
    (tmp_path / "w.csv").write_text("x,y\n0,0\n2,0\n2,1\n")
    (tmp_path / "w.json").write_text(json.dumps({"waypoints": [{"x": 0, "y": 0}, {"x": 2, "y": 0}, {"x": 2, "y": 1}]}))
    (tmp_path / "w.toml").write_text("[[waypoint]]\nx=0\ny=0\n[[waypoint]]\nx=2\ny=0\n[[waypoint]]\nx=2\ny=1\n")
    for name in ("w.csv", "w.json", "w.toml"):
        t2 = tj.load_waypoints(tmp_path / name, speed=0.5)
        assert np.isclose(t2.duration, traj.duration)
    (tmp_path / "timed.csv").write_text("x,y,yaw,t\n0,0,0,0\n1,0,0.5,3\n")
    t3 = tj.load_waypoints(tmp_path / "timed.csv")
    assert np.allclose(t3.at(1.5), [0.5, 0, 0.25])
    (tmp_path / "bad.csv").write_text("x,q\n0,0\n")
    with pytest.raises(ValueError, match="bad.csv"):
        tj.load_waypoints(tmp_path / "bad.csv")


def test_yaw_interpolates_across_pi():
    traj = tj.Trajectory(np.array([0.0, 1.0]), np.zeros(2), np.zeros(2), np.array([3.0, -3.0]))
    assert abs(abs(traj.at(0.5)[2]) - np.pi) < 0.01


def test_aisles_between_rows_and_rows_from_points(tmp_path):
    rows = [tj.RowBox(0, 10, -1.2, -0.6), tj.RowBox(0, 10, 0.6, 1.2), tj.RowBox(0, 10, 2.4, 3.0)]
    wp = tj.aisle_waypoints(rows, margin=1.0)
    assert np.allclose(wp, [[-1, 0], [11, 0], [11, 1.8], [-1, 1.8]])
    rng = np.random.default_rng(0)
    pts = np.concatenate([np.c_[rng.uniform(r.xmin, r.xmax, 500), rng.uniform(r.ymin, r.ymax, 500),
                                rng.uniform(0.2, 1.5, 500)] for r in rows] +
                         [np.c_[rng.uniform(-2, 12, 2000), rng.uniform(-3, 5, 2000), np.zeros(2000)]])  # floor
    found = tj.rows_from_points(pts)
    assert len(found) == 3
    for a, b in zip(found, rows):
        assert abs(a.ymin - b.ymin) < 0.15 and abs(a.ymax - b.ymax) < 0.15 and abs(a.xmax - b.xmax) < 0.2
    (tmp_path / "rows.json").write_text(json.dumps({"rows": [vars(r) for r in rows]}))
    assert tj.load_row_boxes(tmp_path / "rows.json") == rows
    with pytest.raises(ValueError):
        tj.aisle_waypoints([tj.RowBox(0, 1, 0, 1), tj.RowBox(0, 1, 1.1, 2)])  # 0.1 m gap: no aisle


def test_rows_from_points_ignores_end_walls():
    rng = np.random.default_rng(1)
    rows = [tj.RowBox(0, 8, y - 0.3, y + 0.3) for y in (-1.6, 0.0, 1.6)]
    pts = [np.c_[rng.uniform(r.xmin, r.xmax, 3000), rng.uniform(r.ymin, r.ymax, 3000), rng.uniform(0.2, 1.2, 3000)]
           for r in rows]
    for x in (-3.5, 11.5):  # walls across the row ends
        pts.append(np.c_[np.full(2000, x), rng.uniform(-3, 3, 2000), rng.uniform(0, 2, 2000)])
    found = tj.rows_from_points(np.concatenate(pts))
    assert len(found) == 3
    for a, b in zip(found, rows):
        assert abs(a.xmin - b.xmin) < 0.2 and abs(a.xmax - b.xmax) < 0.2 and abs(a.ymin - b.ymin) < 0.15
