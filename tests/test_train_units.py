"""Training building blocks without the rasterizer: losses, schedules, config, densification
invariants, opacity reset, pool growth, checkpoints and trace counting."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ghsplat_jax.core.quaternions import to_rotation_matrix
from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.train import checkpoint, densify, losses, optim
from ghsplat_jax.train.config import ConfigError, TrainConfig, apply_overrides, load_config, save_config
from ghsplat_jax.train.state import INACTIVE_LOGIT, grow, knn_log_scales, new_state, pad_params


# --- losses -----------------------------------------------------------------------------------
def _ssim_reference(a, b, size=11, sigma=1.5):
    """float64 SSIM with a zero-padded Gaussian window, written straight from the definition."""
    x = np.arange(size) - size // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    w = np.outer(g, g) / np.sum(g) ** 2
    h, wd, c = a.shape
    r = size // 2

    def blur(img):
        p = np.pad(img, ((r, r), (r, r), (0, 0)))
        out = np.zeros_like(img)
        for i in range(size):
            for j in range(size):
                out += w[i, j] * p[i:i + h, j:j + wd]
        return out

    a, b = a.astype(np.float64), b.astype(np.float64)
    mu_a, mu_b = blur(a), blur(b)
    va, vb, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return np.mean((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2)))


@pytest.mark.parametrize("shape", [(20, 27, 3), (70, 45, 2)])  # one blur block; several, cut mid-block
def test_ssim_identical_is_one_and_matches_float64_reference(shape):
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, shape).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.25, a.shape), 0, 1).astype(np.float32)
    assert float(losses.ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    ref = _ssim_reference(a, b)
    assert 0.3 < ref < 0.95
    assert float(losses.ssim(a, b)) == pytest.approx(ref, abs=2e-4)


def test_ssim_gradients_match_autodiff_of_a_plain_convolution():
    """The blur's hand-written (self-adjoint) gradient, for either image, against autodiff of
    the same SSIM built on jax.scipy's 2D convolution."""
    from jax.scipy.signal import convolve2d

    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    window = jnp.asarray(np.outer(g, g) / np.sum(g) ** 2, jnp.float32)

    def plain_ssim(a, b):
        blur = lambda img: jnp.stack([convolve2d(img[..., c], window, mode="same") for c in range(img.shape[-1])], -1)
        mu_a, mu_b = blur(a), blur(b)
        va, vb, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
        c1, c2 = 0.01**2, 0.03**2
        return jnp.mean((2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2)))

    rng = np.random.default_rng(1)
    a = jnp.asarray(rng.uniform(0, 1, (37, 45, 3)), jnp.float32)  # several blur blocks, cut mid-block
    b = jnp.asarray(np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1), jnp.float32)
    got = jax.grad(losses.ssim, argnums=(0, 1))(a, b)
    want = jax.grad(plain_ssim, argnums=(0, 1))(a, b)
    for g_got, g_want in zip(got, want):
        scale = float(jnp.max(jnp.abs(g_want)))
        assert scale > 0
        np.testing.assert_allclose(np.asarray(g_got), np.asarray(g_want), atol=2e-3 * scale)


def test_psnr_and_l1_known_values():
    a = np.zeros((4, 4, 3), np.float32)
    b = np.full((4, 4, 3), 0.1, np.float32)
    assert float(losses.psnr(a, b)) == pytest.approx(20.0, abs=1e-3)  # mse 0.01
    assert float(losses.l1(a, b)) == pytest.approx(0.1, abs=1e-6)


