"""The self-sizing, self-stopping recipe: the plateau rule, the resolution schedule, the
growth rule of the `auto` strategy, and a whole tiny run that stops by itself."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ghsplat_jax.train.config import ConfigError, TrainConfig
from ghsplat_jax.train.recipes import RECIPES
from ghsplat_jax.train.resolution import (
    box_downscale,
    crop_stack,
    crop_windows,
    energy_kept,
    factor_at,
    scale_intrinsics,
    spectrum_schedule,
)
from ghsplat_jax.train.stopping import PlateauRule
from ghsplat_jax.train.strategies.auto import level_gain, start_hold
from ghsplat_jax.train.trainer import hold_out


def test_plateau_rule_anneals_once_then_stops_and_remembers_the_best():
    rule = PlateauRule(patience=2, min_gain=0.1, stop_after=0, anneal=0.5)
    s = rule.initial()
    actions = []
    for step, psnr in enumerate([20.0, 21.0, 21.05, 21.02, 21.5, 21.5, 21.55], start=1):
        s, a = rule.update(s, step * 100, psnr)
        actions.append(a)
    # 21.05 and 21.55 are better but under min_gain: kept as the best model, yet they count as waiting.
    assert actions == ["best", "best", "best", "anneal", "best", "wait", "stop"]
    assert s["lr_scale"] == 0.5 and s["annealed_at"] == 400 and s["stopped_at"] == 700
    assert s["best_step"] == 700 and s["best_psnr"] == 21.55 and "0.1 dB" in s["reason"]


def test_plateau_rule_waits_for_stop_after_and_ignores_nan():
    rule = PlateauRule(patience=1, min_gain=0.1, stop_after=1000, anneal=1.0)
    s = rule.initial()
    s, _ = rule.update(s, 100, 20.0)
    s, a = rule.update(s, 200, float("nan"))
    assert a == "wait" and s["best_psnr"] == 20.0  # a NaN check is never the best
    s, a = rule.update(s, 1000, 19.0)
    assert a == "wait" and s["waited"] == 0  # checks up to stop_after count towards no plateau
    s, a = rule.update(s, 1100, 19.0)
    assert a == "stop" and s["annealed_at"] is None  # anneal = 1: stop at the first plateau


def test_plateau_rule_counts_no_check_made_at_reduced_resolution():
    """A real plant's run: validation flat over the last half-resolution checks (1500-2000), full
    resolution from step 2000. The rule waits for a plateau of full-resolution checks."""
    rule = PlateauRule(patience=3, min_gain=0.1, stop_after=2000, anneal=0.3)
    s = rule.initial()
    for step, psnr in [(1000, 28.0), (1250, 29.0), (1500, 29.8), (1750, 29.78), (2000, 29.79)]:
        s, a = rule.update(s, step, psnr)
    assert a == "wait" and s["annealed_at"] is None and s["lr_scale"] == 1.0
    for step, psnr in [(2250, 29.7), (2500, 29.75)]:  # two flat full-resolution checks: not yet three
        s, a = rule.update(s, step, psnr)
    assert a == "wait" and s["annealed_at"] is None
    s, a = rule.update(s, 2750, 29.8)
    assert a == "anneal" and s["annealed_at"] == 2750


def test_plateau_rule_keeps_only_a_model_trained_under_the_late_loss():
    """normal_settle: a run whose validation peaks before the normal prior starts (step 7,000) and
    dips under it. Without keep_from the pre-prior model is kept and the run stops at 7,750; with
    it, the best restarts at 8,000 (the anneal stays) and the kept model comes from then on."""
    curve = [(5500, 28.0), (5750, 28.3), (6000, 28.35), (6250, 28.36), (6500, 28.37), (6750, 28.38),
             (7000, 28.5), (7250, 28.3), (7500, 28.35), (7750, 28.4), (8000, 28.3), (8250, 28.42),
             (8500, 28.45), (8750, 28.44), (9000, 28.46), (9250, 28.43)]

    def run(rule):
        s, actions = rule.initial(), {}
        for step, psnr in curve:
            s, actions[step] = rule.update(s, step, psnr)
            if actions[step] == "stop":
                break
        return s, actions

    s, actions = run(PlateauRule(patience=3, min_gain=0.1, stop_after=2000, anneal=0.3))
    assert actions[6500] == "anneal" and s["stopped_at"] == 7750 and s["best_step"] == 7000
    s, actions = run(PlateauRule(patience=3, min_gain=0.1, stop_after=2000, anneal=0.3, keep_from=8000))
    assert actions[6500] == "anneal" and actions[7750] == "wait"  # a plateau before keep_from stops nothing
    assert s["kept_from"] == 8000 and actions[8000] == "best" and s["lr_scale"] == 0.3
    assert s["stopped_at"] == 9000 and s["best_step"] == 9000 and s["best_psnr"] == 28.46


def test_normal_settle_sets_the_rule_only_where_the_normal_loss_acts():
    cfg = TrainConfig().replace(recipe="auto", normal_settle=1000)
    assert PlateauRule.from_config(cfg).keep_from == cfg.normal_from + 1000
    assert PlateauRule.from_config(cfg.replace(steps=cfg.normal_from + 500)).keep_from == cfg.normal_from + 500
    for off in (dict(lambda_normal=0.0), dict(normal_from=cfg.steps), dict(normal_settle=0)):
        assert PlateauRule.from_config(cfg.replace(**off)).keep_from == 0
    with pytest.raises(ConfigError, match="normal_settle"):
        TrainConfig(normal_settle=-1)


def test_box_downscale_and_intrinsics_agree_on_where_a_point_lands():
    img = np.zeros((1, 24, 32, 3), np.float32)
    img[0, 8:12, 20:24] = 1.0  # a 4x4 block
    small = box_downscale(img, 4)
    assert small.shape == (1, 6, 8, 3) and small[0, 2, 5, 0] == 1.0 and small.sum() == 3.0
    K = np.array([[[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]]], np.float32)
    p = K[0] @ np.array([0.3, -0.1, 1.0])  # pixel coordinates at full size
    q = scale_intrinsics(K, 4)[0] @ np.array([0.3, -0.1, 1.0])
    np.testing.assert_allclose(q[:2], p[:2] / 4, rtol=1e-6)
    assert box_downscale(np.ones((2, 25, 33, 4), np.float32), 2).shape == (2, 12, 16, 4)  # remainders cropped


def test_spectrum_schedule_starts_coarse_for_smooth_images_and_ends_at_full_resolution():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:256, 0:256] / 256.0
    smooth = np.stack([np.sin(2 * np.pi * (x + k * y))[..., None].repeat(3, -1) for k in range(4)]).astype(np.float32)
    noise = rng.random((4, 256, 256, 3), np.float32)
    assert energy_kept(smooth, 8) > 0.99 and energy_kept(noise, 2) < 0.3
    sched = spectrum_schedule(smooth, until=1000, energy=0.8, min_side=32)
    assert sched[0] == (0, 8) and sched[-1] == (1000, 1)
    assert [f for _, f in sched] == [8, 4, 2, 1] and all(a[0] < b[0] for a, b in zip(sched, sched[1:]))
    assert factor_at(sched, 0) == 8 and factor_at(sched, 999) == 2 and factor_at(sched, 1000) == 1
    assert spectrum_schedule(noise, until=1000) == [(0, 1)]  # white noise needs every pixel from the start
    assert spectrum_schedule(smooth, until=1000, min_side=200) == [(0, 1)]  # 128 px < 200: no smaller scale


@pytest.mark.parametrize("width,height,tiles", [(192, 144, 2), (50, 37, 2), (50, 37, 3), (31, 17, 1)])
def test_crop_windows_are_one_size_and_cover_every_pixel(width, height, tiles):
    windows = crop_windows(width, height, tiles)
    assert len(windows) == tiles * tiles and len({(w, h) for _, _, w, h in windows}) == 1
    hits = np.zeros((height, width), int)
    for x0, y0, w, h in windows:
        assert 0 <= x0 and x0 + w <= width and 0 <= y0 and y0 + h <= height
        hits[y0:y0 + h, x0:x0 + w] += 1
    assert hits.min() == 1 and hits.max() <= 4  # neighbours overlap by under a window's pixel at most


def test_a_window_renders_as_the_same_pixels_of_the_whole_view():
    """A window's camera (the principal point moved by the window's corner) renders exactly the
    pixels the whole view shows there, so a step on a window trains the same model."""
    from raster_scenes import camera, random_scene

    import ghsplat_jax as gs

    scene, cam = random_scene(60, seed=3), camera(50, 37)
    whole = np.asarray(gs.render(scene, cam).rgb)
    crops, Ks, w, h = crop_stack(whole[None], np.asarray(cam.K)[None], 2)
    for t, (x0, y0, _, _) in enumerate(crop_windows(50, 37, 2)):
        out = np.asarray(gs.render(scene, gs.Camera(K=Ks[t], world_to_cam=cam.world_to_cam, width=w, height=h)).rgb)
        np.testing.assert_allclose(out, crops[t], atol=2e-5)
        np.testing.assert_array_equal(crops[t], whole[y0:y0 + h, x0:x0 + w])


def test_level_gain_nets_out_the_time_trend_per_doubling():
    assert level_gain((1000, 1000, 20.0), (2000, 2000, 20.5), trend=0.0) == pytest.approx(0.5)
    assert level_gain((1000, 1000, 20.0), (2000, 4000, 21.0), trend=0.0) == pytest.approx(0.5)
    # 1 dB a doubling, of which 1000 steps at 0.6 dB per 1000 steps explain 0.6.
    assert level_gain((1000, 1000, 20.0), (2000, 2000, 21.0), trend=6e-4) == pytest.approx(0.4)
    assert level_gain((1000, 1000, 20.0), (2000, 2000, 21.0), trend=-1e-3) == pytest.approx(1.0)  # never credited
    assert level_gain((1000, 2000, 20.0), (2000, 2000, 21.0), trend=0.0) == -math.inf  # no growth: nothing bought


def _growth_decisions(checks, width=400, height=400, early_until=0, **settings):
    """Feed (count, val_psnr, train_scale) checks, 250 steps apart, to the auto strategy's hook (the
    checks at reduced resolution or up to step `early_until` marked early, as the trainer marks
    them); a level's growth ends (the hold begins) where a check's count reaches the level's
    target, as `refine` ends it. Returns the counts it froze at and the last state."""
    from types import SimpleNamespace

    from ghsplat_jax.train.strategies import make_strategy

    strategy = make_strategy(TrainConfig().replace(recipe="auto", **{f"strategy.{k}": v for k, v in settings.items()}))
    sstate, ctx, frozen = strategy.init_state(100), SimpleNamespace(width=width, height=height), []
    for step, (count, psnr, scale) in enumerate(checks, start=1):
        target = int(sstate["level_target"])
        if target and count >= target and not int(sstate["holding"]) and int(sstate["growing"]):
            sstate = start_hold(sstate)
        state = SimpleNamespace(num_active=lambda count=count: count)
        val = {"psnr": psnr, "early": scale != 1 or step * 250 <= early_until}
        sstate, info = strategy.on_validation(ctx, state, sstate, step * 250, val)
        frozen += [info["growth_stopped"]] if "growth_stopped" in info else []
    return frozen, sstate


# Reduced resolution (ignored), then the first level's hold at 10,000 surfels (three checks), a
# check while the next level grows (ignored), and the second level's hold at 20,000.
FIRST_LEVEL = [(2000, 18.0, 4), (10000, 25.0, 1), (10000, 25.5, 1), (10000, 26.0, 1), (15000, 26.1, 1)]


def test_growth_rule_judges_levels_net_of_the_time_trend():
    frozen, sstate = _growth_decisions(FIRST_LEVEL)
    assert frozen == [] and int(sstate["level_target"]) == 20000 and not int(sstate["holding"])
    assert (int(sstate["checked_step"]), int(sstate["checked_count"])) == (1000, 10000)
    # The doubling bought 1.6 dB in 1,000 steps, but at 20,000 the model still gains 1.2 dB per
    # 1,000 steps without growing: net 0.4 dB per doubling, under 0.5: the count freezes.
    frozen, sstate = _growth_decisions(FIRST_LEVEL + [(20000, 27.0, 1), (20000, 27.3, 1), (20000, 27.6, 1)])
    assert frozen == [20000] and not int(sstate["growing"]) and int(sstate["frozen_at"]) == 2000
    # The same gain with a flat hold (0.2 dB per 1,000 steps) is the count's: the next level grows.
    frozen, sstate = _growth_decisions(FIRST_LEVEL + [(20000, 27.5, 1), (20000, 27.55, 1), (20000, 27.6, 1)])
    assert frozen == [] and int(sstate["level_target"]) == 40000
    # The ceiling (ceiling_per_pixel x one image's pixels: 2 x 100 x 100) freezes it at its hold's end.
    frozen, _ = _growth_decisions(FIRST_LEVEL + [(20000, 27.5, 1), (20000, 27.55, 1), (20000, 29.6, 1)],
                                  width=100, height=100)
    assert frozen == [20000]


def test_shed_gain_is_the_validation_loss_without_the_least_weighted_surfels_per_doubling(monkeypatch):
    from types import SimpleNamespace

    import jax.numpy as jnp
    from raster_scenes import random_scene

    from ghsplat_jax.train import optim
    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.strategies import auto

    params, active = pad_params(random_scene(8, seed=0, degree=0), 16)
    state = new_state(params, active, optim.make_optimizers(TrainConfig().replace(sh_degree=0)))
    weight = jnp.zeros(16).at[:8].set(jnp.array([5.0, 0.1, 3.0, 0.2, 4.0, 0.3, 6.0, 0.4]))
    monkeypatch.setattr(auto, "accumulated_weights", lambda ctx, s: weight)
    # A validation score that each live surfel raises by its weight: what the model loses without
    # some of them is their weight.
    ctx = SimpleNamespace(validate=lambda s: 20.0 + float(jnp.sum(jnp.where(s.active, weight, 0.0))))
    assert auto.shed_gain(ctx, state, 4) == pytest.approx(1.0)  # the 4 lightest: 0.1 + 0.2 + 0.3 + 0.4, one doubling
    assert auto.shed_gain(ctx, state, 6) == pytest.approx((1.0 + 3.0 + 4.0) / 2)  # two doublings: 8 -> 2
    assert auto.shed_gain(ctx, state, 0) == -math.inf  # the count did not grow
    assert int(state.num_active()) == 8  # judged, not removed


def test_shed_judge_sheds_the_level_it_judges(monkeypatch):
    from ghsplat_jax.train.strategies import auto

    sheds = []

    def fake_gain(ctx, state, shed, value):
        sheds.append(shed)
        return value

    # The first level judged sheds half of what grew before full resolution; 0.8 dB per doubling
    # is worth it, and the next level grows to twice the count.
    monkeypatch.setattr(auto, "shed_gain", lambda c, s, shed: fake_gain(c, s, shed, 0.8))
    frozen, sstate = _growth_decisions(FIRST_LEVEL, level_judge="shed")
    assert frozen == [] and sheds == [5000] and int(sstate["level_target"]) == 20000
    # The next level sheds what it added; 0.3 dB per doubling freezes the count. No time trend
    # enters: the same checks with a steep hold (1.2 dB per 1,000 steps) read the same.
    monkeypatch.setattr(auto, "shed_gain", lambda c, s, shed: fake_gain(c, s, shed, 0.8 if shed == 5000 else 0.3))
    frozen, sstate = _growth_decisions(FIRST_LEVEL + [(20000, 27.0, 1), (20000, 27.3, 1), (20000, 27.6, 1)],
                                       level_judge="shed")
    assert frozen == [20000] and sheds[-1] == 10000 and int(sstate["frozen_at"]) == 2000
    with pytest.raises(ValueError, match="level_judge"):
        _growth_decisions(FIRST_LEVEL, level_judge="guess")


def test_fork_judge_sets_the_model_against_its_shed_copy_trained_as_long(monkeypatch):
    from ghsplat_jax.train.strategies import auto

    forks = []

    def fake_fork(psnr):
        def fork(ctx, state, shed_count, start, steps):
            forks.append((shed_count, start, steps))
            return psnr
        return fork

    # A hold of three checks at 10,000 surfels (steps 500-1000): at its end the shed copy (half
    # the count) trains 500 steps; the count holds until the run has trained as many.
    hold = [(2000, 18.0, 4), (10000, 25.0, 1), (10000, 25.5, 1), (10000, 26.0, 1), (10000, 26.2, 1)]
    monkeypatch.setattr(auto, "fork_psnr", fake_fork(25.8))
    frozen, sstate = _growth_decisions(hold, level_judge="fork")
    assert forks == [(5000, 1000, 500)] and int(sstate["fork_due"]) == 1500 and int(sstate["holding"])
    assert int(sstate["level_target"]) == 0 and frozen == []
    # At step 1500 the model that kept them scores 26.5 against the copy's 25.8: 0.7 dB for one
    # doubling, worth it: the next level grows to twice the count.
    frozen, sstate = _growth_decisions(hold + [(10000, 26.5, 1)], level_judge="fork")
    assert frozen == [] and int(sstate["level_target"]) == 20000 and not int(sstate["fork_due"])
    # Against a copy that recovered to 26.2 dB it is 0.3 dB: the count freezes at 10,000.
    monkeypatch.setattr(auto, "fork_psnr", fake_fork(26.2))
    frozen, sstate = _growth_decisions(hold + [(10000, 26.5, 1)], level_judge="fork")
    assert frozen == [10000] and not int(sstate["growing"])


def test_plateau_judge_grows_at_each_plateau_while_the_last_level_paid():
    from types import SimpleNamespace

    from ghsplat_jax.train.strategies import make_strategy

    strategy = make_strategy(TrainConfig().replace(recipe="auto", **{"strategy.level_judge": "plateau"}))
    ctx = SimpleNamespace(width=400, height=400)

    def plateau(sstate, it, count, best):
        return strategy.on_plateau(ctx, SimpleNamespace(num_active=lambda: count), sstate, it, best)

    def checks(sstate, n):
        for it in range(n):
            sstate, info = strategy.on_validation(ctx, None, sstate, 250 * it, {"psnr": 24.0, "early": False})
            assert info == {}  # the hook judges nothing at a check
        return sstate

    # The first check at full resolution begins the hold; a plateau before `hold_checks` checks at
    # the count waits (the flat checks were made while the count still grew).
    sstate = checks(strategy.init_state(100), 1)
    assert int(sstate["holding"]) and plateau(sstate, 2500, 14000, 26.0)[1] and int(sstate["level_target"]) == 0
    sstate, grows, _ = plateau(checks(sstate, 2), 4000, 14000, 26.0)  # the first plateau: grow
    assert grows and int(sstate["level_target"]) == 28000 and not int(sstate["holding"])
    assert plateau(sstate, 4500, 20000, 26.1)[1]  # a plateau while the level grows: wait for its own
    sstate = start_hold(sstate)  # the level reached its target (refine begins the hold)
    sstate, grows, _ = plateau(checks(sstate, 3), 6000, 28000, 26.8)  # +0.8 dB for one doubling: grow again
    assert grows and int(sstate["level_target"]) == 56000
    sstate = start_hold(sstate)
    sstate, grows, info = plateau(checks(sstate, 3), 8000, 56000, 27.1)  # +0.3 dB: not worth it
    assert not grows and info == {"growth_stopped": 56000} and int(sstate["frozen_at"]) == 8000
    assert plateau(sstate, 9000, 56000, 27.2)[1] is False  # frozen: the stop rule acts
    # The ceiling (2 x 100 x 100 pixels) freezes at the first plateau.
    small = SimpleNamespace(width=100, height=100)
    s0 = dict(strategy.init_state(100), holding=1, hold_seen=3)
    assert strategy.on_plateau(small, SimpleNamespace(num_active=lambda: 20000), s0, 4000, 26.0)[1] is False


def test_a_level_grown_after_the_first_trains_with_the_means_rate_rewound():
    from types import SimpleNamespace

    from ghsplat_jax.train.strategies import make_strategy

    ctx = SimpleNamespace(width=400, height=400)
    for rewind in (False, True):
        strategy = make_strategy(TrainConfig().replace(recipe="auto", **{"strategy.level_judge": "plateau",
                                                                         "strategy.rewind_lr": rewind}))
        sstate = strategy.init_state(100)
        for it in (3000, 3250, 3500):  # the first level's checks at full resolution: the first begins it
            sstate, _ = strategy.on_validation(ctx, None, sstate, it, {"psnr": 24.0, "early": False})
        assert strategy.schedule_step(sstate, 4000) == 4000  # the first level: the schedule as it is
        sstate, grows, _ = strategy.on_plateau(ctx, SimpleNamespace(num_active=lambda: 14000), sstate, 5000, 26.0)
        assert grows and int(sstate["level_target"]) == 28000
        # The next level trains from the rate of step 3,000 on; without the setting, as scheduled.
        assert [strategy.schedule_step(sstate, t) for t in (5000, 5100)] == ([3000, 3100] if rewind else [5000, 5100])


def test_the_stop_rule_waits_while_the_strategy_grows_at_a_plateau():
    from ghsplat_jax.train.stopping import PlateauRule

    rule = PlateauRule(patience=2, min_gain=0.1, anneal=0.5)
    before = dict(rule.initial(), best_psnr=26.0, best_step=500, waited=1)
    after, action = rule.update(before, 1000, 26.05)
    assert action == "anneal"
    held = rule.held(before, after)
    assert held["waited"] == 0 and held["lr_scale"] == 1.0 and held["annealed_at"] is None
    assert held["best_psnr"] == 26.05 and held["best_step"] == 1000  # the better model is still kept


def test_a_training_copy_trains_as_the_run_does_and_leaves_the_run_alone(tmp_path):
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset
    from ghsplat_jax.train.trainer import TrainingSession

    ds = cached_synthetic_dataset(num_views=8, width=32, height=24, num_surfels=40, test_every=4, num_points=200)
    cfg = TrainConfig().replace(steps=20, progress=False, pair_capacity=16384, densify_from=1000).resolved()
    session = TrainingSession(cfg, tmp_path / "s", ds, resume=False)
    start = session.state
    copy = session.train_copy(start, 0, 3)
    for step in range(3):
        session.step(step)
    assert session.state is not start and int(copy.step) == int(session.state.step) == 3
    np.testing.assert_allclose(np.asarray(copy.params.means), np.asarray(session.state.params.means), atol=1e-6)
    assert not np.allclose(np.asarray(copy.params.means), np.asarray(start.params.means))


def test_early_checks_judge_no_level_even_at_full_resolution():
    # Without a resolution schedule every check is at full resolution; those the stop rule does not
    # count yet (the trainer marks them early) neither begin nor judge a level.
    full = [(count, psnr, 1) for count, psnr, _ in FIRST_LEVEL]
    _, sstate = _growth_decisions(full)
    assert int(sstate["level_target"]) == 20000  # judged at the third check: the next level grows
    frozen, sstate = _growth_decisions(full, early_until=1250)
    assert frozen == [] and int(sstate["level_target"]) == 0 and not int(sstate["holding"])


def test_a_level_grows_to_its_target_then_holds_in_its_pool_and_a_frozen_count_fits_its_pool():
    from types import SimpleNamespace

    from raster_scenes import random_scene

    from ghsplat_jax.train import optim
    from ghsplat_jax.train.state import new_state, pad_params
    from ghsplat_jax.train.strategies import make_strategy

    cfg = TrainConfig().replace(recipe="auto", densify_from=0, densify_every=1, sh_degree=1,
                                **{"strategy.grow_rate": 0.25, "strategy.noise_lr": 0.0})
    strategy = make_strategy(cfg)
    params, active = pad_params(random_scene(40, seed=0, degree=1), 8192)
    state = new_state(params, active, optim.make_optimizers(cfg))
    ctx = SimpleNamespace(width=100, height=100, extent=1.0, means_lr=lambda it: 1e-4, validate=None)
    sstate = dict(strategy.init_state(40), level_target=60)
    counts = []
    for it in range(1, 6):
        state, sstate, _ = strategy.refine(ctx, state, sstate, it)
        counts.append(state.num_active())
    assert counts == [50, 60, 60, 60, 60] and int(sstate["holding"]) == 1  # 40 x 1.25, then the target
    assert state.capacity == 8192  # a hold keeps its pool: the next level grows into it
    state, _, _ = strategy.refine(ctx, state, dict(sstate, growing=0, holding=0), 6)
    assert state.num_active() == 60 and state.capacity < 8192  # frozen: the pool shrinks to fit


def test_auto_recipe_is_a_table_under_the_other_settings():
    cfg = TrainConfig().replace(recipe="auto", val_every=50)
    assert cfg.val_every == 50 and cfg.strategy.name == "auto" and cfg.res_schedule == "spectrum"
    assert cfg.stop_patience == RECIPES["auto"]["stop_patience"]
    with pytest.raises(ConfigError, match="recipe must be one of"):
        TrainConfig().replace(recipe="fastest")
    with pytest.raises(ConfigError, match="stop_patience needs validation"):
        TrainConfig(stop_patience=3)


def test_a_recipes_step_ceiling_does_not_scale_its_schedule(caplog):
    # Experiment files set scale_schedule for the 2DGS default; an auto variant with a lower
    # ceiling must keep the recipe's own schedule, not one shrunk to the ceiling.
    cfg = TrainConfig(scale_schedule=True).replace(recipe="auto", steps=8000)
    with caplog.at_level("WARNING", logger="ghsplat.train"):
        done = cfg.resolved()
    assert (done.densify_every, done.densify_from, done.res_until, done.lr_means_steps, done.normal_from) == (
        100, RECIPES["auto"]["densify_from"], RECIPES["auto"]["res_until"], RECIPES["auto"]["lr_means_steps"], 7000)
    assert not done.scale_schedule and "ceiling" in caplog.text
    assert TrainConfig(scale_schedule=True, steps=8000).resolved().densify_every == 27  # no recipe: scaled


@pytest.mark.parametrize("at_freeze,normal_from", [(False, 0), (True, 0), (False, 120)])
def test_a_tiny_auto_run_stops_by_itself_and_keeps_its_best_model(tmp_path, at_freeze, normal_from):
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset

    ds = cached_synthetic_dataset(num_views=20, width=32, height=24, num_surfels=40, test_every=5, num_points=200)
    cfg = TrainConfig().replace(recipe="auto", steps=400, val_every=10, stop_patience=2, stop_min_gain=0.5,
                                stop_after=0, res_until=20, res_min_side=8, densify_from=5, densify_every=5,
                                normal_from=normal_from, normal_settle=60 if normal_from else 0, lr_sh_dc=0.02,
                                sh_degree=1, sh_increase_every=10, progress=False, checkpoint_every=1000,
                                pair_capacity=16384)
    # min_gain_db 5: the first level judged freezes the count (a level in two checks, 20 steps).
    cfg = cfg.replace(**{"strategy.compact_at_freeze": at_freeze, "strategy.min_gain_db": 5.0,
                         "strategy.hold_checks": 2})
    assert cfg.replace(recipe="auto").val_every == 10  # the same recipe again changes nothing
    metrics = train_and_evaluate(cfg, tmp_path / "run", dataset=ds)
    stop = metrics["stop"]
    assert metrics["finished"] and metrics["steps"] == stop["stopped_at"] < 400, stop
    assert "validation PSNR gained less than 0.5 dB" in stop["reason"] and stop["annealed_at"] is not None
    rows = [json.loads(x) for x in (tmp_path / "run" / "stats.jsonl").read_text().splitlines()]
    checks = {r["step"]: r for r in rows if "val_psnr" in r}
    assert max(checks) == stop["stopped_at"] and checks[stop["best_step"]]["val_psnr"] == stop["best_val_psnr"]
    assert stop["best_val_psnr"] == max(r["val_psnr"] for r in checks.values())
    assert stop["validation_views"] == [v.name for v in hold_out(ds.train, cfg.val_hold_every)[1]] != []
    if normal_from:  # the same run with normal_from = 0 stops at step 100, before this one's normal loss starts
        assert stop["kept_from"] == 180 <= stop["best_step"] and stop["stopped_at"] >= 180 + 2 * 10
    else:
        assert stop["kept_from"] is None
    # The first steps trained on half-size images: the schedule reached full size at step 20.
    assert (tmp_path / "run" / "point_cloud.ply").is_file() and math.isfinite(metrics["test"]["psnr"])
    assert metrics["num_gaussians"] > 0 and metrics["recipe"] == "auto" and metrics["strategy"] == "auto"
    # Compaction at the end: the kept model is the compacted one, within its allowed validation loss.
    c = metrics["compaction"]
    assert c["after"] == metrics["num_gaussians"] <= c["before"]
    assert c["val_psnr_before"] == pytest.approx(stop["best_val_psnr"], abs=1e-3)
    assert c["val_psnr_before"] - c["val_psnr_after"] <= c["max_loss_db"] + 1e-6
    if at_freeze:  # compacted where the count froze too, and trained on with the rest
        f = c["at_freeze"]
        assert f["after"] <= f["before"] and 0 < f["step"] < stop["stopped_at"]
    else:
        assert "at_freeze" not in c


def test_a_tiny_run_judged_by_forks_freezes_its_count_only_after_the_fork_trained(tmp_path, caplog):
    import logging

    from ghsplat_jax.train.synthetic import cached_synthetic_dataset
    from ghsplat_jax.train.trainer import train

    ds = cached_synthetic_dataset(num_views=20, width=32, height=24, num_surfels=40, test_every=5, num_points=200)
    cfg = TrainConfig().replace(recipe="auto", steps=120, val_every=10, stop_patience=0, stop_after=0, res_until=20,
                                res_min_side=8, densify_from=5, densify_every=5, sh_degree=1, progress=False,
                                checkpoint_every=1000, pair_capacity=16384)
    # min_gain_db 5: the first fork (30 steps after the hold's end) cannot earn it; the count freezes.
    cfg = cfg.replace(**{"strategy.level_judge": "fork", "strategy.fork_steps": 30, "strategy.min_gain_db": 5.0,
                         "strategy.hold_checks": 2, "strategy.compact": False})
    with caplog.at_level(logging.INFO, logger="ghsplat.train"):
        result = train(cfg, tmp_path / "run", dataset=ds)
    rows = [json.loads(x) for x in (tmp_path / "run" / "stats.jsonl").read_text().splitlines()]
    (frozen,) = [r for r in rows if "growth_stopped" in r]
    forked = [m for m in caplog.messages if "trained 30 steps on" in m]
    assert len(forked) == 1 and f"against this model's at step {frozen['step']}" in forked[0]
    assert "against the model trained without" in caplog.text and result.steps == 120
    assert len({r["num_surfels"] for r in rows if r["step"] >= frozen["step"]}) == 1  # held since
    assert np.isfinite(np.asarray(result.surfels.means)).all()


@pytest.mark.parametrize("rewind_lr", [False, True])
def test_a_tiny_run_judged_at_plateaus_anneals_only_once_its_count_is_final(tmp_path, rewind_lr):
    from ghsplat_jax.eval.evaluate import train_and_evaluate
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset

    ds = cached_synthetic_dataset(num_views=20, width=32, height=24, num_surfels=40, test_every=5, num_points=200)
    cfg = TrainConfig().replace(recipe="auto", steps=600, val_every=10, stop_patience=2, stop_min_gain=0.5,
                                stop_after=0, res_until=20, res_min_side=8, densify_from=5, densify_every=5,
                                sh_degree=1, progress=False, checkpoint_every=1000, pair_capacity=16384)
    cfg = cfg.replace(**{"strategy.level_judge": "plateau", "strategy.min_gain_db": 5.0,
                         "strategy.rewind_lr": rewind_lr})
    metrics = train_and_evaluate(cfg, tmp_path / "run", dataset=ds)
    rows = [json.loads(x) for x in (tmp_path / "run" / "stats.jsonl").read_text().splitlines()]
    grew = [r["step"] for r in rows if r.get("stop_action") == "grow"]
    (frozen,) = [r["step"] for r in rows if "growth_stopped" in r]
    stop = metrics["stop"]
    # The first plateau grows a level (plateaus while it grows wait for its own; 5 dB a doubling is
    # out of reach after it): the count freezes at the level's plateau, and the rule anneals there.
    assert grew and max(grew) < frozen == stop["annealed_at"] < stop["stopped_at"]
    counts = {r["step"]: r["num_surfels"] for r in rows}
    assert counts[frozen] > counts[grew[0]] and len({n for t, n in counts.items() if t >= frozen}) == 1
    assert metrics["finished"] and math.isfinite(metrics["test"]["psnr"])
    # The step after a growth trains at the rate of the first level's start when rewound, else
    # at the schedule's (which only decays). stats.jsonl's step s is the 0-based step s - 1.
    lr = {r["step"]: r["means_lr"] for r in rows}
    assert (lr[grew[0] + 1] > lr[grew[0]]) == rewind_lr
    assert all(lr[t + 1] <= lr[t] for t in lr if t + 1 in lr and t not in grew)  # else it only decays


def _fake_run(root, scene, variant, psnr, count, seconds, curve, seed=0, revision="abc", settings="", machine=None):
    run = root / scene / variant
    run.mkdir(parents=True)
    (run / "config.toml").write_text(f"seed = {seed}\ntest_curve_every = 500\n{settings}")
    (run / "metrics.json").write_text(json.dumps({
        "test": {"psnr": psnr, "l1": 0.02, "ssim": 0.9}, "train": {"psnr": psnr + 2}, "num_gaussians": count,
        "train_seconds": seconds, "steps": 5000, "stop": {"best_step": 4750, "reason": "plateau"},
        "code_revision": revision, "machine": machine}))
    (run / "test_curve.jsonl").write_text("".join(json.dumps({"step": 500 * (i + 1), "elapsed_s": t, "psnr": p})
                                                  + "\n" for i, (t, p) in enumerate(curve)))


def test_auto_recipe_report_gives_an_ablation_with_seeds_its_mean_beside_the_recipes(tmp_path):
    from benchmark_scripts import load_benchmark

    report = load_benchmark("auto_recipe")
    runs, out = tmp_path / "runs", tmp_path / "out"
    _fake_run(runs, "seg", "auto", 28.0, 30000, 700.0, [(700, 28.0)])
    _fake_run(runs, "seg", "auto_seed1", 27.6, 32000, 640.0, [(640, 27.6)], seed=1)
    judge = "[strategy]\nname = 'auto'\nlevel_judge = 'shed'\n"
    _fake_run(runs, "seg", "auto_shed", 29.0, 55000, 1000.0, [(1000, 29.0)], settings=judge)
    _fake_run(runs, "seg", "auto_shed_seed1", 28.6, 54000, 1100.0, [(1100, 28.6)], seed=1, settings=judge)
    _fake_run(runs, "seg", "auto_nores", 27.5, 31000, 900.0, [(900, 27.5)], settings="res_schedule = 'none'\n")
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"rows": []}))
    assert report.main(["--runs", str(runs), "--reference", str(ref), "--out", str(out)]) == 0
    text = (out / "README.md").read_text()
    # One row for the two seeds of auto_shed (28.80 against the recipe's 27.80), none for auto_nores.
    assert ("| seg | auto_shed | 2 | 28.80 ± 0.28 | 27.80 ± 0.28 (2) | +1.00 | - | - | - | 54,500 ± 707 | "
            "31,000 ± 1,414 | 1050 ± 71 | 670 ± 42 |") in text
    assert "| seg | auto_nores | 1 |" not in text and report.check(out) == ""


def test_auto_recipe_report_times_levels_keeps_gone_runs_and_reads_ablations(tmp_path):
    from benchmark_scripts import load_benchmark

    report = load_benchmark("auto_recipe")
    runs, out = tmp_path / "runs", tmp_path / "out"
    recipe = "res_schedule = 'spectrum'\n"
    _fake_run(runs, "seg", "auto", 28.0, 30000, 700.0, [(100, 25.5), (400, 27.2), (650, 28.0)], settings=recipe)
    _fake_run(runs, "seg", "auto_seed1", 27.6, 32000, 640.0, [(120, 26.1), (500, 27.6)], seed=1)
    _fake_run(runs, "seg", "auto_nores", 27.5, 31000, 900.0, [(300, 26.0), (900, 27.5)],
              settings="res_schedule = 'none'\n")
    # The previous recipe's run, and an ablation of it: compared with it, not with the recipe.
    _fake_run(runs, "seg", "auto_normal2k", 27.0, 30000, 700.0, [(700, 27.0)], settings="normal_from = 2000\n" + recipe)
    _fake_run(runs, "seg", "auto_old_nores", 26.0, 30000, 900.0, [(900, 26.0)],
              settings="normal_from = 2000\nres_schedule = 'none'\n")
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"rows": [{"scene": "seg", "variant": "compact", "psnr": 29.0, "num_gaussians": 30500,
                                         "train_seconds": 2500.0}]}))
    assert report.main(["--runs", str(runs), "--reference", str(ref), "--out", str(out)]) == 0
    first = json.loads((out / "results.json").read_text())
    (summary,) = first["summary"]
    assert summary["seeds"] == 2 and summary["psnr"]["mean"] == pytest.approx(27.8)  # the ablation is no seed
    assert summary["time_to_level_s"]["27"]["mean"] == pytest.approx(450.0)  # 400 s and 500 s
    assert summary["time_to_level_s"]["28"]["n"] == 1 and summary["psnr_at_10_min"]["mean"] == pytest.approx(27.4)
    assert summary["goal"] == {"psnr_at_least_compact": False, "count_at_most_compact": False,
                               "every_run_within_10_min": False}
    abl, normal2k, old = first["ablations"]
    assert abl["delta_psnr_db"] == pytest.approx(-0.5) and abl["delta_seconds"] == pytest.approx(200.0)
    assert (abl["against"], abl["differs_in"]) == ("auto", ["res_schedule"])
    assert (normal2k["against"], normal2k["differs_in"]) == ("auto", ["normal_from"])
    assert (old["against"], old["differs_in"]) == ("auto_normal2k", ["res_schedule"])
    assert old["delta_psnr_db"] == pytest.approx(-1.0)
    # A run folder that is gone keeps its row from the previous report, and a setting newer than
    # that report reads as its default (as the run trained), not as a difference.
    import shutil
    shutil.rmtree(runs / "seg" / "auto_seed1")
    shutil.rmtree(runs / "seg" / "auto")
    older = dict(first, runs=[dict(r, settings={k: v for k, v in r["settings"].items() if k != "exposure_lr"})
                              for r in first["runs"]])
    (out / "results.json").write_text(json.dumps(older))
    assert report.main(["--runs", str(runs), "--reference", str(ref), "--out", str(out)]) == 0
    again = json.loads((out / "results.json").read_text())
    assert [r["variant"] for r in again["runs"]] == ["auto", "auto_nores", "auto_normal2k", "auto_old_nores",
                                                     "auto_seed1"]
    assert "| seg | auto_nores | auto | res_schedule | 27.50 | -0.50 |" in (out / "README.md").read_text()


def test_an_ablation_is_compared_with_the_base_it_truly_differs_least_from():
    from benchmark_scripts import load_benchmark

    report = load_benchmark("auto_recipe")

    def run(variant, psnr, **settings):
        return {"scene": "seg", "variant": variant, "psnr": psnr, "num_gaussians": 20000, "train_seconds": 600.0,
                "code_revision": "abc", "settings": {"normal_from": 7000, "normal_settle": 0} | settings}

    # The recipe's run predates the judge's settings (None: unrecorded); the settle run records them.
    unrecorded = {"strategy.level_judge": None, "strategy.fork_steps": None, "strategy.rewind_lr": None}
    judge = {"strategy.level_judge": "gain", "strategy.fork_steps": 500, "strategy.rewind_lr": False}
    recipe = run("auto", 28.0, **unrecorded)
    settle = run("auto_settle", 28.1, normal_settle=1000, **judge)
    plateau = run("auto_plateau", 27.9, **(judge | {"strategy.level_judge": "plateau"}))
    early = run("auto_normal5k", 27.7, normal_from=5000, normal_settle=1000, **judge)
    by = {a["variant"]: a for a in report.ablations([recipe, settle, plateau, early])}
    # Two settings only the newer run records count for less than one both record and set apart.
    assert by["auto_plateau"]["against"] == "auto"
    assert report.differs_cell(by["auto_plateau"]) == ("-; recorded by one run only (the other predates them): "
                                                       "strategy.fork_steps, strategy.level_judge, strategy.rewind_lr")
    assert (by["auto_normal5k"]["against"], by["auto_normal5k"]["differs_in"]) == ("auto_settle", ["normal_from"])
    assert by["auto_normal5k"]["delta_psnr_db"] == pytest.approx(-0.4)
    assert (by["auto_settle"]["against"], by["auto_settle"]["differs_in"][0]) == ("auto", "normal_settle")


def test_auto_recipe_report_times_only_runs_of_one_kind_of_machine(tmp_path):
    """Seeds trained on two kinds of machine: the PSNR counts every seed, the times only those of
    the report's main kind (one scene's seeds all elsewhere: its own kind), and the rows say so."""
    from benchmark_scripts import load_benchmark

    report = load_benchmark("auto_recipe")
    runs, out = tmp_path / "runs", tmp_path / "out"
    amd = {"processor": "AMD EPYC", "cpu_count": 2, "device": "cpu"}
    intel = {"processor": "Intel Xeon", "cpu_count": 2, "device": "cpu"}
    _fake_run(runs, "a", "auto", 28.0, 30000, 600.0, [(300, 27.0), (600, 28.0)], machine=amd)
    _fake_run(runs, "a", "auto_seed1", 28.4, 30000, 1300.0, [(650, 27.2), (1300, 28.4)], seed=1, machine=intel)
    _fake_run(runs, "b", "auto", 27.0, 30000, 500.0, [(500, 27.0)], machine=amd)
    _fake_run(runs, "c", "auto", 26.0, 30000, 1000.0, [(1000, 26.0)], machine=intel)
    stopped = runs / "a" / "auto_seed2"  # a stopped run: its test curve names its machine
    stopped.mkdir()
    (stopped / "test_curve.jsonl").write_text(json.dumps({"step": 500, "elapsed_s": 90.0, "psnr": 24.0,
                                                          "host": "Intel Xeon x2, cpu"}) + "\n")
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"rows": []}))
    assert report.main(["--runs", str(runs), "--reference", str(ref), "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    a, b, c = res["summary"]
    assert [report.machine_kind(u) for u in res["unfinished"]] == ["Intel Xeon x2, cpu"]
    assert a["psnr"]["mean"] == pytest.approx(28.2) and a["train_seconds"]["n"] == 1
    assert a["train_seconds"]["mean"] == 600.0 and a["psnr_at_10_min"]["mean"] == 28.0
    assert a["timed_on"] == {"machine": "AMD EPYC x2, cpu", "runs": 1} and b["timed_on"]["runs"] == 1
    assert c["timed_on"] == {"machine": "Intel Xeon x2, cpu", "runs": 1}
    text = (out / "README.md").read_text()
    assert "| a | 2 | 28.20 ± 0.28 | 30,000 ± 0 | 600 ± 0 (1 of 2 runs: AMD EPYC x2, cpu) |" in text
    assert "| b | 1 | 27.00 ± 0.00 | 30,000 ± 0 | 500 ± 0 |" in text
    assert "| 1300 | 5000 | 4750 | Intel Xeon x2, cpu |" in text  # every run names its machine
    assert (out / "psnr_vs_time_a.png").is_file() and report.check(out) == ""


def test_auto_recipe_report_reads_reference_curves_at_equal_time(tmp_path):
    """A stopped compact_curve run (a test curve, no metrics.json) is read at fixed training times
    up to where it stopped, never beyond; the auto seeds are read at their final model once they
    stopped themselves; the README names how far the curve reached and its code revision. The
    mcmc_full control's curve is read under its own name."""
    from benchmark_scripts import load_benchmark

    report = load_benchmark("auto_recipe")
    runs, out = tmp_path / "runs", tmp_path / "out"
    _fake_run(runs, "seg", "auto", 28.0, 30000, 500.0, [(100, 25.5), (290, 27.2), (480, 28.0)])
    for folder, points in (("compact_curve", [(60, 22.0), (200, 24.0), (400, 26.0)]), ("mcmc_full", [(150, 23.0)])):
        curve = runs / "seg" / folder
        curve.mkdir(parents=True)
        (curve / "test_curve.jsonl").write_text("".join(
            json.dumps({"step": 500 * (i + 1), "elapsed_s": t, "psnr": p, "num_surfels": 9000, "code_revision": "f00d",
                        "load_average": [2.0 + i, 2.0, 2.0]})
            + "\n" for i, (t, p) in enumerate(points)))
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"rows": []}))
    assert report.main(["--runs", str(runs), "--reference", str(ref), "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    c, control = res["reference_curves"]
    assert c["variant"] == "compact" and not c["finished"] and c["last_step"] == 1500
    assert control["variant"] == "mcmc_full" and control["last_step"] == 500
    at = res["summary"][0]["equal_time"]
    assert at["compact"] == {"120": 22.0, "300": 24.0, "600": None}  # stopped at 400 s: 10 min not reached
    assert at["mcmc_full"] == {"120": None, "300": None, "600": None}  # nothing scored by 2 min; stopped before 5
    assert at["auto"]["600"]["mean"] == 28.0 and at["auto"]["120"]["mean"] == 25.5
    text = (out / "README.md").read_text()
    assert "| seg | compact | 22.00 | 24.00 | - | 1,500 | 4.00 | f00d |" in text  # the load at its third point
    assert (out / "psnr_vs_time_seg.png").is_file()
    assert report.check(out) == ""


def test_window_training_visits_every_window_of_every_view_once_an_epoch_at_full_resolution(tmp_path):
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset
    from ghsplat_jax.train.trainer import TrainingSession, train

    ds = cached_synthetic_dataset(num_views=8, width=32, height=24, num_surfels=40, test_every=4, num_points=200)
    cfg = TrainConfig().replace(steps=60, crop_tiles=2, res_schedule="spectrum", res_until=12, res_min_side=8,
                                progress=False, pair_capacity=16384).resolved()
    session = TrainingSession(cfg, tmp_path / "s", ds, resume=False)
    n = session.images.shape[0]
    start = session.schedule[-1][0]  # the first full-resolution step
    v, _, K, w, h = session.view_at(0)  # reduced resolution: a whole view at half size, not a window
    assert start > 0 and (w, h) == (16, 12) and float(K[0, 0]) == pytest.approx(float(session.Ks[v][0, 0]) / 2)
    seen = set()
    first = -(-start // (4 * n)) * (4 * n)  # epochs of windows count from step 0
    for step in range(first, first + 4 * n):
        v, image, K, w, h = session.view_at(step)
        assert (w, h) == (16, 12) and image.shape == (12, 16, 3)
        seen.add((v, float(K[0, 2]), float(K[1, 2])))
    assert len(seen) == 4 * n
    result = train(cfg, tmp_path / "run", dataset=ds)
    assert result.steps == 60 and np.isfinite(np.asarray(result.surfels.means)).all()


def test_a_switch_to_a_finer_scale_sizes_the_pair_buffer_from_the_last_check(tmp_path):
    from ghsplat_jax.train.synthetic import cached_synthetic_dataset
    from ghsplat_jax.train.trainer import TrainingSession, pair_bucket

    ds = cached_synthetic_dataset(num_views=8, width=32, height=24, num_surfels=40, test_every=4, num_points=200)
    cfg = TrainConfig().replace(steps=60, res_schedule="spectrum", res_until=12, res_min_side=8,
                                progress=False).resolved()
    session = TrainingSession(cfg, tmp_path, ds, resume=False)
    (_, coarse), (first, _) = session.schedule
    state, count = session.state, session.state.num_active()
    session._presize_for_scale(0, state)  # the first scale: nothing to predict from
    session.val_pairs = (40_000, count // 2)  # a check at full resolution, when half as many surfels lived
    capacity = session.pair_capacity
    session._presize_for_scale(first - 1, state)  # the same scale: the buffer is left as it is
    assert session.pair_capacity == capacity < 40_000
    session._presize_for_scale(first, state)  # full resolution: the check's pairs, scaled by the count
    assert session.pair_capacity == pair_bucket(80_000)
    session.pair_capacity = capacity
    session._presize_for_scale(first + 1, state)  # grown once, at the switch
    assert session.pair_capacity == capacity and coarse == 2


def test_validation_holds_out_views_only_when_enough_train():
    train, val = hold_out(list(range(16)), 8)
    assert val == [4, 12] and sorted(train + val) == list(range(16))
    # lund_door's 10 training views: one could be spared, too few to judge by; nothing is held out.
    assert hold_out(list(range(10)), 8) == (list(range(10)), [])
    assert hold_out(list(range(9)), 3) == (list(range(9)), [])  # 3 held out would leave 6 to train
