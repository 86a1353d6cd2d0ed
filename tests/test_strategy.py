"""Densification strategies as objects (train/strategies/): invariants of each strategy, the
contribution-pruning pass, the trainer calling hooks of any registered strategy, resume of a
strategy's state, count_fraction variants of the experiment runner and the compactness report."""

from __future__ import annotations

import dataclasses
import inspect
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from raster_scenes import camera, random_scene

from ghsplat_jax.train import optim, trainer
from ghsplat_jax.train import strategies as strat
from ghsplat_jax.train.config import ConfigError, TrainConfig
from ghsplat_jax.train.state import new_state, pad_params
from ghsplat_jax.train.strategies import mcmc as strat_mcmc
from ghsplat_jax.train.synthetic import cached_synthetic_dataset
from ghsplat_jax.train.trainer import train

CONFIG = TrainConfig(steps=20, lr_sh_dc=0.02, lr_means_init=1e-3, lr_means_final=1e-4, sh_degree=1,
                     sh_increase_every=10, densify_from=2, densify_every=4, densify_until=18,
                     opacity_reset_every=1000, lambda_normal=0.0, initial_capacity=512, init_random_points=120,
                     progress=False, checkpoint_every=10).replace(pair_capacity=16384)


def dataset():
    return cached_synthetic_dataset(num_views=6, width=32, height=24, num_surfels=40, test_every=3, num_points=200)


def small_state(n=48, cap=64, seed=0):
    params, active = pad_params(random_scene(n, seed=seed, degree=1), cap)
    return new_state(params, active, optim.make_optimizers(CONFIG))


def test_relocation_values_match_the_binomial_sum_and_keep_a_single_surfel():
    op = jnp.array([0.05, 0.3, 0.7, 0.95, 0.5])
    ls = jnp.log(jnp.full((5, 2), 0.1))
    for n in range(1, 7):
        new_op, new_ls = strat.relocation_values(op, ls, jnp.full(5, n))
        o2 = np.asarray(new_op, np.float64)
        # 3DGS-MCMC's double sum with 1/(k+1) (the 2D area integral of the k+1-th power of a Gaussian)
        denom = sum(math.comb(i - 1, k) * (-1) ** k * o2 ** (k + 1) / (k + 1)
                    for i in range(1, n + 1) for k in range(i))
        np.testing.assert_allclose(np.asarray(strat.relocation_integral(new_op, jnp.full(5, n))), denom, rtol=1e-4)
        # N stacked copies cover the plane like the original: s'^2 I(o', N) = s^2 o
        area = np.exp(2 * np.asarray(new_ls[:, 0], np.float64)) * denom
        np.testing.assert_allclose(area, 0.01 * np.asarray(op), rtol=1e-4)
        np.testing.assert_allclose(1 - (1 - o2) ** n, np.asarray(op), rtol=1e-4)
        if n == 1:
            np.testing.assert_allclose(np.asarray(new_op), np.asarray(op), rtol=1e-5)
            np.testing.assert_allclose(np.asarray(new_ls), np.asarray(ls), atol=1e-5)


def test_sources_are_drawn_in_proportion_to_opacity_and_never_from_zero_weight():
    w = jnp.array([0.0, 1.0, 0.0, 3.0, 0.0, 0.0, 4.0, 0.0])
    draws = np.concatenate([np.asarray(strat.sample_in_proportion(jax.random.PRNGKey(k), jnp.tile(w, 500)))
                            for k in range(4)]) % 8
    freq = np.bincount(draws, minlength=8) / len(draws)
    np.testing.assert_allclose(freq, w / w.sum(), atol=0.01)  # 16k draws: sd about 0.004
    assert set(np.flatnonzero(freq)) == {1, 3, 6}
    assert np.all(np.asarray(strat.sample_in_proportion(jax.random.PRNGKey(0), jnp.zeros(5))) == 0)