def test_depth_normal_of_a_plane_faces_the_camera():
    from ghsplat_jax.core.camera import intrinsics, look_at

    K = jnp.asarray(intrinsics(16, 12))
    w2c = jnp.asarray(look_at([0.3, -3.0, 1.0], [0.3, 0.0, 1.0]))  # looking along +y
    n = losses.depth_to_normal(jnp.full((12, 16), 3.0), K, w2c)
    assert np.allclose(np.asarray(n[1:-1, 1:-1]), [0, -1, 0], atol=1e-4)  # towards the camera
    assert np.all(np.asarray(n[0]) == 0)
    # A plane normal to the view: full alpha gives zero normal loss for the matching render.
    loss = losses.normal_consistency(n, n, jnp.ones((12, 16)))
    interior = (12 * 16 - (12 * 16 - 10 * 14)) / (12 * 16)
    assert float(loss) == pytest.approx(1 - interior, abs=1e-4)
    g = jax.grad(lambda d: jnp.sum(losses.depth_to_normal(d, K, w2c)))(jnp.zeros((12, 16)))
    assert np.all(np.isfinite(np.asarray(g)))  # zero depth: double-where keeps gradients finite


def test_depth_normal_matches_float64_cross_products_of_back_projected_points():
    from ghsplat_jax.core.camera import intrinsics, look_at

    K = np.asarray(intrinsics(23, 17), np.float64)
    K[0, 1] = 0.7  # a skewed camera: every entry of K^-1 matters
    w2c = np.asarray(look_at([0.4, -2.5, 1.2], [0.1, 0.3, 0.6]), np.float64)
    depth = np.random.default_rng(2).uniform(1.5, 3.0, (17, 23))
    jj, ii = np.meshgrid(np.arange(23) + 0.5, np.arange(17) + 0.5)
    cam = (np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(K).T) * depth[..., None]
    world = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    n = np.cross(world[2:, 1:-1] - world[:-2, 1:-1], world[1:-1, 2:] - world[1:-1, :-2])
    want = np.pad(n / np.linalg.norm(n, axis=-1, keepdims=True), ((1, 1), (1, 1), (0, 0)))
    got = losses.depth_to_normal(jnp.asarray(depth, jnp.float32), jnp.asarray(K, jnp.float32),
                                 jnp.asarray(w2c, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), want, atol=2e-4)
    points = losses.depth_to_points(jnp.asarray(depth, jnp.float32), jnp.asarray(K, jnp.float32),
                                    jnp.asarray(w2c, jnp.float32))
    np.testing.assert_allclose(np.asarray(points), world, atol=1e-4)


# --- schedules and config -----------------------------------------------------------------------
def test_means_learning_rate_schedule_endpoints():
    cfg = TrainConfig(steps=30_000)
    sched = optim.means_schedule(cfg, scene_extent=4.0)
    assert float(sched(0)) == pytest.approx(1.6e-4 * 4.0, rel=1e-5)
    assert float(sched(30_000)) == pytest.approx(1.6e-6 * 4.0, rel=1e-4)
    assert float(sched(15_000)) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6) * 4.0, rel=1e-3)  # log-linear
    assert float(sched(60_000)) == pytest.approx(1.6e-6 * 4.0, rel=1e-4)
    lrs = optim.learning_rates(cfg)
    assert lrs["sh_rest"] == pytest.approx(2.5e-3 / 20) and lrs["opacity_logits"] == 0.05
    # As 2DGS (position_lr_max_steps): a shorter run follows the 30k decay, not one squeezed into it.
    short = optim.means_schedule(TrainConfig(steps=3_000), scene_extent=4.0)
    assert float(short(3_000)) == pytest.approx(float(sched(3_000)), rel=1e-6)
    own = optim.means_schedule(TrainConfig(steps=3_000, lr_means_steps=0), scene_extent=4.0)
    assert float(own(3_000)) == pytest.approx(1.6e-6 * 4.0, rel=1e-4)
    scaled = optim.means_schedule(TrainConfig(steps=3_000, scale_schedule=True).resolved(), scene_extent=4.0)
    assert float(scaled(3_000)) == pytest.approx(1.6e-6 * 4.0, rel=1e-4)


