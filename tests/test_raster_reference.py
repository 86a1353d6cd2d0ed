"""The tiled rasterizer against the dense float64 reference, and its gradients against
central finite differences of that reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raster_scenes import camera, psnr, random_scene

import ghsplat_jax as gs
from ghsplat_jax.raster import rasterize
from ghsplat_jax.raster.reference import render_reference

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
# Each case compiles its own programs (10-100 s on 2 busy cores): `make test` keeps one case of
# each test, the default carried compositor (and the log-space one against the reference), and
# `make test-all` runs the other settings.
slow = pytest.mark.slow


@pytest.mark.parametrize("cfg", [
    gs.RasterConfig(),
    pytest.param(gs.RasterConfig(tile_size=8, chunk_size=8, background=(0.2, 0.5, 1.0)), marks=slow),
    pytest.param(gs.RasterConfig(tile_size=32, lowpass_filter=False, batch_chunks=4), marks=slow),
    pytest.param(gs.RasterConfig(tile_size=8, batch_chunks=3), marks=slow),
    gs.RasterConfig(compositor="logspace"),
    pytest.param(gs.RasterConfig(compositor="logspace", tile_size=32, lowpass_filter=False, batch_chunks=4),
                 marks=slow),
    pytest.param(gs.RasterConfig(backend="dense"), marks=slow),
], ids=["default", "tile8-bg", "tile32-nofilter", "tile8-odd-batch", "logspace", "logspace-tile32-nofilter",
        "dense-baseline"])
def test_low_opacity_matches_reference(cfg):
    s, cam = random_scene(300, degree=3), camera()
    out = gs.render(s, cam, cfg)
    ref = render_reference(s, cam, cfg)
    assert psnr(out.rgb, ref["rgb"]) >= 50
    assert np.abs(np.asarray(out.alpha) - ref["alpha"]).max() <= 1e-4
    for key in ("depth", "median_depth", "normal", "distortion"):
        np.testing.assert_allclose(np.asarray(getattr(out, key)), ref[key], atol=1e-3, err_msg=key)


@pytest.mark.parametrize("compositor", ["carried", pytest.param("logspace", marks=slow)])
def test_opaque_scene_close_to_reference(compositor):
    s, cam = random_scene(400, seed=3, opacity=(0.6, 0.99), scale=(0.05, 0.3)), camera(64, 48)
    # 16-px tiles as in 2DGS: tiles cut the tails of opaque surfels past their 3-sigma ellipse
    # (alpha >= 1/255 reaches rho = 2 ln(255 o) > 9 there), and smaller tiles cut more of them.
    cfg = gs.RasterConfig(compositor=compositor, tile_size=16)
    out, ref = gs.render(s, cam, cfg), render_reference(s, cam, cfg)
    assert psnr(out.rgb, ref["rgb"]) >= 60
    assert np.mean(np.abs(np.asarray(out.alpha) - ref["alpha"])) < 1e-4
    # The median surfel is a discontinuous choice: a tiny change in T may flip it at a few pixels.
    ok = ref["alpha"] > 0.5
    same = np.abs(np.asarray(out.median_depth) - ref["median_depth"])[ok] < 1e-3
    assert same.mean() >= 0.99


def test_single_tile_with_thousands_of_surfels_is_exact():
    """2,500 surfels overlap one 16x16 tile: nothing is dropped, the image is exact."""
    r = np.random.default_rng(7)
    n = 2500
    op = np.full(n, 0.02)
    s = gs.make_surfels(r.uniform([-0.3, -0.3, -0.3], [0.3, 0.3, 0.3], (n, 3)), r.normal(size=(n, 4)),
                        np.log(np.full((n, 2), 0.5)), np.log(op / (1 - op)), r.normal(0, 0.5, (n, 3)))
    cam = camera(16, 16, eye=(0, -4, 0))
    cfg = gs.RasterConfig(tile_size=16)
    out = gs.render(s, cam, cfg)
    assert int(out.stats.max_tile_pairs) == n and int(out.stats.overflow) == 0
    ref = render_reference(s, cam, cfg)
    assert psnr(out.rgb, ref["rgb"]) >= 50
    assert np.abs(np.asarray(out.alpha) - ref["alpha"]).max() <= 1e-4


VARIANTS = [("carried", "custom_vjp"), ("logspace", "custom_vjp"), ("logspace", "autodiff")]


@pytest.mark.parametrize("compositor, backward", [pytest.param(*v, marks=() if i == 0 else slow)
                                                  for i, v in enumerate(VARIANTS)], ids=["-".join(v) for v in VARIANTS])
def test_gradients_match_finite_differences(compositor, backward):
    s, cam = random_scene(40, seed=1, opacity=(0.3, 0.9), degree=2), camera(32, 24)
    r = np.random.default_rng(5)
    h, w = cam.height, cam.width
    weights = {"rgb": r.normal(size=(h, w, 3)), "alpha": r.normal(size=(h, w)), "depth": r.normal(size=(h, w)),
               "median_depth": r.normal(size=(h, w)), "normal": r.normal(size=(h, w, 3)),
               "distortion": 100 * r.normal(size=(h, w))}
    # 16-px tiles: the reference has no tiles, and 8-px tiles cut more of the opaque surfels'
    # tails past 3 sigma (bounds="tight" and "box3" give identical gradients either way).
    cfg = gs.RasterConfig(compositor=compositor, backward=backward, batch_chunks=4, tile_size=16)

    def loss(s):
        out = rasterize(s, cam, cfg, 4096)
        return sum(jnp.sum(getattr(out, k) * v) for k, v in weights.items())

    def loss_ref(s):
        out = render_reference(s, cam, cfg)
        return sum(np.sum(out[k] * v) for k, v in weights.items())

    grads = jax.jit(jax.grad(loss))(s)
    s64 = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), s)
    eps = 1e-5
    for field in FIELDS:
        g = np.asarray(getattr(grads, field)).ravel()
        assert np.all(np.isfinite(g))
        for i in np.argsort(-np.abs(g))[:3]:  # the entries that matter most
            def shifted(d):
                a = getattr(s64, field).copy().ravel()
                a[i] += d
                return loss_ref(gs.Surfels(**{**{f: getattr(s64, f) for f in FIELDS},
                                              field: a.reshape(getattr(s64, field).shape)}))
            fd = (shifted(eps) - shifted(-eps)) / (2 * eps)
            assert abs(g[i] - fd) <= 3e-2 * max(abs(fd), 1e-3), (field, i, g[i], fd)


@pytest.mark.parametrize("distortion", [pytest.param(False, marks=slow), True])
def test_skipped_outputs_change_nothing_else(distortion):
    """depth_normal=False (what training renders until its normal term starts) leaves depth and
    normal at zero and everything else bit for bit: the image, the distortion and the gradients
    of a loss that reads them."""
    s, cam = random_scene(300, degree=1), camera()

    def loss(s, depth_normal):
        cfg = gs.RasterConfig(depth_normal=depth_normal, distortion=distortion, median=False)
        out = rasterize(s, cam, cfg, 1 << 14)
        return jnp.sum(out.rgb * jnp.arange(1.0, 4.0)) + jnp.sum(out.alpha) + jnp.sum(out.distortion), out

    grad = jax.jit(jax.value_and_grad(loss, has_aux=True), static_argnums=1)
    (_, full), g_full = grad(s, True)
    (_, lean), g_lean = grad(s, False)
    assert np.abs(np.asarray(full.depth)).max() > 0
    for key in ("rgb", "alpha", "distortion"):
        assert_same_math(getattr(lean, key), getattr(full, key), key)
    assert not np.any(np.asarray(lean.depth)) and not np.any(np.asarray(lean.normal))
    for field in FIELDS:
        assert_same_math(getattr(g_lean, field), getattr(g_full, field), field)


def assert_same_math(a, b, what):
    """Two compiled programs doing the same arithmetic: bit for bit on a CPU, where XLA fuses both
    alike; within float32 rounding elsewhere (on an H100 the two programs' images differed by up to
    6e-8, one ulp, as their fusions and the GPU's scatter-add order differ)."""
    a, b = np.asarray(a), np.asarray(b)
    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(a, b, err_msg=what)
    else:
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(b).max(), err_msg=what)