def test_mcmc_round_relocates_only_dead_surfels_and_keeps_the_count_at_the_cap():
    s = small_state(n=64, cap=64)
    dead = np.zeros(64, bool)
    dead[[3, 10, 11, 40]] = True
    logits = np.where(dead, -8.0, np.asarray(s.params.opacity_logits))
    s = dataclasses.replace(s, params=dataclasses.replace(s.params, opacity_logits=jnp.asarray(logits)))
    new, counts = strat_mcmc.mcmc_round_jit(s, jax.random.PRNGKey(0), jnp.int32(64), min_opacity=0.005, grow_rate=0.05)
    assert int(counts["relocated"]) == 4 and int(counts["added"]) == 0
    assert int(jnp.sum(new.active)) == 64  # fixed count at the cap
    moved = np.any(np.asarray(new.params.means) != np.asarray(s.params.means), axis=1)
    assert set(np.nonzero(moved)[0]) <= set(np.nonzero(dead)[0])  # only dead surfels move
    assert moved[dead].all()
    # Each relocated surfel sits on a live one, and no live surfel stays dead.
    means = np.asarray(new.params.means)
    for i in np.nonzero(dead)[0]:
        assert np.any(np.all(means[~dead] == means[i], axis=1))
    assert float(jnp.min(jax.nn.sigmoid(new.params.opacity_logits))) > 0.005
    for leaf in jax.tree_util.tree_leaves(new.params):
        assert np.all(np.isfinite(np.asarray(leaf)))


def test_mcmc_growth_fills_free_slots_up_to_the_cap_and_noise_moves_only_live_means():
    s = small_state(n=40, cap=64)
    new, counts = strat_mcmc.mcmc_round_jit(s, jax.random.PRNGKey(1), jnp.int32(50), min_opacity=0.005, grow_rate=0.5)
    assert int(counts["added"]) == 10 and int(jnp.sum(new.active)) == 50
    new2, _ = strat_mcmc.mcmc_round_jit(new, jax.random.PRNGKey(2), jnp.int32(50), min_opacity=0.005, grow_rate=0.5)
    assert int(jnp.sum(new2.active)) == 50  # never past the cap
    noisy = strat_mcmc.mcmc_noise_jit(new2, jax.random.PRNGKey(3), jnp.float32(1e3))
    moved = np.any(np.asarray(noisy.params.means) != np.asarray(new2.params.means), axis=1)
    assert not moved[~np.asarray(new2.active)].any() and moved[np.asarray(new2.active)].any()


def test_contribution_weights_sum_to_the_rendered_alpha_and_pruning_uses_the_threshold():
    from ghsplat_jax.raster.config import RasterConfig
    from ghsplat_jax.raster.render import render
    from ghsplat_jax.train.state import render_params

    s = small_state(n=48, cap=64)
    cam = camera(32, 24)
    K, w2c = jnp.asarray(cam.K, jnp.float32), jnp.asarray(cam.world_to_cam, jnp.float32)
    ctx = strat.StrategyContext(extent=1.0, Ks=K[None], w2cs=w2c[None], width=32, height=24, pair_capacity=256,
                                means_lr=lambda i: 0.0, raster=RasterConfig())
    w = np.asarray(strat.accumulated_weights(ctx, s))
    out = render(render_params(s.params, s.active, w2c), cam, RasterConfig())
    # Sum over surfels of (alpha x transmittance) per pixel = the pixel's alpha.
    np.testing.assert_allclose(w.sum(), float(jnp.sum(out.alpha)), rtol=1e-3)
    assert np.all(w[~np.asarray(s.active)] == 0) and np.all(w >= -1e-5)
    threshold = float(np.median(w[np.asarray(s.active)]))
    new, n = strat.contribution_prune(s, jnp.asarray(w), jnp.float32(threshold))
    expect = np.asarray(s.active) & (w < threshold)
    assert int(n) == expect.sum() > 0
    np.testing.assert_array_equal(np.asarray(new.active), np.asarray(s.active) & ~expect)