def test_config_overrides_save_and_errors(tmp_path):
    p = tmp_path / "exp.toml"
    p.write_text('steps = 500\nstrategy = "budget"\nbackground = [1, 1, 1]\n')
    cfg = load_config(p)
    assert cfg.steps == 500 and cfg.strategy.name == "budget" and cfg.raster.background == (1.0, 1.0, 1.0)
    save_config(cfg, tmp_path / "config.toml")
    assert load_config(tmp_path / "config.toml") == cfg
    p.write_text("stepz = 3\n")
    with pytest.raises(ConfigError, match="exp.toml.*stepz"):
        load_config(p)
    with pytest.raises(ConfigError, match="strategy"):
        apply_overrides(cfg, {"strategy": "nonesuch"})
    with pytest.raises(ConfigError, match="integer"):
        apply_overrides(cfg, {"steps": "many"})
    with pytest.raises(ConfigError, match="densify_every must be >= 1.*densify_until = 0"):
        apply_overrides(cfg, {"densify_every": 0})
    short = TrainConfig(steps=3000, scale_schedule=True).resolved()
    assert (short.densify_from, short.densify_until, short.densify_every, short.opacity_reset_every) == (50, 1500, 10,
                                                                                                        300)
    assert not short.scale_schedule and short.normal_from == 700


def test_resuming_a_run_saved_before_a_setting_existed_names_it(tmp_path, caplog):
    import argparse

    from ghsplat_jax.commands import train as train_command
    from ghsplat_jax.train.config import settings_missing_from

    save_config(TrainConfig(steps=500), tmp_path / "config.toml")
    assert settings_missing_from(tmp_path / "config.toml") == []
    text = (tmp_path / "config.toml").read_text()
    old = "\n".join(line for line in text.splitlines()
                    if not line.startswith(("normal_loss_alpha_mask", "compositor")))
    (tmp_path / "config.toml").write_text(old)
    assert settings_missing_from(tmp_path / "config.toml") == ["normal_loss_alpha_mask", "raster.compositor"]

    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    args = parser.parse_args(["--out", str(tmp_path), "--resume", "--set", "normal_loss_alpha_mask=false"])
    with caplog.at_level("WARNING"):
        config = train_command.resolve_config(args)
    assert config.steps == 500 and not config.normal_loss_alpha_mask
    warned = [r.getMessage() for r in caplog.records if "predates" in r.getMessage()]
    assert len(warned) == 1 and "raster.compositor" in warned[0] and "normal_loss_alpha_mask" not in warned[0]


# --- densification -------------------------------------------------------------------------------
CAP = 16
PARAMS = densify.DensifyParams(grad_threshold=2e-4, clone_max_scale=0.1, split_scale_div=1.6, prune_opacity=0.05,
                               prune_world_scale=1.0, prune_screen_px=20.0)


def _state(n_active=4, scales=(0.05, 0.05, 0.5, 0.5), grads=(1e-3, 0.0, 1e-3, 0.0), opacity=0.5):
    rng = np.random.default_rng(1)
    s = Surfels(
        means=rng.normal(size=(n_active, 3)).astype(np.float32),
        quats=rng.normal(size=(n_active, 4)).astype(np.float32),
        log_scales=np.log(np.stack([np.asarray(scales), 0.5 * np.asarray(scales)], 1)).astype(np.float32),
        opacity_logits=np.full(n_active, math.log(opacity / (1 - opacity)), np.float32),
        sh_dc=rng.normal(size=(n_active, 3)).astype(np.float32),
        sh_rest=np.zeros((n_active, 3, 3), np.float32),
    )
    params, active = pad_params(s, CAP)
    st = new_state(params, active, optim.make_optimizers(TrainConfig()))
    # Non-zero Adam moments so resets are visible.
    opt = jax.tree_util.tree_map(lambda x: x + 1.0 if x.ndim else x, st.opt_state)
    g = np.zeros(CAP, np.float32)
    g[:n_active] = grads
    return dataclasses.replace(st, opt_state=opt, grad_accum=jnp.asarray(g * 2), grad_count=jnp.full(CAP, 2.0),
                               max_radii=jnp.full(CAP, 5.0))


