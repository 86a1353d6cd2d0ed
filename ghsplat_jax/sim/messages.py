"""ROS 2 messages built with rosbags' typesys (Humble definitions), and their inverses.

These rosbags dataclasses are the single source of every message: the bag recorder
serialises them with `typestore.serialize_cdr`, the DDS node converts them field by field
to its IDL types (transport/dds_types.py), and tests check both give the same bytes.
"""

from __future__ import annotations

import functools

import numpy as np

from ghsplat_jax.sim import frames


# The service /register_camera uses the standard sensor_msgs/srv/SetCameraInfo; rosbags
# ships message types only, so its request and response are registered as messages.
class MessageError(ValueError):
    """An incoming message that cannot be used; the text names the topic and the problem."""


SET_CAMERA_INFO_REQUEST = "sensor_msgs/srv/SetCameraInfo_Request"
SET_CAMERA_INFO_RESPONSE = "sensor_msgs/srv/SetCameraInfo_Response"
_SRV_DEFS = {
    SET_CAMERA_INFO_REQUEST: "sensor_msgs/CameraInfo camera_info\n",
    SET_CAMERA_INFO_RESPONSE: "bool success\nstring status_message\n",
}

POINT_FIELD_TYPES = {np.dtype(np.int8): 1, np.dtype(np.uint8): 2, np.dtype(np.int16): 3, np.dtype(np.uint16): 4,
                     np.dtype(np.int32): 5, np.dtype(np.uint32): 6, np.dtype(np.float32): 7, np.dtype(np.float64): 8}
_DTYPE_OF_FIELD = {v: k for k, v in POINT_FIELD_TYPES.items()}


@functools.cache
def typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in _SRV_DEFS.items():
        # rosbags files every parsed type under <pkg>/msg/; keep the srv name ROS uses.
        (_, fields), = get_types_from_msg(text, name).items()
        types[name] = fields
    ts.register(types)
    return ts


def T(name: str):
    return typestore().types[name]


def stamp(t: float):
    if not np.isfinite(t) or t < 0:
        raise ValueError(f"bad time stamp {t}")
    ns = int(round(t * 1e9))
    return T("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def to_seconds(time_msg) -> float:
    return time_msg.sec + time_msg.nanosec * 1e-9


def to_nanoseconds(t: float) -> int:
    return int(round(t * 1e9))


def header(t: float, frame_id: str):
    return T("std_msgs/msg/Header")(stamp=stamp(t), frame_id=frame_id)


# ----------------------------------------------------------------------------- images

def image(array: np.ndarray, t: float, frame_id: str, encoding: str | None = None):
    """rgb8 from (H,W,3) floats in [0,1] or uint8 (default for 3 channels); 32FC1 from 2-D
    float depth (default); 32FC3 (normals) and mono8 when asked."""
    a = np.asarray(array)
    if encoding is None:
        encoding = "rgb8" if a.ndim == 3 else "32FC1"  # normals need an explicit "32FC3"
    if encoding == "rgb8":
        if a.dtype != np.uint8:
            a = np.clip(np.round(np.nan_to_num(a) * 255.0), 0, 255).astype(np.uint8)
        channels, itemsize = 3, 1
    elif encoding in ("32FC1", "32FC3"):
        a = np.asarray(a, np.float32)
        channels, itemsize = (1 if encoding == "32FC1" else 3), 4
    elif encoding == "mono8":
        a, channels, itemsize = np.asarray(a, np.uint8), 1, 1
    else:
        raise ValueError(f"unsupported encoding {encoding!r}")
    H, W = a.shape[:2]
    if a.size != H * W * channels:
        raise ValueError(f"array of shape {a.shape} does not fit encoding {encoding}")
    data = np.ascontiguousarray(a).view(np.uint8).reshape(-1)
    return T("sensor_msgs/msg/Image")(header=header(t, frame_id), height=H, width=W, encoding=encoding,
                                     is_bigendian=0, step=W * channels * itemsize, data=data)


def image_array(msg) -> np.ndarray:
    dtype, channels = {"rgb8": (np.uint8, 3), "mono8": (np.uint8, 1), "32FC1": (np.float32, 1),
                       "32FC3": (np.float32, 3)}[msg.encoding]
    a = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), dtype)
    return a.reshape(msg.height, msg.width, channels) if channels > 1 else a.reshape(msg.height, msg.width)


