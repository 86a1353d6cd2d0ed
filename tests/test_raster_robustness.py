"""Bad geometry, bad input, capacity handling and tracing behaviour of the rasterizer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raster_scenes import camera, random_scene

import ghsplat_jax as gs
from ghsplat_jax.raster import rasterize


def _finite(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree)
               if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating))


def _loss(s, cam, cfg=gs.RasterConfig(), capacity=8192):
    out = rasterize(s, cam, cfg, capacity)
    return (jnp.sum(out.rgb) + jnp.sum(out.depth) + jnp.sum(out.median_depth) + jnp.sum(out.normal)
            + jnp.sum(out.distortion) + jnp.sum(out.alpha))


def bad_scene():
    """One surfel of every awkward kind, plus a few ordinary ones."""
    cam = camera(48, 32, eye=(0, -3, 0))
    means = [[0, 0, 0], [0.3, 0, 0.1], [-0.3, 0, -0.1],   # ordinary
             [0, 0, 0.2],                                # edge-on to the camera
             [0, -5, 0],                                 # behind the camera
             [0, -2.7, 0],                               # centre 0.3 m ahead, plane reaching behind the camera
             [0.2, 0, 0], [0.1, 0, 0],                   # zero (tiny) and huge scales
             [0, 2, 0],                                  # covers the whole screen
             [0.1, 0.1, 0], [0.2, 0.1, 0],               # unnormalised and zero quaternion
             [np.nan, 0, 0], [0, 0, np.inf]]             # non-finite
    n = len(means)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    quats[0] = [0.7071, 0.7071, 0, 0]   # plane facing -y: toward the camera
    quats[3] = [1, 0, 0, 0]             # plane z-normal: seen edge-on from -y
    quats[9] = [5.0, 3.0, -2.0, 1.0]
    quats[10] = [0, 0, 0, 0]
    ls = np.full((n, 2), np.log(0.1))
    ls[5] = np.log(0.5)
    ls[6] = -80.0
    ls[7] = 60.0
    ls[8] = np.log(50.0)
    s = gs.make_surfels(np.array(means, np.float64), quats, ls, np.full(n, 2.0),
                        np.random.default_rng(0).normal(size=(n, 3)))
    return s, cam


# `make test` runs the default compositor; the log-space ones (a compile each) run in `make test-all`.
@pytest.mark.parametrize("compositor, backward", [("carried", "custom_vjp"),
                                                  pytest.param("logspace", "custom_vjp", marks=pytest.mark.slow),
                                                  pytest.param("logspace", "autodiff", marks=pytest.mark.slow)])
def test_bad_geometry_never_produces_nan(compositor, backward):
    s, cam = bad_scene()
    cfg = gs.RasterConfig(compositor=compositor, backward=backward)
    out = gs.render(s, cam, cfg)
    assert _finite(out)
    assert int(out.stats.num_invalid) == 3  # NaN, Inf and the zero quaternion
    assert int(out.stats.num_culled_near) == 1
    grads = jax.jit(jax.grad(_loss), static_argnums=(2,))(s, cam, cfg)
    assert _finite(grads)
    # Invalid surfels get zero gradients; valid visible ones get some.
    assert float(jnp.abs(grads.means[11:]).sum()) == 0.0
    assert float(jnp.abs(grads.sh_dc[0]).sum()) > 0


def test_empty_scene_renders_background():
    s = random_scene(0)
    cfg = gs.RasterConfig(background=(0.1, 0.2, 0.3))
    out = gs.render(s, camera(), cfg)
    np.testing.assert_allclose(np.asarray(out.rgb[5, 7]), [0.1, 0.2, 0.3])
    assert float(out.alpha.max()) == 0.0


def test_all_surfels_culled_renders_background():
    s = random_scene(50)
    s = gs.Surfels(s.means + np.array([0, -10.0, 0]), *[getattr(s, f) for f in
                   ("quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")])
    out = gs.render(s, camera())
    assert float(out.alpha.max()) == 0.0 and int(out.stats.num_visible) == 0


def test_overflow_under_jit_is_reported_or_raised():
    s, cam = random_scene(300), camera()
    small = gs.RasterConfig(pair_capacity=64, on_overflow="report")
    out = jax.jit(lambda s: gs.render(s, cam, small))(s)
    assert int(out.stats.overflow) == int(out.stats.num_pairs) - 64 > 0
    strict = gs.RasterConfig(pair_capacity=64)
    with pytest.raises(Exception, match="pair capacity is 64"):
        jax.block_until_ready(jax.jit(lambda s: gs.render(s, cam, strict).rgb)(s))


def test_eager_render_grows_capacity_and_recompiles_only_per_bucket():
    from ghsplat_jax.raster.render import rasterize_jit

    cam = camera(128, 96)
    first = gs.render(random_scene(200, seed=0), cam)
    compiled = rasterize_jit._cache_size()
    for seed in (1, 2, 3):  # same shapes, new values, same bucket: no new compilation
        out = gs.render(random_scene(200, seed=seed), cam)
        assert int(out.stats.capacity) == int(first.stats.capacity)
    assert rasterize_jit._cache_size() == compiled
    # Larger surfels need more pairs: the exact count picks a bigger bucket, compiled once.
    big = random_scene(200, scale=(0.5, 0.9))
    out = gs.render(big, cam)
    assert int(out.stats.overflow) == 0 and int(out.stats.capacity) > int(first.stats.capacity)
    assert int(out.stats.num_pairs) > int(first.stats.capacity)
    assert rasterize_jit._cache_size() == compiled + 1


@pytest.mark.slow  # five views at several capacities: the file's longest test (the one above checks buckets)
def test_one_capacity_for_many_views_renders_them_all_with_one_compile():
    from ghsplat_jax.raster.render import capacity_for_views, rasterize_jit

    s = random_scene(200, scale=(0.1, 0.9), seed=4)
    cams = [camera(96, 72, eye=(x, -3.5 + abs(x), 1.0)) for x in (-1.5, -0.5, 0.0, 0.7, 1.6)]
    alone = [gs.render(s, c) for c in cams]
    assert len({int(o.stats.capacity) for o in alone}) > 1  # sized view by view: several buckets
    capacity = capacity_for_views(s, cams)
    assert capacity >= max(int(o.stats.num_pairs) for o in alone)
    cfg = gs.RasterConfig(pair_capacity=capacity)
    compiled = rasterize_jit._cache_size()
    for c, o in zip(cams, alone):
        out = gs.render(s, c, cfg)
        assert int(out.stats.overflow) == 0 and int(out.stats.capacity) == capacity
        np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(o.rgb), atol=1e-6)
    assert rasterize_jit._cache_size() == compiled + 1
    assert capacity_for_views(s, []) is None


def test_jit_and_vmap_over_cameras():
    s = random_scene(100)
    cams = [camera(eye=(x, -3.5, 1.0)) for x in (-0.5, 0.0, 0.5)]
    stacked = gs.Camera(jnp.stack([c.K for c in cams]), jnp.stack([c.world_to_cam for c in cams]),
                        cams[0].width, cams[0].height)
    cfg = gs.RasterConfig(pair_capacity=4096)
    batched = jax.jit(jax.vmap(lambda c: gs.render(s, c, cfg).rgb))(stacked)
    for i, c in enumerate(cams):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(gs.render(s, c).rgb), atol=1e-5)


def test_sh_degree_restriction_and_config_errors():
    s, cam = random_scene(100, degree=3), camera()
    base = gs.render(s, cam, gs.RasterConfig(sh_degree=0)).rgb
    dc_only = gs.render(gs.Surfels(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh_dc,
                                   np.zeros((100, 0, 3), np.float32)), cam).rgb
    np.testing.assert_allclose(np.asarray(base), np.asarray(dc_only), atol=1e-6)
    with pytest.raises(ValueError, match="tile_size"):
        gs.RasterConfig(tile_size=12)
    with pytest.raises(ValueError, match="backward"):
        gs.RasterConfig(backward="magic")