def test_clone_keeps_position_and_split_halves_in_tangent_plane():
    st = _state()
    key = jax.random.PRNGKey(0)
    new, counts = densify.densify_jit(st, key, jnp.int32(CAP), jnp.bool_(False), p=PARAMS)
    assert int(counts["cloned"]) == 1 and int(counts["split"]) == 1 and int(counts["pruned"]) == 0
    act = np.asarray(new.active)
    assert act.sum() == 6 and act[:4].all()
    old, p = st.params.to_numpy(), new.params.to_numpy()
    born = np.flatnonzero(act & ~np.asarray(st.active))
    assert len(born) == 2
    clone_slot = [b for b in born if np.allclose(p.log_scales[b], old.log_scales[0])]
    assert len(clone_slot) == 1
    np.testing.assert_array_equal(p.means[clone_slot[0]], old.means[0])  # clone: same position
    np.testing.assert_array_equal(p.means[0], old.means[0])  # original untouched
    child = [b for b in born if b != clone_slot[0]][0]
    # split: parent slot 2 and a new slot, scales / 1.6, offsets in the parent's tangent plane
    q = old.quats[2] / np.linalg.norm(old.quats[2])
    normal = np.asarray(to_rotation_matrix(jnp.asarray(q)))[:, 2]
    for slot in (2, child):
        np.testing.assert_allclose(p.log_scales[slot], old.log_scales[2] - math.log(1.6), atol=1e-6)
        offset = p.means[slot] - old.means[2]
        assert abs(offset @ normal) < 1e-5 * max(1.0, np.linalg.norm(offset))
        assert np.linalg.norm(offset) > 0
        np.testing.assert_array_equal(p.sh_dc[slot], old.sh_dc[2])
    assert not np.allclose(p.means[2], p.means[child])
    # fresh moments for new and split rows, old ones kept for the others
    mu = np.asarray(new.opt_state["means"][0].mu)
    assert np.all(mu[[2, child, clone_slot[0]]] == 0) and np.all(mu[[0, 1, 3]] == 1)
    assert np.all(np.asarray(new.grad_accum) == 0) and np.all(np.asarray(new.max_radii) == 0)


def test_prune_and_capacity_limit_and_no_retrace():
    before = densify.TRACE_COUNTS["densify"]
    st = _state(opacity=0.5)
    # lower one opacity below the threshold and make one huge
    logits = st.params.opacity_logits.at[1].set(math.log(0.01 / 0.99))
    st = dataclasses.replace(st, params=dataclasses.replace(st.params, opacity_logits=logits),
                             max_radii=st.max_radii.at[3].set(50.0))
    new, counts = densify.densify_jit(st, jax.random.PRNGKey(1), jnp.int32(CAP), jnp.bool_(True), p=PARAMS)
    act = np.asarray(new.active)
    assert not act[1] and not act[3] and act[0]  # transparent and oversized (screen) pruned
    assert float(new.params.opacity_logits[1]) == INACTIVE_LOGIT
    assert int(counts["pruned"]) == 2 and act.sum() == 4 + 2 - 2
    # at most max_new new surfels: the highest-gradient candidate wins
    g = st.grad_accum.at[2].set(10.0)
    st2 = dataclasses.replace(_state(), grad_accum=g)
    new2, counts2 = densify.densify_jit(st2, jax.random.PRNGKey(2), jnp.int32(1), jnp.bool_(False), p=PARAMS)
    assert int(counts2["split"]) == 1 and int(counts2["cloned"]) == 0 and int(counts2["skipped"]) == 1
    assert np.asarray(new2.active).sum() == 5
    # a full pool: nothing born, bookkeeping consistent
    full = _state(n_active=CAP, scales=[0.05] * CAP, grads=[1e-3] * CAP)
    new3, counts3 = densify.densify_jit(full, jax.random.PRNGKey(3), jnp.int32(CAP), jnp.bool_(False), p=PARAMS)
    assert int(counts3["cloned"]) == 0 and int(counts3["skipped"]) == CAP and np.asarray(new3.active).all()
    assert densify.TRACE_COUNTS["densify"] - before <= 1  # same shapes: one trace at most


