"""The training loop on a tiny synthetic scene: loss goes down, no recompilation across
steps and densification, resume reproduces the state, non-finite steps roll back."""

from __future__ import annotations

import dataclasses
import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ghsplat_jax import host_memory
from ghsplat_jax.train import densify
from ghsplat_jax.train import step as step_mod
from ghsplat_jax.train.checkpoint import load_checkpoint, read_meta
from ghsplat_jax.train.config import TrainConfig
from ghsplat_jax.train.run_dir import CHECKPOINT_NAME, PLY_NAME, STATS_NAME
from ghsplat_jax.train.synthetic import cached_synthetic_dataset
from ghsplat_jax.train.trainer import TrainingDivergedError, train

# Every test here uses this config (same step settings: the XLA binary is shared through the
# persistent compilation cache).
CONFIG = TrainConfig(steps=30, lr_sh_dc=0.02, lr_means_init=1e-3, lr_means_final=1e-4, sh_degree=1,
                     sh_increase_every=10, densify_from=4, densify_every=4, densify_until=25,
                     opacity_reset_every=1000, lambda_dist=1.0, dist_from=8, lambda_normal=0.05, normal_from=8,
                     initial_capacity=2048, init_random_points=200, progress=False,
                     checkpoint_every=10).replace(pair_capacity=16384)


def dataset():
    return cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    # A fresh compiled step, so the trace count below is this run's alone even when another
    # test in the session already compiled the same step settings.
    traces0 = step_mod.TRACE_COUNTS["train_step"]
    dens0 = densify.TRACE_COUNTS["densify"]
    result = train(CONFIG, out, dataset=dataset())
    stats = [json.loads(line) for line in (out / STATS_NAME).read_text().splitlines()]
    return dict(out=out, result=result, stats=stats, traces=step_mod.TRACE_COUNTS["train_step"] - traces0,
                dens_traces=densify.TRACE_COUNTS["densify"] - dens0)


def test_loss_decreases_and_outputs_written(run):
    stats, out = run["stats"], run["out"]
    assert [s["step"] for s in stats] == list(range(1, 31))
    # (the total loss jumps when the normal and distortion terms switch on: compare L1 and PSNR)
    first, last = stats[:5], stats[-5:]
    assert np.mean([s["l1"] for s in last]) < 0.8 * np.mean([s["l1"] for s in first])
    assert np.mean([s["psnr"] for s in last]) > np.mean([s["psnr"] for s in first]) + 3.0
    assert all(s["finite"] for s in stats)
    from ghsplat_jax.data.ply import load_ply

    s = load_ply(out / PLY_NAME)
    assert s.num == run["result"].num_surfels == stats[-1]["num_surfels"]
    assert np.all(np.isfinite(s.means))
    assert read_meta(out / CHECKPOINT_NAME)["step"] == 30
    assert (out / "config.toml").is_file()


def test_no_recompilation_across_steps_and_densification(run):
    stats = run["stats"]
    rounds = [s for s in stats if "cloned" in s]
    assert len(rounds) >= 4 and sum(s["cloned"] + s["split"] for s in rounds) > 0  # densification happened
    counts = [s["num_surfels"] for s in stats]
    assert len(set(counts)) > 1  # the count changed ...
    # ... but the step compiled once per pool / pair bucket and set of geometry terms (the distortion
    # and normal terms start together, at step 8; a record's "step" counts the steps done).
    assert CONFIG.dist_from == CONFIG.normal_from
    buckets = {(s["capacity"], s["pair_capacity"], s["step"] - 1 >= CONFIG.normal_from) for s in stats}
    assert run["traces"] == len(buckets)
    assert run["dens_traces"] <= len({s["capacity"] for s in stats})


def test_budget_count_follows_the_cap_schedule(tmp_path):
    """With --strategy budget every densification round grows the count by at most the
    schedule's allowance (linear from the initial count to the cap), and by exactly that
    when there are more candidates than room: the cap is followed, not just not exceeded."""
    out = tmp_path / "budget"
    # a threshold this low makes every surfel seen a candidate
    cfg = CONFIG.replace(strategy={"name": "budget", "max_surfels": 400}, densify_grad_threshold=1e-8)
    result = train(cfg, out, dataset=dataset())
    meta = read_meta(out / CHECKPOINT_NAME)
    initial, cap = meta["initial_count"], meta["max_surfels"]
    assert cap == 400 and initial < cap
    stats = [json.loads(line) for line in (out / STATS_NAME).read_text().splitlines()]
    assert {s["capacity"] for s in stats} == {cap}  # the pool is allocated at the cap
    prev, filled, targets = initial, 0, []
    for s in stats:
        if "candidates" in s:  # a densification round after iteration s["step"]
            target = densify.budget_target(cfg, cfg.strategy.schedule, s["step"], initial, cap)
            targets.append(target)
            grown = prev + s["cloned"] + s["split"]
            assert grown <= target, s
            assert s["num_surfels"] == grown - s["pruned"], s
            if s["skipped"]:  # more candidates than the allowance: filled up to the target
                assert grown == target, s
                filled += 1
        prev = s["num_surfels"]
    assert targets == sorted(targets) and targets[0] < targets[-1] < cap  # a ramp, not the cap at once
    assert filled >= 3 and prev == result.num_surfels


