"""Opacity-aware bounds and the exact ellipse-tile test drop only pairs that contribute nothing.

Checked two ways: renders with tight bounds equal renders with the 2DGS 3-sigma boxes, and every
candidate pair the test drops has float64 alpha below 1/255 at every pixel of its tile (each
surfel rendered alone by the reference renderer)."""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from raster_scenes import camera, random_scene

import ghsplat_jax as gs
from ghsplat_jax.raster import binning
from ghsplat_jax.raster.project import project
from ghsplat_jax.raster.reference import render_reference

OUTPUTS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")


def mixed_scene(n=150, seed=0):
    """Faint to opaque, thin to round, some nearly edge-on: every branch of the bounds."""
    s = random_scene(n, seed=seed, opacity=(0.002, 0.99), scale=(0.01, 0.25), degree=1)
    r = np.random.default_rng(seed)
    log_scales = np.asarray(s.log_scales).copy()
    thin = r.uniform(size=n) < 0.3
    log_scales[thin, 1] -= 3.0
    return gs.Surfels(s.means, s.quats, jnp.asarray(log_scales), s.opacity_logits, s.sh_dc, s.sh_rest)


# Two compiled renders a case: `make test` runs the smallest and the largest tile, `make test-all` all four.
@pytest.mark.parametrize("tile, lowpass", [(8, True), pytest.param(16, True, marks=pytest.mark.slow), (32, False),
                                           pytest.param(8, False, marks=pytest.mark.slow)])
def test_tight_bounds_render_the_same_image_with_fewer_pairs(tile, lowpass):
    s, cam = mixed_scene(seed=tile), camera(80, 56)
    tight = gs.render(s, cam, gs.RasterConfig(tile_size=tile, lowpass_filter=lowpass))
    box3 = gs.render(s, cam, gs.RasterConfig(tile_size=tile, lowpass_filter=lowpass, bounds="box3"))
    for key in OUTPUTS:
        np.testing.assert_allclose(np.asarray(getattr(tight, key)), np.asarray(getattr(box3, key)), atol=2e-5,
                                   err_msg=key)
    assert int(tight.stats.num_kept) < int(box3.stats.num_kept)
    assert int(tight.stats.num_pairs) <= int(box3.stats.num_pairs)


def _kept_pairs(p, grid, cam, tight: bool) -> set[tuple[int, int]]:
    capacity = 1 << 16
    layout = binning.bin_pairs(p, cam.width, cam.height, grid, capacity, 16, capacity // 16 + grid.num_tiles, tight)
    surfel, start = np.asarray(layout.pair_surfel), np.asarray(layout.chunk_start)
    count, tile = np.asarray(layout.chunk_count), np.asarray(layout.chunk_tile)
    return {(int(surfel[start[w] + k]), int(tile[w])) for w in np.nonzero(count)[0] for k in range(count[w])}


@pytest.mark.parametrize("lowpass", [True, False])
def test_every_dropped_pair_has_no_pixel_above_the_alpha_threshold(lowpass):
    s, cam = mixed_scene(seed=3), camera(64, 48)
    cfg = gs.RasterConfig(tile_size=8, lowpass_filter=lowpass)
    grid = binning.TileGrid.for_image(cam.width, cam.height, 8)
    p = project(s, cam, cfg.near, 1, lowpass)
    dropped = _kept_pairs(p, grid, cam, tight=False) - _kept_pairs(p, grid, cam, tight=True)
    assert len(dropped) > 50  # the scene exercises the test
    leaves = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
    alpha = {}
    for i in sorted({i for i, _ in dropped}):
        one = gs.Surfels(*(np.asarray(getattr(s, f))[i:i + 1] for f in leaves))
        alpha[i] = render_reference(one, cam, cfg)["alpha"]
    for i, t in dropped:
        ty, tx = divmod(t, grid.tiles_x)
        block = alpha[i][ty * 8:(ty + 1) * 8, tx * 8:(tx + 1) * 8]
        assert block.max() < 1 / 255, (i, t, block.max())


def test_packed_tile_sort_matches_the_two_key_sort(monkeypatch):
    """The single-uint32 (tile, depth rank) sort lays out the same pairs as the stable two-operand
    sort used where the packed keys would not fit."""
    s, cam = mixed_scene(seed=3), camera(80, 56)
    p = project(s, cam, 0.01, 1, True)
    grid = binning.TileGrid.for_image(cam.width, cam.height, 8)
    layout = lambda: binning.bin_pairs(p, cam.width, cam.height, grid, 4096, 16, 512)
    packed = layout()
    monkeypatch.setattr(binning, "PACKED_KEYS_MAX", 0)
    two_key = layout()
    assert int(packed.num_kept) > 100
    for field in ("pair_surfel", "chunk_tile", "chunk_start", "chunk_count", "chunk_first", "tile_count"):
        np.testing.assert_array_equal(np.asarray(getattr(packed, field)), np.asarray(getattr(two_key, field)),
                                      err_msg=field)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float32, st.sampled_from([0, 1, 2, 37, 300]), elements=st.one_of(
    st.floats(-1e3, 1e3, width=32), st.sampled_from([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-40, 2.5]))))