def test_opacity_reset_and_budget_schedule():
    st = _state(opacity=0.5)
    new = densify.reset_opacity_jit(st, value=0.01)
    op = np.asarray(jax.nn.sigmoid(new.params.opacity_logits))
    assert np.allclose(op[:4], 0.01, atol=1e-6) and np.all(op[4:] < 1e-6)
    assert np.all(np.asarray(new.opt_state["opacity_logits"][0].mu) == 0)
    assert np.all(np.asarray(new.opt_state["means"][0].mu)[:4] == 1)
    cfg = TrainConfig(strategy="budget", densify_from=500, densify_until=1500)
    assert densify.budget_target(cfg, "linear", 500, 100, 1100) == 100
    assert densify.budget_target(cfg, "linear", 1000, 100, 1100) == 600
    assert densify.budget_target(cfg, "linear", 5000, 100, 1100) == 1100
    assert densify.budget_target(cfg, "immediate", 500, 100, 1100) == 1100


def test_random_init_box_is_where_the_cameras_look():
    import ghsplat_jax as gs
    from ghsplat_jax.train.state import random_init_box

    target = np.array([0.3, -0.2, 0.5])
    K = gs.intrinsics(64, 48, 60)
    ring = [gs.Camera(K, gs.look_at(target + 4.0 * np.array([np.cos(a), np.sin(a), 0.5]), target), 64, 48)
            for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    center, half = random_init_box(ring, np.zeros(3), 9.0)
    assert np.allclose(center, target, atol=1e-5)
    assert half == pytest.approx(4.0 * np.sqrt(1.25) * np.tan(np.radians(30)), rel=1e-4)  # 60 deg wide view
    # forward-facing: no meeting point, the fallback cube
    row = [gs.Camera(K, gs.look_at([x, -4.0, 0.0], [x, 0.0, 0.0]), 64, 48) for x in np.linspace(-1, 1, 5)]
    center, half = random_init_box(row, np.ones(3), 9.0)
    assert np.allclose(center, 1.0) and half == 9.0


def test_grow_pool_and_knn_init():
    st = _state()
    g = grow(st, 2 * CAP)
    assert g.capacity == 2 * CAP and np.asarray(g.active).sum() == 4
    np.testing.assert_array_equal(np.asarray(g.params.means[:CAP]), np.asarray(st.params.means))
    assert np.all(np.asarray(g.opt_state["sh_dc"][0].nu)[CAP:] == 0)
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [10, 10, 10]], np.float32)
    ls = knn_log_scales(pts)
    assert ls[0] == pytest.approx(0.5 * math.log((1 + 4 + 9) / 3), rel=1e-5)



def test_initial_scales_random_factor_and_clamp():
    from ghsplat_jax.train.state import initial_surfels

    pts = np.random.default_rng(1).uniform(-1, 1, (500, 3)).astype(np.float32)
    knn = knn_log_scales(pts)
    init = lambda points, **kw: initial_surfels(points, None, np.zeros(3), 1.0, 4.0,
                                                TrainConfig(init_random_points=500, **kw), np.random.default_rng(0))
    # dataset points keep the nearest-neighbour scale; the factor applies to random points only
    np.testing.assert_allclose(init(pts, random_init_scale=0.5).log_scales[:, 0], knn, rtol=1e-6)
    rand = init(None, random_init_scale=0.5)
    np.testing.assert_allclose(rand.log_scales[:, 0], knn_log_scales(rand.means) + math.log(0.5), rtol=1e-5)
    # the clamp is a fraction of the extent (4.0 here)
    clamped = init(pts, init_scale_max=0.01).log_scales
    assert np.all(clamped <= math.log(0.04) + 1e-6) and np.any(clamped < knn[:, None] - 1e-3)
    # a zero factor would give -inf log scales: refused up front
    with pytest.raises(ConfigError, match="random_init_scale"):
        TrainConfig(random_init_scale=0.0)

