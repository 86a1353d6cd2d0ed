"""ROS 2 message types as Cyclone DDS IDL structs, named as rmw_cyclonedds names them
(`<pkg>::msg::dds_::<Name>_`), plus conversion from the rosbags messages of
sim/messages.py (which stay the single source of every message).

Services follow rmw_cyclonedds: the request and reply topics carry the message prefixed
by its request header, the client's 64-bit id (the second half of its writer GUID) and a
sequence number, which the server copies into the reply so clients match their answers.
"""


import dataclasses
from dataclasses import dataclass, field

import numpy as np
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int32, int64, sequence, uint8, uint32, uint64


@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class Image_(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header_ = field(default_factory=Header_)
    height: uint32 = 0
    width: uint32 = 0
    encoding: str = ""
    is_bigendian: uint8 = 0
    step: uint32 = 0
    data: sequence[uint8] = b""  # bytes serialise as sequence<uint8> directly


@dataclass
class RegionOfInterest_(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: uint32 = 0
    y_offset: uint32 = 0
    height: uint32 = 0
    width: uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo_(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header_ = field(default_factory=Header_)
    height: uint32 = 0
    width: uint32 = 0
    distortion_model: str = ""
    d: sequence[float64] = field(default_factory=list)
    k: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    r: array[float64, 9] = field(default_factory=lambda: [0.0] * 9)
    p: array[float64, 12] = field(default_factory=lambda: [0.0] * 12)
    binning_x: uint32 = 0
    binning_y: uint32 = 0
    roi: RegionOfInterest_ = field(default_factory=RegionOfInterest_)


@dataclass
class PointField_(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str = ""
    offset: uint32 = 0
    datatype: uint8 = 0
    count: uint32 = 0


@dataclass
class PointCloud2_(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header_ = field(default_factory=Header_)
    height: uint32 = 0
    width: uint32 = 0
    fields: sequence[PointField_] = field(default_factory=list)
    is_bigendian: bool = False
    point_step: uint32 = 0
    row_step: uint32 = 0
    data: sequence[uint8] = b""
    is_dense: bool = False


@dataclass
class Point_(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose_(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point_ = field(default_factory=Point_)
    orientation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class PoseStamped_(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header_ = field(default_factory=Header_)
    pose: Pose_ = field(default_factory=Pose_)


@dataclass
class Transform_(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3_ = field(default_factory=Vector3_)
    rotation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class TransformStamped_(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header_ = field(default_factory=Header_)
    child_frame_id: str = ""
    transform: Transform_ = field(default_factory=Transform_)


@dataclass
class TFMessage_(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: sequence[TransformStamped_] = field(default_factory=list)


# sensor_msgs/srv/SetCameraInfo with rmw_cyclonedds' request header in front.
@dataclass
class SetCameraInfo_Request_(IdlStruct, typename="sensor_msgs::srv::dds_::SetCameraInfo_Request_"):
    client_id: uint64 = 0
    sequence_number: int64 = 0
    camera_info: CameraInfo_ = field(default_factory=CameraInfo_)


@dataclass
class SetCameraInfo_Response_(IdlStruct, typename="sensor_msgs::srv::dds_::SetCameraInfo_Response_"):
    client_id: uint64 = 0
    sequence_number: int64 = 0
    success: bool = False
    status_message: str = ""


REQUEST_HEADER_BYTES = 16  # uint64 client id + int64 sequence number

IDL_OF_MSGTYPE = {
    "builtin_interfaces/msg/Time": Time_, "std_msgs/msg/Header": Header_,
    "sensor_msgs/msg/Image": Image_, "sensor_msgs/msg/RegionOfInterest": RegionOfInterest_,
    "sensor_msgs/msg/CameraInfo": CameraInfo_, "sensor_msgs/msg/PointField": PointField_,
    "sensor_msgs/msg/PointCloud2": PointCloud2_, "geometry_msgs/msg/Point": Point_,
    "geometry_msgs/msg/Vector3": Vector3_, "geometry_msgs/msg/Quaternion": Quaternion_,
    "geometry_msgs/msg/Pose": Pose_, "geometry_msgs/msg/PoseStamped": PoseStamped_,
    "geometry_msgs/msg/Transform": Transform_, "geometry_msgs/msg/TransformStamped": TransformStamped_,
    "tf2_msgs/msg/TFMessage": TFMessage_,
}
MSGTYPE_OF_IDL = {v: k for k, v in IDL_OF_MSGTYPE.items()}


def _convert(value):
    if dataclasses.is_dataclass(value) and hasattr(value, "__msgtype__"):
        return to_dds(value)
    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else [float(v) for v in value]
    if isinstance(value, list):
        return [_convert(v) for v in value]
    return value


def decode(cls: type[IdlStruct], data: bytes, topic: str) -> IdlStruct:
    """Received CDR bytes -> an IDL struct, or MessageError naming the topic. Lengths inside
    the bytes are checked against the buffer by the deserialiser before anything is sized."""
    from ghsplat_jax.sim.messages import MessageError

    try:
        return cls.deserialize(bytes(data))
    except Exception as exc:  # the deserialiser raises struct, index, unicode and type errors alike
        raise MessageError(f"{topic}: malformed {cls.__name__.rstrip('_')} ({type(exc).__name__}: {exc})") from None


def to_dds(msg) -> IdlStruct:
    """rosbags message -> the IDL struct of the same type, field by field."""
    cls = IDL_OF_MSGTYPE[msg.__msgtype__]
    return cls(**{f.name: _convert(getattr(msg, f.name)) for f in dataclasses.fields(cls)})


def payload(sample: IdlStruct) -> bytes:
    """XCDR1 little-endian bytes with the 4-byte encapsulation header, as ROS 2 sends them."""
    return bytes(sample.serialize(use_version_2=False))


def from_dds(sample: IdlStruct):
    """IDL struct -> rosbags message (through its CDR bytes)."""
    from ghsplat_jax.sim import messages

    return messages.deserialize(payload(sample), MSGTYPE_OF_IDL[type(sample)])


def make_request(info_msg, client_id: int, sequence_number: int) -> SetCameraInfo_Request_:
    return SetCameraInfo_Request_(client_id, sequence_number, to_dds(info_msg))


def request_body(req: SetCameraInfo_Request_):
    """The rosbags SetCameraInfo request inside a wire request (header stripped)."""
    from ghsplat_jax.sim import messages

    data = payload(req)
    body = data[:4] + data[4 + REQUEST_HEADER_BYTES:]
    return messages.deserialize(body, messages.SET_CAMERA_INFO_REQUEST)