def test_resume_reproduces_state(run, tmp_path):
    out = tmp_path / "resumed"
    part = train(CONFIG, out, dataset=dataset(), until=13)
    assert part.steps == 13 and not (out / PLY_NAME).exists()
    assert read_meta(out / CHECKPOINT_NAME)["step"] == 13
    done = train(CONFIG, out, dataset=dataset(), resume=True)
    assert done.steps == 30
    a, b = run["result"].state, done.state
    assert a.capacity == b.capacity
    np.testing.assert_array_equal(np.asarray(a.active), np.asarray(b.active))
    for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    lines = (out / STATS_NAME).read_text().splitlines()
    assert [json.loads(x)["step"] for x in lines] == list(range(1, 31))


def test_compiled_programs_dropped_mid_run_change_nothing(run, tmp_path, monkeypatch, caplog):
    """Near the kernel's limit on memory mappings a run drops JAX's compiled programs (see
    host_memory) and compiles again: the model is the one the run that kept them made."""
    from ghsplat_jax.train import trainer

    monkeypatch.setattr(trainer, "IN_RUN_MAP_SHARE", 0.0)  # every check finds the process "near the limit"
    monkeypatch.setattr(trainer, "MAPS_CHECK_EVERY", 10)
    with caplog.at_level(logging.INFO, logger="ghsplat"):
        done = train(CONFIG, tmp_path / "released", dataset=dataset())
    if host_memory.memory_maps() is not None:  # Linux: the maps were counted and the programs dropped
        assert caplog.text.count("released JAX's compiled programs") == 3
    a, b = run["result"].state, done.state
    np.testing.assert_array_equal(np.asarray(a.active), np.asarray(b.active))
    for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)


def test_nan_step_rolls_back(tmp_path, caplog):
    ds = dataset()
    bad_view = dataclasses.replace(ds.train[0], image=np.full_like(ds.train[0].image, np.nan))
    bad = dataclasses.replace(ds, train=[bad_view] + ds.train[1:])
    with caplog.at_level(logging.WARNING, logger="ghsplat.train"):
        r = train(CONFIG, tmp_path / "nan", dataset=bad, until=10)
    assert r.rollbacks >= 1 and "rolled back" in caplog.text
    stats = [json.loads(line) for line in (tmp_path / "nan" / STATS_NAME).read_text().splitlines()]
    assert sum(bool(s.get("rolled_back")) for s in stats) == r.rollbacks
    assert any(s["loss"] is None for s in stats)  # NaN is written as null, never as NaN
    state, _ = load_checkpoint(tmp_path / "nan" / CHECKPOINT_NAME, r.state)
    act = np.asarray(state.active)
    for leaf in jax.tree_util.tree_leaves(state.params):
        assert np.all(np.isfinite(np.asarray(leaf)[act]))
    all_bad = dataclasses.replace(ds, train=[bad_view] * len(ds.train))
    with pytest.raises(TrainingDivergedError, match="diverged"):
        train(dataclasses.replace(CONFIG, max_consecutive_rollbacks=3), tmp_path / "div", dataset=all_bad)