def test_checkpoint_roundtrip_and_refuses_nan(tmp_path):
    st = _state()
    path = checkpoint.save_checkpoint(tmp_path / "c.npz", st, {"step": 3, "capacity": CAP})
    template = _state(grads=(0, 0, 0, 0))
    back, meta = checkpoint.load_checkpoint(path, template)
    assert meta["step"] == 3
    for a, b in zip(jax.tree_util.tree_leaves(st), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    bad = dataclasses.replace(st, params=dataclasses.replace(st.params, means=st.params.means.at[0, 0].set(jnp.nan)))
    with pytest.raises(checkpoint.CheckpointError, match="non-finite"):
        checkpoint.save_checkpoint(tmp_path / "d.npz", bad, {})
    assert not (tmp_path / "d.npz").exists()
    (tmp_path / "e.npz").write_bytes(b"junk")
    with pytest.raises(checkpoint.CheckpointError, match="e.npz"):
        checkpoint.read_meta(tmp_path / "e.npz")


def test_strategy_state_of_an_older_checkpoint_loads_with_the_new_entries_at_their_start(tmp_path):
    old = {"growing": jnp.int32(0), "frozen_at": jnp.int32(3750)}
    path = checkpoint.save_checkpoint(tmp_path / "c.npz", _state(), {"step": 3}, aux=old)
    template = {"compact_due": jnp.int32(0), "frozen_at": jnp.int32(0), "growing": jnp.int32(1)}
    back = checkpoint.load_aux(path, template)
    assert int(back["frozen_at"]) == 3750 and int(back["growing"]) == 0 and int(back["compact_due"]) == 0
    with pytest.raises(checkpoint.CheckpointError, match="another strategy"):  # entries this strategy lacks
        checkpoint.load_aux(path, {"frozen_at": jnp.int32(0)})


def test_opacity_reset_recovery_window():
    from ghsplat_jax.train.trainer import last_reset_before

    c = TrainConfig()
    # 2DGS: resets at 3000, 6000, ...; the round at 3000 runs before that reset, 3100 is 100 steps after.
    assert last_reset_before(c, 3000) is None and last_reset_before(c, 3100) == 3000
    assert last_reset_before(c, 20_000) == 12_000  # no resets after densify_until
    white = TrainConfig().replace(background=(1.0, 1.0, 1.0))
    assert last_reset_before(white, 600) == 500  # white backgrounds also reset at densify_from
    short = TrainConfig(steps=300, scale_schedule=True).resolved()
    assert 2 * short.opacity_reset_every >= short.densify_until  # at most one reset in a 300-step run


def test_no_opacity_reset_where_the_run_cannot_recover():
    from ghsplat_jax.train.strategies import is_opacity_reset, last_reset_before

    ends_on_reset = TrainConfig(steps=3000)
    assert not is_opacity_reset(ends_on_reset, 3000) and last_reset_before(ends_on_reset, 3001) is None
    late = TrainConfig(steps=6050)    # 50 steps after the reset at 6000: too few to recover
    assert is_opacity_reset(late, 3000) and not is_opacity_reset(late, 6000)
    assert last_reset_before(late, 6050) == 3000
    assert is_opacity_reset(TrainConfig(steps=3100), 3000)


def test_inputs_that_predict_a_poor_model_are_warned_about(caplog):
    import dataclasses as dc
    import logging

    from ghsplat_jax.train.synthetic import cached_synthetic_dataset
    from ghsplat_jax.train.trainer import FEW_TRAIN_VIEWS, warn_about_inputs

    ds = cached_synthetic_dataset(num_views=16, test_every=4)
    cfg = TrainConfig(data="row")
    assert len(ds.train) >= FEW_TRAIN_VIEWS and warn_about_inputs(cfg, ds) == []
    with caplog.at_level(logging.WARNING, logger="ghsplat.train"):
        few = warn_about_inputs(cfg, dc.replace(ds, train=ds.train[:5]))
        no_points = warn_about_inputs(cfg, dc.replace(ds, points=np.full((500, 3), np.nan, np.float32)))
    assert len(few) == 1 and "only 5 training views" in few[0]
    assert len(no_points) == 1 and "0 SfM points" in no_points[0] and "random points" in no_points[0]
    assert [r.getMessage() for r in caplog.records] == few + no_points


def test_pair_buffer_shrinks_after_an_epoch_that_needs_under_half_of_it():
    """An automatically sized pair buffer follows a falling pair count down, once per epoch of
    steps and only by a factor of two or more (growth on overflow doubles); a capacity set in
    the config is kept."""
    import types

    from ghsplat_jax.raster.render import capacity_bucket
    from ghsplat_jax.train.trainer import TrainingSession, pair_bucket

    assert pair_bucket(100_000) == capacity_bucket(125_000) == 131_072
    assert pair_bucket(461_229) == 655_360  # lego's settled need: a third of its 2M buffer

    def session(capacity, config_capacity=None, views=4):
        return types.SimpleNamespace(
            config=TrainConfig().replace(pair_capacity=config_capacity), images=np.zeros((views, 1)),
            pair_capacity=capacity, epoch_pairs=0, epoch_steps=0)

    s = session(1 << 21)
    for pairs in (300_000, 461_229, 290_000):   # part of an epoch: nothing changes yet
        TrainingSession._refit_pairs(s, pairs)
        assert s.pair_capacity == 1 << 21
    TrainingSession._refit_pairs(s, 350_000)
    assert s.pair_capacity == 655_360 and s.epoch_steps == 0
    for _ in range(4):                           # needs over half of the buffer: kept
        TrainingSession._refit_pairs(s, 300_000)
    assert s.pair_capacity == 655_360
    fixed = session(1 << 21, config_capacity=1 << 21)
    for _ in range(4):
        TrainingSession._refit_pairs(fixed, 1000)
    assert fixed.pair_capacity == 1 << 21


def test_accelerators_grow_buffers_by_doubling_and_keep_them(monkeypatch):
    """On a CPU buffers grow to the renderer's buckets (at most 25% spare); on an accelerator,
    where a recompile costs a thousand steps, the pool grows to powers of two (at least doubling)
    and the pair buffer is never shrunk."""
    import types

    from ghsplat_jax.train.state import growth_bucket
    from ghsplat_jax.train.trainer import TrainingSession

    assert [growth_bucket(n) for n in (21_000, 40_000, 327_000)] == [24_576, 40_960, 327_680]
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert [growth_bucket(n) for n in (21_000, 40_000, 327_000, 1 << 15)] == [1 << 15, 1 << 16, 1 << 19, 1 << 15]
    s = types.SimpleNamespace(config=TrainConfig(), images=np.zeros((2, 1)), pair_capacity=1 << 21,
                              epoch_pairs=0, epoch_steps=0)
    for _ in range(4):
        TrainingSession._refit_pairs(s, 1000)
    assert s.pair_capacity == 1 << 21


def test_pool_growth_follows_the_backend(monkeypatch):
    """The default strategy grows a full pool to growth_bucket of what its candidates need."""
    from raster_scenes import random_scene

    from ghsplat_jax.raster.render import capacity_bucket
    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.step_builder import make_train_step
    from ghsplat_jax.train.strategies import make_strategy

    optimizers, _ = make_train_step(TrainConfig())
    params, active = pad_params(random_scene(3000, seed=1, degree=0), 3000)
    state = new_state(params, active, optimizers)
    state = dataclasses.replace(state, grad_accum=jnp.ones(3000), grad_count=jnp.ones(3000))  # all candidates
    strategy = make_strategy(TrainConfig())
    grown = {}
    for backend in ("cpu", "gpu"):
        monkeypatch.setattr(jax, "default_backend", lambda b=backend: b)
        grown[backend] = strategy._ensure_capacity(None, state, 3000).capacity
    need = math.ceil(6000 / (1.0 - TrainConfig().capacity_headroom))  # 3000 live + 3000 new slots
    assert grown == dict(cpu=capacity_bucket(need), gpu=8192) and grown["cpu"] == 7168
