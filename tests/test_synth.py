"""Procedural greenhouse generator and ground-truth renderer (ghsplat_jax.synth)."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest

from ghsplat_jax.core.camera import Camera, intrinsics, look_at
from ghsplat_jax.synth import capture, config, render
from ghsplat_jax.synth import scene as synth_scene


def small_config(**layout) -> config.SceneConfig:
    cfg = config.SceneConfig(seed=7)
    return cfg.replace(
        layout=dataclasses.replace(cfg.layout, rows=2, plants_per_row=3, **layout),
        plant=dataclasses.replace(cfg.plant, leaves=(5, 7)),
        ground=dataclasses.replace(cfg.ground, margin=1.0),
        render=dataclasses.replace(cfg.render, texture_size=64))


@pytest.fixture(scope="module")
def small_scene():
    return synth_scene.generate_scene(small_config())


def side_camera(scene, width=96, height=72):
    row = scene.rows[0]
    eye = [(row.x0 + row.x1) / 2, row.y - 0.8, 1.1]
    return Camera(intrinsics(width, height, 65.0), look_at(eye, [eye[0], row.y, 0.5]), width, height)


# --- config -------------------------------------------------------------------------------

def test_config_round_trips_through_toml():
    cfg = small_config(identical_plants=True, container="pot")
    assert config.config_from_dict(tomllib.loads(config.config_to_toml(cfg))) == cfg


@pytest.mark.parametrize("text, needle", [
    ("[layout]\nrows = \"four\"\n", "layout.rows must be an integer"),
    ("[layot]\nrows = 2\n", "unknown key(s) ['layot']"),
    ("[plant]\nleaf_size = 2\n", "plant.leaf_size"),
    ("[layout]\ncontainer = \"crate\"\n", "layout.container"),
    ("[plant]\nheight = [1.0, 0.5]\n", "min <= max"),
    ("[layout\nrows = 2\n", "invalid TOML"),
])
def test_bad_toml_gives_clear_error(tmp_path, text, needle):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as err:
        config.load_config(path)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such scene config"):
        config.load_config(tmp_path / "absent.toml")


# --- scene --------------------------------------------------------------------------------

def test_scene_is_deterministic_from_seed(small_scene):
    again = synth_scene.generate_scene(small_config())
    np.testing.assert_array_equal(again.vertices, small_scene.vertices)
    np.testing.assert_array_equal(again.faces, small_scene.faces)
    np.testing.assert_array_equal(again.face_tint, small_scene.face_tint)
    for a, b in zip(again.materials, small_scene.materials):
        np.testing.assert_array_equal(a.texture, b.texture)
    other = synth_scene.generate_scene(small_config().replace(seed=8))
    assert other.vertices.shape != small_scene.vertices.shape or not np.allclose(other.vertices, small_scene.vertices)


def test_scene_layout_and_instances(small_scene):
    s = small_scene
    assert len(s.rows) == 2 and len(s.tags) == 4
    assert {i.cls for i in s.instances} == {"ground", "plant", "container", "post", "wire", "tag"}
    assert sum(i.cls == "plant" for i in s.instances) == 6
    assert np.all(np.isfinite(s.vertices)) and s.faces.max() < len(s.vertices)
    assert s.vertices[:, 2].min() >= -1e-9  # nothing below the ground
    # plants stand in their rows: each plant's faces lie near its row's centre line
    for inst in s.instances:
        if inst.cls == "plant":
            verts = s.vertices[s.faces[s.face_instance == inst.id]].reshape(-1, 3)
            row = s.rows[int(inst.name.split("_")[1][1:])]
            assert abs(np.median(verts[:, 1]) - row.y) < 0.15


def test_identical_plants_repeat_one_mesh():
    s = synth_scene.generate_scene(small_config(identical_plants=True))
    plants = [i.id for i in s.instances if i.cls == "plant"]
    verts = [s.vertices[np.unique(s.faces[s.face_instance == p])] for p in plants]
    for v in verts[1:]:
        np.testing.assert_allclose(v - v.mean(0), verts[0] - verts[0].mean(0), atol=1e-9)


# --- renderer -----------------------------------------------------------------------------

def brute_force_first_hit(vertices, faces, origin, direction):
    """Distance to the nearest triangle along one ray, by testing every triangle (numpy)."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origin - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ direction) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
    ok = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return (t[ok].min(), np.flatnonzero(ok)[t[ok].argmin()]) if ok.any() else (np.inf, -1)


