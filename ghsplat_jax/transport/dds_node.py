"""A ROS 2 renderer node over Cyclone DDS, without a ROS installation.

Topics (ROS 2 names -> DDS topics `rt/<name>`, types as rmw_cyclonedds names them):
  subscribes /camera_pose   geometry_msgs/PoseStamped: header.frame_id names a registered
                            camera's optical frame (or the LiDAR frame), the pose is that
                            frame's pose in `map`, header.stamp is echoed on the outputs
  publishes  render         sensor_msgs/Image (rgb8, frame = the camera's optical frame)
             render_depth   sensor_msgs/Image (32FC1 z-depth, 0 = no surface), if enabled
             /camera_info   sensor_msgs/CameraInfo matching each image
             /lidar         sensor_msgs/PointCloud2 (x y z intensity ring time) in the LiDAR frame
             /tf, /tf_static tf2_msgs/TFMessage
  serves     /register_camera  sensor_msgs/srv/SetCameraInfo (a standard service type): the
                            request's CameraInfo defines the camera (header.frame_id = its
                            optical frame, width, height, K, zero distortion); DDS topics
                            rq/register_cameraRequest and rr/register_cameraReply carrying
                            rmw_cyclonedds' request header (client id, sequence number).

Bad input (NaN or non-unit quaternions, unknown frames, conflicting re-registration,
malformed requests) is logged and ignored; the node keeps serving. Discovery can be
restricted to loopback (`localhost_config`), which the tests always do.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from ghsplat_jax.sim import frames, messages
from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
from ghsplat_jax.sim.messages import MessageError
from ghsplat_jax.transport import dds_types as D

log = logging.getLogger("ghsplat.sim.node")

TOPICS = {
    "camera_pose": "rt/camera_pose", "render": "rt/render", "render_depth": "rt/render_depth",
    "camera_info": "rt/camera_info", "lidar": "rt/lidar", "tf": "rt/tf", "tf_static": "rt/tf_static",
    "request": "rq/register_cameraRequest", "reply": "rr/register_cameraReply",
}
# topics of the simulated stream (sim.simulate.run) that the node publishes, by their TOPICS key
_STREAM_TOPICS = {"/tf_static": "tf_static", "/tf": "tf", "/render": "render", "/camera_info": "camera_info",
                  "/render_depth": "render_depth", "/lidar": "lidar"}


def localhost_config(domain_id: int | None = None) -> str:
    """Cyclone DDS XML that binds to 127.0.0.1, disables multicast and only discovers
    peers on this host (unicast to 127.0.0.1)."""
    dom = f'id="{int(domain_id)}"' if domain_id is not None else 'id="any"'
    return (f'<CycloneDDS><Domain {dom}><General><Interfaces><NetworkInterface address="127.0.0.1"/>'
            '</Interfaces><AllowMulticast>false</AllowMulticast></General>'
            '<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>'
            '<Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')


def _qos(static: bool = False):
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    policies = [Policy.Reliability.Reliable(duration(seconds=1)),
                Policy.DataRepresentation(use_cdrv0_representation=True),  # XCDR1, as ROS 2
                Policy.History.KeepLast(1 if static else 10)]
    if static:
        policies.append(Policy.Durability.TransientLocal)
    else:
        policies.append(Policy.Durability.Volatile)
    return Qos(*policies)


_DOMAINS: dict[int, object] = {}  # configured domains live as long as the process


def participant(domain_id: int, localhost_only: bool = True):
    from cyclonedds.domain import Domain, DomainParticipant

    if localhost_only and domain_id not in _DOMAINS:
        _DOMAINS[domain_id] = Domain(domain_id, localhost_config(domain_id))
    return DomainParticipant(domain_id)


class _Endpoints:
    def __init__(self, dp, server: bool):
        from cyclonedds.pub import DataWriter
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        self.dp = dp
        types = {"camera_pose": D.PoseStamped_, "render": D.Image_, "render_depth": D.Image_,
                 "camera_info": D.CameraInfo_, "lidar": D.PointCloud2_, "tf": D.TFMessage_,
                 "tf_static": D.TFMessage_, "request": D.SetCameraInfo_Request_, "reply": D.SetCameraInfo_Response_}
        self.topics = {k: Topic(dp, TOPICS[k], types[k], qos=_qos(k == "tf_static")) for k in types}
        ins = (("camera_pose", "request") if server
               else ("render", "render_depth", "camera_info", "lidar", "tf", "tf_static", "reply"))
        self.readers = {k: DataReader(dp, self.topics[k], qos=_qos(k == "tf_static")) for k in ins}
        self.writers = {k: DataWriter(dp, self.topics[k], qos=_qos(k == "tf_static"))
                        for k in types if k not in ins}

    def take(self, name: str, n: int = 64) -> list:
        from cyclonedds.internal import InvalidSample

        try:
            samples = self.readers[name].take(N=n)
        except Exception as exc:  # a sample that does not deserialise: drop it, keep serving
            log.warning("dropped malformed sample on %s: %r", TOPICS[name], exc)
            return []
        # Instance-state notices (a writer that vanished or disposed) carry no data.
        return [s for s in samples if not isinstance(s, InvalidSample)]

    def write(self, name: str, sample) -> None:
        self.writers[name].write(sample)


class SimNode:
    """Serves renders of `surfels` to registered cameras, and LiDAR scans.

    `camera_renderer` and `lidar` may use any render function (tests pass analytic ones).
    """

    def __init__(self, surfels, *, domain_id: int = 0, localhost_only: bool = True,
                 camera_renderer: CameraRenderer | None = None, lidar=None, lidar_frame: str = "lidar_link",
                 map_frame: str = "map", publish_depth: bool = False, organised_cloud: bool = False):
        self.surfels = surfels
        self.renderer = camera_renderer or CameraRenderer()
        self.lidar, self.lidar_frame, self.map_frame = lidar, lidar_frame, map_frame
        self.publish_depth, self.organised_cloud = publish_depth, organised_cloud
        self.cameras: dict[str, CameraModel] = {}
        self.counts = {"renders": 0, "scans": 0, "registrations": 0, "rejected": 0}
        self.dp = participant(domain_id, localhost_only)
        self.io = _Endpoints(self.dp, server=True)
        self._scan_seq = 0

    # ------------------------------------------------------------------ registration
    def _register(self, req: D.SetCameraInfo_Request_) -> tuple[bool, str]:
        try:
            model = camera_from_request(req)
        except MessageError as exc:
            return False, str(exc)
        if model.frame_id in (self.map_frame, self.lidar_frame):
            return False, f"frame {model.frame_id!r} is reserved"
        old = self.cameras.get(model.frame_id)
        if old is not None:
            if old == model:
                return True, f"{model.frame_id} already registered (unchanged)"
            return False, f"{model.frame_id} is already registered with other intrinsics"
        self.cameras[model.frame_id] = model
        self.counts["registrations"] += 1
        return True, f"registered {model.frame_id} ({model.width}x{model.height})"

    def _serve_requests(self) -> int:
        reqs = self.io.take("request", 16)
        for req in reqs:
            try:
                ok, msg = self._register(req)
            except Exception as exc:  # never let one request stop the node
                ok, msg = False, f"internal error: {exc!r}"
            (log.info if ok else log.warning)("register_camera from %016x #%d: %s",
                                              req.client_id, req.sequence_number, msg)
            if not ok:
                self.counts["rejected"] += 1
            self.io.write("reply", D.SetCameraInfo_Response_(req.client_id, req.sequence_number, ok, msg))
        return len(reqs)

    # ------------------------------------------------------------------------ poses
    def _valid_pose(self, sample) -> tuple[str, np.ndarray, float] | None:
        try:
            frame, T, t = pose_from_sample(sample)
        except MessageError as exc:
            log.warning("ignored pose: %s", exc)
            self.counts["rejected"] += 1
            return None
        if frame not in self.cameras and not (frame == self.lidar_frame and self.lidar is not None):
            log.warning("ignored pose for unknown frame %r (register it first)", frame)
            self.counts["rejected"] += 1
            return None
        return frame, T, t

    def _serve_poses(self) -> int:
        latest: dict[str, tuple[np.ndarray, float]] = {}
        samples = self.io.take("camera_pose", 64)
        for s in samples:  # only the newest pose per frame: never build a backlog
            v = self._valid_pose(s)
            if v is not None:
                latest[v[0]] = (v[1], v[2])
        for frame, (T, t) in latest.items():
            try:
                if frame == self.lidar_frame:
                    self.publish_scan(T, t)
                else:
                    self.publish_camera(self.cameras[frame], T, t)
            except Exception:  # a failed render must not stop the node
                log.exception("render for %s failed", frame)
        return len(samples)

    # --------------------------------------------------------------------- outputs
    def publish_tf(self, transforms: list[frames.Transform], t: float, static: bool = False) -> None:
        self.io.write("tf_static" if static else "tf", D.to_dds(messages.tf_message(transforms, t)))

    def publish_camera(self, model: CameraModel, map_from_optical: np.ndarray, t: float, frame=None):
        frame = frame or self.renderer.render(self.surfels, model, map_from_optical, t)
        self.publish_tf([frames.Transform(self.map_frame, model.frame_id, map_from_optical)], t)
        self.io.write("render", D.to_dds(messages.image(frame.rgb, t, model.frame_id, "rgb8")))
        if self.publish_depth:
            self.io.write("render_depth", D.to_dds(messages.image(np.nan_to_num(frame.depth, nan=0.0), t,
                                                                  model.frame_id, "32FC1")))
        self.io.write("camera_info", D.to_dds(model.info(t)))
        self.counts["renders"] += 1
        return frame

    def publish_scan(self, map_from_lidar: np.ndarray, t: float, publish_tf: bool = True):
        self._scan_seq += 1
        scan = self.lidar.scan(self.surfels, map_from_lidar, t, seed=self._scan_seq)
        if publish_tf:
            self.publish_tf([frames.Transform(self.map_frame, self.lidar_frame, map_from_lidar)], t)
        self.io.write("lidar", D.to_dds(cloud_message(scan, self.lidar_frame, self.organised_cloud)))
        self.counts["scans"] += 1
        return scan

    # ------------------------------------------------------------------------- loop
    def sink(self, topic: str, msg, t: float, payload=None) -> None:
        """A sink for the simulated stream (sim.simulate.run): its messages of the node's
        topics are published as they come; the others (e.g. /robot_pose) are not."""
        if topic in _STREAM_TOPICS:
            self.io.write(_STREAM_TOPICS[topic], D.to_dds(msg))

    def spin_once(self) -> int:
        return self._serve_requests() + self._serve_poses()

    def spin(self, duration: float | None = None, idle_sleep: float = 0.005,
             should_stop: Callable[[], bool] | None = None) -> None:
        end = None if duration is None else time.monotonic() + duration
        while (end is None or time.monotonic() < end) and not (should_stop and should_stop()):
            if self.spin_once() == 0:
                time.sleep(idle_sleep)

    def close(self) -> None:
        self.io = None
        self.dp = None


def pose_from_sample(sample, topic: str = "/camera_pose") -> tuple[str, np.ndarray, float]:
    """(frame id, 4x4 pose in the map, stamp in seconds) of a received PoseStamped_, or
    MessageError: NaN, a non-unit quaternion or a negative stamp never reach a render."""
    try:
        frame = sample.header.frame_id
        stamp = sample.header.stamp
        if not (isinstance(frame, str) and frame) or stamp.sec < 0 or not 0 <= stamp.nanosec < 1_000_000_000:
            raise ValueError(f"bad header (frame {frame!r}, stamp {stamp.sec}.{stamp.nanosec})")
        p, q = sample.pose.position, sample.pose.orientation
        T = frames.from_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    except (ValueError, TypeError, AttributeError) as exc:
        raise MessageError(f"{topic}: {exc}") from None
    return frame, T, stamp.sec + stamp.nanosec * 1e-9


def camera_from_request(req: D.SetCameraInfo_Request_, topic: str = "/register_camera") -> CameraModel:
    """The camera a registration request defines, or MessageError saying why not."""
    try:
        return CameraModel.from_camera_info(D.request_body(req).camera_info)
    except (ValueError, TypeError, AttributeError, OverflowError) as exc:
        raise MessageError(f"{topic}: bad camera info: {exc}") from None


def cloud_message(scan, frame_id: str, organised: bool = False):
    f = scan.fields(organised)
    shape = scan.ranges.shape if organised else None
    return messages.point_cloud2(f, scan.stamp, frame_id, shape)


class SimClient:
    """A camera client: registers, sends poses, receives renders and clouds (tests, tools)."""

    def __init__(self, domain_id: int = 0, localhost_only: bool = True):
        self.dp = participant(domain_id, localhost_only)
        self.io = _Endpoints(self.dp, server=False)
        guid = self.io.writers["request"].guid
        self.client_id = int.from_bytes(guid.bytes[8:], "little")  # second half of the writer GUID
        self._seq = 0

    def wait_for_server(self, timeout: float = 10.0) -> bool:
        """True once the node's request reader is matched (discovery done)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.io.writers["request"].get_matched_subscriptions() and \
               self.io.writers["camera_pose"].get_matched_subscriptions():
                return True
            time.sleep(0.05)
        return False

    def send_request(self, info_msg) -> int:
        self._seq += 1
        self.io.write("request", D.make_request(info_msg, self.client_id, self._seq))
        return self._seq

    def register(self, model: CameraModel, timeout: float = 10.0) -> tuple[bool, str]:
        seq = self.send_request(model.info(0.0))
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for rep in self.io.take("reply"):
                if rep.client_id == self.client_id and rep.sequence_number == seq:
                    return bool(rep.success), rep.status_message
            time.sleep(0.02)
        raise TimeoutError("no reply from /register_camera")

    def send_pose(self, frame_id: str, map_from_frame: np.ndarray, t: float) -> None:
        self.io.write("camera_pose", D.to_dds(messages.pose_stamped(map_from_frame, t, frame_id)))

    def send_raw_pose(self, frame_id: str, position, quat_xyzw, t: float) -> None:
        """A pose as given, unchecked (for testing how the node handles bad input)."""
        s = D.PoseStamped_(D.Header_(D.Time_(int(t), int((t % 1) * 1e9)), frame_id),
                           D.Pose_(D.Point_(*map(float, position)), D.Quaternion_(*map(float, quat_xyzw))))
        self.io.write("camera_pose", s)

    def receive(self, topic: str, timeout: float = 10.0, predicate=None):
        """The next message on `topic` (a rosbags message; service replies stay IDL structs
        with their request header) satisfying `predicate`."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for s in self.io.take(topic):
                msg = D.from_dds(s) if type(s) in D.MSGTYPE_OF_IDL else s
                if predicate is None or predicate(msg):
                    return msg
            time.sleep(0.01)
        raise TimeoutError(f"nothing received on {TOPICS[topic]} within {timeout} s")

    def close(self) -> None:
        self.io = None
        self.dp = None