def test_largest_safe_count_bisects_to_the_last_count_within_the_loss():
    from ghsplat_jax.train.compaction import largest_safe_count

    calls = []

    def loss(k):  # no loss up to 300 of 1000, then 0.01 dB more per surfel
        calls.append(k)
        return max(0.0, (k - 300) * 0.01)

    k = largest_safe_count(loss, 1000, max_loss_db=0.5)
    assert 350 - 1000 / 256 <= k <= 350 and loss(k) <= 0.5 and len(calls) <= 12
    assert largest_safe_count(lambda k: 0.0, 1000, 0.1) == 900  # never more than 90%
    assert largest_safe_count(lambda k: 1.0 if k else 0.0, 1000, 0.1) == 0
    assert largest_safe_count(loss, 0, 0.1) == 0


def test_compaction_removes_what_no_view_sees_and_keeps_what_validation_needs():
    """48 surfels in front of the camera and 16 behind it: with no loss allowed, compaction
    removes exactly the 16 the view cannot see, and the model renders as before."""
    from ghsplat_jax.raster.config import RasterConfig
    from ghsplat_jax.raster.render import render
    from ghsplat_jax.train.compaction import compact_model, lowest_mask
    from ghsplat_jax.train.state import render_params

    cam = camera(32, 24)
    scene = random_scene(64, seed=3, degree=1)
    centre, backward = np.asarray(cam.center), -np.asarray(cam.world_to_cam)[2, :3]
    hidden = np.zeros(64, bool)
    hidden[48:] = True
    means = np.where(hidden[:, None], centre + 0.5 * backward + 0.01 * np.arange(64)[:, None], scene.means)
    params, active = pad_params(dataclasses.replace(scene, means=means), 80)
    s = new_state(params, active, optim.make_optimizers(CONFIG))
    K, w2c = jnp.asarray(cam.K, jnp.float32), jnp.asarray(cam.world_to_cam, jnp.float32)
    ctx = strat.StrategyContext(extent=1.0, Ks=K[None], w2cs=w2c[None], width=32, height=24, pair_capacity=4096,
                                means_lr=lambda i: 0.0, raster=RasterConfig())
    weight = strat.accumulated_weights(ctx, s)
    assert np.all(np.asarray(weight)[48:64] == 0) and np.all(np.asarray(weight)[:48] > 0)
    mask = np.asarray(lowest_mask(s.active, weight, jnp.int32(20)))
    assert mask.sum() == 20 and mask[48:64].all() and not mask[64:].any()

    def rgb(state):
        return np.asarray(render(render_params(state.params, state.active, w2c), cam, RasterConfig()).rgb, np.float64)

    target = rgb(s)

    def validate(state):  # PSNR against the full model's own render (100 dB when identical)
        return float(-10 * np.log10(np.mean((rgb(state) - target) ** 2) + 1e-10))

    small, rec = compact_model(s, weight, validate, max_loss_db=0.0)
    assert rec["before"] == 64 and rec["after"] == 48 == small.num_active(), rec
    assert rec["val_psnr_after"] == rec["val_psnr_before"] == 100.0 and small.capacity <= s.capacity
    np.testing.assert_allclose(rgb(small), target, atol=1e-6)


def test_config_validation_names_the_setting():
    with pytest.raises(ConfigError, match="strategy must be one of .*mcmc"):
        TrainConfig(strategy="nonesuch")
    with pytest.raises(ConfigError, match="min_opacity"):
        TrainConfig(strategy={"name": "mcmc", "min_opacity": 0.0})
    with pytest.raises(ConfigError, match="strategy 'default' has no setting 'max_surfels'"):
        TrainConfig().replace(**{"strategy.max_surfels": 10})
    with pytest.raises(ConfigError, match="lambda_scale_reg"):
        TrainConfig(lambda_scale_reg=-0.5)
    with pytest.raises(ConfigError, match="contrib_prune"):
        TrainConfig(strategy={"name": "default", "contrib_prune_threshold": -1})
    assert strat.loss_weight(TrainConfig(strategy="mcmc"), "lambda_opacity_reg") == 0.01
    assert strat.loss_weight(TrainConfig(), "lambda_opacity_reg") == 0.0
    scaled = TrainConfig(steps=3000, strategy={"name": "default", "contrib_prune_every": 3000}, scale_schedule=True)
    assert scaled.resolved().strategy.contrib_prune_every == 300


