"""Our files read by independent implementations: MCAP bags by Foxglove's `mcap` and
`mcap-ros2-support` (beside rosbags), viewer PLYs by `plyfile` in the property order
SuperSplat expects, transforms.json by nerfstudio's format rules."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ghsplat_jax.transport import recorder


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from ghsplat_jax.cli import main
    from ghsplat_jax.data.ply import save_ply
    from ghsplat_jax.scene import surfaces
    from ghsplat_jax.scene.merge import merge

    d = tmp_path_factory.mktemp("bag")
    green, faces = surfaces.constant_colour((0.2, 0.6, 0.2)), ("+x", "-x", "+y", "-y", "+z")
    save_ply(merge([surfaces.box((0, -1.2, 0), (3, -0.6, 1.0), 0.2, green, faces=faces),
                    surfaces.box((0, 0.6, 0), (3, 1.2, 1.0), 0.2, green, faces=faces)]), d / "s.ply")
    rc = main(["simulate", str(d / "s.ply"), "--trajectory", "aisles", "--record", str(d / "run.mcap"), "--quiet",
               "--width", "32", "--height", "24", "--lidar-face-width", "64", "--max-events", "6", "--depth"])
    assert rc == 0
    return recorder.bag_dir(d / "run.mcap")


def test_mcap_bag_decodes_with_foxglove_readers(bag):
    import yaml
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    expected = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    (mcap_file,) = bag.glob("*.mcap")
    ours = recorder.read_bag(bag)
    counts, decoded = {}, {}
    with open(mcap_file, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            decoded.setdefault(channel.topic, []).append((message.log_time, msg))
    assert counts == expected and sum(counts.values()) == info["message_count"]
    assert set(counts) == {"/tf_static", "/tf", "/robot_pose", "/render", "/camera_info", "/render_depth", "/lidar"}
    # the second implementation sees the same contents as rosbags
    for topic, items in decoded.items():
        assert [t for t, _ in items] == [t for t, _ in ours[topic]]
    for (_, a), (_, b) in zip(decoded["/render"], ours["/render"]):
        assert (a.width, a.height, a.encoding, a.header.frame_id) == (b.width, b.height, b.encoding, b.header.frame_id)
        assert bytes(a.data) == np.asarray(b.data, np.uint8).tobytes()
    for (_, a), (_, b) in zip(decoded["/lidar"], ours["/lidar"]):
        assert [f.name for f in a.fields] == [f.name for f in b.fields] and a.point_step == b.point_step
        assert bytes(a.data) == np.asarray(b.data, np.uint8).tobytes()
    a, b = decoded["/camera_info"][0][1], ours["/camera_info"][0][1]
    np.testing.assert_array_equal(a.k, b.k)
    a, b = decoded["/tf_static"][0][1], ours["/tf_static"][0][1]
    assert [t.child_frame_id for t in a.transforms] == [t.child_frame_id for t in b.transforms]
    a, b = decoded["/robot_pose"][-1][1], ours["/robot_pose"][-1][1]
    assert (a.pose.position.x, a.pose.orientation.w) == (b.pose.position.x, b.pose.orientation.w)


# 3DGS PLY properties in the order of the reference implementation's save_ply, which
# SuperSplat and other viewers read.
def _3dgs_names(k: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * k)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@pytest.mark.parametrize("degree", [0, 3])
def test_viewer_ply_loads_in_plyfile_with_3dgs_order(tmp_path, degree):
    from plyfile import PlyData
    from raster_scenes import random_scene

    from ghsplat_jax.data.ply import save_ply

    s = random_scene(37, degree=degree)
    path = save_ply(s, tmp_path / "viewer.ply", viewer_compatible=True)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"] and not ply.text
    vertex = ply["vertex"]
    k = (degree + 1) ** 2 - 1
    assert [p.name for p in vertex.properties] == _3dgs_names(k)
    assert all(p.val_dtype in ("f4", "float32", "float") for p in vertex.properties)
    assert vertex.count == 37
    np.testing.assert_array_equal(vertex["x"], np.asarray(s.means, np.float32)[:, 0])
    np.testing.assert_array_equal(vertex["rot_0"], np.asarray(s.quats, np.float32)[:, 0])
    np.testing.assert_allclose(vertex["scale_2"], np.log(1e-6), rtol=1e-6)  # flat third axis
    if k:  # channel-major f_rest: all red coefficients first
        np.testing.assert_array_equal(vertex[f"f_rest_{k}"], np.asarray(s.sh_rest, np.float32)[:, 0, 1])


# nerfstudio's transforms.json rules (nerfstudio_dataparser.py): camera_model one of its
# CAMERA_MODEL_TO_TYPE keys; fl_x, fl_y, cx, cy, w, h at the top (shared) or in every frame;
# every frame a file_path and a 4x4 camera-to-world transform_matrix (OpenGL axes);
# applied_transform, when present, 3x4.
NERFSTUDIO_CAMERA_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
                            "EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L",
                            "VR180_R", "ORTHOPHOTO", "FISHEYE624"}


def nerfstudio_problems(meta: dict) -> list[str]:
    problems = []
    if meta.get("camera_model", "OPENCV") not in NERFSTUDIO_CAMERA_MODELS:
        problems.append(f"camera_model {meta.get('camera_model')!r}")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        return problems + ["no frames"]
    for key, kind in (("fl_x", float), ("fl_y", float), ("cx", float), ("cy", float), ("w", int), ("h", int)):
        for i, frame in enumerate(frames):
            value = meta.get(key, frame.get(key))
            if not isinstance(value, (int, float)) or (kind is int and int(value) != value) or not value > 0:
                problems.append(f"frame {i}: {key} = {value!r}")
    for key in ("k1", "k2", "k3", "k4", "p1", "p2"):
        if key in meta and not isinstance(meta[key], (int, float)):
            problems.append(f"{key} = {meta[key]!r}")
    for i, frame in enumerate(frames):
        if not isinstance(frame.get("file_path"), str):
            problems.append(f"frame {i}: file_path")
        c2w = np.asarray(frame.get("transform_matrix"), np.float64)
        if c2w.shape != (4, 4) or not np.allclose(c2w[3], [0, 0, 0, 1]):
            problems.append(f"frame {i}: transform_matrix is not 4x4 homogeneous")
        elif not np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-6):
            problems.append(f"frame {i}: transform_matrix rotation is not orthonormal")
    if "applied_transform" in meta and np.asarray(meta["applied_transform"]).shape != (3, 4):
        problems.append("applied_transform is not 3x4")
    return problems


def test_exported_transforms_json_follows_nerfstudio_rules(tmp_path):
    from ghsplat_jax.core.camera import Camera, intrinsics, look_at
    from ghsplat_jax.data.nerf import read_transforms
    from ghsplat_jax.io_utils import write_json
    from ghsplat_jax.synth.dataset import transforms_json

    K = intrinsics(40, 30, 60.0)
    eyes = [(3.0, 0.0, 1.0), (0.0, 3.0, 1.5), (-2.0, -2.0, 0.5)]
    cams = [Camera(K, look_at(np.array(e), np.zeros(3)), 40, 30) for e in eyes]
    names = [f"{i:05d}.png" for i in range(len(cams))]
    meta = transforms_json(cams, names, times=np.arange(3) / 2.0)
    assert nerfstudio_problems(meta) == []
    assert meta["camera_model"] == "OPENCV" and np.array_equal(meta["applied_transform"], np.eye(4)[:3])
    assert nerfstudio_problems({**meta, "camera_model": "KANNALA"}) == ["camera_model 'KANNALA'"]
    # nerfstudio's applied_transform composes with the poses: identity leaves our world frame
    c2w = np.array(meta["frames"][1]["transform_matrix"]) @ np.vstack([meta["applied_transform"], [0, 0, 0, 1]])
    np.testing.assert_allclose(np.linalg.inv(c2w @ np.diag([1.0, -1, -1, 1])), cams[1].world_to_cam, atol=1e-5)
    # and our own reader takes it back
    from ghsplat_jax.data.images import write_image

    for n in names:
        write_image(tmp_path / "images" / n, np.zeros((30, 40, 3), np.float32))
    write_json(tmp_path / "transforms.json", json.loads(json.dumps(meta)))
    spec = read_transforms(tmp_path, 1.0)
    for frame, cam in zip(spec.frames, cams):
        np.testing.assert_allclose(frame.world_to_cam, cam.world_to_cam, atol=1e-5)
        np.testing.assert_allclose(frame.K, K, atol=1e-5)