def camera_info(K: np.ndarray, width: int, height: int, t: float, frame_id: str):
    """Pinhole CameraInfo matching an undistorted image: D = 0 (plumb_bob), R = I, P = [K | 0]."""
    K = np.asarray(K, np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = T("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T("sensor_msgs/msg/CameraInfo")(
        header=header(t, frame_id), height=int(height), width=int(width), distortion_model="plumb_bob",
        d=np.zeros(5), k=K.reshape(-1).copy(), r=np.eye(3).reshape(-1), p=P.reshape(-1),
        binning_x=0, binning_y=0, roi=roi)


# ------------------------------------------------------------------------------- clouds

def point_cloud2(fields: dict[str, np.ndarray], t: float, frame_id: str, shape: tuple[int, int] | None = None):
    """PointCloud2 from named 1-D arrays (packed in the given order, each field aligned to
    its size). `shape` = (height, width) for an organised cloud (NaN for no return)."""
    names = list(fields)
    arrays = [np.asarray(fields[n]) for n in names]
    n = len(arrays[0]) if arrays else 0
    if any(a.ndim != 1 or len(a) != n for a in arrays):
        raise ValueError("point fields must be 1-D arrays of one length")
    offset, descr, pf = 0, [], []
    for name, a in zip(names, arrays):
        size = a.dtype.itemsize
        offset = -(-offset // size) * size  # align
        descr.append((name, a.dtype.newbyteorder("<"), offset))
        pf.append(T("sensor_msgs/msg/PointField")(name=name, offset=offset,
                                                  datatype=POINT_FIELD_TYPES[a.dtype], count=1))
        offset += size
    step = -(-offset // 4) * 4
    dtype = np.dtype({"names": names, "formats": [d[1] for d in descr], "offsets": [d[2] for d in descr],
                      "itemsize": step})
    rec = np.zeros(n, dtype)
    for name, a in zip(names, arrays):
        rec[name] = a
    height, width = shape if shape is not None else (1, n)
    if height * width != n:
        raise ValueError(f"cloud shape {shape} does not hold {n} points")
    dense = all(np.all(np.isfinite(a)) for a in arrays if a.dtype.kind == "f")
    return T("sensor_msgs/msg/PointCloud2")(
        header=header(t, frame_id), height=height, width=width, fields=pf, is_bigendian=False,
        point_step=step, row_step=step * width, data=rec.view(np.uint8).reshape(-1), is_dense=dense)


def point_cloud2_arrays(msg) -> dict[str, np.ndarray]:
    dtype = np.dtype({"names": [f.name for f in msg.fields],
                      "formats": [_DTYPE_OF_FIELD[f.datatype] for f in msg.fields],
                      "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    rec = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), dtype)
    return {f.name: np.array(rec[f.name]) for f in msg.fields}


# -------------------------------------------------------------------------- poses and tf

def pose(Tm: np.ndarray):
    q = frames.quat_xyzw(Tm)
    p = np.asarray(Tm, np.float64)[:3, 3]
    return T("geometry_msgs/msg/Pose")(
        position=T("geometry_msgs/msg/Point")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=T("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def pose_stamped(Tm: np.ndarray, t: float, frame_id: str):
    return T("geometry_msgs/msg/PoseStamped")(header=header(t, frame_id), pose=pose(Tm))


def pose_matrix(pose_msg, unit_tol: float = 1e-3) -> np.ndarray:
    """4x4 of a geometry_msgs/Pose; ValueError on NaN or a non-unit quaternion."""
    p, q = pose_msg.position, pose_msg.orientation
    return frames.from_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w], unit_tol)


def transform_stamped(tf: frames.Transform, t: float | None = None):
    stamp_t = tf.stamp if t is None else t
    q = frames.quat_xyzw(tf.matrix)
    p = np.asarray(tf.matrix, np.float64)[:3, 3]
    return T("geometry_msgs/msg/TransformStamped")(
        header=header(0.0 if stamp_t is None else stamp_t, tf.parent), child_frame_id=tf.child,
        transform=T("geometry_msgs/msg/Transform")(
            translation=T("geometry_msgs/msg/Vector3")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
            rotation=T("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def tf_message(transforms: list[frames.Transform], t: float | None = None):
    return T("tf2_msgs/msg/TFMessage")(transforms=[transform_stamped(tf, t) for tf in transforms])


def set_camera_info_request(info):
    return T(SET_CAMERA_INFO_REQUEST)(camera_info=info)


def set_camera_info_response(success: bool, message: str):
    return T(SET_CAMERA_INFO_RESPONSE)(success=bool(success), status_message=str(message))


def serialize(msg) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def deserialize(data: bytes, msgtype: str):
    return typestore().deserialize_cdr(data, msgtype)