def test_old_flat_strategy_settings_load_with_a_warning(caplog):
    cfg = TrainConfig().replace(strategy="mcmc", mcmc_grow_rate=0.2, max_surfels=300)
    assert cfg.strategy == strat.MCMCSettings(max_surfels=300, grow_rate=0.2)
    assert "deprecated" in caplog.text and "mcmc_grow_rate -> strategy.grow_rate" in caplog.text
    # A saved config of old wrote every flat field at its default, whatever its strategy.
    assert TrainConfig().replace(budget_schedule="linear", mcmc_noise_lr=5e5).strategy == strat.DefaultSettings()
    with pytest.raises(ConfigError, match="mcmc_grow_rate.*no meaning for strategy 'default'"):
        TrainConfig().replace(mcmc_grow_rate=0.3)


def test_strategy_table_round_trips_through_the_saved_config(tmp_path):
    from ghsplat_jax.train.config import load_config, save_config

    cfg = TrainConfig().replace(recipe="auto", **{"strategy.min_gain_db": 0.25})
    assert cfg.strategy.name == "auto" and cfg.val_every > 0
    save_config(cfg, tmp_path / "c.toml")
    assert "[strategy]" in (tmp_path / "c.toml").read_text()
    assert load_config(tmp_path / "c.toml") == cfg


@dataclasses.dataclass(frozen=True)
class CountingSettings(strat.StrategySettings):
    """No settings of its own."""


@strat.register("test_counting", CountingSettings)
@dataclasses.dataclass(frozen=True)
class CountingStrategy(strat.Strategy):
    """A strategy only a test knows: counts its hook calls in its state."""

    def init_state(self, initial_count):
        return dict(super().init_state(initial_count), calls=jnp.zeros((), jnp.int32), ended=jnp.zeros((), jnp.int32))

    def refine(self, ctx, state, sstate, it):
        return state, dict(sstate, calls=sstate["calls"] + 1), {}

    def at_end(self, ctx, state, sstate):
        state, sstate, info = super().at_end(ctx, state, sstate)
        return state, dict(sstate, ended=sstate["ended"] + 1), info


def test_trainer_has_no_strategy_branches_and_runs_a_registered_strategy(tmp_path):
    src = inspect.getsource(trainer)
    assert "strategy ==" not in src and '"budget"' not in src and '"mcmc"' not in src
    result = train(CONFIG.replace(strategy="test_counting", steps=6), tmp_path / "t", dataset=dataset())
    assert int(result.strategy_state["calls"]) == 6 and int(result.strategy_state["ended"]) == 1
    assert result.num_surfels == result.initial_count  # the base strategy never densifies


def test_mcmc_and_budget_training_stay_under_the_cap(tmp_path):
    for name, extra in (("mcmc", {"strategy.grow_rate": 0.5}), ("budget", dict(densify_grad_threshold=1e-8))):
        out = tmp_path / name
        res = train(CONFIG.replace(strategy=name, **{"strategy.max_surfels": 150}, **extra), out, dataset=dataset())
        counts = [json.loads(x)["num_surfels"] for x in (out / "stats.jsonl").read_text().splitlines()]
        assert max(counts) <= 150 and res.state.capacity == 150
        for leaf in jax.tree_util.tree_leaves(res.state.params):
            assert np.all(np.isfinite(np.asarray(leaf)[np.asarray(res.state.active)]))
        if name == "mcmc":
            assert counts[-1] == 150 and int(res.strategy_state["added"]) == 150 - res.initial_count


