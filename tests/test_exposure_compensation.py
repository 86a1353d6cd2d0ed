"""Exposure compensation (TrainConfig.exposure_compensation): the off path left as it was, a known
exposure change recovered on a tiny synthetic scene, the parted step against the one program, and
the run's outputs and resume."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ghsplat_jax.train import exposure as E
from ghsplat_jax.train.config import ConfigError, TrainConfig
from ghsplat_jax.train.state import compact, grow, new_state, pad_params
from ghsplat_jax.train.step_builder import make_train_step
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, random_scene
from ghsplat_jax.train.trainer import step_raster_config

STEP_CONFIG = TrainConfig(lambda_normal=0.0, sh_degree=0, progress=False, exposure_from=0,
                          exposure_lr=0.02).replace(pair_capacity=16384)
GAIN = np.array([0.6, 0.7, 0.55], np.float32)  # the first training photo, darker and tinted


def dataset():
    return cached_synthetic_dataset(num_views=6, width=48, height=32, num_surfels=80, test_every=3, num_points=200)


def step_args(view, cfg):
    return (jnp.asarray(view.image), view.camera.K, view.camera.world_to_cam, jnp.float32(1e-5),
            step_raster_config(cfg, 16384), view.camera.width, view.camera.height)


def test_off_leaves_the_step_as_it_was_and_on_matches_it_at_zero():
    """Off: no exposure leaves in the state, and the exposure settings do not reach the program.
    On, with every correction at zero, the surfels' update is the off step's, bit for bit."""
    view = dataset().train[0]
    params, active = pad_params(random_scene(80, 0), 128)
    off = STEP_CONFIG.replace(step_threads=1)
    texts = []
    for cfg in (off, off.replace(exposure_lr=0.5, exposure_from=7, exposure_reg=3.0)):
        opt, step = make_train_step(cfg)
        state = new_state(params, active, opt)
        assert state.exposure is None
        texts.append(step.lower(state, *step_args(view, cfg)).as_text())
    assert texts[0] == texts[1]
    a, ma = step(state, *step_args(view, off))
    opt, step_on = make_train_step(off.replace(exposure_compensation=True))
    b, mb = step_on(new_state(params, active, opt, exposure=E.init_exposure(4)), *step_args(view, off),
                    view=jnp.int32(0))
    assert float(ma["loss"]) == float(mb["loss"])
    for x, y in zip(jax.tree_util.tree_leaves((a.params, a.opt_state)),
                    jax.tree_util.tree_leaves((b.params, b.opt_state))):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    values = np.asarray(b.exposure.values)
    assert np.any(values[0] != 0) and np.all(values[1:] == 0)  # that view only


def test_parted_step_learns_the_same_correction_as_the_one_program():
    view = dataset().train[0]
    params, active = pad_params(random_scene(80, 0), 128)
    image = jnp.asarray(view.image) * jnp.asarray(GAIN)
    out = {}
    for threads in (1, 2):
        cfg = STEP_CONFIG.replace(exposure_compensation=True, step_threads=threads)
        opt, step = make_train_step(cfg)
        state = new_state(params, active, opt, exposure=E.init_exposure(3))
        out[threads] = step(state, image, *step_args(view, cfg)[1:], view=jnp.int32(1))
    (a, ma), (b, mb) = out[1], out[2]
    assert float(mb["loss"]) == pytest.approx(float(ma["loss"]), rel=1e-6)
    np.testing.assert_allclose(np.asarray(b.exposure.values), np.asarray(a.exposure.values), rtol=1e-5, atol=1e-7)
    assert np.any(np.asarray(a.exposure.values)[1] != 0)


def test_a_darker_photo_is_matched_by_its_gain_and_the_model_keeps_the_others_exposure():
    """The first training photo is darker and tinted (GAIN); the model starts at the true scene.
    Compensation learns that view's gains near GAIN, leaves the other views at 1, and the
    surfels' colours stay what the other photos show (0.012 mean error of their DC colour)."""
    ds = dataset()
    cfg = STEP_CONFIG.replace(exposure_compensation=True)
    opt, step = make_train_step(cfg)
    scene = random_scene(80, 0)
    params, active = pad_params(scene, 128)
    state = new_state(params, active, opt, exposure=E.init_exposure(len(ds.train)))
    images = [jnp.asarray(v.image) for v in ds.train]
    images[0] = images[0] * jnp.asarray(GAIN)
    for i in range(60 * len(ds.train)):
        k = i % len(ds.train)
        state, m = step(state, images[k], *step_args(ds.train[k], cfg)[1:], view=jnp.int32(k))
        assert bool(m["finite"])
    rows = E.corrections_report(state.exposure, [v.name for v in ds.train])
    np.testing.assert_allclose(rows[0]["gain"], GAIN, atol=0.03)
    for r in rows[1:]:  # the median photo's exposure (a squared penalty had drifted them to 1.03)
        np.testing.assert_allclose(r["gain"], 1.0, atol=0.015)
    dc = np.asarray(state.params.sh_dc)[np.asarray(active)]
    assert np.abs(dc - np.asarray(scene.sh_dc)).mean() < 0.025
    summary = E.corrections_summary(rows)
    assert summary["large_views"] == [ds.train[0].name] and summary["min_gain"] < 0.65


