"""`ghsplat simulate --foxglove`: a WebSocket client (the `websockets` package, Foxglove's
protocol) subscribes and receives a camera frame and a point cloud equal to the simulator's."""

from __future__ import annotations

import base64
import json
import struct

import numpy as np
import pytest

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")

from test_sim_fakes import box_room_renderer

from ghsplat_jax.sim import beams, simulate
from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
from ghsplat_jax.sim.lidar import Lidar
from ghsplat_jax.sim.robot import Robot
from ghsplat_jax.sim.trajectory import from_waypoints

# foxglove-sdk >= 0.2x speaks "foxglove.sdk.v1"; older servers "foxglove.websocket.v1" (same frames)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def _simulated_messages():
    """(topic, message, stamp) of a short drive in a box room, rendered analytically."""
    robot = Robot()
    traj = from_waypoints(np.array([[0.0, 0.0], [1.0, 0.5]]), speed=1.0)
    camera = CameraModel.from_fov(robot.optical_frame, 32, 24, 70.0)
    lidar = Lidar(beams.get_pattern("vlp16"), face_width=48, render_fn=box_room_renderer())
    cfg = simulate.SimConfig(camera_rate=5.0, lidar_rate=5.0, max_events=4)
    run = simulate.run(None, robot, traj, cfg, camera, lidar, CameraRenderer(render_fn=box_room_renderer()))
    return [(topic, msg, t) for topic, msg, t, _ in run]


def _decoder(channel: dict):
    """A protobuf message class from an advertised channel's FileDescriptorSet."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def test_foxglove_client_receives_the_simulators_image_and_cloud():
    from ghsplat_jax.sim import messages as m
    from ghsplat_jax.transport.foxglove_sink import FoxgloveSink

    sim = _simulated_messages()
    sink = FoxgloveSink(port=0)  # 127.0.0.1, a free port
    try:
        for topic, msg, t in sim:  # first pass: channels exist (and are advertised)
            sink.sink(topic, msg, t)
        with websockets_sync.connect(f"ws://127.0.0.1:{sink.port}", subprotocols=SUBPROTOCOLS,
                                     open_timeout=10) as ws:
            assert ws.subprotocol in SUBPROTOCOLS
            channels = {}
            while not {"/render", "/lidar", "/camera_info", "/tf", "/robot_pose"} <= set(channels):
                op = json.loads(ws.recv(timeout=10))
                if op["op"] == "advertise":
                    channels.update({c["topic"]: c for c in op["channels"]})
            wanted = ["/render", "/lidar", "/camera_info", "/robot_pose"]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[topic]["id"]} for i, topic in enumerate(wanted)]}))
            # the server applies the subscription asynchronously: publish until frames arrive
            received = {}
            for _ in range(20):
                for topic, msg, t in sim:
                    sink.sink(topic, msg, t)
                try:
                    while len(received) < len(wanted):
                        frame = ws.recv(timeout=0.5)
                        if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                            sub, log_time = struct.unpack_from("<IQ", frame, 1)
                            received.setdefault(wanted[sub], (log_time, frame[13:]))
                except TimeoutError:
                    pass
                if len(received) == len(wanted):
                    break
    finally:
        sink.close()
    assert set(received) == set(wanted)

    # The subscription may start mid-pass: compare each topic's first received message with the
    # simulated message of the same log time.
    by_time = {(topic, m.to_nanoseconds(t)): (msg, t) for topic, msg, t in sim}
    expected = {topic: by_time[topic, log_time] for topic, (log_time, _) in received.items()}
    image_msg, t_image = expected["/render"]
    log_time, payload = received["/render"]
    image = _decoder(channels["/render"]).FromString(payload)
    assert (image.width, image.height, image.encoding, image.frame_id) == (32, 24, "rgb8", "camera_optical_frame")
    assert image.data == np.asarray(image_msg.data, np.uint8).tobytes() and image.step == 32 * 3
    assert image.timestamp.seconds + image.timestamp.nanos * 1e-9 == pytest.approx(t_image)
    assert log_time == m.to_nanoseconds(t_image)

    cloud_msg, t_cloud = expected["/lidar"]
    cloud = _decoder(channels["/lidar"]).FromString(received["/lidar"][1])
    assert cloud.frame_id == "lidar_link" and cloud.point_stride == cloud_msg.point_step
    assert cloud.data == np.asarray(cloud_msg.data, np.uint8).tobytes()
    assert [(f.name, f.offset) for f in cloud.fields] == [(f.name, f.offset) for f in cloud_msg.fields]
    points = m.point_cloud2_arrays(cloud_msg)
    xyz = np.frombuffer(cloud.data, np.uint8).reshape(-1, cloud.point_stride)[:, :12].copy().view("<f4")
    np.testing.assert_array_equal(xyz, np.stack([points["x"], points["y"], points["z"]], 1))

    calibration = _decoder(channels["/camera_info"]).FromString(received["/camera_info"][1])
    np.testing.assert_allclose(list(calibration.K), expected["/camera_info"][0].k)
    pose = _decoder(channels["/robot_pose"]).FromString(received["/robot_pose"][1])
    assert pose.frame_id == "map" and pose.pose.orientation.w == expected["/robot_pose"][0].pose.orientation.w


def test_simulate_foxglove_flag_binds_loopback_by_default():
    import argparse

    from ghsplat_jax.commands.simulate import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["scene.ply", "--foxglove"])
    assert args.foxglove and args.host == "127.0.0.1" and args.port == 8765
