"""`ghsplat simulate` end to end: a bag rosbags reads back; clean failures before output."""

import numpy as np
import pytest

pytest.importorskip("rosbags")

from ghsplat_jax.data.ply import save_ply
from ghsplat_jax.scene import surfaces
from ghsplat_jax.scene.merge import merge
from ghsplat_jax.sim import messages as m
from ghsplat_jax.transport import recorder


@pytest.fixture(scope="module")
def rows_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("rows")
    green, grey = surfaces.constant_colour((0.2, 0.6, 0.2)), surfaces.constant_colour((0.5, 0.45, 0.4))
    faces = ("+x", "-x", "+y", "-y", "+z")
    save_ply(merge([surfaces.box((0, -1.2, 0), (3, -0.6, 1.0), 0.15, green, faces=faces),
                    surfaces.box((0, 0.6, 0), (3, 1.2, 1.0), 0.15, green, faces=faces),
                    surfaces.box((-2, -2.5, -0.02), (5, 2.5, 0.0), 0.15, grey, faces=("+z",))]), d / "rows.ply")
    return d / "rows.ply"


def test_simulate_records_bag(rows_scene, tmp_path):
    from ghsplat_jax.cli import main

    bag = tmp_path / "run.mcap"
    rc = main(["simulate", str(rows_scene), "--trajectory", "aisles", "--record", str(bag), "--quiet",
               "--width", "48", "--height", "32", "--lidar-face-width", "160", "--max-events", "4", "--depth"])
    assert rc == 0
    msgs = recorder.read_bag(bag)
    assert set(msgs) == {"/tf_static", "/tf", "/robot_pose", "/render", "/camera_info", "/render_depth", "/lidar"}
    assert len(msgs["/render"]) == 2 and len(msgs["/lidar"]) == 2 and len(msgs["/tf_static"]) == 1
    # everything time-stamped, bag time = header stamp
    for topic in ("/render", "/camera_info", "/lidar", "/robot_pose"):
        for t, msg in msgs[topic]:
            assert t == m.to_nanoseconds(m.to_seconds(msg.header.stamp)) and t > 0
    # camera info consistent with the image
    (_, img), (_, info) = msgs["/render"][0], msgs["/camera_info"][0]
    assert (img.width, img.height, img.header.frame_id) == (info.width, info.height, info.header.frame_id)
    assert info.header.frame_id == "camera_optical_frame" and not np.any(info.d)
    assert m.image_array(img).shape == (32, 48, 3)
    # the aisle (between rows at y = +-0.6) starts 1 m before the rows, heading +x
    _, pose = msgs["/robot_pose"][0]
    assert np.allclose([pose.pose.position.x, pose.pose.position.y], [-1.0, 0.0], atol=0.1)
    # lidar: VLP-16 fields; ahead (rows start 1 m in front), the rows' inner faces at |y| = 0.6
    pts = m.point_cloud2_arrays(msgs["/lidar"][0][1])
    assert set(pts) == {"x", "y", "z", "intensity", "ring", "time"} and pts["ring"].max() == 15
    side = (pts["x"] > 1.5) & (pts["x"] < 3.5) & (np.abs(pts["z"]) < 0.3) & (np.abs(pts["y"]) < 1.3)
    y_world = pts["y"][side] + pose.pose.position.y  # robot heads +x: lidar y is parallel to world y
    err = np.abs(np.abs(y_world) - 0.6)
    assert side.sum() > 100 and np.median(err) < 1e-3 and np.mean(err < 0.02) > 0.95  # edges of the rows aside
    depth = m.image_array(msgs["/render_depth"][0][1])
    assert depth.dtype == np.float32 and np.isfinite(depth).all()


def test_bad_scene_fails_before_output(tmp_path, capsys):
    from ghsplat_jax.cli import main

    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n")
    bag = tmp_path / "run.mcap"
    assert main(["simulate", str(bad), "--record", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "broken.ply" in err
    assert not (tmp_path / "run").exists()
    assert main(["simulate", str(tmp_path / "missing.ply"), "--record", str(bag)]) == 2
    assert "no such scene file" in capsys.readouterr().err


def test_velocity_command_trajectory(tmp_path):
    from ghsplat_jax.sim import trajectory as tj

    cmd = tmp_path / "cmd.csv"
    cmd.write_text("v,w\n" + "0.5,0.0\n" * 10 + "0.5,0.5\n" * 10)
    assert tj.is_twist_file(cmd) and not tj.is_twist_file(tmp_path / "path.json")
    traj = tj.load_twist(cmd, dt=0.1)
    assert np.isclose(traj.duration, 2.0) and np.isclose(traj.x[10], 0.5) and np.isclose(traj.yaw[-1], 0.5)
    slow = tj.load_twist(cmd, dt=0.1, max_speed=0.25, max_yaw_rate=0.1)  # the robot's limits clamp commands
    assert np.isclose(slow.x[10], 0.25) and np.isclose(slow.yaw[-1], 0.1)


def test_live_and_robot_config_errors_stop_before_publishing(rows_scene, tmp_path, capsys):
    from ghsplat_jax.cli import main

    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"not a ply")
    assert main(["simulate", str(bad), "--live", "--domain-id", "151"]) == 2
    assert "broken.ply" in capsys.readouterr().err
    robot_toml = tmp_path / "robot.toml"
    robot_toml.write_text("[robot]\nwheels = 6\n")
    assert main(["simulate", str(rows_scene), "--robot", str(robot_toml), "--record", str(tmp_path / "r.mcap")]) == 2
    assert "unknown keys ['wheels']" in capsys.readouterr().err and not (tmp_path / "r").exists()
    assert main(["simulate", str(rows_scene), "--trajectory", str(tmp_path / "nope.csv"), "--live"]) == 2
    assert main(["simulate", str(rows_scene)]) == 2  # nothing to do
    assert "nothing to do" in capsys.readouterr().err