def test_depth_normal_agrees_with_rendered_normal_of_a_tilted_surfel():
    import ghsplat_jax as gs
    from ghsplat_jax.core.quaternions import from_rotation_matrix
    from ghsplat_jax.train import losses

    a = np.deg2rad(30)
    tilt = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rot = tilt @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # normal (3rd column) towards -y, tilted 30 deg
    s = gs.make_surfels([[0, 0, 0]], quats=[from_rotation_matrix(rot)], log_scales=[[np.log(2.0)] * 2],
                        opacity_logits=[5.0], sh_dc=[[1, 1, 1]])
    cam = gs.Camera(gs.intrinsics(32, 24, 40), gs.look_at([0, -4, 0], [0, 0, 0]), 32, 24)
    out = gs.render(s, cam, gs.RasterConfig())
    dn = np.asarray(losses.depth_to_normal(out.depth, cam.K, cam.world_to_cam))
    np.testing.assert_allclose(dn[12, 16], rot[:, 2], atol=1e-3)  # both face the camera
    np.testing.assert_allclose(np.asarray(out.normal[12, 16]) / float(out.alpha[12, 16]), rot[:, 2], atol=2e-2)
    good = float(losses.normal_consistency(out.normal[8:-8, 8:-8], dn[8:-8, 8:-8], out.alpha[8:-8, 8:-8]))
    flipped = float(losses.normal_consistency(out.normal[8:-8, 8:-8], -dn[8:-8, 8:-8], out.alpha[8:-8, 8:-8]))
    assert good < 0.1 < 1.5 < flipped


def _facing_surfel():
    import ghsplat_jax as gs
    from ghsplat_jax.core.quaternions import from_rotation_matrix

    rot = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # normal towards -y, at the camera
    return gs.make_surfels([[0, 0, 0]], quats=[from_rotation_matrix(rot)], log_scales=[[np.log(1.0)] * 2],
                           opacity_logits=[0.0], sh_dc=[[1, 1, 1]])


def test_alpha_masked_normal_loss_gives_uncovered_pixels_no_pull_towards_opacity():
    import ghsplat_jax as gs
    from ghsplat_jax.train import losses

    cam = gs.Camera(gs.intrinsics(32, 24, 40), gs.look_at([0, -4, 0], [0, 0, 0]), 32, 24)

    def normal_loss(logit, coverage):
        s = dataclasses.replace(_facing_surfel(), opacity_logits=jnp.reshape(logit, (1,)))
        out = gs.render(s, cam, gs.RasterConfig(pair_capacity=64))
        dn = losses.depth_to_normal(out.depth, cam.K, cam.world_to_cam)
        return losses.normal_consistency(out.normal, dn, out.alpha, coverage)

    grad = jax.value_and_grad(normal_loss)
    plain, plain_grad = grad(0.0, None)
    assert float(plain_grad) < 0  # the 2DGS term: more opacity, lower loss, wherever it is
    ones, ones_grad = grad(0.0, jnp.ones((24, 32)))
    assert float(ones) == float(plain) and float(ones_grad) == float(plain_grad)
    empty, empty_grad = grad(0.0, jnp.zeros((24, 32)))
    assert float(empty) == 0.0 and float(empty_grad) == 0.0  # an empty image asks for no surface


def test_training_images_carry_their_alpha_to_the_step_only_for_the_normal_loss():
    import ghsplat_jax as gs
    from ghsplat_jax.data.dataset import View
    from ghsplat_jax.train.step import LossWeights, _loss
    from ghsplat_jax.train.trainer import stack_views

    cam = gs.Camera(gs.intrinsics(32, 24, 40), gs.look_at([0, -4, 0], [0, 0, 0]), 32, 24)
    rgb = np.full((24, 32, 3), 0.5, np.float32)
    alpha = np.linspace(0, 1, 24 * 32, dtype=np.float32).reshape(24, 32)
    views = [View("a", cam, rgb, alpha), View("b", cam, rgb)]
    images = np.asarray(stack_views(views, with_alpha=True)[0])
    assert images.shape == (2, 24, 32, 4)
    np.testing.assert_array_equal(images[0, :, :, 3], alpha)
    np.testing.assert_array_equal(images[1, :, :, 3], 1.0)  # no alpha: covered everywhere
    assert stack_views(views)[0].shape[-1] == 3
    assert stack_views(views[1:], with_alpha=True)[0].shape[-1] == 3  # no view has alpha

    w = LossWeights.from_config(dataclasses.replace(CONFIG, normal_from=0))
    cfg = gs.RasterConfig(pair_capacity=64)

    def loss(image):
        s = _facing_surfel()
        value, aux = _loss(s, jnp.zeros((1, 2)), jnp.ones(1, bool), jnp.asarray(image), cam, 0, w, cfg, gs.render)
        return float(value), float(aux["l1"]), float(aux["normal"])

    three = loss(rgb)
    assert three[2] > 0
    assert loss(np.concatenate([rgb, np.ones((24, 32, 1), np.float32)], 2)) == three
    no_cover = loss(np.concatenate([rgb, np.zeros((24, 32, 1), np.float32)], 2))
    assert no_cover[1] == three[1] and no_cover[2] == 0.0  # colour terms unchanged