def test_the_mcmc_pool_grows_with_the_count_and_stops_at_the_cap_bucket():
    from types import SimpleNamespace

    from ghsplat_jax.train.state import growth_bucket
    from ghsplat_jax.train.strategies import make_strategy

    def mcmc(max_surfels):
        return make_strategy(CONFIG.replace(strategy="mcmc", densify_from=0, densify_every=1, densify_until=100,
                                            **{"strategy.max_surfels": max_surfels, "strategy.grow_rate": 0.5,
                                               "strategy.noise_lr": 0.0}).resolved())

    rng = np.random.default_rng(0)
    assert mcmc(100).initial_pool(random_scene(30, seed=0, degree=1), rng)[1] == 100  # a cap under the first pool
    strategy = mcmc(6000)
    init = random_scene(3000, seed=0, degree=1)
    _, first = strategy.initial_pool(init, rng)
    assert first == 4096  # not the cap: free slots cost every step the per-surfel work of live ones
    params, active = pad_params(init, first)
    state = new_state(params, active, optim.make_optimizers(CONFIG))
    ctx = SimpleNamespace(width=32, height=24, extent=1.0, means_lr=lambda it: 1e-4, validate=None)
    sstate = strategy.init_state(3000)
    counts, pools = [], []
    for it in range(1, 4):
        state, sstate, _ = strategy.refine(ctx, state, sstate, it)
        counts.append(state.num_active())
        pools.append(state.capacity)
    assert counts == [4500, 6000, 6000]  # 3000 x 1.5, then the cap
    assert pools == [growth_bucket(6000)] * 3  # the cap's bucket (6,144 slots on a CPU), not a doubling to 8,192
    for leaf in jax.tree_util.tree_leaves(state.params):
        assert np.all(np.isfinite(np.asarray(leaf)[np.asarray(state.active)]))


def test_the_budget_pool_grows_with_its_schedule():
    from ghsplat_jax.train.state import growth_bucket
    from ghsplat_jax.train.strategies import make_strategy

    strategy = make_strategy(CONFIG.replace(strategy="budget", densify_from=0, densify_until=100,
                                            **{"strategy.max_surfels": 6000}).resolved())
    init = random_scene(3000, seed=0, degree=1)
    _, first = strategy.initial_pool(init, np.random.default_rng(0))
    assert first == 4096  # the initial count and a quarter, not the cap
    params, active = pad_params(init, first)
    state = new_state(params, active, optim.make_optimizers(CONFIG))
    sstate = strategy.init_state(3000)
    grown, new = strategy.max_new(None, state, sstate, 25, 3000)
    assert new == 750 and grown.capacity == first  # a quarter of the way to the cap fits the first pool
    grown, new = strategy.max_new(None, grown, sstate, 50, 3000)
    assert new == 1500 and grown.capacity == growth_bucket(6000)  # grown, but not past the cap's bucket
    np.testing.assert_array_equal(np.asarray(grown.params.means)[:3000], np.asarray(state.params.means)[:3000])


@pytest.mark.slow  # three MCMC runs; test_train_loop.py checks resume of the default strategy in make test
def test_resume_restores_the_strategy_state(tmp_path):
    cfg = CONFIG.replace(strategy=dict(name="mcmc", max_surfels=250, grow_rate=0.2, contrib_prune_every=8,
                                       contrib_prune_threshold=0.05))
    full = train(cfg, tmp_path / "full", dataset=dataset())
    train(cfg, tmp_path / "part", dataset=dataset(), until=10)
    done = train(cfg, tmp_path / "part", dataset=dataset(), resume=True)
    for k, v in full.strategy_state.items():
        assert int(done.strategy_state[k]) == int(v), k
    assert int(full.strategy_state["relocated"]) + int(full.strategy_state["added"]) > 0
    np.testing.assert_array_equal(np.asarray(full.state.active), np.asarray(done.state.active))
    np.testing.assert_allclose(np.asarray(full.state.params.means), np.asarray(done.state.params.means), atol=1e-5)


