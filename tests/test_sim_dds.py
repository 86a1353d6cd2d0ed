"""The live DDS node and a client in separate processes, loopback only, bounded waits."""

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from ghsplat_jax.sim import frames
from ghsplat_jax.sim.camera_sensor import CameraModel
from ghsplat_jax.transport import dds_node

TESTS = Path(__file__).parent

NODE = textwrap.dedent("""
    import json, logging, os, sys, time
    sys.path.insert(0, {tests!r})
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    from ghsplat_jax.sim import beams, camera_sensor, lidar
    from ghsplat_jax.transport import dds_node
    from test_sim_fakes import box_room_renderer
    r = box_room_renderer()
    node = dds_node.SimNode(None, domain_id={domain},
                            camera_renderer=camera_sensor.CameraRenderer(render_fn=r),
                            lidar=lidar.Lidar(beams.get_pattern("vlp16").replace(columns=360), face_width=64,
                                              render_fn=r))
    print("ready", flush=True)
    stop = {stop!r}
    node.spin(duration=90.0, should_stop=lambda: os.path.exists(stop))
    print(json.dumps(node.counts), flush=True)
""")


def _domain() -> int:
    return 100 + os.getpid() % 100  # unique per test run; DDS domains must be < 233


@pytest.fixture()
def node(tmp_path):
    domain = _domain()
    stop = tmp_path / "stop"
    env = dict(os.environ, JAX_PLATFORMS="cpu", CYCLONEDDS_URI=dds_node.localhost_config(domain))
    proc = subprocess.Popen([sys.executable, "-c", NODE.format(tests=str(TESTS), domain=domain, stop=str(stop))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        yield domain, proc, stop
    finally:
        stop.touch()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def test_register_pose_render_and_bad_input(node):
    domain, proc, stop = node
    assert proc.stdout.readline().strip() == "ready"
    client = dds_node.SimClient(domain_id=domain)
    try:
        assert client.wait_for_server(30), "node not discovered on loopback"
        cam = CameraModel.from_fov("front_optical", 40, 30, 60.0)
        ok, msg = client.register(cam)
        assert ok, msg
        assert client.register(cam)[0]  # same camera again: idempotent
        ok, msg = client.register(CameraModel.from_fov("front_optical", 40, 30, 90.0))
        assert not ok and "already registered" in msg
        bad = cam.info(0.0)
        bad.k[0] = 0.0  # malformed: zero focal length
        bad.header.frame_id = "other_optical"
        client.send_request(bad)
        rep = client.receive("reply", 10, lambda r: True)
        assert rep.success is False and "bad camera info" in rep.status_message

        # bad poses: NaN, non-unit quaternion, unknown frame -> ignored
        client.send_raw_pose("front_optical", (0, 0, float("nan")), (0, 0, 0, 1), 1.0)
        client.send_raw_pose("front_optical", (0, 0, 1), (0, 0, 0, 3), 1.0)
        client.send_raw_pose("nobody_optical", (0, 0, 1), (0, 0, 0, 1), 1.0)
        time.sleep(0.3)
        # and the node still serves
        T = frames.from_xyz_rpy((0.5, 0.5, 1.0), (0, 0, 0.4)) @ frames.make_transform(frames.LINK_FROM_OPTICAL_R)
        client.send_pose("front_optical", T, 5.5)
        img = client.receive("render", 30, lambda im: im.header.stamp.sec == 5)
        assert (img.width, img.height, img.encoding, img.header.frame_id) == (40, 30, "rgb8", "front_optical")
        info = client.receive("camera_info", 10, lambda i: i.header.stamp.sec == 5)
        assert np.allclose(np.asarray(info.k).reshape(3, 3), cam.matrix) and (info.width, info.height) == (40, 30)
        tf = client.receive("tf", 10, lambda t: t.transforms[0].child_frame_id == "front_optical")
        assert abs(tf.transforms[0].transform.translation.z - 1.0) < 1e-9

        client.send_pose("lidar_link", frames.from_xyz_rpy((0, 0, 0.5), (0, 0, 0)), 6.0)
        cloud = client.receive("lidar", 30)
        from ghsplat_jax.sim import messages

        pts = messages.point_cloud2_arrays(cloud)
        assert cloud.header.frame_id == "lidar_link" and len(pts["x"]) == 16 * 360
        assert set(pts) == {"x", "y", "z", "intensity", "ring", "time"}
    finally:
        client.close()
    del client
    # the first client vanished (its writers are gone): a new client is still served
    client2 = dds_node.SimClient(domain_id=domain)
    try:
        assert client2.wait_for_server(30)
        assert client2.register(cam)[0]
        client2.send_pose("front_optical", T, 7.0)
        assert client2.receive("render", 30, lambda im: im.header.stamp.sec == 7).width == 40
    finally:
        client2.close()
        stop.touch()
    out, err = proc.communicate(timeout=30)
    counts = json.loads(out.strip().splitlines()[-1])
    assert counts["renders"] == 2 and counts["scans"] == 1 and counts["registrations"] == 1
    assert counts["rejected"] == 2 + 3  # two registrations, three poses
    assert "non-finite" in err and "quaternion norm" in err and "unknown frame 'nobody_optical'" in err


def test_localhost_config_is_loopback_only():
    xml = dds_node.localhost_config(5)
    assert 'address="127.0.0.1"' in xml and "<AllowMulticast>false</AllowMulticast>" in xml
    assert '<Peer address="127.0.0.1"/>' in xml and 'id="5"' in xml