def test_depth_agrees_with_brute_force_ray_casts(small_scene):
    cam = side_camera(small_scene)
    out = render.render_view(small_scene, cam, shadows=False)
    K = np.asarray(cam.K, np.float64)
    w2c = np.asarray(cam.world_to_cam, np.float64)
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, [72, 96], size=(40, 2))
    for i, j in pixels:
        d_cam = np.linalg.solve(K, [j + 0.5, i + 0.5, 1.0])
        d = w2c[:3, :3].T @ (d_cam / np.linalg.norm(d_cam))
        t, face = brute_force_first_hit(small_scene.vertices, small_scene.faces, centre, d)
        if np.isinf(t):
            assert out["depth"][i, j] == 0 and out["instance"][i, j] == 0
            continue
        z = t * d_cam[2] / np.linalg.norm(d_cam)
        assert out["depth"][i, j] == pytest.approx(z, abs=1e-5, rel=1e-6)
        assert out["instance"][i, j] == small_scene.face_instance[face]
    assert (out["depth"] > 0).mean() > 0.9  # the view is mostly scene, not sky


def test_normals_are_unit_and_face_the_camera(small_scene):
    cam = side_camera(small_scene)
    out = render.render_view(small_scene, cam, shadows=False)
    origins, dirs, _ = render.pixel_rays(cam)
    n = out["normal"].reshape(-1, 3)
    hit = out["depth"].ravel() > 0
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", n[hit], dirs[hit]) <= 1e-6)
    assert np.all(n[~hit] == 0)
    # and they are the hit faces' geometric normals (up to the flip)
    faces = out["face"].ravel()[hit]
    cos = np.abs(np.einsum("ij,ij->i", n[hit], small_scene.face_normals[faces]))
    np.testing.assert_allclose(cos, 1.0, atol=1e-5)


def test_render_outputs_are_finite_and_lit(small_scene):
    out = render.render_view(small_scene, side_camera(small_scene, 48, 36), supersample=2)
    assert out["rgb"].shape == (36, 48, 3) and out["rgb"].dtype == np.float32
    assert np.all(np.isfinite(out["rgb"])) and 0.05 < out["rgb"].mean() < 0.95
    assert set(np.unique(out["semantic"])) <= set(range(len(synth_scene.CLASSES)))
    lit = render.render_view(small_scene, side_camera(small_scene, 48, 36), shadows=False)["rgb"].mean()
    assert lit >= out["rgb"].mean() - 1e-3  # shadows only darken


def test_shadow_rays_find_the_grow_bag(small_scene):
    s = small_scene
    row = s.rows[0]
    sun = render.sun_direction(s)
    assert sun[1] > 0  # the default sun shines from +y: a bag shades the ground just on its -y side
    half_width = synth_scene.BAG_SIZE[0] / 2
    x = row.x0 + 1.5 * s.config.layout.plant_spacing + 0.01  # between two plants, mid bag
    shaded = np.array([[x, row.y - half_width - 0.02, 0.0]])
    sunny = np.array([[x, row.y + 0.3, 0.0]])
    up = np.array([[0.0, 0.0, 1.0]])
    assert render._sun_visibility(s, shaded, up, True, 1, None)[0] == 0.0
    assert render._sun_visibility(s, sunny, up, True, 1, None)[0] == 1.0
    soft = render._sun_visibility(s, shaded, up, True, 8, np.random.default_rng(0))[0]
    assert 0.0 <= soft <= 0.5