def test_ctrl_c_saves_a_checkpoint(tmp_path, monkeypatch):
    from ghsplat_jax.train import trainer

    real_step = trainer.TrainingSession.step

    def step(self, i, **kwargs):
        if i == 5:
            raise KeyboardInterrupt
        return real_step(self, i, **kwargs)

    monkeypatch.setattr(trainer.TrainingSession, "step", step)
    with pytest.raises(KeyboardInterrupt):
        train(CONFIG, tmp_path / "int", dataset=dataset())
    assert read_meta(tmp_path / "int" / CHECKPOINT_NAME)["step"] == 5
    lines = (tmp_path / "int" / STATS_NAME).read_text().splitlines()
    assert json.loads(lines[-1])["step"] == 5


def test_sigterm_saves_a_checkpoint_like_ctrl_c(tmp_path, monkeypatch):
    import os
    import signal

    from ghsplat_jax.train import trainer

    real_step = trainer.TrainingSession.step

    def step(self, i, **kwargs):
        if i == 4:
            os.kill(os.getpid(), signal.SIGTERM)
        return real_step(self, i, **kwargs)

    monkeypatch.setattr(trainer.TrainingSession, "step", step)
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        train(CONFIG, tmp_path / "term", dataset=dataset())
    assert read_meta(tmp_path / "term" / CHECKPOINT_NAME)["step"] == 4
    assert signal.getsignal(signal.SIGTERM) is previous  # the handler is only set while training


def test_pair_overflow_discards_the_step_and_grows_the_buffer(tmp_path, caplog):
    before = step_mod.TRACE_COUNTS["train_step"]
    with caplog.at_level(logging.INFO, logger="ghsplat.train"):
        r = train(CONFIG.replace(pair_capacity=64), tmp_path / "ovf", dataset=dataset(), until=3)
    assert "overflowed" in caplog.text and r.steps == 3
    stats = [json.loads(line) for line in (tmp_path / "ovf" / STATS_NAME).read_text().splitlines()]
    assert all(s["overflow"] == 0 and s["num_pairs"] <= s["pair_capacity"] for s in stats)  # nothing dropped
    assert stats[0]["pair_capacity"] >= 4096 and len({s["pair_capacity"] for s in stats}) == 1
    assert step_mod.TRACE_COUNTS["train_step"] - before == 2  # the 64-pair bucket and the grown one


def test_compiled_step_follows_every_setting_of_its_config():
    """Steps are built from their config, not looked up by a hand-picked key: variants that differ
    only in a learning rate or a loss weight get their own compiled step, equal configs equal results."""
    from raster_scenes import random_scene

    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.step_builder import make_train_step
    from ghsplat_jax.train.trainer import step_raster_config

    view = dataset().train[0]
    image, cam = jnp.asarray(view.image), view.camera
    params, active = pad_params(random_scene(64, seed=2, degree=1), 128)
    variants = {"base": CONFIG, "same": CONFIG.replace(), "lr": CONFIG.replace(lr_opacity=10 * CONFIG.lr_opacity),
                "loss": CONFIG.replace(lambda_dssim=0.9)}
    out = {}
    for name, cfg in variants.items():
        optimizers, step = make_train_step(cfg)
        new, m = step(new_state(params, active, optimizers), image, cam.K, cam.world_to_cam, jnp.float32(1e-4),
                      step_raster_config(cfg, 16384), cam.width, cam.height)
        out[name] = (np.asarray(new.params.opacity_logits), float(m["loss"]))
    assert np.array_equal(out["base"][0], out["same"][0]) and out["base"][1] == out["same"][1]
    assert not np.allclose(out["lr"][0], out["base"][0])      # the learning rate reached the update
    assert out["loss"][1] != pytest.approx(out["base"][1])    # the loss weight reached the loss


@pytest.mark.parametrize("extra", [dict(), pytest.param(dict(strategy={"name": "mcmc", "max_surfels": 100}),
                                                        marks=pytest.mark.slow)], ids=["default", "mcmc"])
