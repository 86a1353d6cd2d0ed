"""Pose refinement (TrainConfig.pose_refine): the so(3) exponential, the off path left as it was,
recovery of a known pose error on a tiny synthetic scene, and the run's outputs and resume."""

from __future__ import annotations

import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ghsplat_jax.train import pose as P
from ghsplat_jax.train.config import ConfigError, TrainConfig
from ghsplat_jax.train.state import new_state, pad_params
from ghsplat_jax.train.step_builder import make_train_step, step_threads
from ghsplat_jax.train.synthetic import cached_synthetic_dataset, random_scene
from ghsplat_jax.train.trainer import step_raster_config

# Geometry terms off: the pose's gradient comes from the photometric loss alone, and the step
# compiles without the median, distortion and normal outputs (fast).
STEP_CONFIG = TrainConfig(lambda_normal=0.0, sh_degree=0, progress=False, pose_refine_from=0, pose_lr_rot=3e-3,
                          pose_lr_trans=3e-3).replace(pair_capacity=16384)
# A known camera-frame error of the first training view: about 1.5 degrees and 1.9% of the extent.
ERROR = np.array([0.02, -0.015, 0.01, 0.01, -0.015, 0.005])


def dataset():
    return cached_synthetic_dataset(num_views=6, width=48, height=32, num_surfels=80, test_every=3, num_points=200)


def pose_error(delta, perturbation, extent: float) -> tuple[float, float]:
    """(degrees, % of extent) of what remains of `perturbation` after the correction `delta`."""
    E = P.correction_matrix(delta, extent) @ P.correction_matrix(perturbation, extent)
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
    return float(angle), float(100 * np.linalg.norm(E[:3, 3]) / extent)


def test_so3_exp_matches_rodrigues_and_is_smooth_at_zero():
    for w in ([0.3, -0.2, 0.5], [1e-5, 2e-5, -1e-5], [0.0, 0.0, 0.0]):
        got = np.asarray(P.so3_exp(jnp.asarray(w, jnp.float32)))
        np.testing.assert_allclose(got, P.correction_matrix(np.r_[w, 0, 0, 0], 1.0)[:3, :3], atol=1e-6)
        np.testing.assert_allclose(got @ got.T, np.eye(3), atol=1e-6)
    # d exp(w) / dw at 0 is the generator: finite, and exactly the cross-product matrix's entries.
    jac = jax.jacobian(P.so3_exp)(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(jac)))
    np.testing.assert_allclose(np.asarray(jac)[2, 1], [1.0, 0.0, 0.0], atol=1e-7)  # R[2,1] = +w_x
    w2c = jnp.asarray(dataset().train[0].camera.world_to_cam)
    assert np.array_equal(np.asarray(P.correct(w2c, jnp.zeros(6), 3.0)), np.asarray(w2c))  # zero is exact
    moved = P.refined_world_to_cam(w2c, ERROR, 3.0)
    centre = lambda m: -np.asarray(m)[:3, :3].T @ np.asarray(m)[:3, 3]  # noqa: E731
    assert np.linalg.norm(centre(moved) - centre(w2c)) == pytest.approx(3.0 * np.linalg.norm(ERROR[3:]), rel=1e-5)


def test_off_leaves_the_state_and_step_as_they_were_and_on_matches_it_at_zero():
    """Off: no pose leaves in the state or checkpoint, and the pose settings do not reach the
    program. On, with every correction at zero, the step's surfel update is the off step's, bit
    for bit (the correction moves only after the render it was differentiated in)."""
    view = dataset().train[0]
    image, cam = jnp.asarray(view.image), view.camera
    params, active = pad_params(random_scene(80, 0), 128)
    off = STEP_CONFIG.replace(pose_refine=False, step_threads=1)  # the one program, as pose_refine runs
    rcfg = step_raster_config(off, 16384)
    args = (image, cam.K, cam.world_to_cam, jnp.float32(1e-4), rcfg, cam.width, cam.height)
    texts = []
    for cfg in (off, off.replace(pose_lr_rot=0.5, pose_lr_trans=0.5, pose_refine_from=7)):
        opt, step = make_train_step(cfg)
        state = new_state(params, active, opt)
        assert state.pose is None and not any("pose" in jax.tree_util.keystr(p)
                                              for p, _ in jax.tree_util.tree_flatten_with_path(state)[0])
        texts.append(step.lower(state, *args).as_text())
    assert texts[0] == texts[1]
    a, ma = step(state, *args)
    opt, step_on = make_train_step(STEP_CONFIG.replace(pose_refine=True))
    b, mb = step_on(new_state(params, active, opt, P.init_pose(4, 3.0)), *args, view=jnp.int32(0))
    assert float(ma["loss"]) == float(mb["loss"])
    for x, y in zip(jax.tree_util.tree_leaves((a.params, a.opt_state)), jax.tree_util.tree_leaves((b.params,
                                                                                                   b.opt_state))):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    assert np.any(np.asarray(b.pose.delta[0]) != 0) and np.all(np.asarray(b.pose.delta[1:]) == 0)  # that view only


