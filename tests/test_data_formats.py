"""Dataset readers on small synthetic scenes written in every format we read.

The same cameras written as COLMAP text/binary, transforms.json and LLFF must load to
the same K and world_to_cam; undistortion and downscaling are checked against an
analytic image of a smooth pattern; bad inputs must raise DatasetError naming the file.
"""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest

from ghsplat_jax.core.camera import look_at
from ghsplat_jax.data import Dataset, DatasetError, DatasetWarning, View, detect_format, load_dataset
from ghsplat_jax.data.colmap import read_cameras, read_images, read_points
from ghsplat_jax.data.images import read_image, write_image
from ghsplat_jax.data.splits import split_indices, subsample

W, H = 24, 18


def _cameras(n=10):
    """n OpenCV cameras on a ring looking at the origin: (K, world_to_cam) float64."""
    K = np.array([[20.0, 0, 12.5], [0, 21.0, 8.75], [0, 0, 1]])
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 1.0 + 0.1 * i])
        out.append((K, look_at(eye, [0.1, -0.2, 0.3]).astype(np.float64)))
    return out


def _quat_wxyz(R):
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _write_colmap_text(folder, cams, names, model="PINHOLE", params=None, points=None, size=(W, H)):
    folder.mkdir(parents=True, exist_ok=True)
    K = cams[0][0]
    params = params if params is not None else [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    (folder / "cameras.txt").write_text(
        f"# Camera list\n1 {model} {size[0]} {size[1]} {' '.join(repr(float(p)) for p in params)}\n"
    )
    pts = points if points is not None else np.zeros((0, 3))
    lines = ["# Image list with two lines of data per image:"]
    for i, ((_, w2c), name) in enumerate(zip(cams, names), 1):
        q, t = _quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i} {' '.join(map(repr, q.tolist()))} {' '.join(map(repr, t.tolist()))} 1 {name}")
        # the first image observes every point (keypoint k <-> point k+1); others have none
        lines.append(" ".join(f"{k}.5 {k}.5 {k + 1}" for k in range(len(pts))) if i == 1 else "")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text(
        "".join(f"{k + 1} {x} {y} {z} 255 128 0 0.5 1 {k}\n" for k, (x, y, z) in enumerate(pts))
    )


def _write_images(folder, names, size=(W, H), value=None, rgba=False):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        shape = (size[1], size[0], 4 if rgba else 3)
        img = rng.random(shape, dtype=np.float32) if value is None else np.full(shape, value, np.float32)
        write_image(folder / name, img)


def _write_transforms(path, cams, file_paths, w=W, h=H, **extra):
    K = cams[0][0]
    frames = []
    for (_, w2c), fp in zip(cams, file_paths):
        c2w = np.linalg.inv(w2c)
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": fp, "transform_matrix": c2w.tolist()})
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h, **extra}
    meta["frames"] = frames
    path.write_text(json.dumps(meta))


