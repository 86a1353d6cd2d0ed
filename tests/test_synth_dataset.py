"""Dataset folders written by ghsplat_jax.synth: every file describes the generator's cameras."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ghsplat_jax.core.quaternions import to_rotation_matrix
from ghsplat_jax.data.images import read_pixels
from ghsplat_jax.scene.tags import load_tags
from ghsplat_jax.synth import capture, config, dataset, render
from ghsplat_jax.synth import scene as synth_scene

W, H, VIEWS = 64, 48, 5


def small_config() -> config.SceneConfig:
    cfg = config.SceneConfig(seed=7)
    return cfg.replace(
        layout=dataclasses.replace(cfg.layout, rows=2, plants_per_row=3),
        plant=dataclasses.replace(cfg.plant, leaves=(5, 7)),
        ground=dataclasses.replace(cfg.ground, margin=1.0),
        render=dataclasses.replace(cfg.render, texture_size=64))


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    s = synth_scene.generate_scene(small_config())
    cams = capture.capture_path(s, "handheld", VIEWS, row=0, width=W, height=H, seed=1)
    out = dataset.write_dataset(s, cams, tmp_path_factory.mktemp("ds") / "row0", n_points=400, fps=4.0)
    return s, cams, out


def parse_colmap(folder):
    cams, images, points = {}, [], {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            cid, model, w, h, *params = line.split()
            cams[int(cid)] = (model, int(w), int(h), [float(p) for p in params])
    lines = [ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    for head, obs in zip(lines[0::2], lines[1::2]):
        iid, qw, qx, qy, qz, tx, ty, tz, cid, name = head.split()
        xy_id = np.array(obs.split(), float).reshape(-1, 3)
        q, t = np.array([qw, qx, qy, qz], float), np.array([tx, ty, tz], float)
        images.append((int(iid), q, t, int(cid), name, xy_id))
    for line in (folder / "points3D.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            v = line.split()
            points[int(v[0])] = (np.array(v[1:4], float), np.array(v[4:7], int), np.array(v[8:], int).reshape(-1, 2))
    return cams, images, points


def test_colmap_text_describes_the_generator_cameras(written):
    s, cams, out = written
    colmap_cams, images, points = parse_colmap(out / "sparse" / "0")
    assert len(images) == VIEWS and len(colmap_cams) == 1
    for cam, (_iid, q, t, cid, name, _) in zip(cams, images):
        model, w, h, (fx, fy, cx, cy) = colmap_cams[cid]
        K = np.asarray(cam.K, np.float64)
        assert (model, w, h) == ("PINHOLE", W, H) and (out / "images" / name).exists()
        np.testing.assert_allclose([fx, fy, cx, cy], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=1e-12)
        w2c = np.asarray(cam.world_to_cam, np.float64)
        np.testing.assert_allclose(np.asarray(to_rotation_matrix(q)), w2c[:3, :3], atol=2e-6)
        np.testing.assert_allclose(t, w2c[:3, 3], atol=1e-12)
    assert len(points) > 100


def test_points3d_lie_on_visible_surfaces_and_reproject(written):
    s, cams, out = written
    _, images, points = parse_colmap(out / "sparse" / "0")
    depth = [read_pixels(out / "depth" / f"{i:05d}.exr") for i in range(VIEWS)]
    n_obs = 0
    for (iid, _q, _t, _cid, _name, xy_id), cam in zip(images, cams):
        K, w2c = np.asarray(cam.K, np.float64), np.asarray(cam.world_to_cam, np.float64)
        for k, (x, y, pid) in enumerate(xy_id):
            xyz = points[int(pid)][0]
            pc = w2c[:3, :3] @ xyz + w2c[:3, 3]
            np.testing.assert_allclose((K @ pc)[:2] / pc[2], [x, y], atol=1e-6)
            assert [iid, k] in points[int(pid)][2].tolist()  # the track points back at this observation
            z = depth[iid - 1][int(y), int(x)]
            n_obs += abs(z - pc[2]) < 0.01 + 0.02 * pc[2]
    total = sum(len(im[5]) for im in images)
    assert total > 0 and n_obs / total > 0.9  # visible points agree with the depth map (edges aside)
    rgb = np.array([p[1] for p in points.values()])
    assert rgb.std() > 5


def test_point_colours_are_what_the_photos_show(written):
    # As COLMAP colours its points: the mean of the observed pixels (lit, shaded), not the albedo.
    s, cams, out = written
    _, images, points = parse_colmap(out / "sparse" / "0")
    photos = {iid: read_pixels(out / "images" / name).astype(float) for iid, _, _, _, name, _ in images}
    observed = {iid: xy_id for iid, _, _, _, _, xy_id in images}
    for _pid, (_, rgb, track) in points.items():
        seen = [photos[iid][int(observed[iid][k][1]), int(observed[iid][k][0]), :3] for iid, k in track]
        np.testing.assert_allclose(rgb, np.mean(seen, axis=0), atol=0.51)


def test_transforms_json_matches_colmap(written):
    s, cams, out = written
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (W, H) and len(meta["frames"]) == VIEWS
    for v, (cam, frame) in enumerate(zip(cams, meta["frames"])):
        c2w_gl = np.array(frame["transform_matrix"])
        w2c = np.linalg.inv(c2w_gl @ np.diag([1.0, -1, -1, 1]))
        np.testing.assert_allclose(w2c, np.asarray(cam.world_to_cam, np.float64), atol=1e-6)
        K = np.asarray(cam.K, np.float64)
        np.testing.assert_allclose([meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]],
                                   [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        assert frame["time"] == pytest.approx(v / 4.0)
        assert (out / frame["file_path"]).exists() and (out / frame["depth_file_path"]).exists()


def test_ground_truth_images_round_trip(written):
    s, cams, out = written
    views = render.render_view(s, cams[2])
    np.testing.assert_array_equal(read_pixels(out / "depth" / "00002.exr"), views["depth"])
    np.testing.assert_array_equal(read_pixels(out / "normals" / "00002.exr"), views["normal"])
    np.testing.assert_array_equal(read_pixels(out / "masks" / "00002.png"), views["instance"])
    rgb = read_pixels(out / "images" / "00002.png")
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8
    np.testing.assert_allclose(rgb / 255.0, views["rgb"], atol=1 / 255 + 1e-6)
    inst = json.loads((out / "instances.json").read_text())
    assert {i["id"] for i in inst["instances"]} >= set(np.unique(views["instance"])) - {0}


def test_side_files_regenerate_the_scene(written):
    import trimesh

    s, cams, out = written
    family, tags = load_tags(out / "tags.json")
    assert family == "tag36h11" and [t.id for t in tags] == [t.id for t in s.tags]
    for a, b in zip(tags, s.tags):
        np.testing.assert_allclose(a.world_from_tag, b.world_from_tag)
        assert a.size == b.size
    again = synth_scene.generate_scene(config.load_config(out / "scene.toml"))
    np.testing.assert_array_equal(again.vertices, s.vertices)
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert ply.vertices.shape == s.vertices.shape and ply.faces.shape == s.faces.shape
    glb = trimesh.load(out / "mesh.glb")
    assert sum(len(g.faces) for g in glb.geometry.values()) == len(s.faces)


def test_existing_dataset_is_not_clobbered(written, tmp_path):
    s, cams, out = written
    with pytest.raises(FileExistsError, match="already holds a dataset"):
        dataset.write_dataset(s, cams[:1], out)
    small = tmp_path / "again"
    dataset.write_dataset(s, cams[:3], small, n_points=50, meshes=False)
    dataset.write_dataset(s, cams[:2], small, n_points=50, meshes=False, overwrite=True)
    assert sorted(p.name for p in (small / "images").iterdir()) == ["00000.png", "00001.png"]


def test_command_line(tmp_path, capsys):
    """`ghsplat synth` end to end: every option reaches the files, and the project's reader loads them."""
    from ghsplat_jax.cli import main
    from ghsplat_jax.data import load_dataset

    toml = tmp_path / "scene.toml"
    toml.write_text("seed = 4\n[layout]\nrows = 1\nplants_per_row = 2\n[render]\ntexture_size = 64\n")
    out = tmp_path / "ds"
    argv = ["synth", "--config", str(toml), "--out", str(out), "--views", "3", "--width", "32", "--height", "24",
            "--path", "robot", "--points", "100", "--no-mesh", "--seed", "9", "--fps", "4"]
    assert main(argv) == 0
    assert sorted(p.name for p in (out / "images").iterdir()) == ["00000.png", "00001.png", "00002.png"]
    assert not (out / "mesh.ply").exists()
    for i in range(3):
        rgb = read_pixels(out / "images" / f"{i:05d}.png")
        depth = read_pixels(out / "depth" / f"{i:05d}.exr")
        normal = read_pixels(out / "normals" / f"{i:05d}.exr")
        mask = read_pixels(out / "masks" / f"{i:05d}.png")
        assert rgb.shape == (24, 32, 3) and rgb.dtype == np.uint8 and rgb.std() > 5
        assert depth.shape == (24, 32) and depth.dtype == np.float32 and depth.min() >= 0 and depth.max() > 0
        hit = depth > 0
        np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=-1), 1.0, atol=1e-4)
        assert not normal[~hit].any() and mask.dtype == np.uint16 and not mask[~hit].any()
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (32, 24) and [f["time"] for f in meta["frames"]] == [0.0, 0.25, 0.5]
    cfg = config.load_config(out / "scene.toml")
    assert cfg.seed == 9 and (cfg.layout.rows, cfg.layout.plants_per_row, cfg.render.texture_size) == (1, 2, 64)
    ds = load_dataset(out, split="all")
    assert len(ds.train) == 3 and (ds.train[0].camera.width, ds.train[0].camera.height) == (32, 24)
    np.testing.assert_allclose(ds.train[0].image, read_pixels(out / "images" / "00000.png") / 255.0, atol=1e-6)
    toml.write_text("[layout]\nrows = 0\n")
    assert main(argv + ["--overwrite"]) == 2
    assert "layout.rows must be >= 1" in capsys.readouterr().err