def test_refinement_recovers_a_known_pose_error():
    """One training view's pose is off by ~1.5 degrees and ~1.9% of the extent; the others are
    exact and the model starts at the true scene. Refinement takes most of the error out of that
    view (the correction moves toward the perturbation's inverse) and leaves exact views near zero."""
    ds = dataset()
    extent = float(ds.scene_extent)
    cfg = STEP_CONFIG.replace(pose_refine=True)
    opt, step = make_train_step(cfg)
    params, active = pad_params(random_scene(80, 0), 128)
    state = new_state(params, active, opt, P.init_pose(len(ds.train), extent))
    rcfg = step_raster_config(cfg, 16384)
    w2cs = [np.asarray(v.camera.world_to_cam, np.float64) for v in ds.train]
    w2cs[0] = P.correction_matrix(ERROR, extent) @ w2cs[0]
    before = pose_error(np.zeros(6), ERROR, extent)
    for i in range(30 * len(ds.train)):
        k = i % len(ds.train)
        v = ds.train[k]
        state, m = step(state, jnp.asarray(v.image), v.camera.K, jnp.asarray(w2cs[k], jnp.float32),
                        jnp.float32(1e-5), rcfg, v.camera.width, v.camera.height, view=jnp.int32(k))
        assert bool(m["finite"])
    after = pose_error(np.asarray(state.pose.delta[0]), ERROR, extent)
    assert after[0] < 0.4 * before[0] and after[1] < 0.4 * before[1], (before, after)
    rows = P.corrections_report(state.pose, [v.name for v in ds.train])
    assert rows[0]["rotation_deg"] > 2 * max(r["rotation_deg"] for r in rows[1:])


def test_large_corrections_are_named_in_a_warning(caplog):
    rows = [dict(name="good", rotation_deg=0.1, translation_m=0.01, translation_pct_extent=0.2),
            dict(name="IMG_0042.jpg", rotation_deg=2.0, translation_m=0.1, translation_pct_extent=3.0)]
    with caplog.at_level(logging.WARNING, logger="ghsplat.train"):
        messages = P.warn_large(rows)
    assert len(messages) == 1 and "IMG_0042.jpg" in caplog.text and "good" not in caplog.text
    summary = P.corrections_summary(rows)
    assert summary["max_rotation_deg"] == 2.0 and summary["large_views"] == ["IMG_0042.jpg"]


def test_config_and_command_line(tmp_path):
    from ghsplat_jax.train.config import load_config

    (tmp_path / "c.toml").write_text("[train]\npose_refine = true\npose_lr_rot = 2e-3\n")
    cfg = load_config(tmp_path / "c.toml")
    assert cfg.pose_refine and cfg.pose_lr_rot == 2e-3 and step_threads(cfg.replace(step_threads=0)) == 1
    with pytest.raises(ConfigError):
        TrainConfig().replace(pose_refine=True, step_threads=2)
    assert TrainConfig(steps=3000, scale_schedule=True).resolved().pose_refine_from == 50
    import argparse

    from ghsplat_jax.commands import train as train_cmd

    p = argparse.ArgumentParser()
    train_cmd.add_arguments(p)
    out = str(tmp_path / "run")
    assert train_cmd.resolve_config(p.parse_args(["--out", out, "--pose-refine"])).pose_refine
    assert train_cmd.resolve_config(p.parse_args(["--out", out, "--set", "pose_refine_from=9"])).pose_refine_from == 9
    assert not train_cmd.resolve_config(p.parse_args(["--out", out])).pose_refine


def test_run_writes_corrections_and_resume_keeps_them(tmp_path):
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.train.trainer import TrainingSession

    cfg = TrainConfig(steps=8, sh_degree=0, lambda_normal=0.0, densify_from=100, initial_capacity=512,
                      progress=False, checkpoint_every=4, pose_refine=True, pose_refine_from=2,
                      save_test_renders=False).replace(pair_capacity=16384)
    ds = dataset()
    out = tmp_path / "run"
    part = train_and_evaluate(cfg, out, dataset=ds, until=4)
    assert not part["finished"]
    saved = json.loads((out / "pose_corrections.json").read_text())
    assert [r["name"] for r in saved["views"]] == [v.name for v in ds.train] and saved["step"] == 4
    session = TrainingSession(cfg, out, ds, resume=True)
    np.testing.assert_array_equal(np.asarray(session.state.pose.delta), np.array([r["delta"] for r in saved["views"]],
                                                                                  np.float32))
    assert np.any(np.asarray(session.state.pose.delta) != 0)
    metrics = train_and_evaluate(cfg, out, dataset=ds, resume=True)
    summary = json.loads((out / "metrics.json").read_text())["pose_refinement"]
    assert metrics["pose_refinement"] == summary and summary["num_views"] == len(ds.train)
    assert summary["max_rotation_deg"] >= summary["median_rotation_deg"] > 0