def test_parted_step_matches_the_one_program_step(extra):
    """The step whose compositor runs in two threads (`parted_step`) computes what the single
    program does: the same loss and metrics, and updates equal to float32 rounding (the parts'
    gradients add up in another order, and the parts walk in batches of another size), with every
    output on (median, distortion, normals) and with the MCMC regularisers, whose gradient does not
    pass through the renderer."""
    from raster_scenes import random_scene

    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.step_builder import make_train_step
    from ghsplat_jax.train.trainer import step_raster_config

    view = dataset().train[0]
    image, cam = jnp.asarray(view.image), view.camera
    params, active = pad_params(random_scene(64, seed=2, degree=1, opacity=(0.3, 0.9)), 128)
    # Batches of 2 chunks in one program, of 3 in each part: both walks carry across batches.
    cfg = CONFIG.replace(depth_ratio=0.5, **extra).replace(batch_chunks=2, **{"raster.part_batch_chunks": 3})
    rcfg = step_raster_config(cfg, 16384)
    assert rcfg.median and rcfg.distortion and rcfg.depth_normal
    out = {}
    for threads in (1, 2):
        optimizers, step = make_train_step(cfg.replace(step_threads=threads))
        out[threads] = step(new_state(params, active, optimizers), image, cam.K, cam.world_to_cam,
                            jnp.float32(1e-4), rcfg, cam.width, cam.height)
    (a, ma), (b, mb) = out[1], out[2]
    for key in ("loss", "l1", "ssim", "distortion", "normal", "num_pairs", "finite"):
        assert float(mb[key]) == pytest.approx(float(ma[key]), rel=1e-6, abs=1e-9), key
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-5, atol=1e-6)
    moved = np.abs(np.asarray(a.params.means) - np.asarray(params.means))[np.asarray(active)]
    assert moved.max() > 0  # the comparison is of a real update