EXPERIMENT = """
name = "frac"
output = "{out}"
[train]
steps = 10
[[scenes]]
name = "s"
data = "nowhere"
[[variants]]
name = "default"
[[variants]]
name = "mcmc_20"
count_fraction = 0.2
train = {{ strategy = "mcmc" }}
"""


def test_count_fraction_resolves_from_the_default_run_and_errors_before_it(tmp_path):
    from ghsplat_jax.experiments.runner import load_experiment, resolve_count, run_one

    f = tmp_path / "frac.toml"
    f.write_text(EXPERIMENT.format(out=tmp_path / "runs"))
    exp = load_experiment(f)
    ref, run = exp.runs
    assert run.count_fraction == 0.2 and run.count_of == "default" and ref.count_fraction is None
    with pytest.raises(ConfigError,
                       match="s/mcmc_20: count_fraction = 0.2 of variant 'default', which has not finished"):
        resolve_count(run, exp.runs)
    assert "has not finished" in run_one(run, exp.runs)  # the runner reports it as that run's failure
    # The reference's folder lost between sessions: its final count comes from the last report.
    reported = {("s", "default"): 10000}
    assert resolve_count(run, exp.runs, reported).config.strategy.max_surfels == 2000
    ref.out_dir.mkdir(parents=True)  # a folder without metrics.json is a run in progress, not a lost one
    with pytest.raises(ConfigError, match="which has not finished"):
        resolve_count(run, exp.runs, reported)
    (ref.out_dir / "metrics.json").write_text(json.dumps({"num_gaussians": 12345}))
    assert resolve_count(run, exp.runs, reported).config.strategy.max_surfels == 2469  # the run's own count comes first
    f.write_text(EXPERIMENT.format(out=tmp_path / "runs").replace('strategy = "mcmc"', 'strategy = "default"'))
    with pytest.raises(ConfigError, match="caps the count"):
        load_experiment(f)
    f.write_text(EXPERIMENT.format(out=tmp_path / "runs").replace("count_fraction = 0.2", 'count_fraction = 0.2\n'
                                                                  'count_of = "other"'))
    with pytest.raises(ConfigError, match="count_of names 'other'"):
        load_experiment(f)


def test_runner_takes_a_lost_references_count_from_the_report(tmp_path, monkeypatch):
    # `ghsplat run --only s/mcmc_20` in a later session whose runs folder is gone: the default's
    # row survives in results.json, so the compact run starts with its cap instead of failing.
    from ghsplat_jax.experiments import runner

    f = tmp_path / "frac.toml"
    f.write_text(EXPERIMENT.format(out=tmp_path / "runs"))
    exp = runner.load_experiment(f)
    exp.results.mkdir(parents=True, exist_ok=True)
    (exp.results / "results.json").write_text(json.dumps({"rows": [{"scene": "s", "variant": "default",
                                                                      "num_gaussians": 10000}]}))
    caps = []
    monkeypatch.setattr(runner, "train_and_evaluate",
                        lambda config, out_dir, resume: caps.append(config.strategy.max_surfels))
    monkeypatch.setattr(runner, "collect", lambda exp: ([], []))
    assert runner.run_experiment(exp, only={"s/mcmc_20"})["failed"] == []
    assert caps == [2000]


def test_compactness_report_states_the_goal_check(tmp_path):
    from ghsplat_jax.experiments.compactness import write_compactness

    rows = []
    for variant, strategy, frac, n, psnr in (("default", "default", None, 1000, 25.0),
                                             ("mcmc_20", "mcmc", 0.2, 200, 24.9),
                                             ("budget_20", "budget", 0.2, 200, 24.5)):
        d = tmp_path / variant
        d.mkdir()
        (d / "metrics.json").write_text(json.dumps({"num_gaussians": n, "peak_rss_mb": 100.0}))
        (d / "stats.jsonl").write_text("".join(json.dumps({"step": i, "elapsed_s": i * n / 1e4}) + "\n"
                                               for i in range(1, 11)))
        rows.append(dict(scene="s", variant=variant, strategy=strategy, count_fraction=frac, num_gaussians=n, psnr=psnr,
                         train_seconds=n / 100, render_seconds_per_view=n / 1e5, steps=10, run_dir=str(d)))
    made = write_compactness(rows, tmp_path / "rep", "t")
    names = {p.name for p in made}
    assert {"compactness.md", "compactness_psnr_vs_count.png", "compactness_psnr_vs_train_time.png",
            "compactness_psnr_vs_render_time.png"} <= names
    md = (tmp_path / "rep" / "compactness.md").read_text()
    assert "| s | mcmc | 200 (0.20) | 24.90 | -0.10 | yes | 0.020 (0.20)" in md
    assert "1 of 2 runs at 20% meet the goal" in md