def _write_llff(root, cams, focal):
    rows = []
    for _, w2c in cams:
        c2w = np.linalg.inv(w2c)
        R = c2w[:3, :3]  # OpenCV columns [right, down, forward] -> LLFF [down, right, back]
        axes = np.stack([R[:, 1], R[:, 0], -R[:, 2]], 1)
        pose = np.concatenate([axes, c2w[:3, 3:], [[H], [W], [focal]]], 1)
        rows.append(np.concatenate([pose.ravel(), [0.5, 10.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))


def _assert_same_cameras(a: list[View], b: list[View], tol=1e-5):
    assert [v.name.split("/")[-1] for v in a] == [v.name.split("/")[-1] for v in b]
    for va, vb in zip(a, b):
        np.testing.assert_allclose(np.asarray(va.camera.K), np.asarray(vb.camera.K), rtol=tol, atol=tol)
        np.testing.assert_allclose(
            np.asarray(va.camera.world_to_cam), np.asarray(vb.camera.world_to_cam), rtol=tol, atol=tol
        )
        assert (va.camera.width, va.camera.height) == (vb.camera.width, vb.camera.height)


@pytest.fixture
def scene(tmp_path):
    """The same 10 cameras as COLMAP text (sparse/0), transforms.json and (centred K) LLFF."""
    cams = _cameras()
    names = [f"img{i:02d}.png" for i in range(len(cams))]
    _write_images(tmp_path / "colmap" / "images", names)
    points = [[0.0, 0.0, 0.0], [0.2, 0.1, 0.3]]
    _write_colmap_text(tmp_path / "colmap" / "sparse" / "0", cams, names, points=points)
    (tmp_path / "ngp").mkdir()
    shutil.copytree(tmp_path / "colmap" / "images", tmp_path / "ngp" / "images")
    _write_transforms(tmp_path / "ngp" / "transforms.json", cams, [f"images/{n}" for n in names])
    return tmp_path, cams, names


def test_colmap_text_binary_and_transforms_agree(scene):
    root, cams, names = scene
    col = load_dataset(root / "colmap")
    ngp = load_dataset(root / "ngp")
    assert (col.format, ngp.format) == ("colmap", "transforms")
    # every 8th in sorted order is a test view: img00 and img08
    assert [v.name for v in col.test] == ["img00.png", "img08.png"]
    _assert_same_cameras(col.train, ngp.train)
    _assert_same_cameras(col.test, ngp.test)
    for view, i in zip(col.train, [1, 2, 3, 4, 5, 6, 7, 9]):
        np.testing.assert_allclose(np.asarray(view.camera.world_to_cam), cams[i][1], atol=1e-5)
        np.testing.assert_allclose(np.asarray(view.camera.K), cams[i][0], atol=1e-5)
    np.testing.assert_allclose(col.points, [[0, 0, 0], [0.2, 0.1, 0.3]])
    np.testing.assert_allclose(col.point_colors[0], [1.0, 128 / 255, 0.0])
    assert ngp.points.shape == (0, 3) and ngp.point_colors is None
    # 3DGS convention: 1.1 x the largest distance of a training camera from their mean
    centres = np.array([-w2c[:3, :3].T @ w2c[:3, 3] for _, w2c in cams])[[1, 2, 3, 4, 5, 6, 7, 9]]
    expected = 1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max()
    assert col.scene_extent == pytest.approx(expected, rel=1e-5)
    np.testing.assert_allclose(col.scene_center, centres.mean(0), atol=1e-5)

    pycolmap = pytest.importorskip("pycolmap")
    binary = root / "colmap_bin"
    shutil.copytree(root / "colmap" / "images", binary / "images")
    (binary / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(str(root / "colmap" / "sparse" / "0")).write_binary(str(binary / "sparse" / "0"))
    assert (binary / "sparse" / "0" / "images.bin").is_file()
    _assert_same_cameras(load_dataset(binary).views, col.views)


def test_llff_axis_reorder_matches_colmap(tmp_path):
    cams = [(np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]), w2c) for _, w2c in _cameras(9)]
    names = [f"image{i:03d}.png" for i in range(9)]
    _write_images(tmp_path / "llff" / "images", names)
    _write_llff(tmp_path / "llff", cams, focal=20.0)
    _write_images(tmp_path / "col" / "images", names)
    _write_colmap_text(tmp_path / "col" / "sparse" / "0", cams, names, "SIMPLE_PINHOLE", [20.0, W / 2, H / 2])
    llff, col = load_dataset(tmp_path / "llff"), load_dataset(tmp_path / "col")
    assert llff.format == "llff"
    _assert_same_cameras(llff.views, col.views)
    # the camera looks at its target: the origin-ish point is in front (z > 0), near the centre
    target = np.array([0.1, -0.2, 0.3, 1.0])
    for view in llff.views:
        x = np.asarray(view.camera.world_to_cam, np.float64) @ target
        assert x[2] > 0
        u = np.asarray(view.camera.K, np.float64) @ (x[:3] / x[2])
        np.testing.assert_allclose(u[:2], [W / 2, H / 2], atol=1e-3)


def test_llff_uses_downscaled_folder_and_scales_focal(tmp_path):
    cams = _cameras(3)
    _write_images(tmp_path / "images_2", [f"a{i}.png" for i in range(3)], size=(W // 2, H // 2), value=0.25)
    _write_llff(tmp_path, cams, focal=20.0)
    ds = load_dataset(tmp_path, downscale=2, split="all")
    assert len(ds.train) == 3 and not ds.test
    view = ds.train[0]
    assert view.image.shape == (H // 2, W // 2, 3) and np.allclose(view.image, 0.25, atol=1 / 255)
    expected = [[10, 0, W / 4], [0, 10, H / 4], [0, 0, 1]]
    np.testing.assert_allclose(np.asarray(view.camera.K), expected, atol=1e-5)
    # further downscaled from images_2; no full-resolution folder for downscale 1
    assert load_dataset(tmp_path, downscale=4, max_views=1).train[0].image.shape == (H // 4, W // 4, 3)
    with pytest.raises(DatasetError, match=r"images_2/ \(downscale 2\).*downscale=2"):
        load_dataset(tmp_path, downscale=1)
    (tmp_path / "images_2" / "a2.png").unlink()
    with pytest.raises(DatasetError, match=r"images_2: 2 images, but .*poses_bounds.npy has 3 poses"):
        load_dataset(tmp_path, downscale=2)


def _pattern(x, y):
    """A smooth image of normalised camera coordinates (period ~ 0.25, i.e. ~20 px here)."""
    r = 0.5 + 0.3 * np.sin(2 * np.pi * x / 0.25) * np.cos(2 * np.pi * y / 0.3)
    return np.stack([r, 0.5 + 0.4 * np.sin(2 * np.pi * (x + y) / 0.35), 0.5 + 0.4 * x], -1)


def _distort(x, y, k1, k2, p1, p2):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    return xd, y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def _render_pattern(K, width, height, dist=(0.0, 0.0, 0.0, 0.0)):
    """The pattern seen by a camera with OpenCV-model distortion (numpy inverse, no cv2)."""
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # our pixel centres
    xd, yd = (j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(100):  # fixed point: undistorted coords whose distortion is (xd, yd)
        dx, dy = _distort(x, y, *dist)
        x, y = x - (dx - xd), y - (dy - yd)
    return _pattern(x, y).astype(np.float32)


@pytest.mark.parametrize(
    "model, params, dist",
    [
        ("OPENCV", [100.0, 104.0, 61.0, 44.5, -0.25, 0.06, 0.004, -0.003], (-0.25, 0.06, 0.004, -0.003)),
        ("SIMPLE_RADIAL", [100.0, 60.0, 45.0, -0.2], (-0.2, 0.0, 0.0, 0.0)),
        ("RADIAL", [100.0, 60.0, 45.0, 0.15, -0.05], (0.15, -0.05, 0.0, 0.0)),
    ],
)
def test_undistortion_matches_the_pinhole_projection(tmp_path, model, params, dist):
    """A distorted image of a known pattern, undistorted, equals the pattern seen through the new K."""
    width, height = 120, 90
    fx, fy, cx, cy = params[:4] if model == "OPENCV" else (params[0], params[0], params[1], params[2])
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    write_image(tmp_path / "images" / "d.png", _render_pattern(K, width, height, dist), "uint16")
    cams = [(K, look_at([0, 0, -3.0], [0, 0, 0]).astype(np.float64))]
    _write_colmap_text(tmp_path / "sparse" / "0", cams, ["d.png"], model, params, size=(width, height))
    view = load_dataset(tmp_path, split="all").train[0]
    K2 = np.asarray(view.camera.K, np.float64)
    assert K2[0, 1] == 0 and view.image.shape == (height, width, 3)
    err = np.abs(view.image - _render_pattern(K2, width, height)).mean()
    naive = np.abs(_render_pattern(K, width, height, dist) - _render_pattern(K2, width, height)).mean()
    shifted = K2 + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # the half-pixel-convention mistake
    half_pixel = np.abs(view.image - _render_pattern(shifted, width, height)).mean()
    assert err < 0.002, err
    assert naive > 10 * err and half_pixel > 3 * err, (err, naive, half_pixel)

    if model == "OPENCV":  # the instant-ngp parameters give the same image and camera
        (tmp_path / "sparse" / "0" / "images.txt").unlink()
        k1, k2, p1, p2 = dist
        _write_transforms(
            tmp_path / "transforms.json", cams, ["images/d.png"], width, height, k1=k1, k2=k2, p1=p1, p2=p2
        )
        ngp = load_dataset(tmp_path, split="all").train[0]
        np.testing.assert_allclose(np.asarray(ngp.camera.K), K2, rtol=1e-6)
        np.testing.assert_allclose(ngp.image, view.image, atol=1e-6)


def test_undistortion_maps_follow_the_distortion_model():
    """Each output pixel centre, through the new K and the OPENCV model, lands where the map samples."""
    from ghsplat_jax.data.distortion import make_undistorter

    K = np.array([[100.0, 0, 61.0], [0, 104.0, 44.5], [0, 0, 1]])
    dist = (-0.25, 0.06, 0.004, -0.003)
    und = make_undistorter(K, np.array(dist), 120, 90)
    j, i = np.meshgrid(np.arange(120) + 0.5, np.arange(90) + 0.5)
    x, y = (j - und.new_K[0, 2]) / und.new_K[0, 0], (i - und.new_K[1, 2]) / und.new_K[1, 1]
    xd, yd = _distort(x, y, *dist)
    # the maps are in OpenCV's convention (pixel centres at integers): subtract 0.5
    np.testing.assert_allclose(und.map_x, K[0, 0] * xd + K[0, 2] - 0.5, atol=2e-3)
    np.testing.assert_allclose(und.map_y, K[1, 1] * yd + K[1, 2] - 0.5, atol=2e-3)
    # every output pixel sees the source image (up to the estimate's sliver)
    assert und.map_x.min() > -1 and und.map_x.max() < 120 and und.map_y.min() > -1 and und.map_y.max() < 90


def test_downscale_scales_K_with_pixel_centres_at_half(tmp_path):
    width, height = 96, 64
    K = np.array([[80.0, 0, 47.0], [0, 80.0, 33.0], [0, 0, 1]])
    write_image(tmp_path / "images" / "a.png", _render_pattern(K, width, height), "uint16")
    wrong_size = (width // 4 + 3, height // 4)
    _write_images(tmp_path / "images_4", ["a.png"], size=wrong_size, value=0.0)
    _write_colmap_text(tmp_path / "sparse" / "0", [(K, np.eye(4))], ["a.png"], size=(width, height))
    # images_4 has the wrong size: fall back to images/ and area-filter it ourselves
    view = load_dataset(tmp_path, downscale=4, split="all").train[0]
    assert view.image_path == tmp_path / "images" / "a.png"
    K4 = np.asarray(view.camera.K, np.float64)
    np.testing.assert_allclose(K4, np.diag([0.25, 0.25, 1]) @ K, rtol=1e-6)
    assert np.abs(view.image - _render_pattern(K4, width // 4, height // 4)).mean() < 0.01
    shutil.move(tmp_path / "images", tmp_path / "full")
    with pytest.raises(DatasetError, match=r"downscale 2 needs images/ or images_N/ with N <= 2.*images_4/"):
        load_dataset(tmp_path, downscale=2)
    shutil.move(tmp_path / "full", tmp_path / "images")
    # a pre-downscaled copy of the right size is used as it is
    _write_images(tmp_path / "images_4", ["a.png"], size=(width // 4, height // 4), value=0.5)
    view = load_dataset(tmp_path, downscale=4, split="all").train[0]
    assert view.image_path == tmp_path / "images_4" / "a.png" and np.allclose(view.image, 0.5, atol=1 / 255)
    # non-integer factors go through cv2's area filter
    assert load_dataset(tmp_path, downscale=1.5, split="all").train[0].image.shape == (43, 64, 3)


@pytest.mark.parametrize(
    "ext, dtype, tol",
    [("png", "uint8", 1 / 255), ("png", "uint16", 1e-4), ("tif", "uint16", 1e-4), ("exr", "half", 1e-3),
     ("exr", "float", 1e-6)],
)
def test_image_io_bit_depths_and_alpha(tmp_path, ext, dtype, tol):
    rng = np.random.default_rng(1)
    rgba = rng.random((7, 5, 4), dtype=np.float32)
    write_image(tmp_path / f"a.{ext}", rgba, dtype)
    rgb, alpha = read_image(tmp_path / f"a.{ext}")
    assert rgb.dtype == np.float32 and rgb.shape == (7, 5, 3)
    np.testing.assert_allclose(alpha, rgba[..., 3], atol=tol)
    np.testing.assert_allclose(rgb, rgba[..., :3] * rgba[..., 3:], atol=2 * tol)  # premultiplied


def test_integer_pixels_are_stored_as_given_and_floats_quantised(tmp_path):
    import OpenImageIO as oiio

    from ghsplat_jax.data.images import read_pixels

    rng = np.random.default_rng(2)
    mask = rng.integers(0, 60000, (6, 4), dtype=np.uint16)
    write_image(tmp_path / "m.png", mask)
    np.testing.assert_array_equal(read_pixels(tmp_path / "m.png"), mask)
    rgb8 = rng.integers(0, 256, (6, 4, 3), dtype=np.uint8)
    write_image(tmp_path / "c.png", rgb8)
    np.testing.assert_array_equal(read_pixels(tmp_path / "c.png"), rgb8)
    grey = rng.random((6, 4), dtype=np.float32)
    write_image(tmp_path / "g.png", grey)  # floats in [0, 1] -> rounded 8-bit
    np.testing.assert_array_equal(read_pixels(tmp_path / "g.png"), np.round(grey * 255).astype(np.uint8))
    depth = rng.random((6, 4), dtype=np.float32) * 40.0
    write_image(tmp_path / "d.exr", depth)
    np.testing.assert_array_equal(read_pixels(tmp_path / "d.exr"), depth)
    assert oiio.ImageBuf(str(tmp_path / "d.exr")).spec().channelnames == ("Z",)
    with pytest.raises(ValueError, match="non-finite"):
        write_image(tmp_path / "bad.exr", np.full((2, 2), np.nan, np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.png", "d.exr", "g.png", "m.png"]  # no temp files


def test_area_resize_without_opencv_is_block_means(monkeypatch):
    import sys

    from ghsplat_jax.data.images import resize_area

    image = np.random.default_rng(4).random((8, 12, 3), dtype=np.float32)
    with_cv2 = resize_area(image, 6, 4)
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 now raises ImportError
    np.testing.assert_allclose(resize_area(image, 6, 4), image.reshape(4, 2, 6, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    np.testing.assert_allclose(resize_area(image, 6, 4), with_cv2, atol=1e-5)
    with pytest.raises(DatasetError, match="needs OpenCV"):
        resize_area(image, 5, 4)


def test_rgba_is_composited_on_the_background(tmp_path):
    cams = _cameras(2)
    rgba = np.zeros((H, W, 4), np.float32)
    rgba[..., 0], rgba[..., 3] = 1.0, 0.25  # quarter-opaque red
    (tmp_path / "train").mkdir()
    for i in range(2):
        write_image(tmp_path / "train" / f"r_{i}.png", rgba)
    c2w = [np.linalg.inv(w2c) @ np.diag([1, -1, -1, 1]) for _, w2c in cams]
    for part in ("train", "test"):
        frames = [{"file_path": f"./train/r_{i}", "transform_matrix": c2w[i].tolist()} for i in range(2)]
        meta = {"camera_angle_x": 0.9, "frames": frames[: 2 if part == "train" else 1]}
        (tmp_path / f"transforms_{part}.json").write_text(json.dumps(meta))
    ds = load_dataset(tmp_path, background=(0.0, 0.0, 1.0))
    assert ds.split == "dataset" and (len(ds.train), len(ds.test)) == (2, 1)
    view = ds.train[0]
    assert view.name == "train/r_0.png"
    np.testing.assert_allclose(view.image[0, 0], [0.25, 0.0, 0.75], atol=2 / 255)
    np.testing.assert_allclose(view.alpha, 0.25, atol=1 / 255)
    assert view.camera.K[0, 0] == pytest.approx(0.5 * W / np.tan(0.45), rel=1e-6)
    np.testing.assert_allclose(np.asarray(view.camera.world_to_cam), cams[0][1], atol=1e-5)
    assert len(load_dataset(tmp_path, split="every").test) == 1  # r_0 of the 3 frames, sorted


def test_splits_and_max_views():
    names = [f"{i:03d}" for i in range(20)]
    train, test, rule = split_indices(names[::-1], None)  # sorted file order, not listing order
    assert rule == "every" and sorted(names[::-1][i] for i in test) == ["000", "008", "016"]
    assert len(train) == 17 and not set(train) & set(test)
    assert split_indices(names, ["train"] * 18 + ["test"] * 2)[1:] == ([18, 19], "dataset")
    assert split_indices(names, None, "all")[:2] == (list(range(20)), [])
    assert subsample(list(range(100)), 5) == [0, 25, 50, 74, 99]
    with pytest.raises(DatasetError, match="defines no train/test split"):
        split_indices(names, None, "dataset")
    with pytest.raises(DatasetError, match="unknown split"):
        split_indices(names, None, "bogus")


def test_max_views_keeps_extent(scene):
    root, _, _ = scene
    full, few = load_dataset(root / "colmap"), load_dataset(root / "colmap", max_views=3)
    assert (len(few.train), len(few.test)) == (3, 2)
    assert few.scene_extent == full.scene_extent
    assert isinstance(full, Dataset) and full.train[0].image.dtype == np.float32
    assert isinstance(full.train[0].image, np.ndarray) and full.train[0].alpha is None


# ---- bad input -------------------------------------------------------------------------


def test_corrupt_truncated_and_missing_images_name_the_file(scene):
    root, _, _ = scene
    bad = root / "colmap" / "images" / "img03.png"
    data = bad.read_bytes()
    bad.write_bytes(b"not an image at all")
    with pytest.raises(DatasetError, match="img03.png: cannot read image"):
        load_dataset(root / "colmap")
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="img03.png: corrupt or truncated image"):
        load_dataset(root / "colmap")
    bad.unlink()
    with pytest.raises(DatasetError, match=r"images.txt.*image not found for 'img03.png'.*img03.png not"):
        load_dataset(root / "colmap")


def test_size_mismatch_names_the_file(scene):
    root, _, _ = scene
    _write_images(root / "colmap" / "images", ["img05.png"], size=(W + 2, H))
    with pytest.raises(DatasetError, match=r"img05.png is 26x18 but its camera says 24x18"):
        load_dataset(root / "colmap")


def test_zero_registered_images_and_bad_models(scene):
    root, _, _ = scene
    model = root / "colmap" / "sparse" / "0"
    (model / "images.txt").write_text("# no images\n")
    with pytest.raises(DatasetError, match=r"images.txt: COLMAP model has zero registered images"):
        load_dataset(root / "colmap")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 7 img00.png\n\n")
    with pytest.raises(DatasetError, match=r"images.txt.*refers to camera 7, absent from .*cameras.txt"):
        load_dataset(root / "colmap")
    (model / "cameras.txt").write_text("7 OPENCV_FISHEYE 24 18 20 20 12 9 0.1 0 0 0\n")
    with pytest.raises(DatasetError, match=r"cameras.txt: camera 7 uses the OPENCV_FISHEYE model"):
        load_dataset(root / "colmap")
    (model / "cameras.txt").write_text("7 PINHOLE 24 18 20\n")
    with pytest.raises(DatasetError, match=r"cameras.txt:1: malformed COLMAP text \(PINHOLE takes 4"):
        load_dataset(root / "colmap")


def test_truncated_binary_model_names_the_file(scene):
    pycolmap = pytest.importorskip("pycolmap")
    root, _, _ = scene
    model = root / "colmap" / "sparse" / "0"
    pycolmap.Reconstruction(str(model)).write_binary(str(model))
    for f in model.glob("*.txt"):
        f.unlink()
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[:100])
    with pytest.raises(DatasetError, match=r"images.bin: truncated COLMAP binary file"):
        load_dataset(root / "colmap")


def test_unknown_layout_and_bad_arguments(tmp_path):
    with pytest.raises(DatasetError, match=r"unknown dataset layout"):
        load_dataset(tmp_path)
    with pytest.raises(DatasetError, match=r"nope: dataset folder not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="downscale must be a positive number"):
        load_dataset(tmp_path, downscale=0)
    with pytest.raises(DatasetError, match="background must be 1 or 3 numbers"):
        load_dataset(tmp_path, background=(1, 1))
    (tmp_path / "transforms.json").write_text("{ not json")
    with pytest.raises(DatasetError, match=r"transforms.json: cannot parse transforms file"):
        load_dataset(tmp_path)
    assert issubclass(DatasetError, ValueError)


def test_missing_transforms_frames_warn_and_skip(scene):
    root, _, names = scene
    for n in ("img02.png", "img07.png"):
        (root / "ngp" / "images" / n).unlink()
    with pytest.warns(DatasetWarning, match=r"skipping 2 frame\(s\).*images/img02.png, images/img07.png"):
        ds = load_dataset(root / "ngp")
    assert len(ds.views) == 8 and "images/img02.png" not in [v.name for v in ds.views]
    shutil.rmtree(root / "ngp" / "images")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DatasetWarning)
        with pytest.raises(DatasetError, match=r"none of the frames in transforms.json has an image file"):
            load_dataset(root / "ngp")


def test_format_detection_prefers_a_complete_colmap_model(scene):
    root, cams, _ = scene
    # LLFF scenes ship cameras.bin + points3D.bin without images.bin: that is no COLMAP model
    assert detect_format(root / "colmap") == "colmap"
    (root / "colmap" / "sparse" / "0" / "images.txt").unlink()
    _write_llff(root / "colmap", cams, 20.0)
    assert detect_format(root / "colmap") == "llff"
    with pytest.raises(DatasetError, match=r"sparse/0: incomplete COLMAP model, images.bin / images.txt is"):
        load_dataset(root / "colmap", format="colmap")
    # transforms.json beside a model in a non-standard sub-folder (colmap2nerf's colmap_sparse/0)
    shutil.copytree(root / "colmap" / "sparse", root / "ngp" / "colmap_sparse")
    _write_colmap_text(root / "ngp" / "colmap_sparse" / "0", cams, ["x.png"])
    assert detect_format(root / "ngp") == "transforms"
    (root / "ngp" / "transforms.json").unlink()
    assert detect_format(root / "ngp") == "colmap"  # like lund_door/colmap_ground_truth


def test_colmap_parser_reads_what_pycolmap_writes(scene):
    pycolmap = pytest.importorskip("pycolmap")
    root, _, _ = scene
    model = root / "colmap" / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    out = root / "bin"
    out.mkdir()
    rec.write_binary(str(out))
    for folder in (model, out):
        ext = "txt" if folder == model else "bin"
        cams = read_cameras(folder / f"cameras.{ext}")
        imgs = read_images(folder / f"images.{ext}")
        xyz, rgb = read_points(folder / f"points3D.{ext}")
        assert set(imgs) == set(rec.images) and len(xyz) == rec.num_points3D()
        for image_id, image in rec.images.items():
            pose = image.cam_from_world()
            x, y, z, w = pose.rotation.quat
            assert imgs[image_id].name == image.name
            q = imgs[image_id].qvec
            np.testing.assert_allclose(q * np.sign(q[0] * w), [w, x, y, z], atol=1e-9)
            np.testing.assert_allclose(imgs[image_id].tvec, pose.translation, atol=1e-9)
        np.testing.assert_allclose(cams[1].params, rec.cameras[1].params)
