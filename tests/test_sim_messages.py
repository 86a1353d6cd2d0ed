"""ROS 2 messages: rosbags CDR == Cyclone DDS IDL serialisation, round trips, bags."""

import numpy as np
import pytest

pytest.importorskip("cyclonedds")
pytest.importorskip("rosbags")

from ghsplat_jax.sim import frames, robot
from ghsplat_jax.sim import messages as m
from ghsplat_jax.transport import dds_types as D
from ghsplat_jax.transport import recorder


def _samples():
    rng = np.random.default_rng(1)
    r = robot.Robot()
    K = np.array([[120.5, 0, 32.25], [0, 119.0, 24.0], [0, 0, 1]])
    f = {"x": rng.normal(size=7).astype(np.float32), "y": rng.normal(size=7).astype(np.float32),
         "z": rng.normal(size=7).astype(np.float32), "intensity": rng.uniform(0, 255, 7).astype(np.float32),
         "ring": np.arange(7, dtype=np.uint16), "time": np.linspace(0, 0.09, 7).astype(np.float32)}
    return [
        m.image(rng.uniform(size=(5, 7, 3)), 12.5, "cam_optical"),
        m.image(rng.uniform(size=(5, 7)).astype(np.float32), 12.5, "cam_optical", "32FC1"),
        m.camera_info(K, 64, 48, 3.000000001, "cam_optical"),
        m.point_cloud2(f, 7.25, "lidar_link"),
        m.pose_stamped(r.map_from_optical(1.0, 2.0, 0.3), 1.5, "cam_optical"),
        m.tf_message(r.static_transforms(), 2.0),
        m.tf_message([r.base_transform(1, 2, 3, 4.0)]),
    ]


@pytest.mark.parametrize("i", range(7))
def test_dds_bytes_equal_rosbags_cdr(i):
    msg = _samples()[i]
    dds = D.to_dds(msg)
    assert type(dds).__idl_typename__.replace("::dds_::", "::").replace("::", "/").rstrip("_") == msg.__msgtype__
    assert D.payload(dds) == m.serialize(msg)
    back = D.from_dds(type(dds).deserialize(D.payload(dds)))
    assert m.serialize(back) == m.serialize(msg)


def test_service_request_is_header_plus_standard_message():
    info = m.camera_info(np.array([[50.0, 0, 16], [0, 50, 12], [0, 0, 1]]), 32, 24, 0.0, "c")
    req = D.make_request(info, 0x1122334455667788, 42)
    data = D.payload(req)
    assert data[4:12] == (0x1122334455667788).to_bytes(8, "little") and data[12:20] == (42).to_bytes(8, "little")
    assert data[20:] == m.serialize(m.set_camera_info_request(info))[4:]
    rep = D.SetCameraInfo_Response_(7, 42, True, "ok")
    assert D.payload(rep)[20:] == m.serialize(m.set_camera_info_response(True, "ok"))[4:]
    assert D.request_body(req).camera_info.width == 32


def test_message_contents():
    K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
    info = m.camera_info(K, 64, 48, 1.25, "cam")
    assert list(info.d) == [0.0] * 5 and info.distortion_model == "plumb_bob"
    assert np.allclose(np.asarray(info.p).reshape(3, 4)[:, :3], K) and info.header.stamp.nanosec == 250_000_000
    rgb = np.random.default_rng(0).uniform(size=(4, 6, 3))
    img = m.image(rgb, 0.5, "cam")
    assert img.encoding == "rgb8" and img.step == 18
    assert np.abs(m.image_array(img) / 255.0 - rgb).max() <= 0.5 / 255 + 1e-9
    f = {"x": np.array([1.0, np.nan], np.float32), "ring": np.array([0, 1], np.uint16)}
    pc = m.point_cloud2(f, 0.0, "l", shape=(1, 2))
    assert not pc.is_dense and pc.point_step == 8
    back = m.point_cloud2_arrays(pc)
    assert back["ring"].tolist() == [0, 1] and np.isnan(back["x"][1])
    T = frames.from_xyz_rpy((1, 2, 3), (0.1, -0.2, 0.3))
    assert np.allclose(m.pose_matrix(m.pose_stamped(T, 0, "map").pose), T)
    with pytest.raises(ValueError):
        m.stamp(float("nan"))


def test_bag_round_trip_with_tf_static(tmp_path):
    msgs = _samples()
    r = robot.Robot()
    with recorder.BagRecorder(tmp_path / "run.mcap") as bag:
        bag.write("/tf_static", m.tf_message(r.static_transforms(), 1.0), 1.0)
        bag.write("/render", msgs[0], 12.5)
        bag.write("/lidar", msgs[3], 7.25)
    assert (tmp_path / "run" / "run.mcap").exists() and (tmp_path / "run" / "metadata.yaml").exists()
    meta = (tmp_path / "run" / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta and "version: 8" in meta
    assert "durability: 1" in meta  # /tf_static offered transient-local (latched)
    back = recorder.read_bag(tmp_path / "run.mcap")
    assert set(back) == {"/tf_static", "/render", "/lidar"}
    assert back["/render"][0][0] == 12_500_000_000
    assert m.serialize(back["/lidar"][0][1]) == m.serialize(msgs[3])
    children = {t.child_frame_id for t in back["/tf_static"][0][1].transforms}
    assert children == {"camera_link", "camera_optical_frame", "lidar_link"}
    with pytest.raises(FileExistsError):
        recorder.BagRecorder(tmp_path / "run.mcap")


def test_interrupted_recording_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with recorder.BagRecorder(tmp_path / "x.mcap") as bag:
            bag.write("/tf", m.tf_message([robot.Robot().base_transform(0, 0, 0, 1.0)]), 1.0)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
