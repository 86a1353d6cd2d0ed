"""ROS 2 bag recording (rosbag2 directory, MCAP storage) with rosbags.

The bag is written into a temporary directory beside the target and renamed when closed,
so an interrupted run never leaves a half bag under the requested name. /tf_static is
offered transient-local (latched), as tf2 publishers do, so `ros2 bag play` replays it
to late subscribers.

rosbag2 bags are directories: `run.mcap` names the bag `run/` holding `run/run.mcap` and
`run/metadata.yaml` (`bag_dir` gives the directory for any requested name).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ghsplat_jax.io_utils import atomic_path
from ghsplat_jax.sim import messages


def _qos(latched: bool):
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1 if latched else 10, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               deadline=never, lifespan=never, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=never, avoid_ros_namespace_conventions=False)


def bag_dir(path: str | os.PathLike) -> Path:
    path = Path(path)
    return path.with_suffix("") if path.suffix.lower() == ".mcap" else path


class BagRecorder:
    """`with BagRecorder(path) as bag: bag.write("/tf", msg, t)`; topics are added on first use."""

    def __init__(self, path: str | os.PathLike, overwrite: bool = False, version: int = 8):
        self.path = bag_dir(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path}: already exists (pass overwrite to replace it)")
        # Metadata v8 writes QoS profiles as a YAML string, the form Humble's rosbag2 reads;
        # Iron and Jazzy read it too (v9, a YAML list, is Jazzy-only).
        self.version = version
        self._writer = None
        self._connections = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> "BagRecorder":
        from rosbags.rosbag2 import StoragePlugin, Writer

        self._output = contextlib.ExitStack()
        tmp = self._output.enter_context(atomic_path(self.path))  # same name: the bag's files take it
        self._writer = Writer(tmp, version=self.version, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        return self

    def write(self, topic: str, msg, t: float) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msg.__msgtype__, typestore=messages.typestore(),
                                               offered_qos_profiles=[_qos(topic == "/tf_static")])
            self._connections[topic] = conn
        self._writer.write(conn, messages.to_nanoseconds(t), messages.serialize(msg))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self._writer.close()
        finally:
            self._output.__exit__(exc_type, exc, tb)  # renamed into place, or discarded on an error


def read_bag(path: str | os.PathLike) -> dict[str, list[tuple[int, object]]]:
    """Every message of a bag as {topic: [(timestamp_ns, message), ...]} (tests, tools)."""
    from rosbags.rosbag2 import Reader

    out: dict[str, list] = {}
    ts = messages.typestore()
    with Reader(bag_dir(path)) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, ts.deserialize_cdr(raw, conn.msgtype)))
    return out
