"""Live view in Foxglove: the simulation's topics over the Foxglove WebSocket protocol
(foxglove-sdk), for `ghsplat simulate SCENE --foxglove [--port 8765] [--host 127.0.0.1]`.

Each ROS 2 message of sim/messages.py (still the single source of every message) becomes
the matching Foxglove schema: /render and /render_depth RawImage, /camera_info
CameraCalibration, /lidar PointCloud, /tf and /tf_static FrameTransforms, /robot_pose
PoseInFrame. Open Foxglove, "Open connection", ws://127.0.0.1:8765. The server binds to
127.0.0.1 unless told otherwise; /tf_static is sent again every second of simulated time so
that a client connecting late still gets the robot's static frames.
"""

from __future__ import annotations

import numpy as np

from ghsplat_jax.sim import messages

TOPICS = ("/render", "/render_depth", "/render_normals", "/camera_info", "/lidar", "/tf", "/tf_static",
          "/robot_pose")
STATIC_EVERY = 1.0  # simulated seconds between repeats of /tf_static


def _stamp(header):
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(header.stamp.sec), nsec=int(header.stamp.nanosec))


def _vector(v):
    from foxglove.messages import Vector3

    return Vector3(x=float(v.x), y=float(v.y), z=float(v.z))


def _quaternion(q):
    from foxglove.messages import Quaternion

    return Quaternion(x=float(q.x), y=float(q.y), z=float(q.z), w=float(q.w))


def raw_image(msg):
    from foxglove.messages import RawImage

    return RawImage(timestamp=_stamp(msg.header), frame_id=msg.header.frame_id, width=int(msg.width),
                    height=int(msg.height), encoding=msg.encoding, step=int(msg.step),
                    data=np.asarray(msg.data, np.uint8).tobytes())


def camera_calibration(msg):
    from foxglove.messages import CameraCalibration

    return CameraCalibration(timestamp=_stamp(msg.header), frame_id=msg.header.frame_id, width=int(msg.width),
                             height=int(msg.height), distortion_model=msg.distortion_model,
                             D=[float(v) for v in msg.d], K=[float(v) for v in msg.k],
                             R=[float(v) for v in msg.r], P=[float(v) for v in msg.p])


def point_cloud(msg):
    """PointCloud2 -> PointCloud with the same packed bytes (the cloud sits at its frame's origin)."""
    from foxglove.messages import PackedElementField, PointCloud, Pose, Quaternion, Vector3
    from foxglove.messages import PackedElementFieldNumericType as N

    types = {1: N.Int8, 2: N.Uint8, 3: N.Int16, 4: N.Uint16, 5: N.Int32, 6: N.Uint32, 7: N.Float32, 8: N.Float64}
    if msg.is_bigendian:
        raise ValueError("big-endian point clouds are not supported")
    fields = [PackedElementField(name=f.name, offset=int(f.offset), type=types[f.datatype]) for f in msg.fields]
    identity = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    return PointCloud(timestamp=_stamp(msg.header), frame_id=msg.header.frame_id, pose=identity,
                      point_stride=int(msg.point_step), fields=fields,
                      data=np.asarray(msg.data, np.uint8).tobytes())


def frame_transforms(msg):
    from foxglove.messages import FrameTransform, FrameTransforms

    return FrameTransforms(transforms=[
        FrameTransform(timestamp=_stamp(tf.header), parent_frame_id=tf.header.frame_id,
                       child_frame_id=tf.child_frame_id, translation=_vector(tf.transform.translation),
                       rotation=_quaternion(tf.transform.rotation)) for tf in msg.transforms])


def pose_in_frame(msg):
    from foxglove.messages import Pose, PoseInFrame

    return PoseInFrame(timestamp=_stamp(msg.header), frame_id=msg.header.frame_id,
                       pose=Pose(position=_vector(msg.pose.position), orientation=_quaternion(msg.pose.orientation)))


CONVERT = {"sensor_msgs/msg/Image": raw_image, "sensor_msgs/msg/CameraInfo": camera_calibration,
           "sensor_msgs/msg/PointCloud2": point_cloud, "tf2_msgs/msg/TFMessage": frame_transforms,
           "geometry_msgs/msg/PoseStamped": pose_in_frame}


def _channel_class(msgtype: str):
    from foxglove import channels

    return {"sensor_msgs/msg/Image": channels.RawImageChannel,
            "sensor_msgs/msg/CameraInfo": channels.CameraCalibrationChannel,
            "sensor_msgs/msg/PointCloud2": channels.PointCloudChannel,
            "tf2_msgs/msg/TFMessage": channels.FrameTransformsChannel,
            "geometry_msgs/msg/PoseStamped": channels.PoseInFrameChannel}[msgtype]


class FoxgloveSink:
    """A Foxglove WebSocket server fed by the simulator: `sink(topic, msg, t, payload)`.

    It uses its own foxglove Context, so it never mixes with other foxglove logging in the
    process. Channels are created on a topic's first message."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "ghsplat simulate"):
        import foxglove

        self.context = foxglove.Context()
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        self.port = self.server.port  # the bound port (port 0 picks a free one)
        self._channels: dict[str, object] = {}
        self._static = None  # (message, last simulated time it was sent)

    def publish(self, topic: str, msg, t: float) -> None:
        convert = CONVERT.get(msg.__msgtype__)
        if convert is None:
            return
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = _channel_class(msg.__msgtype__)(topic, context=self.context)
        channel.log(convert(msg), log_time=messages.to_nanoseconds(t))

    def sink(self, topic: str, msg, t: float, payload=None) -> None:
        if topic == "/tf_static":
            self._static = [msg, t]
        elif self._static is not None and t - self._static[1] >= STATIC_EVERY:
            self._static[1] = t
            self.publish("/tf_static", self._static[0], t)
        self.publish(topic, msg, t)

    def close(self) -> None:
        self.server.stop()