def test_compactness_cpu_preset_caps_strategies_at_fractions_of_the_self_sized_run():
    """`compactness.toml --preset auto_cpu`: the auto recipe's run is the reference, and MCMC and the
    budget schedule train at fractions of its count with the recipe's split, stop rule and schedule."""
    from ghsplat_jax.experiments.runner import load_experiment

    exp = load_experiment("experiments/compactness.toml", preset="auto_cpu")
    runs = {r.variant: r for r in exp.runs}
    assert runs["auto"].config.strategy.name == "auto" and runs["auto"].count_fraction is None
    capped = [r for r in exp.runs if r.count_fraction is not None]
    assert {r.config.strategy.name for r in capped} == {"mcmc", "budget"} and {r.count_of for r in capped} == {"auto"}
    for r in exp.runs:
        assert r.config.recipe == "auto" and r.config.val_every == 250 and r.config.res_schedule == "spectrum"
        assert r.config.downscale == 2.0  # the Table 1 protocol's 192x144
    assert exp.results.as_posix() == "benchmarks/results/compactness/auto_cpu"


def test_compactness_report_against_a_self_sized_reference(tmp_path):
    """Capped runs whose counts are fractions of the auto run are compared with it, also at its
    training time (from their test curves), and the default's goal check is not claimed for them."""
    from ghsplat_jax.experiments.compactness import compare, summary_markdown

    rows = []
    for variant, strategy, frac, n, psnr, seconds, curve in (
            ("auto", "auto", None, 1000, 28.0, 600.0, [(300.0, 26.0), (590.0, 27.9)]),
            ("mcmc_50", "mcmc", 0.5, 500, 27.5, 900.0, [(300.0, 25.0), (600.0, 26.5), (610.0, 26.8), (900.0, 27.5)]),
            ("default", "default", None, 9000, 27.0, 7000.0, [])):
        run = tmp_path / variant
        run.mkdir()
        lines = "".join(json.dumps({"elapsed_s": t, "psnr": p}) + "\n" for t, p in curve)
        (run / "test_curve.jsonl").write_text(lines + '{"elapsed_s": 95')  # a line cut short by a stop
        rows.append(dict(scene="s", variant=variant, strategy=strategy, count_fraction=frac,
                         count_of="auto" if frac else None, num_gaussians=n, psnr=psnr, train_seconds=seconds,
                         run_dir=str(run)))
    compared = {r["variant"]: r for r in compare(rows)}
    assert compared["mcmc_50"]["dpsnr"] == -0.5 and compared["mcmc_50"]["count_ratio"] == 0.5
    assert compared["mcmc_50"]["psnr_at_reference_time"] == 26.5  # its point at 600 s, not the one after
    assert compared["auto"]["psnr_at_reference_time"] == 28.0  # finished by then: its result, not its last point
    assert compared["default"]["count_ratio"] == 9.0 and compared["default"]["psnr_at_reference_time"] is None
    md = summary_markdown(list(compared.values()), "t")
    assert "same scene's `auto` run" in md and "No goal check" in md and "meet the goal" not in md
    assert "| s | mcmc_50 | mcmc | 50% | 500 | 27.50 | -0.50 | 900 | 26.50 |" in md