# --- capture paths ------------------------------------------------------------------------

def test_handheld_path_circles_the_row_with_more_views_at_the_ends(small_scene):
    cams = capture.capture_path(small_scene, "handheld", 40, row=1, width=64, height=48, seed=3)
    row = small_scene.rows[1]
    centres = np.array([np.asarray(c.center) for c in cams])
    at_ends = (centres[:, 0] < row.x0) | (centres[:, 0] > row.x1)
    d = small_scene.config.layout.row_spacing / 2
    end_density = at_ends.sum() / (2 * np.pi * d)
    aisle_density = (~at_ends).sum() / (2 * (row.x1 - row.x0))
    assert at_ends.sum() > 0 and end_density > 1.5 * aisle_density
    assert np.ptp(centres[:, 2]) > 0.01 and np.all(np.abs(centres[:, 2] - 1.15) < 0.3)
    # every camera looks at the row: the row axis point nearest to it is in front, near centre
    for cam, c in zip(cams, centres):
        target = np.array([np.clip(c[0], row.x0, row.x1), row.y, 0.55])
        p = np.asarray(cam.world_to_cam, np.float64) @ np.append(target, 1.0)
        assert p[2] > 0 and abs(p[0] / p[2]) < 0.5
    again = capture.capture_path(small_scene, "handheld", 40, row=1, width=64, height=48, seed=3)
    np.testing.assert_array_equal(np.asarray(again[5].world_to_cam), np.asarray(cams[5].world_to_cam))


@pytest.mark.parametrize("end", ["x0", "x1"])
def test_one_end_walk_covers_that_end_and_its_share_of_the_row(small_scene, end):
    row = small_scene.rows[1]
    path = capture.PathConfig(end=end, segment_fraction=0.5)
    cams = capture.capture_path(small_scene, "handheld", 30, row=1, width=64, height=48, seed=3, config=path)
    centres = np.array([np.asarray(c.center) for c in cams])
    mid = (row.x0 + row.x1) / 2
    near = centres[:, 0] > mid - 1e-6 if end == "x1" else centres[:, 0] < mid + 1e-6
    assert near.all()  # never walks past the middle of the row
    beyond = centres[:, 0] > row.x1 if end == "x1" else centres[:, 0] < row.x0
    assert beyond.sum() >= 3  # rounds the end
    assert set(np.sign(np.round(centres[:, 1] - row.y, 3))) >= {-1.0, 1.0}  # both aisles
    steps = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1)
    assert steps.max() < 3 * np.median(steps)  # one continuous walk, no jump across the row
    with pytest.raises(ValueError, match="unknown row end"):
        capture.capture_path(small_scene, "handheld", 4, config=capture.PathConfig(end="middle"))
    with pytest.raises(ValueError, match="segment_fraction"):
        capture.capture_path(small_scene, "handheld", 4, config=capture.PathConfig(end=end, segment_fraction=0))


def test_orbit_rings_one_plant_evenly_and_closes_the_loop(small_scene):
    path = capture.PathConfig(plant=1, orbit_radius=0.6)
    cams = capture.capture_path(small_scene, "orbit", 72, row=1, width=64, height=48, seed=3, config=path)
    row, spacing = small_scene.rows[1], small_scene.config.layout.plant_spacing
    plant = np.array([1.5 * spacing, row.y])
    centres = np.array([np.asarray(c.center, np.float64) for c in cams])
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2] - plant, axis=1), 0.6, atol=1e-4)
    np.testing.assert_allclose(centres[:, 2], 1.1, atol=0.1)
    heading = np.unwrap(np.arctan2(*(centres[:, :2] - plant).T[::-1]))
    steps = np.diff(np.append(heading, heading[0] + 2 * np.pi))  # the last view neighbours the first
    np.testing.assert_allclose(steps, 2 * np.pi / 72, atol=1e-6)
    for cam in cams:  # every view looks at the plant
        p = np.asarray(cam.world_to_cam, np.float64) @ np.append(plant, [0.55, 1.0])
        assert p[2] > 0 and abs(p[0] / p[2]) < 0.1 and abs(p[1] / p[2]) < 0.1
    with pytest.raises(ValueError, match="plant 3 does not exist"):
        capture.capture_path(small_scene, "orbit", 4, config=capture.PathConfig(plant=3))