def test_compacted_pool_steps_like_the_full_one_and_densification_end_compacts():
    """state.compact moves each live surfel with its moments and statistics: a step on the
    compacted pool gives the live surfels the same loss and updates as on the full pool. The
    default strategy compacts at its first round after densification ends."""
    from raster_scenes import random_scene

    from ghsplat_jax.raster.render import capacity_bucket
    from ghsplat_jax.train.state import compact, new_state, pad_params
    from ghsplat_jax.train.step_builder import make_train_step
    from ghsplat_jax.train.strategies import make_strategy
    from ghsplat_jax.train.trainer import step_raster_config

    view = dataset().train[0]
    image, cam = jnp.asarray(view.image), view.camera
    params, active = pad_params(random_scene(64, seed=2, degree=1), 256)
    active[::3] = False  # free slots between live ones, as pruning leaves them
    active[200:230] = True
    optimizers, step = make_train_step(CONFIG)
    full = new_state(params, active, optimizers)
    full = dataclasses.replace(full, grad_accum=jnp.arange(256.0), max_radii=jnp.arange(256.0) + 0.5)
    small = compact(full, 128)
    live = np.flatnonzero(active)
    assert small.capacity == 128 and int(small.active.sum()) == len(live) and bool(np.all(small.active[:len(live)]))
    np.testing.assert_array_equal(np.asarray(small.grad_accum[:len(live)]), live)
    args = (image, cam.K, cam.world_to_cam, jnp.float32(1e-4), step_raster_config(CONFIG, 16384), cam.width,
            cam.height)
    (a, ma), (b, mb) = step(full, *args), step(small, *args)
    assert float(mb["loss"]) == pytest.approx(float(ma["loss"]), rel=1e-6)
    for x, y in zip(jax.tree_util.tree_leaves((a.params, a.opt_state, a.max_radii)),
                    jax.tree_util.tree_leaves((b.params, b.opt_state, b.max_radii))):
        if np.ndim(x):
            np.testing.assert_allclose(np.asarray(y)[:len(live)], np.asarray(x)[live], rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="do not fit"):
        compact(full, len(live) - 1)

    big = compact(full, 3 * 4096)  # a spare pool, as growth leaves it
    strategy = make_strategy(CONFIG)
    kept, _, _ = strategy.refine(None, big, strategy.init_state(len(live)), CONFIG.densify_until - 3)
    assert kept.capacity == big.capacity  # densification still running: the pool stays
    first_round = -(-CONFIG.densify_until // CONFIG.densify_every) * CONFIG.densify_every
    done, _, _ = strategy.refine(None, big, strategy.init_state(len(live)), first_round)
    assert done.capacity == capacity_bucket(len(live)) < big.capacity
    np.testing.assert_array_equal(np.asarray(done.params.means[:len(live)]), np.asarray(full.params.means)[live])


def _dot_precisions(jaxpr) -> list:
    """The precision of every dot_general in a jaxpr, its sub-jaxprs (loops, conds, jits) included."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            found.append(eqn.params["precision"])
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                sub = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr holds its Jaxpr
                if hasattr(sub, "eqns"):
                    found += _dot_precisions(sub)
    return found


def test_every_matrix_product_of_the_step_asks_for_float32():
    """A GPU runs float32 products as TF32 by default, which broke the exactness tests on an
    H100 (alpha off by 3.6e-3): every product of the step, the compositor's hand-written backward
    and the SSIM blur included, must name full float32 precision (on a CPU it changes nothing)."""
    from raster_scenes import random_scene

    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.step_builder import make_train_step
    from ghsplat_jax.train.trainer import step_raster_config

    view = dataset().train[0]
    image, cam = jnp.asarray(view.image), view.camera
    params, active = pad_params(random_scene(64, seed=2, degree=1), 128)
    optimizers, step = make_train_step(CONFIG.replace(step_threads=1))  # one program, as on a GPU
    state = new_state(params, active, optimizers)
    jaxpr = jax.make_jaxpr(lambda s: step(s, image, cam.K, cam.world_to_cam, jnp.float32(1e-4),
                                          step_raster_config(CONFIG, 16384), cam.width, cam.height))(state)
    precisions = _dot_precisions(jaxpr.jaxpr)
    assert len(precisions) >= 8  # the compositor's forward and backward, projection, SH and SSIM
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert all(p == highest for p in precisions), precisions


@pytest.mark.slow  # two runs with evaluations slowed on purpose (test_resume_reproduces_state covers resume)
def test_test_curve_resumes_without_gaps_and_ends_at_the_final_metrics(tmp_path, monkeypatch):
    """With test_curve_every, training writes the test views' metrics every so many steps to
    test_curve.jsonl, continued across a resume without repeated or missing points; its last
    point (the padded pool rendered with colour only) equals the final evaluation's test PSNR,
    its time is left out of the training seconds, and a point on an opacity-reset step shows the
    model before the reset."""
    import time

    from ghsplat_jax.eval import evaluate
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.io_utils import code_revision, host_label
    from ghsplat_jax.train.run_dir import TEST_CURVE_NAME

    slow = 2.0  # each evaluation made this much slower, so leaving it out shows in the step times
    real = evaluate.test_curve_metrics

    opacity = []  # the mean opacity of each point's model

    def slowed(dataset, config):
        measure = real(dataset, config)

        def timed(params, active, pair_capacity):
            opacity.append(float(np.mean(jax.nn.sigmoid(np.asarray(params.opacity_logits)[np.asarray(active)]))))
            time.sleep(slow)
            return measure(params, active, pair_capacity)
        return timed

    monkeypatch.setattr(evaluate, "test_curve_metrics", slowed)
    config = CONFIG.replace(test_curve_every=10, save_test_renders=False, opacity_reset_every=20,
                            reset_recovery_steps=1)  # opacities reset to 0.01 after step 20
    out = tmp_path / "run"
    train_and_evaluate(config, out, dataset=dataset(), until=15)   # checkpoints at 10 and 15
    metrics = train_and_evaluate(config, out, dataset=dataset(), resume=True)
    curve = [json.loads(line) for line in (out / TEST_CURVE_NAME).read_text().splitlines()]
    assert [p["step"] for p in curve] == [10, 20, 30]
    assert all(p["num_views"] == len(dataset().test) > 0 and np.isfinite(p["psnr"]) for p in curve)
    assert all(p["code_revision"] == code_revision() and len(p["load_average"]) == 3 for p in curve)
    assert all(p["host"] == host_label(metrics["machine"]) for p in curve)  # a stopped run's kind of machine
    assert curve[-1]["psnr"] == pytest.approx(metrics["test"]["psnr"], abs=1e-3)
    assert curve[-1]["l1"] == pytest.approx(metrics["test"]["l1"], rel=1e-4)
    stats = {r["step"]: r for r in map(json.loads, (out / STATS_NAME).read_text().splitlines())}
    assert curve[0]["eval_seconds"] >= slow
    assert opacity[1] > 0.05  # the step-20 point came before the reset
    for step in (10, 11):  # the step with the evaluation and the next (no compile falls on them)
        assert stats[step]["elapsed_s"] - stats[step - 1]["elapsed_s"] < slow
    assert curve[0]["elapsed_s"] == pytest.approx(stats[10]["elapsed_s"], abs=0.1)
    assert metrics["train_seconds"] == pytest.approx(stats[30]["elapsed_s"], abs=0.5)
    with pytest.raises(Exception, match="test_curve_every"):
        TrainConfig(test_curve_every=-1)