def test_pool_growth_and_compaction_keep_the_corrections():
    params, active = pad_params(random_scene(80, 0), 128)
    opt, _ = make_train_step(STEP_CONFIG)
    exposure = dataclasses.replace(E.init_exposure(128), values=jnp.arange(128 * 6, dtype=jnp.float32).reshape(128, 6))
    state = new_state(params, active, opt, exposure=exposure)  # as many views as slots: rows must not move
    for moved in (grow(state, 256), compact(state, 96)):
        np.testing.assert_array_equal(np.asarray(moved.exposure.values), np.asarray(exposure.values))


def test_config_and_command_line(tmp_path):
    import argparse

    from ghsplat_jax.commands import train as train_cmd

    with pytest.raises(ConfigError, match="exposure_lr"):
        TrainConfig(exposure_lr=-1.0)
    assert TrainConfig(steps=3000, scale_schedule=True).resolved().exposure_from == 50
    p = argparse.ArgumentParser()
    train_cmd.add_arguments(p)
    out = str(tmp_path / "run")
    assert train_cmd.resolve_config(p.parse_args(["--out", out, "--exposure-compensation"])).exposure_compensation
    assert not train_cmd.resolve_config(p.parse_args(["--out", out])).exposure_compensation


def test_run_writes_corrections_and_resume_keeps_them(tmp_path):
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.train.trainer import TrainingSession

    cfg = TrainConfig(steps=8, sh_degree=0, lambda_normal=0.0, densify_from=100, initial_capacity=512,
                      progress=False, checkpoint_every=4, exposure_compensation=True, exposure_from=2,
                      save_test_renders=False).replace(pair_capacity=16384)
    ds = dataset()
    out = tmp_path / "run"
    assert not train_and_evaluate(cfg, out, dataset=ds, until=4)["finished"]
    saved = json.loads((out / "exposure_corrections.json").read_text())
    assert [r["name"] for r in saved["views"]] == [v.name for v in ds.train] and saved["step"] == 4
    session = TrainingSession(cfg, out, ds, resume=True)
    values = np.asarray(session.state.exposure.values)
    np.testing.assert_allclose(np.exp(values[:, :3]), [r["gain"] for r in saved["views"]], rtol=1e-6)
    assert np.any(values != 0)
    metrics = train_and_evaluate(cfg, out, dataset=ds, resume=True)
    summary = json.loads((out / "metrics.json").read_text())["exposure_compensation"]
    assert metrics["exposure_compensation"] == summary and summary["num_views"] == len(ds.train)
    assert np.isfinite(metrics["test"]["psnr"])
    # Training views are scored under their learnt corrections, as training scored them: a large
    # correction (made here) changes their score and no test view's.
    from ghsplat_jax.eval.evaluate import by_view, evaluate
    from ghsplat_jax.train.run_dir import load_run

    config, surfels, _, _ = load_run(out)
    saved = json.loads((out / "exposure_corrections.json").read_text())
    for r in saved["views"]:
        r["gain"], r["offset"] = [2.0, 2.0, 2.0], [0.3, 0.3, 0.3]
    plain = evaluate(surfels, ds, config, tmp_path / "plain", progress=False)
    corrected = evaluate(surfels, ds, config, tmp_path / "corrected", progress=False, train_exposure=by_view(saved))
    assert corrected["train"]["psnr"] < plain["train"]["psnr"] - 3.0
    assert corrected["test"]["psnr"] == plain["test"]["psnr"] == pytest.approx(metrics["test"]["psnr"], abs=1e-4)