@pytest.mark.parametrize("host", [True, False])
def test_radix_depth_order_is_the_stable_argsort(host, depths):
    """The depth order the pairs are generated in equals the stable argsort it replaces: ties,
    signed zeros, infinities, NaNs and denormals (which XLA:CPU compares as zero) included."""
    x = jnp.asarray(depths)
    np.testing.assert_array_equal(np.asarray(binning.stable_argsort(x, host)), np.asarray(jnp.argsort(x, stable=True)))


@pytest.mark.parametrize("host", [True, False])
def test_radix_depth_order_with_three_passes(host):
    """Above 65,536 surfels each pass sorts a 15-bit digit: three passes, still the stable order."""
    x = jnp.asarray(np.random.default_rng(0).integers(0, 500, 70001).astype(np.float32) / 7)  # many ties
    np.testing.assert_array_equal(np.asarray(binning.stable_argsort(x, host)), np.asarray(jnp.argsort(x, stable=True)))


@pytest.mark.parametrize("host", [True, False])
def test_depth_order_is_a_stable_argsort_on_the_host_and_on_the_device(host):
    """NumPy's sort through a host callback and XLA's radix passes both give jnp.argsort's
    stable order: ties by index, -0 as 0, NaN last; also under vmap."""
    import functools

    import jax

    r = np.random.default_rng(1)
    x = np.round(r.normal(size=3001), 1).astype(np.float32)  # many ties
    x[[5, 9]], x[7], x[11] = np.nan, -0.0, 0.0
    x = jnp.asarray(x)
    argsort = functools.partial(binning.stable_argsort, host=host)
    np.testing.assert_array_equal(jax.jit(argsort)(x), jnp.argsort(x, stable=True))
    both = jnp.stack([x, x[::-1]])
    np.testing.assert_array_equal(jax.vmap(argsort)(both), jnp.argsort(both, axis=1, stable=True))
    keys = jnp.asarray(r.integers(0, 2**32, 4097, dtype=np.uint32))
    np.testing.assert_array_equal(jax.jit(functools.partial(binning.sort_unsigned, host=host))(keys),
                                  np.sort(np.asarray(keys)))


def test_host_and_device_sorts_bin_the_same_pairs(monkeypatch):
    s, cam = mixed_scene(seed=3), camera(80, 56)
    p = project(s, cam, 0.2, 1, True)
    grid = binning.TileGrid.for_image(80, 56, 8)
    binning_with = lambda sort: binning.bin_pairs(p, 80, 56, grid, 4096, 16, 512, sort=sort)
    monkeypatch.setattr(binning, "HOST_SORT_MIN_KEYS", 1)  # this small scene sorts on the host too
    layouts = [binning_with("auto"), binning_with("xla")]
    for field in ("pair_surfel", "chunk_tile", "chunk_start", "chunk_count", "tile_count", "num_kept"):
        np.testing.assert_array_equal(getattr(layouts[0], field), getattr(layouts[1], field), err_msg=field)
    assert int(layouts[0].num_kept) > 0
    import jax

    assert binning.host_sorts("auto", 1 << 16) == (jax.default_backend() == "cpu")
    assert not binning.host_sorts("xla", 1 << 16)
    monkeypatch.undo()
    assert not binning.host_sorts("auto", 4096)  # small sorts stay in XLA (and its compilation cache)
    with pytest.raises(ValueError, match="sort"):
        gs.RasterConfig(sort="numpy")


def test_eager_renders_along_a_moving_camera_compile_a_few_times():
    """A camera walking towards a scene needs more tile-surfel pairs every frame; eager renders
    reuse the compiled buffer while it fits and grow it with headroom, so 8 poses compile a
    handful of programs, not one per capacity bucket crossed."""
    from ghsplat_jax.raster.render import _EAGER_CAPACITY, capacity_bucket, rasterize_jit, render

    scene = random_scene(1500, seed=3)
    cfg = gs.RasterConfig(tile_size=8)
    _EAGER_CAPACITY.clear()
    before = rasterize_jit._cache_size()
    needs, used = [], []
    for k in range(8):
        cam = camera(96, 72, eye=(0.0, -4.5 + 0.3 * k, 1.0))
        out = render(scene, cam, cfg)
        needs.append(int(out.stats.num_pairs))
        used.append(max(_EAGER_CAPACITY.values()))
    compiles = rasterize_jit._cache_size() - before
    per_frame = len({capacity_bucket(n) for n in needs})  # what sizing each frame alone compiled
    assert needs[-1] > 1.9 * needs[0] and per_frame >= 5  # 4.9k to 9.7k pairs
    assert all(u >= n for u, n in zip(used, needs)) and compiles <= 3, (needs, used, compiles)