def test_robot_path_drives_both_aisles_at_robot_height(small_scene):
    cams = capture.capture_path(small_scene, "robot", 10, row=0, width=64, height=48)
    row = small_scene.rows[0]
    centres = np.array([np.asarray(c.center) for c in cams])
    np.testing.assert_allclose(centres[:, 2], 0.5, atol=0.02)
    assert set(np.sign(np.round(centres[:, 1] - row.y, 3))) == {-1.0, 1.0}
    with pytest.raises(ValueError, match="unknown capture path"):
        capture.capture_path(small_scene, "drone", 4)
    with pytest.raises(ValueError, match="row 5 does not exist"):
        capture.capture_path(small_scene, "robot", 4, row=5)


# --- tags ---------------------------------------------------------------------------------

@pytest.mark.parametrize("tag_index, side, tolerance", [(1, 0.0, 0.1), (2, 0.1, 1.0)])
def test_rendered_tag_is_detected_at_its_recorded_pose(small_scene, tag_index, side, tolerance):
    import cv2

    tag = small_scene.tags[tag_index]
    R, t = tag.world_from_tag[:3, :3], tag.world_from_tag[:3, 3]
    width, height = 160, 120
    eye = t + R[:, 2] * 0.45 + R[:, 0] * side  # in front of the printed face (fronto-parallel or oblique)
    cam = Camera(intrinsics(width, height, 50.0), look_at(eye, t, up=R[:, 1]), width, height)
    rgb = render.render_view(small_scene, cam, shadows=False)["rgb"]
    gray = np.clip(rgb.mean(-1) * 255 + 0.5, 0, 255).astype(np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(gray)
    assert ids is not None and tag.id in ids.ravel()
    found = corners[list(ids.ravel()).index(tag.id)].reshape(4, 2)
    K, w2c = np.asarray(cam.K, np.float64), np.asarray(cam.world_to_cam, np.float64)
    pc = tag.corners_world() @ w2c[:3, :3].T + w2c[:3, 3]
    expected = (pc @ K.T)[:, :2] / pc[:, 2:]
    # OpenCV reports corners in pixel-index coordinates (pixel centre at integer), ours at +0.5
    # (fronto-parallel: sub-pixel; oblique: within the aliasing of one sample per pixel)
    np.testing.assert_allclose(found + 0.5, expected, atol=tolerance)


def test_pots_cover_and_intermediate_posts():
    cfg = small_config(container="pot")
    cfg = cfg.replace(ground=dataclasses.replace(cfg.ground, kind="cover"),
                      structure=dataclasses.replace(cfg.structure, post_spacing=0.5),
                      tags=dataclasses.replace(cfg.tags, first_id=10))
    s = synth_scene.generate_scene(cfg)
    assert sum(i.cls == "container" for i in s.instances) == 6  # one pot per plant
    assert sum(i.cls == "post" for i in s.instances) == 2 * 4  # two ends + 0.5 and 1.0 m, per row
    assert [t.id for t in s.tags] == [10, 11, 12, 13]
    views = render.render_views(s, [side_camera(s, 32, 24)] * 2, shadows=False)
    assert views["rgb"].shape == (2, 24, 32, 3) and views["depth"].shape == (2, 24, 32)
    np.testing.assert_array_equal(views["rgb"][0], views["rgb"][1])