@pytest.mark.parametrize("median", [True, pytest.param(False, marks=slow)])  # True checks the median's too
def test_backward_skips_exactly(monkeypatch, median):
    """The carried backward walks only the pairs that can change an output (alpha > 0 at a pixel
    still open before them), cut again into chunks ("pairs"), or the chunks holding alpha > 0 at a
    pixel open at their start ("chunks"). On an opaque scene that is fewer chunks, pairs fewest,
    and the gradients equal those of walking every chunk ("none") and those of the log-space
    compositor differentiated by autodiff (which walks every pair); with the median too, whose
    gradient finds its pair by layout index."""
    from ghsplat_jax.raster import carried

    s, cam = random_scene(600, seed=4, opacity=(0.3, 0.99), scale=(0.2, 0.5), degree=1), camera(32, 24)
    weights = np.random.default_rng(2).normal(size=(cam.height, cam.width, 3))
    walked = []  # (chunks walked, chunks in use) per traced backward
    live_pairs = carried.live_pairs

    def recorded(live, surfel, valid, tile, num_tiles):
        out = live_pairs(live, surfel, valid, tile, num_tiles)
        jax.debug.callback(lambda *n: walked.append(tuple(int(x) for x in n)), out[-1], jnp.sum(valid[:, 0]))
        return out

    monkeypatch.setattr(carried, "live_pairs", recorded)

    def grad(**kw):
        cfg = gs.RasterConfig(tile_size=8, chunk_size=8, batch_chunks=4, median=median, **kw)

        def loss(s):
            out = rasterize(s, cam, cfg, 1 << 14)
            return (jnp.sum(out.rgb * weights) + jnp.sum(out.depth) + jnp.sum(out.median_depth)
                    + jnp.sum(out.distortion))
        return jax.jit(jax.grad(loss))(s)

    grads, walks = {}, {}
    for skip in ("none", "chunks", "pairs"):
        walked.clear()
        grads[skip] = grad(backward_skip=skip)
        walks[skip] = walked[0]
    (all_chunks, used), (chunk_skip, _), (pair_skip, _) = walks["none"], walks["chunks"], walks["pairs"]
    assert all_chunks == used and pair_skip < chunk_skip <= 0.8 * used  # enough closed to exercise both
    autodiff = grad(compositor="logspace", backward="autodiff")
    for skip in ("chunks", "pairs"):
        for field in FIELDS:
            a, b, c = (np.asarray(getattr(g, field)) for g in (grads[skip], grads["none"], autodiff))
            assert np.abs(b).max() > 0, field
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(b).max(), err_msg=f"{skip} {field}")
            np.testing.assert_allclose(a, c, rtol=1e-2, atol=1e-3 * np.abs(c).max(), err_msg=f"{skip} {field}")
