"""Sample-point renders: at pixel centres they are the image render; gradients agree too.

Faint scenes (the default random scene): alpha >= 1/255 stays inside every surfel's 3-sigma box,
so tile granularity, which differs between the two (tiles meeting the box's pixel centres, or
the box itself), cuts nothing and the two agree to rounding. Opaque tails past the box are cut
per tile; there sample renders are compared with the float64 reference instead."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raster_scenes import camera, psnr, random_scene

import ghsplat_jax as gs
from ghsplat_jax.raster.reference import render_reference
from ghsplat_jax.raster.samples import pixel_samples, stack

CFG = gs.RasterConfig(tile_size=8, median=True, distortion=True)


def _pixel_points(rng, width, height, n):
    """n distinct pixel centres, clustered so that some tiles hold many and most none."""
    flat = rng.choice(width * height // 3, n, replace=False) * 3 % (width * height)
    return np.stack([flat % width + 0.5, flat // width + 0.5], axis=1), flat


def test_samples_at_pixel_centres_equal_the_image():
    s, cam = random_scene(300, seed=3), camera(48, 32)
    xy, flat = _pixel_points(np.random.default_rng(0), 48, 32, 150)
    image = gs.render(s, cam, CFG)
    points = gs.render(s, cam, CFG, samples=pixel_samples(xy, 48, 32, 8))
    for name in ("rgb", "alpha", "depth", "median_depth", "normal", "distortion"):
        want = np.asarray(getattr(image, name)).reshape((48 * 32,) + getattr(image, name).shape[2:])[flat]
        np.testing.assert_allclose(np.asarray(getattr(points, name)), want, atol=2e-6, err_msg=name)
    # tiles without samples get no pairs
    assert int(points.stats.num_kept) < int(image.stats.num_kept)


def test_sample_gradients_equal_the_image_gradients():
    s, cam = random_scene(120, seed=5), camera(32, 24)
    xy, flat = _pixel_points(np.random.default_rng(1), 32, 24, 60)
    samples = pixel_samples(xy, 32, 24, 8)
    w = jnp.asarray(np.random.default_rng(2).normal(size=(60, 3)), jnp.float32)
    cfg = gs.RasterConfig(tile_size=8, pair_capacity=1 << 13, median=False)

    def on_image(s):
        out = gs.raster.rasterize(s, cam, cfg, cfg.pair_capacity)
        return jnp.sum(out.rgb.reshape(-1, 3)[flat] * w) + jnp.sum(out.depth.reshape(-1)[flat])

    def on_samples(s):
        out = gs.raster.rasterize(s, cam, cfg, cfg.pair_capacity, samples=samples)
        return jnp.sum(out.rgb * w) + jnp.sum(out.depth)

    g_image, g_samples = jax.grad(on_image)(s), jax.grad(on_samples)(s)
    for a, b in zip(jax.tree_util.tree_leaves(g_image), jax.tree_util.tree_leaves(g_samples)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-5)


@pytest.mark.slow  # two more compiled renders; the pixel-centre tests above cover the layout
def test_off_centre_samples_match_a_shifted_image():
    """A sample at (x + 0.3, y + 0.7) is the pixel centre of a camera shifted by that much."""
    s, cam = random_scene(200, seed=4), camera(40, 24)
    xy, flat = _pixel_points(np.random.default_rng(3), 40, 24, 80)
    inside = (xy[:, 0] < 39) & (xy[:, 1] < 23)   # the shifted points stay in the image
    xy, flat = xy[inside], flat[inside]
    K = np.asarray(cam.K).copy()
    K[0, 2] -= 0.3
    K[1, 2] -= 0.7
    shifted = gs.render(s, gs.Camera(K=K, world_to_cam=cam.world_to_cam, width=40, height=24), CFG)
    points = gs.render(s, cam, CFG, samples=pixel_samples(xy + [0.3, 0.7], 40, 24, 8))
    np.testing.assert_allclose(np.asarray(points.depth), np.asarray(shifted.depth).reshape(-1)[flat], atol=1e-4)
    np.testing.assert_allclose(np.asarray(points.rgb), np.asarray(shifted.rgb).reshape(-1, 3)[flat], atol=1e-5)


@pytest.mark.slow  # the reference comparisons themselves run in test_raster_reference.py
def test_opaque_samples_close_to_reference():
    s, cam = random_scene(400, seed=3, opacity=(0.6, 0.99), scale=(0.05, 0.3)), camera(64, 48)
    xy, flat = _pixel_points(np.random.default_rng(4), 64, 48, 300)
    out = gs.render(s, cam, CFG, samples=pixel_samples(xy, 64, 48, 8))
    ref = render_reference(s, cam, CFG)
    assert psnr(out.rgb, ref["rgb"].reshape(-1, 3)[flat]) >= 60
    assert np.mean(np.abs(np.asarray(out.alpha) - ref["alpha"].reshape(-1)[flat])) < 1e-4


def test_layouts_group_points_and_reject_bad_ones():
    xy = np.array([[0.5, 0.5], [7.9, 7.9], [8.0, 0.5], [15.0, 16.0], [16.0, 16.0]])
    lay = pixel_samples(xy, 16, 16, 8)
    assert lay.slots == 8 and lay.offsets.shape == (4, 8, 2)
    np.testing.assert_array_equal(lay.index // lay.slots, [0, 0, 1, 3, 3])     # edges go to the last tile
    got = lay.offsets.reshape(-1, 2)[lay.index] + np.array([[0, 0], [0, 0], [8, 0], [8, 8], [8, 8]])
    np.testing.assert_allclose(got, xy)
    assert lay.boxes[2, 0] > lay.boxes[2, 2]                                        # empty tile
    assert stack([lay, pixel_samples(xy[:2], 16, 16, 8)]).index.shape == (2, 5)
    with pytest.raises(ValueError, match="inside"):
        pixel_samples([[16.5, 1.0]], 16, 16, 8)
    with pytest.raises(ValueError, match="slots"):
        pixel_samples(xy, 16, 16, 8, slots=1)
    with pytest.raises(ValueError, match="tile size"):
        gs.render(random_scene(5), camera(16, 16), gs.RasterConfig(tile_size=16), samples=lay)
    with pytest.raises(ValueError, match="same image size"):
        stack([lay, pixel_samples(xy, 16, 16, 16)])
    with pytest.raises(ValueError, match="carried"):
        gs.render(random_scene(5), camera(16, 16), gs.RasterConfig(compositor="logspace"), samples=lay)
